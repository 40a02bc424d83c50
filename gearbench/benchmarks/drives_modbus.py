"""Benchmark: Modbus TCP sampling of two emulated drives, server in another process.

Reports samples/s per drive (goal >= 500/s on loopback), request latency
percentiles (one multi-register read of one drive's sample block) and CPU use, for
  - lockstep: each sample = sync write + read of drive 1 (one 0x17 request) + read
    of drive 2; throughput is what the link and both ends allow;
  - free-running: the emulator runs the bench at 1 kHz real time; the master
    takes the next counter value each time, gaps are counted as lost samples.

    python -m gearbench.benchmarks.drives_modbus [--seconds 10] [--map drivers/generic-modbus-servo.yaml]
"""
from __future__ import annotations

import argparse
import os
import select
import subprocess
import sys
import time

import numpy as np

from ..drives.base import AxisConfig, Mode
from ..drives.modbus import ModbusNetwork

DEFAULT_MAP = "drivers/generic-modbus-servo.yaml"
SERVER = ("import sys; from gearbench.emulate.bench import EmulatedBench; "
          "from gearbench.emulate.modbus_server import start_modbus_server; "
          "b = EmulatedBench(); b.advance(); "       # compile the physics before 'ready'
          "h = start_modbus_server(b, '127.0.0.1', 0, register_map={map!r}, lockstep={lockstep}); "
          "print('ready', h.port, flush=True); sys.stdin.read(); h.stop()")   # port 0: the OS picks, no race


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


def measure(regmap: str, seconds: float, lockstep: bool) -> dict:
    """Sample both drives for ``seconds``; returns figures (see module docstring)."""
    proc, port = _start_server(regmap, lockstep)
    try:
        net = ModbusNetwork(port=port, lockstep=lockstep, timeout_s=2.0)
        with net:
            d_in = net.add_drive(AxisConfig("in", 1, regmap))
            d_out = net.add_drive(AxisConfig("out", 2, regmap))
            net.start(1e-3)
            d_in.enable(Mode.VELOCITY)
            d_out.enable(Mode.TORQUE)
            d_in.set_setpoint(50.0)
            d_out.set_setpoint(0.1)
            cpu0, srv0, t0 = time.process_time(), _cpu_s(proc.pid), time.perf_counter()
            per_sample, n, first_index = [], 0, None
            while (now := time.perf_counter()) - t0 < seconds:
                samples = net.sample()
                per_sample.append(time.perf_counter() - now)
                first_index = samples["in"].index if first_index is None else first_index
                n += 1
            wall = time.perf_counter() - t0
            cpu, srv = time.process_time() - cpu0, _cpu_s(proc.pid) - srv0
            # latency of single requests: one read of one drive's sample block
            lat = []
            for _ in range(2000):
                t = time.perf_counter()
                d_out.read_sample()
                lat.append(time.perf_counter() - t)
            lost, span = net.lost_samples, samples["in"].index - first_index + 1
    finally:
        proc.stdin.close()
        proc.terminate()
        proc.wait(5)
    lat_ms, per_ms = np.array(lat) * 1e3, np.array(per_sample) * 1e3
    return {"mode": "lockstep" if lockstep else "free-running 1 kHz", "samples": n,
            "samples_per_s_per_drive": n / wall, "lost": lost, "lost_fraction": lost / max(span, 1),
            "request_p50_ms": float(np.percentile(lat_ms, 50)), "request_p99_ms": float(np.percentile(lat_ms, 99)),
            "request_max_ms": float(lat_ms.max()),
            "sample_p50_ms": float(np.percentile(per_ms, 50)), "sample_p99_ms": float(np.percentile(per_ms, 99)),
            "client_cpu": cpu / wall, "server_cpu": srv / wall}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="gearbench.benchmarks.drives_modbus", description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="measuring time per mode")
    ap.add_argument("--map", default=DEFAULT_MAP, help="register map of both drives")
    args = ap.parse_args(argv)
    print(f"Modbus TCP, 2 drives (unit ids 1, 2), loopback, emulator in another process, map {args.map}")
    for lockstep in (True, False):
        r = measure(args.map, args.seconds, lockstep)
        print(f"{r['mode']:>20}: {r['samples_per_s_per_drive']:7.0f} samples/s per drive "
              f"({r['samples']} samples, lost {r['lost']} = {100 * r['lost_fraction']:.1f} %); "
              f"sample (2 drives) p50 {r['sample_p50_ms']:.2f} ms p99 {r['sample_p99_ms']:.2f} ms; "
              f"single read p50 {r['request_p50_ms']:.2f} ms p99 {r['request_p99_ms']:.2f} ms "
              f"max {r['request_max_ms']:.1f} ms; CPU client {100 * r['client_cpu']:.0f} % "
              f"server {100 * r['server_cpu']:.0f} %")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
