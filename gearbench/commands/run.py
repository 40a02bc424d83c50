"""gearbench run PROFILE: the end-of-line test (calibrate -> load -> efficiency)."""
from __future__ import annotations

import sys
from datetime import datetime, timezone
from pathlib import Path

from ..errors import GearbenchError

NAME = "run"
HELP = "Run a test profile on the bench (or on the simulated bench with --sim)."


def add_arguments(p) -> None:
    p.add_argument("profile", help="test profile: a YAML file (e.g. profiles/cvt.yaml) or a shipped "
                                   "profile's name (e.g. cvt)")
    p.add_argument("--sim", action="store_true",
                   help="run against the simulated bench (emulated drives behind real CANopen/Modbus); "
                        "the result says SIMULATED")
    p.add_argument("--serial", default=None,
                   help="serial number of the unit under test; required without --sim "
                        "(with --sim the default is SIM-0001)")
    p.add_argument("--out", help="output folder for this run (default results/<serial>-<UTC time>)")
    p.add_argument("--db", help="station database (default station.sqlite beside the output folder); "
                                "checked writable before anything moves")
    p.add_argument("--yes", action="store_true", help="answer operator prompts with yes (unattended)")
    p.add_argument("--quiet", action="store_true",
                   help="no progress and no table: only the verdict line (with the output folder) on stdout")
    p.add_argument("--twin", metavar="YAML",
                   help="with --sim: run against this fitted digital twin (a simulation: block written by "
                        "'gearbench twin --write') instead of the profile's simulation: section")
    p.add_argument("--report", action="store_true",
                   help="also write the per-unit report.html into the output folder (also for a failed unit)")
    p.add_argument("--mdf", action="store_true",
                   help="also write the traces as ASAM MDF4 (traces.mf4, as 'gearbench export --mdf'); "
                        "the profile's outputs: {mdf: true} does the same for every run")
    p.add_argument("--rrd", help="record the live view to this .rrd file (checked writable before anything moves)")
    p.add_argument("--live", action="store_true", help="open a Rerun viewer with the live view")
    p.add_argument("--connect", metavar="URL",
                   help="stream the live view to a running Rerun viewer, e.g. rerun+http://127.0.0.1:9876/proxy")
    p.add_argument("--method", choices=["default", "paper"], default="default",
                   help="identification method: default (bias-reduced), paper (as published, at the data rate)")
    p.add_argument("--seed", type=int, default=None, help="with --sim: the plant's noise seed (default: the profile's)")
    p.add_argument("--central", metavar="URL",
                   help="also push the finished run to this central database postgresql://... "
                        "(default: $GEARBENCH_CENTRAL or central: in the station config); "
                        "the station database stays the outbox if it is unreachable")
    p.add_argument("--golden", action="store_true",
                   help="the unit is a reference unit: compare it to its stored baseline "
                        "(its first passed golden run), exit 1 if it deviates")


def run(args) -> int:
    from ..api import run_profile

    if args.twin and not args.sim:
        raise GearbenchError("--twin is the simulated bench's plant; add --sim")

    serial = args.serial or ("SIM-0001" if args.sim else None)
    if serial is None:
        raise GearbenchError("no --serial given; scan or type the unit's serial number "
                             "(e.g. --serial SN12345)")
    if args.connect:                    # before anything moves (rerun is imported only then)
        from ..reports.live.rerun_view import check_connect_url
        check_connect_url(args.connect)
    stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    out = Path(args.out or f"results/{serial}-{stamp}")
    if not args.yes and not args.sim and not sys.stdin.isatty():
        raise GearbenchError("no operator terminal to answer the mounting prompts; "
                             "run from a terminal or pass --yes for an unattended run")
    db = Path(args.db) if args.db else out.resolve().parent / "station.sqlite"  # as open_bench
    if args.golden:
        from ..fleet.golden import mark_golden
        from ..profile import load_profile

        mark_golden(db, serial, load_profile(args.profile).name)
    result = run_profile(args.profile, sim=args.sim, out_dir=out, serial=serial,
                         db=db, yes=args.yes or args.sim, rrd=args.rrd, live=args.live,
                         connect=args.connect, method=args.method, seed=args.seed,
                         quiet=args.quiet, central=args.central, twin=args.twin, summary=sys.stdout)
    if args.report:
        _report(out)
    if args.mdf or _profile_wants_mdf(args.profile):
        _mdf(out)
    if args.golden:
        return _golden(db, out, result)
    return int(result["exit_code"])


def _report(out: Path) -> None:
    """report.html beside result.json; a report problem never changes the unit's verdict."""
    from ..reports.unit_report import write_report

    try:
        print(f"gearbench run: report {write_report(out)}", file=sys.stderr)
    except GearbenchError as exc:
        print(f"gearbench run: warning: no report: {exc}", file=sys.stderr)


def _profile_wants_mdf(profile: str) -> bool:
    from ..profile import load_profile

    try:
        return bool(load_profile(profile).outputs.mdf)
    except GearbenchError:
        return False


def _mdf(out: Path) -> None:
    """traces.mf4 beside the Parquet traces; an export problem never changes the verdict."""
    from .export import command_units_of
    from ..reports.mdf import write_mdf

    try:
        print(f"gearbench run: MDF4 {write_mdf(out, None, command_units_of(out))}", file=sys.stderr)
    except GearbenchError as exc:
        print(f"gearbench run: warning: no MDF4 file: {exc}", file=sys.stderr)


def _golden(db: Path, out: Path, result: dict) -> int:
    from ..fleet.golden import check_golden, format_report
    from ..station.results import write_result_json

    rep = check_golden(db, result)
    write_result_json(out / "golden.json", rep)
    print("\n".join(format_report(rep)), file=sys.stderr)
    if result["exit_code"]:
        return int(result["exit_code"])
    return 1 if rep["status"] in ("deviates", "not-judged") else 0
