"""A profile's steps as a plan: a plain list of typed actions, made by pure functions.

``plan_step(profile, step, known)`` turns one profile step (or a tuple of calibrate
steps run at once, see ``step_groups``) into actions the sequencer plays in order:

- ``Segment``: one acquisition — per motor a drive mode and a setpoint array (or an
  adaptive controller, ``gearbench.station.adaptive``, that gives the setpoints and
  decides when the segment ends);
- ``Prompt``: the operator changes the bench (text, and what physically changes, for a
  simulated bench that mounts it itself);
- ``CalibrationAnalysis`` / ``EfficiencyAnalysis`` (``Analyse``): analyse recorded segments.

What a step's commands depend on from earlier steps (the calibrated Kt, the output
motor's friction, an unloaded run's streaming estimate) comes in ``Known``; nothing
here acquires, analyses or writes.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Mapping, Union

import numpy as np

from ..analysis.streaming import kt_share_loaded, kt_share_unloaded
from ..drives.base import Mode
from ..profile import CalibrateStep, EfficiencyStep, LoadStep
from .adaptive import CalibrationRuns, Staircase, stop_ramp

RAMP_RAD_S2 = 2000.0         # speed-command slew: run-up and the stop ramp ending every segment


@dataclass
class Segment:
    """One acquisition: per motor a mode and a setpoint array (SI)."""

    name: str
    step_kind: str
    commands: dict[str, tuple[Mode, np.ndarray | None]]
    description: str = ""
    meta: dict = field(default_factory=dict)
    # adaptive segment (gearbench.station.adaptive): gives each sample's setpoints and decides
    # when the segment ends; ``commands`` then hold (mode, None)
    controller: object = None

    @property
    def max_samples(self) -> int:
        if self.controller is not None:
            return int(self.controller.max_samples)
        return len(next(iter(self.commands.values()))[1])


@dataclass(frozen=True)
class Prompt:
    """The operator changes the bench; ``coupling`` and ``disk_kgm2`` say what (a
    simulated bench mounts it itself)."""

    text: str
    coupling: str = "none"
    disk_kgm2: Mapping[str, float] = field(default_factory=dict)

    @property
    def mount(self) -> dict:
        return dict(coupling=self.coupling, disk_kgm2=dict(self.disk_kgm2))


@dataclass(frozen=True)
class CalibrationAnalysis:
    """Identify ``motor``'s Kt from its run alone (segment ``unloaded``) and with its disk
    (segment ``loaded``)."""

    motor: str
    disk_kgm2: float
    disk_std_kgm2: float
    disk_name: str
    unloaded: str
    loaded: str


@dataclass(frozen=True)
class EfficiencyAnalysis:
    """The efficiency points of one recorded speed (segment ``segment``)."""

    segment: str
    speed_rad_s: float
    adaptive: bool = False


Analyse = Union[CalibrationAnalysis, EfficiencyAnalysis]
Action = Union[Segment, Prompt, CalibrationAnalysis, EfficiencyAnalysis]


@dataclass(frozen=True)
class Known:
    """What earlier steps of the run found, as far as later commands need it."""

    kt: Mapping[str, float]                       # each motor's Kt: calibrated, else datasheet
    loss_out: Callable | None = None              # output motor's friction torque(ω), once calibrated
    b2_unloaded: Callable[[str, str], float] = lambda segment, motor: float("nan")
    inertia_kgm2: Mapping[str, float] = field(default_factory=dict)   # calibrated rotor J per motor

    @classmethod
    def from_datasheet(cls, profile) -> "Known":
        return cls({m: float(spec.kt_datasheet) for m, spec in profile.motors.items()})


def step_groups(profile) -> list:
    """The profile's steps as run: each step alone, except that with
    ``bench.parallel_calibration`` calibrate steps of different motors next to each
    other form one tuple, calibrated at once (the motors are independent before the
    reducer is mounted)."""
    groups: list = []
    parallel = profile.bench.parallel_calibration
    for step in profile.steps:
        last = groups[-1] if groups else None
        if (parallel and isinstance(step, CalibrateStep) and isinstance(last, tuple)
                and step.motor not in {s.motor for s in last}):
            groups[-1] = last + (step,)
        elif parallel and isinstance(step, CalibrateStep):
            groups.append((step,))
        else:
            groups.append(step)
    return [g[0] if isinstance(g, tuple) and len(g) == 1 else g for g in groups]


def plan(profile, known: Known | None = None) -> list[Action]:
    """Every action of the run, with ``known`` (default: the datasheet values) standing in
    for what earlier steps will find. Plain data: easy to print, count and test."""
    known = known or Known.from_datasheet(profile)
    return [a for group in step_groups(profile) for a in plan_step(profile, group, known)]


def plan_step(profile, step, known: Known) -> list[Action]:
    """The actions of one profile step (or of a tuple of calibrate steps run at once)."""
    if isinstance(step, tuple) or (isinstance(step, CalibrateStep) and step.adaptive):
        return plan_calibration(profile, step if isinstance(step, tuple) else (step,), known)
    if isinstance(step, CalibrateStep):
        return _plan_fixed_calibration(profile, step)
    if isinstance(step, LoadStep):
        name = profile.reducer.name if profile.reducer else "reducer"
        return [Prompt(step.prompt or f"Mount reducer '{name}' between the motors", coupling="reducer")]
    if isinstance(step, EfficiencyStep):
        actions: list[Action] = []
        for k, speed in enumerate(step.speeds_in_rad_s):
            seg = (staircase_segment(profile, step, k, speed, known) if step.adaptive
                   else efficiency_segment(profile, step, k, speed, known))
            actions += [seg, EfficiencyAnalysis(seg.name, speed, adaptive=step.adaptive)]
        return actions
    raise TypeError(f"unknown profile step {step!r}")


def _render(profile, step) -> np.ndarray:
    n = int(round(step.duration_s / profile.bench.period_s))
    wave = profile.waveforms[step.waveform]
    return np.asarray(wave.render(np.arange(n) * profile.bench.period_s), dtype=float)


def _mode(step) -> Mode:
    return Mode.TORQUE if step.mode in ("current", "torque") else Mode.VELOCITY


def _plan_fixed_calibration(profile, step) -> list[Action]:
    """One motor, fixed length: alone, then with its disk, one prompt each."""
    m, disk = step.motor, profile.disks[step.disk]
    cmd, mode = _render(profile, step), _mode(step)
    if mode is Mode.VELOCITY:
        cmd = np.concatenate([cmd, stop_ramp(cmd[-1], RAMP_RAD_S2, profile.bench.period_s)])
    unloaded, loaded = f"calibrate-{m}-unloaded", f"calibrate-{m}-{disk.name}"
    return [
        Prompt(f"Motor '{m}': shafts free, no disk, no reducer"),
        Segment(unloaded, "calibrate", {m: (mode, cmd)}, f"motor {m} without disk"),
        Prompt(step.prompt or f"Mount disk '{disk.name}' on motor '{m}'", disk_kgm2={m: disk.inertia_kgm2}),
        Segment(loaded, "calibrate", {m: (mode, cmd)}, f"motor {m} with disk {disk.name}"),
        Prompt(step.remove_prompt or f"Remove disk '{disk.name}' from motor '{m}'"),
        CalibrationAnalysis(m, disk.inertia_kgm2, disk.inertia_std_kgm2, disk.name, unloaded, loaded),
    ]


def plan_calibration(profile, steps: tuple, known: Known) -> list[Action]:
    """Calibrate steps run at once (or one adaptive step): every motor alone, then every
    motor with its disk — at once when each has its own disk, else the shared disk goes
    from motor to motor (its inertia error then cancels in K_out/K_in, the incremental
    efficiency). Adaptive steps stop each motor's run on ``targets.kt_rel``."""
    motors = [s.motor for s in steps]
    disks = {s.motor: profile.disks[s.disk] for s in steps}
    who = " and ".join(f"'{m}'" for m in motors)
    tag = ".".join(motors)          # file-name safe: trace-calibrate-in.out-unloaded.parquet
    unloaded = f"calibrate-{tag}-unloaded"
    actions: list[Action] = [
        Prompt(f"Motor{'s' if len(motors) > 1 else ''} {who}: shafts free, no disk, no reducer"),
        calibration_segment(profile, steps, "unloaded", unloaded, unloaded, known)]
    loaded = {}
    if len({d.name for d in disks.values()}) == len(motors):   # a disk per motor: at once
        mount = " and ".join(f"disk '{disks[m].name}' on motor '{m}'" for m in motors)
        seg_name = f"calibrate-{tag}-{'.'.join(disks[m].name for m in motors)}"
        loaded = dict.fromkeys(motors, seg_name)
        remove = " and ".join(f"disk '{disks[m].name}' from motor '{m}'" for m in motors)
        actions += [
            Prompt(steps[0].prompt if len(steps) == 1 else f"Mount {mount}",
                   disk_kgm2={m: disks[m].inertia_kgm2 for m in motors}),
            calibration_segment(profile, steps, "loaded", seg_name, unloaded, known),
            Prompt(steps[0].remove_prompt if len(steps) == 1 else f"Remove {remove}")]
    else:
        previous = None
        for s in steps:
            m, d = s.motor, disks[s.motor]
            loaded[m] = f"calibrate-{m}-{d.name}"
            text = (s.prompt or f"Mount disk '{d.name}' on motor '{m}'") if previous is None else \
                f"Move disk '{d.name}' from motor '{previous}' to motor '{m}'"
            actions += [Prompt(text, disk_kgm2={m: d.inertia_kgm2}),
                        calibration_segment(profile, (s,), "loaded", loaded[m], unloaded, known)]
            previous = m
        actions.append(Prompt(steps[-1].remove_prompt or
                              f"Remove disk '{disks[previous].name}' from motor '{previous}'"))
    for s in steps:
        d = disks[s.motor]
        actions.append(CalibrationAnalysis(s.motor, d.inertia_kgm2, d.inertia_std_kgm2, d.name,
                                           unloaded, loaded[s.motor]))
    return actions


def calibration_segment(profile, steps: tuple, run: str, seg_name: str, unloaded: str,
                        known: Known) -> Segment:
    """The motors of ``steps`` each playing its waveform (``run``: "unloaded" or "loaded");
    each stops once its Kt share is known to ``targets.kt_rel`` (fixed length if any step
    is not adaptive). A disk run's share uses the unloaded run's streaming b2."""
    modes, runs = {}, {}
    for s in steps:
        m = s.motor
        modes[m] = _mode(s)
        if run == "unloaded":
            share = (lambda b2, kt=profile.motors[m].kt_datasheet, j=profile.disks[s.disk].inertia_kgm2:
                     kt_share_unloaded(b2, kt, j))
        else:
            share = (lambda b2, m=m: kt_share_loaded(known.b2_unloaded(unloaded, m), b2))
        runs[m] = dict(command=_render(profile, s), velocity=modes[m] is Mode.VELOCITY, share=share,
                       label="unloaded" if run == "unloaded" else profile.disks[s.disk].name)
    if not all(s.adaptive for s in steps):   # fixed-length runs played together
        lo = hi = max(s.duration_s for s in steps)
        kt_rel = 0.0
    else:
        lo, hi = max(s.min_s for s in steps), max(s.max_s for s in steps)
        kt_rel = profile.targets.kt_rel
    ctl = CalibrationRuns(runs, period_s=profile.bench.period_s, min_s=lo, max_s=hi, kt_rel=kt_rel,
                          ramp_rad_s2=RAMP_RAD_S2, segment=seg_name)
    what = "without disk" if run == "unloaded" else "with disk"
    return Segment(seg_name, "calibrate", {m: (modes[m], None) for m in runs},
                   f"motor{'s' if len(runs) > 1 else ''} {', '.join(runs)} {what}", controller=ctl)


def staircase_segment(profile, step, k: int, speed: float, known: Known) -> Segment:
    """Adaptive efficiency at one speed: a continuous staircase of braking torques, each
    level held until eq. 18's slope is known to ``targets.eta_pp`` (gearbench.station.adaptive)."""
    kt_out = known.kt["out"]
    reducer = profile.reducer
    ctl = Staircase(speed=speed, currents_out_a=[-abs(t) / kt_out for t in step.torques_out_nm],
                    loss_out=known.loss_out,
                    torques_out_nm=list(step.torques_out_nm), period_s=profile.bench.period_s,
                    min_s=step.min_s, max_s=step.max_s, eta_pp=profile.targets.eta_pp,
                    kt_in=known.kt["in"], kt_out=kt_out,
                    eta_prior=sum(reducer.efficiency_range) / 2 if reducer else 0.8,
                    ratio_prior=reducer.ratio if reducer else None,
                    ramp_rad_s2=RAMP_RAD_S2, segment=f"efficiency-{k}",
                    inertia_kgm2=dict(known.inertia_kgm2))
    return Segment(f"efficiency-{k}", "efficiency",
                   {"in": (Mode.VELOCITY, None), "out": (Mode.TORQUE, None)},
                   f"input {speed:g} rad/s, staircase of {len(step.torques_out_nm)} braking torques",
                   meta=dict(speed=speed, settle_s=0.0, n_ramp=ctl.n_ramp, inertia_corrected=ctl.corrected),
                   controller=ctl)


def output_friction_nm(profile, speed_in_rad_s: float, known: Known) -> float:
    """The output motor's friction torque |D ω + Tc| at the output speed the reducer
    turns it at (input speed over the profile's nominal ratio); 0 while the output motor is
    not calibrated or the profile names no reducer ratio."""
    reducer = profile.reducer
    if known.loss_out is None or reducer is None or not reducer.ratio:
        return 0.0
    loss = abs(float(known.loss_out(speed_in_rad_s / abs(reducer.ratio))))
    return loss if np.isfinite(loss) else 0.0


def efficiency_segment(profile, step, k: int, speed: float, known: Known) -> Segment:
    """Input motor at ``speed`` (velocity mode, ramped); output motor in current mode:
    zero load, each braking torque, zero load again (the references of eq. 18).

    The output motor's own friction at the output speed (``known.loss_out``, once it is
    calibrated) already brakes the reducer, so each level's current is reduced by it, as
    the adaptive staircase does from its measured zero-load speed: the braking torque is
    then the profile's, not that plus the motor's friction."""
    per = profile.bench.period_s
    n_level = int(round((step.settle_s + step.measure_s) / per))
    n_ramp = int(round(max(abs(speed) / RAMP_RAD_S2, 0.05) / per))
    kt_out = known.kt["out"]
    zero = [0.0] if step.include_zero_load else []
    torques = zero + list(step.torques_out_nm) + zero
    loss = output_friction_nm(profile, speed, known)
    levels = zero + [-max(abs(t) - loss, 0.0) / kt_out for t in step.torques_out_nm] + zero
    stop = stop_ramp(speed, RAMP_RAD_S2, per)
    speed_cmd = np.concatenate([np.linspace(0.0, speed, n_ramp), np.full(n_level * len(levels), speed), stop])
    cur_cmd = np.concatenate([np.zeros(n_ramp)] + [np.full(n_level, c) for c in levels]
                             + [np.zeros(len(stop))])
    points = [(n_ramp + j * n_level, f"{speed:g} rad/s, {t:g} N m" + (" (reference)" if t == 0 else ""))
              for j, t in enumerate(torques)]
    return Segment(f"efficiency-{k}", "efficiency",
                   {"in": (Mode.VELOCITY, speed_cmd), "out": (Mode.TORQUE, cur_cmd)},
                   f"input {speed:g} rad/s, {len(step.torques_out_nm)} braking torques",
                   meta=dict(speed=speed, settle_s=step.settle_s, n_ramp=n_ramp, points=points))


def command_units(profile) -> dict[str, dict[str, str]]:
    """Per segment name per motor the unit of its ``<motor>.command`` column: ``"rad_s"``
    (velocity mode) or ``"a"`` (current/torque mode), from the plan (datasheet values
    standing in; the modes do not depend on them)."""
    out: dict[str, dict[str, str]] = {}
    for action in plan(profile):
        if isinstance(action, Segment):
            out[action.name] = {m: "rad_s" if mode is Mode.VELOCITY else "a"
                                for m, (mode, _) in action.commands.items()}
    return out
