"""Measured against model: the identified motor equation replayed on a recorded run.

``torque_balance`` puts both sides of ``J θ'' + D θ' + Tc s(θ') = Kt i`` (paper eq. 6,
the disk's inertia added for the loaded run) through the same zero-phase filter the
identification uses (``derivatives.consistent_derivatives``), so the two curves
differ only by what the model leaves out plus noise. The report draws them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import derivatives as dv


@dataclass(frozen=True)
class TorqueBalance:
    time_s: np.ndarray
    measured_nm: np.ndarray      # Kt · i, filtered
    model_nm: np.ndarray         # (J + disk) θ'' + D θ' + Tc sign(θ'), filtered angle
    r2: float                    # 1 - var(measured - model) / var(measured)
    rms_error_nm: float


def torque_balance(time_s, position_rad, current_a, *, Kt: float, J: float, D: float, Tc: float,
                   disk_kgm2: float = 0.0, cutoff_hz: float | None = None) -> TorqueBalance:
    """Both sides of the motor equation on one recorded run, through one filter.

    ``Kt i`` against ``(J + disk) θ'' + D θ' + Tc sign(θ')`` — paper eq. 6 — with the
    angle differentiated and the current filtered by the identification's own
    zero-phase FIR (``derivatives.consistent_derivatives``), so the two differ only by
    what the model leaves out, plus noise.

    Parameters
    ----------
    time_s, position_rad, current_a : array_like
        The run's samples (s, rad, A), evenly spaced.
    Kt, J, D, Tc : float
        The identified motor: N m/A, kg m², N m s/rad, N m.
    disk_kgm2 : float, optional
        Inertia added for the loaded run (kg m²).
    cutoff_hz : float, optional
        Filter cut-off; default min(40 Hz, rate/10).

    Returns
    -------
    TorqueBalance
        ``measured_nm``, ``model_nm`` on the filtered time base, their ``r2`` and
        ``rms_error_nm``.

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", eq. 6
    (the motor equation J θ'' + D θ' + Tc sign θ' = Kt i).

    Examples
    --------
    >>> import numpy as np
    >>> t = np.arange(0, 2, 1e-3)
    >>> w = 50 * np.sin(2 * np.pi * t)                       # rad/s
    >>> theta = np.cumsum(w) * 1e-3
    >>> i = (1e-5 * np.gradient(w, t) + 1e-4 * w + 0.01 * np.sign(w)) / 0.05
    >>> tb = torque_balance(t, theta, i, Kt=0.05, J=1e-5, D=1e-4, Tc=0.01)
    >>> bool(tb.r2 > 0.95)
    True
    """
    t = np.asarray(time_s, float)
    th = np.asarray(position_rad, float)
    i = np.asarray(current_a, float)
    dt = float(np.median(np.diff(t)))
    rate = 1.0 / dt
    taps = dv.lowpass_fir(cutoff_hz or min(40.0, rate / 10.0), rate)
    fs = dv.consistent_derivatives(th, {"current": i}, dt, taps)
    n = len(fs["acceleration"])
    at = slice((len(taps) - 1) // 2 + 1, (len(taps) - 1) // 2 + 1 + n)
    w = fs["velocity"]
    model = (J + disk_kgm2) * fs["acceleration"] + D * w + Tc * np.sign(w)
    measured = Kt * fs["current"]
    err = measured - model
    var = float(np.var(measured))
    r2 = 1.0 - float(np.var(err)) / var if var > 0 else float("nan")
    return TorqueBalance(t[at], measured, model, r2, float(np.sqrt(np.mean(err ** 2))) if n else float("nan"))
