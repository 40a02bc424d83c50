"""The default Rerun layout for a gearbench run: readable on an operator's screen
without arranging anything.

::

    +----------------+----------------+----------------------+
    | motor in       | motor out      | Results (markdown:   |
    |  current [A]   |  current [A]   |  Kt, J, D, Tc, map,  |
    |  velocity      |  velocity      |  limits, verdict)    |
    |  command       |  command       +----------------------+
    |  position      |  position      | Efficiency map *     |
    +----------------+----------------+ Diagnosis residuals *|
    | Steps, operating points and operator prompts (log)     |
    +--------------------------------------------------------+

Each quantity has its own axis: a current of 0-3 A drawn on the axis of a
velocity of 0-300 rad/s would be a flat line, and the current is the quantity
the whole method rests on. Panels marked * appear only once they have data
(``RerunView`` sends the layout again when they do). Entity paths are the ones
``RerunView`` logs (see ``gearbench.reports.live.rerun_view``).
"""
from __future__ import annotations

from typing import Sequence

import rerun.blueprint as rrb

from .paths import DIAGNOSIS, EFFICIENCY_MAP, LOG, SUMMARY, TIMELINE, motor_path, part

# (quantity column, panel title) per motor, top to bottom
MOTOR_QUANTITIES = (("current_a", "current [A]"), ("velocity_rad_s", "velocity [rad/s]"),
                    ("command", "command (setpoint: rad/s or A by mode)"),
                    ("position_rad", "position [rad]"))


def panel_names(motors: Sequence[str] = ("in", "out"), *, efficiency: bool = False,
                diagnosis: bool = False) -> list[str]:
    """Names of the panels ``default_blueprint`` lays out (what a person sees)."""
    names = [f"motor {m}: {title}" for m in motors for _, title in MOTOR_QUANTITIES]
    names.append("Results")
    if efficiency:
        names.append(EFFICIENCY_TITLE)
    if diagnosis:
        names.append("Diagnosis residuals")
    names.append("Steps and operator")
    return names


EFFICIENCY_TITLE = "Efficiency vs output torque, per input speed (95 % intervals, limits)"


def default_blueprint(motors: Sequence[str] = ("in", "out"), *, live: bool = False,
                      efficiency: bool = False, diagnosis: bool = False) -> rrb.Blueprint:
    """Per motor one time-series view per quantity, the results panel, the efficiency
    map and diagnosis residuals when they have data, and the step/operator log; the
    time axis is the drive time base (``bench_time``), linked across the views.

    The time cursor follows the newest sample, live and in a recording alike, so the
    results panel and the map show the final state when a finished run is opened.
    ``live`` is kept for callers; it no longer changes the layout.
    """
    columns = []
    for m in motors:
        views = [rrb.TimeSeriesView(origin=f"{motor_path(m)}/{part(q)}", name=f"motor {m}: {title}",
                                    axis_x=rrb.TimeAxis(link="LinkToGlobal"), plot_legend=rrb.PlotLegend(visible=False))
                 for q, title in MOTOR_QUANTITIES]
        columns.append(rrb.Vertical(*views, name=f"motor {m}"))
    right = [rrb.TextDocumentView(origin=SUMMARY, name="Results")]
    shares = [3.0]
    if efficiency:
        right.append(rrb.Spatial2DView(origin=EFFICIENCY_MAP, name=EFFICIENCY_TITLE))
        shares.append(3.0)
    if diagnosis:
        right.append(rrb.TimeSeriesView(origin=DIAGNOSIS, name="Diagnosis residuals"))
        shares.append(1.5)
    top = rrb.Horizontal(*columns, rrb.Vertical(*right, row_shares=shares),
                         column_shares=[2.0] * len(columns) + [2.4])
    return rrb.Blueprint(
        rrb.Vertical(top, rrb.TextLogView(origin=LOG, name="Steps and operator"),
                     row_shares=[5.0, 1.0]),
        rrb.TimePanel(timeline=TIMELINE, state="collapsed", play_state="following"),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        auto_views=False,
        collapse_panels=False,
    )
