"""The sequencer: a profile's steps as a plain sequence, run against drives.

calibrate (each motor unloaded, then with a disk) -> load (mount reducer) ->
efficiency (grid of input speeds x output braking torques). Steps with min_s/max_s are
adaptive (``gearbench.station.adaptive``): a controller plays their commands and ends each
measurement when its statistical interval meets the profile's targets; with
``bench.parallel_calibration`` neighbouring calibrate steps run at once. Everything that
happens is emitted as records (``gearbench.station.records``); the sequencer writes no
files itself. A watchdog enforces the motors' current and speed limits; a limit,
a drive fault or an operator abort quick-stops and disables every drive at once
and ends the run with exit code 3, keeping every sample recorded before it.
"""
from __future__ import annotations

import gc
import signal
import socket
import threading
import time
import uuid
from datetime import datetime, timezone
from typing import Callable, Protocol

import numpy as np

from .. import __version__
from ..analysis import METHOD_VERSIONS
from ..analysis.calibration import MotorCalibration
from ..drives.base import DriveNetwork
from ..drives.realtime import acquisition_priority
from ..errors import Aborted, BenchFault, GearbenchError
from . import analyse, limits
from .results import round_floats
from . import plan as planning
from .plan import Analyse, CalibrationAnalysis, Known, Prompt, Segment
from ..analysis.efficiency import EfficiencyPoint
from .records import EfficiencyPoint as EfficiencyPointRecord
from .records import (Calibration, Message, OutputFailure, Progress,
                      RunStart, RunStop, SampleBatch, StepStart, StepStop)
from ..trace import Trace

BATCH_SAMPLES = 200          # samples per SampleBatch (and per flush of the recorder)
OVERCURRENT_SAMPLES = 5      # consecutive samples over the limit before the watchdog trips
WATCHDOG_MARGIN = 1.1        # the drive clamps at the profile's current limit (0x6073); the
                             # watchdog catches a drive that does not, so it sits above the clamp


class Operator(Protocol):
    def confirm(self, prompt: str) -> None:
        """Block until the operator confirms ``prompt``; raise ``Aborted`` to abort."""


class Fixture(Protocol):
    def mount(self, *, coupling: str, disk_kgm2: dict[str, float]) -> None:
        """What physically changes on the bench (nothing to do on a real bench:
        the operator did it); the simulated bench mounts it itself."""


class AutoOperator:
    """``--yes`` / simulated bench: every prompt is answered at once."""

    def confirm(self, prompt: str) -> None:
        pass


class NoFixture:
    def mount(self, *, coupling: str, disk_kgm2: dict[str, float]) -> None:
        pass


def now_utc() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


class Sequencer:
    """Runs one profile on one drive network, emitting records to ``emit``."""

    def __init__(self, profile, network: DriveNetwork, *, emit: Callable, operator: Operator,
                 fixture: Fixture | None = None, serial: str = "", out_dir: str = "",
                 sim_truth: Callable | None = None, method: str = "default"):
        self.profile = profile
        self.net = network
        self._emit = emit
        self.operator = operator
        self.fixture = fixture or NoFixture()
        self.serial = serial
        self.out_dir = out_dir
        self.sim_truth = sim_truth
        self.method = method
        self.period_s = profile.bench.period_s
        self.run_id = uuid.uuid4().hex   # full 128 bits: a plant makes tens of millions of runs a year
        self._abort_reason: str | None = None
        self._samples_done = 0
        self._samples_total = 1
        self._wall0 = 0.0
        self.traces: dict[str, Trace] = {}
        self.calibrations: dict[str, MotorCalibration] = {}   # motor -> its identification
        self.points: list[EfficiencyPoint] = []               # every efficiency point so far
        self.ratio: float | None = None
        self.prompts: list[dict] = []              # operator prompts and when each was confirmed
        self.lost_by_step: dict[str, int] = {}
        self.lost: dict[str, list[int]] = {}     # step -> sample counter values that never arrived
        self.priority_granted = ""
        self._output_failure: str | None = None     # a required output failed on a path that went on
        self.measurements: list[dict] = []         # adaptive measurements: duration, interval, stopped_by
        self.adaptive: dict[str, object] = {}      # segment name -> its finished controller
        self._recorded: dict = {}                  # re-analysis: adaptive decisions from result.json

    def emit(self, record) -> None:
        """Emit a record; a required output that failed becomes a bench fault."""
        try:
            self._emit(record)
        except OutputFailure as exc:
            raise BenchFault(f"output failed: {exc}; a unit cannot pass without its records") from None

    def _emit_quiet(self, record) -> None:
        """Emit on a path that is already ending (the stream keeps the failure and turns
        the run's result into a fault itself)."""
        try:
            self._emit(record)
        except OutputFailure as exc:   # raised once: keep it, so no further segment starts
            self._output_failure = str(exc)

    def _stop_drives(self, exc: BenchFault) -> BenchFault:
        """Stop every drive unless the fault already did; the fault's text says what was verified."""
        if getattr(exc, "stop_report", None):
            return exc
        stopped = self.net.stop_all()
        new = type(exc)(f"{exc}; {stopped}")
        new.stop_report = stopped
        return new

    # ------------------------------------------------------------------ abort
    def request_abort(self, reason: str) -> None:
        """Thread/signal safe: the acquisition loop stops at the next sample."""
        self._abort_reason = reason

    def _abort(self) -> Aborted:
        return Aborted(self._abort_reason)

    def _install_signals(self):
        if threading.current_thread() is not threading.main_thread():
            return {}
        old = {}

        def handler(signum, frame):
            self.request_abort("operator abort (Ctrl-C)" if signum == signal.SIGINT
                               else "terminated (SIGTERM)")
        for sig in (signal.SIGINT, signal.SIGTERM):
            old[sig] = signal.signal(sig, handler)
        return old

    # -------------------------------------------------------------- the plan
    def known(self) -> Known:
        """What this run has found so far, as later steps' commands need it."""
        out = self.calibrations.get("out")
        return Known(kt={m: self._kt(m) for m in self.profile.motors},
                     loss_out=out.loss_torque_nm if out else None,
                     b2_unloaded=self._b2_unloaded,
                     inertia_kgm2={m: c.J for m, c in self.calibrations.items()})

    def plan(self) -> list:
        """The whole run's actions (``gearbench.station.plan``), datasheet values standing in
        for the calibrations still to come."""
        return planning.plan(self.profile, self.known())

    def step_groups(self) -> list:
        return planning.step_groups(self.profile)

    def plan_step(self, step) -> list:
        """The actions of one step, planned when it starts (with the Kt found so far)."""
        return planning.plan_step(self.profile, step, self.known())

    def _b2_unloaded(self, segment: str, motor: str) -> float:
        """The unloaded run's streaming b2 of ``motor`` (for the disk run's share of Kt)."""
        return self.adaptive[segment].b2.get(motor, float("nan"))

    def _kt(self, motor: str) -> float:
        if motor in self.calibrations:
            return self.calibrations[motor].Kt
        return float(self.profile.motors[motor].kt_datasheet)

    # ------------------------------------------------------------------- run
    def run(self) -> dict:
        """Run every step; return the result dict (also emitted in RunStop)."""
        self.begin()
        try:
            for step in self.step_groups():
                self.run_step(step)
        except GearbenchError as exc:
            return self.finish(error=exc)
        except BaseException:
            self.net.stop_all()
            self.restore_signals()
            raise
        return self.finish()

    def begin(self) -> None:
        """Emit RunStart and take over Ctrl-C/SIGTERM (they request a safe stop)."""
        p = self.profile
        self._started = now_utc()
        self._wall0 = time.monotonic()
        self._samples_total = max(1, sum(a.max_samples for a in self.plan() if isinstance(a, Segment)))
        self.emit(RunStart(self.run_id, self.serial, p.name, str(p.path), p.sha256, self._started,
                           self.sim_truth is not None, tuple(p.motors), self.period_s,
                           str(self.out_dir)))
        self._old_signals = self._install_signals()
        # everything imported and configured so far lives for the whole run: keep it out of
        # the collector, so a collection between segments is short
        gc.collect()
        gc.freeze()

    def record_failed_start(self, error: Exception) -> dict:
        """The drives could not be configured (no answer, wrong drive...): nothing moved,
        but the attempt is recorded like any run (result.json, junit.xml, station database)."""
        self.begin()
        return self.finish(error=error if isinstance(error, BenchFault) else BenchFault(f"bench did not start: {error}"))

    def run_step(self, step) -> None:
        """Run one profile step (calibrate / load / efficiency). A fault quick-stops
        the drives and raises BenchFault (samples so far are already emitted)."""
        try:
            for action in self.plan_step(step):
                if self._abort_reason:
                    raise self._abort()
                if self._output_failure:   # seen on a quiet path (a segment's end): no further segment
                    raise BenchFault(f"output failed: {self._output_failure}; a unit cannot pass "
                                     f"without its records")
                if isinstance(action, Segment):
                    self._acquire(action)
                elif isinstance(action, Prompt):
                    self._prompt(action)
                else:
                    self.analyse(action)
        except BenchFault as exc:
            raise self._stop_drives(exc) from None
        except GearbenchError as exc:   # analysis refused the data, a drive could not be configured...
            stopped = self.net.stop_all()
            exc.args = (f"{exc}; {stopped}",)
            raise

    def finish(self, error: Exception | None = None) -> dict:
        """Check limits (unless the run stopped early), emit RunStop, return the result."""
        self.restore_signals()
        status, exit_code, reason = "passed", 0, ""
        limits: list[dict] = []
        if error is not None:
            # a bench fault, an abort, or analysis refusing the data: drives are safe, run over
            status, exit_code, reason = ("aborted" if isinstance(error, Aborted) else "fault"), 3, str(error)
            self._emit_quiet(Message(f"run stopped: {error}", level="error"))
        else:
            limits = self.check_limits()
            if not all(lim["passed"] for lim in limits):
                status, exit_code = "failed", 1
                reason = ", ".join(lim["name"] for lim in limits if not lim["passed"])
        result = self._result(self._started, status, exit_code, reason, limits)
        self._emit_quiet(RunStop(status, exit_code, reason, result))   # the stream makes it a fault if an output failed
        return result

    def restore_signals(self) -> None:
        for sig, h in getattr(self, "_old_signals", {}).items():
            signal.signal(sig, h)
        self._old_signals = {}

    def _prompt(self, prompt: Prompt) -> None:
        self.emit(Message(prompt.text, level="prompt"))
        shown = now_utc()
        self.operator.confirm(prompt.text)
        self.prompts.append({"prompt": prompt.text, "shown_utc": shown, "confirmed_utc": now_utc(),
                             "operator": type(self.operator).__name__})
        self.fixture.mount(**prompt.mount)

    # ----------------------------------------------------------- acquisition
    def _acquire(self, seg: Segment) -> Trace:
        """Play ``seg``'s setpoints sample by sample, recording every sample.

        The loop does acquisition only: records go to the stream's queue (written by
        another thread). The segment ends with every drive disabled and read back; a
        drive that does not disable is a fault and no further segment starts."""
        net = self.net
        motors = list(seg.commands)
        n = seg.max_samples
        ctl = seg.controller
        self.emit(StepStart(seg.name, seg.step_kind, seg.description, n))
        drives = {m: net.drives[m] for m in motors}
        for m, (mode, cmd) in seg.commands.items():
            drives[m].enable(mode)
        names = [m for m in self.profile.motors if m in net.drives]
        buf_idx = np.zeros(n, dtype=np.int64)
        buf_t = np.zeros(n)
        cols = {f"{m}.{q}": np.zeros(n) for m in names
                for q in ("position_rad", "velocity_rad_s", "current_a", "command")}
        limits = {m: (WATCHDOG_MARGIN * self.profile.motors[m].current_limit_a,
                      WATCHDOG_MARGIN * self.profile.motors[m].speed_limit_rad_s) for m in names}
        over = dict.fromkeys(names, 0)
        last_sp = dict.fromkeys(motors, None)
        flushed = done = 0
        status = "ok"
        net.discard_backlog()      # paced, SYNC ran on while the drives were enabled: not this segment's
        lost0 = net.lost_samples
        end_fault: BenchFault | None = None
        try:
            with acquisition_priority(net.acquisition_threads(),
                                      realtime=not net.lockstep) as granted:
                self.priority_granted = granted
                for k in range(n):
                    if self._abort_reason:
                        raise self._abort()
                    step_sp = ctl.setpoints(k) if ctl is not None else None
                    for m in motors:
                        sp = step_sp[m] if ctl is not None else float(seg.commands[m][1][k])
                        if sp != last_sp[m]:
                            drives[m].set_setpoint(sp)
                            last_sp[m] = sp
                    samples = net.sample()
                    s0 = samples[names[0]]
                    buf_idx[k], buf_t[k] = s0.index, s0.time_s
                    for m in names:
                        s = samples[m]
                        cols[f"{m}.position_rad"][k] = s.position_rad
                        cols[f"{m}.velocity_rad_s"][k] = s.velocity_rad_s
                        cols[f"{m}.current_a"][k] = s.current_a
                        cols[f"{m}.command"][k] = last_sp.get(m) or 0.0
                    done = k + 1
                    self._watchdog(seg.name, samples, names, limits, over)
                    if done - flushed >= BATCH_SAMPLES:
                        self._flush(seg.name, buf_idx, buf_t, cols, flushed, done)
                        flushed = done
                        self._progress(seg, done, n)
                    if ctl is not None and ctl.update(done, cols):
                        break
        except BenchFault as exc:
            status = "aborted" if isinstance(exc, Aborted) else "fault"
            raise self._stop_drives(exc) from None   # first the drives, within this sample period; then the books
        finally:
            if status == "ok":
                end_fault = self._end_segment(seg, drives)
                status = "ok" if end_fault is None else "fault"
            self._flush_quiet(seg.name, buf_idx, buf_t, cols, flushed, done)
            self._samples_done += done
            self.lost_by_step[seg.name] = net.lost_samples - lost0
            gaps = np.flatnonzero(np.diff(buf_idx[:done]) > 1)
            self.lost[seg.name] = [int(v) for i in gaps for v in range(buf_idx[i] + 1, buf_idx[i + 1])][:1000]
            self._emit_quiet(StepStop(seg.name, status, done, net.lost_samples - lost0))
            self.traces[seg.name] = Trace(buf_t[:done], {"sample": buf_idx[:done],
                                          **{c: v[:done] for c, v in cols.items()}},
                                          {"step": seg.name, **seg.meta}, seg.name)
            if ctl is not None and status == "ok":
                self._adaptive_done(seg, ctl, cols, buf_idx, done)
        if end_fault is not None:
            raise end_fault
        return self.traces[seg.name]

    def _adaptive_done(self, seg: Segment, ctl, cols: dict, buf_idx: np.ndarray, done: int) -> None:
        """Keep what an adaptive segment measured (for the analysis and result.json) and
        say it: one line per measurement, how long, the interval reached, why it stopped."""
        if hasattr(ctl, "finish"):
            ctl.finish(cols, done)
            seg.meta["windows"] = ctl.windows(buf_idx[:done])
            self.traces[seg.name].meta["windows"] = seg.meta["windows"]
            if hasattr(ctl, "corrected"):       # the series the staircase chose (adaptive.Staircase)
                seg.meta["inertia_corrected"] = self.traces[seg.name].meta["inertia_corrected"] = ctl.corrected
        self.adaptive[seg.name] = ctl
        for rec in ctl.measurements():
            self.measurements.append(rec)
            reached = rec.get("interval_reached")
            unit = "%" if rec["kind"] == "calibrate" else "pp"
            scale = 100.0 if rec["kind"] == "calibrate" else 1.0
            shown = "n/a" if reached is None else f"{scale * reached:.3g} {unit}"
            self._emit_quiet(Message(f"{rec['name']}: {rec['duration_s']:.2f} s, stopped by "
                                     f"{rec['stopped_by']} (95 % statistical half-width {shown}, "
                                     f"target {scale * rec['target']:.3g} {unit})", step=seg.name))

    def _end_segment(self, seg: Segment, drives: dict) -> BenchFault | None:
        """Zero setpoints and disable, verified; a drive that stays enabled is a fault."""
        for m, d in drives.items():
            try:
                d.set_setpoint(0.0)
                d.disable()
            except GearbenchError as exc:
                stopped = self.net.stop_all()
                fault = BenchFault(f"drive '{m}' did NOT reach a disabled state at the end of "
                                   f"{seg.name} ({exc}); {stopped}")
                fault.stop_report = stopped
                return fault
        return None

    def _watchdog(self, step: str, samples, names, limits, over) -> None:
        """Drive fault, sustained over-current, over-speed -> BenchFault."""
        for m in names:
            s = samples[m]
            if s.fault:
                raise BenchFault(f"drive '{m}' reported a fault (status 0x{s.status:04x}) "
                                 f"in step {step} at t={s.time_s:.3f} s")
            i_lim, w_lim = limits[m]
            over[m] = over[m] + 1 if abs(s.current_a) > i_lim else 0
            if over[m] >= OVERCURRENT_SAMPLES:
                raise BenchFault(f"limit: motor '{m}' current {s.current_a:.3f} A beyond "
                                 f"{i_lim:g} A in step {step} at t={s.time_s:.3f} s")
            if abs(s.velocity_rad_s) > w_lim:
                raise BenchFault(f"limit: motor '{m}' speed {s.velocity_rad_s:.1f} rad/s beyond "
                                 f"{w_lim:g} rad/s in step {step} at t={s.time_s:.3f} s")

    def _flush(self, step, idx, t, cols, i0, i1, emit=None) -> None:
        if i1 > i0:
            (emit or self.emit)(SampleBatch(step, idx[i0:i1].copy(), t[i0:i1].copy(),
                                            {c: v[i0:i1].copy() for c, v in cols.items()}))

    def _flush_quiet(self, step, idx, t, cols, i0, i1) -> None:
        self._flush(step, idx, t, cols, i0, i1, emit=self._emit_quiet)

    def _progress(self, seg: Segment, k: int, n: int) -> None:
        done = self._samples_done + k
        frac = done / self._samples_total
        elapsed = time.monotonic() - self._wall0
        eta = elapsed * (1 - frac) / frac if frac > 0 else None
        point = seg.description
        for start, label in seg.meta.get("points", ()):
            if k >= start:
                point = label
        self.emit(Progress(seg.name, point, k / n, frac, eta))

    # -------------------------------------------------------------- analysis
    def analyse(self, action: Analyse) -> None:
        """Analyse recorded segments (``gearbench.station.analyse``) and emit the result."""
        if isinstance(action, CalibrationAnalysis):
            m = action.motor
            # runs played together: each motor's own run, up to the end of its stop ramp
            unloaded, loaded = (self._motor_run(self.traces[name], m) for name in (action.unloaded, action.loaded))
            cal = analyse.calibrate(unloaded, loaded, motor=m, disk_kgm2=action.disk_kgm2, method=self.method,
                                    disk_std_kgm2=action.disk_std_kgm2, disk_name=action.disk_name,
                                    sampling=_drive_description(self.profile.motors[m]),
                                    rated_current_a=self.profile.motors[m].rated_current_a,
                                    current_limit_a=self.profile.motors[m].current_limit_a)
            self.calibrations[m] = cal
            self.emit(Calibration(m, cal))
            return
        seg = self.traces[action.segment]
        ratio = self.profile.reducer.ratio if self.profile.reducer else None
        if "windows" not in seg.meta and ("windows", action.segment) in self._recorded:
            seg.meta["windows"] = self._recorded[("windows", action.segment)]
            seg.meta["inertia_corrected"] = self._recorded.get(("inertia_corrected", action.segment), False)
        adaptive = "windows" in seg.meta or action.adaptive
        res = analyse.efficiency(seg, self._calibration("in"), self._calibration("out"),
                                 ratio=ratio, settle_s=seg.meta["settle_s"],
                                 speed_setpoint_rad_s=action.speed_rad_s,
                                 skip_samples=seg.meta["n_ramp"], windows=seg.meta.get("windows"),
                                 incremental="slope" if adaptive else "auto",
                                 inertia_corrected=bool(seg.meta.get("inertia_corrected")),
                                 ripple_corrected=self.profile.motors["in"].current_instant)
        self.ratio = res.ratio
        for pt in res.points:
            self.points.append(pt)
            self.emit(EfficiencyPointRecord(pt))

    def _calibration(self, motor: str) -> MotorCalibration:
        """The motor's calibration, else its datasheet Kt alone (no loss model)."""
        return self.calibrations.get(motor) or MotorCalibration.from_kt(self._kt(motor), f"motor {motor}")

    # results as written out (result.json, limits): plain dicts made in one place
    @property
    def motors_result(self) -> dict[str, dict]:
        return {m: c.to_dict() for m, c in self.calibrations.items()}

    @property
    def efficiency(self) -> list[dict]:
        # with the commanded point (speed set point, the profile's torque level): stable names
        return limits.with_setpoints(self.profile, [p.to_dict() for p in self.points])

    def _motor_run(self, trace: Trace, motor: str) -> Trace:
        ctl = self.adaptive.get(trace.source)
        if ctl is not None and hasattr(ctl, "end_sample") and len(ctl.runs) > 1:
            end = ctl.end_sample(motor)
        else:       # re-analysis: where the run ended, from result.json's measurements
            end = self._recorded.get(("run", trace.source, motor))
        return trace if end is None else trace.slice(0, min(int(end), len(trace)))

    def load_recorded(self, measurements: list[dict]) -> None:
        """What an adaptive run decided while acquiring (result.json ``measurements``):
        each motor's run length in a shared calibration segment and each level's settled
        window, so a re-analysis of the recorded traces uses the same data."""
        for m in measurements or []:
            if m.get("kind") == "calibrate" and m.get("run_samples") is not None:
                self._recorded[("run", m["segment"], m["motor"])] = m["run_samples"]
            elif m.get("kind") == "efficiency" and m.get("window_samples"):
                self._recorded.setdefault(("windows", m["segment"]), []).append(tuple(m["window_samples"]))
                if m.get("inertia_corrected") is not None:     # the series the staircase chose
                    self._recorded[("inertia_corrected", m["segment"])] = bool(m["inertia_corrected"])

    # ---------------------------------------------------------------- limits
    def check_limits(self) -> list[dict]:
        """Judge the profile's limits on this run's results; each verdict is emitted."""
        out = []
        for rec in limits.check(self.profile, self.motors_result, self.ratio, self.efficiency):
            self.emit(rec)
            out.append(rec.to_dict())
        return out

    # ---------------------------------------------------------------- result
    def _result(self, started, status, exit_code, reason, limits) -> dict:
        p = self.profile
        n_samples = sum(len(t) for t in self.traces.values())
        result = {
            "serial": self.serial, "run_id": self.run_id, "profile": p.name,
            "profile_path": str(p.path), "profile_sha256": p.sha256,
            "started_utc": started, "finished_utc": now_utc(),
            "status": status, "passed": status == "passed", "exit_code": exit_code,
            "reason": reason, "method": self.method,
            "gearbench_version": __version__, "method_version": METHOD_VERSIONS.get(self.method, ""),
            "station": {"name": p.bench.name, "host": socket.gethostname()},
            "prompts": self.prompts,
            "motors": self.motors_result, "ratio": self.ratio,
            "efficiency": self.efficiency, "limits": limits,
            "bench_time_s": n_samples * self.period_s,
            "wall_time_s": time.monotonic() - self._wall0,
            "samples": n_samples, "lost_samples": self.net.lost_samples,
            "lost_at_sample": {k: v for k, v in self.lost.items() if v},
            "supervision": {**self.net.supervision(), "acquisition_priority": self.priority_granted},
            "steps": {name: len(t) for name, t in self.traces.items()},
            "lost_samples_by_step": dict(self.lost_by_step),
            "measurements": self.measurements,
            "out_dir": str(self.out_dir),
        }
        if self.sim_truth is not None:   # the simulated plant's truth at the commanded points
            result["simulation_truth"] = self.sim_truth(self.efficiency)
        # no rounding noise beside real values (-2.8e-14 beside 241): the same numbers in the
        # returned result as in result.json and the databases
        return round_floats(result)


def _drive_description(spec) -> dict | None:
    """How the motor's drive samples (the profile's ``sampling``) and the current limit it
    clamps at (``current_limit_a``, 0x6073): where it sits at the limit a stepped
    setpoint gives no current kick (``identify.samples._below_current_limit``)."""
    if not spec.sampling:
        return None
    return {**spec.sampling, "current_limit_a": float(spec.current_limit_a)}
