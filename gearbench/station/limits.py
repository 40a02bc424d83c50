"""The profile's limits judged on a run's results (pure: results in, verdicts out)."""
from __future__ import annotations

import math

from .records import LimitResult


def quantity(profile, motors: dict, ratio, efficiency: list[dict], name: str):
    """The value a limit's ``quantity`` names: ``motors.<m>.<key>`` (``Kt_rel_datasheet``
    is Kt over the datasheet value), ``ratio``, or ``efficiency.<key>`` (a list, one value
    per measured point); None when the run did not measure it."""
    parts = name.split(".")
    if parts[0] == "motors" and len(parts) == 3:
        m, key = parts[1], parts[2]
        if m not in motors:
            return None
        if key == "Kt_rel_datasheet":
            return motors[m]["Kt"] / profile.motors[m].kt_datasheet
        return motors[m].get(key)
    if name == "ratio":
        return ratio
    if parts[0] == "efficiency" and len(parts) == 2:
        return [pt.get(parts[1]) for pt in efficiency]
    return None


def point_name(limit_name: str, point: dict) -> str:
    """A per-point limit's name, e.g. ``efficiency[100rad_s,0.06Nm]``."""
    return f"{limit_name}[{point['speed_in_rad_s']:.0f}rad_s,{point['torque_out_nm']:.3g}Nm]"


def check(profile, motors: dict, ratio, efficiency: list[dict]) -> list[LimitResult]:
    """Every limit of the profile (per point for efficiency quantities); a quantity the run
    did not measure, or that is not finite, fails."""
    out = []
    for lim in profile.limits:
        value = quantity(profile, motors, ratio, efficiency, lim.quantity)
        values = value if isinstance(value, list) else [value]
        for j, v in enumerate(values):
            name = point_name(lim.name, efficiency[j]) if isinstance(value, list) else lim.name
            ok = v is not None and math.isfinite(v) and lim.passed(v)
            out.append(LimitResult(name, None if v is None else float(v), lim.low, lim.high,
                                   bool(ok), lim.quantity))
    return out
