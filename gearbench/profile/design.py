"""``design: optimal`` multisines: their parameters from the motors they calibrate.

The profile loader calls ``design_waveform`` once per designed waveform with every
calibrate step that uses it; the design (``gearbench.profile.excitation_design``)
keeps each of those motors (with its disk) inside its limits and minimises the worst
predicted Kt variance per bench second. The rule is in docs/excitation-design.md.
"""
from __future__ import annotations

from .waveforms import DESIGNED_KEYS
from .excitation_design import MotorCase
from .excitation_design import COVER_MARGIN, design_multisine

DEFAULT_MIN_SPEED_SHARE = 0.10   # of speed_limit_rad_s: clear of stick/Stribeck and low-order cogging
DEFAULT_MAX_SPEED_SHARE = 0.90   # of speed_limit_rad_s: headroom for the speed loop's overshoot
DEFAULT_FRICTION_SHARE = 0.10    # of kt_datasheet x rated_current_a: expected no-load torque


class DesignProblem(ValueError):
    """A designed waveform cannot be made: ``path`` (profile keys), problem and fix."""

    def __init__(self, path: tuple, problem: str, fix: str):
        super().__init__(problem)
        self.path, self.problem, self.fix = path, problem, fix


def motor_case(motor, disk, params: dict):
    """``MotorCase`` for ``motor`` (MotorSpec) with ``disk`` (DiskSpec) under the design
    knobs in ``params`` (a multisine's parameters, defaults filled in)."""
    if motor.rotor_inertia_kgm2 is None:
        raise DesignProblem(("motors", motor.name), "design: optimal needs the rotor inertia",
                            f"add 'rotor_inertia_kgm2:' to motors.{motor.name} (datasheet value)")
    limit = motor.speed_limit_rad_s
    lo = params.get("min_speed_rad_s") or DEFAULT_MIN_SPEED_SHARE * limit
    hi = params.get("max_speed_rad_s") or DEFAULT_MAX_SPEED_SHARE * limit
    if hi > limit:
        raise DesignProblem(("max_speed_rad_s",), f"({hi:g}) is above motors.{motor.name}."
                            f"speed_limit_rad_s ({limit:g})", "lower max_speed_rad_s")
    friction = params.get("friction_nm")
    if friction is None:
        friction = DEFAULT_FRICTION_SHARE * motor.kt_datasheet * motor.rated_current_a
    return MotorCase(
        kt_nm_a=motor.kt_datasheet, rotor_inertia_kgm2=motor.rotor_inertia_kgm2,
        disk_inertia_kgm2=disk.inertia_kgm2,
        peak_current_a=params["peak_current_fraction"] * motor.current_limit_a,
        rms_current_a=params["rms_current_fraction"] * motor.rated_current_a,
        min_speed_rad_s=lo, max_speed_rad_s=hi, friction_nm=friction,
        current_noise_a=params["current_noise_a"], counts_per_rev=motor.counts_per_rev,
        name=motor.name)


def design_waveform(params: dict, uses: list, period_s: float, also_fit_s=(), cover=()):
    """Designed multisine parameters for the calibrate ``uses`` = [(motor, disk, duration_s)]
    → (complete params, Design). One waveform, one command: the shortest run sets the
    whole-period grid and every motor's limits hold; the period also divides
    ``also_fit_s`` (an adaptive step's shortest stop) where it can. ``cover``: per use the
    speeds (lo, hi) its motor turns at over the efficiency map, or None: the command
    sweeps their hull, as far as it lies in the speed band (where the current limit
    allows; else the plain design, and ``validate`` names the map points left
    uncovered). Raises ``DesignProblem``."""
    cases = [motor_case(m, d, params) for m, d, _ in uses]
    durations = sorted({round(dur, 9) for _, _, dur in uses})
    duration = durations[0]
    kw = dict(duration_s=duration, period_s=period_s, max_tone_hz=params["max_tone_hz"],
              min_fade_s=params.get("fade_in_s") or 0.2,
              also_fit_s=tuple(durations[1:]) + tuple(also_fit_s))
    design = None
    hull = [c for c in cover if c is not None]
    if hull and cases:
        w_lo = max(c.min_speed_rad_s for c in cases)
        w_hi = min(c.max_speed_rad_s for c in cases)
        # inside the band by twice the sweep's cover margin: a cover at the band's very edge
        # leaves the sweep no room to pass it
        edge = 2 * COVER_MARGIN * (w_hi - w_lo)
        lo = min(max(min(c[0] for c in hull), w_lo + edge), w_hi - edge)
        hi = max(min(max(c[1] for c in hull), w_hi - edge), lo)
        try:
            design = design_multisine(cases, cover_rad_s=(lo, hi), **kw)
        except ValueError:
            design = None          # the plain design below; validate names what it leaves out
    try:
        design = design or design_multisine(cases, **kw)
    except ValueError as exc:
        raise DesignProblem(("design",), f"cannot design the multisine: {exc}",
                            "widen min_speed_rad_s/max_speed_rad_s, raise peak_current_fraction "
                            "or max_tone_hz, or lengthen the calibrate steps' duration_s") from None
    out = dict(params)
    out.update({k: design.params[k] for k in DESIGNED_KEYS})
    out["fade_in_s"] = design.params["fade_in_s"]
    return out, design
