"""Replay of a recorded run through the simulated bench (``gearbench.sim.BenchWorld``).

A run's traces hold, per sample, each motor's setpoint (``<motor>.command``: rad/s in
velocity mode, A in torque mode) as the sequencer sent it *before* the SYNC that
produced the sample. The emulator (``gearbench.emulate.bench.EmulatedBench.advance``)
applies a setpoint, advances the world one period and measures the next sample; the
drives' modes change only when a segment enables or disables them, and ``set_mode``
(which resets the drive's speed integrator) is called only when the mode differs
from the world's. The replay does exactly that, segment after segment, on one world,
so a twin with the run's own plant, seed and noise reproduces an emulated run to the
drive's quantisation, and with noise off it gives the deterministic prediction that
the measured traces scatter around.

What the traces do not say is taken from the profile: the mounting of each segment
(named by the sequencer: ``calibrate-<motors>-unloaded``, ``calibrate-<motors>-<disks>``,
``efficiency-<k>``), the drive mode of each motor (calibration ``mode``; efficiency:
input velocity, output torque) and the disks' inertias.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..errors import ProfileError, TraceError
from ..sim import BenchWorld, PlantParams
from ..sim import kernel as K
from ..trace import Trace

AXES = ("in", "out")
SIGNALS = ("position_rad", "velocity_rad_s", "current_a")
# measurement columns of the kernel's row per axis and signal
_COLS = {("in", "position_rad"): K.M_POS_IN, ("in", "velocity_rad_s"): K.M_VEL_IN,
         ("in", "current_a"): K.M_CUR_IN, ("out", "position_rad"): K.M_POS_OUT,
         ("out", "velocity_rad_s"): K.M_VEL_OUT, ("out", "current_a"): K.M_CUR_OUT}


@dataclass
class Segment:
    """One recorded step as the replay plays it.

    Attributes
    ----------
    name : the trace's step name (``trace-<name>.parquet``).
    coupling : ``"none"`` or ``"reducer"``.
    disks_kgm2 : inertia disk per motor (calibration), else empty.
    modes : drive mode per axis: ``"off"``, ``"velocity"`` or ``"torque"``.
    trace : the recorded trace (columns ``sample``, ``<axis>.command`` ...).
    """

    name: str
    coupling: str
    disks_kgm2: dict
    modes: dict
    trace: Trace
    first_sample: int = 0
    last_sample: int = 0
    meta: dict = field(default_factory=dict)

    @property
    def kind(self) -> str:
        return self.name.split("-", 1)[0]

    def commands(self, axis: str) -> np.ndarray:
        """The setpoint of every world sample first..last (lost samples hold the previous)."""
        samples = self.trace["sample"].astype(np.int64)
        cmd = np.asarray(self.trace.get(f"{axis}.command", np.zeros(len(samples))), float)
        idx = np.searchsorted(samples, np.arange(self.first_sample, self.last_sample + 1), side="right") - 1
        return cmd[np.clip(idx, 0, len(cmd) - 1)]

    def rows(self) -> np.ndarray:
        """Row in the replay's output (0 = first_sample) of each recorded sample."""
        return self.trace["sample"].astype(np.int64) - self.first_sample


def plan_segments(traces: dict[str, Trace], profile) -> list[Segment]:
    """Order the recorded steps by their first sample and give each its mounting and modes.

    Parameters
    ----------
    traces : step name -> recorded Trace (must have ``sample`` and ``<axis>.command``).
    profile : ``gearbench.profile.Profile`` of the run (disks, calibration modes).

    Raises
    ------
    TraceError
        A step name the sequencer does not produce, or a trace without ``sample``.
    """
    disks = {name: d.inertia_kgm2 for name, d in profile.disks.items()}
    cal_modes = {}
    for s in profile.steps:
        mode = getattr(s, "mode", None)
        if type(s).__name__ == "CalibrateStep":
            cal_modes[s.motor] = "torque" if mode in ("current", "torque") else "velocity"
    segs = []
    for name, tr in traces.items():
        if "sample" not in tr:
            raise TraceError(f"{tr.source}: no 'sample' column; the replay needs the bench's sample "
                             f"index (recorded by gearbench run)")
        samples = tr["sample"].astype(np.int64)
        if len(samples) == 0:
            continue
        if name.startswith("efficiency-"):
            coupling, dk, modes = "reducer", {}, {"in": "velocity", "out": "torque"}
        elif name.startswith("calibrate-"):
            motors, dk = _calibration_mount(name, disks, set(cal_modes) | set(AXES))
            coupling = "none"
            modes = {a: (cal_modes.get(a, "velocity") if a in motors else "off") for a in AXES}
        else:
            raise TraceError(f"{tr.source}: step '{name}' is neither calibrate-* nor efficiency-*; "
                             f"the twin replays the sequencer's steps only")
        segs.append(Segment(name, coupling, dk, modes, tr, int(samples[0]), int(samples[-1])))
    segs.sort(key=lambda s: s.first_sample)
    return segs


def _calibration_mount(name: str, disks: dict, motors: set) -> tuple[list[str], dict]:
    """(motors run, {motor: disk inertia}) from ``calibrate-<m1.m2>-<unloaded|d1.d2>``."""
    rest = name[len("calibrate-"):]
    for i in [j for j, ch in enumerate(rest) if ch == "-"]:
        who, what = rest[:i].split("."), rest[i + 1:]
        if not all(m in motors for m in who):
            continue
        if what == "unloaded":
            return who, {}
        names = what.split(".") if len(who) > 1 else [what]
        if len(names) == len(who) and all(n in disks for n in names):
            return who, {m: float(disks[n]) for m, n in zip(who, names)}
    raise TraceError(f"step '{name}': cannot tell the motors and disk from the name "
                     f"(expected calibrate-<motor>-<disk> with a disk of the profile)")


def quiet_plant(plant: PlantParams) -> PlantParams:
    """The plant without sensor noise: the deterministic prediction of the measurement."""
    return replace(plant, motor_in=replace(plant.motor_in, current_noise_a=0.0),
                   motor_out=replace(plant.motor_out, current_noise_a=0.0))


def replay(plant: PlantParams, segments: list[Segment], *, noise: bool = False,
           seed: int | None = None, quanta: "Quanta | None" = None) -> dict[str, np.ndarray]:
    """Play the segments' setpoints on one ``BenchWorld`` in their recorded order.

    Parameters
    ----------
    plant : the simulated bench.
    segments : from ``plan_segments`` (sorted by first sample).
    noise : keep the plant's current noise (``False``: noise-free prediction).
    seed : noise seed (default the plant's).
    quanta : the drives' units of setpoints (``Quanta``): each setpoint is rounded to its
        unit as the bus carries it (an unrounded velocity setpoint leaves 0.14 rad/s rms
        between an emulated run and its replay; rounded, the replay is exact).

    Returns
    -------
    dict
        step name -> (n_world_samples, 16) kernel rows for samples first..last of
        the segment (``Segment.rows()`` picks the recorded ones).
    """
    world = BenchWorld(plant if noise else quiet_plant(plant), seed=seed)
    mount = None
    out = {}
    for seg in segments:
        gap = seg.first_sample - 1 - world.sample_index
        if gap > 0:
            # samples nobody recorded (between sessions of a real bench): drives off
            for a in AXES:
                if world.mode(a) != "off":
                    world.set_mode(a, "off")
            world.run(np.zeros(gap), np.zeros(gap))
        want = (seg.coupling, tuple(sorted(seg.disks_kgm2.items())))
        if want != mount:
            world.mount(coupling=seg.coupling, disk_kgm2=dict(seg.disks_kgm2))
            mount = want
        sp = {}
        for a in AXES:
            mode = seg.modes[a]
            if world.mode(a) != mode:
                world.set_mode(a, mode)
            c = seg.commands(a) if mode != "off" else np.zeros(seg.last_sample - seg.first_sample + 1)
            q = (quanta or Quanta()).setpoint(a, mode)
            if q > 0:
                c = np.round(c / q) * q
            sp[a] = c
        out[seg.name] = world.run(sp["in"], sp["out"])
    return out


def measured(seg: Segment, axis: str, signal: str) -> np.ndarray:
    return np.asarray(seg.trace[f"{axis}.{signal}"], float)


def simulated(rows: np.ndarray, seg: Segment, axis: str, signal: str) -> np.ndarray:
    """The replay's value of one signal at the segment's recorded samples."""
    return rows[seg.rows(), _COLS[(axis, signal)]]


def simulated_trace(rows: np.ndarray, seg: Segment, *, quanta: "Quanta | None" = None) -> Trace:
    """A Trace shaped like the recorded one, holding the replay's measurement (the
    proof re-analyses it with the run's own analysis). Currents are rounded to the
    drive's reporting unit when given."""
    cols = {"sample": seg.trace["sample"].copy()}
    for a in AXES:
        for s in SIGNALS:
            v = simulated(rows, seg, a, s)
            q = (quanta or Quanta()).current_a.get(a, 0.0)
            if s == "current_a" and q > 0:
                v = np.round(v / q) * q
            cols[f"{a}.{s}"] = v
        cols[f"{a}.command"] = np.asarray(seg.trace.get(f"{a}.command", np.zeros(len(seg.trace))), float)
    return Trace(seg.trace.time_s.copy(), cols, dict(seg.trace.meta), f"twin:{seg.name}")


@dataclass(frozen=True)
class Quanta:
    """Units the drives carry values in, per axis (0 = continuous): velocity setpoint in
    rad/s, torque setpoint in A, reported current in A. CiA 402: 0x60FF in the drive's
    velocity unit (inc/s = 2π/counts per rev), 0x6071 and 0x6078 per mille of rated current."""

    velocity_rad_s: dict = field(default_factory=dict)
    torque_a: dict = field(default_factory=dict)
    current_a: dict = field(default_factory=dict)

    def setpoint(self, axis: str, mode: str) -> float:
        if mode == "velocity":
            return float(self.velocity_rad_s.get(axis, 0.0))
        if mode == "torque":
            return float(self.torque_a.get(axis, 0.0))
        return 0.0


def check_axes(profile) -> None:
    """The simulated bench has two axes named in and out."""
    bad = [m for m in profile.motors if m not in AXES]
    if bad:
        raise ProfileError(f"{profile.path}: motors {', '.join(bad)}: the simulated bench (and its "
                           f"twin) has the axes 'in' and 'out' only")
