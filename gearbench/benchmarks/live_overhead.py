"""Benchmark: what the Rerun live view adds to a run's wall time.

Feeds ``--seconds`` of ``--rate-hz`` samples for two drives (4 quantities each)
through ``RerunView`` into an .rrd, in ``SampleBatch``es of ``--batch`` samples
(the sequencer emits ~100-250), and reports the cost per sample instant (both
drives) as wall time spent in the subscriber, and as CPU time of the whole process
(Rerun encodes and writes in a background thread, which competes for the same two
cores). The fraction is given against a real-time 1 kHz run and against the
simulated lockstep run (``--lockstep-hz`` samples per wall second).

    python -m gearbench.benchmarks live_overhead [--seconds 60] [--batch 200]
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from ..reports.live import open_live_view
from ..station.records import RunStart, RunStop, SampleBatch, StepStart, StepStop

QUANTITIES = ("position_rad", "velocity_rad_s", "current_a", "command")


def synthetic_batches(seconds: float, rate_hz: float, batch: int, motors=("in", "out")):
    """SampleBatches of a plausible bench signal (sines + noise), drive time base."""
    n = int(round(seconds * rate_hz))
    rng = np.random.default_rng(0)
    for start in range(0, n, batch):
        sample = np.arange(start, min(start + batch, n), dtype=np.int64)
        t = sample / rate_hz
        cols = {}
        for k, m in enumerate(motors):
            cols[f"{m}.position_rad"] = 50.0 * t + k
            cols[f"{m}.velocity_rad_s"] = 50.0 + np.sin(2 * np.pi * 3 * t) + rng.normal(0, 0.05, t.size)
            cols[f"{m}.current_a"] = 1.0 + 0.3 * np.sin(2 * np.pi * 7 * t) + rng.normal(0, 0.01, t.size)
            cols[f"{m}.command"] = np.full(t.size, 50.0 if k == 0 else 1.0)
        yield SampleBatch("efficiency", sample, t, cols)


def measure(seconds: float, rate_hz: float, batch: int, rrd: Path) -> dict:
    """Wall and CPU seconds spent logging ``seconds`` of bench data to ``rrd``."""
    batches = list(synthetic_batches(seconds, rate_hz, batch))  # generated outside the timing
    n = sum(len(b.sample) for b in batches)
    view = open_live_view(rrd=rrd)
    view(RunStart("bench", "SN-BENCH", "bench", "", "", "", True, ("in", "out"), 1 / rate_hz, ""))
    view(StepStart("efficiency", "efficiency"))
    wall0, cpu0 = time.perf_counter(), time.process_time()
    for b in batches:
        view(b)
    wall_calls = time.perf_counter() - wall0
    view(StepStop("efficiency", "ok", n))
    view(RunStop("passed", 0))
    view.close()  # includes encoding/writing what the background thread still holds
    wall_total = time.perf_counter() - wall0
    cpu_total = time.process_time() - cpu0
    return {"samples": n, "batches": len(batches), "wall_calls_s": wall_calls,
            "wall_total_s": wall_total, "cpu_total_s": cpu_total,
            "rrd_bytes": rrd.stat().st_size}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="gearbench.benchmarks live_overhead", description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="bench time to log (default 60)")
    ap.add_argument("--rate-hz", type=float, default=1000.0, help="drive sample rate (default 1000)")
    ap.add_argument("--batch", type=int, default=200, help="samples per SampleBatch (default 200)")
    ap.add_argument("--lockstep-hz", type=float, default=2000.0,
                    help="samples per wall second of the simulated run (default 2000)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        r = measure(args.seconds, args.rate_hz, args.batch, Path(tmp) / "bench.rrd")
    n = r["samples"]
    us_call = 1e6 * r["wall_calls_s"] / n
    us_wall = 1e6 * r["wall_total_s"] / n
    us_cpu = 1e6 * r["cpu_total_s"] / n
    realtime_s = n / args.rate_hz
    lockstep_s = n / args.lockstep_hz
    print(f"live view overhead: {n} sample instants x 2 drives x 4 quantities, "
          f"{r['batches']} batches of {args.batch}, .rrd {r['rrd_bytes'] / 1e6:.1f} MB")
    print(f"  in subscriber calls : {r['wall_calls_s']:.3f} s wall = {us_call:.2f} us/sample")
    print(f"  incl. final flush   : {r['wall_total_s']:.3f} s wall = {us_wall:.2f} us/sample")
    print(f"  process CPU (all threads): {r['cpu_total_s']:.3f} s = {us_cpu:.2f} us/sample")
    for label, run_s in ((f"real-time {args.rate_hz:g} Hz run", realtime_s),
                         (f"lockstep run at {args.lockstep_hz:g} samples/s", lockstep_s)):
        print(f"  vs {label} ({run_s:.1f} s): wall {100 * r['wall_total_s'] / run_s:.2f} %, "
              f"CPU {100 * r['cpu_total_s'] / run_s:.2f} %  (target < 5 %)")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
