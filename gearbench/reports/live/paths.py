"""Entity paths and timelines of the gearbench recording (one place for each name).

Samples (``send_columns``, timelines ``bench_time`` and ``sample``)::

    /bench/<motor>/current_a | position_rad | velocity_rad_s   Scalars
    /bench/<motor>/command_rad_s | command_a     Scalars: the setpoint, by the step's drive mode

Events and results (logged at the bench time of the last sample seen)::

    /log                                   TextLog: run/step/operating point/operator prompts
    /results/summary                       TextDocument (markdown): parameters, map, limits, verdict
    /results/motors/<motor>                AnyValues: Kt, Kt_ci95_low, Kt_ci95_high, J_kgm2, D_nm_s_per_rad, Tc_nm
    /results/efficiency/points             AnyValues, one row per operating point
    /results/efficiency/series/<incremental|absolute>/<speed>rad_s   Scalars (%) at each point's bench time,
        with .../ci95_low, .../ci95_high (95 % interval) and .../limit_low|high (the limits)
    /results/limits/<name>                 AnyValues: value, low, high, passed
    /diagnosis/<name>                      Scalars: residuals (``RerunView.log_residuals``)
"""
from __future__ import annotations

import rerun as rr

TIMELINE = "bench_time"      # drive time base, duration (s)
SAMPLE_TIMELINE = "sample"   # drive sample counter, sequence
BENCH = "/bench"
LOG = "/log"
RESULTS = "/results"
SUMMARY = "/results/summary"
MOTORS = "/results/motors"
EFFICIENCY_POINTS = "/results/efficiency/points"
LIMITS = "/results/limits"
DIAGNOSIS = "/diagnosis"
EFFICIENCY_SERIES = "/results/efficiency/series"
# ``gearbench diagnose --rrd``: the simulation error and the noise floor that bounds it in one
# panel (same unit, rad/s), the equation error (rad/s²) in its own
DIAGNOSIS_ERROR = f"{DIAGNOSIS}/velocity"            # .../sim_error_rad_s, .../noise_floor_rad_s
DIAGNOSIS_EQUATION = f"{DIAGNOSIS}/acceleration"     # .../equation_error_rad_s2
DIAGNOSIS_TIMELINE = "time"


def efficiency_series(kind: str, speed_rad_s: float) -> str:
    """``incremental``, 100 -> ``/results/efficiency/series/incremental/100rad_s``."""
    return f"{EFFICIENCY_SERIES}/{kind}/{part(f'{speed_rad_s:g}rad_s')}"


def efficiency_limit(kind: str, side: str) -> str:
    return f"{EFFICIENCY_SERIES}/{kind}/limit_{side}"


def part(name: str) -> str:
    """One entity-path part from a free name (motor, limit, speed label)."""
    return rr.escape_entity_path_part(str(name))


def motor_path(motor: str) -> str:
    return f"{BENCH}/{part(motor)}"


def sample_path(column: str) -> str | None:
    """``in.current_a`` -> ``/bench/in/current_a``; None for a column without a motor."""
    motor, dot, quantity = column.partition(".")
    if not dot or not motor or not quantity:
        return None
    return f"{motor_path(motor)}/{part(quantity)}"
