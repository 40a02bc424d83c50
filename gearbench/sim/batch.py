"""Batch simulation into a ``Trace``: one motor (calibration run) or the two-motor
bench. Same kernel and noise stream as ``BenchWorld.step`` (identical numbers)."""
from __future__ import annotations

from dataclasses import asdict

import numpy as np

from ..errors import ProfileError
from ..trace import Trace
from . import kernel as K
from .params import MotorParams, PlantParams
from .world import MODES, BenchWorld


def _rows(world: BenchWorld, in_cmd: np.ndarray, out_cmd: np.ndarray) -> np.ndarray:
    """Row k = measurement at t = k·T; command[k] is applied during [t_k, t_k+1)."""
    first = world.last_row()[None, :]
    rest = world.run(in_cmd[:-1], out_cmd[:-1])
    return np.vstack([first, rest])


def _command(x, name: str) -> np.ndarray:
    arr = np.asarray(x, dtype=float)
    if arr.ndim != 1 or arr.size < 1:
        raise ProfileError(f"{name}: expected a 1-D array of setpoints")
    if not np.isfinite(arr).all():
        raise ProfileError(f"{name}: contains NaN/inf; give finite setpoints")
    return arr


def _mode(mode: str, name: str) -> str:
    if mode not in MODES or mode == "off":
        raise ProfileError(f"{name}: '{mode}' unknown; use 'velocity' or 'torque'")
    return mode


def simulate_motor(motor: MotorParams, command: np.ndarray, *, mode: str = "velocity",
                   period_s: float = 1e-3, disk_kgm2: float = 0.0, seed: int = 0,
                   include_truth: bool = False) -> Trace:
    """One motor alone (optionally with an inertia disk), its drive following ``command``
    (rad/s in velocity mode, A in torque mode), sampled every ``period_s``.

    Trace columns ``position_rad, current_a, command, velocity_rad_s`` (with
    ``include_truth`` also ``true_velocity_rad_s, true_current_a, current_cmd_a``);
    ``meta["truth"]`` = ``{"Kt", "J", "D", "Tc", "disk_inertia"}``.
    """
    cmd = _command(command, "simulate_motor: command")
    plant = PlantParams(motor_in=motor, motor_out=motor, period_s=period_s, seed=seed)
    world = BenchWorld(plant, seed=seed)
    world.mount(coupling="none", disk_kgm2={"in": disk_kgm2})
    world.set_mode("in", _mode(mode, "simulate_motor: mode"))
    rows = _rows(world, cmd, np.zeros_like(cmd))
    cols = {"position_rad": rows[:, K.M_POS_IN], "current_a": rows[:, K.M_CUR_IN],
            "command": cmd, "velocity_rad_s": rows[:, K.M_VEL_IN]}
    if include_truth:
        cols.update(true_velocity_rad_s=rows[:, K.M_W_IN], true_current_a=rows[:, K.M_I_IN],
                    current_cmd_a=rows[:, K.M_CMD_IN])
    truth = {**motor.truth(), "disk_inertia": float(disk_kgm2)}
    meta = {"truth": truth, "sim": {"mode": mode, "seed": seed, "motor": asdict(motor)}}
    return Trace(np.arange(cmd.size) * period_s, cols, meta, source="<simulate_motor>")


def simulate_bench(plant: PlantParams, in_command: np.ndarray, out_command: np.ndarray, *,
                   in_mode: str = "velocity", out_mode: str = "torque", seed: int | None = None,
                   include_truth: bool = False) -> Trace:
    """The reducer bench: input motor follows ``in_command``, output motor ``out_command``
    (per sample; rad/s in velocity mode, A in torque mode; negative out current = braking).

    Bench CSV columns ``in_position_rad, in_current_a, out_position_rad, out_current_a,
    in_command, out_command`` (with ``include_truth`` also true speeds, currents and the
    mean shaft powers ``power_in_w``/``power_out_w`` over each period);
    ``meta["truth"]`` = ``plant.truth()``. ``seed=None`` uses ``plant.seed``.
    """
    cin = _command(in_command, "simulate_bench: in_command")
    cout = _command(out_command, "simulate_bench: out_command")
    if cin.size != cout.size:
        raise ProfileError(f"simulate_bench: in_command has {cin.size} samples, out_command "
                           f"{cout.size}; give equal lengths")
    world = BenchWorld(plant, seed=seed)
    world.mount(coupling="reducer")
    world.set_mode("in", _mode(in_mode, "simulate_bench: in_mode"))
    world.set_mode("out", _mode(out_mode, "simulate_bench: out_mode"))
    rows = _rows(world, cin, cout)
    cols = {"in_position_rad": rows[:, K.M_POS_IN], "in_current_a": rows[:, K.M_CUR_IN],
            "out_position_rad": rows[:, K.M_POS_OUT], "out_current_a": rows[:, K.M_CUR_OUT],
            "in_command": cin, "out_command": cout}
    if include_truth:
        cols.update(in_velocity_rad_s=rows[:, K.M_VEL_IN], out_velocity_rad_s=rows[:, K.M_VEL_OUT],
                    in_true_velocity_rad_s=rows[:, K.M_W_IN], out_true_velocity_rad_s=rows[:, K.M_W_OUT],
                    in_true_current_a=rows[:, K.M_I_IN], out_true_current_a=rows[:, K.M_I_OUT],
                    power_in_w=rows[:, K.M_P_IN], power_out_w=rows[:, K.M_P_OUT])
    meta = {"truth": plant.truth(),
            "sim": {"in_mode": in_mode, "out_mode": out_mode, "seed": world.seed}}
    return Trace(np.arange(cin.size) * plant.period_s, cols, meta, source="<simulate_bench>")



