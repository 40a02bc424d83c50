"""gearbench twin RUN_DIR: the bench's digital twin.

1. Replay the run's recorded setpoints (per step, with its mounting and drive modes)
   through the profile's simulated bench (``gearbench.sim``, the plant ``--sim`` runs
   against) and print the gap per step and signal in noise floors, and where it lies.
2. Fit the simulation's parameters to the run (with 95 % intervals), then add the
   effects it lacks one at a time by held-out gain (``gearbench.twin.fit``).
3. The proof: re-simulate the recorded steps on the fitted twin, analyse them with the
   run's own analysis and print the real run's results beside the twin's, and the
   traces' remaining gap before/after. ``--write twin.yaml`` writes the fitted
   ``simulation:`` block (``gearbench run PROFILE --sim --twin twin.yaml`` runs on it).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import yaml

from ..twin.proof import PROOF_DRAWS, limit_pairs, proof_rows, summary
from ..twin.run import drive_quanta, load_run

NAME = "twin"
HELP = "fit the simulated bench to a recorded run: replay, gap, fitted parameters, missing effects, proof"


def add_arguments(p) -> None:
    p.add_argument("run_dir", help="a run folder of gearbench run (result.json, trace-*.parquet)")
    p.add_argument("--profile", help="profile whose simulation: block is the starting twin "
                                     "(default: the run's own profile.yaml)")
    p.add_argument("--write", metavar="YAML", help="write the fitted simulation: block to this file")
    p.add_argument("--no-fit", action="store_true", help="replay and gap only")
    p.add_argument("--iterations", type=int, default=12, help="Levenberg-Marquardt iterations (default 12)")
    p.add_argument("--max-effects", type=int, default=3, help="effects added at most (default 3)")
    p.add_argument("--no-proof", action="store_true", help="skip re-analysing the twin's traces")
    p.add_argument("--json", metavar="FILE", help="also write the whole report as JSON")


def run(args) -> int:
    from ..sim import PlantParams
    from ..twin import fit as F
    from ..twin.gap import gap_table, noise_floors, total_gap
    from ..twin.replay import check_axes, plan_segments, replay

    t0 = time.monotonic()
    result, traces, run_prof, start = load_run(args.run_dir, args.profile)
    check_axes(run_prof)
    segments = plan_segments(traces, run_prof)
    quanta = drive_quanta(run_prof)
    floors = noise_floors(segments)
    block0 = json.loads(json.dumps(start.simulation))
    plant0 = PlantParams.from_dict(block0, "simulation")
    rows0 = replay(plant0, segments, quanta=quanta)
    report = {"run_dir": str(args.run_dir), "profile": str(start.path),
              "floors": {f"{a}.{s}": v for (a, s), v in floors.items()}}
    print(f"gearbench twin: {args.run_dir}: {len(segments)} steps, "
          f"{sum(len(s.trace) for s in segments)} samples, replayed on {start.path}'s simulated bench")
    print("noise floors: " + ", ".join(f"{a}.{s} {v:.3g}" for (a, s), v in floors.items()))
    before = gap_table(rows0, segments, floors)
    report["gap_before"] = before
    _print_gap(before, "gap of the profile's simulation (rms in noise floors; bias = mean)")
    if args.no_fit:
        _dump(args, report)
        return 0

    prob = F.Problem(segments, block0, quanta, floors)
    params = F.base_params(block0)
    start_values = F.written_values(params)
    print(f"\nfitting {len(params)} parameters (Levenberg-Marquardt on position, velocity and current)")
    F.update_events(prob, params, verbose=print)
    res = F.fit(prob, params, iterations=args.iterations, verbose=print)
    # the base fit, before any effect: a parameter that moves by more than its interval once
    # an effect is added had been fitted against that effect (biased while it was missing)
    base_values = F.written_values(params)
    print(f"S/n {res['S0'] / res['n']:.3f} -> {res['S'] / res['n']:.3f} (1 = at the noise floor)")
    print("\nadding the effects the simulation lacks, by held-out gain:")
    chain = F.add_effects(prob, params, max_effects=args.max_effects, verbose=print, last=res)
    report["chain"] = chain
    report["profiles"] = prob.profiles
    report["ambiguities"] = prob.ambiguities
    report["not_identifiable"] = prob.not_identifiable()
    _print_chain(chain)
    for amb in prob.ambiguities:
        print(f"  AMBIGUOUS: {amb}")
    for what in report["not_identifiable"]:
        print(f"  NOT IDENTIFIABLE from this run: {what}")
    fitted = F.with_params(prob.block, params)
    fitted_values = F.written_values(params)
    report["parameters"] = [{"path": p.path, "start": start_values.get(p.path, 0.0), "fitted": fitted_values[p.path],
                             "before_effects": base_values.get(p.path),
                             "interval95": p.interval, "sigma": p.sigma, "model_bias": p.model_bias,
                             "resolution": p.resolution, "interval95_jacobian": p.jacobian_interval,
                             "replay_jitter_sigma": p.jitter,
                             "smoothing_shift_sigma": p.shift_sigma, "stall": p.stall, "basin_reach": p.basin_reach,
                             "effect": p.effect} for p in params]
    _print_params(report["parameters"])
    s_n = chain[-1]["remaining"] if chain else res["S"] / res["n"]
    report["remaining_s_per_n"] = s_n
    if F.model_limited(s_n):
        print(f"  NOTE: {F.model_limited(s_n)}")
    plant1 = PlantParams.from_dict(fitted, "simulation")
    rows1 = replay(plant1, segments, quanta=quanta)
    after = gap_table(rows1, segments, floors)
    report["gap_after"] = after
    report["gap_total"] = {"before": total_gap(rows0, segments, floors), "after": total_gap(rows1, segments, floors)}
    _print_before_after(before, after)
    if args.write:
        _write_block(Path(args.write), fitted, args.run_dir, report)
        print(f"\nwrote {args.write} (a simulation: block; gearbench run PROFILE --sim --twin {args.write})")
    if not args.no_proof:
        report["proof"] = proof(result, segments, plant1, run_prof, quanta)
        _print_proof(report["proof"])
        report["proof"]["misses"] = _verdict(report["proof"], after)
    report["wall_s"] = time.monotonic() - t0
    report["fit_replays"] = prob.evaluations
    print(f"\n{prob.evaluations} replays in the fit; {report['wall_s']:.0f} s wall")
    _dump(args, report)
    return 0


def proof(result: dict, segments, plant, profile, quanta, draws: int = PROOF_DRAWS) -> dict:
    """Re-simulate the recorded steps on the twin (noise on) ``draws`` times, seeds the
    plant's and the next ones, analyse each as the run was analysed, and set the run's
    results (re-analysed with the same code, so only the data differ) beside the twin's
    pooled over the draws (``twin.proof.pool_draws``): one draw against the run compares
    two noise draws (the hidden cvt bench's truth with another seed missed its own run's
    η by 1.5 intervals)."""
    from ..fleet.reanalysis import reanalyse_result
    from ..twin.proof import pool_draws
    from ..twin.replay import replay, simulated_trace

    real_traces = {s.name: s.trace for s in segments}
    real = reanalyse_result(result, lambda n: real_traces[n], profile, result.get("method", "default"))
    summaries = []
    for k in range(draws):
        rows = replay(plant, segments, noise=True, seed=plant.seed + k, quanta=quanta)
        twin_traces = {s.name: simulated_trace(rows[s.name], s, quanta=quanta) for s in segments}
        summaries.append(summary(reanalyse_result(result, lambda n: twin_traces[n], profile,
                                                   result.get("method", "default"))))
    return {"real": summary(real), "twin": pool_draws(summaries), "twin_draws": summaries}


def _print_proof(pr: dict) -> None:
    from ..twin.proof import half_width, understated, verdict_among_draws, within

    real, twin = pr["real"], pr["twin"]
    k = twin.get("draws", 1)
    print(f"\nthe proof: the run's results (re-analysed) beside the twin's (its traces analysed the same "
          f"way; mean and standard deviation over {k} noise draws)")
    print(f"  {'quantity':<40} {'real':>9} {'twin':>9} {'twin sd':>8} {'±95 %':>8}  within")
    notes, rows = [], proof_rows(pr)
    for label, a, ci, b, sd in rows:
        hw = half_width(ci, sd, k)
        print(f"  {label:<40} {_f(a):>9} {_f(b):>9} {_f(sd):>8} {_f(hw):>8}  {within(a, b, ci, sd, k)}")
        if understated(ci, sd):
            notes.append((1.96 * sd / ((ci[1] - ci[0]) / 2), label))
    print(f"  {'ratio':<40} {_f(real['ratio']):>9} {_f(twin['ratio']):>9}")
    for lim, t in limit_pairs(pr):
        same = "same verdict" if verdict_among_draws(lim["passed"], t, k) else "VERDICT DIFFERS"
        print(f"  {'limit ' + lim['name']:<40} {'PASS' if lim['passed'] else 'FAIL':>9} "
              f"{'PASS' if t.get('passed') else 'FAIL':>9}  {same} ({t.get('passed_draws', '?')}/{k} draws pass)")
    print(f"  {'run':<40} {real['status']:>9} {twin['status']:>9}")
    if notes:
        ratio, label = max(notes)
        print(f"  the run's 95 % interval is narrower than 1.96 sd of the analysis over the twin's draws "
              f"for {len(notes)} of {len(rows)} results (most: {label}, {ratio:.2f}x)")


def _verdict(pr: dict, after: list[dict], worst_floors: float = 3.0) -> list[str]:
    """Say whether the twin reproduces the run within the results' intervals, and where not."""
    from ..twin.proof import verdict_among_draws, within

    k = pr["twin"].get("draws", 1)
    misses = [label for label, a, ci, b, sd in proof_rows(pr) if within(a, b, ci, sd, k) == "NO"]
    misses += [f"limit {lim['name']} verdict" for lim, t in limit_pairs(pr)
               if not verdict_among_draws(lim["passed"], t, k)]
    if misses:
        print(f"\nthe twin does NOT reproduce the run within its intervals: {'; '.join(misses)}")
        far = [f"{r['step']} {r['axis']}.{r['signal']} ({r['gap']:.1f})" for r in after
               if r["gap"] > worst_floors and r["signal"] != "position_rad"]
        if far:
            print(f"  where the traces still part (> {worst_floors:g} noise floors): {', '.join(far)}")
    else:
        print("\nthe twin reproduces the run: every Kt and efficiency within the run's 95 % interval "
              "(and its draws' mean's), every limit's verdict among its draws'")
    return misses


def _f(v) -> str:
    return "-" if v is None else f"{v:.5g}"


def _print_gap(rows: list[dict], title: str) -> None:
    print(f"\n{title}:")
    print(f"  {'step':<28} {'signal':<20} {'gap':>8} {'bias':>8}  where (largest)")
    for r in rows:
        w = r["where"]
        worst = []
        if w.get("time"):
            k = int(np.nanargmax(w["time"]))
            worst.append(f"tenth {k + 1} ({w['time'][k]})")
        if w.get("speed"):
            b = max(w["speed"], key=lambda x: x["gap"] if x["gap"] == x["gap"] else -1)
            worst.append(f"{b['from_rad_s']}-{b['to_rad_s']} rad/s ({b['gap']})")
        if w.get("load"):
            b = max(w["load"], key=lambda x: x["gap"] if x["gap"] == x["gap"] else -1)
            worst.append(f"load {b['out_command']:g} A ({b['gap']})")
        if w.get("reversals") is not None:
            worst.append(f"reversals {w['reversals']}")
        ao = w.get("angle_order")
        if ao and ao["amplitude"] > 3 * ao["white_level"]:
            worst.append(f"order {ao['order']} ({ao['amplitude']})")
        print(f"  {r['step']:<28} {r['axis'] + '.' + r['signal']:<20} {r['gap']:8.2f} {r['bias']:8.2f}  "
              + ", ".join(worst))


def _print_chain(chain: list[dict]) -> None:
    print(f"\n  {'effect':<20} {'parameters':<44} {'held-out shrink':>15} {'significant':>11} {'remaining S/n':>13}")
    for c in chain:
        print(f"  {c['effect']:<20} {', '.join(c['parameters']):<44} {c['held_out_shrink']:15.3f} "
              f"{'yes' if c['significant'] else 'no':>11} {c['remaining']:13.3f}")
    if not chain:
        print("  (no candidate effect left to try)")


def _print_params(rows: list[dict]) -> None:
    # the interval is 1.96·sigma (noise, coloured) + |model bias| (smoothed vs exact replay)
    print(f"\n  {'parameter':<30} {'profile':>12} {'fitted':>12} {'95 % interval':>14} {'sigma':>10} {'model bias':>11}"
          f" {'moved by effects':>17}")
    biased = []
    for r in rows:
        b = r.get("before_effects")
        # how far the effects moved it, in its own intervals (> 1: fitted against a missing effect)
        shift = (r["fitted"] - b) / r["interval95"] if b is not None and r["interval95"] > 0 else float("nan")
        if abs(shift) > 1:
            biased.append(f"{r['path']} ({shift:+.1f})")
        print(f"  {r['path']:<30} {r['start']:12.5g} {r['fitted']:12.5g} {'±' + format(r['interval95'], '.3g'):>14} "
              f"{r.get('sigma', float('nan')):10.3g} {r.get('model_bias', float('nan')):+11.3g} "
              f"{'' if shift != shift else format(shift, '+.1f') + ' ivl':>17}")
    print("  interval = 1.96·sigma (largest of white and block-sandwich covariances, with the smoothing "
          "correction's spread over its points in quadrature) + |model bias| "
          "(smoothed vs exact replay, mean over the points); the ratio's + one output encoder count over the output's travel; "
          "backlash, Kt saturation and current lag from the profile of S (printed above the chain)")
    if biased:
        print(f"  fitted against an effect the simulation lacked (moved by more than their interval once "
              f"the effects were added): {', '.join(biased)}")


def _print_before_after(before, after) -> None:
    print("\nremaining gap in noise floors (rms), profile's simulation -> fitted twin:")
    a = {(r["step"], r["axis"], r["signal"]): r["gap"] for r in after}
    for r in before:
        k = (r["step"], r["axis"], r["signal"])
        print(f"  {r['step']:<28} {r['axis'] + '.' + r['signal']:<20} {r['gap']:10.2f} -> {a.get(k, float('nan')):8.2f}")


def _write_block(path: Path, block: dict, run_dir: str, report: dict) -> None:
    head = (f"# Digital twin fitted by `gearbench twin {run_dir}`.\n"
            f"# Use: gearbench run PROFILE --sim --twin {path.name}\n"
            f"# Effects added: {', '.join(c['effect'] for c in report.get('chain', []) if c['significant']) or 'none'}\n"
            + "".join(f"# Not identifiable from that run: {w}\n" for w in report.get("not_identifiable", [])))
    path.write_text(head + yaml.safe_dump({"simulation": _plain(block)}, sort_keys=False))


def _plain(x):
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    return x


def _dump(args, report) -> None:
    if args.json:
        Path(args.json).write_text(json.dumps(_plain(report), indent=1, default=str))


