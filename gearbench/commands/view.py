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
    p.add_argument("--no-report", action="store_true",
                   help="do not open the run's report.html in the browser (opened when a display exists)")


def run(args) -> int:
    from ..reports.live import open_live_view
    from ..reports.live.rerun_view import check_connect_url
    from ..reports.live.replay import replay_records

    check_connect_url(args.connect)
    live = args.live or not (args.rrd or args.connect)
    records = replay_records(args.result_dir)
    first = next(records)  # checks the folder before anything is opened
    notice = io.StringIO()
    view = open_live_view(live=live, connect=args.connect, rrd=args.rrd, stderr=notice, fallback="")
    if view is None:
        why = notice.getvalue().strip().removeprefix("gearbench: live view: ") or "no viewer"
        raise GearbenchError(f"{why}; pass --rrd FILE to write a recording (open it later with "
                             f"'rerun FILE'), or --connect rerun+http://HOST:9876/proxy")
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
    if live and not args.no_report:
        _open_report(args.result_dir)
    return 0


def _open_report(run_dir) -> None:
    """The run's report.html (made now if missing) in the browser, where there is a display."""
    import os
    import webbrowser

    from ..reports.unit_report import write_report

    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return   # no display: the viewer notice already said so
    try:
        from pathlib import Path

        report = Path(run_dir) / "report.html"
        if not report.exists():
            report = write_report(run_dir)
        if webbrowser.open(report.resolve().as_uri()):
            print(f"gearbench view: opened {report}")
    except (GearbenchError, OSError, webbrowser.Error) as exc:
        print(f"gearbench view: report not opened ({exc})", file=sys.stderr)


def _feed(records, view) -> int:
    n = 0
    for record in records:
        view(record)
        n += len(getattr(record, "sample", ()))
    return n
