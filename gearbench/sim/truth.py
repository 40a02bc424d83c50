"""Known truth of the simulated bench in steady state: what eq. 18 should recover and
the absolute efficiency P_out/P_in at the reducer's shafts.

Steady state, forward rotation (ω_in > 0), input motor in velocity mode, output motor
braking (negative current). Torques at the reducer shafts:

    T_out = K_out,eff·|i_out| + f_out(ω_out)        (braking + output motor's own friction)
    T_in  = T_out / (n·η(ω_in)) + drag(ω_in)         (mesh efficiency in the power-flow direction)

Incremental efficiency (paper eq. 18, reference = zero-load level at the same speed):
dT_in = dT_out/(n·η) so η_inc = η(ω_in): ``eta_mesh`` for the plain reducer, the CVT's
η at the operating input speed. Absolute efficiency: P_out/P_in = T_out·ω_out/(T_in·ω_in),
drag included (lower at light load).

CVT: averaged over whole pulsation cycles, the inertial term r·r'·J_out·ω² has zero
mean (r·r' = d(r²/2)/dθ) and the simulator applies η in the direction of the
quasi-static power flow, so eq. 18 recovers exactly η(ω_in) (checked in
tests/test_sim.py to 2e-4). The one term left out of the mean powers is the output
motor's viscous loss on the pulsating speed, D_out·(ω_in/n)·a²/2 — about 1e-8 N m
for the shipped CVT, far below any measurable difference.
"""
from __future__ import annotations

import math

from ..errors import ProfileError
from .params import MotorParams, PlantParams


def motor_friction_nm(m: MotorParams, speed_rad_s: float) -> float:
    """Friction torque (Coulomb + Stribeck, smoothed sign, + viscous) at a speed."""
    w = speed_rad_s
    s = m.Tc + (m.Ts * math.exp(-(w / m.ws) ** 2) if m.Ts > 0 else 0.0)
    return s * math.tanh(w / m.friction_eps_rad_s) + m.D * w


def drag_nm(plant: PlantParams, speed_in_rad_s: float) -> float:
    """Reducer drag at the input shaft (Coulomb, smoothed sign, + viscous)."""
    w = speed_in_rad_s
    return (plant.drag_torque_nm * math.tanh(w / plant.motor_in.friction_eps_rad_s)
            + plant.drag_viscous * w)


def motor_torque_nm(m: MotorParams, current_a: float) -> float:
    """Mean electromagnetic torque Kt_eff(i)·i (ripple and cogging average to zero)."""
    kt = m.Kt / (1 + (current_a / m.kt_sat_a) ** 2) if m.kt_sat_a > 0 else m.Kt
    return kt * current_a


def current_for_torque_a(m: MotorParams, torque_nm: float) -> float:
    """Invert ``motor_torque_nm`` (the smaller root when Kt saturates)."""
    if m.kt_sat_a <= 0 or torque_nm == 0:
        return torque_nm / m.Kt
    a = torque_nm / m.kt_sat_a ** 2
    disc = m.Kt ** 2 - 4 * a * torque_nm
    if disc < 0:
        raise ProfileError(f"torque {torque_nm:.4g} N m exceeds what the saturating Kt can give "
                           f"({m.Kt * m.kt_sat_a / 2:.4g} N m)")
    return (m.Kt - math.sqrt(disc)) / (2 * a)


def efficiency_truth(plant: PlantParams, speed_in_rad_s: float, torque_out_nm: float) -> dict:
    """Steady-state efficiency truth at input speed ``speed_in_rad_s`` (> 0) with a
    braking torque of magnitude ``torque_out_nm`` at the reducer's output shaft.

    Returns ``eta_incremental`` (what eq. 18 recovers: η(ω_in)), ``eta_absolute``
    (P_out/P_in at the reducer shafts, drag included), plus ``eta_mesh``,
    ``torque_in_nm``, ``torque_out_nm``, ``speed_out_rad_s``, ``power_in_w``,
    ``power_out_w``, ``drag_torque_nm``.
    """
    if not speed_in_rad_s > 0:
        raise ProfileError(f"efficiency_truth: speed_in_rad_s must be > 0 (got {speed_in_rad_s})")
    if not torque_out_nm >= 0:
        raise ProfileError(f"efficiency_truth: torque_out_nm is a braking magnitude, must be >= 0 "
                           f"(got {torque_out_nm})")
    n = plant.ratio
    eta = plant.mesh_efficiency(speed_in_rad_s)
    drag = drag_nm(plant, speed_in_rad_s)
    torque_in = torque_out_nm / (n * eta) + drag
    speed_out = speed_in_rad_s / n
    p_in = torque_in * speed_in_rad_s
    p_out = torque_out_nm * speed_out
    return {"eta_incremental": eta, "eta_absolute": p_out / p_in, "eta_mesh": eta,
            "torque_in_nm": torque_in, "torque_out_nm": torque_out_nm,
            "speed_out_rad_s": speed_out, "power_in_w": p_in, "power_out_w": p_out,
            "drag_torque_nm": drag}


def bench_operating_point(plant: PlantParams, speed_in_rad_s: float, out_current_a: float) -> dict:
    """Expected steady state for an output braking current (``out_current_a`` <= 0):
    ``efficiency_truth`` at the resulting output-shaft torque, plus the true steady
    currents ``current_in_a``/``current_out_a`` and their mean measured values
    (sensor gain and offset applied) ``measured_in_a``/``measured_out_a``."""
    if out_current_a > 0:
        raise ProfileError("bench_operating_point: out_current_a must be <= 0 (braking)")
    n = plant.ratio
    mo, mi = plant.motor_out, plant.motor_in
    speed_out = speed_in_rad_s / n
    torque_out = -motor_torque_nm(mo, out_current_a) + motor_friction_nm(mo, speed_out)
    res = efficiency_truth(plant, speed_in_rad_s, torque_out)
    i_in = current_for_torque_a(mi, res["torque_in_nm"] + motor_friction_nm(mi, speed_in_rad_s))
    res.update(current_in_a=i_in, current_out_a=out_current_a,
               measured_in_a=mi.current_gain * i_in + mi.current_offset_a,
               measured_out_a=mo.current_gain * out_current_a + mo.current_offset_a)
    return res


def simulation_truth(plant: PlantParams | dict, points: list[dict]) -> dict:
    """The simulated plant's truth in the shape of result.json: ``motors`` (Kt, J, D, Tc),
    ``ratio`` and one ``efficiency`` entry per measured point.

    Each point's truth is the plant's steady state at the point's *commanded* operating
    point — input speed setpoint ``in_command`` and output braking-current command
    ``out_command`` (``bench_operating_point``) — never at a measured or estimated
    quantity, so the truth cannot move with the estimate. (The drive rounds the current
    command to its resolution, 0.1 % of rated current for CiA 402; that is below 1e-4
    of η here.)"""
    if not isinstance(plant, PlantParams):
        plant = PlantParams.from_dict(plant, "simulation")
    truth = plant.truth()
    eff = []
    for pt in points:
        speed, current = float(pt["in_command"]), float(pt["out_command"])
        op = bench_operating_point(plant, abs(speed), -abs(current))
        eff.append({"speed_in_rad_s": speed, "out_command": current,
                    "torque_out_nm": op["torque_out_nm"], "eta_incremental": op["eta_incremental"],
                    "eta_absolute": op["eta_absolute"], "torque_in_nm": op["torque_in_nm"],
                    "current_in_a": op["current_in_a"]})
    return {"motors": truth["motors"], "ratio": truth["ratio"], "efficiency": eff}


def truth_of(plant):
    """The sequencer's hook for a simulated run: efficiency points → ``simulation_truth``
    of ``plant`` at the same commanded points (None for a real bench)."""
    if plant is None:
        return None
    return lambda efficiency: simulation_truth(plant, efficiency)
