"""Benchmark: SYNC interval jitter by producer, and lockstep samples/s, on one CAN bus.

``python -m gearbench.benchmarks sync_jitter [--bus socketcan:vcan0] [--period-s 0.001] [--duration-s 5]
[--producers kernel thread loop] [--lockstep-samples 2000]``

Two CiA 402 drives (``gearbench emulate`` in another process) sampled in paced mode
with each SYNC producer in turn: ``kernel`` (socketcan broadcast manager), ``thread``
(a thread at absolute deadlines), ``loop`` (the sample loop paces and sends SYNC
itself). An independent listener (its own python-can bus on the same channel) takes
the bus's receive timestamp of every SYNC; the figure is the deviation of each SYNC
interval from the period (p50 / p99 / max), the SYNC rate achieved, and the samples
the master got and lost. Then lockstep (SYNC as fast as the drives answer): samples/s.
On socketcan run it where vcan0 exists, e.g. ``.ci/vcan -- .venv/bin/python -m
gearbench.benchmarks sync_jitter`` in the CI guest (software-emulated: its figures are
the emulator's, not a real kernel's).

``--candump-log FILE`` adds the kernel broadcast manager's row from a ``candump -L`` log
of its SYNC frames (kernel receive timestamps), as ``.ci/vcan --sync-jitter`` records it
on vcan0 in the guest, where the whole benchmark is too slow to run: there it is the
producer alone, the row beside the others measured here (e.g. ``--bus
udp_multicast:239.74.163.2:43113 --producers thread``).
"""
from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

from ..drives.base import AxisConfig, Mode
from ..drives.buses import open_bus, parse_bus
from ..drives.cia402 import CiA402Network
from ..drives.realtime import acquisition_priority
from ..errors import BenchFault
from ._cpu import floor_text, load_average, realtime_stand_in, timer_floor
from .drives_can import _start_listener, sync_intervals

NET = dict(heartbeat_ms=500, timeout_s=3.0, sdo_timeout_s=1.0, state_timeout_s=3.0)
if os.environ.get("GEARBENCH_VCAN_EMULATED"):   # .ci/vcan's TCG guest: Python 20-100x slower, bounds to match
    NET.update(timeout_s=20.0, sdo_timeout_s=10.0, state_timeout_s=10.0, master_timeout_ms=20000)


class SyncListener:
    """Receive timestamps of SYNC (0x080) frames on its own bus connection."""

    def __init__(self, bus: str):
        self.bus = open_bus(bus, can_filters=[{"can_id": 0x80, "can_mask": 0x7FF}])
        self.stamps: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(0.1)
            if msg is not None and msg.arbitration_id == 0x80:
                self.stamps.append(msg.timestamp)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join(2)
        self.bus.shutdown()


def _drives(net: CiA402Network, period_s: float) -> None:
    din = net.add_drive(AxisConfig("in", 1, ""))
    dout = net.add_drive(AxisConfig("out", 2, ""))
    net.start(period_s)
    din.enable(Mode.VELOCITY)
    dout.enable(Mode.TORQUE)
    din.set_setpoint(100.0)
    dout.set_setpoint(0.1)


def paced(bus: str, producer: str, period_s: float, duration_s: float) -> dict:
    path = os.path.join(tempfile.mkdtemp(prefix="gearbench-sync-"), "stamps.npy")
    with CiA402Network(bus=bus, lockstep=False, sync=producer, **NET) as net:
        _drives(net, period_s)
        with acquisition_priority(net.acquisition_threads(), realtime=True):
            net.sample()                               # producer started, first answer in
            listener = _start_listener(bus, path)      # its own process: its work is not the master's
            try:
                got, t_end = 0, time.perf_counter() + duration_s
                first_index = net.sync_count
                while time.perf_counter() < t_end:
                    net.sample()
                    got += 1
                syncs = net.sync_count - first_index
            finally:
                listener.stdin.close()
                listener.wait(30)
        stamps = np.load(path) if os.path.exists(path) else np.zeros((0, 2))
    intervals = sync_intervals(stamps)
    dev_us = np.abs(intervals - period_s) * 1e6 if len(intervals) > 1 else np.array([np.nan])
    span = stamps[-1, 0] - stamps[0, 0] if len(stamps) > 1 else np.nan
    return {"producer": producer, "syncs_seen": len(stamps), "rate_hz": (len(stamps) - 1) / span,
            "p50_us": np.percentile(dev_us, 50), "p99_us": np.percentile(dev_us, 99), "max_us": dev_us.max(),
            "samples": got, "lost": syncs - got}


def candump_sync_stamps(lines) -> np.ndarray:
    """(receive time s, counter) of the SYNC frames (COB-ID 0x080) in ``candump -L`` log lines,
    ``(1700000000.123456) vcan0 080#2A``; counter -1 where the SYNC carries none."""
    rows = []
    for line in lines:
        parts = line.split()
        if len(parts) < 3 or not parts[0].startswith("("):
            continue
        can_id, _, data = parts[2].partition("#")
        if int(can_id, 16) != 0x80:
            continue
        rows.append((float(parts[0].strip("()")), int(data[:2], 16) if data else -1))
    return np.array(rows, dtype=float).reshape(-1, 2)


def jitter_row(stamps: np.ndarray, period_s: float) -> dict:
    """|dT - T| p50 / p99 / max (us) of the SYNC intervals one counter step apart, the rate achieved
    and the SYNCs the receiver never saw (counter gaps)."""
    intervals = sync_intervals(stamps)
    dev_us = np.abs(intervals - period_s) * 1e6 if len(intervals) > 1 else np.array([np.nan])
    span = stamps[-1, 0] - stamps[0, 0] if len(stamps) > 1 else np.nan
    gaps = int(((np.diff(stamps[:, 1]) - 1) % 240).sum()) if len(stamps) > 1 and (stamps[:, 1] >= 0).all() else 0
    return {"syncs_seen": len(stamps), "rate_hz": (len(stamps) - 1) / span, "p50_us": np.percentile(dev_us, 50),
            "p99_us": np.percentile(dev_us, 99), "max_us": dev_us.max(), "unseen": gaps}


def lockstep(bus: str, period_s: float, n: int) -> dict:
    with CiA402Network(bus=bus, lockstep=True, **NET) as net:
        _drives(net, period_s)
        net.sample()
        t0 = time.perf_counter()
        for _ in range(n):
            net.sample()
        wall = time.perf_counter() - t0
        return {"samples": n, "wall_s": wall, "samples_per_s": n / wall, "lost": net.lost_samples}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m gearbench.benchmarks sync_jitter", description=__doc__.splitlines()[0])
    default_bus = f"socketcan:{os.environ.get('GEARBENCH_VCAN', 'vcan0')}"
    p.add_argument("--bus", default=default_bus, help=f"CAN bus (default {default_bus})")
    p.add_argument("--period-s", type=float, default=1e-3, help="SYNC period (s)")
    p.add_argument("--duration-s", type=float, default=5.0, help="wall time per paced producer (s)")
    p.add_argument("--producers", nargs="+", default=None, choices=["kernel", "thread", "loop"],
                   help="default: kernel (socketcan only), thread, loop")
    p.add_argument("--lockstep-samples", type=int, default=2000)
    p.add_argument("--candump-log", help="a candump -L log of the broadcast manager's SYNC (.ci/vcan --sync-jitter)")
    p.add_argument("--where", default="", help="where the candump log was recorded (printed)")
    args = p.parse_args(argv)
    if args.candump_log:
        try:
            with open(args.candump_log) as f:
                r = jitter_row(candump_sync_stamps(f), args.period_s)
        except (OSError, ValueError) as exc:
            print(f"{args.candump_log}: not a candump -L log of SYNC frames ({exc})", file=sys.stderr)
            return 2
        print(f"SYNC producers, period {args.period_s * 1e3:g} ms; |dT-T| between SYNCs one counter step apart, "
              f"kernel receive timestamps; load {load_average()}")
        print(f"{'producer':<10}{'SYNCs':>7}{'rate Hz':>9}{'|dT-T| p50 us':>15}{'p99 us':>9}{'max us':>9}"
              f"{'unseen':>8}  where")
        print(f"{'kernel':<10}{r['syncs_seen']:>7}{r['rate_hz']:>9.1f}{r['p50_us']:>15.0f}{r['p99_us']:>9.0f}"
              f"{r['max_us']:>9.0f}{r['unseen']:>8}  broadcast manager alone on vcan0 ({args.where or args.candump_log})",
              flush=True)
        if not args.producers:
            return 0
    bus = str(parse_bus(args.bus))
    producers = args.producers or (["kernel"] if bus.startswith("socketcan:") else []) + ["thread", "loop"]
    proc = subprocess.Popen([sys.executable, "-m", "gearbench", "emulate", "--can", bus],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        if proc.stdout.readline().strip() != "ready":
            raise SystemExit("gearbench emulate did not start")
        stand_in = realtime_stand_in(proc.pid)
        print(f"SYNC producers on {bus}: period {args.period_s * 1e3:g} ms, {args.duration_s:g} s each, "
              f"two drives answering (paced; the master at SCHED_FIFO 10, the emulated drives {stand_in}); "
              f"load {load_average()}")
        print(floor_text(timer_floor(args.period_s), args.period_s))
        print(f"{'producer':<10}{'SYNCs':>7}{'rate Hz':>9}{'|dT-T| p50 us':>15}{'p99 us':>9}{'max us':>9}"
              f"{'samples':>9}{'lost':>7}")
        for producer in producers:
            try:
                r = paced(bus, producer, args.period_s, args.duration_s)
            except BenchFault as exc:   # e.g. an emulator starved at this rate: a result, not a crash
                print(f"{producer:<10}bench fault: {str(exc)[:150]}")
                continue
            print(f"{r['producer']:<10}{r['syncs_seen']:>7}{r['rate_hz']:>9.1f}{r['p50_us']:>15.0f}"
                  f"{r['p99_us']:>9.0f}{r['max_us']:>9.0f}{r['samples']:>9}{r['lost']:>7}")
        if args.lockstep_samples <= 0:
            return 0
        r = lockstep(bus, args.period_s, args.lockstep_samples)
        print(f"lockstep on {bus}: {r['samples']} samples of both drives in {r['wall_s']:.1f} s = "
              f"{r['samples_per_s']:.0f} samples/s, lost {r['lost']}")
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(30)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
