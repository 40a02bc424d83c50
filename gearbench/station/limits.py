"""The profile's limits judged on a run's results (pure: results in, verdicts out)."""
from __future__ import annotations

import math

from ..analysis.calibration import motor_value
from ..analysis.efficiency import above_one
from ..analysis.model_check import kt_not_constant
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
    did not measure, or that is not finite, fails. So does one the model checks reject
    (``model_checks``): a limit on a motor whose Kt is not constant over its calibration's
    currents, an efficiency limit where either motor's is not or where the point's
    efficiency is above 1 beyond its interval; each failing check adds its own verdict."""
    out = []
    efficiency = with_setpoints(profile, efficiency)
    bad_kt = {m: msg for m, r in motors.items() if (msg := kt_not_constant(r))}
    for lim in profile.limits:
        value = quantity(profile, motors, ratio, efficiency, lim.quantity)
        values = value if isinstance(value, list) else [value]
        for j, v in enumerate(values):
            name = point_name(lim.name, efficiency[j]) if isinstance(value, list) else lim.name
            ok = v is not None and math.isfinite(v) and lim.passed(v)
            reason = _rejected(lim.quantity, bad_kt, efficiency[j] if isinstance(value, list) else None)
            out.append(LimitResult(name, None if v is None else float(v), lim.low, lim.high,
                                   bool(ok and not reason), lim.quantity, reason))
    return out + model_checks(motors, efficiency)


def _rejected(quantity_name: str, bad_kt: dict, point: dict | None) -> str:
    """Why a limit's value is no result (a model check), or ""."""
    parts = quantity_name.split(".")
    if parts[0] == "motors" and len(parts) == 3:
        return bad_kt.get(parts[1], "")
    if parts[0] == "efficiency":
        # eq. 18 is K_out/K_in times a current ratio: either Kt's message is its own verdict's
        why = [f"motor {m}'s Kt is not constant over current (kt_constant[{m}])" for m in bad_kt]
        why += [above_one(point)] if point is not None and above_one(point) else []
        return "; ".join(why)
    return ""


def model_checks(motors: dict, efficiency: list[dict]) -> list[LimitResult]:
    """A failing verdict for each model check a result fails, whatever the profile's limits:
    ``kt_constant[<motor>]`` (Kt not constant over the calibration's currents, value Kt's
    shift from its small-current value, ``analysis.model_check.kt_linearity``) and
    ``efficiency_at_most_1[<point>]`` (``analysis.efficiency.above_one``, value the
    efficiency). A result these reject is never reported without a verdict against it."""
    out = []
    for m, r in motors.items():
        msg = kt_not_constant(r)
        if msg:
            shift = ((r.get("fit") or {}).get("kt_linearity") or {}).get("kt_shift_rel")
            out.append(LimitResult(f"kt_constant[{m}]", shift, None, None, False,
                                   f"motors.{m}.kt_linearity", msg))
    for p in efficiency:
        msg = above_one(p)
        if msg:
            key = "eta_incremental" if msg.startswith("incremental") else "eta_absolute"
            out.append(LimitResult(point_name("efficiency_at_most_1", p), p.get(key), None, 1.0,
                                   False, f"efficiency.{key}", msg))
    return out
