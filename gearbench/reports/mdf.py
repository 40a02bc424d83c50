"""A run's traces as ASAM MDF4 (``.mf4``), the format automotive and drive-train test
benches exchange measurements in (CANape, asammdf's viewer, MATLAB's Vehicle Network
Toolbox read it).

One channel group per step (its acquisition name is the step, e.g. ``efficiency-0``),
the drive time base ``time_s`` as the master channel, every recorded column as a
channel with its unit, and the run's identity (serial, profile and its sha256, run id,
status, station, gearbench version) in the file header. The setpoint column
``<motor>.command`` is in rad/s or A depending on the drive mode of that step, so it
is written as ``<motor>.command_rad_s`` or ``<motor>.command_a`` (modes from the
run's profile, ``gearbench.station.plan.command_units``).
"""
from __future__ import annotations

import json
from datetime import datetime, timezone
from pathlib import Path
from xml.sax.saxutils import escape

import numpy as np

from ..errors import GearbenchError
from ..station.recorder import load_step_trace

# unit of a column by its SI suffix (gearbench's naming: SI inside, unit in the name)
SUFFIX_UNITS = (("_rad_s", "rad/s"), ("_rad", "rad"), ("_a", "A"), ("_nm", "N m"), ("_s", "s"),
                ("_v", "V"), ("_w", "W"))
COMMAND_UNITS = {"rad_s": "rad/s", "a": "A"}
HEADER_KEYS = ("serial", "profile", "profile_sha256", "run_id", "status", "exit_code", "started_utc",
               "finished_utc", "method", "method_version", "gearbench_version")


def column_unit(column: str) -> str:
    """``in.current_a`` -> ``A``; ``sample`` -> ``""`` (a count)."""
    name = column.rsplit(".", 1)[-1]
    for suffix, unit in SUFFIX_UNITS:
        if name.endswith(suffix):
            return unit
    return ""


def _header_comment(result: dict) -> str:
    props = "".join(f'<e name="{escape(k)}">{escape(str(result.get(k, "")))}</e>' for k in HEADER_KEYS)
    station = result.get("station") or {}
    props += "".join(f'<e name="station_{escape(k)}">{escape(str(v))}</e>' for k, v in station.items())
    sim = "simulated bench" if result.get("simulation_truth") is not None else "bench"
    text = (f"gearbench run {result.get('run_id', '')} of unit {result.get('serial', '')} "
            f"({result.get('profile', '')}, {sim}): {str(result.get('status', '')).upper()}")
    return (f"<HDcomment><TX>{escape(text)}</TX><common_properties>{props}"
            f"</common_properties></HDcomment>")


def trace_files(run_dir: Path) -> list[Path]:
    """The run's step traces in the order they were recorded (Parquet, else the partial
    Arrow stream of an interrupted step)."""
    files = sorted(run_dir.glob("trace-*.parquet")) or sorted(run_dir.glob("trace-*.arrows"))
    return sorted(files, key=lambda f: _first_sample(f))


def _first_sample(path: Path) -> float:
    try:
        tr = load_step_trace(path)
        return float(tr["sample"][0]) if len(tr) else float("inf")
    except Exception:
        return float("inf")


def write_mdf(run_dir: str | Path, out: str | Path | None = None,
              command_units: dict[str, dict[str, str]] | None = None) -> Path:
    """Write ``run_dir``'s traces as MDF4 to ``out`` (default ``run_dir/traces.mf4``).

    ``command_units``: per step per motor ``"rad_s"`` or ``"a"`` (the drive mode); a step
    not in it keeps ``<motor>.command`` without a unit and says so in its comment.
    Raises GearbenchError when the folder has no traces or result.json is unreadable."""
    from asammdf import MDF, Signal

    run = Path(run_dir)
    if not run.is_dir():
        raise GearbenchError(f"{run}: not a folder; give a run folder (the --out of 'gearbench run')")
    result = {}
    if (run / "result.json").is_file():
        try:
            result = json.loads((run / "result.json").read_text())
        except (OSError, ValueError) as exc:
            raise GearbenchError(f"{run / 'result.json'}: unreadable ({exc})") from None
    files = trace_files(run)
    if not files:
        raise GearbenchError(f"{run}: no trace-*.parquet files; is this a gearbench run folder?")
    units = command_units or {}
    mdf = MDF(version="4.10")
    mdf.header.comment = _header_comment(result)
    mdf.header.author = "gearbench"
    mdf.header.project = str(result.get("profile", ""))
    mdf.header.subject = str(result.get("serial", ""))
    started = result.get("started_utc")
    if started:
        try:
            mdf.header.start_time = datetime.fromisoformat(started.replace("Z", "+00:00"))
        except ValueError:
            mdf.header.start_time = datetime.now(timezone.utc)
    for path in files:
        step = path.stem.removeprefix("trace-")
        tr = load_step_trace(path)
        if not len(tr):
            continue
        t = np.asarray(tr.time_s, dtype=float)
        signals = []
        for col in tr.columns:
            if col == "time_s":
                continue
            data = np.asarray(tr[col])
            name, unit, comment = col, column_unit(col), ""
            motor, _, quantity = col.partition(".")
            if quantity == "command":
                kind = units.get(step, {}).get(motor)
                if step in units and kind is None:
                    comment = f"motor {motor} not driven in this step (disabled)"
                elif kind in COMMAND_UNITS:
                    name, unit = f"{motor}.command_{kind}", COMMAND_UNITS[kind]
                    comment = f"motor {motor} setpoint ({'velocity' if kind == 'rad_s' else 'current'} mode)"
                else:
                    comment = f"motor {motor} setpoint (drive mode unknown: rad/s or A)"
            elif col == "sample":
                comment = "drive sample counter (SYNC)"
            signals.append(Signal(data, t, name=name, unit=unit, comment=comment))
        mdf.append(signals, acq_name=step, comment=f"step {step}")
    target = Path(out) if out else run / "traces.mf4"
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        mdf.save(target, overwrite=True)
    except OSError as exc:
        raise GearbenchError(f"{target}: cannot write the MDF4 file ({exc.strerror or exc})") from None
    finally:
        mdf.close()
    return target
