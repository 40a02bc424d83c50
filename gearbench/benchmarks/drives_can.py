"""Benchmark: two CiA 402 drives sampled on SYNC from the emulated bench.

``python -m gearbench.benchmarks drives_can [--duration-s 60] [--period-s 0.001] [--bus udp_multicast virtual] [--paced]
[--hog N]``

A run is ``duration_s / period_s`` SYNCs of drive time (60,000 at 1 kHz for 60 s).
Lockstep (default): SYNCs go out as fast as the drives answer, so the figure is the
sustained sample rate; ``--paced`` sends them on the wall clock at ``period_s`` and
shows the CPU a real-time run costs. udp_multicast runs the emulator in another
process (``gearbench emulate``); virtual runs it in this one. Prints samples/s of both
drives, lost samples and CPU (fraction of one core, master and emulator); paced, also
the SYNC interval jitter seen by an independent listener on the bus (|dT - T| p50 /
p99 / max) and the acquisition priority granted. ``--hog N`` keeps N processes
spinning at normal priority during each run (a busy tester PC: N = 2 loads both cores).
"""
from __future__ import annotations

import argparse
import multiprocessing
import resource
import signal
import subprocess
import sys
import time

import numpy as np

from ..drives.base import AxisConfig, Mode
from ..drives.buses import BusSpec, free_udp_port
from ..drives.cia402 import CiA402Network
from ..drives.realtime import acquisition_priority
from ..emulate.launch import _child_setup
from .sync_jitter import SyncListener


def _children_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _spin() -> None:
    while True:
        pass


def run_once(interface: str, duration_s: float, period_s: float, paced: bool, hog: int = 0) -> dict:
    proc = server = None
    if interface == "udp_multicast":
        bus = BusSpec("udp_multicast", "239.74.163.2", free_udp_port())
        proc = subprocess.Popen([sys.executable, "-m", "gearbench", "emulate", "--can", str(bus)],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                preexec_fn=_child_setup)   # as --sim starts it: the drives' stand-in
        if proc.stdout.readline().strip() != "ready":
            raise RuntimeError("gearbench emulate did not start")
    else:
        from ..emulate.bench import EmulatedBench
        from ..emulate.canopen_server import start_canopen_server
        bus = BusSpec("virtual", f"bench-{time.monotonic_ns()}")
        server = start_canopen_server(EmulatedBench(), "virtual", bus.channel)
    n = round(duration_s / period_s)
    hogs = [multiprocessing.Process(target=_spin, daemon=True) for _ in range(hog)]
    stamps = []
    try:
        with CiA402Network(bus=str(bus), lockstep=not paced) as net:
            din = net.add_drive(AxisConfig("in", 1, ""))
            dout = net.add_drive(AxisConfig("out", 2, ""))
            if proc is not None:
                net.watch_process(proc.pid)
            net.start(period_s)
            din.enable(Mode.VELOCITY)
            dout.enable(Mode.TORQUE)
            din.set_setpoint(100.0)
            dout.set_setpoint(0.1)
            for h in hogs:
                h.start()
            listener = SyncListener(str(bus)) if paced and interface != "virtual" else None
            if listener:
                listener.__enter__()
            with acquisition_priority(net.acquisition_threads(), realtime=paced) as granted:
                cpu0, child0, t0 = time.process_time(), _children_cpu_s(), time.perf_counter()
                got = 0
                while got + net.lost_samples < n:
                    net.sample()
                    got += 1
                wall = time.perf_counter() - t0
                master_cpu = time.process_time() - cpu0
            if listener:
                listener.__exit__()
                stamps = listener.stamps
            lost = net.lost_samples
            sup = net.supervision()
    finally:
        for h in hogs:
            h.kill()
        if server is not None:
            server.stop()
        if proc is not None:
            proc.send_signal(signal.SIGTERM)
            proc.wait(10)
    emulator_cpu = (_children_cpu_s() - child0) if proc is not None else None   # after it exited
    dev_us = np.abs(np.diff(stamps) - period_s) * 1e6 if len(stamps) > 2 else np.array([np.nan])
    return {"bus": interface, "syncs": n, "samples": got, "lost": lost, "wall_s": wall,
            "samples_per_s": got / wall, "master_cpu": master_cpu / wall,
            "emulator_cpu": None if emulator_cpu is None else emulator_cpu / wall,
            "jitter_us": [np.percentile(dev_us, 50), np.percentile(dev_us, 99), np.max(dev_us)],
            "priority": granted, "host_stall_max_s": sup.get("host_stall_max_s", 0.0)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m gearbench.benchmarks drives_can", description=__doc__.splitlines()[0])
    p.add_argument("--duration-s", type=float, default=60.0, help="drive time per bus (s)")
    p.add_argument("--period-s", type=float, default=1e-3, help="SYNC period (s)")
    p.add_argument("--bus", nargs="+", default=["udp_multicast", "virtual"], choices=["udp_multicast", "virtual"])
    p.add_argument("--paced", action="store_true", help="send SYNC on the wall clock instead of lockstep")
    p.add_argument("--hog", type=int, default=0, help="processes spinning during each run (2 = both cores busy)")
    args = p.parse_args(argv)
    print(f"two CiA 402 drives, SYNC period {args.period_s * 1e3:g} ms, {args.duration_s:g} s of drive time, "
          f"{'paced' if args.paced else 'lockstep'}, {args.hog} CPU hog(s)")
    print(f"{'bus':<14}{'samples':>9}{'lost':>6}{'wall s':>9}{'samples/s':>11}{'master CPU':>12}{'emulator CPU':>14}"
          f"{'SYNC |dT-T| p50/p99/max us':>28}{'stall max s':>12}  priority")
    for interface in args.bus:
        r = run_once(interface, args.duration_s, args.period_s, args.paced, args.hog)
        emu = "in-process" if r["emulator_cpu"] is None else f"{r['emulator_cpu']:.0%}"
        jit = "/".join(f"{v:.0f}" for v in r["jitter_us"]) if args.paced and interface != "virtual" else "-"
        print(f"{r['bus']:<14}{r['samples']:>9}{r['lost']:>6}{r['wall_s']:>9.2f}{r['samples_per_s']:>11.0f}"
              f"{r['master_cpu']:>12.0%}{emu:>14}{jit:>28}{r['host_stall_max_s']:>12.3f}  {r['priority']}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
