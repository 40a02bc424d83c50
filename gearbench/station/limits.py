"""The profile's limits judged on a run's results (pure: results in, verdicts out)."""
from __future__ import annotations

import math

from ..analysis.calibration import motor_value
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
        return motor_value(motors[m], key)
    if name == "ratio":
        return ratio
    if parts[0] == "efficiency" and len(parts) == 2:
        return [pt.get(parts[1]) for pt in efficiency]
    return None


def commanded_points(profile, efficiency: list[dict]) -> list[tuple[float, float]]:
    """Each measured point's commanded operating point (input speed rad/s, braking torque
    N m) as the profile states it: the speed set point the station recorded, and the
    profile torque level of that speed by rank of the braking current (the levels run in
    the profile's order; the current is the torque less the output motor's friction, so
    it is not the torque over Kt). Where a speed lost a point, the level nearest the
    measured torque. Stable from run to run: what a factory system keys on."""
    levels = sorted({float(t) for s in profile.steps for t in getattr(s, "torques_out_nm", ())})
    speeds = [float(p.get("speed_setpoint_rad_s") if p.get("speed_setpoint_rad_s") is not None
                    else p.get("speed_in_rad_s", math.nan)) for p in efficiency]
    out = [(s, float(p.get("torque_out_nm", math.nan))) for s, p in zip(speeds, efficiency)]
    if not levels:
        return out
    for s in set(speeds):
        idx = [j for j, x in enumerate(speeds) if x == s]
        if len(idx) == len(levels):
            ranked = sorted(idx, key=lambda j: abs(float(efficiency[j].get("out_command") or 0.0)))
            for j, t in zip(ranked, levels):
                out[j] = (s, t)
        else:
            for j in idx:
                measured = float(efficiency[j].get("torque_out_nm", math.nan))
                out[j] = (s, min(levels, key=lambda t: abs(t - measured) if math.isfinite(measured) else 0))
    return out


def point_tag(speed_rad_s: float, torque_nm: float) -> str:
    """A commanded point's name, e.g. ``100rad_s,0.06Nm`` (the profile's numbers, ``:g``)."""
    return f"{speed_rad_s:g}rad_s,{torque_nm:g}Nm"


def point_name(limit_name: str, point: dict) -> str:
    """A per-point limit's name from the commanded point, e.g. ``efficiency[100rad_s,0.06Nm]``
    (``point`` carries ``speed_setpoint_rad_s`` and ``torque_setpoint_nm``; without them,
    as an older result.json, the measured values rounded)."""
    speed = point.get("speed_setpoint_rad_s")
    torque = point.get("torque_setpoint_nm")
    if speed is None or torque is None:
        return f"{limit_name}[{point['speed_in_rad_s']:.0f}rad_s,{point['torque_out_nm']:.3g}Nm]"
    return f"{limit_name}[{point_tag(speed, torque)}]"


def with_setpoints(profile, efficiency: list[dict]) -> list[dict]:
    """The efficiency entries with ``torque_setpoint_nm`` (and ``speed_setpoint_rad_s``)
    filled in from the profile (``commanded_points``)."""
    return [{**p, "speed_setpoint_rad_s": s, "torque_setpoint_nm": t}
            for p, (s, t) in zip(efficiency, commanded_points(profile, efficiency))]


def check(profile, motors: dict, ratio, efficiency: list[dict]) -> list[LimitResult]:
    """Every limit of the profile (per point for efficiency quantities); a quantity the run
    did not measure, or that is not finite, fails."""
    out = []
    efficiency = with_setpoints(profile, efficiency)
    for lim in profile.limits:
        value = quantity(profile, motors, ratio, efficiency, lim.quantity)
        values = value if isinstance(value, list) else [value]
        for j, v in enumerate(values):
            name = point_name(lim.name, efficiency[j]) if isinstance(value, list) else lim.name
            ok = v is not None and math.isfinite(v) and lim.passed(v)
            out.append(LimitResult(name, None if v is None else float(v), lim.low, lim.high,
                                   bool(ok), lim.quantity))
    return out
