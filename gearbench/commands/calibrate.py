"""gearbench calibrate: a motor's Kt, J, D, Tc from two offline runs (paper eq. 17, corrected)."""
from __future__ import annotations

import math

from ..analysis.calibration import calibrate_motor
from ..analysis.identify import METHODS
from ..errors import GearbenchError
from ..trace import SINGLE_MOTOR_COLUMNS
from ._offline import dump, read_trace

NAME = "calibrate"
HELP = "Identify a motor's torque constant from an unloaded run and a run with a known disk."


def add_arguments(p) -> None:
    p.add_argument("--unloaded", required=True, metavar="U.csv", help="run of the motor alone")
    p.add_argument("--loaded", required=True, metavar="L.csv", help="run with the inertia disk")
    p.add_argument("--inertia", required=True, type=float, metavar="J",
                   help="the disk's inertia, kg m^2")
    p.add_argument("--method", choices=METHODS, default="default",
                   help="identification method (default: bias-reduced; paper: as published)")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def run(args) -> int:
    if not (math.isfinite(args.inertia) and args.inertia > 0):
        raise GearbenchError(f"--inertia must be > 0 kg m^2 (got {args.inertia}); pass the disk's "
                             f"inertia, e.g. --inertia 1.5e-5")
    unloaded = read_trace(args.unloaded, SINGLE_MOTOR_COLUMNS)
    loaded = read_trace(args.loaded, SINGLE_MOTOR_COLUMNS)
    cal = calibrate_motor(unloaded, loaded, args.inertia, method=args.method)
    if args.json:
        dump(cal.to_dict())
        return 0
    lo, hi = cal.Kt_ci95
    f = cal.fit
    print(f"method       {cal.method}")
    print(f"Kt           {cal.Kt:.6g} N m/A   (95 %: {lo:.6g} .. {hi:.6g})")
    print(f"J            {cal.J:.6g} kg m^2 (rotor, without disk)")
    print(f"D            {cal.D:.6g} N m s/rad")
    print(f"Tc           {cal.Tc:.6g} N m")
    print(f"b2 unloaded  {f['b2_unloaded']:.6g} 1/(A s^2)   loaded {f['b2_loaded']:.6g}")
    print(f"fit          r2 {f['r2']:.6f}  condition {f['condition']:.3g}  samples {f['n_samples']}")
    return 0
