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
from .uncertainty import block_covariance, covariance_block, coverage_factor


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


# ------------------------------------------------------------ Kt's constancy over current
#: two-sided level at which a Kt shift counts as shown (not noise): 99.9 %, so the check
#: does not fire on one in twenty good calibrations as a 95 % test would
KT_LINEARITY_LEVEL = 0.999


@dataclass(frozen=True)
class CurrentDependence:
    """One calibration run's Kt against current (``current_dependence``)."""
    peak_current_a: float        # 99th percentile of |i|
    drop_at_peak: float          # Kt's relative fall at that current, first order: c·i_peak²
    drop_std: float
    b_small_current: float       # A per rad/s² at small currents ((J + disk)/Kt(0))
    b_average: float             # the same from the linear model (Kt over the run's currents)
    shift_gradient: float        # d b_average / d c (the cubic term's projection on θ'')
    c_std: float                 # standard uncertainty of c (1/A²)
    dof: int


@dataclass(frozen=True)
class KtLinearity:
    """Whether Kt is constant over a calibration's currents (``kt_linearity``)."""
    motor: str
    unloaded: CurrentDependence
    loaded: CurrentDependence
    kt_shift_rel: float          # Kt from eq. 17 over the small-current Kt, − 1
    kt_shift_std: float
    constant: bool
    message: str

    def to_dict(self) -> dict:
        """As result.json's ``motors.<m>.fit.kt_linearity`` holds it."""
        return {"constant": self.constant, "kt_shift_rel": self.kt_shift_rel,
                "kt_shift_std": self.kt_shift_std,
                "peak_current_a": [self.unloaded.peak_current_a, self.loaded.peak_current_a],
                "drop_at_peak": [self.unloaded.drop_at_peak, self.loaded.drop_at_peak],
                "drop_std": [self.unloaded.drop_std, self.loaded.drop_std],
                **({} if self.constant else {"message": self.message})}


def current_dependence(time_s, position_rad, current_a, *, cutoff_hz: float | None = None
                       ) -> CurrentDependence | None:
    """Kt's dependence on current in one calibration run: the motor equation (paper eq. 6)
    in current form with a cubic term, ``i = b θ'' + d θ' + t s(θ') + o + τ di/dt + c i³``.

    A torque constant that falls with current, ``Kt(i) = Kt / (1 + (i/i_s)²)`` (magnetic
    saturation), needs ``i ≈ T/Kt + i³/i_s²`` for a torque T: c = 1/i_s² and Kt is
    ``c·i²`` lower at current i, to first order. A constant Kt has c = 0. The current
    loop's lag has its own column (τ di/dt: without it, 5 of 40 random plants of the
    robustness benchmark, seed 1, read a Kt shift of −0.05…−1.1 % for a Kt right to 0.07 %);
    cogging and ripple depend on the angle, not on |i|. All columns go through the
    identification's zero-phase filter (``derivatives.consistent_derivatives``; i³ is
    formed before it, so its noise is the filtered current's, a bias below 10⁻⁵).
    Uncertainty: the identification's overlapping-block covariance.

    Returns None when the run cannot say (too short, or a singular fit).

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", eq. 6;
    W. K. Newey and K. D. West, Econometrica 55(3), 1987 (block covariance).

    Examples
    --------
    >>> import numpy as np
    >>> t = np.arange(0, 3, 1e-3)
    >>> w = 200 + 120 * np.sin(2 * np.pi * 3 * t)
    >>> theta = np.cumsum(w) * 1e-3
    >>> torque = 3.5e-5 * np.gradient(w, t) + 2e-6 * w + 0.008
    >>> i_lin = torque / 0.05
    >>> abs(current_dependence(t, theta, i_lin).drop_at_peak) < 1e-9
    True
    >>> # Kt(i) = Kt/(1+(i/6 A)²): i/(1+(i/6)²) = i_lin solved for i
    >>> i_sat = (1 - np.sqrt(1 - 4 * (i_lin / 6.0) ** 2)) * 6.0 ** 2 / (2 * i_lin)
    >>> d = current_dependence(t, theta, i_sat)
    >>> round(d.peak_current_a, 2), round(d.drop_at_peak, 3), round(1 - 1 / (1 + (1.93 / 6.0) ** 2), 3)
    (1.93, 0.092, 0.094)
    """
    t = np.asarray(time_s, float)
    th = np.asarray(position_rad, float)
    i = np.asarray(current_a, float)
    if len(t) < 200:
        return None
    dt = float(np.median(np.diff(t)))
    taps = dv.lowpass_fir(cutoff_hz or min(40.0, 0.1 / dt), 1.0 / dt)
    fs = dv.consistent_derivatives(th, {"current": i, "cube": i ** 3, "di": np.gradient(i) / dt}, dt, taps)
    a, w, y, cube = fs["acceleration"], fs["velocity"], fs["current"], fs["cube"]
    # Coulomb's sign only where the run reverses (one direction: it is the offset); the
    # current's derivative for the current loop's lag (τ di/dt), which a multisine with a
    # fade-in does not make orthogonal to i³
    s = np.sign(w)
    base = [a, w, np.ones_like(a), fs["di"]] + ([s] if np.any(s > 0) and np.any(s < 0) else [])
    X = np.vstack(base + [cube])
    A = X @ X.T
    try:
        beta = np.linalg.solve(A, X @ y)
        e = y - beta @ X
        cov, dof, _ = block_covariance(X, e, A, block=covariance_block(e, len(taps)))
        X0 = np.vstack(base)
        b_avg = float(np.linalg.solve(X0 @ X0.T, X0 @ y)[0])
        gamma = float(np.linalg.solve(X0 @ X0.T, X0 @ cube)[0])
    except np.linalg.LinAlgError:
        return None
    ip = float(np.percentile(np.abs(i), 99))
    c, c_std = float(beta[-1]), float(np.sqrt(max(cov[-1, -1], 0.0)))
    return CurrentDependence(ip, c * ip ** 2, c_std * ip ** 2, float(beta[0]), b_avg, gamma, c_std, int(dof))


def kt_linearity(unloaded: CurrentDependence, loaded: CurrentDependence, *, kt_half_width_rel: float,
                 motor: str = "", rated_current_a: float | None = None,
                 current_limit_a: float | None = None) -> KtLinearity:
    """Is Kt from eq. 17 the motor's constant, or an average over a Kt that changes with
    current? Kt ∝ disk/(b_loaded − b_unloaded) (corrected eq. 17, b = inertia/Kt in A per
    rad/s²); where Kt falls with current the loaded run, at higher currents, takes a larger
    b, and the difference magnifies it: Kt's shift from its small-current value is
    ``(b0_L − b0_U)/(b_L − b_U) − 1`` (``current_dependence``'s b with and without the
    cubic term; its standard uncertainty from the cubic terms' by first-order propagation).

    Not constant when that shift is larger than Kt's own 95 % half-width
    ``kt_half_width_rel`` (the result is then off by more than it says) and shown at the
    ``KT_LINEARITY_LEVEL`` (two-sided Student t on the runs' fewer degrees of freedom).

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", eq. 17 (corrected,
    ``analysis.torque_constant``).

    Examples
    --------
    >>> u = CurrentDependence(1.2, 0.16, 0.002, 3.0e-4, 3.2e-4, 1.3e-4, 1e-4, 14)
    >>> l = CurrentDependence(3.0, 0.46, 0.005, 7.6e-4, 1.1e-3, 3.7e-4, 1e-4, 14)
    >>> r = kt_linearity(u, l, kt_half_width_rel=0.01, motor="in", current_limit_a=3.0)
    >>> r.constant, round(r.kt_shift_rel, 2)
    (False, -0.41)
    """
    d0 = loaded.b_small_current - unloaded.b_small_current
    d = loaded.b_average - unloaded.b_average
    shift = d0 / d - 1.0 if d and d0 else 0.0
    # b_average = b0 + c·gamma per run: d(shift)/dc_L = −d0·gamma_L/d², d/dc_U = +d0·gamma_U/d²
    std = abs(d0) / d ** 2 * float(np.hypot(loaded.shift_gradient * loaded.c_std,
                                            unloaded.shift_gradient * unloaded.c_std)) if d else float("inf")
    t = coverage_factor(min(unloaded.dof, loaded.dof), KT_LINEARITY_LEVEL)
    constant = not (abs(shift) > kt_half_width_rel and abs(shift) > t * std)
    drive = ", ".join(f"{k} {v:g} A" for k, v in (("rated", rated_current_a), ("drive limit", current_limit_a)) if v)
    message = (f"motor {motor or '?'}: Kt is not constant over the calibration's currents: it falls by about "
               f"{100 * loaded.drop_at_peak:.0f} % (± {100 * loaded.drop_std:.1f}) at {loaded.peak_current_a:.2f} A in "
               f"the loaded run and {100 * unloaded.drop_at_peak:.0f} % (± {100 * unloaded.drop_std:.1f}) at "
               f"{unloaded.peak_current_a:.2f} A unloaded" + (f" ({drive})" if drive else "") +
               f"; eq. 17's Kt is then {100 * shift:+.0f} % (± {100 * std:.1f}) off the small-current Kt, "
               f"beyond its ±{100 * kt_half_width_rel:.2f} % interval. Not a result: calibrate within the "
               f"motor's linear range (a smaller disk or a gentler excitation, currents below the knee)")
    return KtLinearity(motor, unloaded, loaded, float(shift), float(std), bool(constant), message)


def calibration_linearity(unloaded, loaded, *, kt: float, kt_ci95: tuple[float, float], motor: str = "",
                          rated_current_a: float | None = None,
                          current_limit_a: float | None = None) -> KtLinearity | None:
    """``kt_linearity`` of a calibration's two runs (single-motor traces with
    ``position_rad`` and ``current_a``) against the Kt eq. 17 gave and its 95 % interval;
    None when a run cannot say (``current_dependence``)."""
    runs = [current_dependence(tr.time_s, tr["position_rad"], tr["current_a"]) for tr in (unloaded, loaded)]
    if None in runs or not kt:
        return None
    half = (float(kt_ci95[1]) - float(kt_ci95[0])) / 2.0 / abs(kt)
    return kt_linearity(*runs, kt_half_width_rel=half, motor=motor, rated_current_a=rated_current_a,
                        current_limit_a=current_limit_a)


def with_linearity(fit: dict, lin: KtLinearity | None) -> dict:
    """A calibration's ``fit`` record with the check's outcome (``kt_linearity``) and, where
    Kt is not constant, its message among the warnings."""
    if lin is None:
        return fit
    out = {**fit, "kt_linearity": lin.to_dict()}
    if not lin.constant:
        out["warnings"] = [*fit.get("warnings", []), lin.message]
    return out


def kt_not_constant(motor_result: dict) -> str | None:
    """The message of a motor's result (result.json ``motors.<m>``) whose Kt was found not
    constant over its calibration's currents, else None."""
    lin = (motor_result.get("fit") or {}).get("kt_linearity") or {}
    return None if lin.get("constant", True) else lin.get("message", "Kt is not constant over current")
