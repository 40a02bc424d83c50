"""Benchmark: Modbus TCP sampling of two emulated drives, server in another process.

Reports samples/s per drive (goal >= 500/s on loopback), request latency
percentiles (one multi-register read of one drive's sample block) and CPU use, for
  - lockstep: each sample = sync write + read of drive 1 (one 0x17 request) + read
    of drive 2; throughput is what the link and both ends allow;
  - free-running: the emulator runs the bench at 1 kHz real time; the master
    takes the next sample every ``--period-s`` (default 2 ms: the rated 500 samples/s
    per drive over Modbus TCP) at real-time priority, gaps are counted as lost samples.
    The emulator (the drives' stand-in) runs at real-time priority above the master
    (SCHED_FIFO 20 against 10) and reports its own pacing: world periods it could not
    keep (overruns) and the furthest it fell behind the wall clock.

CPU is measured from Linux's schedstat (time on a CPU, not inflated by a busy host) as
microseconds per sample of both drives; ``--hog N`` runs N ``python3 -c "while 1: pass"``
meanwhile; the host's load average is printed with each figure.

    python -m gearbench.benchmarks.drives_modbus [--seconds 10] [--period-s 0.002] [--hog 2]
        [--modes lockstep free] [--map drivers/generic-modbus-servo.yaml]    (--hog 0 2: one run each)
"""
from __future__ import annotations

import argparse
import json
import os
import select
import subprocess
import sys
import time

import numpy as np

from ..drives.base import AxisConfig, Mode
from ..drives.modbus import ModbusNetwork
from ..drives.realtime import acquisition_priority
from . import _cpu
from ._cpu import load_average, normal_priority, realtime_stand_in

HOG = [sys.executable, "-c", "while 1: pass"]

DEFAULT_MAP = "drivers/generic-modbus-servo.yaml"
SERVER = ("import sys, json; from gearbench.emulate.bench import EmulatedBench; "
          "from gearbench.emulate.modbus_server import start_modbus_server; "
          "b = EmulatedBench(); b.advance(); "       # compile the physics before 'ready'
          "h = start_modbus_server(b, '127.0.0.1', 0, register_map={map!r}, lockstep={lockstep}); "
          "print('ready', h.port, flush=True); sys.stdin.read(); "   # port 0: the OS picks, no race
          "print(json.dumps(dict(overruns=h.overruns, lag_max_s=h.lag_max_s, late_periods=h.late_periods, "
          "periods=b.sample_index)), flush=True); "
          "h.stop()")


def _cpu_s(pid: int) -> float:
    """user + system CPU seconds of a process (Linux /proc)."""
    fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _start_server(regmap: str, lockstep: bool) -> tuple[subprocess.Popen, int]:
    proc = subprocess.Popen([sys.executable, "-c", SERVER.format(map=regmap, lockstep=lockstep)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    ready, _, _ = select.select([proc.stdout], [], [], 60)
    words = proc.stdout.readline().split() if ready else []
    if words[:1] != ["ready"]:
        proc.kill()
        raise RuntimeError("emulator process did not start")
    return proc, int(words[1])


def measure(regmap: str, seconds: float, lockstep: bool, period_s: float = 1e-3, hog: int = 0) -> dict:
    """Sample both drives for ``seconds``; returns figures (see module docstring)."""
    proc, port = _start_server(regmap, lockstep)
    stand_in = realtime_stand_in(proc.pid) if not lockstep else "normal"
    hogs: list[subprocess.Popen] = []
    try:
        net = ModbusNetwork(port=port, lockstep=lockstep, timeout_s=2.0)
        with net:
            d_in = net.add_drive(AxisConfig("in", 1, regmap))
            d_out = net.add_drive(AxisConfig("out", 2, regmap))
            net.start(1e-3 if lockstep else period_s)
            d_in.enable(Mode.VELOCITY)
            d_out.enable(Mode.TORQUE)
            d_in.set_setpoint(50.0)
            d_out.set_setpoint(0.1)
            hogs = [subprocess.Popen(HOG, preexec_fn=normal_priority) for _ in range(hog)]
            load0 = load_average()
            with acquisition_priority(realtime=not lockstep) as granted:
                samples = net.sample()
                lost0, first_index = net.lost_samples, samples["in"].index
                cpu0, srv0, t0 = _cpu.threads(), _cpu.threads(proc.pid), time.perf_counter()
                per_sample, n = [], 0
                while (now := time.perf_counter()) - t0 < seconds:
                    samples = net.sample()
                    per_sample.append(time.perf_counter() - now)
                    n += 1
                wall = time.perf_counter() - t0
                cpu1, srv1 = _cpu.threads(), _cpu.threads(proc.pid)
            load1 = load_average()
            cpu, srv = sum(_cpu.delta(cpu0, cpu1).values()), sum(_cpu.delta(srv0, srv1).values())
            lost, span = net.lost_samples - lost0, samples["in"].index - first_index
            # latency of single requests: one read of one drive's sample block
            lat = []
            for _ in range(2000):
                t = time.perf_counter()
                d_out.read_sample()
                lat.append(time.perf_counter() - t)
    finally:
        for h in hogs:
            h.kill()
            h.wait()
        proc.stdin.close()
        line = proc.stdout.readline()
        own = json.loads(line) if line.startswith("{") else {}
        proc.terminate()
        proc.wait(5)
    lat_ms, per_ms = np.array(lat) * 1e3, np.array(per_sample) * 1e3
    return {"mode": "lockstep" if lockstep else "free-running 1 kHz", "samples": n,
            "samples_per_s_per_drive": n / wall, "lost": lost, "lost_fraction": lost / max(span, 1),
            "request_p50_ms": float(np.percentile(lat_ms, 50)), "request_p99_ms": float(np.percentile(lat_ms, 99)),
            "request_max_ms": float(lat_ms.max()),
            "sample_p50_ms": float(np.percentile(per_ms, 50)), "sample_p99_ms": float(np.percentile(per_ms, 99)),
            "client_cpu": cpu / wall, "server_cpu": srv / wall, "client_cpu_us": cpu / n * 1e6,
            "server_cpu_us": srv / n * 1e6, "priority": granted, "stand_in": stand_in, "stand_in_own": own,
            "load": f"{load0} -> {load1}", "period_s": period_s}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="gearbench.benchmarks.drives_modbus", description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="measuring time per mode")
    ap.add_argument("--map", default=DEFAULT_MAP, help="register map of both drives")
    ap.add_argument("--period-s", type=float, default=2e-3, help="free-running sample period (rated: 2 ms)")
    ap.add_argument("--hog", type=int, nargs="+", default=[0],
                    help="processes spinning meanwhile (2 = both cores busy); several values: one run each")
    ap.add_argument("--modes", nargs="+", default=["lockstep", "free"], choices=["lockstep", "free"])
    args = ap.parse_args(argv)
    print(f"Modbus TCP, 2 drives (unit ids 1, 2), loopback, emulator in another process, map {args.map}")
    for mode, hog in ((m, h) for m in args.modes for h in args.hog):
        r = measure(args.map, args.seconds, mode == "lockstep", args.period_s, hog)
        own = r["stand_in_own"]
        label = (r["mode"] if mode == "lockstep" else f"free-running, {1e3 * r['period_s']:g} ms") + f", {hog} hogs"
        print(f"{label:>28}: "
              f"{r['samples_per_s_per_drive']:7.0f} samples/s per drive "
              f"({r['samples']} samples, lost {r['lost']} = {100 * r['lost_fraction']:.2f} %); "
              f"sample (2 drives) p50 {r['sample_p50_ms']:.2f} ms p99 {r['sample_p99_ms']:.2f} ms; "
              f"single read p50 {r['request_p50_ms']:.2f} ms p99 {r['request_p99_ms']:.2f} ms "
              f"max {r['request_max_ms']:.1f} ms; CPU per sample: master {r['client_cpu_us']:.0f} us "
              f"({100 * r['client_cpu']:.0f} %), stand-in {r['server_cpu_us']:.0f} us ({100 * r['server_cpu']:.0f} %)")
        print(f"{'':>30}master {r['priority']}; stand-in {r['stand_in']}, its own pacing: "
              f"{own.get('overruns', '?')} overruns, lag max {1e3 * own.get('lag_max_s', float('nan')):.1f} ms, "
              f"{own.get('late_periods', '?')} of {own.get('periods', '?')} periods stepped over a period late; "
              f"load {r['load']}", flush=True)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
