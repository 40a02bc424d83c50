"""gearbench calibrate: a motor's Kt, J, D, Tc from two offline runs (paper eq. 17, corrected)."""
from __future__ import annotations

import math
from dataclasses import replace

from ..analysis.calibration import calibrate_motor
from ..analysis.identify import DRIVE_LOOP_KEYS, LOOP_DRIVE_KINDS, METHODS
from ..analysis.model_check import calibration_linearity, with_linearity
from ..analysis.uncertainty import TOLERANCE_SOURCES, tolerance_std
from ..errors import GearbenchError
from ..trace import SINGLE_MOTOR_COLUMNS
from ._offline import dump, read_trace

NAME = "calibrate"
HELP = "Identify a motor's torque constant from an unloaded run and a run with a known disk."


def add_arguments(p) -> None:
    p.add_argument("--unloaded", required=True, metavar="U.csv",
                   help="run of the motor alone: CSV/Parquet with time_s, position_rad, current_a, or a run "
                        "folder's trace-<step>.parquet with --motor")
    p.add_argument("--loaded", required=True, metavar="L.csv", help="run with the inertia disk (same columns)")
    p.add_argument("--motor", choices=["in", "out"],
                   help="in gearbench run traces (in.position_rad, out.position_rad ...): the motor to calibrate")
    p.add_argument("--inertia", required=True, type=float, metavar="J",
                   help="the disk's inertia, kg m^2")
    p.add_argument("--inertia-tolerance", type=float, default=0.0, metavar="REL",
                   help="how well the disk's inertia is known, relative (0.005 = ±0.5 %%); it adds to "
                        "Kt's uncertainty 1:1. Default 0: taken as exact, and said so")
    p.add_argument("--inertia-source", choices=tuple(TOLERANCE_SOURCES), default="datasheet",
                   help="datasheet: the tolerance is ± limits (u = tol/√3); measured: it is a 95 %% "
                        "expanded uncertainty (u = tol/2). Default datasheet")
    p.add_argument("--method", choices=METHODS, default="default",
                   help="identification method: default (bias-reduced), the torque-side form; accel, torque, iv: "
                        "the default's formulations alone; paper (as published, at the data rate); "
                        "paper-15ms (as published, resampled to the paper's 15 ms)")
    p.add_argument("--drive-setpoint", choices=["step", "interpolated"],
                   help="how the drive applied its speed setpoint: step (a new value each SYNC) or "
                        "interpolated (ramped between SYNCs); as the profile's motors.<m>.sampling.setpoint")
    p.add_argument("--drive-current", choices=["instant", "mean"],
                   help="how the drive sampled its current: instant (one sample) or mean (averaged over the "
                        "period); as the profile's motors.<m>.sampling.current. With --drive-setpoint step, "
                        "instant declares the current kick a stepped setpoint gives and the fit models it; "
                        "left out, the fit tests for it")
    p.add_argument("--drive-current-limit", type=float, default=None, metavar="A",
                   help="the current the drive clamps at (CiA 402 0x6073; the profile's "
                        "motors.<m>.current_limit_a): with --drive-setpoint step and --drive-current "
                        "instant, samples at the limit carry no setpoint kick")
    p.add_argument("--drive-loop", type=float, nargs=3, default=None,
                   metavar=("KP_A_S_PER_RAD", "TAU_S", "PERIOD_S"),
                   help="the drive's loop as set: speed-loop P gain (A per rad/s), current-loop time "
                        "constant (s), speed-loop period (s), as a profile's motors.<m>.sampling declares "
                        "them: with --drive-setpoint step and --drive-current instant the kick is computed "
                        "(identify.kick_coefficient) instead of fitted (forward and reversing runs); with "
                        "step and mean the kicks, with interpolated and instant the ramps' kinks are "
                        "added to the current's match (identify.declared_period_kick)")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def run(args) -> int:
    if not (math.isfinite(args.inertia) and args.inertia > 0):
        raise GearbenchError(f"--inertia must be > 0 kg m^2 (got {args.inertia}); pass the disk's "
                             f"inertia, e.g. --inertia 1.5e-5")
    tol = args.inertia_tolerance
    if not (math.isfinite(tol) and 0 <= tol <= 0.5):
        raise GearbenchError(f"--inertia-tolerance must be a relative tolerance between 0 and 0.5 "
                             f"(got {tol}); e.g. --inertia-tolerance 0.005 for ±0.5 %")
    unloaded = read_trace(args.unloaded, SINGLE_MOTOR_COLUMNS, motor=args.motor)
    loaded = read_trace(args.loaded, SINGLE_MOTOR_COLUMNS, motor=args.motor)
    if (args.drive_setpoint is None) != (args.drive_current is None):
        raise GearbenchError("--drive-setpoint and --drive-current go together (both say how the drive "
                             "samples, as a profile's motors.<m>.sampling); pass both or neither")
    limit = args.drive_current_limit
    if limit is not None and not (math.isfinite(limit) and limit > 0):
        raise GearbenchError(f"--drive-current-limit must be the drive's current limit in A, > 0 "
                             f"(got {limit}); e.g. --drive-current-limit 3")
    if limit is not None and args.drive_setpoint is None:
        raise GearbenchError("--drive-current-limit goes with --drive-setpoint and --drive-current "
                             "(it says where a stepping drive's setpoint kick is clipped); pass them too")
    loop = args.drive_loop
    if loop is not None and (args.drive_setpoint, args.drive_current) not in LOOP_DRIVE_KINDS:
        raise GearbenchError("--drive-loop goes with --drive-setpoint step --drive-current instant|mean "
                             "or --drive-setpoint interpolated --drive-current instant (it computes what "
                             "such a drive's setpoint does to its current within each period); pass them too")
    if loop is not None and not (all(math.isfinite(v) for v in loop) and loop[0] > 0 and loop[1] >= 0
                                 and loop[2] > 0):
        raise GearbenchError(f"--drive-loop takes the speed-loop P gain in A per rad/s (> 0), the "
                             f"current-loop time constant in s (>= 0) and the speed-loop period in s "
                             f"(> 0); got {' '.join(f'{v:g}' for v in loop)}, e.g. --drive-loop 0.04 5e-4 2.5e-4")
    if args.drive_setpoint is not None:
        for tr in (unloaded, loaded):
            tr.meta["drive"] = {"setpoint": args.drive_setpoint, "current": args.drive_current}
            if limit is not None:
                tr.meta["drive"]["current_limit_a"] = limit
            if loop is not None:
                tr.meta["drive"].update(zip(DRIVE_LOOP_KEYS, loop))
    disk_std = tolerance_std(tol * args.inertia, args.inertia_source)
    cal = calibrate_motor(unloaded, loaded, args.inertia, method=args.method, disk_std_kgm2=disk_std)
    cal = replace(cal, fit=with_linearity(cal.fit, calibration_linearity(
        unloaded, loaded, kt=cal.Kt, kt_ci95=cal.Kt_ci95, motor=args.motor or "", current_limit_a=limit)))
    if args.json:
        dump(cal.to_dict())
        return 0
    lo, hi = cal.Kt_ci95
    f = cal.fit
    print(f"method       {cal.method}")
    print(f"Kt           {cal.Kt:.6g} N m/A   (95 %: {lo:.6g} .. {hi:.6g}; std {cal.Kt_std:.3g}, "
          f"dof {cal.Kt_dof:.0f})")
    if tol == 0:
        print("             disk inertia taken as exact: the interval leaves out its tolerance "
              "(pass --inertia-tolerance)")
    print(f"J            {cal.J:.6g} kg m^2 (rotor, without disk)")
    print(f"D            {cal.D:.6g} N m s/rad")
    print(f"Tc           {cal.Tc:.6g} N m")
    print(f"b2 unloaded  {f['b2_unloaded']:.6g} 1/(A s^2)   loaded {f['b2_loaded']:.6g}")
    print(f"fit          r2 of the acceleration {f['r2']:.6f}  condition {f['condition']:.3g}  samples {f['n_samples']}")
    for w in f.get("warnings", []):
        print(f"warning      {w}")
    return 0
