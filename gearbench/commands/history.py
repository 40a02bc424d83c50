"""gearbench history SN: past runs of a serial, from the station or the central database."""
from __future__ import annotations

import json

NAME = "history"
HELP = "List the runs of a serial number (station database, or the central one with --central)."


def add_arguments(p) -> None:
    p.add_argument("serial", nargs="?", help="unit serial number (omit to list by the filters below)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--db", default="results/station.sqlite",
                     help="station database (default: results/station.sqlite)")
    src.add_argument("--central", metavar="URL", help="the central database postgresql://...")
    p.add_argument("--station", help="only runs of this station: its id ($GEARBENCH_STATION or the station "
                                     "config) or its bench name (the profile's bench.name, e.g. eol-station-1)")
    p.add_argument("--profile", help="only runs of this profile (its name)")
    p.add_argument("--since", help="runs started at or after this UTC date/time, e.g. 2026-11-01")
    p.add_argument("--until", help="runs started before this UTC date/time")
    p.add_argument("--verdict", choices=["passed", "failed", "fault", "aborted"])
    p.add_argument("--limit", type=int, default=None, help="at most this many runs (newest first)")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def run(args) -> int:
    from ..fleet.query import RunQuery, open_results
    from ..errors import GearbenchError

    if args.serial is None and not any((args.station, args.profile, args.since, args.until, args.verdict)):
        raise GearbenchError("give a serial number, or at least one of --station --profile "
                             "--since --until --verdict")
    q = RunQuery(serial=args.serial, station=args.station, profile=args.profile, since=args.since,
                 until=args.until, verdict=args.verdict, limit=args.limit)
    source = args.central or args.db
    with open_results(source) as db:
        runs = db.runs(q)
    if args.json:
        print(json.dumps({"serial": args.serial, "runs": runs}, default=str))
        return 0
    if not runs:
        print(f"no runs for {args.serial or 'these filters'} in {getattr(db, 'name', source)}")
        return 0
    head = ("started (UTC)", "station", "serial", "profile", "status", "ratio", "run / folder")
    rows = [(r["started_utc"] or "-", str(r["station"]), str(r["serial"]), r["profile"] or "-", str(r["status"]),
             f"{r['ratio']:.4f}" if r["ratio"] is not None else "-", f"{r['run_id']} {r['trace_uri']}")
            for r in runs]
    # columns as wide as their widest cell, two spaces apart: never run together
    widths = [max(len(x[k]) for x in [head, *rows]) for k in range(len(head) - 1)]
    print(_row(head, widths))
    for r, cells in zip(runs, rows):
        print(_row(cells, widths))
        for m in r["measurements"]:
            if m["name"].startswith("limit."):
                ok = "PASS" if m["passed"] else "FAIL"
                value = "-" if m["value"] is None else f"{m['value']:.6g}"
                print(f"    {ok} {m['name'][6:]:<40} {value}")
    return 0


def _row(cells, widths) -> str:
    """One line: every column but the last padded to its width (the ratio right-aligned)."""
    out = [c.rjust(w) if k == 5 else c.ljust(w) for k, (c, w) in enumerate(zip(cells, widths))]
    return "  ".join(out + [cells[-1]])
