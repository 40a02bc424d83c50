"""Full profiles on the simulated bench: accuracy against the plant's truth and time.

    python -m gearbench.benchmarks run_profile [--profiles profiles/cvt.yaml ...] [--seeds 0 1 2]

Runs ``gearbench run PROFILE --sim`` (real CANopen/Modbus stack, emulator in a child
process) and prints per run: Kt error per motor (%), incremental and absolute
efficiency error per point (pp; max and mean of |err|), ratio error, bench time,
wall time and samples/s. ``--method paper`` runs the paper's identification on the
same bench for comparison.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

NAME = "run_profile"


def score(res: dict) -> dict:
    truth = res["simulation_truth"]
    kt = {m: 100 * (p["Kt"] / truth["motors"][m]["Kt"] - 1) for m, p in res["motors"].items()}
    inc = [100 * (p["eta_incremental"] - t["eta_incremental"])
           for p, t in zip(res["efficiency"], truth["efficiency"])]
    ab = [100 * (p["eta_absolute"] - t["eta_absolute"])
          for p, t in zip(res["efficiency"], truth["efficiency"])]
    ratio = (100 * (res["ratio"] / truth["ratio"] - 1)) if res.get("ratio") else None
    return dict(kt=kt, inc=np.array(inc), abs=np.array(ab), ratio=ratio)


def main(argv: list[str] | None = None) -> int:
    from ..api import run_profile

    ap = argparse.ArgumentParser(prog="python -m gearbench.benchmarks run_profile", description=__doc__.splitlines()[0])
    ap.add_argument("--profiles", nargs="+", default=["profiles/cvt.yaml", "profiles/cyclo.yaml"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[None])
    ap.add_argument("--methods", nargs="+", default=["default", "paper"])
    args = ap.parse_args(argv)
    print(f"{'profile':<22}{'seed':>5}{'method':>9}{'Kt err % (in, out)':>22}{'|incr| pp max/mean':>20}"
          f"{'|abs| pp max/mean':>19}{'ratio %':>9}{'pts':>5}{'bench s':>9}{'wall s':>8}{'samp/s':>8}  status")
    with tempfile.TemporaryDirectory() as tmp:
        for prof in args.profiles:
            for seed in args.seeds:
                for method in args.methods:
                    out = Path(tmp) / f"{Path(prof).stem}-{seed}-{method}"
                    t0 = time.monotonic()
                    res = run_profile(prof, sim=True, out_dir=out, serial="BENCH", yes=True,
                                      seed=seed, method=method, quiet=True)
                    wall = time.monotonic() - t0
                    s = score(res)
                    kt = ", ".join(f"{v:+.3f}" for v in s["kt"].values())
                    inc = f"{np.abs(s['inc']).max():.3f}/{np.abs(s['inc']).mean():.3f}" if len(s["inc"]) else "-"
                    ab = f"{np.abs(s['abs']).max():.3f}/{np.abs(s['abs']).mean():.3f}" if len(s["abs"]) else "-"
                    ratio = f"{s['ratio']:+.3f}" if s["ratio"] is not None else "-"
                    print(f"{Path(prof).name:<22}{str(seed):>5}{method:>9}{kt:>22}{inc:>20}{ab:>19}{ratio:>9}"
                          f"{len(s['inc']):>5}{res['bench_time_s']:>9.1f}{wall:>8.1f}"
                          f"{res['samples'] / max(res['wall_time_s'], 1e-9):>8.0f}  {res['status']}", flush=True)
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
