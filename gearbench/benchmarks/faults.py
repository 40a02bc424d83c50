"""Benchmark: the fault campaign — many short runs on the simulated bench, each with one
fault injected at a random instant, and the invariants a bench fault must keep.

``python -m gearbench.benchmarks faults [--runs-per-fault 3] [--faults drive-silent,sigkill-gearbench ...]
[--jobs 1] [--seed 1] [--work DIR] [--json FILE]``

Each run is ``gearbench run tests/data/faults-{canopen,modbus}.yaml --sim`` as a
subprocess (four 1 s segments). The faults, the invariants and how each is judged:
``gearbench.emulate.faults``. Prints every failed invariant with its evidence, then the
matrix (fault x invariant: ``ok n`` / ``FAIL k/n`` / ``n/a``, runs, failed runs) and
the figures: time from fault to the last axis without torque, samples on disk, lost
samples, heartbeat gaps, the emulator's exit after SIGKILL of gearbench.
``--jobs`` > 1 runs that many at once: more load than a tester PC has (each run is two
busy processes), useful as a stress test, not the campaign's reference.
Exit 0 when every invariant held, 1 otherwise.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict
from pathlib import Path

from ..emulate.faults import FAULTS, matrix, run_fault


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m gearbench.benchmarks faults", description=__doc__.splitlines()[0])
    ap.add_argument("--runs-per-fault", type=int, default=3)
    ap.add_argument("--faults", default=",".join(FAULTS), help="comma-separated, default all: " + ", ".join(FAULTS))
    ap.add_argument("--jobs", type=int, default=1, help="runs at once (default 1)")
    ap.add_argument("--seed", type=int, default=1, help="first seed (instants are random per fault and seed)")
    ap.add_argument("--work", help="folder for the runs (default: a temporary one, removed)")
    ap.add_argument("--json", help="write every outcome to this file")
    args = ap.parse_args(argv)
    names = [n for n in args.faults.split(",") if n]
    unknown = [n for n in names if n not in FAULTS]
    if unknown:
        print(f"unknown fault(s) {unknown}; known: {', '.join(FAULTS)}", file=sys.stderr)
        return 2
    jobs = [(n, args.seed + k) for k in range(args.runs_per_fault) for n in names]
    tmp = None if args.work else tempfile.TemporaryDirectory(prefix="gearbench-faults-")
    work = Path(args.work or tmp.name)
    t0 = time.monotonic()
    outcomes = []

    def one(job):
        o = run_fault(job[0], job[1], work)
        status = "ok" if o.ok else "FAIL " + " | ".join(o.failures())
        print(f"{o.fault:<18} seed {o.seed:<3} at {o.at_s:5.3f} s  exit {o.rc}  {o.figures.get('wall_s')} s  "
              f"{status}{'  (' + o.note.strip() + ')' if o.note else ''}", flush=True)
        return o

    try:
        with ThreadPoolExecutor(max(1, args.jobs)) as ex:
            outcomes = list(ex.map(one, jobs))
    finally:
        if tmp is not None:
            tmp.cleanup()
    print(f"\nfault campaign: {len(outcomes)} runs in {time.monotonic() - t0:.0f} s, jobs {args.jobs}\n")
    print(matrix(outcomes))
    print("\nfigures (per fault: median [max])")
    for n in dict.fromkeys(o.fault for o in outcomes):
        rows = [o for o in outcomes if o.fault == n]
        parts = []
        for key, label in (("stop_s", "fault->no torque s"), ("samples_on_disk", "samples on disk"),
                           ("lost", "lost"), ("gaps", "counter gaps"), ("heartbeat_gaps", "heartbeat gaps"),
                           ("dropped_frames", "dropped frames"), ("emulator_exit_s", "emulator exit s"),
                           ("wall_s", "run s")):
            vals = [o.figures[key] for o in rows if isinstance(o.figures.get(key), (int, float))]
            if vals:
                parts.append(f"{label} {statistics.median(vals):g} [{max(vals):g}]")
        print(f"  {n:<18} " + ", ".join(parts))
    notes = sorted({o.note.strip() for o in outcomes if o.note.strip()})
    for note in notes:
        print(f"note: {note}")
    if args.json:
        Path(args.json).write_text(json.dumps([asdict(o) for o in outcomes], indent=1, default=str))
    return 0 if all(o.ok for o in outcomes) else 1


if __name__ == "__main__":
    sys.exit(main())
