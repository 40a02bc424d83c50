"""The paper's method as published (Yukawa et al., eqs. 6-10): ``identify_paper``."""
from __future__ import annotations


import numpy as np

from ...errors import ExcitationError, TraceError
from .. import derivatives as dv
from .checks import _condition, _r2
from .result import C_J, D_J, IdentificationResult, KT_J
from .samples import speed_range


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
