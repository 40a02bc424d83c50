"""Single-run motor identification: ``J θ'' + D θ' + Tc s(θ') + C θ = Kt i``.

Two methods, same result type:

``paper``   Yukawa et al., eqs. 6–10: state x = [θ, θ'], input u = i, forward (Euler)
            differences at the data's rate, equation-error least squares written with
            the Q matrices (integrals as sums × dt). Returns A_e, B_e; b2 = B_e[1] = Kt/J.
            ``decimate_s=0.015`` reproduces the paper's 15 ms sampling (every k-th
            sample, as a 15 ms A/D would see it).
``default`` Removes the paper's biases: one zero-phase FIR on every signal and central
            differences (see ``derivatives.consistent_derivatives``) so velocity,
            acceleration and current stay aligned; a Coulomb term sign(θ') instead
            of subtracting a no-load current, integrated at each reversal's
            sub-sample instant as the angle's second difference sees it, with the
            torque regressors zeroed while the rotor sticks at a reversal; C fixed at 0 unless asked; a
            current-noise (errors-in-variables) correction; cogging harmonics
            sin/cos(k θ) with the orders k found from the data (``cogging_order_scores``
            screens k = 1…64 on the rotor angle, an information criterion keeps them);
            a parameter covariance from block sums of the residual scores (valid for
            coloured residuals) with Student-t degrees of freedom = blocks − 1.

``check_excitation`` refuses data that cannot identify b2 (constant speed, no
acceleration content, ill-conditioned regressors) with an ``ExcitationError`` saying
what to change.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from ..errors import ExcitationError, TraceError
from . import derivatives as dv

# Regression written as  θ'' = b2·i − (D/J)·θ' − (Tc/J)·s(θ') − (C/J)·θ + bias.
KT_J, D_J, TC_J, C_J, BIAS, LAG = "Kt/J", "D/J", "Tc/J", "C/J", "bias", "lag"

MAX_CONDITION = 1e4          # of the column-normalised regressor matrix
MIN_ACCEL_SNR = 20.0         # rms filtered acceleration / rms encoder-noise acceleration
# No threshold is in the user's position unit (rad, deg, mm, m are all valid): speeds
# come from the encoder step, the sample rate and the run's own speed range.
STANDSTILL_COUNTS_PER_SAMPLE = 1 / 6   # slower than 1 count per 6 samples (>= 3 samples): sticks
STANDSTILL_TOP_FRACTION = 3e-4  # without a visible encoder step: this share of the top speed
REVERSAL_TOP_FRACTION = 0.02  # a run "reverses" if >5 % of it is beyond ±this share of top speed
MIN_R2_SHARE = 0.5           # refuse a fit explaining < half of what the data's noise allows
MAX_B2_REL_STD = 0.05        # refuse a fit whose b2 is known worse than 5 % (1 sigma)
MAX_COGGING_ORDER = 64       # cogging periods per revolution scanned
COGGING_CANDIDATES = 4       # orders tried in the regression after the screen
COGGING_SCREEN = 8.0         # screen: score > 8x the median score (white noise: 1/256 per order)
MIN_SCREEN_ORDERS = 8        # visible orders needed for the median to mean anything
# Cogging shows only near reversals, a few dozen events per run, so the block covariance
# under-states its pair's variance and W of a spurious order reaches tens. Floor chosen on
# robustness seed 0 (spurious W <= 40, real >= 89, 0.6 mN m), checked on seed 2 (<= 21, >= 96).
COGGING_MIN_WALD = 80.0


@dataclass(frozen=True)
class IdentificationResult:
    """One run's fit. ``values``/``covariance`` follow ``names``; sign convention of
    the module docstring, so ``D/J`` and ``Tc/J`` are positive for a real motor."""

    method: str
    names: tuple[str, ...]
    values: tuple[float, ...]
    covariance: np.ndarray
    dof: int                     # degrees of freedom for Student-t intervals
    dt_s: float
    n_samples: int               # samples in the regression
    n_effective: float           # independent-sample equivalent (coloured residuals)
    r2: float
    rmse: float                  # rad/s² residual
    condition: float             # of the column-normalised regressor matrix
    A: np.ndarray                # 2x2 state matrix (paper eq. 4 / 10)
    B: np.ndarray                # input vector [b1, b2] (paper eq. 5 / 10)
    extras: dict = field(default_factory=dict)

    def value(self, name: str, default: float = 0.0) -> float:
        return self.values[self.names.index(name)] if name in self.names else default

    def std(self, name: str) -> float:
        if name not in self.names:
            return 0.0
        k = self.names.index(name)
        return float(np.sqrt(max(self.covariance[k, k], 0.0)))

    @property
    def b2(self) -> float:
        """Kt/J (paper eq. 11), 1/(A s²)."""
        return self.value(KT_J)

    @property
    def b2_std(self) -> float:
        return self.std(KT_J)

    def to_dict(self) -> dict:
        return {
            "method": self.method,
            "b2": self.b2, "b2_std": self.b2_std,
            "params": dict(zip(self.names, map(float, self.values))),
            "std": {n: self.std(n) for n in self.names},
            "covariance": {"names": list(self.names), "matrix": self.covariance.tolist()},
            "dof": self.dof, "dt_s": self.dt_s, "n_samples": self.n_samples,
            "n_effective": self.n_effective, "r2": self.r2, "rmse": self.rmse,
            "condition": self.condition,
            "A": self.A.tolist(), "B": self.B.tolist(),
            **{k: v for k, v in self.extras.items()},
        }


# --------------------------------------------------------------------------- paper
def identify_paper(time_s: np.ndarray, position_rad: np.ndarray, current_a: np.ndarray, *,
                   decimate_s: float | None = None, no_load_current_a: float = 0.0,
                   check: bool = True, source: str = "<array>") -> IdentificationResult:
    """Equation-error least squares exactly as published (Yukawa et al., eqs. 6–10).

    ``x_d = [θ, θ']``, ``x_d' = [θ', θ'']`` by forward (Euler) differences,
    ``u_d = i − no_load_current_a`` (the paper's variant that subtracts the mean
    no-load current), ``[A_e B_e] = [Q1 Q2] [[Q11, Q12], [Q12ᵀ, Q22]]⁻¹`` (eq. 10)
    with every integral a sum × dt. ``decimate_s`` keeps every k-th sample first
    (the paper sampled at 15 ms).
    """
    t = np.asarray(time_s, float)
    th = np.asarray(position_rad, float)
    i = np.asarray(current_a, float)
    dt = float(np.median(np.diff(t)))
    if decimate_s:
        k = max(1, int(round(decimate_s / dt)))
        t, th, i = t[::k], th[::k], i[::k]
        dt *= k
    if len(t) < 10:
        raise TraceError(f"{source}: only {len(t)} samples after decimation to {dt * 1e3:.3g} ms; "
                         f"record a longer run")
    th = th - th[0]
    w, a = dv.forward_differences(th, dt)
    n = len(a)
    x = np.vstack([th[:n], w])            # 2 x N state
    xd = np.vstack([w, a])                # 2 x N state derivative
    u = (i[:n] - no_load_current_a)[None, :]
    if check:
        _check_paper_excitation(w, a, i[:n], dt, source)
    Q1, Q2 = xd @ x.T * dt, xd @ u.T * dt
    Q11, Q12, Q22 = x @ x.T * dt, x @ u.T * dt, u @ u.T * dt
    M = np.block([[Q11, Q12], [Q12.T, Q22]])
    AB = np.hstack([Q1, Q2]) @ np.linalg.inv(M)          # eq. 10
    A, B = AB[:, :2], AB[:, 2]
    # Classical (white-residual) covariance of the second row, for information only:
    # the paper gives none.
    X = np.vstack([x, u]).T
    e = a - X @ AB[1]
    s2 = float(e @ e) / max(n - 3, 1)
    cov3 = s2 * np.linalg.inv(X.T @ X)
    # Map the second row (−C/J, −D/J, b2) onto the common parameter names.
    perm = [2, 1, 0]
    sign = np.array([1.0, -1.0, -1.0])
    cov = cov3[np.ix_(perm, perm)] * np.outer(sign, sign)
    values = (float(B[1]), float(-A[1, 1]), float(-A[1, 0]))
    return IdentificationResult(
        method="paper" if not decimate_s else f"paper@{dt * 1e3:.3g}ms",
        names=(KT_J, D_J, C_J), values=values, covariance=cov, dof=n - 3, dt_s=dt,
        n_samples=n, n_effective=float(n), r2=_r2(a, e), rmse=float(np.sqrt(np.mean(e * e))),
        condition=_condition(X), A=A, B=B,
        extras={"no_load_current_a": no_load_current_a, "speed_range_rad_s": speed_range(w)})


def _check_paper_excitation(w, a, i, dt, source):
    if np.ptp(w) <= 0 or np.ptp(i) <= 0 or not np.any(a):
        raise ExcitationError(
            f"{source}: speed or current is constant, the regression cannot identify Kt/J; "
            f"add speed steps or a multisine of at least 10 rad/s amplitude")


# ------------------------------------------------------------------------- default
def identify_default(time_s: np.ndarray, position_rad: np.ndarray, current_a: np.ndarray, *,
                     cutoff_hz: float | None = None, spring: bool = False,
                     friction_width_rad_s: float = 0.0, bias: bool | None = None,
                     lag: bool = True, eiv_correction: bool = True,
                     cogging: bool | tuple[int, ...] = True, check: bool = True,
                     source: str = "<array>",
                     rad_per_unit: float | None = 1.0) -> IdentificationResult:
    """Bias-reduced equation-error fit of ``θ'' = b2 i − (D/J)θ' − (Tc/J)s(θ') [− (C/J)θ] [+ c]``.

    Parameters
    ----------
    cutoff_hz : low-pass cutoff of the common FIR; default ``min(40 Hz, rate/10)``.
        The filter never biases the fit (it is applied to both sides of a linear
        relation); it only trades noise against the excitation band it keeps.
    spring : also fit the paper's C/J (spring to ground); off for a real motor.
    friction_width_rad_s : 0 (default): s(θ') is the sign of the speed with each
        reversal placed at its sub-sample instant (``derivatives.coulomb_regressor``);
        > 0: the older sampled tanh(θ'/w), kept for comparison.
    bias : add a constant (current-offset) column. Default: only when the speed
        reverses, since with one rotation direction a constant and the Coulomb term
        are the same column (PAPER-NOTES: "reversals separate them").
    lag : also fit a small lag τ between the measured current and the torque-producing
        current (current-loop lag, sample-instant skew): i_T(t) ≈ i(t + τ) = i + τ i'. Left out, a
        0.5 ms skew biases b2 by ~0.1 % and makes b2 depend on the filter cutoff.
        Reported as ``extras["current_delay_s"]`` (τ > 0: the measured current is late).
    eiv_correction : subtract the filtered current-noise variance from the normal
        matrix (errors-in-variables: noise on the current regressor pulls b2 to zero).
    cogging : cogging torque Σ_k (a_k sin kθ + b_k cos kθ) (periodic in the rotor angle;
        MotorParams' ``cog_amp·sin(cog_order·θ)``). ``True`` (default): the base fit's
        residual is screened for orders 1…``MAX_COGGING_ORDER`` (``cogging_order_scores``,
        ``cogging_candidates``), up to ``COGGING_CANDIDATES`` are fitted, and an order is kept when its pair's Wald
        statistic W (block covariance) beats the Bayesian information criterion's price
        for two parameters, W > 2 ln n_eff (n_eff: independent-sample equivalent), and
        ``COGGING_MIN_WALD``.
        Orders are per motor revolution: ``rad_per_unit`` is the motor angle in radians
        per position unit (1 for rad, pi/180 for deg, 2 pi / lead for a linear axis);
        None (a length with no lead given): no cogging terms — never assumed.
        At low speed, near reversals, cogging sits inside the filter's band and, left
        out, moves b2 by percent. A tuple fits exactly those orders; ``False``: none.
        Kept orders and amplitudes (rad/s², i.e. N m per kg m²) go to
        ``extras["cogging"]``.

    Returns
    -------
    IdentificationResult with a covariance from block sums of residual scores.
    """
    t = np.asarray(time_s, float)
    th = np.asarray(position_rad, float)
    i = np.asarray(current_a, float)
    dt = float(np.median(np.diff(t)))
    rate = 1.0 / dt
    cutoff_hz = cutoff_hz or min(40.0, rate / 10.0)
    taps = dv.lowpass_fir(cutoff_hz, rate)
    if len(t) < len(taps) + 50:
        raise TraceError(f"{source}: only {len(t)} samples, need at least {len(taps) + 50} "
                         f"at {rate:.4g} Hz for the {cutoff_hz:.3g} Hz filter; record a longer run")
    th = th - th[0]
    # Speed between samples for the friction regressor and the reversal test.
    w_smooth = dv.smooth_velocity(th, dt)
    if friction_width_rad_s:
        # Legacy: smoothed sign of the raw speed, sampled, then 3-tap matched.
        w_raw = np.empty_like(th)
        w_raw[1:-1] = (th[2:] - th[:-2]) / (2 * dt)
        w_raw[0], w_raw[-1] = w_raw[1], w_raw[-2]
        fs = dv.consistent_derivatives(
            th, {"current": i, "sign": np.tanh(w_raw / friction_width_rad_s)}, dt, taps)
    else:
        # Coulomb step integrated at its sub-sample reversal instant, exactly as the
        # second difference of the angle sees it (``derivatives.coulomb_regressor``),
        # the instant taken from the angle around it (``derivatives.refine_reversals``).
        # While the rotor sticks at a reversal (a PI speed loop needs time to swing its
        # torque by 2·Tc) friction balances whatever the drive gives: the motor equation
        # there is J θ'' = 0, so every torque regressor is zeroed on those samples and
        # the filtered equation stays exact without dropping data.
        moving = 1.0 - dv.standstill(w_smooth, standstill_speed(th, w_smooth, dt))
        fs = dv.consistent_derivatives(
            th, {"current": i * moving}, dt, taps,
            matched={"sign": dv.coulomb_regressor(
                th, dt, velocity=dv.refine_reversals(th, w_smooth)) * moving})
    n = len(fs["acceleration"])

    w_rev = REVERSAL_TOP_FRACTION * top_speed(w_smooth)
    reverses = bool(np.mean(w_smooth > w_rev) > 0.05 and np.mean(w_smooth < -w_rev) > 0.05)
    use_bias = reverses if bias is None else bias
    if use_bias and not reverses:
        raise ExcitationError(f"{source}: a current offset and Coulomb friction cannot be told "
                              f"apart without speed reversals; reverse the rotation in the run "
                              f"or fit without the offset term")
    cols = [(KT_J, fs["current"], 1.0), (D_J, fs["velocity"], -1.0), (TC_J, fs["sign"], -1.0)]
    if spring:
        cols.append((C_J, fs["position"], -1.0))
    if use_bias:
        cols.append((BIAS, np.ones(n), 1.0))
    n_base = len(cols)
    y = fs["acceleration"]

    # Errors in variables: white current noise σ² becomes σ²·Σh² after the filters.
    h = np.convolve(dv.SECOND_DIFFERENCE_MATCH, taps)
    noise_var_raw = _white_noise_variance(i)
    noise_var = noise_var_raw * float(h @ h)
    block = max(4 * len(taps), len(y) // 64)
    solve = dict(y=y, noise_var=noise_var if eiv_correction else 0.0, lag=lag, dt=dt,
                 source=source)
    beta, Xt, G, Gc, shift_s = _solve(cols, **solve)

    cog_orders: tuple[int, ...] = ()
    if cogging is not False and cogging is not None and rad_per_unit is not None:
        half = (len(taps) - 1) // 2
        at = slice(half + 1, half + 1 + n)          # raw samples under the filtered ones
        ang = th * rad_per_unit                     # motor angle, rad: orders per revolution
        if cogging is True:
            scores = cogging_order_scores(ang[at], w_smooth[at] * rad_per_unit, y - beta @ Xt,
                                          cutoff_hz=cutoff_hz)
            cog_orders = cogging_candidates(scores)
        else:
            cog_orders = tuple(int(k) for k in cogging)
        moving_cog = moving if not friction_width_rad_s else np.ones_like(th)
        while cog_orders:
            harm = np.vstack([f(k * ang) * moving_cog for k in cog_orders for f in (np.sin, np.cos)])
            filt = dv.matched_filter(harm, taps)
            cog_cols = [(f"cog{k}_{p}", filt[2 * j + q], 1.0)
                        for j, k in enumerate(cog_orders) for q, p in enumerate(("sin", "cos"))]
            beta, Xt, G, Gc, shift_s = _solve(cols + cog_cols, **solve)
            if cogging is not True:
                break
            cov, _, n_eff = _block_covariance(Xt, y - beta @ Xt, Gc, block=block)
            wald = []
            for j in range(len(cog_orders)):
                sl = slice(n_base + 2 * j, n_base + 2 * j + 2)
                try:
                    wald.append(float(beta[sl] @ np.linalg.solve(cov[sl, sl], beta[sl])))
                except np.linalg.LinAlgError:
                    wald.append(0.0)
            price = max(2.0 * np.log(max(n_eff, 2.0)), COGGING_MIN_WALD)
            keep = tuple(k for k, wk in zip(cog_orders, wald) if wk > price)
            if keep == cog_orders:
                break
            cog_orders = keep
            if not cog_orders:
                beta, Xt, G, Gc, shift_s = _solve(cols, **solve)
        cols = cols + (cog_cols if cog_orders else [])
    if lag:
        cols.append((LAG, None, 1.0))
    names = tuple(c[0] for c in cols)
    sign = np.array([c[2] for c in cols])

    e = y - beta @ Xt
    cond = _condition_gram(G[:n_base, :n_base])
    cov, dof, n_eff = _block_covariance(Xt, e, Gc, block=block)
    values = beta * sign
    cov = cov * np.outer(sign, sign)
    b2 = float(values[0])
    b2_std = float(np.sqrt(max(cov[0, 0], 0.0)))
    cog_amps = {int(k): float(np.hypot(values[names.index(f"cog{k}_sin")],
                                       values[names.index(f"cog{k}_cos")])) for k in cog_orders}

    r2 = _r2(y, e)
    if check:
        accel_noise = _encoder_accel_noise(th, dt, taps)
        check_excitation(velocity=fs["velocity"], acceleration=y, accel_noise_rms=accel_noise,
                         condition=cond, b2=b2, b2_std=b2_std, rate_hz=rate, source=source)
        # what a perfect model would leave: encoder noise + current noise through b2
        floor_var = accel_noise ** 2 + b2 ** 2 * noise_var
        check_fit_quality(r2=r2, floor_r2=1.0 - floor_var / max(float(np.var(y)), 1e-300),
                          source=source)

    A = np.array([[0.0, 1.0], [-(values[names.index(C_J)] if spring else 0.0), -values[1]]])
    B = np.array([0.0, b2])
    return IdentificationResult(
        method="default", names=names, values=tuple(map(float, values)), covariance=cov,
        dof=dof, dt_s=dt, n_samples=n, n_effective=n_eff, r2=r2,
        rmse=float(np.sqrt(np.mean(e * e))), condition=cond, A=A, B=B,
        extras={"cutoff_hz": cutoff_hz, "filter_taps": len(taps),
                "current_noise_a": float(np.sqrt(noise_var_raw)),
                "eiv_relative_correction": float(n * noise_var / G[0, 0]) if eiv_correction else 0.0,
                "cogging": cog_amps,
                "friction_width_rad_s": friction_width_rad_s,
                "speed_range_rad_s": speed_range(w_smooth),
                "current_delay_s": shift_s + ((float(values[names.index(LAG)]) / b2) if lag and b2 else 0.0)})


def _solve(cols, *, y, noise_var, lag, dt, source):
    """Least squares of ``y`` on the columns (plus the lag column ``i'`` when ``lag``) with
    the errors-in-variables correction ``n·noise_var`` on the current's diagonal.

    The lag column is first order in τ; past ~0.1 sample the τ² term biases b2, so the
    (band-limited) current is shifted by the estimated τ and refitted (converges in 2-3).
    Returns (β, X (k x n), Gram, corrected Gram, total shift in s)."""
    base = cols[0][1]
    Xt = np.empty((len(cols) + bool(lag), len(y)))   # k x n, rows contiguous for speed
    for r, c in enumerate(cols):
        Xt[r] = c[1]
    if lag:
        Xt[-1] = np.gradient(base, dt)
    shift_s = 0.0
    idx = None
    for _ in range(4 if lag else 1):
        G = Xt @ Xt.T
        Gc = G.copy()
        Gc[0, 0] -= len(y) * noise_var
        try:
            beta = np.linalg.solve(Gc, Xt @ y)
        except np.linalg.LinAlgError:
            raise ExcitationError(f"{source}: regressors are linearly dependent; add speed steps "
                                  f"or a multisine of at least 10 rad/s amplitude") from None
        if not lag or beta[0] == 0:
            break
        tau = float(beta[-1] / beta[0])
        if abs(tau) < 0.02 * dt or abs(shift_s + tau) > 5 * dt:
            break
        shift_s += tau
        if idx is None:
            idx = np.arange(len(y), dtype=float)
        Xt[0] = np.interp(idx + shift_s / dt, idx, base)            # i(t + shift)
        Xt[-1] = np.gradient(Xt[0], dt)
    return beta, Xt, G, Gc, shift_s


def cogging_order_scores(position_rad: np.ndarray, velocity_rad_s: np.ndarray,
                         residual: np.ndarray, *, cutoff_hz: float,
                         max_order: int = MAX_COGGING_ORDER, bins: int = 2048) -> np.ndarray:
    """Screen of cogging orders on the rotor angle: for k = 1…``max_order``

        z_k = |Σ_t e_t exp(−i k θ_t)|² / Σ_t e_t²   over samples with k·|ω_t| < 2π f_c,

    the angle-domain periodogram of the residual e, restricted to the samples where the
    low-pass (cutoff f_c) lets order k through (elsewhere the filtered cogging is zero
    and those samples only add noise); NaN for an order no sample can show. White
    residual: E z_k = 1. O(n) in one pass: per speed class (limits 2π f_c/2^j) a
    histogram of e over ``bins`` angle bins, then one FFT per class.
    Returns ``z`` (index k − 1)."""
    th = np.asarray(position_rad, float)
    e = np.asarray(residual, float)
    speed = np.abs(np.asarray(velocity_rad_s, float))
    nclass = int(np.ceil(np.log2(max_order))) + 1
    # class j: 2π fc / 2^(j+1) <= |ω| < 2π fc / 2^j  (last class: everything slower)
    with np.errstate(divide="ignore"):
        level = np.floor(np.log2(2 * np.pi * cutoff_hz / np.maximum(speed, 1e-12)))
    ok = level >= 0
    cls = np.minimum(level[ok], nclass - 1).astype(np.int64)
    b = (np.mod(th[ok], 2 * np.pi) * (bins / (2 * np.pi))).astype(np.int64) % bins
    eo = e[ok]
    S = np.bincount(cls * bins + b, eo, minlength=nclass * bins).reshape(nclass, bins)
    E2 = np.bincount(cls, eo * eo, minlength=nclass)
    # order k needs |ω| < 2π fc / k: classes j >= ceil(log2 k); sum them from the slow end
    S = np.cumsum(S[::-1], axis=0)[::-1]
    E2 = np.cumsum(E2[::-1])[::-1]
    F = np.fft.rfft(S, axis=1)
    orders = np.arange(1, max_order + 1)
    j = np.ceil(np.log2(orders)).astype(int)
    power = np.abs(F[j, orders]) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(E2[j] > 0, power / E2[j], np.nan)


def cogging_candidates(scores: np.ndarray) -> tuple[int, ...]:
    """Orders worth a regression test: at most ``COGGING_CANDIDATES`` whose score beats
    ``COGGING_SCREEN`` x the median score of the orders the run can show. The median
    calibrates out the residual's colour; with fewer than ``MIN_SCREEN_ORDERS`` visible
    orders (a fast run: the filter hides all but the lowest) there is nothing to
    compare with and no cogging can bias the fit, so none are tried."""
    visible = np.isfinite(scores)
    if visible.sum() < MIN_SCREEN_ORDERS:
        return ()
    screen = COGGING_SCREEN * float(np.median(scores[visible]))
    z = np.where(visible, scores, -np.inf)
    ranked = np.argsort(z)[::-1][:COGGING_CANDIDATES]
    return tuple(int(k) + 1 for k in ranked if z[k] > screen)


def identify(time_s, position_rad, current_a, *, method: str = "default",
             source: str = "<array>", **options) -> IdentificationResult:
    """Dispatch on ``method``: ``default``, ``paper`` (data rate) or ``paper-15ms``."""
    if method == "default":
        return identify_default(time_s, position_rad, current_a, source=source, **options)
    if method == "paper":
        return identify_paper(time_s, position_rad, current_a, source=source, **options)
    if method == "paper-15ms":
        return identify_paper(time_s, position_rad, current_a, decimate_s=0.015,
                              source=source, **options)
    raise ValueError(f"unknown identification method {method!r}; use default, paper or paper-15ms")


METHODS = ("default", "paper", "paper-15ms")


def identify_trace(trace, *, method: str = "default", **options) -> IdentificationResult:
    """Validate a single-motor ``Trace`` (columns ``position_rad``, ``current_a``) and fit it."""
    trace.validate(["position_rad", "current_a"], min_samples=50)
    return identify(trace.time_s, trace["position_rad"], trace["current_a"], method=method,
                    source=trace.source, **options)


# ---------------------------------------------------------------- excitation check
def check_excitation(*, velocity: np.ndarray, acceleration: np.ndarray, accel_noise_rms: float,
                     condition: float, b2: float, b2_std: float, rate_hz: float,
                     source: str = "<array>") -> None:
    """Raise ``ExcitationError`` unless the data can identify b2.

    Three tests, each with its fix: the filtered acceleration must stand well above
    what encoder quantisation alone would produce (else: constant speed); the
    column-normalised regressors must be well conditioned; b2 must come out
    positive and known to better than ``MAX_B2_REL_STD``.
    """
    # Amplitude of a 2 Hz speed sine whose acceleration reaches the SNR target.
    # amplitude of a 2 Hz speed sine whose acceleration reaches the SNR target, and at
    # least a tenth of the run's top speed (both in the trace's own position unit)
    need = max(0.1 * top_speed(velocity),
               MIN_ACCEL_SNR * np.sqrt(2) * accel_noise_rms / (2 * np.pi * 2.0) ** 2)
    fix = (f"add speed steps or a multisine of at least {need:.2g} rad/s amplitude (1-10 Hz; "
           f"in the trace's position unit per second)")
    acc_rms = float(np.std(acceleration))
    if acc_rms < MIN_ACCEL_SNR * accel_noise_rms or np.ptp(velocity) == 0:
        raise ExcitationError(
            f"{source}: almost no acceleration content (rms {acc_rms:.3g} rad/s² vs encoder "
            f"noise {accel_noise_rms:.3g}); {fix}")
    if not np.isfinite(condition) or condition > MAX_CONDITION:
        raise ExcitationError(
            f"{source}: regressors ill-conditioned (condition {condition:.3g} > "
            f"{MAX_CONDITION:.0g}): speed, current and friction do not vary independently; {fix}")
    if not (b2 > 0) or b2_std > MAX_B2_REL_STD * abs(b2):
        raise ExcitationError(
            f"{source}: Kt/J is not identifiable from this run (b2 = {b2:.4g} ± {b2_std:.2g}); {fix}")


def check_fit_quality(*, r2: float, floor_r2: float, source: str = "<array>") -> None:
    """Refuse a fit that explains far less than the data's noise allows.

    ``floor_r2`` is the r² a perfect model would reach, given the encoder and current
    noise; a fit below ``MIN_R2_SHARE`` of it means the model does not describe this
    axis (or a channel is mis-scaled / mis-assigned) — its numbers would be wrong."""
    if not np.isfinite(r2) or r2 < MIN_R2_SHARE * max(floor_r2, 0.0):
        raise ExcitationError(
            f"{source}: the model explains little of the measured acceleration (r2 "
            f"{r2:.3f}, while the data's noise allows {floor_r2:.3f}); check that "
            f"current_a is the torque-producing current (or force) of this axis and "
            f"position_rad its position, and run `gearbench diagnose` on the trace to see "
            f"which effect the model lacks")


def top_speed(velocity: np.ndarray) -> float:
    """The run's top speed (99.5th percentile of |w|), in the trace's own units."""
    return max(float(np.percentile(np.abs(velocity), 99.5)), 1e-300)


def standstill_speed(position: np.ndarray, velocity: np.ndarray, dt_s: float) -> float:
    """Speed below which the rotor counts as sticking: 1 encoder count per 6 samples
    (the encoder step read from the data), else a small share of the top speed."""
    q = encoder_resolution(position)
    if q > 0:
        return STANDSTILL_COUNTS_PER_SAMPLE * q / dt_s
    return STANDSTILL_TOP_FRACTION * top_speed(velocity)


# ------------------------------------------------------------------------- helpers
def _r2(y: np.ndarray, e: np.ndarray) -> float:
    ss = float(np.sum((y - y.mean()) ** 2))
    return float(1.0 - (e @ e) / ss) if ss > 0 else float("nan")


def _condition(X: np.ndarray) -> float:
    """2-norm condition number of X (n x k) with unit-norm columns (scale-free)."""
    return _condition_gram(X.T @ X)


def _condition_gram(G: np.ndarray) -> float:
    """Condition number of the column-normalised regressor matrix, from its Gram matrix."""
    d = np.sqrt(np.diag(G))
    if np.any(d == 0):
        return float("inf")
    ev = np.linalg.eigvalsh(G / np.outer(d, d))
    return float(np.sqrt(ev[-1] / ev[0])) if ev[0] > 0 else float("inf")


def _white_noise_variance(x: np.ndarray) -> float:
    """White-noise variance from the second difference (var = 6σ² for white noise),
    with a robust (MAD) scale so steps and spikes do not inflate it."""
    d2 = x[2:] - 2 * x[1:-1] + x[:-2]
    mad = float(np.median(np.abs(d2 - np.median(d2))))
    return (1.4826 * mad) ** 2 / 6.0


def _encoder_accel_noise(th: np.ndarray, dt: float, taps: np.ndarray) -> float:
    """rms acceleration that encoder quantisation alone produces after the filter."""
    q = encoder_resolution(th)
    h = np.convolve([1.0, -2.0, 1.0], taps) / dt ** 2
    return q / np.sqrt(12.0) * float(np.sqrt(h @ h))


def speed_range(velocity_rad_s: np.ndarray) -> list[float]:
    """[low, high] speed a run covered (0.5th/99.5th percentiles, so a glitch does not
    stretch it): where its friction losses D ω + Tc s(ω) were actually identified."""
    lo, hi = np.percentile(velocity_rad_s, [0.5, 99.5])
    return [float(lo), float(hi)]


def encoder_resolution(position_rad: np.ndarray) -> float:
    """Encoder step (rad) from the gaps between distinct angle increments; 0 if the
    angle does not look quantised."""
    steps = np.diff(np.asarray(position_rad[:200_000], float))
    scale = float(np.max(np.abs(steps))) if len(steps) else 0.0
    if scale == 0:
        return 0.0
    # relative rounding: the position's unit is the user's (rad, deg, mm, m)
    d = np.unique(np.round(steps / scale, 9)) * scale
    gaps = np.diff(d)
    gaps = gaps[gaps > 1e-8 * scale]
    return float(gaps.min()) if len(gaps) else 0.0


def _block_covariance(Xt: np.ndarray, e: np.ndarray, G: np.ndarray, *, block: int):
    """Sandwich covariance (X'X)⁻¹ Ω (X'X)⁻¹ with Ω = Σ_b S_b S_bᵀ over contiguous
    blocks (S_b = Σ_{t∈b} x_t e_t). Blocks longer than the residual correlation
    (several filter lengths) make Ω honest for coloured residuals; the t quantile
    uses blocks − 1 degrees of freedom. Also returns an effective sample count."""
    k, n = Xt.shape
    nb = max(n // block, 2)
    size = n // nb
    m = nb * size
    S = np.einsum("kbt,bt->bk", Xt[:, :m].reshape(k, nb, size), e[:m].reshape(nb, size))
    Ginv = np.linalg.inv(G)
    omega = S.T @ S * nb / max(nb - 1, 1)
    cov = Ginv @ omega @ Ginv
    # Effective n: how many white samples would give the same b2 variance.
    white = float(e @ e) / max(n - k, 1) * Ginv[0, 0]
    n_eff = float(n * white / cov[0, 0]) if cov[0, 0] > 0 else float(n)
    return cov, nb - 1, min(n_eff, float(n))


def t_quantile(dof: int, level: float = 0.95) -> float:
    return float(stats.t.ppf(0.5 + level / 2, max(dof, 1)))
