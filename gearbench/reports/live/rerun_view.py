"""``RerunView``: a record-stream subscriber that shows a run in Rerun as it goes.

Samples go out in batches with ``send_columns`` (one call per motor quantity per
``SampleBatch``), on the drive's time base (timeline ``bench_time``, a duration) and
its sample counter (timeline ``sample``). Steps, operating points and operator
prompts go to a text log; calibrations, efficiency points and limits to
``/results`` as they arrive, with a markdown results panel that is rewritten at
each change. Entity paths: ``gearbench.reports.live.paths``.

``open_live_view`` picks the sinks (``--live``, ``--connect``, ``--rrd``, any
combination) on a dedicated ``rr.RecordingStream``; an unavailable viewer is a
one-line notice on stderr, never an exception into the run.
"""
from __future__ import annotations

import os
import shutil
import socket
import sys
import uuid
from pathlib import Path
from typing import Sequence, TextIO
from urllib.parse import urlparse

import numpy as np
import rerun as rr

from ...station.results import finite_or_none
from ...station.records import (Calibration, EfficiencyPoint, LimitResult, Message, Progress,
                       RunStart, RunStop, SampleBatch, StepStart, StepStop, Subscriber)
from ..plots import SPEED_COLOURS
from . import paths as P
from .blueprint import default_blueprint, panel_names
from ...analysis.calibration import SUFFIXED, motor_value
from ...errors import GearbenchError

DEFAULT_VIEWER_URL = "rerun+http://127.0.0.1:9876/proxy"

# Per quantity: legend name and colour (each quantity has its own panel, see blueprint).
_QUANTITY_STYLE = {
    "current_a": ("current [A]", (228, 26, 28), True),
    "velocity_rad_s": ("velocity [rad/s]", (55, 126, 184), True),
    "command": ("command", (120, 120, 120), True),
    "command_rad_s": ("speed command [rad/s]", (120, 120, 120), True),
    "command_a": ("current command [A]", (152, 78, 163), True),
    "position_rad": ("position [rad]", (77, 175, 74), True),
}
_LEVEL = {"info": rr.TextLogLevel.INFO, "prompt": rr.TextLogLevel.WARN,
          "warning": rr.TextLogLevel.WARN, "error": rr.TextLogLevel.ERROR}


class RerunView(Subscriber):
    """Subscriber logging a run to a ``rr.RecordingStream`` (see module docstring).

    Parameters
    ----------
    recording : the stream to log to (its sinks already set).
    live : the time panel follows the newest sample (viewer attached).
    """

    def __init__(self, recording: rr.RecordingStream, *, live: bool = False):
        self.rec = recording
        self.live = live
        self.motors: tuple[str, ...] = ()
        self.run: RunStart | None = None
        self.calibrations: dict[str, dict] = {}
        self.points: list[dict] = []
        self.limits: list[LimitResult] = []
        self.status = "running"
        self.ratio: float | None = None
        self.bench_time_s: float | None = None
        self.step = ""
        self._point = ""
        self._paths: dict[str, str | None] = {}
        self._last_time_s = 0.0
        self._last_sample = 0
        self._closed = False
        self.panels: list[str] = []          # the layout's panels as last sent
        self._has_map = self._has_residuals = False
        # the unit of each motor's setpoint per step (velocity mode rad/s, current mode A)
        self._command_units: dict[str, dict[str, str]] = {}
        self._step_units: dict[str, str] = {}
        self._speed_colours: dict[float, tuple] = {}
        self._series: set[str] = set()          # efficiency series styled so far
        self._commands: dict[str, list[str]] = {}   # per motor the setpoint units seen

    # ---------------------------------------------------------------- records
    def on_run_start(self, r: RunStart) -> None:
        self.run = r
        self.motors = tuple(r.motors)
        self._command_units = _command_units_of(r)
        self._layout()
        self._at_last_sample()
        self._text(f"run {r.run_id}: serial {r.serial}, profile {r.profile_name}"
                   f"{' (simulated bench)' if r.sim else ''}")
        self._summary()

    def on_step_start(self, r: StepStart) -> None:
        self.step = r.name
        self._step_units = self._command_units.get(r.name) or _units_by_kind(r.step_kind)
        self._point = r.description   # a point named like its step is not news
        self._at_last_sample()
        extra = f": {r.description}" if r.description else ""
        self._text(f"step {r.name} ({r.step_kind}) started{extra}")

    def on_sample_batch(self, r: SampleBatch) -> None:
        n = len(r.time_s)
        if n == 0:
            return
        time_ns = np.rint(np.asarray(r.time_s, dtype=float) * 1e9).astype(np.int64)
        indexes = [rr.TimeColumn(P.TIMELINE, duration=time_ns.astype("timedelta64[ns]")),
                   rr.TimeColumn(P.SAMPLE_TIMELINE, sequence=np.asarray(r.sample, dtype=np.int64))]
        for column, values in r.columns.items():
            motor, _, quantity = column.partition(".")
            if quantity == "command":     # rad/s and A never share an axis
                unit = self._step_units.get(motor)
                if unit is None:
                    continue              # a motor this step does not drive: nothing commanded
                column = f"{motor}.command_{unit}"
                if unit not in self._commands.setdefault(motor, []):
                    self._commands[motor].append(unit)
                    self._layout()            # a panel per setpoint unit, once it has data
            path = self._paths[column] if column in self._paths else self._new_series(column)
            if path is not None:
                rr.send_columns(path, indexes=indexes,
                                columns=rr.Scalars.columns(scalars=values), recording=self.rec)
        self._last_time_s = float(r.time_s[-1])
        self._last_sample = int(r.sample[-1])

    def on_step_stop(self, r: StepStop) -> None:
        self._at_last_sample()
        lost = f", {r.lost_samples} lost" if r.lost_samples else ""
        level = "info" if r.status == "ok" else "error"
        self._text(f"step {r.name} {r.status}: {r.n_samples} samples{lost}", level)

    def on_message(self, r: Message) -> None:
        self._at_last_sample()
        prefix = "OPERATOR: " if r.level == "prompt" else ""
        self._text(prefix + r.text, r.level)

    def on_progress(self, r: Progress) -> None:
        # Only operating-point changes go to the log; fractions would flood it.
        if r.point and r.point != self._point:
            self._point = r.point
            self._at_last_sample()
            self._text(f"operating point {r.point} ({r.step})")

    def on_calibration(self, r: Calibration) -> None:
        self._at_last_sample()
        params = dict(r.params)
        self.calibrations[r.motor] = params
        kt = _num(params.get("Kt"))
        lo, hi = _interval(kt, params.get("Kt_ci95"))
        values = {"Kt": kt, "Kt_ci95_low": lo, "Kt_ci95_high": hi,
                  **{new: _num(motor_value(params, k)) for k, new in SUFFIXED.items()}}
        self.rec.log(f"{P.MOTORS}/{P.part(r.motor)}",
                     rr.AnyValues(**{k: v for k, v in values.items() if v is not None}))
        self._text(f"calibration {r.motor}: {_param_line(params)}")
        self._summary()

    def on_efficiency_point(self, r: EfficiencyPoint) -> None:
        self._at_last_sample()
        point = {k: _num(v) for k, v in r.point.items() if _num(v) is not None}
        self.points.append(point)
        flat = {}
        for key, value in r.point.items():
            if key.endswith("_ci95"):
                center = _num(r.point.get(key[:-len("_ci95")]))
                flat[key + "_low"], flat[key + "_high"] = _interval(center, value)
            else:
                flat[key] = _num(value)
        self.rec.log(P.EFFICIENCY_POINTS,
                     rr.AnyValues(**{k: v for k, v in flat.items() if v is not None}))
        self._series_point(r.point)
        self._text("efficiency " + _point_line(point))
        self._summary()

    def on_limit(self, r: LimitResult) -> None:
        self._at_last_sample()
        self.limits.append(r)
        self._series_limit(r)
        values = {"value": _num(r.value), "low": _num(r.low), "high": _num(r.high),
                  "passed": bool(r.passed)}
        self.rec.log(f"{P.LIMITS}/{P.part(r.name)}",
                     rr.AnyValues(**{k: v for k, v in values.items() if v is not None}))
        self._text(f"limit {r.name}: {_fmt(r.value)} in [{_fmt(r.low)}, {_fmt(r.high)}] "
                   f"{'PASS' if r.passed else 'FAIL'}", "info" if r.passed else "error")
        self._summary()

    def on_run_stop(self, r: RunStop) -> None:
        self.status = r.status
        self.ratio = _num(r.result.get("ratio")) if isinstance(r.result, dict) else None
        self.bench_time_s = _num(r.result.get("bench_time_s")) if isinstance(r.result, dict) else None
        self._at_last_sample()
        reason = f": {r.reason}" if r.reason else ""
        self._text(f"run {r.status.upper()} (exit {r.exit_code}){reason}",
                   "info" if r.status == "passed" else "error")
        self._summary()
        # the final results also as static data: a finished recording opens on them at any
        # time cursor, never on the "RUNNING" of the first sample while the rest loads
        self._summary(static=True)

    # ------------------------------------------------------------------ hooks
    def log_residuals(self, name: str, time_s, values) -> None:
        """Diagnosis hook: residuals ``values`` at ``time_s`` (drive time base) to
        ``/diagnosis/<name>`` in one batch."""
        t = np.asarray(time_s, dtype=float)
        v = np.asarray(values, dtype=float)
        if t.size == 0:
            return
        if not self._has_residuals:
            self._has_residuals = True
            self._layout()
        ns = np.rint(t * 1e9).astype(np.int64).astype("timedelta64[ns]")
        rr.send_columns(f"{P.DIAGNOSIS}/{P.part(name)}",
                        indexes=[rr.TimeColumn(P.TIMELINE, duration=ns)],
                        columns=rr.Scalars.columns(scalars=v), recording=self.rec)

    def close(self) -> None:
        """Flush and close the sinks (finalises the .rrd footer); idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            self.rec.flush(timeout_sec=10.0)
        except Exception:  # a gone viewer must not fail the run's cleanup
            pass
        self.rec.disconnect()

    # ---------------------------------------------------------------- helpers
    def _new_series(self, column: str) -> str | None:
        path = P.sample_path(column)
        self._paths[column] = path
        if path is not None:
            motor, _, quantity = column.partition(".")
            label, color, visible = _QUANTITY_STYLE.get(quantity, (quantity, None, True))
            self.rec.log(path, rr.SeriesLines(names=f"{motor} {label}", colors=color,
                                              visible_series=visible), static=True)
        return path

    def _at_last_sample(self) -> None:
        self.rec.set_time(P.TIMELINE, duration=self._last_time_s)
        self.rec.set_time(P.SAMPLE_TIMELINE, sequence=self._last_sample)

    def _text(self, text: str, level: str = "info") -> None:
        self.rec.log(P.LOG, rr.TextLog(text, level=_LEVEL.get(level, rr.TextLogLevel.INFO)))

    def efficiency_grid(self) -> tuple[list[float], list[float], dict[tuple[int, int], dict]]:
        """Operating points on their nominal grid: (speeds, torques, {(i, j): point}).

        Measured speeds and torques scatter around the setpoints (100.003 rad/s for
        100), so each axis is clustered; the speed setpoint is used when present.
        """
        pts = [p for p in self.points if p.get("torque_out_nm") is not None
               and (p.get("speed_setpoint_rad_s") or p.get("speed_in_rad_s")) is not None]
        speed = [p.get("speed_setpoint_rad_s") or p["speed_in_rad_s"] for p in pts]
        speeds, torques = _cluster(speed), _cluster([p["torque_out_nm"] for p in pts])
        cells = {(_nearest(speeds, s), _nearest(torques, p["torque_out_nm"])): p
                 for s, p in zip(speed, pts)}
        return speeds, torques, cells

    def _layout(self) -> None:
        """(Re)send the layout: panels only for what has data so far."""
        flags = dict(efficiency=self._has_map, diagnosis=self._has_residuals, commands=self._planned_commands())
        self.rec.send_blueprint(default_blueprint(self.motors or ("in", "out"), live=self.live, **flags))
        self.panels = panel_names(self.motors or ("in", "out"), **flags)

    def _planned_commands(self) -> dict[str, list[str]]:
        """Per motor the setpoint units of its panels: those the profile's steps use (known
        at the start, so the layout does not jump), and any seen since."""
        out: dict[str, list[str]] = {}
        for units in self._command_units.values():
            for m, u in units.items():
                if u not in out.setdefault(m, []):
                    out[m].append(u)
        for m, us in self._commands.items():
            for u in us:
                if u not in out.setdefault(m, []):
                    out[m].append(u)
        return {m: sorted(us, key=["rad_s", "a"].index) for m, us in out.items()}

    def _summary(self, static: bool = False) -> None:
        self.rec.log(P.SUMMARY, rr.TextDocument(self.summary_markdown(),
                                                media_type=rr.MediaType.MARKDOWN), static=static)

    # efficiency as Rerun's own series (live, zoomable): each point at its bench time, one
    # series per input speed, its 95 % interval as two thin series, the limits as lines
    def _series_point(self, point: dict) -> None:
        speed = _num(point.get("speed_setpoint_rad_s")) or _num(point.get("speed_in_rad_s"))
        if speed is None:
            return
        t = _num(point.get("t_mid_s"))
        if t is not None:
            self.rec.set_time(P.TIMELINE, duration=t)
        colour = self._speed_colours.setdefault(
            round(speed, 6), _hex_rgb(SPEED_COLOURS[len(self._speed_colours) % len(SPEED_COLOURS)]))
        label = f"{speed:g} rad/s"
        for kind, key in (("incremental", "eta_incremental"), ("absolute", "eta_absolute")):
            eta = _num(point.get(key))
            if eta is None:
                continue
            base = P.efficiency_series(kind, speed)
            if base not in self._series:
                self._series.add(base)
                self.rec.log(base, rr.SeriesLines(names=f"η {kind[:3]} {label}", colors=colour, widths=1.5),
                             rr.SeriesPoints(names=f"η {kind[:3]} {label}", colors=colour,
                                             markers="circle", marker_sizes=4.0), static=True)
                for side, marker in (("ci95_low", "down"), ("ci95_high", "up")):
                    self.rec.log(f"{base}/{side}",
                                 rr.SeriesPoints(names=f"{label} 95 % {side[-4:].strip('_')}",
                                                 colors=colour, markers=marker, marker_sizes=3.0),
                                 static=True)
            self.rec.log(base, rr.Scalars(100 * eta))
            lo, hi = _interval(eta, point.get(f"{key}_ci95"))
            for side, v in (("ci95_low", lo), ("ci95_high", hi)):
                if v is not None:
                    self.rec.log(f"{base}/{side}", rr.Scalars(100 * v))
        if not self._has_map:
            self._has_map = True
            self._layout()
        self._at_last_sample()

    def _series_limit(self, lim: LimitResult) -> None:
        """An efficiency limit as a horizontal line over the points' bench times."""
        kind = {"efficiency.eta_incremental": "incremental",
                "efficiency.eta_absolute": "absolute"}.get(lim.quantity)
        times = [t for t in (_num(p.get("t_mid_s")) for p in self.points) if t is not None]
        if kind is None or not times:
            return
        for side, v in (("low", _num(lim.low)), ("high", _num(lim.high))):
            path = P.efficiency_limit(kind, side)
            if v is None or path in self._series:
                continue
            self._series.add(path)
            self.rec.log(path, rr.SeriesLines(names=f"limit {side} {100 * v:.4g} %", colors=(178, 24, 43),
                                              widths=1.0), static=True)
            for t in (min(times), max(times)):
                self.rec.set_time(P.TIMELINE, duration=t)
                self.rec.log(path, rr.Scalars(100 * v))
        self._at_last_sample()

    def summary_markdown(self) -> str:
        """The results panel: verdict, motor parameters, efficiency map, limits."""
        lines = []
        head = "# Run"
        if self.run:
            head = f"# {self.run.serial} · {self.run.profile_name}"
        sim = " · SIMULATED bench" if self.run and self.run.sim else ""
        status = (f"RUNNING · step {self.step}" if self.status == "running" and self.step else
                  "RUNNING" if self.status == "running" else f"finished: {self.status.upper()}")
        lines += [head, "", f"**{status}**{sim}", ""]
        if self.limits:     # the verdict's reasons first: a short panel shows them
            failed = [lim for lim in self.limits if not lim.passed]
            lines += [f"Limits: {len(self.limits) - len(failed)} of {len(self.limits)} passed"
                      + (": failed " + ", ".join(lim.name for lim in failed) if failed else ""), ""]
        if self.ratio is not None or self.bench_time_s is not None:
            lines += [f"Reduction ratio n = {_fmt(self.ratio)} · bench time {_fmt(self.bench_time_s)} s", ""]
        if self.calibrations:
            lines += ["## Motors", "", "| motor | Kt [N·m/A] | 95 % interval | J [kg·m²] | D [N·m·s/rad] | Tc [N·m] |",
                      "|---|---|---|---|---|---|"]
            for motor, p in self.calibrations.items():
                kt = _num(p.get("Kt"))
                lo, hi = _interval(kt, p.get("Kt_ci95"))
                lines.append(f"| {motor} | {_fmt(kt)} | [{_fmt(lo)}, {_fmt(hi)}] | "
                             f"{_fmt(motor_value(p, 'J'))} | {_fmt(motor_value(p, 'D'))} | {_fmt(motor_value(p, 'Tc'))} |")
            lines.append("")
        speeds, torques, cells = self.efficiency_grid()
        if speeds:
            lines += ["## Efficiency map (incremental η, %)", "",
                      "| ω_in [rad/s] \\ T_out [N·m] | " + " | ".join(f"{t:.4g}" for t in torques) + " |",
                      "|---" * (len(torques) + 1) + "|"]
            for i, s in enumerate(speeds):
                row = []
                for j in range(len(torques)):
                    eta = _num(cells.get((i, j), {}).get("eta_incremental"))
                    row.append("·" if eta is None else f"{100 * eta:.2f}")
                lines.append(f"| {s:.4g} | " + " | ".join(row) + " |")
            lines.append("")
        if self.limits:
            lines += ["## Limits", "", "| limit | value | low | high | |", "|---|---|---|---|---|"]
            for lim in self.limits:
                lines.append(f"| {lim.name} | {_fmt(lim.value)} | {_fmt(lim.low)} | {_fmt(lim.high)} | "
                             f"{'✅ pass' if lim.passed else '❌ FAIL'} |")
            lines.append("")
        return "\n".join(lines)


def _hex_rgb(colour: str) -> tuple[int, int, int]:
    return tuple(int(colour[i:i + 2], 16) for i in (1, 3, 5))


def _units_by_kind(step_kind: str) -> dict[str, str]:
    """Without the profile: an efficiency step drives the input in speed and brakes the
    output in current; other steps run the motors in speed."""
    return {"in": "rad_s", "out": "a"} if step_kind == "efficiency" else {"in": "rad_s", "out": "rad_s"}


def _command_units_of(r: RunStart) -> dict[str, dict[str, str]]:
    """Per step per motor the setpoint's unit, from the run's profile (the copy in the run
    folder, else the path it ran); empty when neither loads."""
    from ...profile import load_profile
    from ...station.plan import command_units

    for path in (Path(r.out_dir) / "profile.yaml" if r.out_dir else None, r.profile_path):
        if not path or not Path(path).is_file():
            continue
        try:
            return command_units(load_profile(path))
        except Exception:       # a profile that no longer loads: fall back to the step kinds
            continue
    return {}


# ------------------------------------------------------------------- factory
RERUN_SCHEMES = ("rerun+http://", "rerun+https://", "rerun://")


def check_connect_url(url: str | None) -> None:
    """Refuse a ``--connect`` that is not a Rerun URL (``localhost:9876``), naming the fix."""
    if url and not url.startswith(RERUN_SCHEMES):
        bare = url.split("://", 1)[-1].split("/", 1)[0] or "127.0.0.1:9876"
        raise GearbenchError(f"--connect {url}: not a Rerun viewer URL; write it as "
                             f"rerun+http://{bare}/proxy")


def open_live_view(*, live: bool = False, connect: str | None = None,
                   rrd: str | os.PathLike | None = None, application_id: str = "gearbench",
                   recording_id: str | None = None, motors: Sequence[str] | None = None,
                   stderr: TextIO | None = None,
                   fallback: str = "run continues without it") -> RerunView | None:
    """A ``RerunView`` on a dedicated recording stream with the requested sinks.

    ``live``: spawn (or reuse) a local viewer; ``connect``: a viewer already open
    at that URL (``rerun+http://HOST:9876/proxy``); ``rrd``: record to that file.
    Any combination. A viewer that cannot be reached (no display, nothing
    listening) gives ONE line on ``stderr``; the view still records to ``rrd`` if
    asked, else None is returned. Never raises. ``motors`` sends the default
    layout at once (otherwise it is sent at ``RunStart``).
    """
    err = stderr or sys.stderr
    if not (live or connect or rrd):
        return None
    try:
        rec = rr.RecordingStream(application_id, recording_id=recording_id or uuid.uuid4().hex)
        sinks, problems = [], []
        if rrd:
            rrd_path = Path(rrd)
            rrd_path.parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(str(rrd_path)))
        if connect:
            if _listening(connect):
                sinks.append(rr.GrpcSink(connect))
            else:
                problems.append(f"no Rerun viewer at {connect}")
        if live:
            url, problem = _spawn_viewer(rec)
            if url and url != connect:
                sinks.append(rr.GrpcSink(url))
            elif problem:
                problems.append(problem)
        if problems:
            fallback = f"recording to {rrd} only" if rrd else fallback
            print(f"gearbench: live view: {'; '.join(problems)}" + (f"; {fallback}" if fallback else ""),
                  file=err)
        if not sinks:
            return None
        rec.set_sinks(*sinks)
        view = RerunView(rec, live=len(sinks) > (1 if rrd else 0))
        if motors:
            view.motors = tuple(motors)
            view._layout()
        return view
    except Exception as exc:  # a display problem must never stop a test run
        print(f"gearbench: live view off: {type(exc).__name__}: {exc}".splitlines()[0], file=err)
        return None


def _listening(url: str, timeout_s: float = 0.5) -> bool:
    """Is something accepting TCP connections at the URL's host:port?"""
    try:
        parsed = urlparse(url)
        host, port = parsed.hostname or "127.0.0.1", parsed.port or 9876
        with socket.create_connection((host, port), timeout=timeout_s):
            return True
    except (OSError, ValueError):
        return False


def _spawn_viewer(rec: rr.RecordingStream, port: int = 9876) -> tuple[str | None, str | None]:
    """Start a native viewer (or reuse one on ``port``): (url, None) or (None, why not)."""
    url = f"rerun+http://127.0.0.1:{port}/proxy"
    if _listening(url):
        return url, None
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY")
                                                 or os.environ.get("WAYLAND_DISPLAY")):
        return None, "no display for a viewer (use --connect URL or --rrd FILE)"
    exe = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
    if not Path(exe).exists():
        return None, "no 'rerun' viewer executable found (pip install rerun-sdk)"
    try:
        rr.spawn(port=port, connect=False, executable_path=exe, recording=rec)
    except Exception as exc:
        return None, f"viewer did not start ({exc})".splitlines()[0]
    # spawn() waits for the viewer; a viewer that died at once (no usable display)
    # is not listening, and a gRPC sink to nowhere would only stall the close.
    if not _listening(url):
        return None, "viewer did not start (no usable display?)"
    return url, None


# --------------------------------------------------------------- formatting
def _cluster(values, rel_tol: float = 0.02) -> list[float]:
    """Centres of groups of nearly equal values (gap > rel_tol of the value starts
    a new group): the nominal grid behind measured operating points."""
    groups: list[list[float]] = []
    for v in sorted(float(x) for x in values):
        if groups and abs(v - groups[-1][-1]) <= rel_tol * max(abs(v), abs(groups[-1][-1]), 1e-9):
            groups[-1].append(v)
        else:
            groups.append([v])
    return [float(np.mean(g)) for g in groups]


def _nearest(centres: list[float], v: float) -> int:
    return int(np.argmin([abs(c - v) for c in centres]))


_num = finite_or_none


def _interval(center: float | None, ci) -> tuple[float | None, float | None]:
    """A 95 % interval given as [low, high] or as a half-width around ``center``."""
    if ci is None:
        return None, None
    if isinstance(ci, (list, tuple, np.ndarray)) and len(ci) == 2:
        return _num(ci[0]), _num(ci[1])
    half = _num(ci)
    if half is None or center is None:
        return None, None
    return center - half, center + half


def _fmt(v) -> str:
    f = _num(v)
    return "–" if f is None else f"{f:.5g}"


def _param_line(p: dict) -> str:
    kt = _num(p.get("Kt"))
    lo, hi = _interval(kt, p.get("Kt_ci95"))
    return (f"Kt = {_fmt(kt)} N·m/A [{_fmt(lo)}, {_fmt(hi)}], J = {_fmt(motor_value(p, 'J'))} kg·m², "
            f"D = {_fmt(motor_value(p, 'D'))} N·m·s/rad, Tc = {_fmt(motor_value(p, 'Tc'))} N·m")


def _point_line(p: dict) -> str:
    eta_i, eta_a = p.get("eta_incremental"), p.get("eta_absolute")
    return (f"ω_in = {_fmt(p.get('speed_in_rad_s'))} rad/s, T_out = {_fmt(p.get('torque_out_nm'))} N·m: "
            f"η_inc = {'–' if eta_i is None else f'{100 * eta_i:.2f} %'}, "
            f"η_abs = {'–' if eta_a is None else f'{100 * eta_a:.2f} %'}")
