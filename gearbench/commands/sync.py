"""gearbench sync: push the station's pending runs to the central database."""
from __future__ import annotations

NAME = "sync"
HELP = "Push runs waiting in the station database (the outbox) to the central database."


def add_arguments(p) -> None:
    p.add_argument("--db", default="results/station.sqlite",
                   help="station database (default: results/station.sqlite)")
    p.add_argument("--to", metavar="URL", help="central database postgresql://... "
                   "(default: $GEARBENCH_CENTRAL, else central: in the station config)")


def run(args) -> int:
    import sys
    from pathlib import Path

    from ..station.config import central_url
    from ..fleet.push import push_pending
    from ..errors import GearbenchError

    db = Path(args.db)
    if not db.exists():
        raise GearbenchError(f"{db}: no station database here; pass --db PATH")
    url = central_url(args.to, db)
    if not url:
        raise GearbenchError("no central database: pass --to postgresql://USER@HOST/DB, set "
                             "GEARBENCH_CENTRAL, or put central: in the station config")
    rep = push_pending(db, url)
    print(f"{rep.target}: {rep.pushed} run(s) pushed, {rep.already} already there, "
          f"{rep.pending} pending")
    for run_id, why in rep.failed_runs.items():
        print(f"  run {run_id} refused: {why}")
    if rep.error:
        print(f"gearbench sync: error: {rep.error}; {rep.pending} run(s) stay in the outbox, "
              f"run sync again later", file=sys.stderr)
        return 3
    return 0 if rep.ok else 1
