"""gearbench view RESULT_DIR: replay a finished run into Rerun (viewer or .rrd)."""
from __future__ import annotations

import io
import sys

from ..errors import GearbenchError

NAME = "view"
HELP = "Replay a finished run folder (traces + result.json) in the Rerun viewer or to an .rrd."


def add_arguments(p) -> None:
    p.add_argument("result_dir", metavar="RESULT_DIR", help="output folder of 'gearbench run'")
    p.add_argument("--rrd", help="write the recording to this .rrd file")
    p.add_argument("--live", action="store_true",
                   help="open a Rerun viewer (default when neither --rrd nor --connect is given)")
    p.add_argument("--connect", help="send to a Rerun viewer at this URL "
                                     "(e.g. rerun+http://127.0.0.1:9876/proxy)")


def run(args) -> int:
    from ..live import open_live_view
    from ..live.replay import replay_records

    live = args.live or not (args.rrd or args.connect)
    records = replay_records(args.result_dir)
    first = next(records)  # checks the folder before anything is opened
    notice = io.StringIO()
    view = open_live_view(live=live, connect=args.connect, rrd=args.rrd, stderr=notice)
    if view is None:
        raise GearbenchError(f"{notice.getvalue().strip() or 'no viewer'}; "
                             f"pass --rrd FILE to write a recording instead")
    if notice.getvalue():
        sys.stderr.write(notice.getvalue())
    try:
        view(first)
        n = _feed(records, view)
    finally:
        view.close()
    where = ", ".join(x for x in (args.rrd and f"wrote {args.rrd}",
                                  args.connect and f"sent to {args.connect}") if x) or "sent to viewer"
    print(f"gearbench view: {n} samples replayed from {args.result_dir}; {where}")
    return 0


def _feed(records, view) -> int:
    n = 0
    for record in records:
        view(record)
        n += len(getattr(record, "sample", ()))
    return n
