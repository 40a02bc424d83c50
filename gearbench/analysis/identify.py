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
            sub-sample instant as the angle's second difference sees it; stuck and
            breakaway stretches (a dwell the drive pushes against) left out of the
            equation (``equation_weight``: the raw equation is weighted 0 there before
            the filter, so the fit stays exact on what remains and its intervals count
            only that; a rotor at rest that nothing pushes stays in, friction 0 there);
            C fixed at 0 unless asked; a
            current-noise (errors-in-variables) correction; cogging harmonics
            sin/cos(k θ) with the orders k found from the data (``cogging_order_scores``
            screens k = 1…64 on the rotor angle, an information criterion keeps them);
            a parameter covariance from overlapping window sums of the residual scores
            (a Bartlett HAC estimate, valid for coloured residuals; window = the FIR or
            8 correlation times of the residual) with Student-t degrees of freedom
            1.5 (n/window − 1); optionally the setpoint-step term of a drive that steps
            its speed setpoint every SYNC (``setpoint_step``, shared between a motor's
            two calibration runs by ``calibration.share_setpoint_step``); optionally
            the speed loop's quantisation ripple in a current sampled at one instant
            (``SPEED_ERR``, from the speed estimate the drive reports, shared alike).

``check_excitation`` refuses data that cannot identify b2 (constant speed, no
acceleration content, ill-conditioned regressors) with an ``ExcitationError`` saying
what to change.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
from scipy import ndimage

from ..errors import ExcitationError, TraceError
from . import derivatives as dv
from .uncertainty import block_covariance, covariance_block, coverage_factor

# Regression written as  θ'' = b2·i − (D/J)·θ' − (Tc/J)·s(θ') − (C/J)·θ + bias.
KT_J, D_J, TC_J, C_J, BIAS, LAG = "Kt/J", "D/J", "Tc/J", "C/J", "bias", "lag"

MAX_CONDITION = 1e4          # of the column-normalised regressor matrix
MIN_ACCEL_SNR = 20.0         # rms filtered acceleration / rms encoder-noise acceleration
# No threshold is in the user's position unit (rad, deg, mm, m are all valid): speeds
# come from the encoder step, the sample rate and the run's own speed range.
STANDSTILL_COUNTS_PER_SAMPLE = 1 / 6   # slower than 1 count per 6 samples (>= 3 samples): sticks
STANDSTILL_TOP_FRACTION = 3e-4  # without a visible encoder step: this share of the top speed
# A reversal is a dwell below this share of the top speed too, whatever the encoder: a 20-bit
# encoder resolves the creep while the current swings through the friction's transition,
# which sign(ω) does not describe (robustness seeds 7/8, every encoder at 2^20 counts/rev,
# ``--encoder-counts 1048576``: plants meeting every target 56/65 -> 64/71 %, reversing
# ones 29/14 -> 53/43 %, biased 14/8 -> 8/8 %, exceptions 1/1 -> 0/0; D of the reversing
# motors 1.37x its truth (median) before; encoders as drawn: seed 7 unchanged, seed 8
# 85 -> 84 % (case 13's output Kt -0.18 -> -0.25 ± 0.19 %)). A start from rest keeps the
# encoder's band: its acceleration is the run's information.
CREEP_TOP_FRACTION = 1e-3
SHORT_SPEED_SPAN = 6          # samples: the standstill speed's own window (equation_weight)
STICK_BAND = 3.0            # x the standstill speed: the slow stretch around a dwell, left out
STICK_MARGIN_S = 0.01       # ... widened by this on each side (presliding, breakaway),
STICK_MARGIN_SAMPLES = 2     # and by at least this many samples (100 Hz: 10 ms is 1 sample)
STUCK_CURRENT_SIGMAS = 4.0   # a dwell is stuck only while the drive pushes: |running mean i| > this x its noise
PUSHED_MIN_SAMPLES = 5       # ... over the margin's samples, at least this many
LEFT_OUT_WARN_SHARE = 0.25   # warn when more of the run than this is left out
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

    Parameters
    ----------
    time_s, position_rad, current_a : the run's samples (s, rad, A).
    decimate_s : keep every k-th sample first (the paper sampled at 15 ms).
    no_load_current_a : subtracted from the current (the paper's variant).
    check : refuse constant speed or current.
    source : the run's name for messages.

    Returns
    -------
    IdentificationResult
        ``Kt/J``, ``D/J``, ``C/J`` with a white-residual covariance (information only).

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md)

    Examples
    --------
    >>> fit = identify_paper(t, theta, i, decimate_s=0.015)   # doctest: +SKIP

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
# Equation forms (``identify_default(form=...)``), compared in ``bench accuracy``/``robustness``:
#   accel   θ'' = b2 i − (D/J)θ' − (Tc/J)s − …   least squares, errors in the current regressor
#           corrected for white current noise (the form this module started with);
#   torque  i = (J/Kt)θ'' + (D/Kt)θ' + (Tc/Kt)s + …   inverse-dynamics least squares as robotics
#           uses it (IDIM-LS, Gautier & Khalil 1988; Janot, Vandanjon & Gautier 2014): the
#           current, noisy and carrying whatever the model lacks, is the dependent variable;
#   iv      the torque form with instrumental variables built from the recorded speed command
#           (its filtered value, derivative and sign), which no disturbance inside the loop
#           can reach (Janot et al. 2014, IDIM-IV; Söderström & Stoica 1989, ch. 8).
FORMS = ("auto", "accel", "torque", "iv")
# Chosen from the measurements in ``bench accuracy`` (real section: robot joints at 100 Hz,
# EMPS at 1 kHz/250 Hz/100 Hz) and ``bench robustness --methods accel,torque,iv``: the
# torque form matches the accel form on the random plants and is right where the accel
# form fails (friction-dominated joints: J 4-5x too large); iv is unbiased there too but
# its intervals are 1.5-3x wider, so fewer runs meet the targets.
AUTO_FORM = "torque"
# Share of the two regression directions' difference added as model-error variance:
# (Δ/2)², the variance of a value anywhere between them (as calibration.LOSS_RUN_SPREAD).
FORM_SPREAD = 0.25
# ... unless the other direction's key regressor carries more than this share of noise:
# then it is attenuated by errors in variables (friction-dominated robot joints: accel form
# 0.12-5.5) and its difference says nothing about this fit's model error (random plants
# at 1 kHz: <= 0.05)
FORM_SPREAD_MAX_SHARE = 0.1
LOAD_SIN, LOAD_COS = "load_sin", "load_cos"
SP_STEP = "setpoint_step"
# The speed loop's encoder-quantisation ripple in a current sampled at one instant: the
# drive's P gain turns its speed estimate's count quantum into current, and the instant
# sample aliases that into the fit band, where it follows the motion (noise-free forward
# random plants: Kt off by 0.2-0.5 %, gone with a fine encoder or a period-mean current).
# Its regressor is e = F[v_drive] − F[θ'], the speed the drive reports (CiA 402 0x606C,
# ``velocity_rad_s``) less the encoder's, both through the fit's filter. e also holds the
# drive estimate's lag, −τ·θ'', so within one run its gain trades with J/Kt; one gain for
# both calibration runs (``calibration.share_setpoint_step``) puts the same γ·τ on both
# runs' J/Kt, which cancels in eq. 17. Not on reversing runs: around the zero crossing
# the drive's estimate and the encoder part for other reasons (seeds 7/8: helped 10, hurt 7
# reversing motors by > 0.05 % noise-free, against 12/3 forward).
SPEED_ERR = "speed_error"
# The common filter's cutoff: at most 40 Hz and a tenth of the rate, and no more than
# MOTION_BAND_FACTOR x the motion's own band (``default_cutoff``). Under a position or speed
# loop what lies above the motion's band is the loop's answer to disturbances, which
# correlates with the equation error (closed-loop bias); the motion itself lies below
# (a decade holds the odd harmonics a Coulomb sign adds up to the 9th; the IDIM practice).
MOTION_BAND_FACTOR = 10.0
MOTION_BAND_SHARE = 0.99       # the band: below it this share of the velocity's variance
MIN_FILTER_RUNS = 8            # the filter at most 1/8 of the run (its taps ≈ 5.5·rate/cutoff)


@dataclass
class _Signals:
    """One run's filtered, aligned signals (``_prepare``)."""

    th: np.ndarray              # angle, first sample subtracted
    dt: float
    cutoff_hz: float
    taps: np.ndarray
    w_smooth: np.ndarray        # speed at every raw sample
    moving: np.ndarray          # equation weight: 0 on stuck/breakaway stretches, else 1
    fs: dict                    # filtered signals, ``consistent_derivatives`` layout
    reverses: bool
    noise_var_raw: float        # white current-noise variance, A²
    source: str
    i_raw: np.ndarray | None = None   # raw current (weighted form: the lag refit filters it again)
    current_mean: bool = False        # each current sample the mean over the period ending at it

    @property
    def n(self) -> int:
        return len(self.fs["acceleration"])

    @property
    def at(self) -> slice:
        """Raw samples under the filtered ones."""
        half = (len(self.taps) - 1) // 2
        return slice(half + 1, half + 1 + self.n)

    def matched(self, rows: np.ndarray, match=dv.match_samples) -> np.ndarray:
        """Rows through ``match``, the equation weight and the FIR (as ``fs``)."""
        if self.i_raw is None:
            return dv.matched_filter(rows * self.moving, self.taps)
        x = match(np.atleast_2d(rows)) * self.moving
        return dv.filter_valid_rows(x, self.taps)[:, 1:-1]

    def matched_current(self, rows: np.ndarray) -> np.ndarray:
        """Current-like rows through the current's match (``current_mean``:
        ``derivatives.match_period_means``), the equation weight and the FIR."""
        return self.matched(rows, dv.match_period_means if self.current_mean else dv.match_samples)

    @property
    def current_match(self) -> np.ndarray:
        return dv.PERIOD_MEAN_MATCH if self.current_mean else dv.SECOND_DIFFERENCE_MATCH

    @cached_property
    def speed_range(self) -> list[float]:
        """Speeds the run covered (once per run: a percentile of n samples is not free)."""
        return speed_range(self.w_smooth)

    @cached_property
    def accel_noise(self) -> float:
        """rms acceleration encoder quantisation alone produces after the filter."""
        return _encoder_accel_noise(self.th, self.dt, self.taps)


def _prepare(t, th, i, *, cutoff_hz, friction_width_rad_s, command, source,
             current_limit_a=None, kick_a_per_rad_s=None, drive_velocity=None,
             current_mean=False, period_kick=None) -> _Signals:
    """Filter every signal with one zero-phase FIR (``derivatives.consistent_derivatives``).

    The Coulomb step is integrated at its sub-sample reversal instant as the angle's second
    difference sees it (``derivatives.coulomb_regressor``). While the rotor sticks
    static friction balances whatever the drive gives (any value up to the breakaway),
    and sign(θ') does not describe the breakaway either: those samples, with a margin,
    are weighted out of the raw equation before the filter (``equation_weight``,
    ``derivatives.weighted_derivatives``), so the filtered equation stays exact on the
    rest. A stuck stretch carries no Kt information; the intervals count what remains.
    A rotor at rest with no current (before a speed step from rest) is not stuck: it
    stays in with its friction term 0."""
    dt = float(np.median(np.diff(t)))
    rate = 1.0 / dt
    cutoff_hz = cutoff_hz or default_cutoff(t, th)
    taps = dv.lowpass_fir(cutoff_hz, rate)
    if len(t) < len(taps) + 50:
        raise TraceError(f"{source}: only {len(t)} samples, need at least {len(taps) + 50} "
                         f"at {rate:.4g} Hz for the {cutoff_hz:.3g} Hz filter; record a longer run")
    th = th - th[0]
    hw = smoothing_half_width(dt)
    w_smooth = dv.smooth_velocity(th, dt, half_width=hw)
    extra = {} if command is None else {"command": np.asarray(command, float)}
    reverses = _reverses(w_smooth)
    if kick_a_per_rad_s and command is not None:
        # the current the sampled equation holds for (``kick_coefficient``; spreading each
        # kick over the equations it reaches moved Kt < 0.04 %, D < 4 % of itself)
        i = np.asarray(i, float) + kick_a_per_rad_s * dt * _setpoint_steps(
            extra["command"], dt) * _below_current_limit(
            i, current_limit_a, float(np.sqrt(_white_noise_variance(i))))
    noise_var = _white_noise_variance(i)     # once: a robust scale of n samples is not free
    if friction_width_rad_s:
        # Legacy: smoothed sign of the raw speed, sampled, then 3-tap matched.
        w_raw = np.empty_like(th)
        w_raw[1:-1] = (th[2:] - th[:-2]) / (2 * dt)
        w_raw[0], w_raw[-1] = w_raw[1], w_raw[-2]
        moving = np.ones_like(th)
        fs = dv.consistent_derivatives(
            th, {"current": i, "sign": np.tanh(w_raw / friction_width_rad_s), "moving": moving,
                 **extra}, dt, taps)
    else:
        w_still = standstill_speed(th, w_smooth, dt)
        moving = equation_weight(w_smooth, w_still, dt, current=i,
                                 current_noise=float(np.sqrt(noise_var)),
                                 angle=th, creep_speed=CREEP_TOP_FRACTION * top_speed(w_smooth))
        # a rotor at rest that nothing pushes stays in the equation (J θ'' = Kt i = 0, a
        # speed step from rest), its friction is zero there, not ±Tc
        sliding = 1.0 - (dv.standstill(w_smooth, w_still) > 0) * (moving == 1.0)
        matched = {"sign": dv.coulomb_regressor(
            th, dt, velocity=dv.refine_reversals(th, w_smooth, half_width=hw)) * sliding}
        if command is not None:
            matched["command_sign"] = np.sign(extra["command"]) * sliding
            matched["setpoint_step"] = _setpoint_steps(extra["command"], dt) * _below_current_limit(
                i, current_limit_a, float(np.sqrt(noise_var)))
        # the masked offset column is needed only where an offset is fitted (reversing)
        others = {"current": i, **({"moving": np.ones_like(th)} if reverses else {})}
        kicks = period_kick is not None and command is not None
        if current_mean or kicks:
            # the current matched here (period means: ``derivatives.match_period_means``)
            # where it is not the instant samples' plain match: kicks are added to it
            match = dv.match_period_means if current_mean else dv.match_samples
            matched["current"] = match(others.pop("current"))
        if kicks:
            # what the match cannot see of the setpoint's shape within each period (a
            # stepping drive's front-loaded kicks, an interpolating one's kinks:
            # ``declared_period_kick``); none where the drive sits at its current limit
            # (``_below_current_limit``). Kept apart too: the lag refit re-matches the raw
            # current and adds it back
            kick = _period_kick_current(np.asarray(period_kick, float), extra["command"]) * (
                _below_current_limit(i, current_limit_a, float(np.sqrt(noise_var))))
            matched["current"] = matched["current"] + kick
            matched["current_kick"] = kick
        if drive_velocity is not None:
            others["drive_velocity"] = np.asarray(drive_velocity, float)
        fs = dv.weighted_derivatives(th, others, dt, taps, moving, matched=matched,
                                     unweighted=extra)
        return _Signals(th, dt, cutoff_hz, taps, w_smooth, moving, fs, reverses,
                        noise_var, source, i_raw=np.asarray(i, float),
                        current_mean=bool(current_mean))
    return _Signals(th, dt, cutoff_hz, taps, w_smooth, moving, fs, reverses,
                    noise_var, source)


def motion_band_hz(time_s: np.ndarray, position: np.ndarray, share: float = MOTION_BAND_SHARE) -> float:
    """The frequency below which ``share`` of the velocity's variance lies: the motion's band.

    Periodogram of the angle's first difference (Hann window, its mean removed); any
    angle unit. Stick-slip and steps spread the velocity's power, so their band is wide.

    Parameters
    ----------
    time_s, position : the run's samples.
    share : the share of the variance below the band's edge.

    Returns
    -------
    float
        Hz (0 for a run that does not move).

    References
    ----------
    P. Stoica and R. Moses, *Spectral Analysis of Signals*, Prentice Hall 2005, sec. 2.6 (windowed periodogram)

    Examples
    --------
    >>> t = np.arange(6000) * 0.01
    >>> round(motion_band_hz(t, np.sin(2 * np.pi * 0.5 * t)), 1)   # the window's leakage
    0.5
    """
    t = np.asarray(time_s, float)
    dt = float(np.median(np.diff(t)))
    w = np.diff(np.asarray(position, float)) / dt
    if len(w) < 8 or not np.any(w != w[0]):
        return 0.0
    w = w - w.mean()
    power = np.abs(np.fft.rfft(w * np.hanning(len(w)))) ** 2
    power[0] = 0.0
    cum = np.cumsum(power)
    f = np.fft.rfftfreq(len(w), dt)
    return float(f[min(int(np.searchsorted(cum, share * cum[-1])), len(f) - 1)])


def default_cutoff(time_s: np.ndarray, position: np.ndarray) -> float:
    """The common filter's default cutoff: min(40 Hz, rate/10, MOTION_BAND_FACTOR × the
    motion's band), never so low that the filter exceeds 1/MIN_FILTER_RUNS of the run.

    Above the motion's band a closed loop (the position loop of a robot joint, the speed
    loop of a drive) puts its answer to disturbances into the angle and the current; that
    content correlates with the equation error and biases least squares (measured on the
    second joint simulator's PID-loop wrist at 100 Hz: J −4.6 % at 10 Hz, −3.2 % at its
    motion-band cutoff 5.5 Hz; the first simulator's wrist −6.2 % → −2.0 %). A multisine
    calibration up to 10 Hz, or any run faster than 4 Hz, keeps 40 Hz.

    Parameters
    ----------
    time_s, position : the run's samples.

    Returns
    -------
    float
        Hz.

    References
    ----------
    M. Gautier, "Dynamic identification of robots with power model", Proc. IEEE ICRA 1997
    (the filter's cutoff about ten times the joint dynamics' band in inverse-dynamics
    least squares); U. Forssell and L. Ljung, "Closed-loop identification revisited",
    Automatica 35, 1999 (the bias of direct least squares under feedback).

    Examples
    --------
    >>> t = np.arange(6000) * 0.01
    >>> round(default_cutoff(t, np.sin(2 * np.pi * 0.5 * t)))   # a 0.5 Hz sine at 100 Hz
    5
    >>> round(default_cutoff(t, np.sin(2 * np.pi * 8 * t)), 1)  # rate/10
    10.0
    """
    t = np.asarray(time_s, float)
    rate = 1.0 / float(np.median(np.diff(t)))
    cutoff = dv.rate_cutoff(rate)
    band = motion_band_hz(t, position)
    if band > 0:
        shortest = 5.5 * rate * MIN_FILTER_RUNS / max(len(t), 1)
        cutoff = min(cutoff, max(MOTION_BAND_FACTOR * band, shortest))
    return float(cutoff)


def _reverses(w_smooth: np.ndarray) -> bool:
    """A run "reverses" where over 5 % of it is beyond ±REVERSAL_TOP_FRACTION of its top
    speed in each direction."""
    w_rev = REVERSAL_TOP_FRACTION * top_speed(w_smooth)
    return bool(np.mean(w_smooth > w_rev) > 0.05 and np.mean(w_smooth < -w_rev) > 0.05)


def kick_coefficient(kp_a_s_per_rad: float, current_lag_s: float, period_s: float,
                     loop_period_s: float) -> float:
    """The current kick of a drive that steps its speed setpoint each SYNC and samples its
    current at the SYNC instant, c in A per rad/s of setpoint step (ī = i + c·Δcmd).

    Derivation (the discrete loop within one period T): the sampled equation
    J Δ²θ_k = Kt ∫ i(t) tri(t − t_k) dt − … holds for the triangle-weighted current
    ĩ_k (``derivatives.match_samples`` takes it from samples of a piecewise-linear
    current). Against a drive that ramps to the new setpoint (reaching it at the last
    of its M = T/T_loop speed-loop ticks), stepping adds the P-command pulse
    Kp·Δcmd·p_m, p_m = 1 − (m+1)/M at tick m, through the first-order current loop
    (time constant τ) as g(u). The samples see g(nT), n ≥ 1 (the sample at t_k is taken
    before the period's first tick), the triangles its area: summed over the periods a
    kick reaches,

        c/Kp = (1/T)∫g du − Σ_{n≥1} g(nT) = mean_m p_m − g(T)/(1 − e^{−T/τ}),
        g(T) = Σ_m p_m (e^{−(T − t_{m+1})/τ} − e^{−(T − t_m)/τ}),  t_m = m T/M.

    The speed's own response to the kick within the period changes c by O(x·τ/T),
    x = Kp·Kt·T/J: with τ = 0 it is c/Kp = 1/x − 1/(e^x − 1) = 1/2 − x/12 + …, with
    τ ≥ 0.3 T the simulated drive's c/Kp stays within 0.6 % over x = 0.01–0.2, so one
    c serves both calibration runs. Noise-free (robustness seeds 4, 5: 15 forward
    drives) this c, instead of one fitted from the runs (``calibration.calibrate_motor``,
    current delay fitted), takes Kt from +0.10 ± 0.13 % (mean, rms) to +0.01 ± 0.04 %;
    Kp 10 % off moved Kt by 0.02–0.04 %. τ = 0: g is the pulse itself
    (c/Kp = (M−1)/(2M)).

    Examples
    --------
    >>> round(kick_coefficient(1.0, 0.6e-3, 1e-3, 0.25e-3), 3)
    0.124
    """
    m = max(1, int(round(period_s / loop_period_s)))
    p = 1.0 - (np.arange(m) + 1.0) / m
    if current_lag_s <= 0:
        return float(kp_a_s_per_rad * np.mean(p))
    t_m = np.arange(m + 1) * period_s / m
    g_t = float(np.sum(p * (np.exp(-(period_s - t_m[1:]) / current_lag_s)
                            - np.exp(-(period_s - t_m[:-1]) / current_lag_s))))
    return float(kp_a_s_per_rad * (np.mean(p) - g_t / -np.expm1(-period_s / current_lag_s)))


PERIOD_KICK_PERIODS = 8     # periods a step's pulse is followed over (the current loop's τ ≤ T here)
PERIOD_KICK_FINE = 64       # sub-steps per speed-loop tick for the pulse's shape


def period_mean_kick_weights(kp_a_s_per_rad: float, current_lag_s: float, period_s: float,
                             loop_period_s: float) -> np.ndarray:
    """What the period means' match misses of a drive that steps its speed setpoint each
    SYNC and reports its current as the period mean: weights w_n, n = −2 … 7 (A per rad/s
    of the setpoint step of the period ending n samples before), so that

        ĩ_k = match(m)_k + Σ_n w_n Δcmd_{k−n}.

    Derivation: the sampled equation J Δ²θ_k = Kt ∫ i(t) tri(t − t_k) dt − … holds for the
    triangle-weighted current ĩ_k; ``derivatives.PERIOD_MEAN_MATCH`` rebuilds it from the
    period means m_k, exactly for a current smooth across periods. Stepping adds in each
    period the P pulse Kp·Δcmd·p_m, p_m = 1 − (m+1)/M at tick m (against a drive that
    ramps, as ``kick_coefficient``), through the first-order current loop (τ): g(u), front-
    loaded in its period. With its period means G_n and the triangle's rising halves
    R_n = (1/T)∫ g·(u − nT)/T over period n (falling halves F_n = G_n − R_n),

        w_n = R_n + F_{n+1} − (−G_{n−1} + 13 G_n + 13 G_{n+1} − G_{n+2})/24.

    Σ w_n = 0: a steady acceleration's kicks are matched; a changing one's are not, and the
    closed loop's phase puts part of that in phase with θ''. At 250 Hz (robustness seed 8
    case 58's input drive, noise-free, 2^20 counts) b2 came out −0.151 % without the
    correction and −0.000 % with it (the exact triangle: +0.02 %), in both runs alike (x =
    Kp·Kt·T/J 0.63 and 0.20: the speed's own response within the period is left out); the
    bias grew with Kp (−0.06/−0.15/−0.26 % at Kp ×½/1/2), and at 1 kHz it is ≤ 0.02 %.

    Examples
    --------
    >>> w = period_mean_kick_weights(0.09, 0.42e-3, 4e-3, 0.25e-3)
    >>> len(w), abs(float(w.sum())) < 1e-12
    (10, True)
    """
    m = max(1, int(round(period_s / loop_period_s)))
    # a step against a ramp: the pulse 1 − (m+1)/M over one period, nothing after
    return _match_error(1.0 - (np.arange(m) + 1.0) / m, 0.0, "mean", kp_a_s_per_rad,
                        current_lag_s, period_s, loop_period_s)


def interpolated_kink_weights(kp_a_s_per_rad: float, current_lag_s: float, period_s: float,
                              loop_period_s: float) -> np.ndarray:
    """What the 3-tap match of instant current samples misses of a drive that ramps its
    speed setpoint linearly over each SYNC period: weights w_n, n = −2 … 7 (A per rad/s of
    the setpoint's rise over the period ending n samples before), so that

        ĩ_k = match(i)_k + Σ_n w_n Δcmd_{k−n}.

    Why: the ramps join with a kink at every SYNC, where the setpoint's slope changes by
    Δ²cmd/T; the speed loop's P gain passes the kinks into the current, and through the
    current loop (τ) the sample at the period's end sees them at one phase while the
    rotor integrates them over the triangle about it. ``derivatives.SECOND_DIFFERENCE_MATCH``
    ([1, 10, 1]/12, exact for a current smooth across samples) cannot see that. The
    weights are a unit ramp's P current (held per speed-loop tick, through τ) taken as the
    rotor sees it (triangle) less as the match sees it (samples at period ends); their
    steady part Σw — a smooth setpoint's hold and lag, a delay that the fitted current
    delay already takes for the whole current — is taken out, so Σw = 0.

    Measured noise-free (robustness seed 7 cases 1, 37 and 52, interpolating drives with
    instant current, 2^20 counts, no cogging): at 250 Hz b2 −0.157/−0.089/−0.144 % without,
    −0.004/−0.003/−0.015 % with them, unchanged at 1 kHz (≤ 0.014 % either way); at 100 Hz
    −1.12 % → −0.03 %; the same at Kp ×½ and ×2 and a 0.1 ms loop. A drive with no current
    lag (τ = 0) keeps −0.2 % at 250 Hz: its samples sit on the knots, and what remains is
    not this.

    Examples
    --------
    >>> w = interpolated_kink_weights(0.005, 0.3e-3, 4e-3, 0.25e-3)
    >>> len(w), abs(float(w.sum())) < 1e-12
    (10, True)
    """
    m = max(1, int(round(period_s / loop_period_s)))
    w = _match_error((np.arange(m) + 1.0) / m, 1.0, "instant", kp_a_s_per_rad,
                     current_lag_s, period_s, loop_period_s)
    steady = float(w.sum())
    w[1:3] -= steady / 2.0        # n = −1, 0: the slope at t_k, from the periods either side
    return w


def _match_error(first: np.ndarray, hold: float, current: str, kp_a_s_per_rad: float,
                 current_lag_s: float, period_s: float, loop_period_s: float) -> np.ndarray:
    """Triangle-weighted current less the match of its samples, n = −2 … 7, for a setpoint
    that is ``first`` (per speed-loop tick) over period 0 and ``hold`` after, times Kp,
    through a first-order current loop. ``current``: "mean" (period means, the 4-tap
    ``PERIOD_MEAN_MATCH``) or "instant" (the value at each period's end, the 3-tap match)."""
    from scipy.signal import lfilter

    m = len(first)
    per = m * PERIOD_KICK_FINE
    x = np.concatenate([np.repeat(first, PERIOD_KICK_FINE), np.full(per * (PERIOD_KICK_PERIODS - 1), hold)])
    if current_lag_s > 0:
        a = -np.expm1(-(loop_period_s / PERIOD_KICK_FINE) / current_lag_s)
        g = lfilter([a], [1.0, a - 1.0], x)
    else:
        g = x
    g = kp_a_s_per_rad * g.reshape(PERIOD_KICK_PERIODS, per)
    G = g.mean(axis=1)
    R = (g * ((np.arange(per) + 0.5) / per)).mean(axis=1)
    F = G - R
    E = g[:, -1]

    def pad(v):   # v_n at [n + 3]; before the step nothing, after it what it settled to
        return np.concatenate([np.zeros(3), v, np.full(3, v[-1])])
    Gp, Rp, Fp, Ep = pad(G), pad(R), pad(F), pad(E)
    n = np.arange(-2, PERIOD_KICK_PERIODS)
    tri = Rp[n + 3] + Fp[n + 4]
    # both matches start at sample k − 1
    seen, kernel = (Gp, dv.PERIOD_MEAN_MATCH) if current == "mean" else (Ep, dv.SECOND_DIFFERENCE_MATCH)
    return tri - sum(c * seen[n + 2 + j] for j, c in enumerate(kernel))


# drive kinds (setpoint, current) whose declared loop gives weights (``declared_period_kick``),
# and every kind whose loop the analysis uses (``declared_kick``: step, instant)
PERIOD_KICK_WEIGHTS = {("step", "mean"): period_mean_kick_weights,
                       ("interpolated", "instant"): interpolated_kink_weights}
LOOP_DRIVE_KINDS = (("step", "instant"), *PERIOD_KICK_WEIGHTS)


def _period_kick_current(weights: np.ndarray, command: np.ndarray) -> np.ndarray:
    """Σ_n w_n Δcmd_{k−n} (``period_mean_kick_weights``), Δcmd_k the setpoint step of the
    period ending at sample k: command[k] is applied during [t_k, t_{k+1}), so that step is
    command[k−1] − command[k−2]."""
    step = np.zeros(len(command))
    step[2:] = command[1:-1] - command[:-2]
    return np.convolve(step, weights)[2:2 + len(step)]


def _setpoint_steps(command: np.ndarray, dt: float) -> np.ndarray:
    """The speed setpoint's step at each SYNC, Δcmd_k / dt (rad/s², first sample 0).

    Why (a drive that steps its setpoint and samples its current at one instant):
    the rotor integrates the current over the period, J Δω = Kt ∫ i dt − ∫ f dt, so the
    torque equation holds for the period-mean current ī_k. With its speed loop ticking
    at t_m = t_{k−1} + m T/M (m = 0..M−1), a drive that applies each setpoint as a step
    commands Kp·Δcmd_k·(1 − (m+1)/M) more current at tick m than one that ramps to it
    (the P part of the error it sees); through a first-order current loop (time
    constant τ) that periodic kick has a period mean and an end-of-period value both
    proportional to Kp·Δcmd_k, with factors set by τ/T and M alone. A sample at the SYNC
    instant sees the kick's end value, the rotor its mean, hence to first order

        ī_k = i_k + c·Δcmd_k,   c = Kp·(h̄(τ/T, M) − h_T(τ/T, M)),

    with the same c for every run on that drive: the speed's own response to the kick
    within the period changes c by O(x), x = Kp·Kt·T/J (ideal current loop:
    c/Kp = 1/x − 1/(e^x − 1) = 1/2 − x/12 + …), but behind a current loop of τ ≥ 0.3 T
    c/Kp stays within 0.6 % over x = 0.01–0.2 (simulated steady speed ramp). Combined,
    Kt still comes out high by about x/100 of itself, x of the unloaded run (noise-free,
    robustness seeds 4+5, 15 forward drives: +0.03/+0.08/+0.22 % mean for x below 0.05,
    0.05–0.1, above 0.1), and the cause is the fitted c, not the relation: with the
    exact triangle-weighted current (no kick left) each run's fit still finds
    c ≈ 0.03 Kp and b2 low by up to 0.55 % (0.02 % without the term), and a drive
    that interpolates gets 0.07–0.10 Kp: nearly collinear with θ'', the term takes up
    misfit that differs between the runs. Where the drive declares its loop (Kp, τ,
    loop period), ``kick_coefficient`` gives c in closed form and it is added to the
    current, not fitted; the current delay is then fitted, as D and Tc need it even
    from the exact current (4 seed-7 motors noise-free: D +33…+212 % without, within
    5 % with): those 15 drives +0.005/−0.001/+0.045 %, and with the drawn noise 69
    forward kick motors of seeds 7+8 from +0.09 ± 0.14 % (mean, rms) to +0.02 ± 0.09 %.
    Without the declared loop (or on a reversing run, where the fitted term also takes
    up the zero crossing's misfit) Δcmd/T follows θ'' within one run (the loop follows
    its command), so ``calibration.share_setpoint_step``
    fits one c for both runs of a motor and Kt from their difference. An interpolating
    drive (c = 0) or a period-averaged current (the sample is ī_k) has no such term
    (robustness benchmark, seed 8 case 11 input: b2 of the unloaded run +0.87 % from
    the sample, +0.04 % from the period mean)."""
    d = np.zeros_like(command)
    d[1:] = np.diff(command) / dt
    return d


def _below_current_limit(current_a: np.ndarray, limit_a: float | None,
                         noise_std_a: float) -> np.ndarray:
    """1 where the current sample is below the drive's limit, 0 where it sits at it (within
    3 noise std), all 1 without a limit.

    Why: where the drive holds its current command at the limit the whole SYNC period,
    the setpoint step adds no kick (its speed loop's P part is clipped away), so the
    sample is the period mean and ``_setpoint_steps``'s term c·Δcmd is 0 there. A run
    that sits at the limit on half its samples (the loaded one: it needs more current)
    otherwise shares one c with a run that hardly does (robustness seed 11 case 8's
    output motor: at the limit on 66 % of the loaded and 20 % of the unloaded samples,
    Kt −0.55 ± 0.11 %; with the term zeroed there −0.01 ± 0.08 %; an unlimited drive
    +0.15 %)."""
    if not limit_a:
        return np.ones_like(current_a)
    return (np.abs(current_a) < limit_a - 3.0 * noise_std_a).astype(float)


def _base_columns(sig: _Signals, form: str, *, spring: bool, use_bias: bool) -> list:
    """(name, filtered regressor, sign) of the motor model in ``form``; ``sign`` maps the
    fitted coefficient onto the accel-form names of the module docstring."""
    fs = sig.fs
    if form == "accel":
        cols = [(KT_J, fs["current"], 1.0), (D_J, fs["velocity"], -1.0), (TC_J, fs["sign"], -1.0)]
        offset = np.ones(sig.n)
    else:
        cols = [(KT_J, fs["acceleration"], 1.0), (D_J, fs["velocity"], 1.0),
                (TC_J, fs["sign"], 1.0)]
        offset = fs.get("moving", np.ones(sig.n))
    if spring:
        cols.append((C_J, fs["position"], -1.0 if form == "accel" else 1.0))

    if use_bias:
        cols.append((BIAS, offset, 1.0 if form == "accel" else -1.0))
    return cols


def _harmonic_columns(sig: _Signals, prefix: str, angle_rad: np.ndarray, orders, form: str) -> list:
    """sin/cos(k·angle) of the position-dependent torques (cogging, load), masked while
    the rotor sticks, through the same filters as the current."""
    harm = np.vstack([f(k * angle_rad) for k in orders for f in (np.sin, np.cos)])
    filt = sig.matched(harm)
    s = 1.0 if form == "accel" else -1.0
    return [(f"{prefix}{k}_{p}" if prefix else f"{p}", filt[2 * j + q], s)
            for j, k in enumerate(orders) for q, p in enumerate(("sin", "cos"))]


def _load_columns(sig: _Signals, load_rad_per_unit: float | None, form: str) -> list:
    """Position-dependent load torque of order 1 in the load angle (gravity on an arm,
    an unbalance, an eccentric load): q_s sin θ_L + q_c cos θ_L, θ_L = angle × ``load_rad_per_unit``."""
    if not load_rad_per_unit:
        return []
    cols = _harmonic_columns(sig, "", sig.th * load_rad_per_unit, (1,), form)
    return [((LOAD_SIN, LOAD_COS)[k], c[1], c[2]) for k, c in enumerate(cols)]


@dataclass
class _Fit:
    """A solved regression in its own form (coefficients ``beta`` on rows of ``Xt``)."""

    form: str
    cols: list
    beta: np.ndarray
    Xt: np.ndarray               # k x n regressors as used (lag column last)
    Z: np.ndarray | None         # instruments (iv) or None
    y: np.ndarray
    A: np.ndarray                # normal matrix (Z'X for iv), EIV-corrected
    G: np.ndarray                # plain Gram matrix X'X
    shift_s: float

    @property
    def residual(self) -> np.ndarray:
        return self.y - self.beta @ self.Xt


def _fit(sig: _Signals, cols: list, form: str, *, lag: bool, eiv: bool) -> _Fit:
    """Solve ``cols`` in ``form`` (see ``_solve`` for the accel form's lag and EIV)."""
    if form == "accel":
        noise = sig.noise_var_raw * float(np.sum(np.convolve(sig.current_match,
                                                             sig.taps) ** 2))
        beta, Xt, G, Gc, shift = _solve(cols, y=sig.fs["acceleration"],
                                        noise_var=noise if eiv else 0.0, lag=lag, dt=sig.dt,
                                        source=sig.source)
        return _Fit(form, cols, beta, Xt, None, sig.fs["acceleration"], Gc, G, shift)
    Z = _instruments(sig, cols) if form == "iv" else None
    acc_noise = sig.accel_noise ** 2 if eiv and form == "torque" else 0.0
    return _solve_torque(cols, sig, Z=Z, lag=lag, accel_noise_var=acc_noise)


def _instruments(sig: _Signals, cols: list) -> np.ndarray:
    """Rows of instruments for the iv form: the speed command (filtered as the angle's
    speed), its derivative and its sign stand for θ', θ'' and s(θ'); the other columns
    are their own instruments (the angle is known to an encoder count)."""
    fs = sig.fs
    if "command" not in fs:
        raise ExcitationError(f"{sig.source}: the iv form needs the recorded speed command "
                              f"(column 'command'); use form 'torque' or record the command")
    cmd = fs["command"]
    sub = {KT_J: np.gradient(cmd, sig.dt), D_J: cmd, TC_J: fs["command_sign"]}
    rows = [sub.get(c[0], c[1]) for c in cols]
    return np.vstack(rows)


def _solve_torque(cols, sig: _Signals, *, Z, lag, accel_noise_var):
    """Least squares (or IV) of the filtered current on ``cols`` with a lag column.

    A current measured τ late, i(t + τ) ≈ i + τ i', is the torque-producing one: the
    column −i' carries τ; past ~0.1 sample the τ² term matters, so the current is shifted
    by the estimate and refitted (as ``_solve``). Encoder noise on θ'' (errors in
    variables for this form) is subtracted from its diagonal: ``n·accel_noise_var``."""
    base = sig.fs["current"]
    n = len(base)
    k = len(cols) + bool(lag)
    Xt = np.empty((k, n))
    for r, c in enumerate(cols):
        Xt[r] = c[1]
    y = base
    raw = sig.i_raw

    def lag_column(y, shifted):
        # d/dt of the weighted, filtered current is not the weighted derivative where the
        # weight steps: differentiate the raw current, then weight and filter it
        if raw is None:
            return -np.gradient(y, sig.dt)
        return -sig.matched_current(np.gradient(shifted, sig.dt))[0]

    if lag:
        Xt[-1] = lag_column(y, raw)
    Zt = None
    if Z is not None:
        Zt = np.vstack([Z, Xt[-1:]]) if lag else Z
    shift_s = 0.0
    for _ in range(4 if lag else 1):
        G = Xt @ Xt.T
        if Zt is None:
            A = G.copy()
            A[0, 0] -= n * accel_noise_var
            rhs = Xt @ y
        else:
            A = Zt @ Xt.T
            rhs = Zt @ y
        try:
            beta = np.linalg.solve(A, rhs)
        except np.linalg.LinAlgError:
            raise ExcitationError(f"{sig.source}: regressors are linearly dependent; the run "
                                  f"needs speed changes that are not a copy of its current "
                                  f"(acceleration, speed and reversals varying on their own)") from None
        if not lag:
            break
        tau = float(beta[-1])
        if abs(tau) < 0.02 * sig.dt or abs(shift_s + tau) > 5 * sig.dt:
            break
        shift_s += tau
        if raw is None:
            y = dv.shift_samples(base, shift_s / sig.dt)
            Xt[-1] = lag_column(y, None)
        else:
            shifted = dv.shift_samples(raw, shift_s / sig.dt)
            y = sig.matched_current(shifted)[0] + sig.fs.get("current_kick", 0.0)
            Xt[-1] = lag_column(y, shifted)
        if Zt is not None:
            Zt[-1] = Xt[-1]
    return _Fit("iv" if Zt is not None else "torque", cols, beta, Xt, Zt, y, A, G, shift_s)


def _select_cogging(sig, cols, form, fit, cogging, rad_per_unit, lag, eiv, block):
    """Cogging orders: screened on the residual (``cogging_order_scores``), kept when the
    pair's Wald statistic beats the BIC price 2 ln n_eff and ``COGGING_MIN_WALD``
    (backward elimination: the weakest order dropped and the rest refitted, one at a
    time). Returns (fit, orders)."""
    if cogging is False or cogging is None or rad_per_unit is None:
        return fit, ()
    ang = sig.th * rad_per_unit                     # motor angle, rad: orders per revolution
    if cogging is True:
        scores = cogging_order_scores(ang[sig.at], sig.w_smooth[sig.at] * rad_per_unit,
                                      fit.residual, cutoff_hz=sig.cutoff_hz)
        orders = cogging_candidates(scores)
    else:
        orders = tuple(int(k) for k in cogging)
    n_base = len(cols)
    base_fit = fit
    while orders:
        fit = _fit(sig, cols + _harmonic_columns(sig, "cog", ang, orders, form), form,
                   lag=lag, eiv=eiv)
        if cogging is not True:
            return fit, orders
        cov, _, n_eff = block_covariance(fit.Xt, fit.residual, fit.A, block=block, Z=fit.Z)
        wald = []
        for j in range(len(orders)):
            sl = slice(n_base + 2 * j, n_base + 2 * j + 2)
            try:
                wald.append(float(fit.beta[sl] @ np.linalg.solve(cov[sl, sl], fit.beta[sl])))
            except np.linalg.LinAlgError:
                wald.append(0.0)
        price = max(2.0 * np.log(max(n_eff, 2.0)), COGGING_MIN_WALD)
        if min(wald) > price:
            return fit, orders
        # backward elimination, the weakest order first: neighbouring orders of a run
        # over few revolutions are nearly collinear, and dropping every order short of
        # the price at once dropped the true one with them (seed 7 case 61's loaded
        # output motor: orders 19-22 screened, each pair's Wald < 80 jointly, order 21
        # alone 1148; without it b2 +1.57 %, with it +0.15 %)
        orders = tuple(k for j, k in enumerate(orders) if j != int(np.argmin(wald)))
    return base_fit, ()


def _to_accel_names(fit: _Fit, cov: np.ndarray):
    """Values and covariance on the accel-form names (``own_to_accel_names``)."""
    names = tuple(c[0] for c in fit.cols) + ((LAG,) if len(fit.beta) > len(fit.cols) else ())
    sign = np.array([c[2] for c in fit.cols] + [1.0] * (len(names) - len(fit.cols)))
    values, cov = own_to_accel_names(fit.form, fit.beta, sign, cov)
    return names, values, cov


def own_to_accel_names(form: str, beta, sign, cov) -> tuple[np.ndarray, np.ndarray]:
    """A form's own coefficients → values and covariance on the accel-form names.

    The accel form's coefficients times their signs; the torque/iv form's
    p = (J/Kt, D/Kt, …) mapped by v_0 = 1/p_0, v_k = s_k p_k / p_0 (delta method for
    the covariance).

    Parameters
    ----------
    form : ``accel``, ``torque`` or ``iv``.
    beta, sign, cov : the form's coefficients, their signs onto the accel names and
        their covariance (``extras["own_form"]`` of a fit).

    Returns
    -------
    (values, covariance) on the accel-form names.

    References
    ----------
    JCGM 100:2008 (GUM), 5.1.2 (first-order propagation)

    Examples
    --------
    >>> own_to_accel_names("torque", [0.5, 0.1], [1.0, 1.0], np.zeros((2, 2)))[0]
    array([2. , 0.2])
    """
    beta, sign, cov = np.asarray(beta, float), np.asarray(sign, float), np.asarray(cov, float)
    if form == "accel":
        return beta * sign, cov * np.outer(sign, sign)
    a = beta[0]
    values = sign * beta / a
    values[0] = 1.0 / a
    Jac = np.diag(sign / a)
    Jac[:, 0] = -values / a
    Jac[0, 0] = -1.0 / a ** 2
    return values, Jac @ cov @ Jac.T


def identify_default(time_s: np.ndarray, position_rad: np.ndarray, current_a: np.ndarray, *,
                     cutoff_hz: float | None = None, spring: bool = False,
                     friction_width_rad_s: float = 0.0, bias: bool | None = None,
                     lag: bool = True, eiv_correction: bool = True,
                     cogging: bool | tuple[int, ...] = True, check: bool = True,
                     source: str = "<array>", rad_per_unit: float | None = 1.0,
                     form: str = "auto", command: np.ndarray | None = None,
                     load_rad_per_unit: float | None = None,
                     form_spread: bool = True, setpoint_step: bool = False,
                     current_limit_a: float | None = None,
                     kick_a_per_rad_s: float | None = None,
                     drive_velocity_rad_s: np.ndarray | None = None,
                     current_period_mean: bool = False,
                     period_kick_weights: np.ndarray | None = None) -> IdentificationResult:
    """Bias-reduced fit of ``J θ'' + D θ' + Tc s(θ') [+ C θ] [+ q·(sin, cos) θ_L] = Kt i [+ c]``.

    Every run is fitted twice: in ``form`` and, as a cross-check, by the plain filtered
    torque-side least squares (IDIM-LS); both are reported (``extras["cross_check"]``),
    with a verdict when they disagree beyond their intervals.

    Parameters
    ----------
    time_s, position_rad, current_a : the run's samples (angle in radians of the motor,
        or the user's unit with ``rad_per_unit``; current or force).
    cutoff_hz : low-pass cutoff of the common FIR; default ``default_cutoff``: min(40 Hz,
        rate/10, 10 x the motion's band).
        Applied to both sides of a linear relation, the filter never biases the fit.
    spring : also fit the paper's C/J (spring to ground); off for a real motor.
    friction_width_rad_s : 0 (default): s(θ') is sign(θ') with each reversal at its
        sub-sample instant (``derivatives.coulomb_regressor``); > 0: the older tanh(θ'/w).
    bias : constant current offset. Default: only when the speed reverses (with one
        direction an offset and Coulomb friction are one column, PAPER-NOTES).
    lag : fit a lag τ of the measured current behind the torque-producing one,
        i_T(t) ≈ i(t + τ) (``extras["current_delay_s"]``, τ > 0: the current is late).
    eiv_correction : errors-in-variables correction of the regressor that carries the
        noise (accel form: white current noise; torque form: encoder noise on θ'').
    cogging : sin/cos(k θ) cogging orders per motor revolution; ``True``: screened
        (``cogging_order_scores``) and kept by a Wald test (BIC price and
        ``COGGING_MIN_WALD``); a tuple: exactly those; ``False``: none.
    rad_per_unit : motor radians per position unit (None: no cogging terms).
    form : ``accel``, ``torque``, ``iv`` (see ``FORMS``) or ``auto`` (``AUTO_FORM``,
        chosen from the benchmark tables).
    command : the recorded speed command (same unit as the angle per second), the
        instrument of the iv form.
    load_rad_per_unit : load angle per position unit (1 for a load-side angle, 1/ratio
        for a motor angle behind a gear): adds a position-dependent load torque of
        order 1, q_s sin θ_L + q_c cos θ_L (gravity, unbalance, an eccentric load),
        reported as ``load_sin``/``load_cos`` — distinct from cogging (motor angle).
    setpoint_step : add the speed setpoint's step per SYNC, Δcmd/dt (``command``
        needed), as a regressor ``setpoint_step``: the current kick of a drive that
        steps its setpoint without interpolation (``_setpoint_steps``). Nearly collinear
        with θ'' within one run; ``calibrate_motor`` turns it on and shares it between
        its two runs.
    current_limit_a : the drive's current limit (its description's ``current_limit_a``,
        CiA 402 max current 0x6073), or None: at a sample at the limit the
        ``setpoint_step`` regressor is 0 (``_below_current_limit``).
    kick_a_per_rad_s : the drive's known setpoint-step kick c (``kick_coefficient``, from
        its declared loop): c·Δcmd is added to the sampled current (0 at the current
        limit) instead of fitting a ``setpoint_step`` term.
    drive_velocity_rad_s : the speed estimate the drive reports with each sample (same
        unit as the angle per second): adds the speed loop's ripple regressor
        ``speed_error`` (``SPEED_ERR``) on a run that does not reverse; for a drive that
        samples its current at one instant (``calibrate_motor`` passes it then).
    current_period_mean : each current sample is the mean over the period ending at it
        (a drive that says ``current: mean``; ``identify_trace`` reads it from the
        trace's drive description): matched by ``derivatives.match_period_means``.
    period_kick_weights : with ``command``: what the current's match misses of the speed
        setpoint's shape within each period, added to the matched current — a stepping
        drive's kicks with ``current_period_mean`` (``period_mean_kick_weights``), an
        interpolating drive's kinks with instant samples (``interpolated_kink_weights``);
        ``identify_trace`` computes them from the drive's declared loop.
    form_spread : also fit the other regression direction (accel for the torque side,
        and vice versa) with the same terms and add ``FORM_SPREAD``·ΔΔᵀ of their
        difference Δ in (Kt/J, D/J, Tc/J) to the covariance: with a correct model both
        directions estimate the same parameters, so what separates them beyond noise is
        model error (closed-loop friction transitions, unmodelled current content) that
        the block covariance cannot see (``extras["form_spread"]``).

    Returns
    -------
    IdentificationResult
        On the accel-form names (``Kt/J``, ``D/J``, ``Tc/J``, …) whatever the form,
        with a covariance from overlapping window sums of residual scores (valid for coloured
        residuals); ``extras["identified"]`` says per parameter whether the run
        identifies it (95 % interval excluding zero, Kt/J to ``MAX_B2_REL_STD``).

    References
    ----------
    Yukawa, Ohishi, Katsura et al., "Identification of motor parameters …" (the
    paper's method, ``identify_paper``); M. Gautier and W. Khalil, "On the
    identification of the inertial parameters of robots", Proc. 27th IEEE CDC, 1988,
    pp. 2264–2269 (IDIM-LS); A. Janot, P.-O. Vandanjon and M. Gautier, "A generic
    instrumental variable approach for industrial robot identification", IEEE Trans.
    Control Syst. Technol. 22(1), 2014, pp. 132–145 (IDIM-IV).

    Examples
    --------
    >>> fit = identify_default(t, theta, i, load_rad_per_unit=1.0)   # doctest: +SKIP
    >>> fit.b2, fit.extras["cross_check"]["agree"]                   # doctest: +SKIP
    """
    if form not in FORMS:
        raise ValueError(f"unknown form {form!r}; use one of {', '.join(FORMS)}")
    sig = _prepare(np.asarray(time_s, float), np.asarray(position_rad, float),
                   np.asarray(current_a, float), cutoff_hz=cutoff_hz,
                   friction_width_rad_s=friction_width_rad_s, command=command, source=source,
                   current_limit_a=current_limit_a, kick_a_per_rad_s=kick_a_per_rad_s,
                   drive_velocity=drive_velocity_rad_s, current_mean=current_period_mean,
                   period_kick=period_kick_weights)
    use_bias = sig.reverses if bias is None else bias
    if use_bias and not sig.reverses:
        raise ExcitationError(f"{source}: a current offset and Coulomb friction cannot be told "
                              f"apart without speed reversals; reverse the rotation in the run "
                              f"or fit without the offset term")
    label = "default" if form == "auto" else form
    if form == "auto":
        form = AUTO_FORM
    if setpoint_step and command is None:
        raise ExcitationError(f"{source}: the setpoint-step term needs the recorded speed "
                              f"command (column 'command'); record it or fit without the term")
    opts = dict(spring=spring, use_bias=use_bias, lag=lag, eiv=eiv_correction, cogging=cogging,
                rad_per_unit=rad_per_unit, load_rad_per_unit=load_rad_per_unit,
                setpoint_step=setpoint_step,
                speed_error=drive_velocity_rad_s is not None and not sig.reverses)
    # with the drive's kick added to the current (its declared loop), the accel form's Kt/J
    # is off by what that kick does to a regressor: a stepping, instant-sampling drive's
    # reversing runs (robustness seed 7) put its calibrated Kt 0.04-0.34 % below the torque
    # form's whatever the noise, encoder, cogging or friction smoothing (an interpolating
    # or averaging drive on the same runs: 0.001-0.003 %; current lag -> 0: 0.66 %), so its
    # difference is no model error of this fit (``calibrate_motor`` skips it as a variant)
    kicked = bool(kick_a_per_rad_s) and command is not None
    fit = _identify_checked(sig, form, label, opts, check=check,
                            form_spread=form_spread and not kicked)
    if form_spread and kicked:
        fit.extras["form_spread"] = {"skipped": "the drive's kick is added to the current: the "
                                                "other direction's difference is its own"}
    return fit


def _identify_checked(sig: _Signals, form: str, label: str, opts: dict, *, check: bool,
                      form_spread: bool) -> IdentificationResult:
    """``form`` on prepared signals, its form spread, the plain torque-side cross-check,
    the fallback to the cross-check where only it identifies Kt/J, and the checks."""
    main = replace(_identify_form(sig, form, **opts), method=label)
    other = None
    if form_spread:
        # the other regression direction, same terms: their spread is model error
        orders = tuple(main.extras["cogging"]) or False
        other = _identify_form(sig, "accel" if form != "accel" else "torque",
                               **{**opts, "cogging": orders})
        main = _with_form_spread(main, other)
    plain = replace(_identify_form(sig, "torque", **{**opts, "eiv": False, "lag": False,
                                                     "cogging": False, "setpoint_step": False,
                                                     "speed_error": False}),
                    method="torque-ls")
    cross = _cross_check(main, plain)
    chosen = main
    # (not with the setpoint-step term: its collinearity with θ'' is resolved across
    # the two calibration runs, ``calibration.share_setpoint_step``)
    if (not main.extras["identified"][KT_J] and plain.extras["identified"][KT_J]
            and not opts.get("setpoint_step")):
        # the textbook fit may identify what this one cannot (with the same model-error term)
        alt = _with_form_spread(plain, other) if other is not None else plain
        if alt.extras["identified"][KT_J]:
            chosen = alt
            cross["returned"] = plain.method
    if check:
        _check(sig, chosen)
    chosen.extras["cross_check"] = cross
    left_out = float(1.0 - np.mean(sig.moving))
    chosen.extras["left_out_share"] = left_out
    if left_out > LEFT_OUT_WARN_SHARE:
        chosen.extras.setdefault("warnings", []).append(
            f"the rotor sticks or breaks away on {100 * left_out:.0f} % of the run; those "
            f"samples carry no Kt information and are left out of the fit (its intervals "
            f"count only the rest): move faster through zero speed or avoid the stops")
    return chosen


def _identify_form(sig: _Signals, form: str, *, spring, use_bias, lag, eiv, cogging,
                   rad_per_unit, load_rad_per_unit, setpoint_step=False,
                   speed_error=False) -> IdentificationResult:
    """One formulation on prepared signals → an ``IdentificationResult`` (no checks)."""
    cols = _base_columns(sig, form, spring=spring, use_bias=use_bias)
    n_base = len(cols)
    cols += _load_columns(sig, load_rad_per_unit, form)
    if setpoint_step and "setpoint_step" in sig.fs:
        cols.append((SP_STEP, sig.fs["setpoint_step"], 1.0 if form == "accel" else -1.0))
    if speed_error and "drive_velocity" in sig.fs:
        cols.append((SPEED_ERR, sig.fs["drive_velocity"] - sig.fs["velocity"],
                     1.0 if form == "accel" else -1.0))
    fit = _fit(sig, cols, form, lag=lag, eiv=eiv)
    block = covariance_block(fit.residual, len(sig.taps))
    fit, orders = _select_cogging(sig, cols, form, fit, cogging, rad_per_unit, lag, eiv, block)
    e = fit.residual
    cov_own, dof, n_eff = block_covariance(fit.Xt, e, fit.A, block=block, Z=fit.Z)
    names, values, cov = _to_accel_names(fit, cov_own)
    b2 = float(values[0])
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    tq = coverage_factor(dof)
    identified = {nm: bool(abs(v) > tq * s) for nm, v, s in zip(names, values, std)}
    identified[KT_J] = bool(b2 > 0 and std[0] <= MAX_B2_REL_STD * b2)
    cog_amps = {int(k): float(np.hypot(values[names.index(f"cog{k}_sin")],
                                       values[names.index(f"cog{k}_cos")])) for k in orders}
    share = _regressor_noise_share(sig, fit, b2)
    per_ampere = {}
    if form != "accel":
        # the torque side's own coefficients: friction per ampere is identified even when
        # the inertia is not (its uncertainty does not pass through J)
        for k, nm in enumerate(("J/Kt", "D/Kt", "Tc/Kt")):
            per_ampere[nm] = [float(fit.beta[k]), float(np.sqrt(max(cov_own[k, k], 0.0)))]
    spring_v = values[names.index(C_J)] if spring else 0.0
    lag_v = float(values[names.index(LAG)]) if LAG in names else 0.0
    return IdentificationResult(
        method=form, names=names,
        values=tuple(map(float, values)), covariance=cov, dof=dof, dt_s=sig.dt,
        n_samples=sig.n, n_effective=n_eff, r2=_r2(fit.y, e),
        rmse=float(np.sqrt(np.mean(e * e))), condition=_condition_gram(fit.G[:n_base, :n_base]),
        A=np.array([[0.0, 1.0], [-spring_v, -values[1]]]), B=np.array([0.0, b2]),
        extras={"form": fit.form, "cutoff_hz": sig.cutoff_hz, "filter_taps": len(sig.taps),
                "current_noise_a": float(np.sqrt(sig.noise_var_raw)), "cogging": cog_amps,
                "speed_range_rad_s": sig.speed_range,
                "current_delay_s": fit.shift_s + (lag_v / b2 if b2 else 0.0),
                "identified": identified, "regressor_noise_share": share,
                "per_ampere": per_ampere,
                # the form's own coefficients and covariance (calibration combines two runs there)
                "own_form": {"names": list(names), "beta": fit.beta.tolist(),
                             "sign": [c[2] for c in fit.cols] + [1.0] * (len(names) - len(fit.cols)),
                             "cov": cov_own.tolist()},
                "residual_unit": "rad/s^2" if form == "accel" else "A"})


def _with_form_spread(main: IdentificationResult, other: IdentificationResult) -> IdentificationResult:
    """``main`` with ``FORM_SPREAD``·ΔΔᵀ added to its (Kt/J, D/J, Tc/J) covariance, Δ the
    difference to ``other`` (the opposite regression direction, same terms), and its
    per-parameter identifiability re-judged with the wider intervals."""
    share = other.extras["regressor_noise_share"]
    if share > FORM_SPREAD_MAX_SHARE:
        return replace(main, extras={**main.extras, "form_spread": {
            "other": other.method, "skipped": f"its key regressor's noise share {share:.3g} > "
            f"{FORM_SPREAD_MAX_SHARE:g}: the difference is its errors in variables, not model error"}})
    names = [n for n in (KT_J, D_J, TC_J) if n in main.names and n in other.names]
    idx = [main.names.index(n) for n in names]
    delta = np.array([main.value(n) - other.value(n) for n in names])
    cov = main.covariance.copy()
    cov[np.ix_(idx, idx)] += FORM_SPREAD * np.outer(delta, delta)
    identified = dict(main.extras["identified"])
    tq = coverage_factor(main.dof)
    for n, k in zip(names, idx):
        identified[n] = bool(abs(main.values[k]) > tq * np.sqrt(cov[k, k]))
    b2, b2_std = main.values[idx[0]], float(np.sqrt(cov[idx[0], idx[0]]))
    identified[KT_J] = bool(b2 > 0 and b2_std <= MAX_B2_REL_STD * b2)
    extras = {**main.extras, "identified": identified,
              "form_spread": {"other": other.method, "difference": dict(zip(names, map(float, delta)))}}
    if main.extras.get("per_ampere") and len(names) == 3:
        # the torque side's own coefficients (J/Kt, D/Kt, Tc/Kt) = (1, D/J, Tc/J)/b2 carry
        # the same spread (that map is its own inverse: ``own_to_accel_names`` maps it)
        _, spread = own_to_accel_names("torque", [main.value(n) for n in names], np.ones(3),
                                       FORM_SPREAD * np.outer(delta, delta))
        extras["per_ampere"] = {k: [v, float(np.sqrt(s * s + spread[j, j]))]
                                for j, (k, (v, s)) in enumerate(main.extras["per_ampere"].items())}
    return replace(main, covariance=cov, extras=extras)


def _regressor_noise_share(sig: _Signals, fit: _Fit, b2: float) -> float:
    """Variance of what disturbs the key regressor (current for the accel form: the
    residual in current units, e/b2; θ'' for the torque form: encoder noise) over that
    regressor's variance not explained by the other columns: to first order the
    fraction by which least squares attenuates its coefficient (errors in variables)."""
    try:
        partial = 1.0 / np.linalg.inv(fit.G)[0, 0] / sig.n
    except np.linalg.LinAlgError:
        return float("inf")
    if fit.form == "accel":
        e = fit.residual / b2 if b2 else fit.residual
        noise = float(np.mean(e * e))
    else:
        noise = sig.accel_noise ** 2
    return float(noise / partial) if partial > 0 else float("inf")


def _cross_check(main: IdentificationResult, other: IdentificationResult) -> dict:
    """Both fits' Kt/J, D/J, Tc/J with standard uncertainties; where they differ beyond
    2 sigma of the two (taken independent: conservative for one data set) the verdict
    says which one the data supports and why:

    * the fit whose key regressor carries the smaller share of noise (errors in
      variables attenuate its coefficient by about that share: current content the
      model lacks for the accel form, encoder noise on θ'' for the torque form), and
    * for two torque-side fits, the one whose extra terms (current lag, cogging) are
      significant."""
    out = {"method": other.method, "agree": True, "differ": [],
           "noise_share": {main.method: main.extras["regressor_noise_share"],
                           other.method: other.extras["regressor_noise_share"]}}
    for nm in (KT_J, D_J, TC_J):
        a, b = main.value(nm), other.value(nm)
        s = float(np.hypot(main.std(nm), other.std(nm)))
        out[nm] = {main.method: a, other.method: b, "std": s}
        if abs(a - b) > 2.0 * s and s > 0:
            out["agree"] = False
            out["differ"].append(nm)
    if out["agree"]:
        out["verdict"] = "the two fits agree within their intervals"
        return out
    sm, so = main.extras["regressor_noise_share"], other.extras["regressor_noise_share"]
    extra = [nm for nm in main.names if nm not in other.names and main.extras["identified"].get(nm)]
    if main.extras["form"] == other.extras["form"]:
        best = main.method if extra else other.method
        why = (f"{main.method}'s added terms {', '.join(extra)} are significant" if extra else
               f"{main.method}'s added terms are not significant")
    else:
        best = main.method if sm <= so else other.method
        why = (f"noise share of the key regressor {sm:.3g} ({main.method}) vs {so:.3g} "
               f"({other.method}): errors in variables attenuate the other fit")
    out["supported"] = best
    out["verdict"] = (f"{main.method} and {other.method} differ on {', '.join(out['differ'])} "
                      f"beyond their intervals; the data supports {best}: {why}")
    return out


def _check(sig: _Signals, fit: IdentificationResult) -> None:
    """Refuse only what the run cannot identify, with advice in its own numbers: no
    acceleration content, ill-conditioned regressors, a model that explains little, or
    neither Kt/J nor any friction term. A run whose Kt/J misses ``MAX_B2_REL_STD`` but
    whose friction (or b2 itself, at 95 %) is identified is returned with that advice in
    ``extras["warnings"]`` and its honest (wide) intervals."""
    fs = sig.fs
    moving = float(np.sum(sig.moving))
    # what the samples in the equation can tell apart: the filter passes 2·f_c·dt of each
    # sample's information, so n moving samples hold about n·2·f_c·dt independent equations
    equations = moving * 2.0 * sig.cutoff_hz * sig.dt
    if moving < len(sig.moving) and equations < len(fit.names):
        # fewer equations than parameters: the fit leaves almost no residual, and its
        # interval (from that residual) means nothing (robustness seed 7 case 94's output
        # drive at 100 Hz: stuck on 98 % of each run, 1.2 equations for 3 parameters, Kt
        # −10.6 % returned at ± 0.09 %; at 1 kHz the same drive's 3.5 equations give Kt
        # −7.4 % ± 20 %, an honest interval, and are kept)
        raise ExcitationError(
            f"{sig.source}: the rotor moves on only {int(round(moving))} of {len(sig.moving)} "
            f"samples ({100 * moving / len(sig.moving):.0f} %; it sticks or breaks away on the "
            f"rest), about {equations:.1f} independent equations through the "
            f"{sig.cutoff_hz:.3g} Hz filter for {len(fit.names)} parameters: too few to identify "
            f"Kt/J; give the drive more current than its friction holds (a stiffer speed loop "
            f"or a larger command) or move faster through zero speed")
    acc = fs["acceleration"]
    accel_noise = sig.accel_noise
    b2, b2_std = fit.b2, fit.b2_std
    b2_seen = b2 > coverage_factor(fit.dof) * b2_std
    try:
        advice = check_excitation(
            velocity=fs["velocity"], acceleration=acc, accel_noise_rms=accel_noise,
            condition=fit.condition, b2=b2, b2_std=b2_std, rate_hz=1.0 / sig.dt,
            source=sig.source, reversals=count_reversals(sig.w_smooth, sig.moving),
            cutoff_hz=sig.cutoff_hz, require_b2=False)
    except ExcitationError as exc:
        if not b2_seen:
            raise
        # little acceleration content (a rotor stuck for most of the run), yet Kt/J is
        # distinguishable from zero: returned with its honest, wide interval and the advice
        advice = str(exc).removeprefix(f"{sig.source}: ")
    if advice:
        # refused only when nothing is identified: Kt/J not even distinguishable from
        # zero (95 %) and no friction term either; otherwise a warning with the advice
        friction = [n for n in (D_J, TC_J) if fit.extras["identified"].get(n)]
        if not (b2 > 0) or not (friction or b2_seen):
            raise ExcitationError(f"{sig.source}: {advice}")
        fit.extras.setdefault("warnings", []).append(
            f"{advice}; identified: {', '.join(friction) or 'none of D/J, Tc/J'} "
            f"(per ampere in extras['per_ampere'])")
    noise_i = sig.noise_var_raw * float(np.sum(np.convolve(sig.current_match, sig.taps) ** 2))
    if fit.extras["form"] == "accel":
        floor_var, y = accel_noise ** 2 + b2 ** 2 * noise_i, acc
    else:
        floor_var, y = noise_i + (accel_noise / b2) ** 2, fs["current"]
    check_fit_quality(r2=fit.r2, floor_r2=1.0 - floor_var / max(float(np.var(y)), 1e-300),
                      source=sig.source)


def equation_weight(velocity: np.ndarray, standstill_speed_: float, dt_s: float, *,
                    current: np.ndarray | None = None, current_noise: float = 0.0,
                    angle: np.ndarray | None = None, creep_speed: float = 0.0) -> np.ndarray:
    """Per raw sample, 1 where the motor equation is fitted, 0 where it is left out.

    Left out: every dwell (at least 3 samples below the standstill speed), extended to
    the stretch around it slower than ``STICK_BAND`` x that speed (the rotor sticks or
    creeps: static friction takes any value up to the breakaway, so the current there
    says nothing about Kt, J or the sliding friction), widened by ``STICK_MARGIN_S``
    (at least ``STICK_MARGIN_SAMPLES``) on each side (presliding and the
    breakaway transition, which sign(ω) does not describe), then rising to 1 over as
    many samples again (raised cosine). A dwell where the drive pushes (``_pushed``:
    the current's running mean beyond noise) on fewer than ``STICK_MARGIN_S`` worth of
    samples (at least ``PUSHED_MIN_SAMPLES``, at most half the dwell) is a rotor at
    rest that nothing pushes (before a speed step from rest): J θ'' = Kt i = 0 holds
    there, it stays in (weight 1; the caller sets its friction to zero). The weight multiplies
    the raw equation before the filter (``derivatives.weighted_derivatives``), so
    the fit stays exact on what remains; the intervals then count only what remains.

    Parameters
    ----------
    velocity : zero-phase speed at every sample.
    standstill_speed_ : ``standstill_speed`` of the run.
    dt_s : sample period.
    current : raw current (A); None: every dwell counts as stuck.
    current_noise : its white-noise std (A).
    creep_speed : a reversal slower than this for at least 3 samples is a dwell too,
        its slow stretch ``STICK_BAND`` x this (``CREEP_TOP_FRACTION``: a fine encoder
        resolves the creep through the friction's transition; a start from rest keeps the
        encoder's band, its acceleration is information).
    angle : the sampled angle; given, a dwell is also found (and the slow stretch
        measured) on its difference over ``SHORT_SPEED_SPAN`` samples
        (``_short_speed``): the smoothed speed rings across a touch-and-go stop (seed 3
        case 62's input motor at 80,000 counts/rev: ±0.2 rad/s where the rotor stood
        at 0.003 rad/s for 12 ms while the current ramped to the breakaway; a false
        double reversal flipped the Coulomb term, b2 +1.8 %).

    Returns
    -------
    numpy.ndarray, 0..1

    References
    ----------
    M. Gautier and W. Khalil, "On the identification of the inertial parameters of robots", Proc. 27th IEEE CDC, 1988 (data selection); B. Armstrong-Hélouvry, P. Dupont and C. Canudas de Wit, "A survey of models, analysis tools and compensation methods for the control of machines with friction", Automatica 30(7), 1994, pp. 1083-1138 (presliding, breakaway)

    Examples
    --------
    >>> equation_weight(np.r_[np.ones(6), np.zeros(3), np.ones(6)], 0.1, 1e-2).round(2)
    array([1.  , 1.  , 0.75, 0.25, 0.  , 0.  , 0.  , 0.  , 0.  , 0.  , 0.  ,
           0.25, 0.75, 1.  , 1.  ])
    """
    w = np.asarray(velocity, float)
    current = None if current is None else np.asarray(current, float)
    core = dv.standstill(w, standstill_speed_) > 0
    if angle is not None:
        # the smoother rings across a touch-and-go stop; the angle's own count says it
        w_short = _short_speed(angle, dt_s)
        core |= dv.standstill(w_short, standstill_speed_) > 0
        # ... and so does an angle held over the whole standstill window, every sample of
        # it: the centred difference above needs 3 samples more before it calls a dwell,
        # and at 100 Hz it missed the 54-68 ms stops (6-8 readings) at every reversal of
        # a stick-slip joint (Fc +2.8 %, Fv -6.6 % on one run)
        core |= _held(angle, SHORT_SPEED_SPAN + 1)
        w = np.where(np.abs(w_short) < np.abs(w), w_short, w)
    stuck = np.zeros(len(w), bool)
    creeping = (_reversing_stretches(w, STICK_BAND * creep_speed) if creep_speed > standstill_speed_
                else np.zeros(len(w), bool))
    core |= creeping & (dv.standstill(w, creep_speed) > 0)
    if core.any():
        # each dwell widened to the slow stretch around it (hysteresis) and the margin; a
        # fast crossing (below the standstill speed for fewer than 3 samples) is no dwell
        # and stays in: its reversal and acceleration are information, not breakaway
        # (left out too, a 2,000-count encoder's 1.5 rad/s band cost seed 0 case 2's
        # heavy output motor 3x its Kt interval; seeds 0/7/8/9 biased 7/3/3/8 % vs 4/3/7/8 %)
        margin = max(int(round(STICK_MARGIN_S / dt_s)), STICK_MARGIN_SAMPLES)
        slow = (np.abs(w) < STICK_BAND * standstill_speed_) | creeping
        # pushed for the margin's time (at least PUSHED_MIN_SAMPLES: at 100 Hz a 2-sample
        # mean beyond 4 of its sigmas twice in a row is no rare event over a long dwell)
        width = max(margin, PUSHED_MIN_SAMPLES)
        pushed = None if current is None else _pushed(current, current_noise, width)
        for a, b in dv.runs(slow):
            if core[a:b].any() and (pushed is None
                                    or np.count_nonzero(pushed[a:b]) >= min(width, (b - a) / 2)):
                stuck[a:b] = True
        if stuck.any() and margin > 0:
            # the margin, then a raised-cosine ramp as long: a hard edge lets the raw
            # second difference's quantisation noise through the filter (its partial sums
            # no longer telescope; seed 0 case 31: r² 0.9974 with, 0.99989 without)
            dist = ndimage.distance_transform_edt(~stuck) - margin
            ramp = 0.5 - 0.5 * np.cos(np.pi * np.clip(dist, 0, margin + 1) / (margin + 1))
            return np.where(stuck, 0.0, ramp)
    return 1.0 - stuck.astype(float)


def _reversing_stretches(w: np.ndarray, speed: float) -> np.ndarray:
    """True on every stretch slower than ``speed`` inside which the speed changes sign.

    >>> _reversing_stretches(np.array([2., .5, -.5, -2., -.5, -.6, -2.]), 1.0)
    array([False,  True,  True, False, False, False, False])
    """
    slow = np.abs(w) < speed
    out = np.zeros(len(w), bool)
    for a, b in dv.runs(slow):
        seg = w[a:b]
        if seg.max() > 0 > seg.min() or (a > 0 and b < len(w) and w[a - 1] * w[b] < 0):
            out[a:b] = True
    return out


def _short_speed(angle: np.ndarray, dt_s: float) -> np.ndarray:
    """The angle's central difference over ``SHORT_SPEED_SPAN`` samples (ends: one-sided):
    below the standstill speed (1 count per 6 samples) exactly when no count changed."""
    th = np.asarray(angle, float)
    h = SHORT_SPEED_SPAN // 2
    if len(th) <= 2 * h:
        return np.gradient(th, dt_s)
    idx = np.arange(len(th))
    hi, lo = np.minimum(idx + h, len(th) - 1), np.maximum(idx - h, 0)
    return (th[hi] - th[lo]) / ((hi - lo) * dt_s)


def _held(angle: np.ndarray, samples: int) -> np.ndarray:
    """True on every sample of a stretch of at least ``samples`` equal angle readings (no
    encoder count changed).

    >>> _held(np.array([0., 1., 1., 1., 2.]), 3)
    array([False,  True,  True,  True, False])
    """
    th = np.asarray(angle, float)
    # runs of zero steps (the standstill finder on the one-sample difference): n readings
    # are n - 1 steps, and a step's run holds the readings on both its sides
    still = dv.standstill(np.diff(th), np.finfo(float).tiny, min_samples=samples - 1) > 0
    held = np.zeros(len(th), bool)
    held[:-1] |= still
    held[1:] |= still
    return held


def _pushed(current: np.ndarray, current_noise: float, width: int) -> np.ndarray:
    """Samples where the drive pushes: the current's running mean over ``width`` samples
    beyond ``STUCK_CURRENT_SIGMAS`` x its own noise (current_noise / sqrt(width)).

    Why the running mean, not the dwell's median |i|: static friction holds any current
    below the breakaway, and a dwell whose current passes through zero (a reversing
    speed loop ramping from +16 mA to the −79 mA breakaway over 65 ms, robustness seed 3
    case 62's input motor, noise 7 mA) had a median within 3 sigma and stayed in with
    zero friction: a residual of up to 60 mA, correlated over the dwell (Kt ±1.7 %)."""
    m = max(int(width), 1)
    mean = ndimage.uniform_filter1d(np.asarray(current, float), m, mode="nearest")
    return np.abs(mean) > STUCK_CURRENT_SIGMAS * current_noise / np.sqrt(m)


def smoothing_half_width(dt_s: float) -> int:
    """Half-width (samples) of the zero-phase speed estimate near reversals: 10 ms of
    data (10 samples at 1 kHz, as tuned there), at least 3 samples. A fixed 10 samples
    spans 210 ms at 100 Hz, smears a joint's dwell at a reversal into the motion on
    either side and misplaces the Coulomb step: Fc −6 %, Fv +14 % on the robot-joint
    traces of ``bench accuracy`` (with 10 ms: see its real section).

    Parameters
    ----------
    dt_s : sample period.

    Returns
    -------
    int

    References
    ----------
    A. Savitzky and M. J. E. Golay, "Smoothing and differentiation of data by simplified least squares procedures", Anal. Chem. 36(8), 1964, pp. 1627-1639

    Examples
    --------
    >>> smoothing_half_width(1e-3), smoothing_half_width(1e-2)
    (10, 3)

    """
    return max(3, int(round(0.010 / dt_s)))


def count_reversals(velocity: np.ndarray, moving: np.ndarray | None = None) -> int:
    """Speed sign changes between moving stretches (a dwell's chatter counts once).

    Parameters
    ----------
    velocity : the run's speed.
    moving : 0 while sticking (those samples are skipped).

    Returns
    -------
    int

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md)

    Examples
    --------
    >>> count_reversals([1.0, 1.0, -1.0, -1.0, 1.0])
    2

    """
    w = np.asarray(velocity, float)
    if moving is not None:
        w = w[moving > 0]
    s = np.sign(w[np.abs(w) > 0.02 * top_speed(w)]) if len(w) else w
    return int(np.sum(s[1:] != s[:-1])) if len(s) > 1 else 0


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
        Xt[0] = dv.shift_samples(base, shift_s / dt)                 # i(t + shift)
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
    Returns ``z`` (index k − 1).

    Parameters
    ----------
    position_rad, velocity_rad_s : rotor angle and speed under the residual's samples.
    residual : the base fit's residual.
    cutoff_hz : the fit's low-pass cutoff.
    max_order, bins : orders screened; angle bins of the histogram.

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md); cogging as a periodic rotor-angle torque

    Examples
    --------
    >>> z = cogging_order_scores(th, w, e, cutoff_hz=40.0)   # doctest: +SKIP

    """
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
    compare with and no cogging can bias the fit, so none are tried.

    Parameters
    ----------
    scores : ``cogging_order_scores`` output.

    Returns
    -------
    tuple of int
        Orders to test in the regression (at most ``COGGING_CANDIDATES``).

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md)

    Examples
    --------
    >>> import numpy as np
    >>> s = np.ones(64); s[5] = 100.0
    >>> cogging_candidates(s)
    (6,)

    """
    visible = np.isfinite(scores)
    if visible.sum() < MIN_SCREEN_ORDERS:
        return ()
    screen = COGGING_SCREEN * float(np.median(scores[visible]))
    z = np.where(visible, scores, -np.inf)
    ranked = np.argsort(z)[::-1][:COGGING_CANDIDATES]
    return tuple(int(k) + 1 for k in ranked if z[k] > screen)


def physical_parameters(fit: IdentificationResult, torque_per_ampere: float) -> dict:
    """Inertia, viscous and Coulomb friction in SI from a fit and a known torque per ampere.

    ``J θ'' + D θ' + Tc s(θ') = k i`` with k known (a motor's Kt for a motor angle; a
    robot joint's torque per ampere, gear included, for a joint angle; a force per
    ampere and a position in metres give kg, N s/m and N): J = k/b2, D = k·(D/J)/b2,
    Tc = k·(Tc/J)/b2, their standard uncertainties by the delta method on the fit's
    whole (Kt/J, D/J, Tc/J) covariance — correlations included, so a friction the run
    identifies keeps its own interval when the inertia is poorly known (to first order:
    the torque side's per-ampere coefficients with their model-error spreads). k is
    taken as exact; its relative tolerance adds in quadrature to each.

    Parameters
    ----------
    fit : an ``IdentificationResult`` with Kt/J, D/J and Tc/J.
    torque_per_ampere : k (N m/A, or N/A for a linear axis in metres).

    Returns
    -------
    dict
        ``{"J": (value, std), "D": (value, std), "Tc": (value, std)}``.

    References
    ----------
    JCGM 100:2008 (GUM), sec. 5.1.2 (law of propagation of uncertainty); M. Gautier and
    W. Khalil, "On the identification of the inertial parameters of robots", Proc. 27th
    IEEE CDC, 1988 (the torque-side model)

    Examples
    --------
    >>> physical_parameters(fit, 60.0)["J"]     # doctest: +SKIP
    (3.89, 0.18)
    """
    k = float(torque_per_ampere)
    if not (np.isfinite(k) and k > 0):
        raise ValueError(f"torque per ampere must be a positive number, got {torque_per_ampere!r}")
    missing = [n for n in (KT_J, D_J, TC_J) if n not in fit.names]
    if missing:
        raise ValueError(f"the {fit.method} fit has no {', '.join(missing)}: J, D and Tc need the "
                         f"motor model's Kt/J, D/J and Tc/J")
    ix = [fit.names.index(n) for n in (KT_J, D_J, TC_J)]
    # (b2, D/J, Tc/J) -> (1, D/J, Tc/J)/b2 is the torque side's map to the accel names
    # (its own inverse)
    values, cov = own_to_accel_names("torque", [fit.values[i] for i in ix], np.ones(3),
                                     np.asarray(fit.covariance)[np.ix_(ix, ix)])
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    return {name: (float(k * v), float(k * s)) for name, v, s in zip(("J", "D", "Tc"), values, std)}


def identify(time_s, position_rad, current_a, *, method: str = "default",
             source: str = "<array>", **options) -> IdentificationResult:
    """Dispatch on ``method``: ``default`` (form ``auto``), ``accel``, ``torque``, ``iv``
    (``identify_default`` in that form), ``paper`` (data rate) or ``paper-15ms``.

    Parameters
    ----------
    time_s, position_rad, current_a : the run's samples.
    method : one of ``METHODS``.
    source : the run's name for messages.
    **options : passed to the method's function.

    Returns
    -------
    IdentificationResult

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md); M. Gautier and W. Khalil, "On the identification of the inertial parameters of robots", Proc. 27th IEEE Conf. Decision and Control, 1988, pp. 2264-2269

    Examples
    --------
    >>> fit = identify(t, theta, i, method="torque")   # doctest: +SKIP

    """
    if method == "default":
        return identify_default(time_s, position_rad, current_a, source=source, **options)
    if method in ("accel", "torque", "iv"):
        return identify_default(time_s, position_rad, current_a, source=source, form=method,
                                **options)
    options.pop("command", None)
    options.pop("load_rad_per_unit", None)
    if method == "paper":
        return identify_paper(time_s, position_rad, current_a, source=source, **options)
    if method == "paper-15ms":
        return identify_paper(time_s, position_rad, current_a, decimate_s=0.015,
                              source=source, **options)
    raise ValueError(f"unknown identification method {method!r}; use {', '.join(METHODS)}")


METHODS = ("default", "accel", "torque", "iv", "paper", "paper-15ms")


def identify_trace(trace, *, method: str = "default", **options) -> IdentificationResult:
    """Validate a single-motor ``Trace`` (columns ``position_rad``, ``current_a``; a
    ``command`` column in velocity mode is the iv form's instrument) and fit it.

    Parameters
    ----------
    trace : a single-motor ``Trace``.
    method : one of ``METHODS``.
    **options : passed on (``identify_default``'s options).

    Returns
    -------
    IdentificationResult

    References
    ----------
    M. Gautier and W. Khalil, "On the identification of the inertial parameters of robots", Proc. 27th IEEE Conf. Decision and Control, 1988, pp. 2264-2269

    Examples
    --------
    >>> fit = identify_trace(Trace.read("run.csv"))   # doctest: +SKIP

    """
    trace.validate(["position_rad", "current_a"], min_samples=50)
    # the iv form asks for the command; the default form takes it when the trace says it
    # is a speed setpoint (it is not used there, but reported with the fit's inputs)
    if "command" in trace and "command" not in options and (
            method == "iv" or (method in ("default", "torque") and is_speed_command(trace))):
        options["command"] = trace["command"]
    if "current_period_mean" not in options and method in ("default", "accel", "torque", "iv"):
        options["current_period_mean"] = (trace.meta.get("drive") or {}).get("current") == "mean"
    if ("period_kick_weights" not in options and "command" in trace and is_speed_command(trace)
            and method in ("default", "accel", "torque", "iv")):
        # a drive that steps its setpoint and reports the period mean, or ramps it and
        # reports an instant (its declared loop): its kicks need the command, in every form
        weights = declared_period_kick(trace)
        if weights is not None:
            options["period_kick_weights"] = weights
            options.setdefault("command", trace["command"])
            # an instant sample at the drive's declared limit: clipped, no kinks there
            # (``_below_current_limit``); a period mean below it may still hold a clipped
            # kick, and the test on it made such drives' Kt worse (250 Hz, seeds 7 and 8:
            # coverage 87.8/90.7 → 79.6/83.3 %), so it is not tested there
            drive = trace.meta.get("drive") or {}
            if (drive.get("current") == "instant" and drive.get("current_limit_a") is not None
                    and options.get("current_limit_a") is None):
                try:
                    options["current_limit_a"] = float(drive["current_limit_a"])
                except (TypeError, ValueError):
                    raise TraceError(f"{trace.source}: meta drive.current_limit_a is "
                                     f"{drive['current_limit_a']!r}; give the drive's current limit "
                                     f"in A (or leave it out)") from None
    if options.pop("speed_error", False) and "velocity_rad_s" in trace:
        options["drive_velocity_rad_s"] = trace["velocity_rad_s"]
    return identify(trace.time_s, trace["position_rad"], trace["current_a"], method=method,
                    source=trace.source, **options)


def drive_sampling(trace) -> str | None:
    """How the trace's drive sampled, as its description says (``meta["drive"]``:
    ``setpoint`` ``step``/``interpolated``, ``current`` ``instant``/``mean``): ``"kick"``
    when it steps its speed setpoint each SYNC *and* samples its current at one instant
    (``_setpoint_steps``: a setpoint-step term belongs in the model), ``"plain"`` when it
    says otherwise, None when it does not say. An optional ``current_limit_a`` (the
    current the drive clamps at) is read by ``calibration.calibrate_motor``.

    Raises TraceError naming the field for a value it does not know."""
    drive = trace.meta.get("drive")
    if not drive:
        return None
    known = {"setpoint": ("step", "interpolated"), "current": ("instant", "mean")}
    for key, values in known.items():
        v = drive.get(key)
        if v is not None and v not in values:
            raise TraceError(f"{trace.source}: meta drive.{key} is {v!r}; use one of "
                             f"{', '.join(values)} (or leave it out)")
    if drive.get("setpoint") is None or drive.get("current") is None:
        return None
    return "kick" if (drive["setpoint"], drive["current"]) == ("step", "instant") else "plain"


DRIVE_LOOP_KEYS = ("speed_kp_a_s_per_rad", "current_loop_time_constant_s", "speed_loop_period_s")


def speed_ripple_to_noise(trace) -> float | None:
    """How far the speed loop's quantisation ripple stands out of the current's noise.

    A drive that estimates its speed from the encoder's counts per loop period T sees
    one count q as a speed step q/T, which its P gain Kp turns into current: a ripple of
    rms Kp·q/(T·√12) (uniform quantisation error). Its ratio to the rest of the
    current's white noise (``_white_noise_variance`` of the recorded current, the ripple's
    own share taken out), or None where the drive does not declare its loop
    (``speed_kp_a_s_per_rad``, ``speed_loop_period_s``) or the angle shows no count.

    >>> speed_ripple_to_noise(trace)            # doctest: +SKIP
    5.8
    """
    drive = trace.meta.get("drive") or {}
    try:
        kp, period = float(drive["speed_kp_a_s_per_rad"]), float(drive["speed_loop_period_s"])
    except (KeyError, TypeError, ValueError):
        return None
    q = encoder_resolution(np.asarray(trace["position_rad"], float))
    if not (kp > 0 and period > 0 and q > 0):
        return None
    ripple_var = (kp * q / period) ** 2 / 12.0
    rest = _white_noise_variance(np.asarray(trace["current_a"], float)) - ripple_var
    return float("inf") if rest <= 0 else float(np.sqrt(ripple_var / rest))


def _declared_loop(trace) -> dict | None:
    """The speed loop a drive's description (``meta["drive"]``) declares,
    ``DRIVE_LOOP_KEYS`` → float, or None where it does not declare all three.

    Raises TraceError naming a declared value that is not a number ≥ 0 (> 0 for the gain
    and the loop period)."""
    drive = trace.meta.get("drive") or {}
    if not all(k in drive for k in DRIVE_LOOP_KEYS):
        return None
    values = {}
    for k in DRIVE_LOOP_KEYS:
        try:
            values[k] = float(drive[k])
        except (TypeError, ValueError):
            values[k] = float("nan")
        low_ok = values[k] >= 0 if k == "current_loop_time_constant_s" else values[k] > 0
        if not (np.isfinite(values[k]) and low_ok):
            raise TraceError(f"{trace.source}: meta drive.{k} is {drive[k]!r}; give a number "
                             f"{'>= 0' if k == 'current_loop_time_constant_s' else '> 0'} "
                             f"in SI units (or leave the drive's loop out)")
    return values


def declared_kick(trace) -> float | None:
    """The setpoint-step kick c (A per rad/s, ``kick_coefficient``) of a drive whose
    description (``meta["drive"]``) declares its loop: ``speed_kp_a_s_per_rad`` (speed-loop
    P gain), ``current_loop_time_constant_s`` and ``speed_loop_period_s``; None where it
    declares no kick (``drive_sampling``) or not all three.

    Raises TraceError naming a declared value that is not a number ≥ 0 (> 0 for the gain
    and the loop period)."""
    loop = _declared_loop(trace) if drive_sampling(trace) == "kick" else None
    if loop is None:
        return None
    period_s = float(np.median(np.diff(trace.time_s)))
    return kick_coefficient(loop["speed_kp_a_s_per_rad"], loop["current_loop_time_constant_s"],
                            period_s, loop["speed_loop_period_s"])


def kick_speed_response(trace, b2: float) -> float:
    """The relative size of what ``kick_coefficient`` leaves out on this run's drive: the
    speed's own response to the kick within the period, in its τ = 0 limit

        ε(x) = 1 − 2 (1/x − 1/(eˣ − 1)),   x = Kp·(Kt/J)·T

    (c/Kp is 1/x − 1/(eˣ − 1) there against the model's ½; x/6 for small x). 0 where the
    drive declares no loop. At 1 kHz x ≤ 0.2 (ε ≤ 0.033); at 100 Hz x reaches 1–2 (ε 0.16–
    0.31), and stepping, instant-sampling drives' Kt came out +0.8 … +5.5 % (robustness
    seeds 7 / 8, all positive, growing with x): ``calibration`` counts ε as part of the
    kick's relative uncertainty.

    Parameters
    ----------
    trace : a run whose ``meta["drive"]`` declares its loop.
    b2 : the run's Kt/J (rad/s² per A).

    Returns
    -------
    float

    Examples
    --------
    >>> round(float(1 - 2 * (1 / 1.75 - 1 / np.expm1(1.75))), 2)     # x = 1.75
    0.28
    """
    loop = _declared_loop(trace)
    if loop is None or not (np.isfinite(b2) and b2 > 0):
        return 0.0
    x = loop["speed_kp_a_s_per_rad"] * b2 * float(np.median(np.diff(trace.time_s)))
    return float(1.0 - 2.0 * (1.0 / x - 1.0 / np.expm1(x))) if x > 1e-9 else 0.0


def declared_period_kick(trace) -> np.ndarray | None:
    """The weights of what the current's match misses of the setpoint's shape within each
    period, where the drive's description declares its loop and says it steps its setpoint
    and reports the period mean (``period_mean_kick_weights``) or ramps it and reports an
    instant (``interpolated_kink_weights``); else None. Raises TraceError as
    ``declared_kick``."""
    drive = trace.meta.get("drive") or {}
    weights = PERIOD_KICK_WEIGHTS.get((drive.get("setpoint"), drive.get("current")))
    if drive_sampling(trace) != "plain" or weights is None:
        return None
    loop = _declared_loop(trace)
    if loop is None:
        return None
    period_s = float(np.median(np.diff(trace.time_s)))
    return weights(loop["speed_kp_a_s_per_rad"], loop["current_loop_time_constant_s"],
                   period_s, loop["speed_loop_period_s"])


def is_speed_command(trace) -> bool:
    """A ``command`` column is a speed setpoint when the trace says so (``meta`` mode
    ``velocity``, as the simulator and the station write it)."""
    mode = (trace.meta.get("sim") or {}).get("mode") or trace.meta.get("mode")
    return mode == "velocity"


# ---------------------------------------------------------------- excitation check
def check_excitation(*, velocity: np.ndarray, acceleration: np.ndarray, accel_noise_rms: float,
                     condition: float, b2: float, b2_std: float, rate_hz: float,
                     source: str = "<array>", reversals: int | None = None,
                     cutoff_hz: float | None = None, require_b2: bool = True) -> str | None:
    """Raise ``ExcitationError`` unless the data can identify b2 = Kt/J.

    Three tests: the filtered acceleration must stand well above what encoder
    quantisation alone would produce (unless b2 comes out known to ``MAX_B2_REL_STD``
    all the same: robustness seed 8 case 34, 12x the noise level, b2 to 0.4 %, Kt
    within 0.08 %); the column-normalised regressors must be well conditioned; b2
    must be positive and known to ``MAX_B2_REL_STD``. The advice is
    computed from the run itself (its speeds, acceleration, reversals and band): b2's
    relative uncertainty scales as 1/(acceleration content) and 1/√(duration), so the
    factor the run falls short by says how much more of *its own* motion is needed.

    Parameters
    ----------
    velocity, acceleration : the run's filtered speed and acceleration.
    accel_noise_rms : rms acceleration encoder quantisation alone produces (filtered).
    condition : of the column-normalised regressor matrix.
    b2, b2_std : the fit's Kt/J and its standard uncertainty.
    rate_hz, source : sample rate and the run's name for the message.
    reversals, cutoff_hz : the run's speed reversals and filter band, quoted in the advice.
    require_b2 : raise when b2 misses ``MAX_B2_REL_STD``; False: return the advice.

    Returns
    -------
    None, or (``require_b2`` False) the advice on Kt/J (``b2_shortfall``).

    Examples
    --------
    >>> check_excitation(velocity=w, acceleration=a, accel_noise_rms=0.1, condition=30,
    ...                  b2=900.0, b2_std=5.0, rate_hz=1000.0)   # doctest: +SKIP

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md); M. Gautier and W. Khalil, "On the identification of the inertial parameters of robots", Proc. 27th IEEE Conf. Decision and Control, 1988, pp. 2264-2269

    """
    acc_rms = float(np.std(acceleration))
    lo, hi = np.percentile(velocity, [0.5, 99.5]) if len(velocity) else (0.0, 0.0)
    held = (f"this run moves {lo:.3g} .. {hi:.3g} (position unit)/s with rms acceleration "
            f"{acc_rms:.3g}/s²" + (f", {reversals} reversals" if reversals is not None else "")
            + (f", filtered to {cutoff_hz:.3g} Hz" if cutoff_hz else ""))
    b2_known = b2 > 0 and b2_std <= MAX_B2_REL_STD * b2
    # low acceleration content is refused only where it shows: b2 not known to 5 %
    well_posed = b2_known and np.isfinite(condition) and condition <= MAX_CONDITION
    # a speed sine well inside the filter's band whose rms acceleration reaches the
    # target, and at least a tenth of the run's own top speed
    f = (cutoff_hz or 0.04 * rate_hz) / 4.0
    amp = max(MIN_ACCEL_SNR * accel_noise_rms * np.sqrt(2) / (2 * np.pi * f),
              0.1 * top_speed(velocity))
    fix = (f"add speed changes, e.g. a multisine of at least {amp:.2g} rad/s amplitude at "
           f"{f:.2g} Hz (in the trace's position unit per second)")
    if (acc_rms < MIN_ACCEL_SNR * accel_noise_rms and not well_posed) or np.ptp(velocity) == 0:
        raise ExcitationError(
            f"{source}: almost no acceleration content: {held}, "
            f"{acc_rms / max(accel_noise_rms, 1e-300):.3g}x the encoder-noise level "
            f"{accel_noise_rms:.3g}/s² where {MIN_ACCEL_SNR:g}x is needed; {fix}")
    if not np.isfinite(condition) or condition > MAX_CONDITION:
        raise ExcitationError(
            f"{source}: regressors ill-conditioned (condition {condition:.3g} > "
            f"{MAX_CONDITION:.0g}): speed, acceleration and friction do not vary independently "
            f"in this run ({held}); {fix}")
    if not (b2 > 0) and require_b2:
        raise ExcitationError(
            f"{source}: Kt/J comes out {b2:.4g} ± {b2_std:.2g} (not positive): check the current's "
            f"sign and that current_a belongs to this axis ({held})")
    advice = b2_shortfall(b2, b2_std, held) if b2 > 0 else (
        f"Kt/J comes out {b2:.4g} ± {b2_std:.2g}, not positive ({held})")
    if advice and require_b2:
        raise ExcitationError(f"{source}: {advice}")
    return advice


def b2_shortfall(b2: float, b2_std: float, held: str) -> str | None:
    """Why and by how much a run misses ``MAX_B2_REL_STD`` on Kt/J, in the run's own
    numbers (``held``: what it holds); None when it does not.

    Parameters
    ----------
    b2, b2_std : Kt/J and its standard uncertainty.
    held : the run's speeds, acceleration, reversals and band, as text.

    Returns
    -------
    str or None
        b2's relative uncertainty scales as 1/(acceleration content) and 1/√(duration):
        the shortfall factor f says the same moves √f x faster or an f² x longer run.

    Examples
    --------
    >>> b2_shortfall(100.0, 10.0, "a slow run") is not None
    True

    References
    ----------
    M. Gautier and W. Khalil, "On the identification of the inertial parameters of robots", Proc. 27th IEEE Conf. Decision and Control, 1988, pp. 2264-2269

    """
    rel = b2_std / b2
    if rel <= MAX_B2_REL_STD:
        return None
    f = rel / MAX_B2_REL_STD
    return (f"Kt/J is not identifiable from this run (b2 = {b2:.4g} ± {b2_std:.2g}, "
            f"{100 * rel:.2g} %; {held}); ±{100 * MAX_B2_REL_STD:.0f} % needs {f:.2g}x its "
            f"acceleration content (the same moves {np.sqrt(f):.2g}x faster) or a {f * f:.2g}x "
            f"longer run")


def check_fit_quality(*, r2: float, floor_r2: float, source: str = "<array>") -> None:
    """Refuse a fit that explains far less than the data's noise allows.

    ``floor_r2`` is the r² a perfect model would reach, given the encoder and current
    noise; a fit below ``MIN_R2_SHARE`` of it means the model does not describe this
    axis (or a channel is mis-scaled / mis-assigned) — its numbers would be wrong.

    Parameters
    ----------
    r2 : the fit's coefficient of determination.
    floor_r2 : what a perfect model would reach given the noise.
    source : the run's name.

    Returns
    -------
    None (raises ``ExcitationError``).

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md)

    Examples
    --------
    >>> check_fit_quality(r2=0.97, floor_r2=0.999)

    """
    if not np.isfinite(r2) or r2 < MIN_R2_SHARE * max(floor_r2, 0.0):
        raise ExcitationError(
            f"{source}: the model explains little of the measured acceleration (r2 "
            f"{r2:.3f}, while the data's noise allows {floor_r2:.3f}); check that "
            f"current_a is the torque-producing current (or force) of this axis and "
            f"position_rad its position, and run `gearbench diagnose` on the trace to see "
            f"which effect the model lacks")


def top_speed(velocity: np.ndarray) -> float:
    """The run's top speed (99.5th percentile of |w|), in the trace's own units.

    Parameters
    ----------
    velocity : speeds (any unit).

    Returns
    -------
    float

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md)

    Examples
    --------
    >>> top_speed([0.0, 1.0, -2.0]) > 1.9
    True

    """
    return max(float(np.percentile(np.abs(velocity), 99.5)), 1e-300)


def standstill_speed(position: np.ndarray, velocity: np.ndarray, dt_s: float) -> float:
    """Speed below which the rotor counts as sticking: 1 encoder count per 6 samples
    (the encoder step read from the data), else a small share of the top speed.

    Parameters
    ----------
    position, velocity : angle and speed (the trace's units).
    dt_s : sample period.

    Returns
    -------
    float
        Speed threshold in the trace's unit per second.

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md)

    Examples
    --------
    >>> standstill_speed(th, w, 1e-3)   # doctest: +SKIP

    """
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
    stretch it): where its friction losses D ω + Tc s(ω) were actually identified.

    Parameters
    ----------
    velocity_rad_s : the run's speeds.

    Returns
    -------
    list of two float
        [low, high].

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md)

    Examples
    --------
    >>> speed_range([1.0, 2.0, 3.0])[1] <= 3.0
    True

    """
    lo, hi = np.percentile(velocity_rad_s, [0.5, 99.5])
    return [float(lo), float(hi)]


def encoder_resolution(position_rad: np.ndarray) -> float:
    """Encoder step (rad) from the gaps between distinct angle increments; 0 if the
    angle does not look quantised.

    Parameters
    ----------
    position_rad : sampled angle.

    Returns
    -------
    float
        The encoder step (0: not quantised).

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md)

    Examples
    --------
    >>> import numpy as np
    >>> round(encoder_resolution(np.arange(100) * 0.01), 6)
    0.0
    >>> q = 2 * np.pi / 2**17                 # a 17-bit encoder, printed to 1e-8 rad
    >>> th = np.round(np.round(np.cumsum(np.random.default_rng(0).integers(-3, 4, 500)) * q, 8), 8)
    >>> round(encoder_resolution(th) / q, 3)
    1.0

    """
    steps = np.diff(np.asarray(position_rad[:200_000], float))
    scale = float(np.max(np.abs(steps))) if len(steps) else 0.0
    if scale == 0:
        return 0.0
    # relative rounding: the position's unit is the user's (rad, deg, mm, m)
    d = np.unique(np.round(steps / scale, 9)) * scale
    gaps = np.diff(d)
    gaps = gaps[gaps > 1e-8 * scale]
    if not len(gaps):
        return 0.0
    digit = float(gaps.min())
    # A file that prints the angle with fixed decimals (k·q rounded to 1e-8 rad) rounds each
    # step by up to two of its digits: the increments then sit in narrow clusters one
    # encoder step apart, and the smallest gap is the print's digit, not the encoder's
    # step (a 2^17-count joint encoder read as 1e-8 rad: its standstill band 300x too narrow)
    edges = np.flatnonzero(np.diff(d) > 3 * digit)
    centres = np.array([c.mean() for c in np.split(d, edges + 1)])
    if len(centres) < 2:
        return digit
    q = float(np.diff(centres).min())
    if q < 20 * digit:
        return digit
    k = np.round(centres / q)           # refined over every cluster: one step's centre is off by a digit
    q = float(np.sum(k * centres) / np.sum(k * k))
    off = np.abs(steps / q - np.round(steps / q)) * q
    return q if np.mean(off <= 2.5 * digit) >= 0.99 else digit
