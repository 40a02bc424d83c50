"""gearbench identify: one run's fit of J θ'' + D θ' + Tc s(θ') = Kt i (per unit inertia)."""
from __future__ import annotations

import math

import numpy as np

from ..analysis.diagnose.nominal import POSITION_UNITS
from ..analysis.identify import METHODS, identify_trace, physical_parameters
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
    p.add_argument("--position-unit", default="rad", choices=tuple(POSITION_UNITS),
                   help="unit of the position column (and of command, velocity_rad_s per "
                        "second) as recorded (default rad): deg and rev are converted to rad; a "
                        "linear axis (m, mm, um) is fitted in metres, with no cogging terms unless "
                        "--travel-per-rev names the motor's lead")
    p.add_argument("--travel-per-rev", type=float, metavar="LEAD",
                   help="linear axis: travel per motor revolution in the position unit (the screw "
                        "lead), for cogging in the motor angle")
    p.add_argument("--load-angle", type=float, default=None, metavar="RAD_PER_UNIT",
                   help="fit a position-dependent load torque of order 1, q_s sin + q_c cos of the "
                        "load angle (gravity on an arm, an unbalance, an eccentric load; not "
                        "cogging): load radians per radian of the recorded angle (1 for a "
                        "load-side angle, 1/ratio for a motor angle behind a gear)")
    p.add_argument("--torque-constant", type=float, default=None, metavar="NM_PER_A",
                   help="the known torque per ampere of the recorded shaft (the motor's Kt for a "
                        "motor angle; a joint's torque per ampere, gear included, for a joint "
                        "angle; N/A for a linear axis): also print inertia J, viscous D and Coulomb "
                        "Tc in SI units with 95 %% intervals (the constant taken as exact)")
    p.add_argument("--no-check", action="store_true",
                   help="report what the run identifies (per parameter) instead of refusing a "
                        "run whose Kt/J is unidentifiable")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def run(args) -> int:
    trace = read_trace(args.trace, SINGLE_MOTOR_COLUMNS, motor=args.motor)
    opts = {"spring": True} if args.spring and args.method == "default" else {}
    trace, si_unit = _in_si_units(trace, args, opts)
    k = args.torque_constant
    if k is not None and not (math.isfinite(k) and k > 0):
        raise GearbenchError(f"--torque-constant must be a positive torque per ampere (N m/A, "
                             f"N/A for a linear axis), got {k}")
    if k is not None and args.method.startswith("paper"):
        raise GearbenchError("--torque-constant needs the default method (or accel/torque/iv): "
                             "the paper's method fits C/J where J, D and Tc need Tc/J")
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
    t = coverage_factor(fit.dof)
    physical = None
    if k is not None:
        units = PHYSICAL_UNITS["m" if si_unit == "m" else "rad"]
        physical = {name: (v, t * s, units[name])
                    for name, (v, s) in physical_parameters(fit, k).items()}
    if args.json:
        extra = {"position_unit": args.position_unit}
        if physical is not None:
            extra["physical"] = {"torque_constant": k, "coverage": 0.95,
                                 **{n: {"value": v, "half_width_95": h, "unit": u}
                                    for n, (v, h, u) in physical.items()}}
        dump({"file": str(args.trace), **fit.to_dict(), **extra})
        return 0
    print(f"{args.trace}: method {fit.method}, {fit.n_samples} samples at {1 / fit.dt_s:.6g} Hz"
          + (f", position in {args.position_unit} (fitted in {si_unit})"
             if args.position_unit != si_unit else ""))
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
    if physical is not None:
        print(f"  with {k:g} {'N' if si_unit == 'm' else 'N m'}/A (taken as exact): "
              + ", ".join(f"{n} {v:.6g} ± {h:.3g} {u}" for n, (v, h, u) in physical.items())
              + " (95 %)")
    return 0


# units of physical_parameters' J, D, Tc for a rotary angle in rad and a linear axis in m
PHYSICAL_UNITS = {"rad": {"J": "kg m^2", "D": "N m s/rad", "Tc": "N m"},
                  "m": {"J": "kg", "D": "N s/m", "Tc": "N"}}
LENGTH_M = {"m": 1.0, "mm": 1e-3, "um": 1e-6}


def _in_si_units(trace, args, opts):
    """The trace with its position (and speed columns) in rad or m, and that unit; sets
    the fit's ``rad_per_unit`` (motor radians per position unit, for cogging) from the
    user's stated unit and lead."""
    unit, lead = args.position_unit, args.travel_per_rev
    if lead is not None and not (math.isfinite(lead) and lead > 0):
        raise GearbenchError(f"--travel-per-rev must be a positive travel per motor revolution "
                             f"in {unit}, got {lead}")
    if unit in LENGTH_M:
        scale, si = LENGTH_M[unit], "m"
        opts["rad_per_unit"] = 2.0 * np.pi / (lead * scale) if lead is not None else None
    else:
        if lead is not None:
            raise GearbenchError(f"--travel-per-rev is for a linear axis (--position-unit m, mm "
                                 f"or um); the position here is in {unit}")
        scale, si = POSITION_UNITS[unit], "rad"
    if scale == 1.0:
        return trace, si
    cols = {c: np.asarray(trace[c], float) * scale
            for c in ("position_rad", "command", "velocity_rad_s") if c in trace}
    return trace.with_columns(**cols), si
