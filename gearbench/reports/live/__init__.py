"""Live view of a run in Rerun (``--live``, ``--connect URL``, ``--rrd FILE``).

Usage in the sequencer (the view is an ordinary record subscriber)::

    view = open_live_view(live=args.live, connect=args.connect, rrd=args.rrd)
    if view is not None:
        stream.subscribe(view)      # RecordStream.close() calls view.close()

``gearbench view RESULT_DIR`` replays a finished run (``gearbench.reports.live.replay``).
"""
from .blueprint import default_blueprint
from .rerun_view import RerunView, open_live_view

__all__ = ["RerunView", "open_live_view", "default_blueprint"]
