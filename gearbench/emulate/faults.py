"""Fault injection on the simulated bench: one run of ``gearbench run --sim`` with one
fault at a chosen instant, and the invariants a bench fault must keep.

Shared by the campaign (``python -m gearbench.benchmarks faults``) and ``tests/test_faults.py``.
Test facility, not a product feature: the emulated drives get their fault through
``GEARBENCH_SIM_FAULT_PLAN`` (fixture commands the emulator applies at a world time,
see ``gearbench.emulate.bench``) and report every state change with its time in
``GEARBENCH_SIM_JOURNAL``; faults outside the drives (signals, disk) are applied by
this harness when the emulator's journal shows the planned ``mark``.

Invariants checked for every run (``None`` = not applicable to this fault):

- ``exit_code``: 3 for a fault, 0 where the fault is tolerated and counted, killed by 9
  for SIGKILL of gearbench;
- ``drives_stopped``: every emulated axis ends without torque (not OPERATION ENABLED or
  QUICK STOP ACTIVE) within ``STOP_BOUND_S`` of the fault, or — for a drive gearbench
  cannot reach (silent, refusing) — is named in the fault as NOT disabled;
- ``samples_kept``: every trace readable (Parquet, or ``read_partial`` of the ``.arrows``
  stream after SIGKILL) and holding what result.json says was acquired;
- ``no_interpolation``: sample counter gaps on disk == lost samples in result.json, no
  repeated counter;
- ``records_consistent``: result.json, junit.xml and the station database agree with
  the exit code and with each other (status, exit code, reason);
- ``no_process_left``: no gearbench or emulator process of the run is alive afterwards.
"""
from __future__ import annotations

import json
import os
import random
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

from ..drives.cia402 import STARVED_LIMIT_FACTOR
from ..station.recorder import read_partial

REPO = Path(__file__).resolve().parents[2]
PROFILES = {"canopen": REPO / "tests" / "data" / "faults-canopen.yaml",
            "modbus": REPO / "tests" / "data" / "faults-modbus.yaml"}
SEGMENT_S = 1.076            # the fault profiles' segments (1 s + fade), world time
ACQUIRED_S = (0.15, 4.2)     # world-time window of their four segments
STOP_BOUND_S = 2.0           # fault (or its detection for a silent drive) -> every axis without torque
SILENCE_S = 0.5              # the CiA 402 master's drive-silence limit (timeout_s default)
KILL_LOSS_BOUND = 2 * 200    # samples SIGKILL may take: the batch being filled and one being written
RUN_TIMEOUT_S = float(os.environ.get("GEARBENCH_FAULT_RUN_TIMEOUT_S", 300))
NO_TORQUE = {"SWITCH ON DISABLED", "READY TO SWITCH ON", "SWITCHED ON", "FAULT", "NOT READY TO SWITCH ON"}
INVARIANTS = ("exit_code", "drives_stopped", "samples_kept", "no_interpolation",
              "records_consistent", "no_process_left")


@dataclass(frozen=True)
class Fault:
    name: str
    bus: str                       # canopen | modbus
    expect_exit: int               # 3 fault, 0 tolerated, -9 killed
    expect_status: str | None      # result.json status (None: no result.json can exist)
    plan: str = "mark"             # how the fault is applied (see _plan / _act)
    reason: str = ""               # a word the fault's reason must contain
    doc: str = ""


FAULTS = {f.name: f for f in [
    Fault("drive-silent", "canopen", 3, "fault", "mute", "silent", "one drive stops answering (cut cable)"),
    Fault("heartbeat-lost", "canopen", 0, "passed", "heartbeat", "",
          "one drive stops its heartbeat only: any frame is life, tolerated and counted"),
    Fault("emcy-overcurrent", "canopen", 3, "fault", "emcy", "0x2310", "drive FAULT with EMCY 0x2310"),
    Fault("pdo-drop-burst", "canopen", 3, "fault", "drop", "lost on the bus",
          "30 % of TPDOs dropped for 50 ms: lost samples counted, never filled in; the "
          "calibration step refuses data with lost samples (repeat the step)"),
    Fault("refuse-disable", "canopen", 3, "fault", "refuse", "did NOT",
          "one drive ignores disable: named, no further segment"),
    Fault("modbus-exception", "modbus", 3, "fault", "modbus-exception", "exception",
          "one Modbus request answered with exception 4 (device failure)"),
    Fault("modbus-disconnect", "modbus", 3, "fault", "modbus-disconnect", "",
          "the drives' TCP connection is closed under the master"),
    Fault("modbus-slow", "modbus", 0, "passed", "modbus-slow", "",
          "10 answers 0.2 s late (within the 1 s timeout): lockstep waits, nothing lost"),
    Fault("sigint", "canopen", 3, "aborted", "mark", "Ctrl-C", "operator abort (Ctrl-C)"),
    Fault("sigterm", "canopen", 3, "aborted", "mark", "SIGTERM", "SIGTERM to gearbench"),
    Fault("sigkill-gearbench", "canopen", -9, None, "mark", "", "SIGKILL of gearbench"),
    Fault("sigkill-emulator", "canopen", 3, "fault", "mark", "silent", "SIGKILL of the emulated drives"),
    Fault("disk-full", "canopen", 3, "fault", "mark", "output failed", "trace folder's disk fills up"),
    Fault("read-only", "canopen", 3, "fault", "mark", "output failed", "trace folder becomes read-only"),
    Fault("vanished-dir", "canopen", 3, "fault", "mark", "output failed", "output folder removed mid-run"),
    Fault("cpu-hog", "canopen", 0, "passed", "hog", "",
          "both cores kept busy by other processes: PASS with 0 lost samples"),
]}


@dataclass
class Outcome:
    fault: str
    seed: int
    at_s: float
    rc: int | None = None
    invariants: dict = field(default_factory=dict)     # name -> (True/False/None, detail)
    figures: dict = field(default_factory=dict)
    note: str = ""
    run_dir: str = ""

    @property
    def ok(self) -> bool:
        return all(v[0] is not False for v in self.invariants.values())

    def failures(self) -> list[str]:
        return [f"{k}: {v[1]}" for k, v in self.invariants.items() if v[0] is False]


# ---------------------------------------------------------------------- the run
def _plan(fault: Fault, at_s: float, axis: str) -> list[dict]:
    p = fault.plan
    if p == "mute":
        return [{"cmd": "mute", "axis": axis, "at_s": at_s}]
    if p == "heartbeat":
        return [{"cmd": "heartbeat", "axis": axis, "on": False, "at_s": at_s}]
    if p == "emcy":
        return [{"cmd": "fault", "axis": axis, "code": 0x2310, "at_s": at_s}]
    if p == "drop":
        return [{"cmd": "drop", "rate": 0.3, "at_s": at_s}, {"cmd": "drop", "rate": 0.0, "at_s": at_s + 0.05}]
    if p == "refuse":
        return [{"cmd": "refuse_disable", "axis": axis, "on": True, "at_s": at_s}]
    if p == "modbus-exception":
        return [{"cmd": "modbus", "exception": 4, "count": 1, "at_s": at_s}]
    if p == "modbus-disconnect":
        return [{"cmd": "modbus", "disconnect": True, "at_s": at_s}]
    if p == "modbus-slow":
        return [{"cmd": "modbus", "delay_s": 0.2, "count": 10, "at_s": at_s}]
    if p == "hog":
        return []
    return [{"cmd": "mark", "label": fault.name, "at_s": at_s}]


def _journal(path: Path) -> list[dict]:
    try:
        lines = path.read_text().splitlines()
    except OSError:
        return []
    out = []
    for ln in lines:
        try:
            out.append(json.loads(ln))
        except ValueError:
            pass      # a line cut by a kill
    return out


def _mount_tmpfs(path: Path, size: str = "4m") -> bool:
    path.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0 or not shutil.which("mount"):
        return False
    return subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                          capture_output=True).returncode == 0


def _umount(path: Path) -> None:
    subprocess.run(["umount", "-l", str(path)], capture_output=True)


def _fill(path: Path) -> None:
    """Fill the file system under ``path`` to the last byte."""
    chunk = b"\0" * (1 << 16)
    try:
        with open(path / "filler.bin", "wb") as f:
            while True:
                f.write(chunk)
                f.flush()
    except OSError:
        pass


def _our_processes(token: str) -> list[int]:
    """Live processes whose command line names ``token`` (this run's unique folder)."""
    pids = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit() or int(d.name) == os.getpid():
            continue
        try:
            cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            state = (d / "stat").read_text().rpartition(")")[2].split()[0]
        except OSError:
            continue
        if token in cmd and state != "Z":
            pids.append(int(d.name))
    return pids


def _hogs(n: int = 2) -> list[subprocess.Popen]:
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def run_fault(name: str, seed: int, work: Path, *, at_s: float | None = None) -> Outcome:
    """One run of the fault's profile with the fault injected; the invariants checked."""
    fault = FAULTS[name]
    rng = random.Random(f"{name}-{seed}")
    at_s = round(rng.uniform(*ACQUIRED_S), 3) if at_s is None else at_s
    # the profiles calibrate 'in' (two segments), then 'out': fault the axis that is moving then
    axis = "in" if at_s < 2 * SEGMENT_S else "out"
    run_dir = work / f"{name}-{seed}"
    if run_dir.exists():
        shutil.rmtree(run_dir)
    run_dir.mkdir(parents=True)
    out = run_dir / "out" / "run"
    db = run_dir / "station.sqlite"
    journal = run_dir / "journal.jsonl"
    outcome = Outcome(name, seed, at_s, figures={"axis": axis})
    mounted = False
    if fault.name in ("disk-full", "read-only"):
        mounted = _mount_tmpfs(out.parent)
        if not mounted:
            outcome.note = "no tmpfs (mount not permitted): "
            outcome.note += ("fell back to a vanished folder" if fault.name == "disk-full"
                             else "fell back to chmod a-w")
    env = dict(os.environ, GEARBENCH_SIM_JOURNAL=str(journal),
               GEARBENCH_SIM_FAULT_PLAN=json.dumps(_plan(fault, at_s, axis)), PYTHONUNBUFFERED="1")
    cmd = [sys.executable, "-m", "gearbench", "run", str(PROFILES[fault.bus]), "--sim", "--quiet",
           "--out", str(out), "--db", str(db), "--serial", f"FI-{name}-{seed}"]
    hogs = _hogs() if fault.plan == "hog" else []
    stderr = open(run_dir / "stderr.txt", "w+")
    t_start = time.time()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=stderr, env=env, cwd=str(run_dir))
    fault_wall = None
    try:
        deadline = time.monotonic() + RUN_TIMEOUT_S
        while proc.poll() is None and time.monotonic() < deadline:
            if fault.plan == "mark" and fault_wall is None:
                if any(e.get("event") == "command" and e.get("cmd") == "mark" for e in _journal(journal)):
                    fault_wall = _act(fault, proc, journal, out, mounted)
            time.sleep(0.02)
        if proc.poll() is None:
            proc.kill()
            outcome.note += f" run did not end within {RUN_TIMEOUT_S:.0f} s (killed)"
        outcome.rc = proc.wait()
    finally:
        for h in hogs:
            h.kill()
            h.wait()
    outcome.figures["wall_s"] = round(time.time() - t_start, 1)
    outcome.figures["fault_wall_s"] = fault_wall
    outcome.run_dir = str(run_dir)
    stderr.close()
    try:
        check_run(outcome, fault)
    finally:
        if mounted:
            subprocess.run(["mount", "-o", "remount,rw", str(out.parent)], capture_output=True)
            _umount(out.parent)
    return outcome


def _act(fault: Fault, proc, journal: Path, out: Path, mounted: bool) -> float:
    """Apply a fault outside the drives, now; returns its wall time."""
    t = time.time()
    if fault.name == "sigint":
        proc.send_signal(signal.SIGINT)
    elif fault.name == "sigterm":
        proc.send_signal(signal.SIGTERM)
    elif fault.name == "sigkill-gearbench":
        proc.kill()
    elif fault.name == "sigkill-emulator":
        pid = next(e["pid"] for e in _journal(journal) if e.get("event") == "ready")
        os.kill(pid, signal.SIGKILL)
    elif fault.name == "disk-full":
        if mounted:
            _fill(out.parent)
        else:
            shutil.rmtree(out, ignore_errors=True)
    elif fault.name == "read-only":
        if mounted:
            # Linux refuses (EBUSY) while a trace file is open for writing: retry until the
            # recorder is between files (a step's end), as a folder going read-only would be seen
            deadline = time.monotonic() + 30
            while subprocess.run(["mount", "-o", "remount,ro", str(out.parent)],
                                 capture_output=True).returncode and time.monotonic() < deadline \
                    and proc.poll() is None:
                time.sleep(0.005)
            t = time.time()
        else:
            os.chmod(out, 0o555)
    elif fault.name == "vanished-dir":
        shutil.rmtree(out, ignore_errors=True)
    return t


# ---------------------------------------------------------------------- the invariants
def _traces(out: Path) -> dict:
    """step file stem -> sample counter array, for every trace file on disk (None: unreadable)."""
    import numpy as np
    import pyarrow.parquet as pq

    found = {}
    for p in sorted(out.glob("trace-*.parquet")) + sorted(out.glob("trace-*.arrows")):
        try:
            table = pq.read_table(p) if p.suffix == ".parquet" else read_partial(p)
            found[p.name] = np.asarray(table.column("sample").to_numpy(), dtype=np.int64)
        except Exception as exc:    # unreadable is exactly what this check looks for
            found[p.name] = f"{type(exc).__name__}: {exc}"
    return found


def _safe(step: str) -> str:
    import re
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", step)


@dataclass
class _Evidence:
    """What a finished fault run left behind, read once for every invariant."""
    out: Path                      # the run's output folder
    db: Path                       # the station database
    events: list[dict]             # the emulator's journal
    injected: list[dict]           # journal lines of injected commands (not mounts)
    result: dict | None            # result.json, if written
    reason: str                    # the run's stated reason: result.json, else database, else stderr
    t_fault: float | None          # wall time of the fault
    arrays: dict                   # trace file -> sample counters
    unreadable: dict               # trace file -> why it could not be read


def check_run(o: Outcome, fault: Fault) -> None:
    """Judge a finished run (its folder ``o.run_dir``) against ``fault``'s expectations:
    one entry in ``o.invariants`` per invariant (module docstring), figures in ``o.figures``."""
    o.invariants = inv = {}
    inv["no_process_left"] = _no_process_left(o, fault)
    ev = _evidence(o)
    inv["exit_code"] = _exit_code(o, fault, ev)
    inv["drives_stopped"] = _drives_stopped(o, fault, ev)
    inv["samples_kept"] = _samples_kept(o, fault, ev)
    inv["no_interpolation"] = _no_interpolation(o, fault, ev)
    inv["records_consistent"] = _records_consistent(o, fault, ev)
    o.figures["heartbeat_gaps"] = ((ev.result or {}).get("supervision") or {}).get("heartbeat_gaps")
    if fault.name == "heartbeat-lost" and ev.result is not None and not o.figures["heartbeat_gaps"]:
        inv["exit_code"] = (False, "heartbeat stopped but supervision.heartbeat_gaps is 0 (not counted)")
    if fault.name == "pdo-drop-burst" and ev.result is not None:
        o.figures["dropped_frames"] = (ev.result.get("supervision") or {}).get("dropped_frames")


def _no_process_left(o: Outcome, fault: Fault) -> tuple:
    """No gearbench or emulator process of the run alive (the emulator ends by itself when
    gearbench is gone); any left are killed, never left to the next run."""
    run_dir = Path(o.run_dir)
    deadline = time.monotonic() + 15
    left = _our_processes(str(run_dir))
    while left and time.monotonic() < deadline:
        time.sleep(0.2)
        left = _our_processes(str(run_dir))
    t_gone = None
    exit_ev = [e for e in _journal(run_dir / "journal.jsonl") if e.get("event") == "exit"]
    fault_wall = o.figures.get("fault_wall_s")
    if exit_ev and fault_wall is not None and fault.name == "sigkill-gearbench":
        t_gone = round(exit_ev[-1]["wall_s"] - fault_wall, 2)
        o.figures["emulator_exit_s"] = t_gone
    for pid in left:
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass
    return (not left, f"left: {left}" if left else
            (f"emulator ended {t_gone} s after the kill" if t_gone is not None else "none left"))


def _evidence(o: Outcome) -> _Evidence:
    run_dir = Path(o.run_dir)
    out, db = run_dir / "out" / "run", run_dir / "station.sqlite"
    err = (run_dir / "stderr.txt").read_text(errors="replace")
    events = _journal(run_dir / "journal.jsonl")
    result = None
    try:
        result = json.loads((out / "result.json").read_text())
    except (OSError, ValueError):
        pass
    db_reason = ""
    try:
        with sqlite3.connect(db) as con:
            row = con.execute("SELECT result_json FROM runs").fetchone()
        db_reason = str(json.loads(row[0]).get("reason", "")) if row else ""
    except (sqlite3.Error, ValueError, TypeError):
        pass
    # the truth where it could be written: result.json, else the station database, else stderr
    reason = str((result or {}).get("reason", "")) or db_reason or err
    o.figures["reason"] = reason.strip().splitlines()[-1][:300] if reason.strip() else ""
    # the fault instant: the harness's action, else the injected command's journal line
    injected = [e for e in events if e.get("event") == "command" and e.get("cmd") != "mount"]
    fault_wall = o.figures.get("fault_wall_s")
    t_fault = fault_wall if fault_wall is not None else (injected[0]["wall_s"] if injected else None)
    o.figures["fault_t_s"] = injected[0]["t_s"] if injected else None
    traces = _traces(out) if out.exists() else {}
    return _Evidence(out, db, events, injected, result, reason, t_fault,
                     {k: v for k, v in traces.items() if not isinstance(v, str)},
                     {k: v for k, v in traces.items() if isinstance(v, str)})


def _exit_code(o: Outcome, fault: Fault, ev: _Evidence) -> tuple:
    ok = (o.rc == fault.expect_exit, f"exit {o.rc}, expected {fault.expect_exit}")
    if fault.reason and o.rc == fault.expect_exit and fault.reason not in ev.reason:
        ok = (False, f"exit {o.rc} but the reason does not say {fault.reason!r}: {ev.reason[-300:]}")
    if fault.plan == "mark" and o.figures.get("fault_wall_s") is None and fault.expect_exit != 0 and ok[0]:
        ok = (False, "the planned instant never came (run ended before it)")
    return ok


def _drives_stopped(o: Outcome, fault: Fault, ev: _Evidence) -> tuple:
    """Every axis without torque within the bound after the fault, or named as NOT disabled."""
    final, since = {}, {}
    for e in ev.events:
        if e.get("event") == "state":
            final[e["axis"]] = e["new"]
            since[e["axis"]] = e["wall_s"]
    if fault.name == "sigkill-gearbench":
        exit_ev = [e for e in ev.events if e.get("event") == "exit"]
        return (None, "nobody left to stop them: lockstep world frozen, emulator "
                      f"ended ({exit_ev[0]['why'] if exit_ev else 'no exit line'})")
    if fault.name == "sigkill-emulator":
        named = all(f"'{a}'" in ev.reason and "did NOT" in ev.reason for a in ("in", "out"))
        return (named, "both drives named as NOT disabled" if named
                else f"the stop report does not name both dead drives: {ev.reason[-300:]}")
    bad, times = [], []
    for a in sorted(final):
        if final[a] not in NO_TORQUE:
            if f"'{a}'" in ev.reason and "did NOT" in ev.reason:
                continue     # truthfully reported: gearbench cannot reach it (silent, refusing)
            bad.append(f"{a} ended {final[a]} and the fault does not name it")
        elif ev.t_fault is not None and since[a] >= ev.t_fault:
            times.append(since[a] - ev.t_fault)
    # a silence verdict comes after the silence limit; an emulated drive starved of CPU is
    # given up to STARVED_LIMIT_FACTOR limits (drives.cia402), counted in the result
    starved = ((ev.result or {}).get("supervision") or {}).get("starved_deferrals")
    bound = STOP_BOUND_S + (SILENCE_S * (STARVED_LIMIT_FACTOR if starved else 1)
                            if fault.name in ("drive-silent", "modbus-disconnect", "modbus-slow") else 0.0)
    # lost samples are judged when the step's data are analysed: the drives stop at the
    # segment's regular end, not at the drop
    if ev.t_fault is not None and fault.expect_exit == 3 and fault.name != "pdo-drop-burst":
        o.figures["stop_s"] = round(max(times), 3) if times else 0.0
        if times and max(times) > bound:
            bad.append(f"last axis without torque {max(times):.2f} s after the fault (bound {bound:g} s)")
    return (not bad, "; ".join(bad) or f"final {final}")


def _samples_kept(o: Outcome, fault: Fault, ev: _Evidence) -> tuple:
    """Every trace readable and holding what result.json says was acquired."""
    arrays, unreadable, result = ev.arrays, ev.unreadable, ev.result
    on_disk = int(sum(len(v) for v in arrays.values()))
    o.figures["samples_on_disk"] = on_disk
    if fault.name in ("disk-full", "read-only", "vanished-dir"):
        # the disk refused the samples: what it did hold must be readable, and the run a fault
        return (not unreadable, "readable: " + (", ".join(sorted(arrays)) or "none")
                + (f"; unreadable {unreadable}" if unreadable else ""))
    if result is not None:
        bad = [f"{k}: {v}" for k, v in unreadable.items()]
        for step, n in result.get("steps", {}).items():
            got = len(arrays.get(f"trace-{_safe(step)}.parquet", ()))
            if got != n:
                bad.append(f"{step}: {got} samples on disk, result.json says {n}")
        if on_disk != result.get("samples"):
            bad.append(f"{on_disk} samples on disk, result.json says {result.get('samples')}")
        return (not bad, "; ".join(bad) or f"{on_disk} samples, all readable")
    if fault.name == "sigkill-gearbench":
        mark = [e for e in ev.injected if e.get("cmd") == "mark"]
        last = max((int(v[-1]) for v in arrays.values() if len(v)), default=0)
        want = round(mark[0]["t_s"] / 1e-3) - KILL_LOSS_BOUND if mark else 0
        ok = not unreadable and (last >= want or not mark)
        return (ok, f"last sample on disk {last}, kill at sample ~{want + KILL_LOSS_BOUND}; "
                    f"{len(arrays)} files readable" + (f"; unreadable {unreadable}" if unreadable else ""))
    return (False, "no result.json")


def _no_interpolation(o: Outcome, fault: Fault, ev: _Evidence) -> tuple:
    """Sample-counter gaps on disk == lost samples in result.json; no repeated counter."""
    import numpy as np

    gaps, repeats = {}, []
    for k, v in ev.arrays.items():
        d = np.diff(v)
        gaps[k] = int(np.sum(d[d > 1] - 1))
        if np.any(d < 1):
            repeats.append(k)
    o.figures["gaps"] = sum(gaps.values())
    if ev.result is None or ev.unreadable:
        return (not repeats and (fault.name != "sigkill-gearbench" or not o.figures["gaps"]),
                f"no result.json; gaps on disk {o.figures['gaps']}, repeats {repeats}")
    lost = int(ev.result.get("lost_samples", -1))
    bad = [f"{s}: {gaps.get(f'trace-{_safe(s)}.parquet', 0)} gaps on disk, {n} lost"
           for s, n in ev.result.get("lost_samples_by_step", {}).items()
           if f"trace-{_safe(s)}.parquet" in ev.arrays and gaps[f"trace-{_safe(s)}.parquet"] != n]
    if fault.name not in ("disk-full", "read-only", "vanished-dir") and sum(gaps.values()) != lost:
        bad.append(f"{sum(gaps.values())} gaps on disk, lost_samples {lost}")
    if fault.name == "cpu-hog" and lost:
        bad.append(f"{lost} samples lost under the CPU hog")
    o.figures["lost"] = lost
    return (not bad and not repeats, "; ".join(bad + [f"repeated counter in {r}" for r in repeats])
            or f"gaps {sum(gaps.values())} == lost {lost}")


def _records_consistent(o: Outcome, fault: Fault, ev: _Evidence) -> tuple:
    """result.json, junit.xml and the station database agree with the exit code and each other."""
    rows = []
    try:
        with sqlite3.connect(ev.db) as con:
            rows = con.execute("SELECT run_id, status, exit_code FROM runs").fetchall()
    except sqlite3.Error:
        pass
    result, bad = ev.result, []
    if fault.expect_status is None:   # killed: nothing may claim the run finished
        if result is not None or rows:
            bad.append(f"a killed run left result.json={result is not None} db rows={rows}")
        return (not bad, "; ".join(bad) or "result.json, junit.xml, database agree")
    if len(rows) != 1:
        bad.append(f"{len(rows)} runs in the station database")
    else:
        _, status, code = rows[0]
        if status != fault.expect_status and fault.expect_exit == o.rc:
            bad.append(f"database status {status}, expected {fault.expect_status}")
        if code != o.rc:
            bad.append(f"database exit code {code}, process exit {o.rc}")
    disk_fault = fault.name in ("disk-full", "read-only", "vanished-dir")
    if result is None:
        if not disk_fault:
            bad.append("no result.json")
        elif fault.reason not in ev.reason:
            bad.append("no result.json and stderr does not name the output failure")
    else:
        if (result.get("status"), result.get("exit_code")) != (fault.expect_status, o.rc):
            bad.append(f"result.json {result.get('status')}/{result.get('exit_code')}, process exit {o.rc}")
        if rows and rows[0][0] != result.get("run_id"):
            bad.append("result.json and the database name different runs")
    junit = ev.out / "junit.xml"
    if junit.exists():
        errors = int(ET.parse(junit).getroot().get("errors", 0))
        if errors != (1 if fault.expect_status in ("fault", "aborted") else 0):
            bad.append(f"junit.xml errors={errors} for status {fault.expect_status}")
    elif not disk_fault:
        bad.append("no junit.xml")
    return (not bad, "; ".join(bad) or "result.json, junit.xml, database agree")


# ---------------------------------------------------------------------- the matrix
def matrix(outcomes: list[Outcome]) -> str:
    """fault x invariant: 'ok n' / 'FAIL k/n' / 'n/a'; runs and failed runs per fault."""
    names = list(dict.fromkeys(o.fault for o in outcomes))
    w = max(len(n) for n in names + ["fault"])
    head = f"{'fault':<{w}}  runs  fail  " + "  ".join(f"{i:>18}" for i in INVARIANTS)
    lines = [head, "-" * len(head)]
    for n in names:
        rows = [o for o in outcomes if o.fault == n]
        cells = []
        for i in INVARIANTS:
            vals = [o.invariants.get(i, (None, ""))[0] for o in rows]
            judged = [v for v in vals if v is not None]
            fails = sum(1 for v in judged if v is False)
            cells.append("n/a" if not judged else (f"FAIL {fails}/{len(judged)}" if fails else f"ok {len(judged)}"))
        lines.append(f"{n:<{w}}  {len(rows):>4}  {sum(not o.ok for o in rows):>4}  "
                     + "  ".join(f"{c:>18}" for c in cells))
    total = len(outcomes)
    lines.append(f"{'total':<{w}}  {total:>4}  {sum(not o.ok for o in outcomes):>4}")
    return "\n".join(lines)
