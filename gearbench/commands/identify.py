"""gearbench identify: one run's fit of J θ'' + D θ' + Tc s(θ') = Kt i (per unit inertia)."""
from __future__ import annotations

import math

from ..analysis.identify import METHODS, identify_trace
from ..analysis.uncertainty import coverage_factor
from ..errors import GearbenchError
from ..trace import SINGLE_MOTOR_COLUMNS
from ._offline import dump, read_trace

NAME = "identify"
HELP = "Fit one single-motor trace: b2 = Kt/J, D/J, Tc/J (and C/J for the paper's method)."


def add_arguments(p) -> None:
    p.add_argument("trace", metavar="TRACE",
                   help="single-motor trace: CSV or Parquet with columns time_s, position_rad, current_a "
                        "(optional command, velocity_rad_s), or a run folder's trace-<step>.parquet "
                        "with --motor")
    p.add_argument("--motor", choices=["in", "out"],
                   help="in a gearbench run trace (in.position_rad, out.position_rad ...): the motor to fit")
    p.add_argument("--method", choices=METHODS, default="default",
                   help="identification method: default (bias-reduced), the torque-side form; accel, torque, iv: "
                        "the default's formulations alone; paper (as published, at the data rate); "
                        "paper-15ms (as published, resampled to the paper's 15 ms)")
    p.add_argument("--spring", action="store_true",
                   help="default method: also fit C/J (spring to ground, the paper's C)")
    p.add_argument("--load-angle", type=float, default=None, metavar="RAD_PER_UNIT",
                   help="fit a position-dependent load torque of order 1, q_s sin + q_c cos of the "
                        "load angle (gravity on an arm, an unbalance, an eccentric load; not "
                        "cogging): the load angle in radians per position unit (1 for a "
                        "load-side angle, 1/ratio for a motor angle behind a gear)")
    p.add_argument("--no-check", action="store_true",
                   help="report what the run identifies (per parameter) instead of refusing a "
                        "run whose Kt/J is unidentifiable")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def run(args) -> int:
    trace = read_trace(args.trace, SINGLE_MOTOR_COLUMNS, motor=args.motor)
    opts = {"spring": True} if args.spring and args.method == "default" else {}
    if args.load_angle is not None:
        if not (math.isfinite(args.load_angle) and args.load_angle > 0):
            raise GearbenchError(f"--load-angle must be a positive number of load radians per "
                                 f"position unit, got {args.load_angle}")
        if args.method.startswith("paper"):
            raise GearbenchError("--load-angle needs the default method (or accel/torque/iv)")
        opts["load_rad_per_unit"] = args.load_angle
    if args.no_check:
        opts["check"] = False
    fit = identify_trace(trace, method=args.method, **opts)
    if args.json:
        dump({"file": str(args.trace), **fit.to_dict()})
        return 0
    t = coverage_factor(fit.dof)
    print(f"{args.trace}: method {fit.method}, {fit.n_samples} samples at {1 / fit.dt_s:.6g} Hz")
    for name, v in zip(fit.names, fit.values):
        print(f"  {name:<6} {v:14.6g}  ± {t * fit.std(name):.3g} (95 %)")
    unit = fit.extras.get("residual_unit", "rad/s^2")
    print(f"  r2 {fit.r2:.6f}  rmse {fit.rmse:.4g} {unit}  condition {fit.condition:.3g}  "
          f"effective samples {fit.n_effective:.0f}")
    ident = fit.extras.get("identified")
    if ident:
        no = [n for n, ok in ident.items() if not ok]
        print(f"  identified: {', '.join(n for n, ok in ident.items() if ok) or 'nothing'}"
              + (f"; not identified by this run: {', '.join(no)}" if no else ""))
    for w in fit.extras.get("warnings", []):
        print(f"  warning: {w}")
    pa = fit.extras.get("per_ampere")
    if pa:
        print("  per ampere: " + ", ".join(f"{k} {v:.6g} ± {t * s:.3g}" for k, (v, s) in pa.items()))
    cc = fit.extras.get("cross_check")
    if cc:
        print(f"  cross-check ({cc['method']}): {cc['verdict']}")
    return 0
