"""``gearbench diagnose TRACE``: where the paper's model and the bench disagree, which
unmodelled effect explains it, and how far adding it closes the gap (issue 6)."""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np

from ..errors import GearbenchError, TraceError
from ..trace import Trace

NAME = "diagnose"
HELP = "diagnose the sim-to-real gap of a single-motor trace (where, which effect, how far)"


def add_arguments(p) -> None:
    p.add_argument("trace", metavar="TRACE", nargs="?", help="single-motor trace (.csv or "
                   ".parquet) with time_s, position_rad, current_a — or a RUN_DIR written by "
                   "'gearbench run': every step diagnosed (calibrations per motor, efficiency "
                   "steps against the reducer model built from the run's calibrations), "
                   "kept as RUN_DIR/diagnosis.json for the run's report.html")
    p.add_argument("--bench", metavar="BENCH_TRACE",
                   help="diagnose a two-motor reducer bench trace instead (in_/out_ position "
                        "and current): where the simulated reducer and the bench disagree")
    p.add_argument("--motor-in", metavar="IN.json",
                   help="with --bench: the input motor's calibration (what 'gearbench "
                        "calibrate --json' prints); the reducer is then fitted in N m")
    p.add_argument("--motor-out", metavar="OUT.json",
                   help="with --bench: the output motor's calibration")
    p.add_argument("--model", metavar="MODEL.json",
                   help='nominal model {"Kt":..,"J":..,"D":..} instead of identifying it on the trace')
    p.add_argument("--position-unit", default="rad", choices=("rad", "deg", "rev", "m", "mm", "um"),
                   help="unit of the trace's position column (default rad): patterns per "
                        "motor revolution (cogging, ripple) are tested only in a known angle")
    p.add_argument("--travel-per-rev", type=float, metavar="LEAD",
                   help="travel per motor revolution in the position unit (a linear axis's "
                        "screw lead, e.g. 0.0025 for 2.5 mm in m): lets a linear axis be "
                        "tested for cogging and ripple")
    p.add_argument("--ratio", type=float, metavar="N",
                   help="gear ratio, motor revolutions per load revolution: a position-"
                        "dependent load torque (gravity, unbalance) is tested as order 1 of "
                        "the load angle, distinct from cogging (motor-angle orders); not "
                        "given: the position is taken as the load's angle")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--report", metavar="DIR", help="write PNG residual maps to DIR")
    p.add_argument("--rrd", metavar="FILE", help="log residuals to a Rerun .rrd file")


def _jsonable(o):
    if isinstance(o, dict):
        return {str(k): _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    if isinstance(o, np.generic):
        o = o.item()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return o


def run(args) -> int:
    from ..analysis.diagnose import diagnose, load_model

    if args.bench:
        return _run_bench(args)
    if not args.trace:
        raise TraceError("give a TRACE to diagnose (or --bench BENCH_TRACE for a reducer bench)")
    p = Path(args.trace)
    if p.is_dir():
        return _run_dir(args, p)
    trace = Trace.read(p)
    model = load_model(args.model) if args.model else None
    result = diagnose(trace, model, position_unit=args.position_unit,
                      travel_per_rev=args.travel_per_rev, ratio=args.ratio)
    out = _jsonable(result.as_dict())
    if args.report:
        out["report"] = write_report(result, Path(args.report))
    if args.rrd:
        out["rrd"] = write_rrd(result, Path(args.rrd))
    if args.json:
        print(json.dumps(out, indent=1))
    else:
        print(summary(out, str(p)))
    return 0


def _run_bench(args) -> int:
    from ..analysis.diagnose.reducer import diagnose_bench

    p = Path(args.bench)
    if p.is_dir():
        raise TraceError(f"{p}: is a folder, not a trace file; pass a .csv or .parquet file")
    if bool(args.motor_in) != bool(args.motor_out):
        raise TraceError("give both --motor-in and --motor-out (each motor's calibration), "
                         "or neither")
    cal_in = _calibration(args.motor_in) if args.motor_in else None
    cal_out = _calibration(args.motor_out) if args.motor_out else None
    d = _jsonable(diagnose_bench(Trace.read(p), motor_in=cal_in, motor_out=cal_out).as_dict())
    if args.json:
        print(json.dumps(d, indent=1))
        return 0
    lines = [f"{p}: simulated reducer (constant efficiency, ideal ratio "
             f"{d['nominal']['noise']['ratio_estimate']:.4g}, Coulomb + viscous drag) vs bench; "
             f"torques in {d['nominal']['noise'].get('torque_unit', 'A')}"
             + ("" if cal_in else " (no motor calibrations: the motors' own losses are in "
                "the nominal)")]
    phys = d["nominal"].get("physical") or {}
    eff = ", ".join(f"{k} {phys[k]:.3f}" for k in ("efficiency_forward", "efficiency_backward")
                    if phys.get(k) is not None)
    if eff:
        lines.append(f"  implied {eff}")
    for problem in phys.get("problems", []):
        lines.append(f"  NOT PHYSICAL: {problem}")
    for rel in ("kinematics", "torque"):
        n = d["nominal"][rel]
        lines.append(f"  {rel}: held-out rms {n['rms']:.3g} vs noise floor {n['noise_floor']:.3g} "
                     f"({n['gap_ratio']:.2f}x)")
    if d["chain"]:
        lines.append("chain (held-out):")
        for k, c in enumerate(d["chain"], 1):
            lines.append(f"  {k}. {c['effect']:22s} ({c['relation']}) shrink {c['shrink_heldout']:.0%}"
                         f", cumulative {c['cumulative_shrink']:.0%}; "
                         + ", ".join(f"{a}={v:.4g}" if isinstance(v, float) else f"{a}={v}"
                                     for a, v in c["params"].items()))
    else:
        lines.append("chain: no reducer effect significant on held-out data")
    for rel, r in d["remaining"].items():
        lines.append(f"remaining ({rel}): {r['gap_ratio']:.2f}x the noise floor"
                     + (" — at the floor" if r["at_noise_floor"] else
                        " — UNKNOWN EFFECT" if r["unknown_effect"] else ""))
    print("\n".join(lines))
    return 0


def _label(text: str, unit: str) -> str:
    """A where-cell label in the trace's position unit (cells say ``units``)."""
    return text.replace("units/s", f"{unit}/s")


def _fmt(params: dict) -> str:
    return ", ".join(f"{k}={val:.4g}" if isinstance(val, float) else f"{k}={val}"
                     for k, val in params.items())


def summary(d: dict, name: str) -> str:
    """The diagnosis as text, speeds in the trace's own position unit per second."""
    fit, v = d["nominal"]["fit"], d["verdict"]
    par = d["nominal"]["params"]
    u = fit.get("position_unit") or "rad"
    lines = [f"{name}: nominal Kt/J = {par['kt_over_j']:.4g} {u}/(A s^2), D/J = "
             f"{par['d_over_j']:.4g} 1/s; held-out sim error {fit['sim_rms_rad_s']:.3g} {u}/s "
             f"vs noise floor {fit['noise_floor_rad_s']:.3g} {u}/s ({fit['gap_ratio']:.2f}x)"]
    phys = d["nominal"].get("physical") or {}
    for problem in phys.get("problems", []):
        lines.append(f"NOMINAL NOT PHYSICAL: {problem}" if not phys.get("ok", True)
                     else f"nominal: {problem}")
    if phys.get("what_it_means"):
        lines.append(f"  what it means: {phys['what_it_means']}")
    hot = [c for c in d["where"] if c["above_floor"]]
    if hot:
        hot.sort(key=lambda c: -c["ratio"])
        lines.append("where: " + "; ".join(f"{c['dimension']} {_label(c['label'], u)} "
                                           f"{c['ratio']:.1f}x" for c in hot[:6]))
    else:
        lines.append("where: no cell above 1.5x its noise floor")
    lines.append(f"{'effect':22s}{'nrmse before':>14s}{'after':>10s}{'shrink':>8s}{'dBIC':>9s}  sig  testable")
    for c in d["candidates"]:
        lines.append(f"{c['effect']:22s}{c['nrmse_before']:14.4g}{c['nrmse_after']:10.4g}"
                     f"{(c['shrink'] if c['shrink'] is not None else float('nan')):8.2f}"
                     f"{(c['delta_bic'] if c['delta_bic'] is not None else float('nan')):9.1f}"
                     f"  {'yes' if c['significant'] else 'no ':3s}  {'yes' if c.get('testable') else 'no'}"
                     + (f"  not physical: {c['params']['not_physical']}"
                        if c["params"].get("not_physical") else ""))
    if v["effect"]:
        # the verdict's own effect: its final parameters from the chain, else its score
        step = next((c for c in d.get("chain") or [] if c["effect"] == v["effect"]), None)
        own = next((c for c in d["candidates"] if c["effect"] == v["effect"]), None)
        shrink = step["shrink_heldout"] if step else own["shrink"]
        params = (step.get("params_final") or step["params"]) if step else own["params"]
        lines.append(f"verdict: {v['effect']} (shrink {shrink:.0%}); params " + _fmt(params))
        if v["confused_with"]:
            lines.append(f"  cannot be told apart here from: {', '.join(v['confused_with'])}")
            lines.append(f"  experiment: {v['experiment']}")
    elif not phys.get("ok", True):
        lines.append("verdict: refused — the nominal is not physical (see above)")
    elif v.get("experiment"):
        lines.append("verdict: none — a gap remains that no testable effect explains")
        lines.append(f"  {v['experiment']}")
    else:
        lines.append("verdict: none — the gap is at the noise floor")
    chain, rem = d.get("chain") or [], d.get("remaining") or {}
    if chain:
        lines.append("chain (effects added one at a time, all refitted together; listed by "
                     "held-out gain at the final settings):")
        for k, c in enumerate(chain, 1):
            lines.append(f"  {k}. {c['effect']:22s} shrink {c['shrink_heldout']:6.0%}  cumulative "
                         f"{c['cumulative_shrink']:6.0%}  ({c['gap_ratio_after']:.2f}x floor after)"
                         + (f"  [added {c['added_at']}.]" if c.get("added_at", k) != k else "")
                         + (f"  [alike: {', '.join(c['confused_with'])}]" if c["confused_with"] else ""))
        lines.append(f"  size (error reopened without it, held-out, {u}/s): " + ", ".join(
            f"{c['effect']} {c['drop_one_gap_rad_s']:.3g}" for c in
            sorted(chain, key=lambda c: c["size_rank"])))
    for x in d.get("dropped") or []:
        lines.append(f"  dropped {x['effect']}: {x['why']}")
    if rem:
        state = ("at the noise floor" if rem["at_noise_floor"] else
                 "UNKNOWN EFFECT: a significant gap that no candidate explains"
                 if rem["unknown_effect"] else
                 f"stopped at the cap of {len(chain)} effects with a significant gap left"
                 if rem["stopped"] == "max_steps" and rem.get("significant_gap") else
                 f"stopped ({rem['stopped']})")
        lines.append(f"remaining: {rem['share_of_gap']:.0%} of the original gap, "
                     f"{rem['gap_ratio']:.2f}x the noise floor — {state}")
        if rem["where"] and not rem["at_noise_floor"]:
            lines.append("  where: " + "; ".join(f"{c['dimension']} {_label(c['label'], u)} "
                                                 f"{c['ratio']:.1f}x" for c in rem["where"][:5]))
    if v.get("untestable"):
        lines.append(f"not testable on this trace: {', '.join(v['untestable'])}")
    return "\n".join(lines)


def write_report(result, folder: Path) -> list[str]:
    """Heat maps of the nominal model's residuals (matplotlib: axes, units, colour bar)."""
    from ..reports.plots import heatmap_png

    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise GearbenchError(f"{folder}: cannot create report folder ({exc.strerror}); "
                             f"choose a writable --report DIR") from None
    maps = result.residuals
    floor = float(maps["floor_rad_s"])
    err = np.abs(np.asarray(maps["horizon_error_rad_s"], float))
    t = np.asarray(maps["time_s"], float).reshape(err.shape) if err.ndim == 2 else None
    if t is not None and t.size:   # rows: horizon starts, columns: time into the horizon
        start, into = (float(t[0, 0]), float(t[-1, 0])), (0.0, float(t[0, -1] - t[0, 0]))
    else:
        start, into = (0.0, float(err.shape[0]) if err.ndim == 2 else 1.0), (0.0, 1.0)
    speed = tuple(maps.get("speed_range_rad_s", (0.0, 1.0)))
    label = "rms simulation error / noise floor"
    files = {
        "horizon_error.png": dict(values=err.T / floor if err.ndim == 2 else np.atleast_2d(err) / floor,
                                  x_extent=start, y_extent=into, xlabel="horizon start [s]",
                                  ylabel="time into the horizon [s]", colorbar_label="|simulation error| / noise floor",
                                  title=f"Held-out simulation error of the nominal model (floor {floor:.3g} rad/s)"),
        "speed_angle.png": dict(values=maps["speed_angle_rms"] / floor, x_extent=speed,
                                y_extent=tuple(maps.get("angle_range_rad", (0.0, 2 * np.pi))),
                                xlabel="|speed| [rad/s]", ylabel="rotor angle mod 2π [rad]",
                                colorbar_label=label, title="Where the error is: speed × rotor angle"),
        "speed_current.png": dict(values=maps["speed_current_rms"] / floor, x_extent=speed,
                                  y_extent=tuple(maps.get("current_range_a", (0.0, 1.0))),
                                  xlabel="|speed| [rad/s]", ylabel="current [A]",
                                  colorbar_label=label, title="Where the error is: speed × current"),
    }
    written = []
    for name, spec in files.items():
        arr = np.asarray(spec["values"], float)
        top = max(3.0, float(np.nanmax(arr))) if np.isfinite(arr).any() else 3.0
        path = folder / name
        path.write_bytes(heatmap_png(vmin=0.0, vmax=top, **spec))
        written.append(str(path))
    (folder / "diagnosis.json").write_text(json.dumps(_jsonable(result.as_dict()), indent=1))
    written.append(str(folder / "diagnosis.json"))
    return written


def write_rrd(result, path: Path) -> str:
    """Log the residuals as time series to a Rerun recording saved at ``path``, in the
    diagnosis layout (``reports.live.blueprint.diagnosis_blueprint``): the simulation error
    and the noise floor that bounds it on one axis, the equation error below."""
    import rerun as rr

    from ..reports.live.blueprint import diagnosis_blueprint
    from ..reports.live.paths import DIAGNOSIS_EQUATION, DIAGNOSIS_ERROR, DIAGNOSIS_TIMELINE

    maps = result.residuals
    rec = rr.RecordingStream("gearbench_diagnose")
    try:
        rec.save(str(path))
    except Exception as exc:  # rerun raises its own error types for bad paths
        raise GearbenchError(f"{path}: cannot write Rerun file ({exc}); choose a writable --rrd FILE") from None
    rec.send_blueprint(diagnosis_blueprint())
    t = maps["time_s"]
    rec.send_columns(f"{DIAGNOSIS_ERROR}/sim_error_rad_s", indexes=[rr.TimeColumn(DIAGNOSIS_TIMELINE, duration=t)],
                     columns=rr.Scalars.columns(scalars=maps["error_flat"]))
    rec.send_columns(f"{DIAGNOSIS_ERROR}/noise_floor_rad_s", indexes=[rr.TimeColumn(DIAGNOSIS_TIMELINE, duration=t)],
                     columns=rr.Scalars.columns(scalars=np.full(t.shape, float(maps["floor_rad_s"]))))
    rec.send_columns(f"{DIAGNOSIS_EQUATION}/equation_error_rad_s2",
                     indexes=[rr.TimeColumn(DIAGNOSIS_TIMELINE, duration=maps["ee_time_s"])],
                     columns=rr.Scalars.columns(scalars=maps["equation_error"]))
    rec.flush()
    rec.disconnect()
    return str(path)


def _calibration(path: str) -> dict:
    from ..analysis.diagnose.reducer import calibration

    p = Path(path)
    data = _read_json(p, f"{p}: calibration file not found; give what 'gearbench calibrate --json' printed")
    return calibration(data, str(p))


def _read_json(path: Path, missing: str):
    """A JSON file, or one TraceError: ``missing`` when it is absent, else what is wrong."""
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise TraceError(missing) from None
    except (OSError, json.JSONDecodeError) as exc:
        raise TraceError(f"{path}: not valid JSON ({exc})") from None


#: The whole-run diagnosis as written into the run folder (read by the unit report).
RUN_DIAGNOSIS = "diagnosis.json"


def _run_dir(args, folder: Path) -> int:
    """``gearbench diagnose RUN_DIR``: every step of a finished run."""
    from ..analysis.diagnose.runs import diagnose_run
    from ..station.recorder import load_step_trace

    result = _read_json(folder / "result.json", f"{folder}: no result.json; give the output folder of "
                                                 f"a 'gearbench run' (or a trace file)")
    files = {q.stem[len("trace-"):]: q for q in sorted(folder.glob("trace-*.arrows"))}
    files.update({q.stem[len("trace-"):]: q for q in sorted(folder.glob("trace-*.parquet"))})
    if not files:
        raise TraceError(f"{folder}: no trace-*.parquet; record the run with traces")
    steps = {}
    for name, q in files.items():
        try:
            steps[name] = load_step_trace(q)
        except Exception as exc:    # a damaged trace must not hide the rest of the run
            print(f"{q}: unreadable ({exc}); skipped")
    run = diagnose_run(steps, result, ratio=args.ratio)
    out = _jsonable({"run_dir": str(folder), **run})
    # kept with the run: `gearbench report` adds its section to report.html
    try:
        (folder / RUN_DIAGNOSIS).write_text(json.dumps(out, indent=1))
    except OSError as exc:
        print(f"{folder / RUN_DIAGNOSIS}: not written ({exc.strerror}); report.html will "
              f"have no diagnosis section", file=sys.stderr)
    if args.rrd:
        out["rrd"] = _run_rrd(run, Path(args.rrd))
    if args.json:
        print(json.dumps(out, indent=1))
        return 0
    lines = [f"{folder}: {len(run['steps'])} traces diagnosed"]
    for e in run["steps"]:
        state = ("at the noise floor" if e["at_noise_floor"] else
                 "UNKNOWN EFFECT" if e["unknown_effect"] else "above the floor")
        lines.append(f"  {e['step']:28s} {e['motor']:8s} {e['kind']:5s} nominal "
                     f"{e['gap_ratio_nominal']:7.2f}x -> "
                     + (", ".join(f"{c['effect']} {c['shrink_heldout']:.0%}"
                                  + (f" [alike: {', '.join(c['confused_with'])}]"
                                     if c["confused_with"] else "") for c in e["chain"])
                        or "no effect")
                     + f" -> {e['gap_ratio_after']:.2f}x ({state})")
        phys = e.get("physical") or {}
        for problem in phys.get("problems", []):
            lines.append(f"      NOT PHYSICAL: {problem}")
    for x in run["skipped"]:
        lines.append(f"  skipped {x.get('step')} {x.get('motor', '')}: {x['why']}")
    if run["worst_gap_ratio"] is not None:
        lines.append(f"worst remainder {run['worst_gap_ratio']:.2f}x the noise floor; unknown "
                     f"effects: {', '.join(run['unknown_effects']) or 'none'}")
    print("\n".join(lines))
    return 0


def _run_rrd(run: dict, path: Path) -> str:
    """Each diagnosed single-motor step's held-out error and floor in one recording."""
    import rerun as rr

    rec = rr.RecordingStream("gearbench_diagnose_run")
    try:
        rec.save(str(path))
    except Exception as exc:  # rerun raises its own error types for bad paths
        raise GearbenchError(f"{path}: cannot write Rerun file ({exc}); choose a writable --rrd FILE") from None
    for e in run["steps"]:
        base = f"diagnose/{e['step']}/{e['motor']}".replace(">", "")
        rec.log(f"{base}/gap_ratio", rr.Scalars([e["gap_ratio_after"]]), static=True)
        rec.log(f"{base}/summary", rr.TextDocument(
            ", ".join(c["effect"] for c in e["chain"]) or "no effect"), static=True)
    rec.flush()
    rec.disconnect()
    return str(path)
