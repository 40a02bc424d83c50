"""Scorecard of the sim-to-real diagnoser on injected effects (issues 6 and 13).

    python -m gearbench.benchmarks diagnose_scorecard [--quick | --full] [--cases LIST]
        [--sections single,composite,units,bench,emps] [--seeds N] [--json FILE]

Default (a few minutes of CPU): every effect once at moderate amplitude under a
reversing multisine, clean controls, the composite cases, a units subset, the
reducer-bench effects and the real EMPS traces (../shared/datasets/real-emps).  ``--quick``: a smaller subset of each section.  ``--full``:
every amplitude and excitation (long).  ``--cases``: only these cases (effect names,
``clean``, composites as ``a+b``).  Prints false alarms, detection and isolation per
effect, testability judged from the trace vs the truth, composite recall and order of
size, units consistency and the bench effects.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter, defaultdict

import numpy as np

NAME = "diagnose_scorecard"
HELP = "diagnoser scorecard: false alarms, detection/isolation per effect, composites, units, bench"

SECTIONS = ("single", "composite", "units", "bench", "emps", "run")
#: --quick: effects kept in the single and composite sections.
QUICK_EFFECTS = ("coulomb_friction", "current_offset", "time_delay", "cogging",
                 "shaft_compliance", "direction_friction")


def _abbrev(name):
    return "none" if name is None else "".join(w[:3] for w in name.split("_"))[:7]


def _wanted(args, name: str | None) -> bool:
    if not args.cases:
        return True
    return (name or "clean") in args.cases


def main(argv: list[str] | None = None) -> int:
    from . import _diagnose_cases as harness
    from ..analysis.diagnose.effects import NAMES

    ap = argparse.ArgumentParser(prog="diagnose_scorecard", description=HELP)
    size = ap.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="a small subset of every section")
    size.add_argument("--full", action="store_true",
                      help="every amplitude and excitation, three clean seeds (long)")
    ap.add_argument("--cases", type=lambda v: [c.strip() for c in v.split(",") if c.strip()],
                    help="only these cases: effect names, 'clean', composites as a+b")
    ap.add_argument("--sections", type=lambda v: [c.strip() for c in v.split(",")],
                    default=list(SECTIONS), help=f"comma list of {', '.join(SECTIONS)}")
    ap.add_argument("--seeds", type=int, default=1, help="seeds per injected case")
    ap.add_argument("--json", help="write per-case results to this file")
    ap.add_argument("--run-dir", action="append", default=[],
                    help="section 'run': a 'gearbench run ... --sim' output folder whose every "
                         "step is diagnosed (self-consistency; repeatable)")
    ap.add_argument("--broadband", action="store_true",
                    help="with --full: add the broadband (chirp to 80 Hz) excitation")
    args = ap.parse_args(argv)
    bad = [s for s in args.sections if s not in SECTIONS]
    if bad:
        ap.error(f"unknown section(s) {', '.join(bad)}; choose from {', '.join(SECTIONS)}")
    report: dict = {}
    t0 = time.perf_counter()
    if "single" in args.sections:
        report["single"] = _single(args, harness, NAMES)
    if "composite" in args.sections:
        report["composite"] = _composite(args, harness)
    if "units" in args.sections:
        report["units"] = _units(args, harness)
    if "bench" in args.sections:
        report["bench"] = _bench(args)
    if "emps" in args.sections:
        report["emps"] = _emps(args)
    if "run" in args.sections:
        report["run"] = _runs(args)
    print(f"\nScorecard done in {time.perf_counter() - t0:.0f} s")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(report, fh, indent=1, default=str)
    return 0


def _composite(args, harness) -> list[dict]:
    """Two and three effects injected together: is each named in the chain, in the
    order of the gap each opens alone, and does the remainder reach the floor?"""
    from ..analysis.diagnose.chain import nominal_gap

    seeds = tuple(range(args.seeds))
    rows = []
    t0 = time.perf_counter()
    comps = [c for c in harness.COMPOSITES if _wanted(args, "+".join(c))]
    if args.quick and not args.cases:
        comps = comps[:2]
    for effects in comps:
        for seed in seeds:
            case = harness.composite_case(effects, seed=seed)
            out = harness.run_case(case)
            solo = {e: nominal_gap(harness.blind_trace(harness.composite_case((e,), seed=seed))[0])
                    for e in effects}
            truth_order = sorted(effects, key=lambda e: -solo[e])
            # the diagnosis's order of size: what removing each effect from the final
            # model reopens (drop-one, held-out) — not the order of addition
            size = {c["effect"]: c["size_rank"] for c in out.diagnosis.chain}
            found = sorted((e for e in out.chain if e in effects), key=lambda e: size[e])
            rem = out.diagnosis.remaining
            rows.append({"effects": list(effects), "seed": seed, "chain": out.chain,
                         "found": {e: e in out.chain for e in effects},
                         "shrink": [round(c["shrink_heldout"], 3) for c in out.diagnosis.chain],
                         "cumulative": [round(c["cumulative_shrink"], 3) for c in out.diagnosis.chain],
                         "order_ok": found == [e for e in truth_order if e in found],
                         "size_rank": size, "truth_order": truth_order,
                         "dropped": [d["effect"] for d in out.diagnosis.dropped],
                         "solo_gap_rad_s": solo, "extra": [e for e in out.chain if e not in effects],
                         "remaining_gap_ratio": rem.get("gap_ratio"),
                         "at_floor": rem.get("at_noise_floor"),
                         "unknown_effect": rem.get("unknown_effect")})
            print(f"\r{len(rows)} composite cases", end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    n_eff = sum(len(r["effects"]) for r in rows)
    hit = sum(sum(r["found"].values()) for r in rows)
    print(f"\nComposite cases (moderate levels, reversing multisine) — {len(rows)} cases, "
          f"{time.perf_counter() - t0:.0f} s")
    print(f"{'injected':48s}{'chain (held-out shrink per step) [size rank]':52s}{'order':>6s}{'left':>7s}  dropped")
    for r in rows:
        ch = ", ".join(f"{_abbrev(e)} {s:.0%} [{r['size_rank'][e]}]"
                       for e, s in zip(r["chain"], r["shrink"]))
        print(f"{'+'.join(r['effects']):48s}{ch:52s}{('ok' if r['order_ok'] else 'NO'):>6s}"
              f"{r['remaining_gap_ratio']:6.2f}x" + (" floor" if r["at_floor"] else
                                                       " unknown" if r["unknown_effect"] else " ")
              + "  " + (",".join(map(_abbrev, r["dropped"])) or "-"))
    print(f"Composite recall: {hit}/{n_eff} injected effects named in the chain "
          f"({hit / max(n_eff, 1):.0%}); all named in {sum(all(r['found'].values()) for r in rows)}"
          f"/{len(rows)} cases; order of size right in {sum(r['order_ok'] for r in rows)}/{len(rows)}; "
          f"extra effects named: {sum(len(r['extra']) for r in rows)} "
          f"({', '.join(e for r in rows for e in r['extra']) or 'none'}); remainder at the noise "
          f"floor in {sum(bool(r['at_floor']) for r in rows)}/{len(rows)}, within 1.5x in "
          f"{sum((r['remaining_gap_ratio'] or 9) <= 1.5 for r in rows)}/{len(rows)}")
    return rows


#: Cases re-run in other position units (the same physics): clean, one effect, composite.
UNIT_CASES = ((None, "reversing"), (("coulomb_friction",), "reversing"),
              (("cogging",), "sweep_slow"), (("time_delay",), "multisine"),
              (("coulomb_friction", "current_offset"), "reversing"))


def _units(args, harness) -> list[dict]:
    """The same traces in rad, deg and m: same chain and shrink (or the same refusal)."""
    from ..errors import GearbenchError

    rows = []
    t0 = time.perf_counter()
    todo = [(e, x) for e, x in UNIT_CASES if _wanted(args, "+".join(e or ()) or None)]
    if not args.full and not args.cases:   # one friction and one angle-order case
        todo = todo[1:3]
    for effects, ex in todo:
        res = {}
        for unit in harness.UNITS:
            case = (harness.composite_case(effects, ex, 0, unit) if effects else
                    harness.Case(None, "-", ex, 0, {}, unit))
            try:
                out = harness.run_case(case)
                res[unit] = {"chain": out.chain, "verdict": out.called,
                             "shrink": [round(c["shrink_heldout"], 3) for c in out.diagnosis.chain],
                             "params": [c.get("params_final", c["params"]) for c in out.diagnosis.chain]}
            except GearbenchError as exc:
                res[unit] = {"refused": str(exc)}
        same = all(r.get("chain") == res["rad"].get("chain") and
                   ("refused" in r) == ("refused" in res["rad"]) for r in res.values())
        close = same and all(np.allclose(r.get("shrink", []), res["rad"].get("shrink", []), atol=0.05)
                             for r in res.values())
        rows.append({"effects": list(effects or ()), "excitation": ex, "by_unit": res,
                     "same_chain": same, "same_shrink": close})
    print(f"\nUnits consistency (rad / deg / m with a 2.5 mm lead, of the same trace; unit "
          f"stated) — {time.perf_counter() - t0:.0f} s")
    for r in rows:
        name = "+".join(r["effects"]) or "clean"
        print(f"{name:40s}" + "  ".join(f"{u}: {', '.join(map(_abbrev, v.get('chain', []))) or ('refused' if 'refused' in v else 'none')}"
                                         for u, v in r["by_unit"].items())
              + f"   same chain {'yes' if r['same_chain'] else 'NO'}, shrink within 0.05 "
                f"{'yes' if r['same_shrink'] else 'NO'}")
    print(f"Units consistency: {sum(r['same_chain'] for r in rows)}/{len(rows)} same chain, "
          f"{sum(r['same_shrink'] for r in rows)}/{len(rows)} same shrink")
    return rows


#: Real data (../shared/datasets/real-emps): file -> (position unit, travel per motor rev).
EMPS_FILES = {"emps_train_motor_rad.csv": ("rad", None),
              "emps_pulses_motor_rad.csv": ("rad", None),
              "emps_train_m.csv": ("m", 0.0025)}
#: The same traces decimated to 100 Hz (every 10th sample), as a slower drive logs them.
EMPS_100HZ = ("emps_train_motor_rad.csv", "emps_pulses_motor_rad.csv")


def _decimate(tr, k: int):
    from ..trace import Trace

    return Trace(tr.time_s[::k], {n: np.asarray(tr[n])[::k] for n in tr.names}, {},
                 f"{tr.source} (every {k}th sample)")


def _non_physical(d) -> list[str]:
    """Every non-physical number in a reported nominal or chain (issue 24)."""
    bad = []
    p = d.nominal["params"]
    if not p["kt_over_j"] > 0:
        bad.append(f"Kt/J {p['kt_over_j']:.3g}")
    if p.get("d_over_j", 0.0) < 0:
        bad.append(f"D/J {p['d_over_j']:.3g}")
    if p.get("c_over_j", 0.0) < 0:
        bad.append(f"C/J {p['c_over_j']:.3g}")
    for c in d.chain:
        q = c.get("params_final") or c["params"]
        for k in ("Tc_a", "Ts_a", "Tp_a"):
            if k in q and q[k] <= 0:
                bad.append(f"{c['effect']} {k} {q[k]:.3g}")
        if q.get("not_physical"):
            bad.append(f"{c['effect']}: {q['not_physical']}")
    return bad


def _emps(args) -> list[dict]:
    """The EMPS benchmark's real traces (nobody here recorded them): chain, remainder
    against the noise floor and where it lies."""
    from ..analysis.diagnose import diagnose
    from ..trace import Trace
    from ._data import SHARED_DIR

    rows = []
    t0 = time.perf_counter()
    folder = SHARED_DIR / "datasets" / "real-emps"
    jobs = [(name, unit, lead, 1) for name, (unit, lead) in EMPS_FILES.items()]
    jobs += [(name, "rad", None, 10) for name in EMPS_100HZ]
    for name, unit, lead, k in jobs:
        if not _wanted(args, name):
            continue
        f = folder / name
        if not f.exists():
            print(f"{name}: not present ({folder}); skipped")
            continue
        tr = Trace.read(f) if k == 1 else _decimate(Trace.read(f), k)
        c0 = time.process_time()
        d = diagnose(tr, position_unit=unit, travel_per_rev=lead)
        cpu = time.process_time() - c0
        rem = d.remaining
        rows.append({"file": name + ("" if k == 1 else " @100 Hz"), "cpu_s": cpu,
                     "samples": len(tr), "non_physical": _non_physical(d),
                     "unknown_effect": rem["unknown_effect"],
                     "gap_ratio_nominal": d.nominal["fit"]["gap_ratio"],
                     "chain": [c["effect"] for c in d.chain],
                     "cumulative": [round(c["cumulative_shrink"], 3) for c in d.chain],
                     "params": [c.get("params_final", c["params"]) for c in d.chain],
                     "remaining_gap_ratio": rem["gap_ratio"],
                     "where": [(w["dimension"], w["label"], round(w["ratio"], 1))
                               for w in rem["where"][:5]]})
    print(f"\nReal data: EMPS (1 kHz, force command and encoder) — "
          f"{time.perf_counter() - t0:.0f} s")
    for r in rows:
        print(f"{r['file']:36s} {r['samples']:6d} samples {r['cpu_s']:6.1f} CPU-s  nominal "
              f"{r['gap_ratio_nominal']:.0f}x floor -> "
              + ", ".join(f"{_abbrev(e)} {c:.0%}" for e, c in zip(r["chain"], r["cumulative"]))
              + f" -> left {r['remaining_gap_ratio']:.1f}x floor"
              + (" UNKNOWN EFFECT" if r["unknown_effect"] else "")
              + f"; non-physical: {', '.join(r['non_physical']) or 'none'}; worst: "
              + "; ".join(f"{d} {lab} {x}x" for d, lab, x in r["where"][:3]))
    return rows


def _runs(args) -> list[dict]:
    """Self-consistency: every step of a simulated run diagnosed against the run's own
    models (issue 24: each should end within 1.5x its noise floor)."""
    import json as _json
    from pathlib import Path

    from ..analysis.diagnose.runs import diagnose_run
    from ..station.recorder import load_step_trace

    out = []
    if not args.run_dir:
        print("\nSelf-consistency: no --run-dir given (make one with 'gearbench run "
              "profiles/cvt.yaml --sim --yes --out DIR'); skipped")
        return out
    for folder in map(Path, args.run_dir):
        steps = {q.stem[len("trace-"):]: load_step_trace(q)
                 for q in sorted(folder.glob("trace-*.parquet"))}
        c0 = time.process_time()
        run = diagnose_run(steps, _json.loads((folder / "result.json").read_text()))
        cpu = time.process_time() - c0
        print(f"\nSelf-consistency: {folder} — {len(run['steps'])} traces, {cpu:.1f} CPU-s")
        for e in run["steps"]:
            print(f"  {e['step']:28s} {e['motor']:8s} nominal {e['gap_ratio_nominal']:7.2f}x -> "
                  + (",".join(_abbrev(c["effect"]) for c in e["chain"]) or "-")
                  + f" -> {e['gap_ratio_after']:.2f}x"
                  + (" ok" if e["gap_ratio_after"] <= 1.5 else " ABOVE 1.5x")
                  + (" UNKNOWN EFFECT" if e["unknown_effect"] else ""))
        n_ok = sum(e["gap_ratio_after"] <= 1.5 for e in run["steps"])
        print(f"  within 1.5x the floor: {n_ok}/{len(run['steps'])}")
        out.append({"run_dir": str(folder), "cpu_s": cpu,
                    "steps": [{k: v for k, v in e.items() if k != "diagnosis"}
                              for e in run["steps"]]})
    return out


def _bench(args) -> list[dict]:
    """Reducer effects injected into the simulated bench, diagnosed blind."""
    from ..analysis.diagnose.reducer import diagnose_bench
    from ._diagnose_cases import BENCH_INJECTIONS, bench_case_trace

    rows = []
    t0 = time.perf_counter()
    effs = [e for e in (None, *BENCH_INJECTIONS) if _wanted(args, e)]
    from ..analysis.diagnose.reducer import calibration
    from ..sim import MotorParams

    m = MotorParams(cog_amp=0.0)       # the bench cases' motors: their calibration
    cal = calibration({"Kt": m.Kt, "J": m.J, "D": m.D, "Tc": m.Tc})
    for seed in range(max(args.seeds, 2) if args.full else args.seeds):
        for eff in effs:
            for c in (None, cal):
                d = diagnose_bench(bench_case_trace(eff, seed), motor_in=c, motor_out=c)
                rows.append({"effect": eff, "seed": seed, "calibrated": c is not None,
                             "chain": [x["effect"] for x in d.chain],
                             "shrink": [round(x["shrink_heldout"], 3) for x in d.chain],
                             "left": {r: round(v["gap_ratio"], 2) for r, v in d.remaining.items()},
                             "flag": any(v["unknown_effect"] for v in d.remaining.values()),
                             "physical": d.nominal["physical"]})
    print(f"\nReducer bench effects (simulated bench, blind) — {len(rows)} cases, "
          f"{time.perf_counter() - t0:.0f} s")
    for r in rows:
        print(f"  {(r['effect'] or 'clean'):22s} seed {r['seed']} "
              f"{'calibrated' if r['calibrated'] else 'raw (A)   '}: chain "
              f"{','.join(r['chain']) or '-'}; left kin {r['left']['kinematics']}x, torque "
              f"{r['left']['torque']}x{'  UNKNOWN EFFECT' if r['flag'] else ''}; "
              + ("physical" if r["physical"]["ok"] else
                 "NOT PHYSICAL: " + "; ".join(r["physical"]["problems"])))
    for eff in effs:
        rs = [r for r in rows if r["effect"] == eff and not r["calibrated"]]
        first = sum(bool(r["chain"]) and r["chain"][0] == eff for r in rs)
        named = sum(eff in r["chain"] for r in rs) if eff else sum(not r["chain"] for r in rs)
        sh = [s for r in rs for e, s in zip(r["chain"], r["shrink"]) if e == eff]
        print(f"{(eff or 'clean'):24s}" + (f"named first {first}/{len(rs)}, in chain {named}/{len(rs)}, "
                                            f"shrink {np.median(sh) if sh else float('nan'):.2f}"
                                            if eff else f"empty chain {named}/{len(rs)}")
              + "   chains: " + "; ".join(",".join(r["chain"]) or "-" for r in rs))
    return rows


def _single(args, harness, NAMES) -> list[dict]:
    """Single injected effects (over 100 lines: a linear sequence of the section's
    printed tables, each reading the same rows; no branch worth a function)."""

    seeds = tuple(range(args.seeds))
    if args.full:
        ex = harness.EXCITATIONS + ((harness.BROADBAND,) if args.broadband else ())
        cs = harness.cases(excitations=ex, seeds=seeds,
                           clean_seeds=tuple(range(max(3, 3 * args.seeds))))
    else:
        # each effect once at moderate amplitude under the reversing multisine (it has
        # reversals, speed and current variation); clean controls under both multisines
        cs = harness.cases(levels=("moderate",), excitations=("reversing",), seeds=seeds,
                           clean_seeds=())
        cs += [harness.Case(None, "-", ex, s, {}) for ex in ("reversing", "multisine")
               for s in seeds]
        # item 4 of issue 13: shafts under an ordinary (<= 6 Hz) multisine, every level —
        # the testability rule checked against the truth
        cs += [harness.Case("shaft_compliance", lev, "multisine", s,
                            harness.INJECTIONS["shaft_compliance"][li])
               for li, lev in enumerate(harness.LEVELS) for s in seeds]
        if args.quick:
            cs = [c for c in cs if c.effect in (None, *QUICK_EFFECTS)]
    cs = [c for c in cs if _wanted(args, c.effect)]
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
          "listed as confusable; direction/position friction ride on an injected Coulomb "
          "friction: isolated = verdict Coulomb with the variation next in the chain)")
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

    # the testability rules checked against the truth: does the injected effect's own
    # structure, fitted on the trace, close a significant part of the gap on held-out
    # data (t, dBIC and shrink, before the testability gate)?  "untestable but shows"
    # means a rule hides a real effect; "testable, does not show" is allowed (too small)
    from ..analysis.diagnose import verdict as vd

    print("\nTestability vs truth (shows = the true effect's fit closes >= 10 % of the gap on "
          "held-out data, t > 2, dBIC < -10)")
    print(f"{'effect':22s}{'test+shows':>12s}{'test+not':>10s}{'UNTEST+shows':>14s}{'untest+not':>12s}")
    wrong = 0
    for eff in NAMES:
        tally = Counter()
        for o in outs:
            if o.case.effect != eff:
                continue
            c = next((c for c in o.diagnosis.candidates if c.effect == eff), None)
            shows = bool(c is not None and c.t_stat > vd.T_CRIT and c.delta_bic < -vd.BIC_STRONG
                         and c.shrink >= 0.1)
            tally[(bool(o.testable), shows)] += 1
        if tally:
            wrong += tally[(False, True)]
            print(f"{eff:22s}{tally[(True, True)]:>12d}{tally[(True, False)]:>10d}"
                  f"{tally[(False, True)]:>14d}{tally[(False, False)]:>12d}")
    print(f"Cases where a testability rule hid an effect that shows: {wrong}")

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
    # the chain on single-effect traces: the injected effect named, anything more?
    inj = [o for o in outs if o.case.effect]
    named = sum(o.in_chain for o in inj)
    extra = [o for o in inj if len(o.chain) > 1]
    floor = sum(bool(o.diagnosis.remaining.get("at_noise_floor")) for o in inj if o.in_chain)
    chain_fa = [o for o in clean if o.chain]
    print(f"Chain on single-effect cases: injected effect named in {named}/{len(inj)}; "
          f"more than one effect named in {len(extra)}/{len(inj)}; remainder at the floor in "
          f"{floor}/{named} where named; clean controls with a non-empty chain: "
          f"{len(chain_fa)}/{len(clean)}")
    print("Chains per case: " + "; ".join(
        f"{o.case.effect or 'clean'}/{o.case.excitation[:4]} -> {','.join(map(_abbrev, o.chain)) or '-'}"
        for o in outs))
    return [{"effect": o.case.effect, "level": o.case.level,
             "excitation": o.case.excitation, "seed": o.case.seed,
             "called": o.called, "confused_with": o.diagnosis.verdict.confused_with,
             "chain": o.chain, "remaining": {k: v for k, v in o.diagnosis.remaining.items()
                                             if k != "where"},
             "true_shrink": o.true_shrink, "testable": o.testable} for o in outs]


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
