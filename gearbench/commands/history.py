"""gearbench history SN: past runs of a serial from the station database."""
from __future__ import annotations

import json
from pathlib import Path

from ..errors import GearbenchError

NAME = "history"
HELP = "List the runs of a serial number from the station database."


def add_arguments(p) -> None:
    p.add_argument("serial", help="unit serial number")
    p.add_argument("--db", default="results/station.sqlite",
                   help="station database (default: results/station.sqlite)")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def run(args) -> int:
    from ..station_db import history

    db = Path(args.db)
    if not db.exists():
        raise GearbenchError(f"{db}: no station database here; pass --db PATH "
                             f"(gearbench run writes it next to its output folder)")
    runs = history(db, args.serial)
    if args.json:
        print(json.dumps({"serial": args.serial, "runs": runs}, default=str))
        return 0
    if not runs:
        print(f"no runs for serial {args.serial} in {db}")
        return 0
    print(f"{'started (UTC)':<30}{'profile':<14}{'status':<9}{'ratio':>9}  run / folder")
    for r in runs:
        ratio = f"{r['ratio']:.4f}" if r["ratio"] is not None else "-"
        print(f"{r['started_utc']:<30}{r['profile']:<14}{r['status']:<9}{ratio:>9}  "
              f"{r['run_id']} {r['out_dir']}")
        for m in r["measurements"]:
            if m["name"].startswith("limit."):
                ok = "PASS" if m["passed"] else "FAIL"
                print(f"    {ok} {m['name'][6:]:<40} {m['value']}")
    return 0
