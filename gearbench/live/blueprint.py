"""The default Rerun layout for a gearbench run: readable on an operator's screen
without arranging anything.

::

    +-----------------------------+----------------------+
    | motor in  (current, position,| Results (markdown:   |
    |   velocity, command)         |  Kt, J, D, Tc, map,  |
    +------------------------------+  limits, verdict)    |
    | motor out                    +----------------------+
    |                              | Efficiency map       |
    +------------------------------+----------------------+
    | Steps, operating points and operator prompts (log)  |
    +-----------------------------------------------------+

Entity paths are the ones ``RerunView`` logs (see ``gearbench.live.rerun_view``).
"""
from __future__ import annotations

from typing import Sequence

import rerun.blueprint as rrb

from .paths import DIAGNOSIS, EFFICIENCY_MAP, LOG, SUMMARY, TIMELINE, motor_path


def default_blueprint(motors: Sequence[str] = ("in", "out"), *,
                      live: bool = False) -> rrb.Blueprint:
    """One time-series view per motor, the efficiency map, a results panel and the
    step/operator log; the time panel shows the drive time base (``bench_time``).

    ``live`` makes the time cursor follow the newest sample.
    """
    motor_views = [rrb.TimeSeriesView(origin=motor_path(m), name=f"motor {m}")
                   for m in motors]
    motor_views.append(rrb.TimeSeriesView(origin=DIAGNOSIS, name="diagnosis residuals"))
    # Residuals are optional: a small share so an empty view does not waste space.
    shares = [3.0] * len(motors) + [1.0]
    right = rrb.Vertical(
        rrb.TextDocumentView(origin=SUMMARY, name="Results"),
        rrb.BarChartView(origin=EFFICIENCY_MAP, name="Efficiency map: η_inc [%] vs output torque [N·m], per input speed"),
        row_shares=[3.0, 2.0])
    top = rrb.Horizontal(rrb.Vertical(*motor_views, row_shares=shares), right,
                         column_shares=[3.0, 2.0])
    return rrb.Blueprint(
        rrb.Vertical(top, rrb.TextLogView(origin=LOG, name="Steps and operator"),
                     row_shares=[5.0, 1.0]),
        rrb.TimePanel(timeline=TIMELINE, state="collapsed",
                      play_state="following" if live else None),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        auto_views=False,
        collapse_panels=False,
    )
