"""Scorecard of the sim-to-real diagnoser on injected effects (issue 6).

    python -m gearbench.bench diagnose_scorecard [--quick] [--seeds N] [--broadband] [--json FILE]
    python -m gearbench.bench.diagnose_scorecard ...

Prints the confusion matrix (true effect x verdict), the detection rate against
amplitude, the false-alarm rate on clean controls, the shrink of the true effect, and
detection over the cases the diagnoser judged testable (from the trace alone) vs all.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter, defaultdict

import numpy as np

NAME = "diagnose_scorecard"
HELP = "diagnoser scorecard: confusion matrix, detection vs amplitude, false alarms, shrink"


def _abbrev(name):
    return "none" if name is None else "".join(w[:3] for w in name.split("_"))[:7]


def main(argv: list[str] | None = None) -> int:
    from ..analysis.diagnose import harness
    from ..analysis.diagnose.effects import NAMES

    ap = argparse.ArgumentParser(prog="diagnose_scorecard", description=HELP)
    ap.add_argument("--quick", action="store_true", help="moderate amplitude, one excitation")
    ap.add_argument("--seeds", type=int, default=1, help="seeds per injected case")
    ap.add_argument("--json", help="write per-case results to this file")
    ap.add_argument("--broadband", action="store_true",
                    help="add the broadband (chirp to 80 Hz) excitation to the case set")
    args = ap.parse_args(argv)

    seeds = tuple(range(args.seeds))
    if args.quick:
        cs = harness.cases(levels=("moderate",), excitations=("multisine", "reversing"),
                           seeds=seeds, clean_seeds=(0, 1))
    else:
        ex = harness.EXCITATIONS + ((harness.BROADBAND,) if args.broadband else ())
        cs = harness.cases(excitations=ex, seeds=seeds,
                           clean_seeds=tuple(range(max(3, 3 * args.seeds))))
    t0 = time.perf_counter()
    outs = []
    for k, c in enumerate(cs):
        outs.append(harness.run_case(c))
        print(f"\r{k + 1}/{len(cs)} cases", end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    elapsed = time.perf_counter() - t0

    rows = [None, *NAMES]
    cols = [None, *NAMES]
    conf = defaultdict(Counter)
    for o in outs:
        conf[o.case.effect][o.called] += 1
    print(f"Confusion matrix (rows: injected, columns: verdict) — {len(outs)} cases, "
          f"{elapsed:.1f} s")
    print(f"{'':22s}" + "".join(f"{_abbrev(c):>8s}" for c in cols))
    for r in rows:
        if r not in conf:
            continue
        print(f"{(r or 'clean'):22s}" + "".join(f"{conf[r][c] or '.':>8}" for c in cols))

    print("\nDetection rate vs amplitude (isolated = verdict names it; [+confused] = named or "
          "listed as confusable)")
    by = defaultdict(list)
    for o in outs:
        if o.case.effect:
            by[(o.case.effect, o.case.level)].append(o)
    print(f"{'effect':22s}" + "".join(f"{lev:>18s}" for lev in harness.LEVELS) + f"{'shrink(mod)':>14s}")
    all_shrink = []
    for eff in NAMES:
        cells = []
        for lev in harness.LEVELS:
            os_ = by.get((eff, lev), [])
            if not os_:
                cells.append(f"{'-':>18s}")
                continue
            iso = sum(o.isolated for o in os_)
            det = sum(o.detected for o in os_)
            cells.append(f"{iso}/{len(os_)} [+{det}/{len(os_)}]".rjust(18))
        mod = [o.true_shrink for o in by.get((eff, "moderate"), []) + by.get((eff, "high"), [])
               if o.isolated and o.true_shrink is not None]
        all_shrink += mod
        sh = f"{np.median(mod):.2f}" if mod else "-"
        print(f"{eff:22s}" + "".join(cells) + f"{sh:>14s}")

    print("\nTestable on the trace (judged from the trace alone) — detection over testable "
          "cases vs over all cases (detected = isolated or listed as confusable)")
    print(f"{'effect':22s}{'testable':>10s}{'iso|test':>10s}{'det|test':>10s}{'det|all':>10s}"
          f"{'det|untest':>12s}")
    tot = Counter()
    for eff in NAMES:
        os_ = [o for o in outs if o.case.effect == eff]
        if not os_:
            continue
        te = [o for o in os_ if o.testable]
        un = [o for o in os_ if not o.testable]
        row = (len(te), sum(o.isolated for o in te), sum(o.detected for o in te),
               sum(o.detected for o in os_), sum(o.detected for o in un))
        tot.update(dict(zip(("te", "iso", "det", "all", "un"), row)))
        tot["n"] += len(os_)
        print(f"{eff:22s}{row[0]:>6d}/{len(os_):<3d}{row[1]:>7d}/{row[0]:<2d}{row[2]:>7d}/{row[0]:<2d}"
              f"{row[3]:>7d}/{len(os_):<2d}{row[4]:>9d}/{len(un):<2d}")
    if tot["n"]:
        print(f"{'all':22s}{tot['te']:>6d}/{tot['n']:<3d}  detection {tot['det'] / max(tot['te'], 1):.0%} "
              f"of testable cases vs {tot['all'] / tot['n']:.0%} of all; isolation "
              f"{tot['iso'] / max(tot['te'], 1):.0%} of testable")

    clean = [o for o in outs if o.case.effect is None]
    fa = [o for o in clean if o.called is not None]
    print(f"\nFalse alarms on clean controls: {len(fa)}/{len(clean)}"
          + (" (" + ", ".join(f"{o.called} on {o.case.excitation}" for o in fa) + ")" if fa else ""))
    if all_shrink:
        print(f"Shrink of the true effect (isolated, moderate+high): median "
              f"{np.median(all_shrink):.2f}, min {np.min(all_shrink):.2f}, "
              f">= 0.8 in {np.mean(np.array(all_shrink) >= 0.8):.0%}")
    per_ex = defaultdict(list)
    for o in outs:
        if o.case.effect and o.case.level != "low":
            per_ex[o.case.excitation].append(o.isolated)
    print("Isolation (moderate+high) by excitation: "
          + ", ".join(f"{k} {np.mean(v):.0%}" for k, v in per_ex.items()))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump([{"effect": o.case.effect, "level": o.case.level,
                        "excitation": o.case.excitation, "seed": o.case.seed,
                        "called": o.called, "confused_with": o.diagnosis.verdict.confused_with,
                        "true_shrink": o.true_shrink, "testable": o.testable} for o in outs],
                      fh, indent=1)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
