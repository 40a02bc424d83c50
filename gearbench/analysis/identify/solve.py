"""The regressions: the torque form (IDIM-LS, or IV on the command) and the accel form,
with the current-lag column and the errors-in-variables corrections."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import ExcitationError
from .. import derivatives as dv
from .result import BIAS, C_J, D_J, KT_J, LAG, LOAD_COS, LOAD_SIN, TC_J, own_to_accel_names
from .signals import _Signals


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


def _to_accel_names(fit: _Fit, cov: np.ndarray):
    """Values and covariance on the accel-form names (``own_to_accel_names``)."""
    names = tuple(c[0] for c in fit.cols) + ((LAG,) if len(fit.beta) > len(fit.cols) else ())
    sign = np.array([c[2] for c in fit.cols] + [1.0] * (len(names) - len(fit.cols)))
    values, cov = own_to_accel_names(fit.form, fit.beta, sign, cov)
    return names, values, cov


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
