"""The default Rerun layout for a gearbench run: readable on an operator's screen
without arranging anything.

::

    +----------------+----------------+----------------------+
    | motor in       | motor out      | Results (markdown:   |
    |  current [A]   |  current [A]   |  verdict, limits,    |
    |  velocity      |  velocity      |  Kt, J, D, Tc, map)  |
    |  cmd [rad/s]   |  cmd [rad/s]   |                      |
    |                |  cmd [A]       | Diagnosis residuals *|
    |  position      |  position      |                      |
    +----------------+----------------+----------------------+
    | incremental efficiency [%] *    | absolute efficiency *|
    +---------------------------------+----------------------+
    | Steps, operating points and operator prompts (log)     |
    +--------------------------------------------------------+

Each quantity has its own axis, and so has each setpoint unit: a current of 0-3 A
drawn on the axis of a velocity of 0-300 rad/s would be a flat line (the output
motor's braking staircase in A beside its calibration speeds in rad/s). The
efficiency panels are Rerun's own series (each point at its bench time, one series
per input speed, its 95 % interval and the limits): live and zoomable, their time
axis linked to the motors'. Panels marked * appear only once they have data
(``RerunView`` sends the layout again when they do). Entity paths are the ones
``RerunView`` logs (``gearbench.reports.live.paths``).
"""
from __future__ import annotations

from typing import Mapping, Sequence

import rerun.blueprint as rrb

from .paths import (DIAGNOSIS, DIAGNOSIS_EQUATION, DIAGNOSIS_ERROR, DIAGNOSIS_TIMELINE, EFFICIENCY_SERIES, LOG,
                    SUMMARY, TIMELINE, motor_path, part)

# (quantity column, panel title) per motor, top to bottom; the setpoint panels go after
# the velocity, one per unit the motor is commanded in
MOTOR_QUANTITIES = (("current_a", "current [A]"), ("velocity_rad_s", "velocity [rad/s]"),
                    ("position_rad", "position [rad]"))
COMMAND_TITLES = {"rad_s": ("command_rad_s", "speed command [rad/s]"),
                  "a": ("command_a", "current command [A]")}
EFFICIENCY_TITLES = {"incremental": "Incremental efficiency [%] (eq. 18, 95 % intervals, limits)",
                     "absolute": "Absolute efficiency [%] (P_out / P_in, 95 % intervals, limits)"}
EFFICIENCY_TITLE = EFFICIENCY_TITLES["incremental"]


def _quantities(motor: str, commands: Mapping[str, Sequence[str]] | None) -> list[tuple[str, str]]:
    units = list((commands or {}).get(motor) or ["rad_s"])
    cmd = [COMMAND_TITLES[u] for u in units if u in COMMAND_TITLES]
    return [MOTOR_QUANTITIES[0], MOTOR_QUANTITIES[1], *cmd, MOTOR_QUANTITIES[2]]


def panel_names(motors: Sequence[str] = ("in", "out"), *, efficiency: bool = False,
                diagnosis: bool = False, commands: Mapping[str, Sequence[str]] | None = None) -> list[str]:
    """Names of the panels ``default_blueprint`` lays out (what a person sees)."""
    names = [f"motor {m}: {title}" for m in motors for _, title in _quantities(m, commands)]
    names.append("Results")
    if diagnosis:
        names.append("Diagnosis residuals")
    if efficiency:
        names += [EFFICIENCY_TITLES["incremental"], EFFICIENCY_TITLES["absolute"]]
    names.append("Steps and operator")
    return names


def default_blueprint(motors: Sequence[str] = ("in", "out"), *, live: bool = False,
                      efficiency: bool = False, diagnosis: bool = False,
                      commands: Mapping[str, Sequence[str]] | None = None) -> rrb.Blueprint:
    """Per motor one time-series view per quantity and per setpoint unit (``commands``:
    motor -> ["rad_s", "a"]), the results panel, the efficiency series and diagnosis
    residuals when they have data, and the step/operator log; the time axis is the drive
    time base (``bench_time``), linked across the views.

    The time cursor follows the newest sample, live and in a recording alike; the final
    results panel is also logged static, so a finished recording shows it at once.
    ``live`` is kept for callers; it no longer changes the layout.
    """
    columns = []
    for m in motors:
        views = [rrb.TimeSeriesView(origin=f"{motor_path(m)}/{part(q)}", name=f"motor {m}: {title}",
                                    axis_x=rrb.TimeAxis(link="LinkToGlobal"), plot_legend=rrb.PlotLegend(visible=False))
                 for q, title in _quantities(m, commands)]
        columns.append(rrb.Vertical(*views, name=f"motor {m}"))
    right = [rrb.TextDocumentView(origin=SUMMARY, name="Results")]
    shares = [3.0]
    if diagnosis:
        right.append(rrb.TimeSeriesView(origin=DIAGNOSIS, name="Diagnosis residuals"))
        shares.append(1.5)
    top = rrb.Horizontal(*columns, rrb.Vertical(*right, row_shares=shares),
                         column_shares=[2.0] * len(columns) + [2.4])
    rows, row_shares = [top], [5.0]
    if efficiency:
        rows.append(rrb.Horizontal(*[
            rrb.TimeSeriesView(origin=f"{EFFICIENCY_SERIES}/{kind}", name=title,
                               axis_x=rrb.TimeAxis(link="LinkToGlobal"),
                               plot_legend=rrb.PlotLegend(corner="RightBottom", visible=True))
            for kind, title in EFFICIENCY_TITLES.items()]))
        row_shares.append(2.4)
    rows.append(rrb.TextLogView(origin=LOG, name="Steps and operator"))
    row_shares.append(2.2)     # a few lines of the step log, not one
    return rrb.Blueprint(
        rrb.Vertical(*rows, row_shares=row_shares),
        rrb.TimePanel(timeline=TIMELINE, state="collapsed", play_state="following"),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        auto_views=False,
        collapse_panels=False,
    )


def diagnosis_blueprint() -> rrb.Blueprint:
    """The layout of ``gearbench diagnose --rrd``: the simulation error with the noise floor
    that bounds it on one axis (both rad/s, under ``paths.DIAGNOSIS_ERROR``), the equation
    error on its own (rad/s², ``paths.DIAGNOSIS_EQUATION``); legends on, the time axes linked."""
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.TimeSeriesView(origin=DIAGNOSIS_ERROR, name="Simulation error and noise floor [rad/s]",
                               axis_x=rrb.TimeAxis(link="LinkToGlobal"), plot_legend=rrb.PlotLegend(visible=True)),
            rrb.TimeSeriesView(origin=DIAGNOSIS_EQUATION, name="Equation error [rad/s²]",
                               axis_x=rrb.TimeAxis(link="LinkToGlobal"), plot_legend=rrb.PlotLegend(visible=True)),
            row_shares=[3.0, 2.0]),
        rrb.TimePanel(timeline=DIAGNOSIS_TIMELINE, state="collapsed"),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        auto_views=False,
        collapse_panels=False,
    )
