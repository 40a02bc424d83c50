"""gearbench identify: one run's fit of J θ'' + D θ' + Tc s(θ') = Kt i (per unit inertia)."""
from __future__ import annotations

from ..analysis.identify import METHODS, identify_trace, t_quantile
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
                   help="identification method: default (bias-reduced), paper (as published, at the data rate), "
                        "paper-15ms (as published, resampled to the paper's 15 ms)")
    p.add_argument("--spring", action="store_true",
                   help="default method: also fit C/J (spring to ground, the paper's C)")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def run(args) -> int:
    trace = read_trace(args.trace, SINGLE_MOTOR_COLUMNS, motor=args.motor)
    opts = {"spring": True} if args.spring and args.method == "default" else {}
    fit = identify_trace(trace, method=args.method, **opts)
    if args.json:
        dump({"file": str(args.trace), **fit.to_dict()})
        return 0
    t = t_quantile(fit.dof)
    print(f"{args.trace}: method {fit.method}, {fit.n_samples} samples at {1 / fit.dt_s:.6g} Hz")
    for name, v in zip(fit.names, fit.values):
        print(f"  {name:<6} {v:14.6g}  ± {t * fit.std(name):.3g} (95 %)")
    print(f"  r2 {fit.r2:.6f}  rmse {fit.rmse:.4g} rad/s^2  condition {fit.condition:.3g}  "
          f"effective samples {fit.n_effective:.0f}")
    return 0
