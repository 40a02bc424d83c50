"""Robustness benchmark: identification and efficiency over randomly drawn plants.

    python -m gearbench.benchmarks robustness [--cases N] [--quick] [--seed S] [--worst K]
                                              [--period-ms MS] [--encoder-counts N] [--as-drawn]
                                              [--noise-draws K [--noise-cases N]]

The accuracy benchmark checks one plant; held-out data comes from *other* motors,
drives and benches of the same kind. Each case here draws, from realistic ranges
around the dev data's kind, two motors with their drives (Kt, J, D, Coulomb
friction and its smoothing, cogging amplitude/order, current noise, encoder counts,
current-loop lag, speed-loop bandwidth, setpoint interpolation, current averaging),
an inertia disk (0.5-3x J), a calibration excitation (forward multisine like the dev
data; about one case in four a reversing multisine) and a reducer bench (ratio
3-60, mesh efficiency 0.6-0.97, Coulomb and viscous drag, input speed, braking
levels). Each calibration command is then moved to reach its motor's bench speed, as
``gearbench validate`` demands of a profile (``--as-drawn``: not moved; seeds 7/8 then
use an extrapolated motor loss on 237/252 of 300 absolute points, moved 108/87). Each
motor is calibrated with ``calibrate_motor`` (excitation check on, as
``gearbench calibrate`` runs it) by every method; the calibrations feed
``efficiency`` on the simulated bench run. Errors against the simulator's truth:
|Kt err| per motor, incremental and absolute efficiency per point at loads >= 50 %
of rated, exceptions, and the fraction of cases meeting every target. Each error
also has the standard uncertainty the method itself reports (Kt_ci95, the points'
intervals): *coverage* is the fraction of intervals holding the truth (an honest
95 % interval covers ~95 %), and a case that misses a target is *biased* when a
missed error exceeds twice its own standard uncertainty, else *noise-limited* (the
data could not do better, and the interval says so). Honest intervals are "biased" by
chance too, on the 4.6 % of errors beyond 2 sigma where sigma is half the target or
more: the per-quantity table prints that share beside the measured one
(``Outcome.chance_biased``). Deterministic for ``--seed``.
``--period-ms 4`` or ``10`` samples the same plants and commands at 250 or 100 Hz
(``with_period``): a family of rates the analysis was not tuned on.
"""
from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass, field, replace

import numpy as np

from ..analysis.calibration import calibrate_motor
from ..analysis.efficiency import (OFF_LINE_SIGMAS, efficiency, measure_windows, staircase_fit,
                                   with_level_scatter)

METHODS = ("paper-15ms", "paper", "default")
TARGETS = {"kt_pct": 0.2, "inc_pp": 0.2, "abs_pp": 0.3}
PERIOD_S = 1e-3
COVERAGE_BAND = (0.93, 0.97)   # issue 23's accepted coverage of the 95 % intervals
BIASED_SIGMAS = 2.0          # |error| > 2 x its own standard uncertainty: biased, not noise
# What the default method claims on random plants (README; tests/test_robustness.py
# checks them on all 40 plants of seed 1, the fraction with a one-sided binomial bound):
# every target met on at least half the plants, and median |error| per quantity
# (kt %, inc pp, abs pp). Seed 1 measured 23/40 meet, medians 0.050 %, 0.090 pp, 0.077 pp.
CLAIMS = {"meet_fraction": 0.5, "kt_median": 0.1, "inc_median": 0.15, "abs_median": 0.15}


@dataclass(frozen=True)
class Case:
    """One drawn plant with its excitations (everything a run needs)."""

    index: int
    plant: object                      # gearbench.sim.PlantParams
    commands: dict                     # side -> speed command of the calibration runs
    disks_kgm2: dict                   # side -> disk inertia of the loaded run
    reversing: bool
    bench_speed_rad_s: float
    levels_a: tuple                    # braking current magnitudes, trace order
    dwell_s: float
    seed: int

    def describe(self) -> str:
        p = self.plant
        parts = []
        for side, m in (("in", p.motor_in), ("out", p.motor_out)):
            bw = m.vel_kp * m.Kt / m.J / (2 * np.pi)
            parts.append(f"{side}: Kt={m.Kt:.3g} J={m.J:.2g} D={m.D:.2g} Tc={m.Tc:.3g} "
                         f"eps={m.friction_eps_rad_s:.2g} cog={m.cog_amp * 1e3:.2g}mNm/{m.cog_order} "
                         f"noise={m.current_noise_a * 1e3:.2g}mA cpr={m.counts_per_rev} "
                         f"lag={m.current_lag_s * 1e3:.2g}ms bw={bw:.3g}Hz "
                         f"interp={m.setpoint_interpolation} avg={m.current_avg_s:g} "
                         f"disk={self.disks_kgm2[side]:.2g} cmd=[{self.commands[side].min():.0f},"
                         f"{self.commands[side].max():.0f}]")
        return (f"case {self.index}{' reversing' if self.reversing else ''}; "
                + "; ".join(parts) + f"; bench n={p.ratio:.3g} eta={p.eta_mesh:.3g} "
                f"drag={p.drag_torque_nm:.3g} speed={self.bench_speed_rad_s:.0f} "
                f"levels={max(self.levels_a):.2g}A")


@dataclass
class Outcome:
    """One method on one case: errors, their reported standard uncertainties (same
    units, as the method stores them) and whether each 95 % interval holds the truth."""

    kt_err_pct: list = field(default_factory=list)
    inc_err_pp: list = field(default_factory=list)
    abs_err_pp: list = field(default_factory=list)
    kt_std_pct: list = field(default_factory=list)
    inc_std_pp: list = field(default_factory=list)
    abs_std_pp: list = field(default_factory=list)
    kt_cover: list = field(default_factory=list)
    inc_cover: list = field(default_factory=list)
    abs_cover: list = field(default_factory=list)
    error: str = ""
    abs_extrapolated: list = field(default_factory=list)   # per abs point: loss extrapolated
    motors: list = field(default_factory=list)   # per motor: what its calibration saw (``_motor_notes``)
    # eq. 18 from the braking levels' slope (zero-load level off their line), and the
    # windows' errors widened because the levels scatter beyond them (``efficiency``)
    off_line_reference: bool = False
    level_scatter: bool = False

    def _quantities(self):
        return (("kt_pct", self.kt_err_pct, self.kt_std_pct),
                ("inc_pp", self.inc_err_pp, self.inc_std_pp),
                ("abs_pp", self.abs_err_pp, self.abs_std_pp))

    def meets_targets(self) -> bool:
        if self.error or not self.kt_err_pct or not self.inc_err_pp:
            return False
        return all(max(map(abs, errs), default=0.0) <= TARGETS[key]
                   for key, errs, _ in self._quantities())

    def biased_in(self, key: str) -> bool:
        """A miss of ``key``'s target beyond ``BIASED_SIGMAS`` x its own standard uncertainty."""
        for k, errs, stds in self._quantities():
            if k == key and any(abs(e) > TARGETS[k] and abs(e) > BIASED_SIGMAS * s
                                for e, s in zip(errs, stds)):
                return True
        return False

    def chance_biased(self, key: str | None = None) -> float:
        """How likely a ``biased`` verdict (with ``key``: a biased miss of that quantity)
        would be if every error were normal with its own reported standard uncertainty
        (honest intervals): 1 − Π (1 − 2Φ(−max(target/σ, ``BIASED_SIGMAS``))) over the
        points, taken independent (the efficiency points share their Kt, so a plant's is
        at most this). Where σ is a good part of the target, 2 sigma draws miss it by
        chance: 4.6 % of honest errors lie beyond 2 sigma."""
        q = 1.0
        for k, errs, stds in self._quantities():
            if key is not None and k != key:
                continue
            for s in stds:
                x = max(TARGETS[k] / s, BIASED_SIGMAS) if s > 0 else math.inf
                q *= 1.0 - math.erfc(x / math.sqrt(2.0))
        return 1.0 - q

    def verdict(self) -> str:
        """``meet``, ``error``, ``biased`` (a missed error > 2 sigma of its own
        uncertainty) or ``noise`` (every missed error within 2 sigma)."""
        if self.error or not self.kt_err_pct or not self.inc_err_pp:
            return "error"
        if self.meets_targets():
            return "meet"
        for key, errs, stds in self._quantities():
            for e, s in zip(errs, stds):
                if abs(e) > TARGETS[key] and abs(e) > BIASED_SIGMAS * s:
                    return "biased"
        return "noise"


# ----------------------------------------------------------------------- drawing
def _loguniform(rng, lo, hi) -> float:
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def _draw_motor(rng):
    from ..sim import MotorParams

    kt = _loguniform(rng, 0.02, 0.15)
    j = _loguniform(rng, 5e-6, 8e-5)
    bw_hz = _loguniform(rng, 3.0, 30.0)
    kp = 2 * np.pi * bw_hz * j / kt               # crossover ≈ kp·Kt/J
    ki = kp * 2 * np.pi * bw_hz / rng.uniform(3.0, 6.0)
    return MotorParams(
        Kt=kt, J=j, D=_loguniform(rng, 3e-7, 1e-5), Tc=float(rng.uniform(0.0, 0.02)),
        friction_eps_rad_s=_loguniform(rng, 0.005, 0.2),
        cog_amp=float(rng.uniform(0.0, 0.003)), cog_order=int(rng.integers(4, 25)),
        current_noise_a=float(rng.uniform(0.002, 0.008)), current_resolution_a=0.001,
        counts_per_rev=int(round(_loguniform(rng, 2000, 20000))),
        current_lag_s=float(rng.uniform(0.2e-3, 1e-3)),
        setpoint_interpolation=int(rng.integers(0, 2)),
        current_avg_s=float(rng.choice([0.0, 1e-3])),
        vel_kp=kp, vel_ki=ki, current_limit_a=3.0, rated_current_a=1.0)


def _draw_command(rng, motor, disk_kgm2: float, reversing: bool, duration_s: float,
                  cover_rad_s: float | None = None) -> np.ndarray:
    """Multisine speed command on harmonics of 1/duration up to 10 Hz (as the dev data),
    amplitude reduced (never below 40 %) where the acceleration it asks for would need
    more than the drive's current limit — a test engineer would do the same."""
    from ..sim import waveforms as wf

    t = wf.time_base(duration_s, PERIOD_S)
    f0 = 1.0 / duration_s
    harmonics = np.arange(1, int(10.0 / f0) + 1)
    k = np.sort(rng.choice(harmonics, size=int(rng.integers(5, 10)), replace=False))
    if reversing:
        amp = rng.uniform(60.0, 200.0)
        offset = rng.uniform(-0.2, 0.2) * amp
        if cover_rad_s is not None:     # a swing that can reach the bench speed (limits allowing)
            amp = max(amp, 1.05 * cover_rad_s)
    else:
        offset = rng.uniform(80.0, 250.0)
        amp = min(rng.uniform(0.4, 0.9) * offset, 400.0 - offset)
    cmd = wf.multisine(t, amplitude=1.0, freqs_hz=k * f0, offset=0.0,
                       phases="random", seed=int(rng.integers(1 << 30)))
    # rms acceleration x 3 as the peak the loop actually asks (it low-passes the command).
    acc = 3.0 * float(np.std(np.gradient(cmd, PERIOD_S)))
    i_peak = ((motor.J + disk_kgm2) * amp * acc + motor.Tc
              + motor.D * (abs(offset) + amp)) / motor.Kt
    amp *= float(np.clip(motor.current_limit_a / i_peak, 0.4, 1.0))
    if cover_rad_s is not None:
        offset = _covering_offset(offset, amp * cmd, cover_rad_s, reversing)
    return offset + amp * cmd


def _covering_offset(offset: float, swing: np.ndarray, speed_rad_s: float, reversing: bool) -> float:
    """The offset moved (the swing, and so the current it asks, unchanged) so the run's
    speeds reach the bench speed, as ``gearbench validate`` demands of a profile (no
    motor loss extrapolated). The speed loop rounds the command's brief extremes off, so
    its 2nd/98th percentiles, not its extremes, reach 5 % beyond the bench speed. A
    forward run stays forward (its slowest speed at least half the bench's); a reversing
    run keeps reversing (down to 10 % of its swing below zero): where its swing is too
    small it still falls short, and the result says so."""
    lo, hi = offset + np.percentile(swing, 2.0), offset + np.percentile(swing, 98.0)
    if hi < 1.05 * speed_rad_s:
        offset += 1.05 * speed_rad_s - hi
    elif lo > 0.95 * speed_rad_s:
        offset -= lo - 0.95 * speed_rad_s
    if reversing:
        offset = float(np.clip(offset, 0.9 * swing.min(), -0.9 * swing.min()))
    else:
        offset = max(offset, 0.5 * speed_rad_s - float(swing.min()))
    return offset


def _scaled_motor(m, kt: float):
    """Same motor family with another Kt: J and the speed-loop gains scale with it, so
    the loop bandwidth and the mechanical time constants stay as drawn."""
    s = kt / m.Kt
    return replace(m, Kt=kt, J=m.J * s, D=m.D * s, vel_kp=m.vel_kp, vel_ki=m.vel_ki)


def draw_case(index: int, seed: int = 0, *, duration_s: float = 3.0, dwell_s: float = 4.0,
              cover_bench_speed: bool = False) -> Case:
    """Case ``index`` of the benchmark drawn with ``seed`` (deterministic);
    ``cover_bench_speed``: each calibration command moved (``_covering_offset``; a
    reversing one's swing raised to the speed first, the current limit still capping it)
    so its speeds reach the motor's bench speed. Everything else is drawn identically."""
    from ..sim import PlantParams

    rng = np.random.default_rng([seed, index])
    reversing = bool(rng.uniform() < 0.25)
    motors = {"in": _draw_motor(rng), "out": _draw_motor(rng)}
    disks = {s: float(rng.uniform(0.5, 3.0) * m.J) for s, m in motors.items()}
    ratio = _loguniform(rng, 3.0, 60.0)
    eta = float(rng.uniform(0.6, 0.97))
    drag = float(rng.uniform(0.0, 0.02))
    drag_visc = float(rng.uniform(0.0, 1e-5))
    speed = float(rng.uniform(80.0, 300.0))
    # A bench is sized so full load moves the input current by 0.15-0.6 A (dev: 0.24 A)
    # with the output motor within 60 % of its limit; where the drawn pair cannot, the
    # output motor is swapped for a bigger one of the same family (as a designer would).
    mi, mo = motors["in"], motors["out"]
    full = float(rng.uniform(0.5, 0.6 * mo.current_limit_a))
    di_in = max(0.15, min(float(rng.uniform(0.15, 0.6)), 0.3 * full / (mi.Kt * ratio * eta)))
    kt_need = di_in * mi.Kt * ratio * eta / full
    if kt_need > mo.Kt:
        mo = _scaled_motor(mo, kt_need)
        disks["out"] *= kt_need / motors["out"].Kt
    full = di_in * mi.Kt * ratio * eta / mo.Kt
    base_in = (mi.Tc + mi.D * speed + drag + drag_visc * speed) / mi.Kt
    mi = replace(mi, current_limit_a=max(mi.current_limit_a, 1.5 * (base_in + di_in)))
    mo = replace(mo, rated_current_a=full)
    cover = {"in": speed, "out": speed / ratio} if cover_bench_speed else {"in": None, "out": None}
    commands = {"in": _draw_command(rng, mi, disks["in"], reversing, duration_s, cover["in"]),
                "out": _draw_command(rng, mo, disks["out"], reversing, duration_s, cover["out"])}
    plant = PlantParams(motor_in=mi, motor_out=mo, ratio=ratio, eta_mesh=eta,
                        drag_torque_nm=drag, drag_viscous=drag_visc, period_s=PERIOD_S,
                        seed=int(rng.integers(1 << 30)))
    levels = tuple(full * x for x in (0.0, 0.25, 0.5, 0.75, 1.0, 0.0))
    return Case(index, plant, commands, disks, reversing, speed, levels, dwell_s,
                int(rng.integers(1 << 30)))


# ----------------------------------------------------------------------- running
def drive_description(motor) -> dict:
    """What a station knows of the drawn drive from its description, as the analysis
    reads it (``identify.drive_sampling``): whether it ramps between SYNC setpoints
    (CiA 402 cyclic synchronous velocity with 0x60C2 set) or steps, and whether its
    current object is a period mean or one sample, and its current limit (CiA 402 max
    current 0x6073, a drive setting), and its loop as set: speed-loop P gain, current-loop
    time constant and speed-loop period (``identify.declared_kick``). Nothing of the motor."""
    return {"setpoint": "interpolated" if motor.setpoint_interpolation else "step",
            "current": "mean" if motor.current_avg_s > 0 else "instant",
            "current_limit_a": float(motor.current_limit_a),
            "speed_kp_a_s_per_rad": float(motor.vel_kp),
            "current_loop_time_constant_s": float(motor.current_lag_s),
            "speed_loop_period_s": float(motor.loop_period_s)}


def simulate_case(case: Case) -> dict:
    """Calibration runs per side (unloaded, loaded) and the bench trace."""
    from ..sim import simulate_bench
    from ..sim import waveforms as wf

    runs = simulate_runs(case)
    period_s = case.plant.period_s
    t = wf.time_base(case.dwell_s * len(case.levels_a), period_s)
    cin = wf.ramp(t, slope=360.0, final=case.bench_speed_rad_s)
    cout = -wf.staircase(t, levels=list(case.levels_a), dwell_s=case.dwell_s)
    bench = simulate_bench(case.plant, cin, cout, seed=case.plant.seed)
    return {"runs": runs, "bench": bench}


def simulate_runs(case: Case) -> dict:
    """The calibration runs alone: side -> (unloaded, loaded) traces."""
    from ..sim import simulate_motor

    runs = {}
    period_s = case.plant.period_s
    for k, (side, motor) in enumerate((("in", case.plant.motor_in), ("out", case.plant.motor_out))):
        s = case.seed + 10 * k
        cmd = case.commands[side]
        runs[side] = (simulate_motor(motor, cmd, seed=s, period_s=period_s),
                      simulate_motor(motor, cmd, disk_kgm2=case.disks_kgm2[side], seed=s + 1,
                                     period_s=period_s))
        for trace in runs[side]:
            trace.meta["drive"] = drive_description(motor)
    return runs


def run_case(case: Case, methods=METHODS, data: dict | None = None) -> dict[str, Outcome]:
    """Every method on one case → {method: Outcome}. Exceptions are recorded, not raised."""
    from ..sim import bench_operating_point

    data = data or simulate_case(case)
    plant = case.plant
    out = {}
    for method in methods:
        oc = Outcome()
        out[method] = oc
        try:
            cals = {}
            for side, motor in (("in", plant.motor_in), ("out", plant.motor_out)):
                u, lo = data["runs"][side]
                cal = cals[side] = calibrate_motor(u, lo, case.disks_kgm2[side], method=method)
                oc.kt_err_pct.append(100 * (cal.Kt / motor.Kt - 1))
                oc.kt_std_pct.append(100 * cal.Kt_std / motor.Kt)
                oc.kt_cover.append(cal.Kt_ci95[0] <= motor.Kt <= cal.Kt_ci95[1])
                oc.motors.append(_motor_notes(cal, motor))
            res = efficiency(data["bench"], cals["in"], cals["out"])
            wins = measure_windows(data["bench"])
            scat = with_level_scatter(wins)
            oc.level_scatter = scat != wins
            fits = [staircase_fit([v for v in scat if v.in_command == c])
                    for c in {v.in_command for v in scat}]
            oc.off_line_reference = any(f is not None and f["off_line_sigmas"] > OFF_LINE_SIGMAS
                                        for f in fits)
            for p in res.points:
                if abs(p.window.out_command) < 0.5 * plant.motor_out.rated_current_a - 1e-12:
                    continue
                truth = bench_operating_point(plant, p.window.in_command, p.window.out_command)
                for kind, errs, stds, cover in (("incremental", oc.inc_err_pp, oc.inc_std_pp, oc.inc_cover),
                                                ("absolute", oc.abs_err_pp, oc.abs_std_pp, oc.abs_cover)):
                    value, (lo_, hi_) = getattr(p, f"eta_{kind}"), getattr(p, f"eta_{kind}_ci95")
                    errs.append(100 * (value - truth[f"eta_{kind}"]))
                    stds.append(100 * getattr(p, f"eta_{kind}_std"))
                    cover.append(lo_ <= truth[f"eta_{kind}"] <= hi_)
                oc.abs_extrapolated.append(p.loss_extrapolated)
        except Exception as exc:            # a failure is a result here, not a crash
            oc.error = f"{type(exc).__name__}: {str(exc)[:160]}"
    return out


def _motor_notes(cal, motor) -> dict:
    """What one motor's calibration saw: the share of each run left out as stuck, whether
    the setpoint-step term was kept, and the drive's setpoint/current sampling (truth)."""
    sp = cal.fit.get("setpoint_step") or {}
    return {"left_out": tuple(float((cal.fit.get(r) or {}).get("left_out_share", 0.0))
                              for r in ("unloaded", "loaded")),
            "step_kept": bool(sp.get("kept", False)),
            "stepping_sampled": bool(not motor.setpoint_interpolation and not motor.current_avg_s)}


def causes(o: Outcome) -> str:
    """Which quantities miss their target, each motor's Kt error ± its standard
    uncertainty, and the conditions measured to go with misses:

    * ``stuck NN%``: a calibration run left NN % of itself out as stuck (the drive's
      current stays below the breakaway while its speed loop winds up; no Kt information
      there: seed 7 case 94's output motor sits still on 98 % of a ±56 rad/s command);
    * ``stepping``: the drawn drive steps its speed setpoint at each SYNC *and* reports
      an instantaneous current sample (``+term``: the shared setpoint-step term was
      kept). The sample then misses the kick's period mean: the unloaded run's b2 from
      the sample is high by 0.5-2.5 % at any filter cutoff (10-150 Hz), also with a
      noise-free current (seed 8 case 11 input: +0.87 %, +0.04 % from the period mean).
      The calibration traces carry the drive's description (``drive_description``), so
      the fit uses the physical model (``identify.drive_loop._setpoint_steps``: one c for both
      runs, no current delay); what remains is the kick's closed-loop feedback;
    * ``zero-load off line``: the zero-load level lay more than ``OFF_LINE_SIGMAS`` off
      the braking levels' line (the mesh's power flow reversing at no load), so eq. 18
      came from their slope (``efficiency.staircase_fit``);
    * ``level scatter``: the levels scattered about their line beyond their window
      errors and those were widened (``efficiency.with_level_scatter``);
    * ``loss extrapolated``: an absolute-efficiency point beyond its target used a motor
      loss extrapolated beyond its calibration's speed range (``loss_extrapolated``: a
      reversing run within ±90 rad/s gives the input motor's viscous loss at a 115-292
      rad/s bench speed; seed 3's six reversing misses of abs alone are within target
      with that motor's true loss).
    """
    if o.error:
        return "exception"
    missed = [q for q, errs, _ in o._quantities() if max(map(abs, errs), default=0.0) > TARGETS[q]]
    tags = []
    for side, m, e, sd in zip(("in", "out"), o.motors, o.kt_err_pct, o.kt_std_pct):
        t = [f"Kt {e:+.3f}±{sd:.3f} %"]
        if max(m["left_out"]) > 0.5:
            t.append(f"stuck {100 * max(m['left_out']):.0f}%")
        if m["stepping_sampled"]:
            t.append("stepping" + ("+term" if m["step_kept"] else ""))
        tags.append(f"{side}: {', '.join(t)}")
    if o.off_line_reference:
        tags.append("zero-load off line")
    if o.level_scatter:
        tags.append("level scatter")
    if any(abs(e) > TARGETS["abs_pp"] and x for e, x in zip(o.abs_err_pp, o.abs_extrapolated)):
        tags.append("loss extrapolated")
    tagged = any(k in t for t in tags
                 for k in ("stuck", "stepping", "off line", "scatter", "extrapolated"))
    return (f"missed {','.join(missed) or '-'}; " + "; ".join(tags)
            + ("" if tagged else "; no tagged condition"))


def print_causes(cases, outcomes, method: str = "default") -> None:
    """Every case that misses a target, its verdict and ``causes``, then counts per tag."""
    print(f"\ncases missing a target ({method}):")
    tally = {}
    for c, out in zip(cases, outcomes):
        o = out[method]
        v = o.verdict()
        if v == "meet":
            continue
        text = causes(o)
        print(f"  case {c.index:3d} {'rev' if c.reversing else 'fwd'} {v:>6}: {text}")
        for tag in ("stuck", "stepping", "zero-load off line", "level scatter",
                    "loss extrapolated", "no tagged condition", "exception"):
            if tag in text:
                tally[(v, tag)] = tally.get((v, tag), 0) + 1
    for (v, tag), n in sorted(tally.items()):
        print(f"  {v:>6} with {tag}: {n}")


def with_encoder(case: Case, counts_per_rev: int) -> Case:
    """``case`` with both motors' encoders at ``counts_per_rev`` (the same plants behind
    another encoder: a 20- or 23-bit absolute encoder resolves what a 2,000-20,000-count
    one, as drawn, reads as standstill)."""
    p = case.plant
    plant = replace(p, motor_in=replace(p.motor_in, counts_per_rev=int(counts_per_rev)),
                    motor_out=replace(p.motor_out, counts_per_rev=int(counts_per_rev)))
    return replace(case, plant=plant)


def with_period(case: Case, period_s: float) -> Case:
    """``case`` sampled every ``period_s`` (a whole multiple of the drawn 1 ms) instead: the
    same plants and commands (every k-th sample of them) behind a bus master that syncs
    at 250 or 100 Hz; a drive that reports its current as the period mean averages the
    new period."""
    k = int(round(period_s / PERIOD_S))
    if k < 1 or abs(k * PERIOD_S - period_s) > 1e-12:
        raise ValueError(f"period_s must be a whole multiple of {PERIOD_S * 1e3:g} ms (got {period_s * 1e3:g} ms)")
    p = case.plant

    def motor(m):
        return replace(m, current_avg_s=period_s if m.current_avg_s > 0 else 0.0)
    plant = replace(p, motor_in=motor(p.motor_in), motor_out=motor(p.motor_out), period_s=period_s)
    return replace(case, plant=plant, commands={s: np.asarray(c)[::k].copy() for s, c in case.commands.items()})


def run(cases: int, seed: int = 0, *, quick: bool = False, methods=METHODS,
        encoder_counts: int | None = None, cover_bench_speed: bool = True, period_s: float = PERIOD_S):
    """Draw and run ``cases`` cases → (list of Case, list of {method: Outcome});
    ``encoder_counts``: every motor's encoder at that many counts per revolution;
    ``cover_bench_speed``: calibrations that reach the bench speeds (``draw_case``);
    ``period_s``: the sample period (``with_period``; drawn at 1 ms)."""
    kw = {"duration_s": 3.0, "dwell_s": 2.5 if quick else 4.0, "cover_bench_speed": cover_bench_speed}
    drawn = [draw_case(k, seed, **kw) for k in range(cases)]
    if encoder_counts:
        drawn = [with_encoder(c, encoder_counts) for c in drawn]
    if period_s != PERIOD_S:
        drawn = [with_period(c, period_s) for c in drawn]
    return drawn, [run_case(c, methods) for c in drawn]


# ----------------------------------------------------------------------- report
def _stats(values) -> str:
    if not values:
        return f"{'-':>23}"
    a = np.abs(values)
    return f"{a.mean():7.3f} {np.percentile(a, 95):7.3f} {a.max():7.3f}"


def summarise(outcomes: list[dict[str, Outcome]], methods=METHODS) -> dict[str, dict]:
    """Per method: pooled errors, interval coverage, exceptions, the fraction of cases
    meeting targets and the misses split into noise-limited and biased."""
    out = {}
    for m in methods:
        ocs = [o[m] for o in outcomes]
        verdicts = [o.verdict() for o in ocs]
        n = max(len(ocs), 1)
        out[m] = {"kt": [e for o in ocs for e in o.kt_err_pct],
                  "inc": [e for o in ocs for e in o.inc_err_pp],
                  "abs": [e for o in ocs for e in o.abs_err_pp],
                  "cover": {q: _fraction([c for o in ocs for c in getattr(o, f"{q}_cover")])
                            for q in ("kt", "inc", "abs")},
                  "cover_abs_extrapolated": _fraction(
                      [c for o in ocs for c, x in zip(o.abs_cover, o.abs_extrapolated) if x]),
                  "n_abs_extrapolated": sum(x for o in ocs for x in o.abs_extrapolated),
                  "fail": sum(bool(o.error) for o in ocs),
                  "biased_by": {q: sum(o.biased_in(k) for o in ocs) / n
                                for q, k in (("kt", "kt_pct"), ("inc", "inc_pp"), ("abs", "abs_pp"))},
                  # what honest intervals would give (``Outcome.chance_biased``)
                  "chance_by": {q: sum(o.chance_biased(k) for o in ocs if not o.error) / n
                                for q, k in (("kt", "kt_pct"), ("inc", "inc_pp"), ("abs", "abs_pp"))},
                  "chance": sum(o.chance_biased() for o in ocs if not o.error) / n,
                  # median |error| / own sigma: 0.674 for honest normal errors; below it the
                  # intervals are wider than the errors (coverage near 100 % says the same
                  # only once it saturates)
                  "z_median": {q: _median_z(ocs, k)
                               for q, k in (("kt", "kt_pct"), ("inc", "inc_pp"), ("abs", "abs_pp"))},
                  "honest": {q: honest_coverage_range(u) for q, u in _units(ocs).items()},
                  "ok": verdicts.count("meet") / n,
                  "noise": verdicts.count("noise") / n,
                  "biased": verdicts.count("biased") / n}
    return out


def honest_coverage_range(units: int, level: float = 0.95, band=COVERAGE_BAND) -> dict:
    """What perfectly honest 95 % intervals give on ``units`` independent units (motors
    for Kt; plants for the efficiencies, whose points at one speed share a slope and a
    Kt ratio): the central 95 % range of their coverage (binomial) and the probability
    it falls inside ``band``. The spread a coverage figure has before it says anything.

    >>> honest_coverage_range(100)["range"]
    (0.9, 0.99)
    """
    from scipy import stats

    if units <= 0:
        return {"range": (math.nan, math.nan), "p_band": math.nan}
    b = stats.binom(units, level)
    lo, hi = (float(b.ppf(q)) / units for q in (0.025, 0.975))
    inside = [k for k in range(units + 1) if band[0] - 1e-12 <= k / units <= band[1] + 1e-12]
    return {"range": (lo, hi), "p_band": float(sum(b.pmf(k) for k in inside))}


def _units(ocs: list[Outcome]) -> dict[str, int]:
    """Independent units per quantity: motors with a Kt; plants with efficiency points."""
    return {"kt": sum(len(o.kt_cover) for o in ocs), "inc": sum(bool(o.inc_cover) for o in ocs),
            "abs": sum(bool(o.abs_cover) for o in ocs)}


def _median_z(ocs: list[Outcome], key: str) -> float:
    """Median of |error| / reported standard uncertainty over every point of ``key``
    (``Outcome._quantities``: "kt_pct", "inc_pp" or "abs_pp"); nan without points."""
    z = [abs(e) / s for o in ocs for k, errs, stds in o._quantities() if k == key
         for e, s in zip(errs, stds) if s > 0]
    return float(np.median(z)) if z else float("nan")


def _fraction(flags) -> float:
    return float(np.mean(flags)) if flags else float("nan")


def _direction_groups(cases: list[Case]) -> list[tuple[str, list[int]]]:
    """The tables' rows: all plants, forward-only and reversing calibrations (case indices)."""
    return [("all", list(range(len(cases)))),
            ("forward", [k for k, c in enumerate(cases) if not c.reversing]),
            ("reversing", [k for k, c in enumerate(cases) if c.reversing])]


def _group_summaries(cases: list[Case], outcomes: list[dict[str, Outcome]], methods):
    """[(row label, {method: summary})] for the non-empty direction groups."""
    return [(f"{name} ({len(idx)})", summarise([outcomes[k] for k in idx], methods))
            for name, idx in _direction_groups(cases) if idx]


def print_table(cases: list[Case], outcomes: list[dict[str, Outcome]], methods=METHODS) -> None:
    print(f"{'cases':<14}{'method':<12}{'|Kt err| %':>23}   {'|incr err| pp':>23}   "
          f"{'|abs err| pp':>23}  {'95% coverage':>14}  fail  meet noise biased")
    print(f"{'':<26}{'mean   95pct     max':>23}   {'mean   95pct     max':>23}   "
          f"{'mean   95pct     max':>23}  {'Kt  incr   abs':>14}")
    for label, s in _group_summaries(cases, outcomes, methods):
        for m in methods:
            r = s[m]
            cov = " ".join(f"{100 * r['cover'][q]:4.0f}" for q in ("kt", "inc", "abs"))
            print(f"{label:<14}{m:<12}{_stats(r['kt'])}   {_stats(r['inc'])}   "
                  f"{_stats(r['abs'])}  {cov:>14}  {r['fail']:4d}  {100 * r['ok']:3.0f}%  "
                  f"{100 * r['noise']:3.0f}%   {100 * r['biased']:3.0f}%")


def print_quantities(cases: list[Case], outcomes: list[dict[str, Outcome]], methods=METHODS) -> None:
    """Per quantity, forward and reversing: 95 % coverage, the share of plants with a
    biased miss (beyond the target and beyond 2 sigma of the method's own uncertainty), and
    the coverage range honest intervals would show on as many plants."""
    rows = _group_summaries(cases, outcomes, methods)
    qs = ("kt", "inc", "abs")
    print(f"\n{'cases':<16}{'method':<12}{'coverage %  Kt  incr   abs':>28}   "
          f"{'biased %  Kt  incr   abs':>26}   {'by chance %  Kt  incr   abs  plants':>37}   "
          f"{'median |err|/sd  Kt  incr  abs':>31}")
    for label, s in rows:
        for m in methods:
            r = s[m]
            cov = " ".join(f"{100 * r['cover'][q]:5.1f}" for q in qs)
            bia = " ".join(f"{100 * r['biased_by'][q]:5.1f}" for q in qs)
            cha = " ".join(f"{100 * r['chance_by'][q]:5.1f}" for q in qs)
            zm = " ".join(f"{r['z_median'][q]:5.2f}" for q in qs)
            print(f"{label:<16}{m:<12}{cov:>28}   {bia:>26}   {cha:>29} "
                  f"{100 * r['chance']:6.1f}   {zm:>31}")
    band = "P(in %g-%g %% band)  Kt  incr   abs" % tuple(100 * b for b in COVERAGE_BAND)
    print(f"\n{'cases':<16}{'method':<12}{'honest coverage range %  Kt      incr       abs':>50}   {band:>35}")
    for label, s in rows:
        for m in methods:
            h = s[m]["honest"]
            rng = " ".join(f"{100 * h[q]['range'][0]:4.0f}-{100 * h[q]['range'][1]:<4.0f}" for q in qs)
            pb = " ".join(f"{h[q]['p_band']:5.2f}" for q in qs)
            print(f"{label:<16}{m:<12}{rng:>50}   {pb:>35}")
    print("honest coverage range: where 95 % of perfectly honest intervals' coverage falls on these "
          "units (motors for Kt, plants for the efficiencies), binomial; P: that it falls in the band")
    print("by chance: the biased share honest intervals would give (every error normal with its "
          "own reported sigma, points independent: a plant's is at most that)")
    print("median |err|/sd: 0.67 for honest normal errors; below it the intervals are wider than "
          "the errors")


def noise_scatter(cases: list[Case], draws: int) -> list[dict]:
    """Each case's calibrations repeated on ``draws`` fresh noise draws (the same plant,
    commands and encoder; only the noise seeds change) → per motor: its drive kind, the
    Kt errors' spread over the draws (what noise alone does, %), the mean reported
    standard uncertainty (%) and the mean error (what the plant does to every draw alike:
    model error, %). An honest statistical σ is close to the spread; the reported σ also
    holds the model-error terms, so it may exceed the spread where the mean error shows
    them. Draws the calibration refuses are left out (counted in ``refused``)."""
    out = []
    for case in cases:
        per = {side: {"err": [], "std": [], "stat": [], "refused": 0} for side in ("in", "out")}
        for d in range(draws):
            runs = simulate_runs(replace(case, seed=case.seed + 7919 * (d + 1)))
            for side in ("in", "out"):
                motor = getattr(case.plant, f"motor_{side}")
                try:
                    cal = calibrate_motor(*runs[side], case.disks_kgm2[side])
                except Exception:       # a refusal is a result here, not a crash
                    per[side]["refused"] += 1
                    continue
                per[side]["err"].append(100 * (cal.Kt / motor.Kt - 1))
                per[side]["std"].append(100 * cal.Kt_std / motor.Kt)
                per[side]["stat"].append(100 * cal.fit.get("Kt_std_statistical", cal.Kt_std) / motor.Kt)
        for side, r in per.items():
            if len(r["err"]) < 2:
                continue
            out.append({"case": case.index, "side": side, "kind": drive_kind(getattr(case.plant, f"motor_{side}")),
                        "spread_pct": float(np.std(r["err"], ddof=1)), "std_pct": float(np.mean(r["std"])),
                        "stat_pct": float(np.mean(r["stat"])), "mean_err_pct": float(np.mean(r["err"])),
                        "draws": len(r["err"]), "refused": r["refused"]})
    return out


def print_noise_scatter(rows: list[dict], draws: int) -> None:
    """Per drive kind: the median ratio of the statistical σ Kt reports to the Kt spread
    over fresh noise (1: honest for noise; a ratio from K draws is itself uncertain by
    about 1/√(2(K−1))), the share of motors below 0.7 and above 1.5, and the median of
    |mean error| / spread (above ~1: the plant's own model error outweighs the noise)."""
    print(f"\nKt over {draws} fresh noise draws per plant (same plants and commands):")
    print(f"  {'drive kind (setpoint/current)':<30}{'motors':>7}{'stat σ / spread':>17}{'< 0.7':>8}{'> 1.5':>8}"
          f"{'total σ / spread':>18}{'|mean err| / spread':>21}")
    for kind in sorted({r["kind"] for r in rows}) + ["all"]:
        sel = [r for r in rows if kind in ("all", r["kind"]) and r["spread_pct"] > 0]
        if not sel:
            continue
        ratio = np.array([r["stat_pct"] / r["spread_pct"] for r in sel])
        total = np.array([r["std_pct"] / r["spread_pct"] for r in sel])
        bias = np.array([abs(r["mean_err_pct"]) / r["spread_pct"] for r in sel])
        print(f"  {kind:<30}{len(sel):>7}{np.median(ratio):>17.2f}{100 * np.mean(ratio < 0.7):>7.0f}%"
              f"{100 * np.mean(ratio > 1.5):>7.0f}%{np.median(total):>18.2f}{np.median(bias):>21.2f}")


def drive_kind(motor) -> str:
    """How the drive meets the bus master (``drive_description``): setpoint stepped or
    interpolated at each SYNC, current one instant or the period mean."""
    d = drive_description(motor)
    return f"{d['setpoint']}/{d['current']}"


def kt_by_drive_kind(cases: list[Case], outcomes: list[dict[str, Outcome]], method: str = "default") -> dict:
    """Per drive kind (``drive_kind``): motors, Kt coverage and the mean of error/σ (a
    model error shows as a mean far from 0 where the coverage falls)."""
    rows: dict[str, list] = {}
    for case, oc in zip(cases, outcomes):
        o = oc[method]
        for motor, e, s, c in zip((case.plant.motor_in, case.plant.motor_out), o.kt_err_pct, o.kt_std_pct,
                                  o.kt_cover):
            rows.setdefault(drive_kind(motor), []).append((e / s if s > 0 else 0.0, c))
    return {k: {"motors": len(v), "cover": _fraction([c for _, c in v]), "mean_z": float(np.mean([z for z, _ in v]))}
            for k, v in sorted(rows.items())}


def print_drive_kinds(cases, outcomes, method: str = "default") -> None:
    print(f"\n{method}: Kt per drive kind (setpoint / current)   motors  coverage %  mean error/σ")
    for kind, r in kt_by_drive_kind(cases, outcomes, method).items():
        print(f"  {kind:<40}{r['motors']:6d}  {100 * r['cover']:10.1f}  {r['mean_z']:+12.2f}")


def print_worst(cases, outcomes, k: int, method: str = "default") -> None:
    def score(o: Outcome) -> float:
        if o.error:
            return np.inf
        return max([abs(e) / TARGETS["kt_pct"] for e in o.kt_err_pct]
                   + [abs(e) / TARGETS["inc_pp"] for e in o.inc_err_pp]
                   + [abs(e) / TARGETS["abs_pp"] for e in o.abs_err_pp] + [0.0])
    order = sorted(range(len(cases)), key=lambda j: -score(outcomes[j][method]))
    print(f"\nworst {k} cases for {method} (score = worst error / target):")
    for j in order[:k]:
        o = outcomes[j][method]
        print(f"  score {score(o):6.2f} {o.verdict():>6}  Kt% {_pm(o.kt_err_pct, o.kt_std_pct)} "
              f"inc {_pm(o.inc_err_pp, o.inc_std_pp)} abs {_pm(o.abs_err_pp, o.abs_std_pp)} "
              f"{o.error}")
        print(f"    {cases[j].describe()}")


def _pm(errs, stds) -> str:
    return "[" + ", ".join(f"{e:.3f}±{s:.3f}" for e, s in zip(errs, stds)) + "]"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m gearbench.benchmarks robustness", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", type=int, default=40, help="random plants (default 40)")
    ap.add_argument("--quick", action="store_true", help="12 cases, shorter bench levels")
    ap.add_argument("--seed", type=int, default=0, help="draw seed (default 0)")
    ap.add_argument("--worst", type=int, default=0, help="list the K worst cases of the default")
    ap.add_argument("--causes", action="store_true",
                    help="list every case the default misses with its measured conditions")
    ap.add_argument("--methods", default=",".join(METHODS),
                    help=f"comma-separated identification methods (default {','.join(METHODS)}; "
                         f"also accel, torque, iv: the default's formulations side by side)")
    ap.add_argument("--encoder-counts", type=int, default=None, metavar="N",
                    help="every motor's encoder at N counts/rev instead of as drawn "
                         "(2,000-20,000), e.g. 1048576 for a 20-bit absolute encoder")
    ap.add_argument("--period-ms", type=float, default=PERIOD_S * 1e3, metavar="MS",
                    help="sample period in ms, a whole multiple of 1 (default 1; e.g. 4 or 10: "
                         "the same plants and commands sampled at 250 or 100 Hz)")
    ap.add_argument("--as-drawn", action="store_true",
                    help="calibration commands as drawn, without moving them to reach the bench "
                         "speeds (the draws before 2026-12-03: most absolute points then use an "
                         "extrapolated motor loss)")
    ap.add_argument("--noise-draws", type=int, default=0, metavar="K",
                    help="also repeat the first --noise-cases plants' calibrations on K fresh "
                         "noise draws: each drive kind's reported Kt sigma against the noise's "
                         "own spread (is the interval honest for noise, where model error starts)")
    ap.add_argument("--noise-cases", type=int, default=30, metavar="N",
                    help="plants for --noise-draws (default 30)")
    args = ap.parse_args(argv)
    methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
    if "default" not in methods:
        methods += ("default",)
    n = 12 if args.quick else max(args.cases, 1)
    t0 = time.perf_counter()
    cases, outcomes = run(n, args.seed, quick=args.quick, methods=methods, encoder_counts=args.encoder_counts,
                          cover_bench_speed=not args.as_drawn, period_s=args.period_ms * 1e-3)
    enc = f", encoders {args.encoder_counts:,} counts/rev" if args.encoder_counts else ""
    enc += f", sampled every {args.period_ms:g} ms" if args.period_ms != PERIOD_S * 1e3 else ""
    enc += ", calibrations as drawn (not covering the bench speeds)" if args.as_drawn else ""
    print(f"robustness: {n} random plants (seed {args.seed}{enc}), 2 motors each; efficiency at loads "
          f">= 50 % rated; targets: Kt <= {TARGETS['kt_pct']} %, incremental <= "
          f"{TARGETS['inc_pp']} pp, absolute <= {TARGETS['abs_pp']} pp; 'meet' = cases meeting all;\n"
          f"misses: 'biased' = a missed error > {BIASED_SIGMAS:g} x its own reported std, else 'noise'; "
          f"coverage = truth inside the reported 95 % interval")
    print_table(cases, outcomes, methods)
    print_quantities(cases, outcomes, methods)
    print_drive_kinds(cases, outcomes)
    s = summarise(outcomes, methods)["default"]
    print(f"default: {s['n_abs_extrapolated']} of {len(s['abs'])} absolute-efficiency points use a "
          f"motor loss extrapolated beyond its calibrated speed range; their coverage "
          f"{100 * s['cover_abs_extrapolated']:.0f} %")
    d = [o["default"] for o in outcomes]
    print(f"default: eq. 18 from the braking levels' slope (zero-load level > "
          f"{OFF_LINE_SIGMAS:g} sigma off their line) on {sum(o.off_line_reference for o in d)} "
          f"plants; window errors widened for level scatter on {sum(o.level_scatter for o in d)}")
    if args.noise_draws >= 2:
        print_noise_scatter(noise_scatter(cases[:max(args.noise_cases, 1)], args.noise_draws),
                            args.noise_draws)
    if args.worst:
        print_worst(cases, outcomes, args.worst)
    if args.causes:
        print_causes(cases, outcomes)
    print(f"benchmark time {time.perf_counter() - t0:.1f} s")
    return 0
