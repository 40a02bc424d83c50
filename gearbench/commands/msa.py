"""gearbench msa: measurement-system analysis (gauge R&R, AIAG MSA 4th ed.) of the tester."""
from __future__ import annotations

import functools
import json
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

from ..errors import GearbenchError

NAME = "msa"
HELP = ("Gauge R&R of the tester (AIAG MSA 4th ed.): efficiency per operating point across units, "
        "stations and repeats; Kt repeatability and bias per station motor. From simulated runs "
        "(PROFILE --sim) or from station databases (--db).")


def add_arguments(p) -> None:
    p.add_argument("profile", nargs="?", help="test profile YAML to run the study with (with --sim)")
    p.add_argument("--sim", action="store_true",
                   help="run the study on simulated units and stations (each run through the normal "
                        "run chain, emulated drives behind real CANopen/Modbus)")
    p.add_argument("--units", type=int, default=10, help="--sim: simulated units (parts), default 10")
    p.add_argument("--repeats", type=int, default=None,
                   help="trials per unit and station (--sim default 3; with --db: use the first N runs "
                        "of each serial on each station)")
    p.add_argument("--stations", type=int, default=2, help="--sim: simulated stations, default 2")
    p.add_argument("--seed", type=int, default=1, help="--sim: seed of the unit/station spreads and noise")
    p.add_argument("--out", help="--sim: study folder (default results/msa-<UTC time>)")
    p.add_argument("--db", action="append", metavar="PATH",
                   help="station database(s) to read runs from (repeat once per station; serial = part, "
                        "station = appraiser, repeated runs of a serial = trials), or a postgresql:// URL")
    p.add_argument("--profile", dest="profile_name", metavar="NAME",
                   help="--db: only runs of this profile name")
    p.add_argument("--alpha", type=float, default=0.05,
                   help="significance level of the part×station interaction test (AIAG: 0.05)")
    p.add_argument("--json", action="store_true", help="print the study as JSON")


def run(args) -> int:
    from ..fleet.gauge_study import check_design, format_table, read_databases, run_sim_study, select_runs, study

    if not 0 < args.alpha < 1:
        raise GearbenchError(f"--alpha {args.alpha}: a significance level between 0 and 1, e.g. 0.05")
    if args.sim:
        if not args.profile:
            raise GearbenchError("--sim needs a profile: gearbench msa profiles/cvt.yaml --sim")
        if args.db:
            raise GearbenchError("--sim makes its own station databases; drop --db (or drop --sim to "
                                 "study existing runs)")
        repeats = 3 if args.repeats is None else args.repeats
        check_design(args.units, repeats, args.stations)
        stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ")
        out = Path(args.out or f"results/msa-{stamp}")
        t0 = time.monotonic()
        print(f"gearbench msa: {args.units} units × {args.stations} stations × {repeats} trials = "
              f"{args.units * args.stations * repeats} simulated runs into {out}", file=sys.stderr)
        from ..api import AutoOperator, run_profile

        runner = functools.partial(run_profile, operator=AutoOperator())
        dbs = run_sim_study(args.profile, runner, units=args.units, repeats=repeats, stations=args.stations,
                            out_dir=out, seed=args.seed)
        print(f"gearbench msa: runs done in {time.monotonic() - t0:.0f} s wall", file=sys.stderr)
        runs = read_databases(dbs)
        name = None
    else:
        if not args.db:
            raise GearbenchError("no runs to study: give --db STATION.sqlite (once per station) for runs "
                                 "of real benches, or PROFILE --sim for a simulated study")
        if args.profile:
            raise GearbenchError(f"'{args.profile}': a profile file is only used with --sim; with --db "
                                 f"select runs by profile name with --profile NAME")
        runs = read_databases(args.db)
        repeats, name = args.repeats, args.profile_name
        if repeats is not None and repeats < 2:
            raise GearbenchError(f"--repeats {repeats}: need at least 2 trials for repeatability")
    source = ", ".join(args.db) if args.db else "simulated study"
    used, left = select_runs(runs, profile=name, repeats=repeats, source=source)
    rep = study(used, alpha=args.alpha, source=source)
    rep["left_out"] = left
    if args.sim:
        rep["databases"] = dbs
    if args.json:
        print(json.dumps(rep, indent=1, default=str))
    else:
        print(format_table(rep))
        if left:
            print(f"{len(left)} run(s) left out: " + "; ".join(
                f"{x['serial']} at {x['station']} ({x['why']})" for x in left[:5]) +
                (" ..." if len(left) > 5 else ""))
    return 0 if rep["verdict"] in (None, "acceptable") else 1
