"""Cycle time against accuracy: bench time vs Kt and efficiency error, three procedures.

    python -m gearbench.benchmarks cycle_time [--plants N] [--seeds 0 1] [--png FILE] [--no-chain]
                                              [--per-plant] [--adaptive-excitation designed|drawn]
                                              [--drive-current drawn|mean] [--current-noise-scale S]

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
braking torques, 50-130 % of the output motor's rated current) and the reducer's
nominal ratio as a ±2 % limit (as cvt.yaml's). The classic and paper procedures
calibrate with the drawn case's own commands (forward or, one case in four,
reversing multisines); the adaptive one (``--adaptive-excitation designed``, default)
with a multisine designed per motor from the profile's data sheet values that sweeps
the speeds the motor turns at over the map (``designed_waveform``; ``drawn`` gives the
procedure as before issue 23). Each plant runs the
real sequencer in-process against the simulated bench stepped one sample per SYNC
(``InProcessBench``: the same physics as ``--sim``, without the CANopen stack); one run
of each profile also goes through the real ``--sim`` CANopen chain.

Scored against the simulator's truth: |Kt error| per motor (%), |incremental| and
|absolute| efficiency error at every one of the 12 points (pp), bench time (s); a plant
meets the goal when both Kt are within 0.2 % and all 12 incremental efficiencies within
0.2 pp, and every target when the absolute efficiencies are within 0.3 pp too
(``robustness.TARGETS``); "in bound" = every target within the profile's bench-time
bound (``bench_time_bound_s``: every measurement at max_s). ``--per-plant`` prints one
line per random plant with why each missed target was missed (``why_missed``).
Writes a PNG of error versus bench time.

``--per-plant`` also prints each missed target's cause (``classify_misses``: from Kt,
stopped early, at max_s, unsettled, extrapolated loss, noise; "biased" beyond 2 sd)
and a tally; where no sweep within the current limit covers a motor's map speeds, the
plain design (as the profile's own design falls back), and a plant the excitation design
finds no waveform for at all is an ERROR row.

The adaptive procedure's incremental error on the cvt plant is mostly where each level
happened to stop: the output motor's calibrated friction sets the braking levels and
the stops. Its target (0.15 pp, 95 %) leaves a miss of the 0.2 pp goal a few times in a
hundred runs; compare calibrations with ``--cvt-runs 30``, not 5 (main 9396cc8: 29/30
meet, bench 16.4 s mean, incremental mean/max 0.084/0.226 pp; issue 23's staircase
— block-means stop, inertia-corrected levels, speed check: 30/30, 16.8 s,
0.076/0.169 pp). Random plants, every target within the bound, draws 0-3 x 20: main
20/35/60/30 % (36 %), issue 23's staircase 55/80/65/55 % (64 %); draws 4-5 crash main
(no designed waveform for 4/9).
"""
from __future__ import annotations

import argparse
import math
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..drives.base import AxisConfig, Drive, DriveNetwork, Mode, Sample
from ..sim.truth import truth_of
from .robustness import BIASED_SIGMAS, TARGETS

NAME = "cycle_time"
REPO = Path(__file__).resolve().parents[2]
PROFILES = {"classic": REPO / "profiles" / "cvt-classic.yaml", "adaptive": REPO / "profiles" / "cvt.yaml"}
GOAL = {"kt_pct": 0.2, "inc_pp": 0.2}
ABS_PP = TARGETS["abs_pp"]   # every target: GOAL and the absolute efficiency within this
MODES = {Mode.VELOCITY: "velocity", Mode.TORQUE: "torque"}
DESIGN_MAX_TONE_HZ = 4.0     # designed calibrations: below the slowest drawn speed loops (3-30 Hz)
DESIGN_MIN_TONES = 4         # designed calibrations: at least 4 tones (2 let a 3 % Kt bias through)


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
    from ..station.sequencer import AutoOperator, Sequencer

    net = InProcessBench(plant, seed=seed)
    net.open()
    for name, m in profile.motors.items():
        net.add_drive(AxisConfig(name, m.address, m.drive, m.rated_current_a, m.current_limit_a,
                                 m.speed_limit_rad_s, m.counts_per_rev))
    net.start(profile.bench.period_s)
    seq = Sequencer(profile, net, emit=lambda rec: None, operator=AutoOperator(), fixture=net,
                    sim_truth=truth_of(plant), method=method)
    try:
        return seq.run()
    finally:
        net.close()


# ------------------------------------------------------------------- scoring
def score(res: dict) -> dict:
    """|errors| against the simulator's truth: Kt % per motor, incremental and absolute
    efficiency pp per point, bench time, whether the goal is met (Kt and incremental, as
    since issue 14) and whether every target is (``meets_all``: the absolute efficiency
    within ``robustness.TARGETS`` too), and for each missed quantity why (``why_missed``)."""
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
    return {"kt": kt, "kt_motors": list(res["motors"]), "inc": inc, "abs": ab,
            "bench_time_s": res["bench_time_s"], "meets": meets,
            "meets_all": meets and max(ab, default=math.inf) <= ABS_PP,
            "why_missed": why_missed(res, kt, inc, ab), "causes": classify_misses(res, kt, inc, ab),
            "shortfall": shortfall(res, kt, inc, ab),
            "stopped_by_max": sum(m.get("stopped_by") == "max" for m in res.get("measurements", []))}


def why_missed(res: dict, kt: list, inc: list, ab: list) -> list[str]:
    """Why each missed target was missed, from the run's own record: *biased* (the error
    beyond ``BIASED_SIGMAS`` of the run's own reported standard uncertainty: a confident
    wrong answer), *noise at the bound* (within its uncertainty, the measurements that
    carry it ended at max_s short of their target), *extrapolated loss* (the absolute
    efficiency used a motor loss outside its calibrated speeds)."""
    out = []
    truth = res["simulation_truth"]
    at_max = lambda kind: sum(_short(m) for m in res.get("measurements", []) if m["kind"] == kind)
    for (m, e) in zip(res["motors"], kt):
        if e <= GOAL["kt_pct"]:
            continue
        sd = 100 * res["motors"][m]["Kt_std"] / truth["motors"][m]["Kt"]
        out.append(f"Kt {m} {e:.2f}% " + (f"biased ({e / sd:.1f} sd)" if e > BIASED_SIGMAS * sd else
                                          f"noise at the bound ({at_max('calibrate')} runs at max)"))
    pts = res["efficiency"]
    bad = [(e, 100 * p["eta_incremental_std"]) for e, p in zip(inc, pts) if e > GOAL["inc_pp"]]
    if bad:
        e, sd = max(bad)
        out.append(f"incr {e:.2f}pp " + (f"biased ({e / sd:.1f} sd)" if e > BIASED_SIGMAS * sd else
                                         f"noise at the bound ({at_max('efficiency')} levels at max)"))
    bad = [(e, 100 * p["eta_absolute_std"], bool(p.get("loss_extrapolated"))) for e, p in zip(ab, pts)
           if e > ABS_PP]
    if bad:
        e, sd, extrap = max(bad)
        why = "extrapolated loss" if extrap else (f"biased ({e / sd:.1f} sd)" if e > BIASED_SIGMAS * sd
                                                  else "noise")
        out.append(f"abs {e:.2f}pp {why}")
    return out


def classify_misses(res: dict, kt: list, inc: list, ab: list) -> list[str]:
    """One cause per missed target, from the run's own record (the issue-23 triage):
    ``Kt|incr|abs`` + ``: `` + one of *from Kt* (incremental: the two Kt errors make most
    of it), *stopped early* (every measurement that carries it
    stopped on its target, yet the error is outside the target: the stopping rule's
    interval was too optimistic), *at max_s* (a measurement that carries it ended at
    max_s short of its target: too little information per second), *unsettled* (a level
    never settled within max_s), *extrapolated loss* (a motor loss used outside its
    calibrated speeds), *noise* (none of these: within its reported uncertainty);
    ``(biased)`` is appended when the error is beyond ``BIASED_SIGMAS`` of the run's own
    standard uncertainty."""
    return [cause for cause, _ in _misses(res, kt, inc, ab)]


def shortfall(res: dict, kt: list, inc: list, ab: list) -> float | None:
    """How far the misses *at max_s* stayed from what the bound allows: the largest
    interval reached / target of the max_s-ended measurements that carry them (None when
    no miss is at max_s). Acquisition time shrinks an interval as 1/√t, so a plant short
    by F needed about F² times its measurements' max_s: near 1 a better share of the
    bench-time budget can close it, far above 1 only more information per second can."""
    ratios = [m["interval_reached"] / m["target"] for cause, carriers in _misses(res, kt, inc, ab)
              if "at max_s" in cause for m in carriers if _short(m)]
    return max(ratios, default=None)


def design_ratio(profile, res: dict) -> dict[str, float]:
    """What each designed calibration run reached against what its excitation design
    predicted (``excitation_design.Prediction``, eq. D1/D2 with the design's noise model:
    current-sensor noise and quantum, encoder quantum, the speed tracked as commanded):
    ``"<motor> <run>"`` -> interval reached / predicted 95 % half-width of that run's
    Kt share, the prediction scaled to the run's length (1/sqrt(t)). Near 1 the design's
    noise model holds; far above it the run saw noise or tracking the design does not
    model. Runs without a designed waveform are left out."""
    from ..analysis.streaming import Z95
    from ..profile.model import CalibrateStep

    out = {}
    for step in profile.steps:
        spec = profile.waveforms.get(getattr(step, "waveform", None)) if isinstance(step, CalibrateStep) else None
        design = getattr(spec, "design", None)
        if design is None or step.motor not in design.predictions:
            continue
        pred = design.predictions[step.motor]
        J = profile.motors[step.motor].rotor_inertia_kgm2
        j = profile.disks[step.disk].inertia_kgm2
        for m in res.get("measurements", []):
            if m["kind"] != "calibrate" or m.get("motor") != step.motor or not m.get("interval_reached"):
                continue
            loaded = m.get("run") != "unloaded"
            # eq. D2: each run's relative b2 error moves Kt by J/j unloaded, (J + j)/j loaded
            share = (J + j) / j if loaded else J / j
            rel = pred.b2_rel_std_loaded if loaded else pred.b2_rel_std_unloaded
            predicted = Z95 * share * rel * math.sqrt(pred.duration_s / max(m["duration_s"], 1e-9))
            if predicted > 0 and math.isfinite(predicted):
                out[f"{step.motor} {'loaded' if loaded else 'unloaded'}"] = m["interval_reached"] / predicted
    return out


def _short(m: dict) -> bool:
    """A measurement that ended at max_s with its interval still above its target."""
    return m.get("stopped_by") == "max" and (m.get("interval_reached") or 0) > m["target"]


def _misses(res: dict, kt: list, inc: list, ab: list) -> list[tuple[str, list[dict]]]:
    """``classify_misses``'s causes, each with the measurements that carry its target."""
    out = []
    truth = res["simulation_truth"]
    meas = res.get("measurements", [])
    for (m, e) in zip(res["motors"], kt):
        if e <= GOAL["kt_pct"]:
            continue
        runs = [r for r in meas if r["kind"] == "calibrate" and r.get("motor") == m]
        why = "at max_s" if any(_short(r) for r in runs) else "stopped early"
        sd = 100 * res["motors"][m]["Kt_std"] / truth["motors"][m]["Kt"]
        out.append((f"Kt: {why}" + (" (biased)" if e > BIASED_SIGMAS * sd else ""), runs))
    pts = res["efficiency"]
    for q, errs, limit in (("incr", inc, GOAL["inc_pp"]), ("abs", ab, ABS_PP)):
        bad = [k for k, e in enumerate(errs) if e > limit]
        if not bad:
            continue
        k = max(bad, key=lambda j: errs[j])
        p = pts[k]
        speed = p.get("speed_setpoint_rad_s")
        levels = [r for r in meas if r["kind"] == "efficiency" and r.get("speed_in_rad_s") == speed]
        if q == "abs":
            levels = [r for r in levels if r.get("reference") or
                      abs(r.get("torque_out_nm", math.nan) - p.get("torque_setpoint_nm", math.nan)) < 1e-9]
        std = 100 * p[f"eta_{'incremental' if q == 'incr' else 'absolute'}_std"]
        # η = K_out/(n K_in b): the Kt errors alone move the incremental efficiency by
        # η·(e_out − e_in); where that is most of the miss, the miss is the calibration's
        kt_part = 100 * p["eta_incremental"] * (res["motors"]["out"]["Kt"] / truth["motors"]["out"]["Kt"]
                                                - res["motors"]["in"]["Kt"] / truth["motors"]["in"]["Kt"]) \
            if q == "incr" and {"in", "out"} <= set(res["motors"]) else 0.0
        if q == "abs" and p.get("loss_extrapolated"):
            why = "extrapolated loss"
        elif abs(kt_part) > 0.5 * errs[k]:
            why = "from Kt"
        elif any(not r.get("settled_in_time", True) for r in levels):
            why = "unsettled"
        elif any(_short(r) for r in levels):
            why = "at max_s"
        elif levels and q == "incr":
            why = "stopped early"
        else:
            why = "noise"
        out.append((f"{q}: {why}" + (" (biased)" if errs[k] > BIASED_SIGMAS * std else ""), levels))
    return out


def bench_time_bound_s(profile) -> float:
    """The profile's bench-time bound: every segment of its plan run to its end (each
    adaptive measurement at max_s, the speed ramps included)."""
    from ..station.plan import Segment, plan

    return sum(a.max_samples for a in plan(profile) if isinstance(a, Segment)) * profile.bench.period_s


# ------------------------------------------------------------------- plants
def random_plant(index: int, seed: int, profile, *, excitation: str = "drawn"):
    """A robustness-benchmark plant (``robustness.draw_case``) with the profile's grid
    scaled to it: the returned profile brakes at 50-130 % of the plant's output rated
    current, at 3 speeds spanning the drawn bench speed, disks as drawn. ``excitation``:
    "drawn" calibrates with the case's own commands (forward or reversing multisines as
    the robustness benchmark draws them), "designed" with a multisine per motor designed
    from the motor's data sheet as the profile gives it (``designed_waveform``)."""
    from .robustness import draw_case

    case = draw_case(index, seed)
    p = case.plant
    mo = p.motor_out
    speed = case.bench_speed_rad_s
    speeds = [round(speed * f, 1) for f in (0.6, 0.8, 1.0)]
    rated = mo.rated_current_a
    torques = [round(mo.Kt * rated * f, 6) for f in (0.5, 0.75, 1.0, 1.3)]
    return case, _adapt_profile(profile, case, speeds, torques, excitation)


def _adapt_profile(profile, case, speeds, torques, excitation: str = "drawn"):
    """``profile`` re-targeted at the drawn plant (motor data, disks, grid, excitation),
    keeping its procedure (fixed or adaptive, sequential or parallel)."""
    from ..profile.model import CalibrateStep, DiskSpec, EfficiencyStep, LimitSpec

    p = case.plant
    motors = dict(profile.motors)
    for name, m in (("in", p.motor_in), ("out", p.motor_out)):
        motors[name] = replace(motors[name], kt_datasheet=m.Kt * 1.03, rated_current_a=m.rated_current_a,
                               current_limit_a=m.current_limit_a, speed_limit_rad_s=1e4,
                               rotor_inertia_kgm2=m.J, counts_per_rev=m.counts_per_rev,
                               sampling=_sampling(m))
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
    # the reducer's nominal ratio, as its name plate gives it (the cvt profile's own limit, 2 %)
    limits = [LimitSpec("ratio", "ratio", p.ratio * 0.98, p.ratio * 1.02)]
    out = replace(profile, motors=motors, disks=disks, waveforms=waves, steps=steps, reducer=reducer,
                  limits=limits)
    if excitation == "designed":
        # the design keeps below the drives' real speed limit (the drawn commands ignore it)
        out = replace(out, motors={n: replace(out.motors[n], speed_limit_rad_s=m.speed_limit_rad_s)
                                   for n, m in (("in", p.motor_in), ("out", p.motor_out))})
        for s in out.steps:
            if isinstance(s, CalibrateStep):
                waves[s.waveform] = designed_waveform(out, s)
        out = replace(out, waveforms=waves)
    return out


def _sampling(motor) -> dict:
    """The drawn drive's ``motors.<m>.sampling`` as its set-up gives it (setpoint stepped or
    interpolated, current one instant or the period mean, its speed loop as set): what
    ``robustness.drive_description`` tells the analysis, without the current limit (the
    profile's own ``current_limit_a``)."""
    from .robustness import drive_description

    return {k: v for k, v in drive_description(motor).items() if k != "current_limit_a"}


def designed_waveform(profile, step):
    """The calibration multisine the excitation design makes for ``step``'s motor from
    the profile alone (data-sheet Kt, rotor inertia, current limits, encoder; the disk),
    sweeping the speeds the motor turns at over the efficiency map
    (``coverage.map_speed_range``) so no motor loss is extrapolated there; the band from
    half the map's lowest speed (at most 10 % of the speed limit) to 90 % of the limit."""
    from ..profile.design import DEFAULT_FRICTION_SHARE
    from ..profile.coverage import map_speed_range
    from ..profile.excitation_design import MotorCase, design_multisine
    from ..profile.model import WaveformSpec

    m, disk = profile.motors[step.motor], profile.disks[step.disk]
    cover = map_speed_range(profile, step.motor)
    top = 0.9 * m.speed_limit_rad_s
    if cover:        # never slower than 10 % of the limit: a slow speed loop's lag must not reach zero
        cover = (max(cover[0], 0.1 * top), max(cover[1], 0.1 * top))
    band = (0.5 * cover[0], top) if cover else (0.1 * top, top)
    case = MotorCase(kt_nm_a=m.kt_datasheet, rotor_inertia_kgm2=m.rotor_inertia_kgm2,
                     disk_inertia_kgm2=disk.inertia_kgm2, peak_current_a=0.65 * m.current_limit_a,
                     rms_current_a=m.rated_current_a, min_speed_rad_s=band[0], max_speed_rad_s=band[1],
                     friction_nm=DEFAULT_FRICTION_SHARE * m.kt_datasheet * m.rated_current_a,
                     counts_per_rev=m.counts_per_rev, name=step.motor)
    dur = step.min_s if step.adaptive else step.duration_s
    kw = dict(duration_s=dur, period_s=profile.bench.period_s, min_tones=DESIGN_MIN_TONES,
              max_tone_hz=DESIGN_MAX_TONE_HZ)
    try:
        d = design_multisine([case], cover_rad_s=cover, **kw)
    except ValueError:
        # as the profile's own design does (``design.design_waveform``): where the current
        # limit lets no sweep cover the map's speeds (a large disk on a small motor), the
        # plain design; the result then names each motor loss it extrapolates
        if not cover:
            raise
        d = design_multisine([case], **kw)
    return WaveformSpec(step.waveform, "multisine", {**d.params, "design": "optimal"}, design=d)


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
    cmd = np.asarray(case.commands[motor], float)
    return _table_waveform(name, np.tile(cmd, 4), 1e-3, len(cmd) * 1e-3)


def _table_waveform(name: str, samples: np.ndarray, period_s: float, natural_s: float | None = None):
    """A waveform that plays ``samples`` (held past the end)."""
    from ..profile.model import WaveformSpec

    table = _Table(samples, period_s)

    class _Spec(WaveformSpec):
        def render(self, time_s):
            return table(time_s)

        @property
        def natural_period_s(self):
            return natural_s

    return _Spec(name, "table", {})


def paper_profile(profile, step_rad_s: float):
    """The paper's procedure on ``profile``'s bench: each calibration run a speed step
    from rest (0 -> ``step_rad_s`` at 0.2 s, as bench/accuracy.py), fixed lengths; run
    with method="paper"."""
    from ..profile.model import CalibrateStep

    n = int(round(max(s.duration_s for s in profile.steps if isinstance(s, CalibrateStep))
                  / profile.bench.period_s)) + 10
    t = np.arange(n) * profile.bench.period_s
    wave = _table_waveform("paper_step", np.where(t >= 0.2, step_rad_s, 0.0), profile.bench.period_s)
    steps = [replace(s, waveform="paper_step") if isinstance(s, CalibrateStep) else s for s in profile.steps]
    return replace(profile, waveforms={**profile.waveforms, "paper_step": wave}, steps=steps)


# ------------------------------------------------------------------- running
def procedures(plant_profile: dict, step_rad_s: float) -> dict:
    """{name: (profile, method)} for the three procedures on one plant."""
    return {"classic": (plant_profile["classic"], "default"),
            "adaptive": (plant_profile["adaptive"], "default"),
            "paper": (paper_profile(plant_profile["classic"], step_rad_s), "paper")}


def run_plants(n_plants: int, seeds, *, which=("classic", "adaptive", "paper"), log=print,
               cvt_seeds=None, adaptive_excitation: str = "designed", drive_current: str = "drawn",
               current_noise_scale: float = 1.0) -> list[dict]:
    """Every procedure on the profile's own plant (one run per noise seed in ``cvt_seeds``,
    default ``seeds``) and on ``n_plants`` random plants per draw seed in ``seeds``.
    ``drive_current="mean"`` is a what-if on the random plants: every drive reports its
    current as a period mean (``period_mean_current``) instead of as drawn;
    ``current_noise_scale`` another: every drive's current noise scaled by it
    (``scaled_current_noise``; 0: noise-free current sensors).
    Returns rows {group, plant, seed, procedure, **score}."""
    from ..profile import load_profile
    from ..sim import PlantParams

    base = {k: load_profile(p) for k, p in PROFILES.items()}
    rows = []
    plant = PlantParams.from_dict(base["adaptive"].simulation)
    for seed in (seeds if cvt_seeds is None else cvt_seeds):
        for name, (prof, method) in procedures(base, 230.0).items():
            if name not in which:
                continue
            rows.append(_one("cvt plant", "cvt", seed, name, prof, plant, method, log))
    for seed in seeds:
        for index in range(n_plants):
            case, _ = random_plant(index, seed, base["classic"])
            profs, failed = {}, {}
            for k in ("classic", "adaptive"):
                try:
                    profs[k] = random_plant(index, seed, base[k],
                                            excitation=adaptive_excitation if k == "adaptive" else "drawn")[1]
                except ValueError as exc:      # the excitation design finds no waveform: a result
                    profs[k], failed[k] = base[k], f"excitation design: {exc}"
            step = float(min(0.9 * case.bench_speed_rad_s * 1.2, 330.0))
            plant = period_mean_current(case.plant) if drive_current == "mean" else case.plant
            if current_noise_scale != 1.0:
                plant = scaled_current_noise(plant, current_noise_scale)
            sampled = {f"current_{m}": "mean" if getattr(plant, f"motor_{m}").current_avg_s > 0 else "instant"
                       for m in ("in", "out")}
            for name, (prof, method) in procedures(profs, step).items():
                if name not in which:
                    continue
                if name in failed:
                    rows.append({"group": "random plants", "plant": f"{seed}/{index}", "seed": case.plant.seed,
                                 "procedure": name, "bound_s": math.nan, "reversing": case.reversing,
                                 "ratio": case.plant.ratio, "error": failed[name][:160],
                                 "bench_time_s": math.nan, "in_time": False})
                    if log:
                        log(f"  random plants  {seed}/{index:<4} {name:<9} ERROR {failed[name][:160]}")
                    continue
                rows.append(_one("random plants", f"{seed}/{index}", case.plant.seed, name, prof,
                                 plant, method, log,
                                 reversing=case.reversing, ratio=case.plant.ratio, **sampled))
    return rows


def period_mean_current(plant):
    """``plant`` with both drives reporting their current as the mean over the sample
    period instead of one current-loop instant (a what-if: an instant sample aliases the
    speed loop's ripple, from its encoder-quantised speed estimate, into the fit band
    and the level means)."""
    return replace(plant, **{f"motor_{m}": replace(getattr(plant, f"motor_{m}"), current_avg_s=plant.period_s)
                             for m in ("in", "out")})


def scaled_current_noise(plant, scale: float):
    """``plant`` with both drives' current noise scaled by ``scale`` (a what-if: how much
    of a plant's bench time its current sensors' noise costs; 0 leaves quantisation,
    cogging and the loops' own ripple as the only disturbances)."""
    if not (scale >= 0 and math.isfinite(scale)):
        raise ValueError(f"current noise scale must be a finite number >= 0, got {scale!r}")
    return replace(plant, **{f"motor_{m}": replace(getattr(plant, f"motor_{m}"),
                                                   current_noise_a=getattr(plant, f"motor_{m}").current_noise_a * scale)
                             for m in ("in", "out")})


def _one(group, plant_id, seed, name, prof, plant, method, log, **about) -> dict:
    t0 = time.perf_counter()
    try:
        res = run_inprocess(prof, plant, seed=int(seed), method=method)
        s = score(res)
        s["design_ratio"] = design_ratio(prof, res)
    except Exception as exc:          # a failure is a result here, not a crash
        s = {"error": f"{type(exc).__name__}: {str(exc)[:120]}", "bench_time_s": float("nan")}
    bound = bench_time_bound_s(prof)
    row = {"group": group, "plant": plant_id, "seed": seed, "procedure": name, "bound_s": bound, **about, **s}
    row["in_time"] = bool(s.get("meets_all")) and s["bench_time_s"] <= bound + 1e-9
    if log:
        if "error" in s:
            log(f"  {group:<14}{plant_id:>7} {name:<9} ERROR {s['error']}")
        else:
            log(f"  {group:<14}{plant_id:>7} {name:<9} bench {s['bench_time_s']:6.1f} s  Kt max "
                f"{max(s['kt']):6.3f} %  inc max {max(s['inc']):6.3f} pp  abs max {max(s['abs']):6.3f} pp"
                f"  {'meets' if s['meets'] else 'MISSES'}  ({time.perf_counter() - t0:.1f} s wall)")
    return row


def run_chain(log=print) -> list[dict]:
    """One run of each shipped profile through the real --sim CANopen chain."""
    from ..api import run_profile
    from ..profile import load_profile

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in ("adaptive", "classic"):
            t0 = time.perf_counter()
            res = run_profile(PROFILES[name], sim=True, out_dir=Path(tmp) / name, serial="CYCLE",
                              yes=True, quiet=True)
            s = score(res)
            bound = bench_time_bound_s(load_profile(PROFILES[name]))
            rows.append({"group": "--sim chain", "plant": "cvt", "seed": "", "procedure": name, "bound_s": bound,
                         "in_time": bool(s.get("meets_all")) and s["bench_time_s"] <= bound + 1e-9, **s})
            if log:
                log(f"  --sim chain    {name:<9} bench {s['bench_time_s']:6.1f} s  Kt max {max(s['kt']):.3f} %  "
                    f"inc max {max(s['inc']):.3f} pp  abs max {max(s['abs']):.3f} pp "
                    f"({time.perf_counter() - t0:.0f} s wall)")
    return rows


# ------------------------------------------------------------------- report
def _label(r: dict) -> str:
    """Summary group: random plants per draw seed (the plant id is seed/index), else the group."""
    return f"random seed {r['plant'].split('/')[0]}" if r["group"] == "random plants" else r["group"]


def summary(rows: list[dict]) -> list[dict]:
    """Per group and procedure (random plants per draw seed, then all of them)."""
    out = []
    groups = []
    for r in rows:
        for key in ((_label(r), r["procedure"]), (r["group"], r["procedure"])):
            if key not in groups:
                groups.append(key)
    groups.sort(key=lambda k: k[0] == "random plants")        # the total after the seeds
    for g, p in groups:
        rs = [r for r in rows if r["procedure"] == p and g in (r["group"], _label(r))]
        ok = [r for r in rs if "error" not in r]

        def stat(q, f):
            vals = [f(r[q]) for r in ok if r[q]]
            return (float(np.mean(vals)), float(np.max(vals))) if vals else (math.nan, math.nan)
        out.append({"group": g, "procedure": p, "runs": len(rs), "errors": len(rs) - len(ok),
                    "bench_mean": float(np.mean([r["bench_time_s"] for r in ok])) if ok else math.nan,
                    "bench_max": float(np.max([r["bench_time_s"] for r in ok])) if ok else math.nan,
                    "kt": stat("kt", max), "inc": stat("inc", max), "abs": stat("abs", max),
                    "meets": sum(bool(r.get("meets")) for r in rs) / max(len(rs), 1),
                    "meets_all": sum(bool(r.get("meets_all")) for r in rs) / max(len(rs), 1),
                    "in_time": sum(bool(r.get("in_time")) for r in rs) / max(len(rs), 1),
                    "bench_p95": float(np.percentile([r["bench_time_s"] for r in ok], 95)) if ok else math.nan,
                    "bound": float(np.nanmean([r.get("bound_s", math.nan) for r in rs])),
                    "at_max": float(np.mean([r.get("stopped_by_max", 0) for r in ok])) if ok else math.nan})
    return out


def print_table(summ: list[dict]) -> None:
    print(f"{'plants':<15}{'procedure':<10}{'runs':>5}{'fail':>5}{'bench s':>15}{'|Kt err| % (max/plant)':>24}"
          f"{'|incr err| pp':>17}{'|abs err| pp':>17}{'meet goal':>11}{'at max':>8}")
    print(f"{'':<35}{'mean    max':>15}{'mean    max':>24}{'mean    max':>17}{'mean    max':>17}")
    for s in summ:
        f2 = lambda v: f"{v[0]:7.3f} {v[1]:7.3f}"
        print(f"{s['group']:<15}{s['procedure']:<10}{s['runs']:>5}{s['errors']:>5}"
              f"{s['bench_mean']:7.1f} {s['bench_max']:7.1f}{f2(s['kt']):>24}{f2(s['inc']):>17}{f2(s['abs']):>17}"
              f"{100 * s['meets']:10.0f}%{s['at_max']:8.1f}")


def print_time_table(summ: list[dict]) -> None:
    """Every target (Kt, incremental and absolute) within the profile's bench-time bound."""
    print(f"{'plants':<15}{'procedure':<10}{'runs':>5}{'Kt+incr':>9}{'every target':>14}{'in bound':>10}"
          f"{'bench s mean':>14}{'95th pct':>10}{'bound':>8}")
    for s in summ:
        print(f"{s['group']:<15}{s['procedure']:<10}{s['runs']:>5}{100 * s['meets']:8.0f}%"
              f"{100 * s['meets_all']:13.0f}%{100 * s['in_time']:9.0f}%{s['bench_mean']:14.1f}"
              f"{s['bench_p95']:10.1f}{s['bound']:8.1f}")


def print_plants(rows: list[dict], procedure: str = "adaptive") -> None:
    """One line per random plant: its errors, time used against the bound, and why each
    missed target was missed."""
    print(f"{'plant':>7} {'kind':<7}{'ratio':>6}{'Kt %':>7}{'incr pp':>8}{'abs pp':>7}{'bench/bound s':>14}"
          f"{'at max':>7}  verdict")
    for r in rows:
        if r["group"] != "random plants" or r["procedure"] != procedure:
            continue
        kind = ("rev" if r.get("reversing") else "fwd") + "".join(
            {"instant": "i", "mean": "m"}.get(r.get(f"current_{m}"), "") for m in ("in", "out"))
        if "error" in r:
            print(f"{r['plant']:>7} {kind:<7}{r.get('ratio', math.nan):6.1f}  ERROR {r['error']}")
            continue
        verdict = "meets all in bound" if r["in_time"] else "; ".join(
            r["why_missed"] + ([] if r["bench_time_s"] <= r["bound_s"] + 1e-9 else ["over the bound"]))
        print(f"{r['plant']:>7} {kind:<7}{r.get('ratio', math.nan):6.1f}{max(r['kt']):7.3f}{max(r['inc']):8.3f}"
              f"{max(r['abs']):7.3f}{r['bench_time_s']:7.1f}/{r['bound_s']:<6.1f}{r['stopped_by_max']:7d}  {verdict}")
        if not r["in_time"]:
            short = f" (at max_s short {r['shortfall']:.1f}x)" if r.get("shortfall") else ""
            print(f"{'':>14}causes: {', '.join(r['causes'] or ['over the bound'])}{short}")
            if r.get("design_ratio"):
                print(f"{'':>14}calibration reached / design predicted: " +
                      ", ".join(f"{k} {v:.1f}x" for k, v in r["design_ratio"].items()))
    tally: dict[str, int] = {}
    for r in rows:
        if r["group"] == "random plants" and r["procedure"] == procedure and not r["in_time"]:
            for c in (r.get("causes") or [r["error"][:40] if "error" in r else "over the bound"]):
                tally[c] = tally.get(c, 0) + 1
    if tally:
        print("misses by cause (a plant may miss several targets): " +
              "; ".join(f"{c} {n}" for c, n in sorted(tally.items(), key=lambda kv: -kv[1])))
    _print_design_ratios(rows, procedure)
    _print_by_kind(rows, procedure)
    shorts = [r["shortfall"] for r in rows if r["group"] == "random plants" and r["procedure"] == procedure
              and not r["in_time"] and r.get("shortfall")]
    if shorts:
        edges = (1.5, 3.0)
        counts = np.histogram(shorts, bins=(0.0, *edges, math.inf))[0]
        print(f"plants missing at max_s, by how far the interval stayed above its target (time needed "
              f"~ factor squared): <= {edges[0]:g}x {counts[0]}, {edges[0]:g}-{edges[1]:g}x {counts[1]}, "
              f"> {edges[1]:g}x {counts[2]} (median {float(np.median(shorts)):.1f}x)")


def _print_by_kind(rows: list[dict], procedure: str) -> None:
    """Plants within the bound: forward / reversing, and by how the input drive reports
    its current (one instant, or the period mean)."""
    rs = [r for r in rows if r["group"] == "random plants" and r["procedure"] == procedure]
    parts = []
    for label, pick in (("forward", lambda r: not r.get("reversing")), ("reversing", lambda r: r.get("reversing")),
                        ("input current instant", lambda r: r.get("current_in") == "instant"),
                        ("input current period mean", lambda r: r.get("current_in") == "mean")):
        sel = [r for r in rs if pick(r)]
        if sel:
            parts.append(f"{label} {sum(bool(r.get('in_time')) for r in sel)}/{len(sel)}")
    if parts:
        print("every target within the bound: " + ", ".join(parts))


def _print_design_ratios(rows: list[dict], procedure: str) -> None:
    """Quartiles of ``design_ratio`` over every designed calibration run, and over the runs
    of plants whose Kt missed."""
    rs = [r for r in rows if r["group"] == "random plants" and r["procedure"] == procedure]
    every = [v for r in rs for v in (r.get("design_ratio") or {}).values()]
    missed = [v for r in rs for k, v in (r.get("design_ratio") or {}).items()
              if dict(zip(r.get("kt_motors", ()), r.get("kt", ()))).get(k.split()[0], 0.0) > GOAL["kt_pct"]]
    for label, vals in (("every designed calibration run", every), ("runs of the motors whose Kt missed", missed)):
        if vals:
            q = np.percentile(vals, (25, 50, 75, 90))
            print(f"{label}: interval reached / design predicted, quartiles {q[0]:.1f} {q[1]:.1f} {q[2]:.1f}x, "
                  f"90th pct {q[3]:.1f}x ({len(vals)} runs)")


def plot(rows: list[dict], path: Path) -> Path | None:
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("cycle_time: matplotlib is not installed; no plot (pip install matplotlib)")
        return None
    colours = {"classic": "tab:blue", "adaptive": "tab:green", "paper": "tab:red"}
    markers = {"cvt plant": "*", "random plants": "o", "--sim chain": "D"}
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.8))
    for ax, (q, label, goal) in zip(axes, (("kt", "max |Kt error| of the two motors, %", GOAL["kt_pct"]),
                                           ("inc", "max |incremental efficiency error|, pp", GOAL["inc_pp"]),
                                           ("abs", "max |absolute efficiency error|, pp", None))):
        for r in rows:
            if "error" in r or not r.get(q):
                continue
            ax.scatter(r["bench_time_s"], max(r[q]), c=colours[r["procedure"]], marker=markers[r["group"]],
                       s=60 if r["group"] != "random plants" else 18, alpha=0.75,
                       edgecolors="k" if r["group"] != "random plants" else "none")
        if goal is not None:
            ax.axhline(goal, color="k", ls="--", lw=0.8)
        ax.axvline(20.0, color="grey", ls=":", lw=0.8)
        ax.set_yscale("log")
        ax.set_xlabel("bench time, s")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    handles = [plt.Line2D([], [], marker="o", ls="", color=c, label=p) for p, c in colours.items()]
    handles += [plt.Line2D([], [], marker=m, ls="", color="grey", label=g) for g, m in markers.items()]
    axes[0].legend(handles=handles, fontsize=8, loc="upper right")
    fig.suptitle("gearbench cycle time vs accuracy (dashed: goal, dotted: 20 s)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m gearbench.benchmarks cycle_time", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--plants", type=int, default=10, help="random plants per draw seed (default 10)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1], help="random-plant draw seeds (default 0 1)")
    ap.add_argument("--cvt-runs", type=int, default=5, help="noise seeds on the cvt plant (default 5)")
    ap.add_argument("--procedures", nargs="+", default=["classic", "adaptive", "paper"])
    ap.add_argument("--png", default="results/cycle_time.png", help="plot file (default results/cycle_time.png)")
    ap.add_argument("--adaptive-excitation", choices=("designed", "drawn"), default="designed",
                    help="random plants' adaptive calibration: a multisine designed per motor from the "
                         "profile covering the map's speeds (default), or the drawn case's own commands "
                         "(as the classic and paper procedures; before issue 23)")
    ap.add_argument("--drive-current", choices=("drawn", "mean"), default="drawn",
                    help="random plants' drives report their current as drawn (one instant or a "
                         "period mean, default) or all as a period mean (a what-if)")
    ap.add_argument("--current-noise-scale", type=float, default=1.0, metavar="S",
                    help="random plants' current noise x S (a what-if: 0.5 a sensor twice as quiet, "
                         "0 none; default 1, as drawn)")
    ap.add_argument("--per-plant", action="store_true", help="one line per random plant: errors, time, why missed")
    ap.add_argument("--no-chain", action="store_true", help="skip the runs through the --sim CANopen chain")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    print(f"cycle_time: the cvt plant x {args.cvt_runs} noise seeds + {len(args.seeds)} draw seed(s) x "
          f"{args.plants} random plants, "
          f"procedures {', '.join(args.procedures)}; goal: Kt <= {GOAL['kt_pct']} % and incremental "
          f"efficiency <= {GOAL['inc_pp']} pp at all 12 points", flush=True)
    rows = run_plants(args.plants, args.seeds, which=tuple(args.procedures),
                      log=lambda s: print(s, flush=True), cvt_seeds=range(args.cvt_runs),
                      adaptive_excitation=args.adaptive_excitation, drive_current=args.drive_current,
                      current_noise_scale=args.current_noise_scale)
    if not args.no_chain:
        rows += run_chain(log=lambda s: print(s, flush=True))
    print()
    if args.per_plant:
        for proc in args.procedures:
            print(f"per plant, {proc}:")
            print_plants(rows, proc)
        print()
    summ = summary(rows)
    print_table(summ)
    print()
    print_time_table(summ)
    png = plot(rows, Path(args.png))
    if png:
        print(f"plot: {png}")
    print(f"benchmark time {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
