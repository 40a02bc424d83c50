"""``gearbench msa``: a measurement-system study of the tester, from its own runs.

What is studied (the numerics are ``gearbench.analysis.msa``, AIAG MSA 4th ed.):

- **Efficiency** (``eta_incremental`` and ``eta_absolute`` at each operating point) is a
  characteristic of the *unit*: a crossed gauge R&R with parts = serial numbers,
  appraisers = test stations, trials = repeated runs of a serial on a station.
  Tolerance = the profile's efficiency limit (``reducer.efficiency_range``) as the runs
  recorded it; a one-sided or missing limit gives %GRR of total variation only.
- **Kt** belongs to the *station's motor*, not to the unit (it is calibrated before the
  unit is mounted), so a gauge R&R over units would be meaningless. What a line
  engineer needs is a type-1 study per station and motor: Kt's repeatability, and on
  ``--sim`` its bias against the simulated motor's true Kt (t-test), with Cg/Cgk
  against the Kt limit of the profile.

Runs come from station databases (``gearbench.station.database``; one database per station,
its station id is the appraiser) or the central database. On ``--sim``,
``run_sim_study`` first makes them: simulated units with part-to-part variation of
the reducer's efficiency, simulated stations whose motors differ, each run through the
normal run API into its station's database.
"""
from __future__ import annotations

import copy
import sys
import time
from collections import defaultdict
from typing import Callable
from pathlib import Path

import numpy as np
import yaml

from ..analysis.msa import (ALPHA_INTERACTION, anova_gauge_rr, crossed_array, range_gauge_rr,
                           type1_study)
from ..errors import Aborted, GearbenchError
from .query import RunQuery, open_results
from ..sim import PlantParams
from ..profile import load_profile
from ..station.database import connect

COMPLETE = ("passed", "failed")      # a faulted/aborted run measured nothing complete
EFFICIENCY_KEYS = ("eta_incremental", "eta_absolute")
VERDICT_ORDER = {"acceptable": 0, "marginal": 1, "unacceptable": 2}

# --sim: seeded spreads (relative standard deviations unless said). Units differ in what
# makes reducers differ (mesh efficiency, drag); stations in what makes benches differ.
UNIT_SPREAD = {"eta_pp": 1.0, "drag_rel": 0.10}
STATION_SPREAD = {"Kt": 0.02, "J": 0.05, "D": 0.20, "Tc": 0.20}


# ------------------------------------------------------------------ collecting
def select_runs(runs: list[dict], *, profile: str | None = None, repeats: int | None = None,
                source: str = "database") -> tuple[list[dict], list[dict]]:
    """(runs used, runs left out) — complete runs of one profile, in time order; with
    ``repeats`` only the first N runs of each (serial, station) cell."""
    runs = sorted(runs, key=lambda r: (r.get("started_utc") or "", r["run_id"]))
    if profile:
        runs = [r for r in runs if r.get("profile") == profile]
    if not runs:
        raise GearbenchError(f"{source}: no runs{' of profile ' + profile if profile else ''}; "
                             f"check --db / --profile (gearbench history lists what is there)")
    profiles = sorted({r.get("profile") or "" for r in runs})
    if len(profiles) > 1:
        raise GearbenchError(f"{source}: runs of several profiles ({', '.join(profiles)}); choose one "
                             f"with --profile NAME")
    used, left = [], []
    per_cell: dict[tuple, int] = defaultdict(int)
    for r in runs:
        if r.get("status") not in COMPLETE:
            left.append(dict(run_id=r["run_id"], serial=r["serial"], station=r["station"],
                             why=f"status {r.get('status')}"))
            continue
        cell = (r["serial"], r["station"])
        if repeats is not None and per_cell[cell] >= repeats:
            left.append(dict(run_id=r["run_id"], serial=r["serial"], station=r["station"],
                             why=f"beyond the first {repeats} runs of this serial on this station"))
            continue
        per_cell[cell] += 1
        used.append(r)
    if not used:
        raise GearbenchError(f"{source}: no completed run (all faulted or aborted); nothing to study")
    return used, left


def _tolerance(lim: dict | None) -> tuple[float | None, str]:
    if lim is None:
        return None, "no limit in the profile: %GRR of total variation only"
    low, high = lim.get("low"), lim.get("high")
    if low is None or high is None:
        return None, "one-sided limit: %GRR of total variation only"
    return float(high) - float(low), f"tolerance {low:.6g} .. {high:.6g}"


def _point_label(pt: dict) -> str:
    speed = pt.get("speed_setpoint_rad_s", pt.get("speed_in_rad_s", 0.0))
    return f"{float(speed):.0f} rad/s, {float(pt.get('torque_out_nm', 0.0)):.2g} N m"


def efficiency_series(runs: list[dict]) -> list[dict]:
    """One entry per (operating point, efficiency key): its label, the records
    (serial, station, value) in time order, tolerance, and the runs' simulated truth."""
    n_points = {len(r["result"].get("efficiency") or []) for r in runs}
    if n_points == {0}:
        return []
    if len(n_points) > 1:
        first = runs[0]
        odd = next(r for r in runs if len(r["result"].get("efficiency") or [])
                   != len(first["result"].get("efficiency") or []))
        raise GearbenchError(f"run {odd['run_id']} ({odd['serial']}) measured "
                             f"{len(odd['result'].get('efficiency') or [])} operating points, run "
                             f"{first['run_id']} {len(first['result'].get('efficiency') or [])}; "
                             f"a study compares the same points — select runs of one profile version "
                             f"(--profile, or leave the odd run out with --repeats)")
    first = runs[0]["result"]
    out = []
    for key in EFFICIENCY_KEYS:
        lims = [x for x in first.get("limits") or [] if x.get("quantity") == f"efficiency.{key}"]
        same: dict[tuple, dict] = {}
        for i, pt in enumerate(first["efficiency"]):
            tol, tol_note = _tolerance(lims[i] if i < len(lims) else None)
            records, errors = [], []
            for r in runs:
                res = r["result"]
                v = res["efficiency"][i].get(key)
                records.append((r["serial"], r["station"], v))
                truth = ((res.get("simulation_truth") or {}).get("efficiency") or [])
                if i < len(truth) and truth[i].get(key) is not None and v is not None:
                    errors.append((r["station"], float(v) - float(truth[i][key])))
            values = tuple(v for _, _, v in records)
            if values in same:
                # one estimate reported at several points (e.g. one eq. 18 slope per speed over
                # a torque staircase): one study, not several copies of it
                e = same[values]
                e["points"].append(i)
                e["torques"].append(float(pt.get("torque_out_nm", 0.0)))
                e["label"] = (f"{e['label'].split(',')[0]}, {min(e['torques']):.2g}-"
                              f"{max(e['torques']):.2g} N m")
                continue
            same[values] = dict(quantity=key, point=i, points=[i], label=_point_label(pt),
                                torques=[float(pt.get("torque_out_nm", 0.0))], records=records,
                                tolerance=tol, tolerance_note=tol_note,
                                truth_errors=errors if len(errors) == len(runs) else None)
            out.append(same[values])
    return out


def kt_series(runs: list[dict]) -> list[dict]:
    """One entry per (station, motor): the Kt values of its runs, the true Kt (simulated
    bench, when every run agrees on it) and the tolerance the profile's Kt limit gives."""
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for r in runs:
        for m in sorted((r["result"].get("motors") or {})):
            groups[(r["station"], m)].append(r)
    out = []
    for (station, m), rs in sorted(groups.items()):
        values = [r["result"]["motors"][m].get("Kt") for r in rs]
        truths = {((r["result"].get("simulation_truth") or {}).get("motors") or {}).get(m, {}).get("Kt")
                  for r in rs}
        reference = truths.pop() if len(truths) == 1 else None
        tol, note = _kt_tolerance(rs[0]["result"], m)
        out.append(dict(station=station, motor=m, values=values, reference=reference,
                        tolerance=tol, tolerance_note=note))
    return out


def _kt_tolerance(result: dict, motor: str) -> tuple[float | None, str]:
    for lim in result.get("limits") or []:
        q = lim.get("quantity")
        if q == f"motors.{motor}.Kt":
            return _tolerance(lim)
        if q == f"motors.{motor}.Kt_rel_datasheet" and lim.get("value"):
            tol, note = _tolerance(lim)
            if tol is None:
                return None, note
            datasheet = result["motors"][motor]["Kt"] / lim["value"]   # value = Kt / datasheet Kt
            return tol * datasheet, f"Kt limit {lim['low']:.3g} .. {lim['high']:.3g} × datasheet"
    return None, "no Kt limit in the profile: repeatability only"


def study(runs: list[dict], *, alpha: float = ALPHA_INTERACTION, source: str = "runs") -> dict:
    """The whole study of selected runs: crossed gauge R&R per efficiency quantity, type-1
    per station motor. A JSON-ready dict (``format_table`` prints it)."""
    parts = list(dict.fromkeys(r["serial"] for r in runs))
    stations = list(dict.fromkeys(r["station"] for r in runs))
    crossed = []
    for s in efficiency_series(runs):
        what = f"{s['quantity']} @ {s['label']}"
        try:
            x, _, _ = crossed_array(s["records"], what=f"{source}: {what}")
        except GearbenchError as exc:
            if "unbalanced" not in str(exc):
                raise
            raise GearbenchError(f"{exc} (or study the first N runs of each with --repeats N)") from None
        g = anova_gauge_rr(x, tolerance=s["tolerance"], alpha=alpha, what=what)
        rng = range_gauge_rr(x, tolerance=s["tolerance"], what=what)
        entry = dict(quantity=s["quantity"], point=s["point"], points=s["points"], label=s["label"], unit="1",
                     tolerance_note=s["tolerance_note"], anova=g.as_dict(),
                     range_check=rng.as_dict() if rng else None)
        if s["truth_errors"]:
            e = np.asarray([err for _, err in s["truth_errors"]])
            by_station = {st: float(np.mean([err for st2, err in s["truth_errors"] if st2 == st]))
                          for st in dict.fromkeys(st for st, _ in s["truth_errors"])}
            entry["bias_vs_truth"] = dict(mean=float(e.mean()), max_abs=float(np.abs(e).max()), n=len(e),
                                          by_station=by_station)
        crossed.append(entry)
    kt = []
    for s in kt_series(runs):
        t = type1_study(s["values"], reference=s["reference"], tolerance=s["tolerance"],
                        what=f"{source}: Kt of motor {s['motor']} at {s['station']}")
        kt.append(dict(station=s["station"], motor=s["motor"], unit="N m/A",
                       tolerance_note=s["tolerance_note"], type1=t.as_dict()))
    if not crossed and not kt:
        raise GearbenchError(f"{source}: the runs hold neither efficiency points nor Kt; nothing to study")
    trials = sorted({n for n in _cell_counts(runs).values()})
    # the verdict is on what releases parts: quantities the profile limits (all, if none is)
    limited = [c for c in crossed if c["anova"]["tolerance"] is not None] or crossed
    verdicts = [c["anova"]["verdict"] for c in limited]
    others = [c for c in crossed if c not in limited]
    return dict(standard="AIAG MSA 4th ed. (ANOVA method; average-and-range cross-check); "
                         "Kt: type-1 study (bias t-test, Cg/Cgk, VDA 5)",
                profile=runs[0].get("profile"), parts=parts, stations=stations,
                trials=trials[0] if len(trials) == 1 else trials, runs_used=len(runs),
                alpha_interaction=alpha, efficiency=crossed, kt=kt,
                verdict=max(verdicts, key=VERDICT_ORDER.get) if verdicts else None,
                verdict_on=sorted({c["quantity"] for c in limited}),
                not_in_verdict={v: sum(c["anova"]["verdict"] == v for c in others)
                                for v in VERDICT_ORDER if others})


def _cell_counts(runs):
    c: dict[tuple, int] = defaultdict(int)
    for r in runs:
        c[(r["serial"], r["station"])] += 1
    return c


def read_databases(targets: list[str]) -> list[dict]:
    """Runs (with their result) from station SQLite files or a central postgresql:// URL."""
    runs, seen = [], {}
    for t in targets:
        with open_results(t) as db:
            station = getattr(db, "station", None)     # a station database's own id
            if station is not None and station in seen:
                raise GearbenchError(f"{seen[station]} and {t} both belong to station '{station}'; "
                                     f"give each station's database once")
            seen[station] = t
            runs += db.runs(RunQuery(newest_first=False), with_result=True)
    return runs


# -------------------------------------------------------------------- printing
def format_table(rep: dict) -> str:
    stations = rep["stations"]
    lines = [f"gauge R&R — profile {rep['profile']}: {len(rep['parts'])} unit(s) × {len(stations)} "
             f"station(s) × {rep['trials']} trial(s), {rep['runs_used']} runs",
             f"{rep['standard']}",
             "efficiency in percentage points (pp); EV repeatability, AV reproducibility (between "
             "stations), GRR, PV part variation, TV total — standard deviations; %GRR of TV; "
             "%P/T = 6·GRR/tolerance"]
    if rep["efficiency"]:
        hdr = (f"{'quantity':<17}{'point':<22}{'EV':>8}{'AV':>8}{'GRR':>8}{'PV':>8}{'TV':>8}"
               f"{'%GRR':>7}{'%P/T':>7}{'ndc':>5}  {'verdict':<13}{'range %GRR':>10}")
        has_truth = any("bias_vs_truth" in c for c in rep["efficiency"])
        if has_truth:
            hdr += "  bias vs truth, pp: by station"
        lines += ["", hdr]
        for c in rep["efficiency"]:
            a = c["anova"]
            pt = f"{a['pct_tolerance']:.2f}" if a["pct_tolerance"] is not None else "—"
            ndc = str(a["ndc"]) if a["ndc"] is not None else "inf"
            rc = f"{c['range_check']['pct_grr']:.1f}" if c.get("range_check") else "—"
            row = (f"{c['quantity']:<17}{c['label']:<22}" +
                   "".join(f"{100 * a[k]:>8.4f}" for k in ("ev", "av", "grr", "pv", "tv")) +
                   f"{a['pct_grr']:>7.1f}{pt:>7}{ndc:>5}  {a['verdict']:<13}{rc:>10}")
            if has_truth:
                b = c.get("bias_vs_truth")
                row += ("  " + " ".join(f"{100 * v:+.3f}" for v in b["by_station"].values())) if b else "  —"
            lines.append(row)
        notes = sorted({n for c in rep["efficiency"] for n in c["anova"]["notes"]
                        if not n.startswith("part×station interaction")})
        pooled = sum(bool(c["anova"].get("interaction_pooled")) for c in rep["efficiency"])
        if len(stations) > 1:
                lines.append(f"part×station interaction: pooled into repeatability in {pooled} of "
                         f"{len(rep['efficiency'])} (not significant at α = {rep['alpha_interaction']}), "
                         f"kept in GRR in the rest")
        lines += notes
        tol_notes = sorted({f"{c['quantity']}: {c['tolerance_note']}" for c in rep["efficiency"]})
        lines += tol_notes
        lines.append("verdict (AIAG): %GRR and %P/T < 10 % acceptable, 10-30 % marginal, > 30 % "
                     "unacceptable; ndc >= 5")
    if rep["kt"]:
        lines += ["", "Kt belongs to the station's motor, not to the unit: a type-1 study per station "
                      "motor (repeatability; bias vs true Kt where known; Cg/Cgk vs the Kt limit)",
                  f"{'station':<18}{'motor':<6}{'n':>4}{'mean Kt N m/A':>15}{'s %':>9}{'bias %':>9}"
                  f"{'t-test p':>10}{'Cg':>9}{'Cgk':>9}  verdict"]
        for k in rep["kt"]:
            t = k["type1"]
            bias = f"{100 * t['bias'] / t['reference']:+.4f}" if t["bias"] is not None else "—"
            p = f"{t['bias_p']:.3g}" if t["bias_p"] is not None else "—"
            cg = f"{t['cg']:.1f}" if t["cg"] is not None else "—"
            cgk = f"{t['cgk']:.1f}" if t["cgk"] is not None else "—"
            lines.append(f"{k['station']:<18}{k['motor']:<6}{t['n']:>4}{t['mean']:>15.6f}"
                         f"{100 * t['s'] / abs(t['mean']):>9.4f}{bias:>9}{p:>10}{cg:>9}{cgk:>9}  "
                         f"{t['verdict']}" + ("; bias significant" if t["bias_significant"] else ""))
        if all(k["type1"]["reference"] is None for k in rep["kt"]):
            lines.append("no true Kt on a real bench: bias needs a reference motor of known Kt")
    if rep["verdict"]:
        lines += ["", f"measurement system ({', '.join(rep['verdict_on'])}, the limited "
                      f"quantities): {rep['verdict'].upper()}"]
        if rep["not_in_verdict"]:
            lines.append("not in the verdict (no limit, so no part is released on it): " + ", ".join(
                f"{n} {v}" for v, n in rep["not_in_verdict"].items()))
    return "\n".join(lines)


# ----------------------------------------------------------------- simulation
def _perturbed(sim: dict, *, unit: int, station: int, seed: int,
               unit_spread: dict, station_spread: dict) -> dict:
    """The ``simulation:`` block of one unit on one station: the profile's plant with the
    unit's reducer efficiency and drag and the station's motors drawn from seeded spreads."""
    base = PlantParams.from_dict(sim, "simulation")
    out = copy.deepcopy(sim)
    rs = np.random.default_rng([seed, 1, station])
    motors = out.setdefault("motors", {})
    for name, m in (("in", base.motor_in), ("out", base.motor_out)):
        d = dict(motors.get(name) or {})
        for key, rel in station_spread.items():
            d[key] = float(getattr(m, key) * max(0.05, 1 + rel * rs.standard_normal()))
        motors[name] = d
    ru = np.random.default_rng([seed, 2, unit])
    d_eta = unit_spread["eta_pp"] / 100 * ru.standard_normal()
    if base.cvt is not None:
        cvt = dict(out.get("cvt") or {})
        cvt["eta_max"] = float(min(0.99, base.cvt.eta_max + d_eta))
        out["cvt"] = cvt
    else:
        out["eta_mesh"] = float(min(0.995, max(0.3, base.eta_mesh + d_eta)))
    for key in ("drag_torque_nm", "drag_viscous"):
        out[key] = float(getattr(base, key) * max(0.0, 1 + unit_spread["drag_rel"] * ru.standard_normal()))
    PlantParams.from_dict(out, "simulation")      # still a valid plant
    return out


def check_design(units: int, repeats: int, stations: int) -> None:
    for name, v, least in (("--units", units, 2), ("--repeats", repeats, 2), ("--stations", stations, 1)):
        if not isinstance(v, int) or v < least:
            raise GearbenchError(f"{name} {v}: need at least {least} (AIAG: 10 units, 2-3 stations, "
                                 f"2-3 trials)")


def run_sim_study(profile_path, run_profile: Callable, *, units: int, repeats: int, stations: int,
                  out_dir, seed: int = 1, unit_spread: dict | None = None, station_spread: dict | None = None,
                  progress=None) -> list[str]:
    """Run ``units × stations × repeats`` simulated runs through the normal run API; returns
    the station databases (``out_dir/station-<s>/station.sqlite``) they landed in.

    Order as MSA4 asks for a study: every station measures every unit once, then the
    next trial. Each run has its own emulator noise seed. ``run_profile`` is
    ``gearbench.api.run_profile`` with an operator bound (the fleet does not run benches
    itself: it is handed the station's runner)."""
    check_design(units, repeats, stations)
    progress = progress or sys.stderr      # looked up now: a default bound at import goes stale
    profile = load_profile(profile_path)
    if not profile.simulation:
        raise GearbenchError(f"{profile.path}: --sim needs a 'simulation:' section describing the plant; "
                             f"add one (see profiles/cvt.yaml)")
    doc = yaml.safe_load(Path(profile.path).read_text(encoding="utf-8-sig"))
    for m, spec in profile.motors.items():      # the derived profiles live elsewhere
        doc["motors"][m]["drive"] = str(spec.drive)
    out = Path(out_dir)
    plants = out / "plants"
    plants.mkdir(parents=True, exist_ok=True)
    dbs = []
    for s in range(1, stations + 1):
        db = out / f"station-{s}" / "station.sqlite"
        con = connect(db)
        with con:
            con.execute("INSERT OR REPLACE INTO meta VALUES ('station', ?)", (f"sim-station-{s}",))
        con.close()
        dbs.append(db)
    total = units * repeats * stations
    k, t0, failed = 0, time.monotonic(), []
    for r in range(1, repeats + 1):
        for s in range(1, stations + 1):
            for u in range(1, units + 1):
                k += 1
                d = copy.deepcopy(doc)
                d["simulation"] = _perturbed(doc["simulation"], unit=u, station=s, seed=seed,
                                             unit_spread=unit_spread or UNIT_SPREAD,
                                             station_spread=station_spread or STATION_SPREAD)
                path = plants / f"unit{u:02d}-station{s}.yaml"
                if not path.exists():
                    path.write_text(yaml.safe_dump(d, sort_keys=False))
                noise = int(np.random.default_rng([seed, 3, u, s, r]).integers(1, 2**31 - 1))
                serial = f"MSA-U{u:02d}"
                run_out = out / f"station-{s}" / f"{serial}-trial{r}"
                w0 = time.monotonic()
                for attempt in (1, 2):
                    try:
                        res = run_profile(path, sim=True, out_dir=run_out, serial=serial, db=dbs[s - 1],
                                          seed=noise, quiet=True)
                        break
                    except Aborted:
                        raise
                    except GearbenchError as exc:   # e.g. the emulated bench did not start on a busy host
                        res = dict(status="fault", reason=str(exc))
                        print(f"msa [{k}/{total}] station {s} {serial} trial {r}: {exc}"
                              + ("; retrying once" if attempt == 1 else ""), file=progress, flush=True)
                        run_out = run_out.with_name(run_out.name + "-retry")
                wall = time.monotonic() - w0
                if res["status"] not in COMPLETE:
                    failed.append(f"{serial} station {s} trial {r}: {res['status']} ({res.get('reason')})")
                left = (time.monotonic() - t0) / k * (total - k)
                print(f"msa [{k}/{total}] station {s} {serial} trial {r}: {res['status']}, "
                      f"{res.get('bench_time_s', 0):.1f} s bench, {wall:.1f} s wall; about "
                      f"{left / 60:.0f} min left", file=progress, flush=True)
    if failed:
        print("msa: runs that did not complete (the study will name the missing cells): "
              + "; ".join(failed), file=progress)
    return [str(d) for d in dbs]

