"""Reducer efficiency from a two-motor bench trace (paper eq. 18 and P_out/P_in).

The bench: input motor in speed control, output motor in current control stepping
through braking currents (``out_command`` < 0), zero-load levels (``out_command`` = 0)
first and last. Steady windows come from the command columns; zero-load windows are
the reference, every loaded window is one point, in trace order. Window means of the
currents are Tukey-weighted (``taper``) so periodic ripple (CVT pulsation, cogging of
either motor) does not bias Δi whatever its period.

Per point
    incremental (eq. 18)  η = K_out·Δi_out / (n·K_in·Δi_in), written with signs as
                          η = −K_out·Δi_out / (n_s·K_in·Δi_in), n_s = ω_in/ω_out signed,
                          because a braking output current is negative. The reducer's
                          no-load loss cancels in Δi (reference interpolated in time
                          between the zero-load windows before and after, cancelling drift).
    absolute              P_in  = (Kt_in·i_in − D_in·ω_in − Tc_in·s(ω_in))·ω_in   at the input shaft
                          P_out = (−Kt_out·i_out + D_out·ω_out + Tc_out·s(ω_out))·ω_out
                          (the output motor's own friction is also driven by the shaft).
Uncertainty: first-order propagation of the window means' standard errors (block
means, so ripple and coloured noise count; block count − 1 degrees of freedom), the Kt
standard uncertainties (with their model-error and disk parts and their degrees of
freedom), the (D, Tc) covariances (with the calibration runs' disagreement as model
error, see ``calibration.calibrate_from_fits``; the calibration's degrees of freedom)
and the ratio. The loss D ω + Tc is
linear in (D, Tc), so its propagated variance grows with the distance of the operating
speed from the calibration runs' speeds: extrapolation widens the absolute interval by
itself. Each point stores its standard uncertainties and Welch–Satterthwaite degrees
of freedom; the 95 % intervals are Student-t on them (``analysis.uncertainty``).
Each point records whether either motor's loss was extrapolated beyond the
speed range its calibration runs covered (``loss_extrapolated``).

Per speed the levels are also fitted as one straight line (``staircase_fit``): a
zero-load level off the braking levels' line (the mesh's power flow reversing at no
load) is no anchor for eq. 18, so those points take the braking levels' slope; levels
scattering about the line beyond their window errors widen those errors
(``with_level_scatter``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import ExcitationError, GearbenchError, TraceError
from ..trace import BENCH_COLUMNS, Trace
from .calibration import MotorCalibration
from .ripple import ripple_corrected_current
from .streaming import slope_dof, slope_fit
from .streaming import tapered_mean_sem as _mean_sem
from .uncertainty import DOF_MAX, effective_dof, interval
from .windows import TAPER_ALPHA, taper  # noqa: F401  (taper: public here since 0.1)


@dataclass(frozen=True)
class SteadyWindow:
    """One steady command level after dropping the settle time."""

    start: int                    # first sample index (inclusive)
    stop: int                     # last sample index (exclusive)
    t_mid_s: float
    in_command: float
    out_command: float
    current_in_a: float
    current_in_sem: float         # standard error of the mean
    current_out_a: float
    current_out_sem: float
    speed_in_rad_s: float
    speed_out_rad_s: float
    current_in_dof: float = DOF_MAX     # degrees of freedom of the standard errors
    current_out_dof: float = DOF_MAX

    @property
    def is_reference(self) -> bool:
        return self.out_command == 0.0


@dataclass(frozen=True)
class EfficiencyPoint:
    window: SteadyWindow = field(compare=False)   # its statistics are not all written out
    speed_in_rad_s: float
    torque_in_nm: float           # delivered into the input shaft, along its rotation
    torque_out_nm: float          # delivered by the output shaft, along its rotation (load)
    delta_current_in_a: float
    delta_current_out_a: float
    eta_incremental: float
    eta_incremental_ci95: tuple[float, float]
    eta_absolute: float
    eta_absolute_ci95: tuple[float, float]
    power_in_w: float
    power_out_w: float
    # Loss D ω + Tc of a motor evaluated outside the speeds its calibration covered.
    loss_extrapolated: bool = False
    loss_speed_range_in_rad_s: tuple[float, float] | None = None
    loss_speed_range_out_rad_s: tuple[float, float] | None = None
    eta_incremental_std: float = 0.0
    eta_incremental_dof: float = DOF_MAX
    eta_absolute_std: float = 0.0
    eta_absolute_dof: float = DOF_MAX
    # "secant": eq. 18 against the zero-load reference (this point alone); "slope": eq. 18
    # as the regression slope of input on output current over the speed's staircase,
    # the secant then kept beside it (a load-dependent efficiency shows as their difference)
    incremental_method: str = "secant"
    eta_incremental_secant: float | None = None
    eta_incremental_secant_ci95: tuple[float, float] | None = None
    # set by a station: the speed the profile commanded (the point's stable name) and how
    # many lost samples were filled in
    speed_setpoint_rad_s: float | None = None
    interpolated_samples: int = 0

    @property
    def out_command_a(self) -> float:
        """The output motor's current command of this level (the set braking torque)."""
        return self.window.out_command

    @classmethod
    def from_dict(cls, d: dict) -> "EfficiencyPoint":
        """From one entry of result.json's ``efficiency`` (or ``gearbench efficiency --json``).
        The window's statistics that are not written out (sample range, mean currents) come
        back as 0 / NaN; everything ``to_dict`` writes round-trips."""
        nan = float("nan")

        def num(key, default=nan):
            v = d.get(key, default) if default is not None else d[key]   # None: a required key
            return nan if v is None else float(v)

        def pair(v):
            return (nan, nan) if v is None else tuple(nan if x is None else float(x) for x in v)

        def opt_pair(v):
            return None if v is None else pair(v)
        w = SteadyWindow(0, 0, num("t_mid_s"), num("in_command"),
                         num("out_command"), nan, nan, nan, nan,
                         num("speed_in_rad_s", None), num("speed_out_rad_s"))
        sp = d.get("speed_setpoint_rad_s")
        return cls(w, num("speed_in_rad_s", None), num("torque_in_nm"), num("torque_out_nm", None),
                   num("delta_current_in_a"), num("delta_current_out_a"),
                   num("eta_incremental", None), pair(d.get("eta_incremental_ci95")),
                   num("eta_absolute"), pair(d.get("eta_absolute_ci95")),
                   num("power_in_w"), num("power_out_w"),
                   bool(d.get("loss_extrapolated", False)), opt_pair(d.get("loss_speed_range_in_rad_s")),
                   opt_pair(d.get("loss_speed_range_out_rad_s")),
                   num("eta_incremental_std", 0.0), num("eta_incremental_dof", DOF_MAX),
                   num("eta_absolute_std", 0.0), num("eta_absolute_dof", DOF_MAX),
                   str(d.get("incremental_method", "secant")), d.get("eta_incremental_secant"),
                   opt_pair(d.get("eta_incremental_secant_ci95")),
                   None if sp is None else float(sp), int(d.get("interpolated_samples", 0) or 0))

    def to_dict(self) -> dict:
        w = self.window
        extra = {} if self.incremental_method == "secant" else {
            "incremental_method": self.incremental_method,
            "eta_incremental_secant": self.eta_incremental_secant,
            "eta_incremental_secant_ci95": _as_list(self.eta_incremental_secant_ci95)}
        return {**extra,"eta_incremental": self.eta_incremental,
                "eta_incremental_std": self.eta_incremental_std,
                "eta_incremental_dof": self.eta_incremental_dof,
                "eta_incremental_ci95": list(self.eta_incremental_ci95),
                "eta_absolute": self.eta_absolute, "eta_absolute_std": self.eta_absolute_std,
                "eta_absolute_dof": self.eta_absolute_dof,
                "eta_absolute_ci95": list(self.eta_absolute_ci95),
                "speed_in_rad_s": self.speed_in_rad_s, "torque_out_nm": self.torque_out_nm,
                "torque_in_nm": self.torque_in_nm, "power_in_w": self.power_in_w,
                "power_out_w": self.power_out_w, "out_command": w.out_command,
                "in_command": w.in_command, "delta_current_in_a": self.delta_current_in_a,
                "delta_current_out_a": self.delta_current_out_a,
                "t_mid_s": w.t_mid_s, "speed_out_rad_s": w.speed_out_rad_s,
                "loss_extrapolated": self.loss_extrapolated,
                "loss_speed_range_in_rad_s": _as_list(self.loss_speed_range_in_rad_s),
                "loss_speed_range_out_rad_s": _as_list(self.loss_speed_range_out_rad_s),
                **({} if self.speed_setpoint_rad_s is None else
                   {"interpolated_samples": self.interpolated_samples,
                    "speed_setpoint_rad_s": self.speed_setpoint_rad_s})}


def _as_list(r):
    return None if r is None else [float(r[0]), float(r[1])]


def loss_speed_range(motor: MotorCalibration) -> tuple[float, float] | None:
    """Speeds the motor's calibration runs covered (``fit.speed_range_rad_s``), or None
    when unknown (``--kt-in`` only, or an older calibrate --json).

    Parameters
    ----------
    motor : a calibration.

    Returns
    -------
    tuple of float or None

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md)

    Examples
    --------
    >>> loss_speed_range(cal)   # doctest: +SKIP

    """
    r = motor.fit.get("speed_range_rad_s") if motor.fit else None
    try:
        lo, hi = float(r[0]), float(r[1])
    except (TypeError, ValueError, IndexError, KeyError):
        return None
    return (lo, hi) if np.isfinite(lo) and np.isfinite(hi) and lo <= hi else None


def shared_disk_covariance(motor_in: MotorCalibration, motor_out: MotorCalibration) -> float:
    """Covariance of the two Kt through a disk both were calibrated with (``fit.disk``
    names it): the product of their disk parts ``fit.Kt_std_disk``; 0 for different or
    unnamed disks.

    Parameters
    ----------
    motor_in, motor_out : the two calibrations.

    Returns
    -------
    float
        Cov(Kt_in, Kt_out), (N m/A)^2.

    References
    ----------
    JCGM 100:2008, "Evaluation of measurement data — Guide to the expression of uncertainty in measurement" (GUM), 5.2

    Examples
    --------
    >>> shared_disk_covariance(cal_in, cal_out)   # doctest: +SKIP

    """
    a, b = (m.fit.get("disk") if m.fit else None for m in (motor_in, motor_out))
    if not a or a != b:
        return 0.0
    return float(motor_in.fit.get("Kt_std_disk", 0.0)) * float(motor_out.fit.get("Kt_std_disk", 0.0))


def is_extrapolated(speed_rad_s: float, speed_range: tuple[float, float] | None) -> bool:
    """True when the motor has a loss model (a known calibrated range) and
    ``speed_rad_s`` lies outside that range.

    Parameters
    ----------
    speed_rad_s : the operating speed.
    speed_range : the calibrated range (None: no loss model).

    Returns
    -------
    bool

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md)

    Examples
    --------
    >>> is_extrapolated(300.0, (70.0, 230.0))
    True

    """
    return speed_range is not None and not (speed_range[0] <= speed_rad_s <= speed_range[1])


@dataclass(frozen=True)
class EfficiencyResult:
    ratio: float                  # |n| used
    ratio_sign: float             # +1 same direction, −1 the reducer reverses
    ratio_measured: float         # |n| from the encoders
    points: tuple[EfficiencyPoint, ...]
    references: tuple[SteadyWindow, ...]

    def to_dict(self) -> dict:
        return {"ratio": self.ratio, "ratio_measured": self.ratio_measured,
                "direction": "same" if self.ratio_sign > 0 else "reversed",
                "points": [p.to_dict() for p in self.points],
                "references": [{"t_mid_s": r.t_mid_s, "in_command": r.in_command,
                                "current_in_a": r.current_in_a, "current_out_a": r.current_out_a,
                                "speed_in_rad_s": r.speed_in_rad_s} for r in self.references]}


# ------------------------------------------------------------------ steady windows
def steady_windows(time_s: np.ndarray, in_command: np.ndarray, out_command: np.ndarray,
                   *, settle_s: float = 0.5, min_window_s: float = 0.3) -> list[tuple[int, int]]:
    """Index ranges where both commands are constant, minus ``settle_s`` after each change.

    Ramps (a command changing every sample) produce no window. Windows shorter than
    ``min_window_s`` after settling are dropped.

    Parameters
    ----------
    time_s, in_command, out_command : the bench trace's time and commands.
    settle_s, min_window_s : settling time dropped after each change; shortest window kept.

    Returns
    -------
    list of (start, stop) index pairs

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md), sec. 4 (steady operating points)

    Examples
    --------
    >>> steady_windows(t, cin, cout)   # doctest: +SKIP

    """
    change = np.flatnonzero((np.diff(in_command) != 0) | (np.diff(out_command) != 0)) + 1
    bounds = np.concatenate([[0], change, [len(time_s)]])
    out = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        if b - a < 2:
            continue
        t0 = time_s[a] + (settle_s if a > 0 else 0.0)
        s = int(np.searchsorted(time_s, t0))
        if s < b and time_s[b - 1] - time_s[s] >= min_window_s:
            out.append((s, int(b)))
    return out




def measure_windows(trace: Trace, *, settle_s: float = 0.5,
                    ranges: list[tuple[int, int]] | None = None) -> list[SteadyWindow]:
    """Steady windows from the command levels minus ``settle_s``, or exactly ``ranges``
    (index pairs; an adaptive run knows where each level settled and ended).

    Parameters
    ----------
    trace : the bench trace.
    settle_s : settling dropped after each command change.
    ranges : exact index pairs (adaptive runs).

    Returns
    -------
    list of SteadyWindow

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md)

    Examples
    --------
    >>> measure_windows(trace)   # doctest: +SKIP

    """
    t = trace.time_s
    if ranges is None:
        ranges = steady_windows(t, trace["in_command"], trace["out_command"], settle_s=settle_s)
    res = []
    for s, e in ranges:
        ci, ci_sem, ci_dof = _mean_sem(trace["in_current_a"][s:e])
        co, co_sem, co_dof = _mean_sem(trace["out_current_a"][s:e])
        dt = t[e - 1] - t[s]
        res.append(SteadyWindow(
            s, e, float((t[s] + t[e - 1]) / 2), float(trace["in_command"][s]),
            float(trace["out_command"][s]) + 0.0, ci, ci_sem, co, co_sem,
            float((trace["in_position_rad"][e - 1] - trace["in_position_rad"][s]) / dt),
            float((trace["out_position_rad"][e - 1] - trace["out_position_rad"][s]) / dt),
            ci_dof, co_dof))
    return res


def measured_ratio(windows: list[SteadyWindow], trace: Trace) -> float:
    """Signed n = Δθ_in/Δθ_out summed over the steady windows (free of start-up backlash).

    Parameters
    ----------
    windows : steady windows.
    trace : the bench trace.

    Returns
    -------
    float
        Signed ratio n.

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md)

    Examples
    --------
    >>> measured_ratio(ws, trace)   # doctest: +SKIP

    """
    din = sum(trace["in_position_rad"][w.stop - 1] - trace["in_position_rad"][w.start] for w in windows)
    dout = sum(trace["out_position_rad"][w.stop - 1] - trace["out_position_rad"][w.start] for w in windows)
    if abs(dout) < 1e-9 * max(abs(din), 1.0) or abs(dout) == 0:
        raise ExcitationError(f"{trace.source}: column 'out_position_rad' does not move while "
                              f"the input turns; check the coupling or pass --ratio")
    return float(din / dout)


# ---------------------------------------------------------------------- equations
def incremental_efficiency(kt_in: float, kt_out: float, delta_current_in_a: float,
                           delta_current_out_a: float, ratio_signed: float) -> float:
    """Paper eq. 18 with signs: η = −K_out Δi_out / (n_s K_in Δi_in).

    Parameters
    ----------
    kt_in, kt_out : torque constants.
    delta_current_in_a, delta_current_out_a : current changes from no load.
    ratio_signed : n with its sign.

    Returns
    -------
    float

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md), eq. 18

    Examples
    --------
    >>> round(incremental_efficiency(0.05, 0.05, 0.1, -0.8, 8.0), 6)
    1.0

    """
    return -kt_out * delta_current_out_a / (ratio_signed * kt_in * delta_current_in_a)


def shaft_powers(current_in_a: float, current_out_a: float, speed_in_rad_s: float,
                 speed_out_rad_s: float, motor_in: MotorCalibration,
                 motor_out: MotorCalibration) -> tuple[float, float, float, float]:
    """(T_in, T_out, P_in, P_out) at the reducer's shafts, signs in the module docstring.

    Parameters
    ----------
    current_in_a, current_out_a : the motors' currents.
    speed_in_rad_s, speed_out_rad_s : shaft speeds.
    motor_in, motor_out : calibrations (Kt and losses).

    Returns
    -------
    tuple of float
        (T_in, T_out, P_in, P_out).

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md)

    Examples
    --------
    >>> shaft_powers(1.0, -0.5, 100.0, 12.5, cal_in, cal_out)   # doctest: +SKIP

    """
    t_in = motor_in.Kt * current_in_a - motor_in.loss_torque_nm(speed_in_rad_s)
    t_out = -motor_out.Kt * current_out_a + motor_out.loss_torque_nm(speed_out_rad_s)
    return t_in, t_out, t_in * speed_in_rad_s, t_out * speed_out_rad_s


def absolute_efficiency(current_in_a: float, current_out_a: float, speed_in_rad_s: float,
                        speed_out_rad_s: float, motor_in: MotorCalibration,
                        motor_out: MotorCalibration) -> float:
    """P_out / P_in at the reducer's shafts using each motor's identified losses.

    Parameters
    ----------
    current_in_a, current_out_a, speed_in_rad_s, speed_out_rad_s : the operating point.
    motor_in, motor_out : calibrations.

    Returns
    -------
    float

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md)

    Examples
    --------
    >>> absolute_efficiency(1.0, -0.5, 100.0, 12.5, cal_in, cal_out)   # doctest: +SKIP

    """
    _, _, p_in, p_out = shaft_powers(current_in_a, current_out_a, speed_in_rad_s,
                                     speed_out_rad_s, motor_in, motor_out)
    return p_out / p_in


# ------------------------------------------------------------------------ the job
SPEED_SPAN_S = 0.1           # inertia correction: speed averaged over 100 ms (encoder quantum, shaft ripple)


def inertia_corrected_current(current_a: np.ndarray, position_rad: np.ndarray, period_s: float,
                              inertia_kgm2: float, kt_nm_a: float) -> np.ndarray:
    """A motor's current less what accelerates its own rotor, i − J θ''/Kt: from the
    motor's equation J θ'' + D θ' + Tc s(θ') + T_shaft = Kt i (eq. 1), the current that
    carries its friction and the shaft torque alone. After a load step a speed loop's
    recovery moves the current for hundreds of milliseconds while the shaft torque is
    already steady; the corrected current is steady as soon as the shaft torque is, so a
    level's window can start right after the step (the mean of J θ''/Kt over a window is
    J Δω/(T Kt): it only needs the speeds at the window's ends to be right).

    Parameters
    ----------
    current_a, position_rad : ndarray
        The motor's current and encoder angle, one sample per ``period_s``.
    period_s : float
        Sample period (s).
    inertia_kgm2, kt_nm_a : float
        The motor's calibrated J and Kt.

    Returns
    -------
    ndarray
        The corrected current (A); θ'' as the difference of the speed averaged over
        ``SPEED_SPAN_S`` (so the encoder's quantum does not dominate), 0 at the two ends.

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", eq. 1-2.

    Examples
    --------
    >>> import numpy as np
    >>> t = np.arange(300) * 1e-3
    >>> i = inertia_corrected_current(np.ones(300), 50.0 * t ** 2, 1e-3, 1e-4, 0.1)
    >>> float(i[150].round(6)), float(i[0])
    (0.9, 1.0)
    """
    th = np.asarray(position_rad, float)
    h = max(1, int(round(SPEED_SPAN_S / 2 / period_s)))
    acc = np.zeros_like(th)
    if len(th) > 2 * h + 2:
        # speed as the angle travelled over 2h samples (the encoder's quantum over one
        # sample would put a 1/dt² noise on θ''); θ'' its first difference
        w = (th[2 * h:] - th[:-2 * h]) / (2 * h * period_s)          # at samples h .. n-h-1
        acc[h + 1:len(th) - h - 1] = (w[2:] - w[:-2]) / (2 * period_s)
    return np.asarray(current_a, float) - inertia_kgm2 * acc / kt_nm_a


def efficiency(trace: Trace, motor_in: MotorCalibration, motor_out: MotorCalibration, *,
               ratio: float | None = None, settle_s: float = 0.5,
               windows: list[tuple[int, int]] | None = None,
               incremental: str = "auto", inertia_corrected: bool = False,
               ripple_corrected: bool = False) -> EfficiencyResult:
    """Efficiency points of a bench trace (see module docstring).

    ``windows``: the steady index ranges (else found from the commands and ``settle_s``).
    ``incremental="slope"``: eq. 18 as the weighted regression slope of input on output
    current over all levels at the same speed (``incremental_slope``), one value per
    speed; every point keeps its own secant beside it. ``"auto"`` (default): that slope
    where the speed's levels lie on one straight line within their errors (zero-load
    level on it, ``OFF_LINE_SIGMAS``; no scatter beyond the errors, ``SCATTER_LEVEL``;
    the zero-load levels' drift free, ``staircase_fit``), else each point's secant from
    the zero-load level (eq. 18 as printed). On a line every secant estimates the same
    slope, and the line uses every level: at half load the secant's standard error is
    about 2.6 times the line's (six levels 0, ¼…1, 0 of full load). ``inertia_corrected``: the input
    motor's current less its own rotor's inertial part (``inertia_corrected_current``,
    its calibrated J and Kt) before the window means: levels that start while its speed
    loop is still recovering (the adaptive staircase) carry no transient. The output
    motor, current-controlled, is left as measured (corrected, the shaft ripple its
    rotor's inertia passes on would add more noise than a braking step's transient).
    ``ripple_corrected``: the input motor's current also less its speed loop's
    quantisation ripple (``ripple.ripple_corrected_current``, from the drive's reported
    speed ``in_velocity_rad_s``): for a drive that reports one current-loop instant.
    Either way, a speed whose zero-load level lies off its braking levels' line by more
    than ``OFF_LINE_SIGMAS`` takes eq. 18 from their slope (``staircase_fit``), and a
    speed whose levels scatter beyond their errors has them widened (``with_level_scatter``).

    Parameters
    ----------
    trace : the bench trace.
    motor_in, motor_out : calibrations.
    settle_s, windows, incremental : see above.

    Returns
    -------
    EfficiencyResult
        Points with incremental and absolute efficiency, intervals and ``loss_extrapolated``.

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md), eq. 18; JCGM 100:2008, "Evaluation of measurement data — Guide to the expression of uncertainty in measurement" (GUM)

    Examples
    --------
    >>> res = efficiency(Trace.read("bench.csv"), cal_in, cal_out)   # doctest: +SKIP

    """
    trace.validate(BENCH_COLUMNS, min_samples=100)
    if ratio is not None and not (np.isfinite(ratio) and ratio > 0):
        raise GearbenchError(f"--ratio must be a positive number, got {ratio}")
    if incremental not in ("secant", "slope", "auto"):
        raise GearbenchError(f"incremental must be 'secant', 'slope' or 'auto', got {incremental!r}")
    if inertia_corrected:
        dt = float(np.median(np.diff(trace.time_s)))
        trace = trace.with_columns(**{
            f"{side}_current_a": inertia_corrected_current(trace[f"{side}_current_a"], trace[f"{side}_position_rad"],
                                                           dt, cal.J, cal.Kt)
            for side, cal in (("in", motor_in),)})
    if ripple_corrected:
        if "in_velocity_rad_s" not in trace:
            raise TraceError(f"{trace.source}: the ripple correction needs the input drive's "
                             f"reported speed (column 'in_velocity_rad_s'); record it or "
                             f"analyse without the correction")
        dt = float(np.median(np.diff(trace.time_s)))
        # the gain from the levels alone: on the ramps and steps the drive's speed lags the
        # encoder's, a difference the current answers through the loop, not ripple
        if windows is None:     # found once, for the gain and the windows below
            windows = steady_windows(trace.time_s, trace["in_command"], trace["out_command"],
                                     settle_s=settle_s)
        cur, _ = ripple_corrected_current(trace["in_current_a"], trace["in_velocity_rad_s"],
                                          trace["in_position_rad"], dt, ranges=windows)
        trace = trace.with_columns(in_current_a=cur)
    raw = measure_windows(trace, settle_s=settle_s, ranges=windows)
    wins = with_level_scatter(raw)
    # speeds whose levels scatter about their line beyond their errors (widened above)
    scattered = {w.in_command for w, r in zip(wins, raw) if w is not r}
    refs = [w for w in wins if w.is_reference]
    loaded = [w for w in wins if not w.is_reference]
    if not refs:
        raise TraceError(f"{trace.source}: column 'out_command' has no zero-load level "
                         f"(out_command = 0) to reference; record one before and after the loads")
    if not loaded:
        raise TraceError(f"{trace.source}: column 'out_command' has no loaded level "
                         f"(out_command != 0); step the output motor through braking currents")
    n_meas = measured_ratio(wins, trace)
    sign = float(np.sign(n_meas))
    n_abs = float(ratio) if ratio is not None else abs(n_meas)
    n_signed = sign * n_abs
    # Ratio from encoders: quantisation over the summed travel only.
    n_rel_std = 0.0 if ratio is not None else 1e-5

    points = []
    for w in loaded:
        ref = _reference(w, refs, trace.source)
        p = _point(w, ref, motor_in, motor_out, n_signed, n_rel_std, trace.source)
        same = [v for v in wins if _same_speed(v, w)]
        fit = staircase_fit(same)
        if fit is not None and fit["off_line_sigmas"] > OFF_LINE_SIGMAS:
            # off the line: the zero-load level is no anchor for eq. 18, the braking
            # levels' slope is (drift taken out by the zero-load levels; the secant stays beside)
            p = _slope_point(p, fit["slope"], fit["slope_sem"], fit["dof"], motor_in, motor_out,
                             n_signed, n_rel_std, trace.source)
        elif incremental == "slope":
            p = _with_slope(p, same, motor_in, motor_out, n_signed, n_rel_std, trace.source)
        elif incremental == "auto" and fit is not None and w.in_command not in scattered:
            # on one line: the line through every level, the zero-load level on it
            line = staircase_fit(same, zero_load_on_line=True)
            if line is not None:
                p = _slope_point(p, line["slope"], line["slope_sem"], line["dof"], motor_in,
                                 motor_out, n_signed, n_rel_std, trace.source)
        points.append(p)
    return EfficiencyResult(n_abs, sign, abs(n_meas), tuple(points), tuple(refs))


def _same_speed(a: SteadyWindow, b: SteadyWindow) -> bool:
    return bool(np.isclose(a.in_command, b.in_command, rtol=1e-6, atol=1e-9))


# The braking levels' scatter about their line is tested at this level (chi-square)
SCATTER_LEVEL = 0.99


def with_level_scatter(windows: list[SteadyWindow]) -> list[SteadyWindow]:
    """The windows with each speed's standard errors widened when its braking levels
    scatter about their straight line beyond what their own errors allow.

    A window's standard error comes from its block means (``tapered_mean_sem``), so it
    sees noise faster than a block (~0.3 s) and nothing slower. A disturbance that wanders
    over seconds (seed 7 case 16 of the robustness benchmark: 0.25 s means of the input
    current wander by ±3 mA at every level while the windows claim 0.3-0.5 mA) moves whole
    levels, and eq. 18's Δi with them. The levels of one speed lie on a straight line
    (input on output current, slope = eq. 18), so their residuals about ``staircase_fit`` (the line, the
    zero-load levels' drift and offset free) measure it: when that χ² (three or more
    braking levels) exceeds its ``SCATTER_LEVEL`` quantile,
    every window of that speed has its errors (both currents) multiplied by the Birge
    ratio √(χ²/ν), ν = windows − fitted parameters their degrees of freedom. Below the quantile (a straight
    line within the errors, ~99 % of plain runs) nothing changes.

    Parameters
    ----------
    windows : the steady windows of a bench trace, any speeds.

    Returns
    -------
    list of SteadyWindow
        Same order; widened where a speed's levels scatter.

    References
    ----------
    R. T. Birge, "The calculation of errors by the method of least squares", Phys. Rev.
    40 (1932) 207; T. Yukawa et al., "Estimation of gear efficiency in reduction gears",
    eq. 18 (the levels' straight line).

    Examples
    --------
    >>> with_level_scatter(ws)   # doctest: +SKIP
    """
    from dataclasses import replace

    from scipy import stats

    out = list(windows)
    done = set()
    for w in windows:
        if w.in_command in done:
            continue
        done.add(w.in_command)
        idx = [k for k, v in enumerate(windows) if _same_speed(v, w)]
        fit = staircase_fit([windows[k] for k in idx])
        if fit is None or fit["chi2_dof"] < 1 or fit["chi2"] <= stats.chi2.ppf(SCATTER_LEVEL, fit["chi2_dof"]):
            continue
        chi2, dof = fit["chi2"], fit["chi2_dof"]
        r = float(np.sqrt(chi2 / dof))
        for k in idx:
            v = windows[k]
            out[k] = replace(v, current_in_sem=v.current_in_sem * r, current_out_sem=v.current_out_sem * r,
                             current_in_dof=float(min(v.current_in_dof, dof)),
                             current_out_dof=float(min(v.current_out_dof, dof)))
    return out


# A zero-load level further than this many standard errors off the braking levels' line
# is not on the one-way branch of eq. 18 (two-sided, ~0.3 % false alarms on a straight line)
OFF_LINE_SIGMAS = 3.0


def staircase_fit(windows: list[SteadyWindow], *, zero_load_on_line: bool = False) -> dict | None:
    """One speed's staircase as a straight line with the zero-load level allowed off it:
    weighted least squares of the window means

        i_in = a + b·i_out + d·(t − t̄) + δ·[zero load]

    (``d`` only with two or more zero-load levels: the drift they measure; ``δ`` only
    with a zero-load level and two or more braking levels, and not with
    ``zero_load_on_line``: the zero-load level then anchors the line as a braking level does). Errors in i_out enter as
    ``slope_fit`` does (effective variance σ² = σ_in² + b² σ_out², two passes).

    Eq. 18 differentiates T_in = T_out/(n η) + drag, which holds while power flows from
    input to output. At zero load the mesh carries only the output motor's friction; where
    that is smaller than the torque ripple passing the mesh (cogging of either motor, the
    speed loop's correction), the mesh's power flow reverses within each ripple period and
    the backward part passes with 1/η instead of η: the zero-load currents leave the line
    the braking levels lie on, and a secant from them is off by δ/Δi_in (seed 1 case 45
    of the robustness benchmark: output Tc 0, cogging 2 mN m, δ 27 standard errors,
    +1.8 pp at 50 % load; this slope b: −0.01 pp). A braking level is far onto the
    one-way branch, so b (δ free) is eq. 18 there.

    Parameters
    ----------
    windows : one speed's steady windows (zero-load and braking).

    Returns
    -------
    dict or None
        ``slope`` b and ``slope_sem``, ``offset`` δ and ``off_line_sigmas`` |δ|/σ_δ (0
        without δ), both errors times the Birge ratio √(χ²/ν) where it exceeds 1 (the
        levels scatter beyond their window errors: seed 9 case 50, δ 4.0 σ from a wobbling
        level, not from the zero-load level), ``chi2`` of the residuals and its
        ``chi2_dof`` ν (windows − parameters),
        ``dof`` the smallest window dof (each mean's error is known from its own blocks);
        None when fewer than two braking levels.

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", eq. 18;
    J. R. Taylor, *An Introduction to Error Analysis*, 2nd ed., sec. 8.4 (errors in both
    variables, effective variance).

    Examples
    --------
    >>> staircase_fit(ws)["slope"]   # doctest: +SKIP
    """
    refs = [w for w in windows if w.is_reference]
    loaded = [w for w in windows if not w.is_reference]
    if len(loaded) < 2:
        return None
    ws = loaded + refs
    x = np.array([w.current_out_a for w in ws])
    y = np.array([w.current_in_a for w in ws])
    sy = np.array([w.current_in_sem for w in ws])
    sx = np.array([w.current_out_sem for w in ws])
    t = np.array([w.t_mid_s for w in ws])
    cols = [np.ones_like(x), x]
    if len(refs) >= 2 and np.ptp([r.t_mid_s for r in refs]) > 0:
        cols.append(t - t.mean())
    if refs and not zero_load_on_line:
        cols.append(np.array([0.0] * len(loaded) + [1.0] * len(refs)))
    X = np.column_stack(cols)
    b = 0.0
    for _ in range(2):
        var = np.maximum(sy ** 2 + (b * sx) ** 2, 1e-24)     # 1 pA floor: noise-free traces
        xtw = X.T / var
        try:
            cov = np.linalg.inv(xtw @ X)
        except np.linalg.LinAlgError:
            return None
        beta = cov @ (xtw @ y)
        b = float(beta[1])
    chi2 = float(np.sum((y - X @ beta) ** 2 / var))
    nu = len(ws) - X.shape[1]
    # levels scattering more than their errors say (a disturbance slower than the windows'
    # blocks) scatter δ and b as much: their errors take the Birge ratio when it exceeds 1
    birge = max(1.0, float(np.sqrt(chi2 / nu))) if nu >= 1 else 1.0
    sd = birge * np.sqrt(np.maximum(np.diag(cov), 0.0))
    off = abs(beta[-1]) / sd[-1] if refs and not zero_load_on_line and sd[-1] > 0 else 0.0
    dof = min(min(w.current_in_dof for w in ws), min(w.current_out_dof for w in ws))
    return {"slope": b, "slope_sem": float(sd[1]),
            "offset": float(beta[-1]) if refs and not zero_load_on_line else 0.0,
            "off_line_sigmas": float(off),
            "chi2": chi2, "chi2_dof": nu, "dof": float(dof)}


def incremental_slope(windows: list[SteadyWindow]) -> tuple[float, float, float]:
    """Eq. 18 as a slope: weighted straight line of the input current's window means on
    the output current's over one speed's levels (zero load included); the reducer's
    no-load loss is the intercept. Returns (slope dI_in/dI_out, its standard error, dof:
    the windows' errors pooled as the slope pools them, ``streaming.slope_dof``).

    Parameters
    ----------
    windows : one speed's steady windows.

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md), eq. 18 as a regression slope

    Examples
    --------
    >>> incremental_slope(ws)   # doctest: +SKIP

    """

    x = np.array([w.current_out_a for w in windows])
    y = np.array([w.current_in_a for w in windows])
    sy = np.array([w.current_in_sem for w in windows])
    sx = np.array([w.current_out_sem for w in windows])
    _, b, sb = slope_fit(x, y, sy, sx)
    dof = slope_dof(x, np.hypot(sy, b * sx) if np.isfinite(b) else sy,
                    [min(w.current_in_dof, w.current_out_dof) for w in windows])
    return b, sb, float(dof)


def _with_slope(p: EfficiencyPoint, same_speed: list[SteadyWindow], m_in, m_out, n_signed,
                n_rel_std, source) -> EfficiencyPoint:
    """``p`` with its incremental efficiency from the speed's slope, η = −K_out/(n_s K_in b):
    variance = the slope's + the Kt ratio's (shared-disk covariance included) + the ratio's."""
    if len(same_speed) < 2:
        raise TraceError(f"{source}: one level at in_command = {p.window.in_command:g}; a slope "
                         f"needs the zero-load level and at least one braking level")
    b, sb, dof_b = incremental_slope(same_speed)
    return _slope_point(p, b, sb, dof_b, m_in, m_out, n_signed, n_rel_std, source)


def _slope_point(p: EfficiencyPoint, b, sb, dof_b, m_in, m_out, n_signed, n_rel_std,
                 source) -> EfficiencyPoint:
    """``p`` with eq. 18 from a slope b = dI_in/dI_out of its speed's staircase."""
    from dataclasses import replace

    # η > 0: the input current rises with braking, whichever way the reducer turns
    eta = -m_out.Kt / (n_signed * m_in.Kt * b) if b else float("nan")
    if not (np.isfinite(eta) and eta > 0):
        raise ExcitationError(f"{source}: input current does not rise with braking at in_command = "
                              f"{p.window.in_command:g} (slope {b:.4g}); check the current signs")
    rel_b = (sb / b) ** 2
    rel_k = ((m_in.Kt_std / m_in.Kt) ** 2 + (m_out.Kt_std / m_out.Kt) ** 2
             - 2 * shared_disk_covariance(m_in, m_out) / (m_in.Kt * m_out.Kt) + n_rel_std ** 2)
    parts = [abs(eta) ** 2 * rel_b, abs(eta) ** 2 * max(rel_k, 0.0)]
    std = float(np.sqrt(sum(parts)))
    dof = effective_dof(parts, [dof_b, min(m_in.Kt_dof, m_out.Kt_dof)])
    return replace(p, eta_incremental=float(eta), eta_incremental_ci95=interval(eta, std, dof),
                   eta_incremental_std=std, eta_incremental_dof=float(dof), incremental_method="slope",
                   eta_incremental_secant=p.eta_incremental,
                   eta_incremental_secant_ci95=p.eta_incremental_ci95)


def _reference(w: SteadyWindow, refs: list[SteadyWindow], source: str):
    """Zero-load currents for window ``w``: linear in time between the nearest reference
    windows before and after at the same speed command, else the nearest one.
    Returns (i_in, sem_in, dof_in, i_out, sem_out, dof_out)."""
    same = [r for r in refs if np.isclose(r.in_command, w.in_command, rtol=1e-6, atol=1e-9)]
    if not same:
        raise TraceError(f"{source}: no zero-load level at in_command = {w.in_command:g}; "
                         f"record one (out_command = 0) at that speed")
    before = [r for r in same if r.t_mid_s < w.t_mid_s]
    after = [r for r in same if r.t_mid_s > w.t_mid_s]
    if before and after:
        a, b = before[-1], after[0]
        f = (w.t_mid_s - a.t_mid_s) / (b.t_mid_s - a.t_mid_s)
        cin = (1 - f) * a.current_in_a + f * b.current_in_a
        cout = (1 - f) * a.current_out_a + f * b.current_out_a
        vin = [((1 - f) * a.current_in_sem) ** 2, (f * b.current_in_sem) ** 2]
        vout = [((1 - f) * a.current_out_sem) ** 2, (f * b.current_out_sem) ** 2]
        return (cin, float(np.sqrt(sum(vin))), effective_dof(vin, [a.current_in_dof, b.current_in_dof]),
                cout, float(np.sqrt(sum(vout))), effective_dof(vout, [a.current_out_dof, b.current_out_dof]))
    r = before[-1] if before else after[0]
    return (r.current_in_a, r.current_in_sem, r.current_in_dof,
            r.current_out_a, r.current_out_sem, r.current_out_dof)


def _point(w, ref, m_in, m_out, n_signed, n_rel_std, source) -> EfficiencyPoint:
    ref_in, ref_in_sem, ref_in_dof, ref_out, ref_out_sem, ref_out_dof = ref
    di_in, di_out = w.current_in_a - ref_in, w.current_out_a - ref_out
    if di_in * np.sign(w.speed_in_rad_s or 1.0) <= 0:
        raise ExcitationError(
            f"{source}: input current does not rise under load at out_command = "
            f"{w.out_command:g} (Δi_in = {di_in:.4g} A); check that out_command brakes "
            f"(negative for forward rotation) and the current signs")

    def etas(v):
        (i_in, i_ref_in, i_out, i_ref_out, kt_in, kt_out, n, d_in, tc_in, d_out, tc_out) = v
        mi = MotorCalibration(kt_in, (kt_in, kt_in), m_in.J, d_in, tc_in, "")
        mo = MotorCalibration(kt_out, (kt_out, kt_out), m_out.J, d_out, tc_out, "")
        inc = incremental_efficiency(kt_in, kt_out, i_in - i_ref_in, i_out - i_ref_out, n)
        ab = absolute_efficiency(i_in, i_out, w.speed_in_rad_s, w.speed_out_rad_s, mi, mo)
        return np.array([inc, ab])

    v0 = np.array([w.current_in_a, ref_in, w.current_out_a, ref_out, m_in.Kt, m_out.Kt,
                   n_signed, m_in.D, m_in.Tc, m_out.D, m_out.Tc])
    cov = np.zeros((11, 11))
    sd = [w.current_in_sem, ref_in_sem, w.current_out_sem, ref_out_sem, m_in.Kt_std,
          m_out.Kt_std, abs(n_signed) * n_rel_std]
    cov[np.arange(7), np.arange(7)] = np.square(sd)
    # both motors calibrated with the same disk share its error: Kt_in and Kt_out move
    # together, so it cancels in the incremental η (∝ Kt_out/Kt_in) and partly in P_out/P_in
    cov[4, 5] = cov[5, 4] = shared_disk_covariance(m_in, m_out)
    cov[7:9, 7:9] = np.asarray(m_in.loss_covariance)
    cov[9:11, 9:11] = np.asarray(m_out.loss_covariance)
    # First-order propagation with a numerical Jacobian (central differences).
    jac = np.zeros((2, 11))
    for k in range(11):
        h = 1e-6 * max(abs(v0[k]), 1e-6)
        vp, vm = v0.copy(), v0.copy()
        vp[k] += h
        vm[k] -= h
        jac[:, k] = (etas(vp) - etas(vm)) / (2 * h)
    eta = etas(v0)
    std = np.sqrt(np.maximum(np.diag(jac @ cov @ jac.T), 0.0))
    # Welch–Satterthwaite over independent input groups: the four window means, the two
    # Kt (one group: they may share the disk), the ratio (type B, known) and each motor's
    # (D, Tc) block (from the same calibration as its Kt)
    groups = ((0,), (1,), (2,), (3,), (4, 5), (6,), (7, 8), (9, 10))
    dofs = (w.current_in_dof, ref_in_dof, w.current_out_dof, ref_out_dof,
            min(m_in.Kt_dof, m_out.Kt_dof), DOF_MAX, m_in.Kt_dof, m_out.Kt_dof)
    dof = []
    for row in jac:
        parts = [max(float(row[list(g)] @ cov[np.ix_(g, g)] @ row[list(g)]), 0.0) for g in groups]
        dof.append(effective_dof(parts, dofs))
    t_in, t_out, p_in, p_out = shaft_powers(w.current_in_a, w.current_out_a, w.speed_in_rad_s,
                                            w.speed_out_rad_s, m_in, m_out)
    r_in, r_out = loss_speed_range(m_in), loss_speed_range(m_out)
    extrapolated = (is_extrapolated(w.speed_in_rad_s, r_in)
                    or is_extrapolated(w.speed_out_rad_s, r_out))
    return EfficiencyPoint(
        w, w.speed_in_rad_s, t_in * np.sign(w.speed_in_rad_s), t_out * np.sign(w.speed_out_rad_s),
        di_in, di_out,
        float(eta[0]), interval(eta[0], std[0], dof[0]),
        float(eta[1]), interval(eta[1], std[1], dof[1]),
        p_in, p_out, bool(extrapolated), r_in, r_out,
        float(std[0]), float(dof[0]), float(std[1]), float(dof[1]))


def above_one(point: dict) -> str | None:
    """A point (result.json ``efficiency`` entry) whose incremental or absolute efficiency
    lies above 1 beyond its 95 % interval (the interval's low end above 1): power out of
    a reducer cannot exceed power in, so one of the numbers it is built of is wrong (most
    often a motor's Kt, eq. 18 is K_out/K_in times a current ratio). The message says
    which; None when both are possible.

    Examples
    --------
    >>> above_one({"eta_incremental": 0.9, "eta_incremental_ci95": [0.88, 0.92]}) is None
    True
    >>> above_one({"eta_incremental": 1.54, "eta_incremental_ci95": [1.06, 2.02]})[:45]
    'incremental efficiency 1.54 (95 %: 1.06..2.02'
    """
    out = []
    for key, label in (("eta_incremental", "incremental"), ("eta_absolute", "absolute")):
        ci = point.get(f"{key}_ci95")
        eta = point.get(key)
        if eta is None or not ci or ci[0] is None or not ci[0] > 1.0:
            continue
        out.append(f"{label} efficiency {eta:.3g} (95 %: {ci[0]:.3g}..{ci[1]:.3g}) is above 1 beyond its "
                   f"interval: impossible for a reducer, a motor's Kt or loss behind it is wrong")
    return "; ".join(out) or None
