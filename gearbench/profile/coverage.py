"""Do a profile's calibration runs cover the speeds its efficiency map runs at?

A motor's losses D ω + Tc (used by the absolute efficiency) are identified only over
the speeds its calibration runs covered; outside, they are extrapolated, and with one
rotation direction D and Tc trade off against each other (``calibration``), so the
extrapolated loss can be off by far more than its interval says. ``uncovered`` names
every map point a motor would reach outside the commanded speed range of its
velocity-mode calibration (shrunk by ``MARGIN`` of its span at each end: the identified
range is the 0.5-99.5 percentile of the measured speed, a little inside the command's
extremes).
"""
from __future__ import annotations

import numpy as np

MARGIN = 0.02


def calibration_speed_range(profile, motor: str) -> tuple[float, float] | None:
    """[low, high] commanded speed (rad/s) of ``motor``'s velocity-mode calibration runs,
    shrunk by ``MARGIN``; None when it has none (current-mode or not calibrated)."""
    ranges = []
    for s in profile.steps:
        if type(s).__name__ != "CalibrateStep" or s.motor != motor or s.mode != "velocity":
            continue
        wf = profile.waveforms[s.waveform]
        dur = s.max_s if s.adaptive else s.duration_s
        t = np.arange(0.0, dur, profile.bench.period_s)
        cmd = wf.render(t)
        lo, hi = float(np.min(cmd)), float(np.max(cmd))
        ranges.append((lo + MARGIN * (hi - lo), hi - MARGIN * (hi - lo)))
    if not ranges:
        return None
    return min(r[0] for r in ranges), max(r[1] for r in ranges)


def ratio_range(profile) -> tuple[float, float] | None:
    """The reduction ratio the map runs at: the reducer's, else the ``ratio`` limit's
    bounds (a measured ratio), else the simulation's; None when unknown."""
    r = profile.reducer
    if r is None:
        return None
    if r.ratio is not None:
        return (abs(r.ratio), abs(r.ratio))
    for lim in profile.limits:
        if lim.quantity == "ratio" and lim.low is not None and lim.high is not None:
            return (abs(lim.low), abs(lim.high))
    sim = profile.simulation or {}
    if "ratio" in sim:
        return (abs(float(sim["ratio"])),) * 2
    return None


def map_speed_range(profile, motor: str) -> tuple[float, float] | None:
    """[low, high] |speed| (rad/s) ``motor`` turns at over the profile's efficiency map:
    the input speeds for ``in``, over the reduction ratio (``ratio_range``) for ``out``;
    None without a map, or for ``out`` when the ratio is unknown. What its calibration
    must sweep so that no motor loss is extrapolated (the excitation design's cover)."""
    speeds = [abs(v) for s in profile.steps if type(s).__name__ == "EfficiencyStep"
              for v in s.speeds_in_rad_s]
    if not speeds:
        return None
    if motor == "in":
        return min(speeds), max(speeds)
    ratio = ratio_range(profile)
    if ratio is None:
        return None
    return min(speeds) / ratio[1], max(speeds) / ratio[0]


def uncovered(profile) -> list[str]:
    """One message per map point a motor reaches outside its calibration's speed range."""
    out = []
    ratio = ratio_range(profile)
    for s in profile.steps:
        if type(s).__name__ != "EfficiencyStep":
            continue
        for motor in ("in", "out"):
            cal = calibration_speed_range(profile, motor)
            if cal is None or motor not in profile.motors:
                continue
            for speed in s.speeds_in_rad_s:
                if motor == "in":
                    need = (abs(speed), abs(speed))
                elif ratio is None:
                    continue
                else:
                    need = (abs(speed) / ratio[1], abs(speed) / ratio[0])
                # the output may turn either way: covered on either side of zero
                ok = any(cal[0] <= sg * need[0] <= cal[1] and cal[0] <= sg * need[1] <= cal[1]
                         for sg in (1.0, -1.0))
                if not ok:
                    at = (f"{need[0]:.4g}" if need[0] == need[1] else f"{need[0]:.4g}..{need[1]:.4g}")
                    out.append(f"map point {s.name} at input {speed:g} rad/s: motor {motor} runs at "
                               f"{at} rad/s, outside its calibration's speeds {cal[0]:.4g}..{cal[1]:.4g} "
                               f"rad/s; its friction would be extrapolated and the point flagged 'extrapolated "
                               f"motor loss' (absolute efficiency only): widen the calibration waveform's "
                               f"speed range to cover it (docs/profile-authoring.md, \"Calibration "
                               f"covering the map\")")
    return out
