"""Benchmark: the main job on a busy PC — does a good unit pass, with nothing lost?

``python -m gearbench.benchmarks busy_host [--profile profiles/cvt.yaml] [--runs 3] [--hog 2]``

Runs ``gearbench run PROFILE --sim`` (the Quick start's job, as a separate process)
``--runs`` times while ``--hog`` processes spin at normal priority (2 keeps both cores
of a 2-core tester busy). Prints per run: status, exit code, lost samples, wall time,
and what supervision saw (host and emulator stalls tolerated, SDO probes, verdicts
deferred while the emulated drives waited for a CPU). A run that faults on a busy
host with healthy drives is a failure of the tester, not of the unit.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .drives_can import _spin


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m gearbench.benchmarks busy_host", description=__doc__.splitlines()[0])
    p.add_argument("--profile", default="profiles/cvt.yaml")
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--hog", type=int, default=2, help="spinning processes (2 = both cores of a 2-core PC)")
    args = p.parse_args(argv)
    hogs = [multiprocessing.Process(target=_spin, daemon=True) for _ in range(args.hog)]
    for h in hogs:
        h.start()
    print(f"{args.profile} --sim, {args.runs} runs, {args.hog} CPU hog(s) at normal priority")
    print(f"{'run':>4}{'status':>9}{'exit':>6}{'samples':>9}{'lost':>6}{'wall s':>8}{'stalls':>8}"
          f"{'max s':>7}{'emu max s':>10}{'probes':>8}{'deferred':>9}  priority")
    bad = 0
    try:
        with tempfile.TemporaryDirectory() as tmp:
            for k in range(args.runs):
                out = Path(tmp) / f"run{k}"
                t0 = time.monotonic()
                rc = subprocess.run([sys.executable, "-m", "gearbench", "run", args.profile, "--sim", "--yes",
                                     "--quiet", "--out", str(out), "--serial", f"BUSY-{k}"],
                                    capture_output=True, text=True).returncode
                wall = time.monotonic() - t0
                try:
                    r = json.loads((out / "result.json").read_text())
                except (OSError, ValueError):
                    print(f"{k:>4}  no result.json (exit {rc})")
                    bad += 1
                    continue
                s = r.get("supervision", {})
                bad += r["status"] != "passed" or r.get("lost_samples", 0) != 0
                print(f"{k:>4}{r['status']:>9}{rc:>6}{r.get('samples', 0):>9}{r.get('lost_samples', 0):>6}"
                      f"{wall:>8.1f}{s.get('host_stalls', 0):>8}{s.get('host_stall_max_s', 0):>7.2f}"
                      f"{s.get('emulator_stall_max_s', 0):>10.2f}{s.get('sdo_probes', 0):>8}"
                      f"{s.get('starved_deferrals', 0):>9}  {s.get('acquisition_priority', '')}")
                if r["status"] != "passed":
                    print(f"      reason: {r.get('reason', '')[:300]}")
    finally:
        for h in hogs:
            h.kill()
    print(f"{args.runs - bad} of {args.runs} runs passed with 0 lost samples")
    return 1 if bad else 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
