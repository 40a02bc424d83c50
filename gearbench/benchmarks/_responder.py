"""The compiled drives' stand-ins of the real-time benchmarks (``tools/responder/``).

``Responder`` (``responder.c``, CANopen, drives_can --paced): fed the TPDO payloads the
emulated drives sent last (their SYNC counter echo is rewritten per SYNC).
``ModbusStandIn`` (``modbus_stand_in.c``, drives_modbus free-running): two Modbus TCP
drives of the generic register map whose sample counter is the clock at each answer.
Both are built with the host's C compiler on first use (a few hundred ms; cached by the
source's hash), started at SCHED_FIFO above the master with their memory locked, and
asked for their own counters over stdin. See the C files for what they count.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import can
import numpy as np

SOURCE = Path(__file__).resolve().parents[2] / "tools" / "responder" / "responder.c"
MODBUS_SOURCE = SOURCE.with_name("modbus_stand_in.c")


def available(source: Path = SOURCE) -> str | None:
    """None when the stand-in can be built here, else why not (said in the benchmark's table)."""
    if not source.exists():
        return f"{source} not found (an installed package without the source tree)"
    if shutil.which(os.environ.get("CC", "gcc")) is None:
        return "no C compiler (gcc) on PATH"
    return None


def build(source: Path = SOURCE) -> Path:
    """The stand-in's executable, compiled once per source version."""
    digest = hashlib.sha256(source.read_bytes()).hexdigest()[:12]
    exe = Path(tempfile.gettempdir()) / f"gearbench-{source.stem.replace('_', '-')}-{digest}"
    if not exe.exists():
        tmp = exe.with_suffix(f".{os.getpid()}")
        subprocess.run([os.environ.get("CC", "gcc"), "-O2", "-Wall", "-o", str(tmp), str(source), "-lm"],
                       check=True, capture_output=True, text=True)
        tmp.replace(exe)
    return exe


def last_tpdos(bus: can.BusABC, cob_ids, timeout_s: float = 2.0) -> dict[int, bytes]:
    """The latest payload of each of ``cob_ids`` seen on ``bus`` (frames the emulated drives send)."""
    want, got = set(cob_ids), {}
    deadline = time.monotonic() + timeout_s
    while set(got) != want:
        if time.monotonic() > deadline:
            raise RuntimeError(f"no TPDO {sorted(hex(c) for c in want - set(got))} on the bus within {timeout_s} s")
        msg = bus.recv(0.05)
        if msg is not None and msg.arbitration_id in want:
            got[msg.arbitration_id] = bytes(msg.data)
    return got


class _StandIn:
    """A compiled stand-in process speaking a line protocol on stdin/stdout: ``counters()`` while
    it runs, ``stop()`` returns the last ones (stdin closed = stop)."""
    proc: subprocess.Popen

    def counters(self) -> dict:
        self.proc.stdin.write("status\n")
        self.proc.stdin.flush()
        return json.loads(self.proc.stdout.readline())

    def stop(self) -> dict:
        if self.proc.poll() is not None:
            return {}
        self.proc.stdin.close()
        out = self.proc.stdout.readline()
        self.proc.wait(5)
        return json.loads(out) if out.strip() else {}


class Responder(_StandIn):
    """The running CAN stand-in: ``counters()`` while it runs, ``stop()`` returns the last ones."""

    def __init__(self, group: str, port: int, period_s: float, late_limit_s: float,
                 tpdos: dict[int, tuple[bytes, int]], priority: int):
        args = [f"{cob:x}:{payload.hex()}:{echo}" for cob, (payload, echo) in sorted(tpdos.items())]
        self.stamps_path = Path(tempfile.mkdtemp(prefix="gearbench-responder-")) / "sync-stamps.bin"
        self.proc = subprocess.Popen([str(build()), "-s", str(self.stamps_path), group, str(port), repr(period_s),
                                      repr(late_limit_s), str(priority), *args],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        line = self.proc.stdout.readline().strip()
        if not line.startswith("ready"):
            self.proc.kill()
            raise RuntimeError(f"responder did not start: {line!r}")
        self.priority = line.removeprefix("ready").strip()
        self.pid = self.proc.pid

    def sync_stamps(self) -> np.ndarray:
        """After ``stop()``: (kernel receive time s, counter) of every SYNC it heard, in order."""
        raw = np.fromfile(self.stamps_path, dtype=np.int64).reshape(-1, 2) if self.stamps_path.exists() \
            else np.zeros((0, 2), np.int64)
        shutil.rmtree(self.stamps_path.parent, ignore_errors=True)
        return np.column_stack([raw[:, 0] * 1e-9, raw[:, 1]])


class ModbusStandIn(_StandIn):
    """Two Modbus TCP drives (unit ids 1, 2, the generic register map) on two loopback ports the OS
    picks (``ports``: one connection per drive, as drives with an IP each); ``counters()`` while it
    runs, ``stop()`` returns the last ones."""

    def __init__(self, counter_period_s: float, cell_counts: int, late_s: float, priority: int,
                 history: tuple[int, int] | None = None):
        ring = [str(history[0]), str(history[1])] if history else []   # (address, depth): the drives' ring
        self.proc = subprocess.Popen([str(build(MODBUS_SOURCE)), repr(counter_period_s), str(cell_counts),
                                      repr(late_s), str(priority), *ring],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        words = self.proc.stdout.readline().split(maxsplit=3)
        if words[:1] != ["ready"] or len(words) < 3:
            self.proc.kill()
            raise RuntimeError(f"Modbus stand-in did not start: {' '.join(words)!r}")
        self.ports = (int(words[1]), int(words[2]))
        self.priority = words[3].strip() if len(words) > 3 else "normal"
        self.pid = self.proc.pid
