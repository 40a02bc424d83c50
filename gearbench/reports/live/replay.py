"""Replay a finished run folder (Parquet traces + result.json) as a record stream.

The folder written by ``gearbench run`` holds ``trace-<step>.parquet`` per step
(``sample``, ``time_s``, ``<motor>.<quantity>``; a partial ``trace-<step>.arrows``
after a crash) and ``result.json``. ``replay_records`` turns it back into the
records a live run emits, so ``RerunView`` (or any subscriber) shows a replay
exactly as it shows a run. Steps come in the order of ``result.json["steps"]``,
then by first sample; results follow the samples.
"""
from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from ...analysis.calibration import MotorCalibration
from ...analysis.efficiency import EfficiencyPoint as AnalysedPoint
from ...errors import GearbenchError
from ...station.records import (Calibration, EfficiencyPoint, LimitResult, Record, RunStart, RunStop,
                       SampleBatch, StepStart, StepStop)
from ...trace import Trace
from ...station.recorder import load_step_trace

REPLAY_BATCH = 10_000   # samples per SampleBatch: large batches are cheapest to log


def _safe(name: str) -> str:
    # Same file-name mapping as the recorder (trace-<step>.parquet).
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name)


def _step_kind(name: str) -> str:
    for kind in ("calibrate", "load", "efficiency"):
        if name.startswith(kind):
            return kind
    return ""


def load_result(result_dir: Path) -> dict:
    """``result.json`` of a run folder, checked for the fields the replay uses."""
    path = result_dir / "result.json"
    if not path.exists():
        return {}
    try:
        result = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise GearbenchError(f"{path}: not readable JSON ({str(exc).splitlines()[0]}); "
                             f"re-run or restore the file") from None
    if not isinstance(result, dict):
        raise GearbenchError(f"{path}: expected a JSON object at the top level")
    for field, kind in (("motors", dict), ("efficiency", list), ("limits", list), ("steps", dict)):
        if result.get(field) is not None and not isinstance(result[field], kind):
            raise GearbenchError(f"{path}: field '{field}' must be a JSON "
                                 f"{'object' if kind is dict else 'list'}")
    for i, lim in enumerate(result.get("limits") or []):
        if not isinstance(lim, dict) or "name" not in lim:
            raise GearbenchError(f"{path}: limits[{i}] needs a 'name'")
    for i, pt in enumerate(result.get("efficiency") or []):
        if not isinstance(pt, dict):
            raise GearbenchError(f"{path}: efficiency[{i}] must be a JSON object")
    return result


def find_traces(result_dir: Path, result: dict) -> list[tuple[str, Trace]]:
    """(step name, trace) in acquisition order."""
    files = {p.stem[len("trace-"):]: p for p in sorted(result_dir.glob("trace-*.arrows"))}
    files.update({p.stem[len("trace-"):]: p for p in sorted(result_dir.glob("trace-*.parquet"))})
    names = {_safe(step): step for step in (result.get("steps") or {})}
    traces = []
    for stem, path in files.items():
        trace = load_step_trace(path)
        if "sample" not in trace:
            raise GearbenchError(f"{path}: no 'sample' column; not a gearbench step trace")
        traces.append((names.get(stem, stem), trace))
    order = list(result.get("steps") or {})
    traces.sort(key=lambda nt: (order.index(nt[0]) if nt[0] in order else len(order),
                                int(nt[1]["sample"][0]) if len(nt[1]) else 0))
    return traces


def replay_records(result_dir: str | Path, *, batch: int = REPLAY_BATCH) -> Iterator[Record]:
    """The records of a finished run, rebuilt from its folder.

    Raises GearbenchError (exit 2) for a folder that is not a run folder.
    """
    d = Path(result_dir)
    if not d.is_dir():
        raise GearbenchError(f"{d}: not a folder; give the output folder of 'gearbench run'")
    result = load_result(d)
    traces = find_traces(d, result)
    if not traces and not result:
        raise GearbenchError(f"{d}: no result.json and no trace-*.parquet; "
                             f"give the output folder of 'gearbench run'")
    motors = tuple(result.get("motors") or ()) or tuple(dict.fromkeys(
        c.partition(".")[0] for _, t in traces for c in t.names if "." in c))
    period_s = next((t.dt_s for _, t in traces if len(t) > 1), 0.0)
    yield RunStart(str(result.get("run_id", d.name)), str(result.get("serial", "")),
                   str(result.get("profile", "")), str(result.get("profile_path", "")),
                   str(result.get("profile_sha256", "")), str(result.get("started_utc", "")),
                   "simulation_truth" in result, motors, period_s, str(d))
    for name, trace in traces:
        yield StepStart(name, _step_kind(name), "replay", len(trace))
        sample = np.asarray(trace["sample"], dtype=np.int64)
        quantities = [c for c in trace.names if c != "sample"]
        for i0 in range(0, len(trace), batch):
            i1 = min(i0 + batch, len(trace))
            yield SampleBatch(name, sample[i0:i1], trace.time_s[i0:i1],
                              {c: trace[c][i0:i1] for c in quantities})
        lost = int(np.sum(np.diff(sample) - 1)) if len(sample) > 1 else 0
        yield StepStop(name, "ok", len(trace), max(lost, 0))
    for motor, params in (result.get("motors") or {}).items():
        try:
            yield Calibration(motor, MotorCalibration.from_dict(params, f"motors.{motor}", motor))
        except GearbenchError:
            continue   # a run that ended before this motor's calibration was complete
    for point in result.get("efficiency") or []:
        try:
            yield EfficiencyPoint(AnalysedPoint.from_dict(point))
        except (KeyError, TypeError, ValueError):
            continue
    for lim in result.get("limits") or []:
        yield LimitResult(str(lim["name"]), lim.get("value"), lim.get("low"), lim.get("high"),
                          bool(lim.get("passed")), str(lim.get("quantity", "")))
    if result:
        status = result.get("status") or ("passed" if result.get("passed") else "failed")
        yield RunStop(str(status), int(result.get("exit_code", 0 if result.get("passed") else 1)),
                      str(result.get("reason", "")), result)


def replay(result_dir: str | Path, subscriber: Callable[[Record], None]) -> int:
    """Feed a finished run to ``subscriber``; returns the number of samples replayed."""
    n = 0
    for record in replay_records(result_dir):
        subscriber(record)
        if isinstance(record, SampleBatch):
            n += len(record.sample)
    return n
