"""Does each motor's calibration cover the speeds it turns at in the efficiency map?

The absolute efficiency subtracts each motor's friction D ω + Tc, identified from its
calibration runs; at a speed outside those runs it is extrapolated, and the point is
flagged ``loss_extrapolated`` (docs/profile-authoring.md, "Calibration covering the map").
Pure: a profile in, sentences out.
"""
from __future__ import annotations

import numpy as np

from .model import CalibrateStep, EfficiencyStep


def map_speeds(profile) -> dict[str, float]:
    """The highest speed each motor turns at in the map (rad/s): the input's is the
    highest input speed; the output's that over the ratio (unknown when it is measured)."""
    speeds = [w for s in profile.steps if isinstance(s, EfficiencyStep) for w in s.speeds_in_rad_s]
    if not speeds:
        return {}
    out = {"in": max(speeds)}
    ratio = profile.reducer.ratio if profile.reducer else None
    if ratio:
        out["out"] = max(speeds) / abs(ratio)
    return out


def calibration_speeds(profile) -> dict[str, float]:
    """The highest speed each motor's velocity-mode calibration waveform reaches (rad/s)."""
    out: dict[str, float] = {}
    for s in profile.steps:
        if not isinstance(s, CalibrateStep) or s.mode != "velocity":
            continue
        duration = s.max_s if s.adaptive else s.duration_s
        t = np.arange(0.0, duration, profile.bench.period_s)
        peak = float(np.max(np.abs(profile.waveforms[s.waveform].render(t)))) if t.size else 0.0
        out[s.motor] = max(out.get(s.motor, 0.0), peak)
    return out


def coverage_warnings(profile) -> list[str]:
    """One sentence per motor whose map speed is above its calibration waveform's."""
    cal, need = calibration_speeds(profile), map_speeds(profile)
    warnings = []
    for m, speed in need.items():
        if m in cal and speed > cal[m] * 1.001:
            warnings.append(
                f"motor {m} turns at up to {speed:.4g} rad/s in the efficiency map but its calibration "
                f"waveform reaches only {cal[m]:.4g} rad/s: its friction will be extrapolated there and "
                f"those points flagged 'extrapolated motor loss' (absolute efficiency only); raise the "
                f"waveform's offset/amplitude (docs/profile-authoring.md, \"Calibration covering the map\")")
    return warnings
