"""gearbench spc: tester health by statistical process control."""
from __future__ import annotations

import json
from pathlib import Path

NAME = "spc"
HELP = ("Control charts (individuals / moving range, Western Electric and Nelson rules) of the "
        "station motors' Kt, J, friction, reference units' ratio and unit efficiency per point.")


def add_arguments(p) -> None:
    src = p.add_mutually_exclusive_group()
    src.add_argument("--db", default="results/station.sqlite",
                     help="station database (default: results/station.sqlite)")
    src.add_argument("--central", metavar="URL", help="the central database postgresql://...")
    p.add_argument("--station", help="only this station (default: each station, charted apart)")
    p.add_argument("--quantity", action="append", metavar="PATTERN",
                   help="quantities to chart, fnmatch patterns (repeatable), e.g. 'motors.*.Kt', "
                        "'ratio@*', '*eta_incremental' (default: all)")
    p.add_argument("--profile", help="only runs of this profile")
    p.add_argument("--since", help="runs started at or after this UTC date/time")
    p.add_argument("--until", help="runs started before this UTC date/time")
    p.add_argument("--baseline", type=int, default=None,
                   help="runs that set the control limits (the first N; default 30)")
    p.add_argument("--rules", default=None,
                   help="rules to flag, comma separated from 1,2,3,4,5,MR (default: all)")
    p.add_argument("--png", default="spc.png",
                   help="chart image (default spc.png; one file per station: spc-<station>.png "
                        "when several)")
    p.add_argument("--json", action="store_true", help="print the charts and flags as JSON")


def run(args) -> int:
    from ..analysis.spc import RULES
    from ..fleet.query import RunQuery, open_results
    from ..fleet.control_charts import charts, require_charts, write_png

    source = args.central or args.db
    q = RunQuery(station=args.station, profile=args.profile, since=args.since, until=args.until,
                 newest_first=False)
    with open_results(source) as db:
        runs = db.runs(q, with_result=True)
    rules = tuple(r.strip() for r in args.rules.split(",")) if args.rules else None
    found = charts(runs, args.quantity, baseline=args.baseline, rules=rules)
    require_charts(found, str(getattr(db, "name", source)))
    stations = sorted({s for s, _, _ in found})
    pngs = {}
    for st in stations:
        path = Path(args.png)
        if len(stations) > 1:
            path = path.with_name(f"{path.stem}-{st}{path.suffix or '.png'}")
        write_png(path, st, [f for f in found if f[0] == st])
        pngs[st] = str(path)
    flagged = sum(len(c.flags) for _, c, _ in found)
    if args.json:
        print(json.dumps([dict(station=s, quantity=c.quantity, n=len(c.values), center=c.center,
                               sigma=c.sigma, ucl=c.ucl, lcl=c.lcl, mr_ucl=c.mr_ucl, baseline=c.baseline_n,
                               png=pngs[s],
                               flags=[dict(index=i, rules=r, value=float(c.values[i]), run_id=runs_[i]["run_id"],
                                           serial=runs_[i]["serial"], started_utc=runs_[i]["started_utc"])
                                      for i, r in c.flags.items()])
                          for s, c, runs_ in found]))
        return 1 if flagged else 0
    for s, c, runs_ in found:
        state = "in control" if c.in_control else f"{len(c.flags)} FLAGGED"
        print(f"{s:<16}{c.quantity:<52} n={len(c.values):<5} centre {c.center:<11.5g} "
              f"limits [{c.lcl:.5g}, {c.ucl:.5g}]  {state}")
        for i, r in list(c.flags.items())[:10]:
            run = runs_[i]
            print(f"    run {i + 1:>4} {run['started_utc']} {run['serial']:<12} {c.values[i]:.6g}  "
                  + "; ".join(f"rule {x}: {RULES[x]}" for x in r))
        if len(c.flags) > 10:
            print(f"    ... {len(c.flags) - 10} more flagged points (--json lists all)")
    print(f"charts: {', '.join(pngs.values())}")
    return 1 if flagged else 0
