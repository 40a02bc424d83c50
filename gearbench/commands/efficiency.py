"""gearbench efficiency: reducer efficiency per loaded level of a two-motor bench trace."""
from __future__ import annotations

from ..analysis.calibration import MotorCalibration
from ..analysis.efficiency import efficiency
from ..errors import GearbenchError
from ..trace import BENCH_COLUMNS
from ._offline import dump, read_json, read_trace

NAME = "efficiency"
HELP = "Incremental (eq. 18) and absolute (P_out/P_in) efficiency from a bench trace."


def add_arguments(p) -> None:
    p.add_argument("bench", metavar="BENCH.csv",
                   help="two-motor bench trace: CSV/Parquet with time_s, in_position_rad, in_current_a, "
                        "in_command, out_position_rad, out_current_a, out_command, or a run folder's "
                        "trace-efficiency-<k>.parquet as it is")
    p.add_argument("--motor-in", metavar="IN.json", help="'calibrate --json' output of the input motor")
    p.add_argument("--motor-out", metavar="OUT.json", help="'calibrate --json' output of the output motor")
    p.add_argument("--kt-in", type=float, metavar="X", help="input motor Kt, N m/A (no loss model)")
    p.add_argument("--kt-out", type=float, metavar="Y", help="output motor Kt, N m/A (no loss model)")
    p.add_argument("--ratio", type=float, metavar="n", help="reduction ratio (default: from the encoders)")
    p.add_argument("--settle", type=float, default=0.5, metavar="S",
                   help="seconds dropped after each command change (default 0.5)")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def _motor(args, side: str) -> MotorCalibration:
    path, kt = getattr(args, f"motor_{side}"), getattr(args, f"kt_{side}")
    if path and kt is not None:
        raise GearbenchError(f"give either --motor-{side} or --kt-{side}, not both")
    if path:
        return MotorCalibration.from_dict(read_json(path), where=path)
    if kt is not None:
        return MotorCalibration.from_kt(kt, where=f"--kt-{side}")
    raise GearbenchError(f"missing the {side}put motor: pass --motor-{side} {side.upper()}.json "
                         f"(from 'gearbench calibrate --json') or --kt-{side} VALUE")


def run(args) -> int:
    m_in, m_out = _motor(args, "in"), _motor(args, "out")
    if not (args.settle >= 0):
        raise GearbenchError(f"--settle must be >= 0 s (got {args.settle})")
    trace = read_trace(args.bench, BENCH_COLUMNS, min_samples=100)
    res = efficiency(trace, m_in, m_out, ratio=args.ratio, settle_s=args.settle)
    if args.json:
        dump(res.to_dict())
        return 0
    src = "given" if args.ratio else "from encoders"
    print(f"{args.bench}: ratio {res.ratio:.5g} ({src}; encoders {res.ratio_measured:.5g}, "
          f"{'same direction' if res.ratio_sign > 0 else 'reversed'})")
    if m_in.D == 0 and m_in.Tc == 0 or m_out.D == 0 and m_out.Tc == 0:
        print("note: a motor without a loss model (--kt-*): absolute efficiency ignores its friction")
    print(f"{'#':>2} {'out cmd A':>9} {'speed in':>9} {'T out Nm':>9} "
          f"{'eta incr':>9} {'95 % interval':>17} {'eta abs':>9} {'95 % interval':>17}")
    for k, p in enumerate(res.points, 1):
        a, b = p.eta_incremental_ci95
        c, d = p.eta_absolute_ci95
        print(f"{k:>2} {p.window.out_command:>9.4g} {p.speed_in_rad_s:>9.4g} {p.torque_out_nm:>9.4g} "
              f"{p.eta_incremental:>9.4f} {a:>8.4f}..{b:<8.4f} {p.eta_absolute:>9.4f} "
              f"{c:>8.4f}..{d:<8.4f}{'  *' if p.loss_extrapolated else ''}")
    if any(p.loss_extrapolated for p in res.points):
        print("* motor losses extrapolated beyond the calibrated speed range (interval widened); "
              "calibrate over the bench's speeds for a tighter absolute efficiency")
    return 0
