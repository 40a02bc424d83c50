"""``python -m gearbench.benchmarks twin``: does ``gearbench twin`` recover a hidden bench?

For each case (cvt, cyclo): the shipped profile's ``simulation:`` block is changed in
secret (``gearbench.twin.hidden.HIDDEN``: parameters moved by 4-30 %, two effects switched
on that the block does not have), ``gearbench run HIDDEN --sim`` records a run, and
``gearbench twin RUN --profile profiles/<case>.yaml`` — which sees only the run and the
*nominal* profile — fits the twin. Printed: parameter, truth, fitted, 95 % interval,
within; each hidden effect found or not; the run's results beside the twin's (the
command's proof); then the twin predicts a second run of the same hidden bench (another
noise seed): ``run --sim --twin`` beside the hidden run.

Runs are cached (``--cache``, default /tmp/gearbench-twin-bench): a run takes ~20-30 s.

    python -m gearbench.benchmarks twin [--cases cvt,cyclo] [--cache DIR] [--iterations N]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

import yaml

from ..sim import PlantParams
from ..twin.hidden import HIDDEN, get_path, hidden_block

ROOT = Path(__file__).resolve().parents[2]


def _defaults(block: dict):
    d = asdict(PlantParams.from_dict(block))
    d["motors"] = {"in": d.pop("motor_in"), "out": d.pop("motor_out")}
    return lambda path: get_path(d, path)


def make_hidden(case: str, seed: int, cache: Path) -> tuple[Path, dict]:
    doc = yaml.safe_load((ROOT / "profiles" / f"{case}.yaml").read_text())
    block, truth = hidden_block(doc["simulation"], HIDDEN[case], _defaults(doc["simulation"]))
    block["seed"] = seed
    doc["simulation"] = block
    path = cache / f"hidden-{case}-{seed}.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path, truth


def gb(*args, log: Path) -> int:
    with open(log, "w") as f:
        return subprocess.call([sys.executable, "-m", "gearbench", *map(str, args)], stdout=f, stderr=subprocess.STDOUT)


def record(profile: Path, out: Path, *extra) -> Path:
    if not (out / "result.json").is_file():
        gb("run", profile, "--sim", "--yes", "--quiet", "--out", out, *extra, log=out.with_suffix(".log"))
    if not (out / "result.json").is_file():
        raise SystemExit(f"run failed: see {out.with_suffix('.log')}")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m gearbench.benchmarks twin")
    ap.add_argument("--cases", default="cvt,cyclo")
    ap.add_argument("--cache", default="/tmp/gearbench-twin-bench")
    ap.add_argument("--iterations", type=int, default=12)
    ap.add_argument("--max-effects", type=int, default=3)
    ap.add_argument("--dev", default=str(ROOT.parent / "shared" / "datasets" / "dev"),
                    help="the independent simulator's data (skipped when absent)")
    a = ap.parse_args(argv)
    if Path(a.dev).is_dir():
        dev_single_axis(Path(a.dev), iterations=a.iterations)
    cache = Path(a.cache)
    cache.mkdir(parents=True, exist_ok=True)
    ok = True
    for case in [c for c in a.cases.split(",") if c]:
        nominal = ROOT / "profiles" / f"{case}.yaml"
        hidden, truth = make_hidden(case, 7, cache)
        hidden2, _ = make_hidden(case, 21, cache)
        run1 = record(hidden, cache / f"run-{case}-7")
        run2 = record(hidden2, cache / f"run-{case}-21")
        rep_path = cache / f"twin-{case}.json"
        twin_yaml = cache / f"twin-{case}.yaml"
        if not rep_path.is_file():
            rc = gb("twin", run1, "--profile", nominal, "--write", twin_yaml, "--json", rep_path,
                    "--iterations", a.iterations, "--max-effects", a.max_effects, log=cache / f"twin-{case}.log")
            if rc:
                raise SystemExit(f"gearbench twin failed: see {cache / f'twin-{case}.log'}")
        rep = json.loads(rep_path.read_text())
        hidden_block_ = yaml.safe_load(hidden.read_text())["simulation"]
        tv = _defaults(hidden_block_)
        print(f"\n=== {case}: hidden bench (seed 7), twin fitted from {nominal.name} ===")
        print(f"{'parameter':<30} {'truth':>11} {'fitted':>11} {'±95 %':>10} {'within':>7} {'moved':>6}")
        n_in = n_moved_in = n_moved = 0
        for p in rep["parameters"]:
            t = tv(p["path"])
            if t is None:
                continue
            within = abs(p["fitted"] - t) <= p["interval95"]
            moved = p["path"] in truth
            n_in += within
            n_moved += moved
            n_moved_in += moved and within
            print(f"{p['path']:<30} {t:11.5g} {p['fitted']:11.5g} {p['interval95']:10.3g} "
                  f"{'yes' if within else 'NO':>7} {'*' if moved else '':>6}")
        print(f"within their interval: {n_in}/{len(rep['parameters'])} "
              f"(moved parameters: {n_moved_in}/{n_moved})")
        found = {c["effect"] for c in rep.get("chain", []) if c["significant"]}
        for eff, paths in HIDDEN[case]["effects"].items():
            hit = eff in found
            ok &= hit
            print(f"hidden effect {eff:<16} ({', '.join(f'{k}={v}' for k, v in paths.items())}): "
                  f"{'FOUND' if hit else 'not found'}")
        extra = found - set(HIDDEN[case]["effects"])
        if extra:
            print(f"effects added that were not hidden: {', '.join(sorted(extra))}")
        gt = rep.get("gap_total", {})
        print(f"total gap (rms, noise floors): profile {gt.get('before', float('nan')):.2f} -> "
              f"twin {gt.get('after', float('nan')):.2f}")
        if "proof" in rep:
            _results("results: run (re-analysed) vs twin (re-simulated, same analysis)",
                     rep["proof"]["real"], rep["proof"]["twin"])
        # the prediction: a second run of the hidden bench vs a run on the twin
        pred = record(nominal, cache / f"pred-{case}-21", "--twin", twin_yaml, "--seed", 21)
        _results("prediction: second hidden run (seed 21) vs run --sim --twin (seed 21)",
                 _res(run2), _res(pred))
    return 0 if ok else 1


def _res(run: Path) -> dict:
    r = json.loads((run / "result.json").read_text())
    return {"status": r["status"], "ratio": r.get("ratio"),
            "motors": {m: {"Kt": v.get("Kt"), "Kt_ci95": v.get("Kt_ci95")} for m, v in r["motors"].items()},
            "efficiency": [{k: e.get(k) for k in ("speed_in_rad_s", "torque_out_nm", "eta_incremental",
                                                  "eta_incremental_ci95", "eta_absolute", "eta_absolute_ci95")}
                           for e in r.get("efficiency") or []],
            "limits": [{"name": x["name"], "passed": x["passed"]} for x in r.get("limits") or []]}


def _results(title: str, real: dict, twin: dict) -> None:
    print(f"\n{title}")
    print(f"  {'quantity':<34} {'real':>9} {'twin':>9}  within real 95 %")

    def line(label, a, b, ci):
        w = "" if not ci or a is None or b is None else ("yes" if abs(a - b) <= (ci[1] - ci[0]) / 2 else "NO")
        print(f"  {label:<34} {_f(a):>9} {_f(b):>9}  {w}")
    for m, v in real["motors"].items():
        line(f"Kt {m}", v["Kt"], (twin["motors"].get(m) or {}).get("Kt"), v.get("Kt_ci95"))
    line("ratio", real["ratio"], twin["ratio"], None)
    for e, f in zip(real["efficiency"], twin["efficiency"]):
        line(f"eta_inc {e['speed_in_rad_s']:.0f} rad/s {e['torque_out_nm']:.3f} N m", e["eta_incremental"],
             f["eta_incremental"], e.get("eta_incremental_ci95"))
    if len(twin["limits"]) == len(real["limits"]):   # efficiency limits carry the measured torque in their names
        same = sum(a["passed"] == b["passed"] for a, b in zip(real["limits"], twin["limits"]))
    else:
        verdicts = {x["name"]: x["passed"] for x in twin["limits"]}
        same = sum(verdicts.get(x["name"]) == x["passed"] for x in real["limits"])
    print(f"  limits with the same verdict: {same}/{len(real['limits'])}; run {real['status']} vs twin {twin['status']}")


def _f(v) -> str:
    return "-" if v is None else f"{v:.5g}"


if __name__ == "__main__":
    sys.exit(main())


# ----------------------------------------------------------------- the independent simulator
def dev_single_axis(dev_dir: Path, motor: str = "motor_a", iterations: int = 12) -> None:
    """The twin on the independent simulator's calibration pair (``shared/datasets/dev``):
    one motor under a PI speed loop, without and with a disk. The two files become the
    sequencer's ``calibrate-in-unloaded`` and ``calibrate-in-disk`` steps (1 s at rest
    between them); the twin starts from gearbench's default motor and fits Kt, J, D, Tc
    and the drive's loop on current only (the files have no velocity column)."""
    import numpy as np

    from ..trace import Trace
    from ..twin import fit as F
    from ..twin.gap import gap_table, noise_floors
    from ..twin.replay import Quanta, Segment, replay

    truth = json.loads((dev_dir / "truth.json").read_text())["calibration"][motor]
    segs, k = [], 1
    for run, disks in (("unloaded", {}), ("loaded", {"in": truth["disk_inertia"]})):
        tr = Trace.read(dev_dir / f"calib_{motor}_{run}.csv")
        n = len(tr)
        cols = {"sample": np.arange(k, k + n), "in.position_rad": tr["position_rad"],
                "in.current_a": tr["current_a"], "in.command": tr["command"]}
        name = "calibrate-in-unloaded" if run == "unloaded" else "calibrate-in-disk"
        segs.append(Segment(name, "none", disks, {"in": "velocity", "out": "off"},
                            Trace(tr.time_s, cols, {}, name), k, k + n - 1))
        k += n + 1000
    block = {"motors": {"in": {"counts_per_rev": 10000, "current_resolution_a": 0.001}}, "seed": 0}
    q = Quanta()
    floors = noise_floors(segs)
    prob = F.Problem(segs, block, q, floors)
    params = [p for p in F.base_params(block) if p.path.startswith("motors.in.")]
    before = gap_table(replay(PlantParams.from_dict(block), segs, quanta=q), segs, floors)
    res = F.fit(prob, params, iterations=iterations)
    after = gap_table(replay(PlantParams.from_dict(F.with_params(prob.block, params)), segs, quanta=q),
                      segs, floors)
    got = F.written_values(params)
    print(f"\n=== independent simulator ({dev_dir.name}/calib_{motor}_*.csv), single axis ===")
    print(f"S/n {res['S0'] / res['n']:.2f} -> {res['S'] / res['n']:.2f}")
    print(f"{'parameter':<30} {'truth':>11} {'fitted':>11} {'±95 %':>10} {'within':>7}")
    for p in params:
        t = truth.get(p.path.rsplit(".", 1)[1])
        w = "" if t is None else ("yes" if abs(got[p.path] - t) <= p.interval else "NO")
        print(f"{p.path:<30} {_f(t):>11} {got[p.path]:11.5g} {p.interval:10.3g} {w:>7}")
    a = {(r["step"], r["signal"]): r["gap"] for r in after}
    for r in before:
        if r["axis"] == "in" and r["signal"] == "current_a" or r["signal"] == "position_rad" and r["axis"] == "in":
            print(f"  gap {r['step']:<24} {r['signal']:<14} {r['gap']:10.2f} -> {a[(r['step'], r['signal'])]:8.2f} floors")
