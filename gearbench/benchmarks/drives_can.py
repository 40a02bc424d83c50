"""Benchmark: two CiA 402 drives sampled on SYNC from the emulated bench.

``python -m gearbench.benchmarks drives_can [--duration-s 60] [--period-s 0.001] [--bus udp_multicast virtual]
[--paced] [--hog N] [--threads]``

A run is ``duration_s / period_s`` SYNCs of drive time (60,000 at 1 kHz for 60 s).
Lockstep (default): SYNCs go out as fast as the drives answer, so the figure is the
sustained sample rate; ``--paced`` sends them on the wall clock at ``period_s``, as a
real tester does. udp_multicast runs the emulator in another process (``gearbench
emulate``); virtual runs it in this one.

The master is measured, not the drives' stand-in: paced, the emulator's threads run at
real-time priority above the master's (SCHED_FIFO 20 against 10) where the OS grants
it, as drive hardware answers whatever the PC does, and its own counters (SYNCs heard,
SYNCs it never heard, answers later than one period) are printed, and the lost samples
are split into the master's (SYNC slots its producer skipped, answers in time it did not
take) and the stand-in's (SYNCs sent but never heard, answers later than a period). CPU is measured per
thread from Linux's schedstat (time on a CPU, which a busy host does not inflate) and
given per SYNC period: the master's whole process (receive, decode, supervision, SYNC
production) and the stand-in's. Paced, the SYNC interval jitter is taken by an
independent listener in its own process (bus receive timestamps, |dT - T| p50 / p99 /
max). ``--hog N`` starts N ``python3 -c "while 1: pass"`` at normal priority during
each run (a busy tester PC: N = 2 loads both cores). The host's load average is
printed with every run: the host is shared. Paced, the host's own floor is measured first
(``_cpu.timer_floor``): how often a real-time process that only sleeps to 1 ms deadlines
wakes more than half a period late, i.e. the SYNC slots no user-space producer could
keep on this host.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

from ..drives.base import AxisConfig, Mode
from ..drives.buses import BusSpec, free_udp_port, open_bus
from ..drives.cia402 import CiA402Network
from ..drives.realtime import acquisition_priority
from ..emulate.launch import _child_setup
from ..errors import BenchFault
from . import _cpu
from ._cpu import floor_text, load_average, realtime_stand_in, timer_floor

HOG = [sys.executable, "-c", "while 1: pass"]


def listen(bus: str, path: str) -> None:
    """Independent SYNC listener (run in its own process, own bus connection): bus receive
    timestamps of every SYNC, saved to ``path`` when stdin closes."""
    b = open_bus(bus, can_filters=[{"can_id": 0x80, "can_mask": 0x7FF}])
    stamps, stop = [], threading.Event()

    def run():
        while not stop.is_set():
            msg = b.recv(0.1)
            if msg is not None and msg.arbitration_id == 0x80:
                stamps.append(msg.timestamp)
    t = threading.Thread(target=run, daemon=True)
    t.start()
    print("ready", flush=True)
    sys.stdin.read()
    stop.set()
    t.join(2)
    b.shutdown()
    np.save(path, np.array(stamps))


def _start_listener(bus: str, path: str) -> subprocess.Popen:
    code = f"from gearbench.benchmarks.drives_can import listen; listen({bus!r}, {path!r})"
    proc = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    if proc.stdout.readline().strip() != "ready":
        raise RuntimeError("SYNC listener did not start")
    return proc


def _status(proc: subprocess.Popen) -> dict:
    proc.stdin.write(json.dumps({"cmd": "status"}) + "\n")
    proc.stdin.flush()
    return json.loads(proc.stdout.readline())


def run_once(interface: str, duration_s: float, period_s: float, paced: bool, hog: int = 0) -> dict:
    proc = server = None
    stand_in = "in-process"
    if interface == "udp_multicast":
        bus = BusSpec("udp_multicast", "239.74.163.2", free_udp_port())
        proc = subprocess.Popen([sys.executable, "-m", "gearbench", "emulate", "--can", str(bus)],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                preexec_fn=_child_setup)   # as --sim starts it: the drives' stand-in
        if proc.stdout.readline().strip() != "ready":
            raise RuntimeError("gearbench emulate did not start")
        stand_in = f"emulator, {realtime_stand_in(proc.pid) if paced else 'nice -10'}"
    else:
        from ..emulate.bench import EmulatedBench
        from ..emulate.canopen_server import start_canopen_server
        bus = BusSpec("virtual", f"bench-{time.monotonic_ns()}")
        server = start_canopen_server(EmulatedBench(), "virtual", bus.channel)
    n = round(duration_s / period_s)
    hogs: list[subprocess.Popen] = []
    listener = None
    stamps_path = os.path.join(tempfile.mkdtemp(prefix="gearbench-sync-"), "stamps.npy")
    counters0 = counters1 = {}
    try:
        if paced and interface != "virtual":
            listener = _start_listener(str(bus), stamps_path)
        with CiA402Network(bus=str(bus), lockstep=not paced) as net:
            din = net.add_drive(AxisConfig("in", 1, ""))
            dout = net.add_drive(AxisConfig("out", 2, ""))
            if proc is not None and not paced:   # paced, the stand-in runs above the master: never starved
                net.watch_process(proc.pid)
            net.start(period_s)
            din.enable(Mode.VELOCITY)
            dout.enable(Mode.TORQUE)
            din.set_setpoint(100.0)
            dout.set_setpoint(0.1)
            hogs = [subprocess.Popen(HOG) for _ in range(hog)]
            load0 = load_average()
            with acquisition_priority(net.acquisition_threads(), realtime=paced) as granted:
                net.sample()                       # the producer's thread started (paced), first answer in
                if proc is not None:
                    counters0 = _status(proc)["counters"]
                got, lost0, skipped0 = 1, net.lost_samples, net.late_syncs
                us0 = _cpu.user_system()
                cpu0, emu0, t0 = _cpu.threads(), _cpu.threads(proc.pid) if proc else {}, time.perf_counter()
                while got + net.lost_samples - lost0 < n + 1:
                    net.sample()
                    got += 1
                wall = time.perf_counter() - t0
                cpu1, emu1 = _cpu.threads(), _cpu.threads(proc.pid) if proc else {}
                us1 = _cpu.user_system()
                if proc is not None:
                    counters1 = _status(proc)["counters"]
            load1 = load_average()
            lost = net.lost_samples - lost0
            skipped = net.late_syncs - skipped0
            sup = net.supervision()
            producer = getattr(net.sync_producer, "kind", "loop" if paced else "lockstep")
    finally:
        for h in hogs:
            h.kill()
            h.wait()
        if listener is not None:
            listener.stdin.close()
            listener.wait(30)
        if server is not None:
            server.stop()
        if proc is not None:
            proc.send_signal(signal.SIGTERM)
            proc.wait(10)
    stamps = np.load(stamps_path) if os.path.exists(stamps_path) else np.array([])
    dev_us = np.abs(np.diff(stamps) - period_s) * 1e6 if len(stamps) > 2 else np.array([np.nan])
    master = _cpu.delta(cpu0, cpu1)
    emulator = sum(_cpu.delta(emu0, emu1).values()) if proc is not None else None
    syncs = got - 1 + lost
    heard = {k: counters1.get(k, 0) - counters0.get(k, 0) for k in ("syncs_heard", "syncs_missed", "late_answers")}
    # who lost what: SYNC slots the producer skipped (the master's: its thread was not run in
    # time), SYNCs sent that the stand-in never heard or answered later than a period (not
    # the master's), and the rest (the master's: answers in time that it did not take)
    stand_in_lost = max(0, heard["syncs_missed"] - skipped) + heard["late_answers"] if proc is not None else 0
    return {"bus": interface, "syncs": syncs, "samples": got - 1, "lost": lost, "wall_s": wall,
            "skipped": skipped, "stand_in_lost": stand_in_lost,
            "master_lost": max(0, lost - skipped - stand_in_lost) + skipped,
            "samples_per_s": (got - 1) / wall, "producer": producer,
            "master_cpu_us": sum(master.values()) / syncs * 1e6,
            "master_user_us": (us1[0] - us0[0]) / syncs * 1e6, "master_system_us": (us1[1] - us0[1]) / syncs * 1e6,
            "master_threads_us":
                {k: v / syncs * 1e6 for k, v in sorted(master.items(), key=lambda kv: -kv[1])},
            "stand_in_cpu_us": None if emulator is None else emulator / syncs * 1e6,
            "stand_in": stand_in, "stand_in_counters": heard if proc is not None else None,
            "answer_delay_max_ms": counters1.get("answer_delay_max_s", float("nan")) * 1e3,
            "jitter_us": [np.percentile(dev_us, 50), np.percentile(dev_us, 99), np.max(dev_us)],
            "priority": granted, "host_stall_max_s": sup.get("host_stall_max_s", 0.0),
            "faults": "", "load": f"{load0} -> {load1}"}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m gearbench.benchmarks drives_can", description=__doc__.splitlines()[0])
    p.add_argument("--duration-s", type=float, default=60.0, help="drive time per bus (s)")
    p.add_argument("--period-s", type=float, default=1e-3, help="SYNC period (s)")
    p.add_argument("--bus", nargs="+", default=["udp_multicast", "virtual"], choices=["udp_multicast", "virtual"])
    p.add_argument("--paced", action="store_true", help="send SYNC on the wall clock instead of lockstep")
    p.add_argument("--hog", type=int, default=0, help="processes spinning during each run (2 = both cores busy)")
    p.add_argument("--threads", action="store_true", help="also print the master's CPU per thread")
    args = p.parse_args(argv)
    print(f"two CiA 402 drives, SYNC period {args.period_s * 1e3:g} ms, {args.duration_s:g} s of drive time, "
          f"{'paced' if args.paced else 'lockstep'}, {args.hog} CPU hog(s); CPU in us per SYNC period")
    if args.paced:
        print(f"load {load_average()}; " + floor_text(timer_floor(args.period_s), args.period_s))
    print(f"{'bus':<14}{'SYNCs':>8}{'lost':>6}{'master/stand-in':>16}{'samples/s':>10}{'master CPU':>11}{'stand-in CPU':>13}"
          f"{'SYNC |dT-T| p50/p99/max us':>28}  stand-in: heard/missed/late, max delay   producer, priority,"
          f" load 1/5/15 min before -> after")
    for interface in args.bus:
        try:
            r = run_once(interface, args.duration_s, args.period_s, args.paced, args.hog)
        except BenchFault as exc:
            print(f"{interface:<14}bench fault: {exc} (load {load_average()})")
            continue
        emu = "in-process" if r["stand_in_cpu_us"] is None else f"{r['stand_in_cpu_us']:.0f}"
        jit = "/".join(f"{v:.0f}" for v in r["jitter_us"]) if args.paced and interface != "virtual" else "-"
        c = r["stand_in_counters"]
        own = "-" if c is None else (f"{c['syncs_heard']}/{c['syncs_missed']}/{c['late_answers']}, "
                                     f"{r['answer_delay_max_ms']:.2f} ms")
        who = f"{r['master_lost']}/{r['stand_in_lost']}" if r["stand_in_counters"] is not None else "-"
        print(f"{r['bus']:<14}{r['syncs']:>8}{r['lost']:>6}{who:>16}{r['samples_per_s']:>10.0f}{r['master_cpu_us']:>11.0f}"
              f"{emu:>13}{jit:>28}  {r['stand_in']}: {own}   {r['producer']}, {r['priority']}, {r['load']}")
        if args.threads:
            print("    master by thread (us/SYNC): " + ", ".join(f"{k} {v:.0f}" for k, v in r["master_threads_us"].items())
                  + f"; user {r['master_user_us']:.0f} / kernel {r['master_system_us']:.0f}"
                  + f"; SYNC slots skipped by the producer: {r['skipped']}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
