"""Cycle time against accuracy: bench time vs Kt and efficiency error, three procedures.

    python -m gearbench.bench cycle_time [--plants N] [--seeds 0 1] [--png FILE] [--no-chain]

Procedures:
  classic   profiles/cvt-classic.yaml — fixed lengths: 4 calibration runs of 3 s one
            after the other, 15 levels of 0.3 s settle + 2.7 s measure, eq. 18 per point.
  adaptive  profiles/cvt.yaml — both motors calibrated at once, every run and every level
            stopped when its statistical 95 % interval meets ``targets`` (min_s..max_s),
            efficiency as one torque staircase per speed, eq. 18 as a regression slope.
  paper     the paper's procedure: a speed step from rest per calibration run (3 s, the
            four runs one after the other) identified with method="paper" (as
            bench/accuracy.py runs it), on the classic efficiency levels.

Plants: the profile's own simulated plant (cvt.yaml ``simulation:``), and random plants
drawn as in the robustness benchmark (``robustness.draw_case``: motors, disks, drive
loops, reducer) with the profile's operating grid scaled to each plant (3 speeds x 4
braking torques, 50-130 % of the output motor's rated current). Each plant runs the
real sequencer in-process against the simulated bench stepped one sample per SYNC
(``InProcessBench``: the same physics as ``--sim``, without the CANopen stack); one run
of each profile also goes through the real ``--sim`` CANopen chain.

Scored against the simulator's truth: |Kt error| per motor (%), |incremental| and
|absolute| efficiency error at every one of the 12 points (pp), bench time (s); a plant
meets the goal when both Kt are within 0.2 % and all 12 incremental efficiencies within
0.2 pp. Writes a PNG of error versus bench time.
"""
from __future__ import annotations

import argparse
import copy
import math
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..drives.base import AxisConfig, Drive, DriveNetwork, Mode, Sample

NAME = "cycle_time"
REPO = Path(__file__).resolve().parents[2]
PROFILES = {"classic": REPO / "profiles" / "cvt-classic.yaml", "adaptive": REPO / "profiles" / "cvt.yaml"}
GOAL = {"kt_pct": 0.2, "inc_pp": 0.2}
MODES = {Mode.VELOCITY: "velocity", Mode.TORQUE: "torque"}


# ------------------------------------------------------------- in-process bench
class _Drive(Drive):
    def __init__(self, net: "InProcessBench", config: AxisConfig):
        super().__init__(config)
        self.net = net

    def enable(self, mode: Mode) -> None:
        self.net.world.set_mode(self.name, MODES[mode])

    def set_setpoint(self, value: float) -> None:
        self.net.world.set_setpoint(self.name, value)

    def quick_stop(self) -> None:
        self.net.world.set_mode(self.name, "velocity")

    def disable(self) -> None:
        # decelerate, then remove power: between segments no bench time is counted
        world = self.net.world
        world.set_mode(self.name, "velocity")
        for _ in range(2000):
            if abs(world.step()[self.name].velocity_rad_s) < 0.5:
                break
        world.set_mode(self.name, "off")

    def reset_fault(self) -> None:
        pass


class InProcessBench(DriveNetwork):
    """The simulated bench (``gearbench.sim.BenchWorld``) as a drive network, stepped one
    period per ``sample()`` in this process; also the fixture that mounts disks/reducer.
    Same physics and noise as the emulator behind ``--sim``, no bus in between."""

    family = "inprocess"
    lockstep = True

    def __init__(self, plant, *, seed: int = 0):
        super().__init__()
        self.plant = plant
        self.seed = seed
        self.world = None
        self._k = 0

    def open(self) -> None: ...

    def add_drive(self, config: AxisConfig) -> Drive:
        self.drives[config.name] = _Drive(self, config)
        return self.drives[config.name]

    def start(self, period_s: float) -> None:
        from ..sim import BenchWorld

        self.period_s = period_s
        self.world = BenchWorld(self.plant, seed=self.seed)

    def _sample(self) -> dict[str, Sample]:
        meas = self.world.step()
        self._k += 1
        k = self._k
        return {n: Sample(k, k * self.period_s, m.position_rad, m.velocity_rad_s, m.current_a)
                for n, m in meas.items() if n in self.drives}

    def mount(self, *, coupling: str, disk_kgm2: dict[str, float]) -> None:
        self.world.mount(coupling=coupling, disk_kgm2=disk_kgm2)

    def _close(self) -> None:
        self.world = None


def run_inprocess(profile, plant, *, seed: int = 0, method: str = "default") -> dict:
    """Run ``profile`` with the real sequencer against ``plant`` in this process; the
    result dict as result.json would hold it (``simulation_truth`` included)."""
    from ..sequencer import AutoOperator, Sequencer

    net = InProcessBench(plant, seed=seed)
    net.open()
    for name, m in profile.motors.items():
        net.add_drive(AxisConfig(name, m.address, m.drive, m.rated_current_a, m.current_limit_a,
                                 m.speed_limit_rad_s, m.counts_per_rev))
    net.start(profile.bench.period_s)
    seq = Sequencer(profile, net, emit=lambda rec: None, operator=AutoOperator(), fixture=net,
                    sim_truth=plant, method=method)
    try:
        return seq.run()
    finally:
        net.close()


# ------------------------------------------------------------------- scoring
def score(res: dict) -> dict:
    """|errors| against the simulator's truth: Kt % per motor, incremental and absolute
    efficiency pp per point, bench time, and whether the goal is met."""
    if res.get("status") not in ("passed", "failed"):
        return {"error": res.get("reason", res.get("status")), "bench_time_s": res.get("bench_time_s", 0.0)}
    truth = res["simulation_truth"]
    kt = [abs(100 * (res["motors"][m]["Kt"] / truth["motors"][m]["Kt"] - 1)) for m in res["motors"]]
    inc = [abs(100 * (p["eta_incremental"] - t["eta_incremental"]))
           for p, t in zip(res["efficiency"], truth["efficiency"])]
    ab = [abs(100 * (p["eta_absolute"] - t["eta_absolute"]))
          for p, t in zip(res["efficiency"], truth["efficiency"])]
    meets = (len(kt) == 2 and len(inc) == 12 and max(kt) <= GOAL["kt_pct"]
             and max(inc) <= GOAL["inc_pp"])
    return {"kt": kt, "inc": inc, "abs": ab, "bench_time_s": res["bench_time_s"], "meets": meets,
            "stopped_by_max": sum(m.get("stopped_by") == "max" for m in res.get("measurements", []))}


# ------------------------------------------------------------------- plants
def random_plant(index: int, seed: int, profile):
    """A robustness-benchmark plant (``robustness.draw_case``) with the profile's grid
    scaled to it: the returned profile brakes at 50-130 % of the plant's output rated
    current, at 3 speeds spanning the drawn bench speed, disks as drawn."""
    from .robustness import draw_case

    case = draw_case(index, seed)
    p = case.plant
    mi, mo = p.motor_in, p.motor_out
    speed = case.bench_speed_rad_s
    speeds = [round(speed * f, 1) for f in (0.6, 0.8, 1.0)]
    rated = mo.rated_current_a
    torques = [round(mo.Kt * rated * f, 6) for f in (0.5, 0.75, 1.0, 1.3)]
    return case, _adapt_profile(profile, case, speeds, torques)


def _adapt_profile(profile, case, speeds, torques):
    """``profile`` re-targeted at the drawn plant (motor data, disks, grid, excitation),
    keeping its procedure (fixed or adaptive, sequential or parallel)."""
    from ..profile.model import CalibrateStep, DiskSpec, EfficiencyStep, WaveformSpec

    p = case.plant
    motors = dict(profile.motors)
    for name, m in (("in", p.motor_in), ("out", p.motor_out)):
        motors[name] = replace(motors[name], kt_datasheet=m.Kt * 1.03, rated_current_a=m.rated_current_a,
                               current_limit_a=m.current_limit_a, speed_limit_rad_s=1e4,
                               rotor_inertia_kgm2=m.J, counts_per_rev=m.counts_per_rev)
    disks = dict(profile.disks)
    steps = []
    waves = dict(profile.waveforms)
    for s in profile.steps:
        if isinstance(s, CalibrateStep):
            dname = f"disk_{s.motor}"
            disks[dname] = DiskSpec(dname, case.disks_kgm2[s.motor], 0.005, "measured")
            wname = f"excite_{s.motor}"
            waves[wname] = _case_waveform(case, s.motor, wname)
            s = replace(s, disk=dname, waveform=wname)
        elif isinstance(s, EfficiencyStep):
            s = replace(s, speeds_in_rad_s=speeds, torques_out_nm=torques)
        steps.append(s)
    reducer = replace(profile.reducer, ratio=None, efficiency_range=(0.5, 1.0))
    return replace(profile, motors=motors, disks=disks, waveforms=waves, steps=steps, reducer=reducer,
                   limits=[])


class _Table:
    """A recorded command as a waveform: ``render`` looks the drawn samples up (held
    past the end)."""

    def __init__(self, samples: np.ndarray, period_s: float):
        self.samples = np.asarray(samples, float)
        self.period_s = period_s

    def __call__(self, t):
        k = np.minimum(np.round(np.asarray(t) / self.period_s).astype(int), len(self.samples) - 1)
        return self.samples[k]


def _case_waveform(case, motor: str, name: str):
    """The drawn plant's own calibration command (robustness: a multisine sized to the
    drive's current limit with its disk), repeated to cover any max_s."""
    from ..profile.model import WaveformSpec

    cmd = np.asarray(case.commands[motor], float)
    long = np.tile(cmd, 4)
    table = _Table(long, 1e-3)

    class _Spec(WaveformSpec):
        def render(self, time_s):
            return table(time_s)

        @property
        def natural_period_s(self):
            return len(cmd) * 1e-3

    return _Spec(name, "table", {})
