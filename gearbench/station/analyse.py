"""From recorded steps to results: the sequencer's bridge to the pure analysis.

Recorded steps carry columns ``<motor>.<quantity>``; the analysis functions take
the single-motor and bench layouts. This module only re-arranges columns and
calls ``gearbench.analysis``; no numbers are computed here.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..analysis.calibration import MotorCalibration, calibrate_motor
from ..analysis.efficiency import EfficiencyResult
from ..analysis.efficiency import efficiency as _efficiency
from ..analysis.model_check import calibration_linearity, with_linearity
from .recorder import bench_trace, motor_trace
from ..errors import TraceError
from ..trace import Trace

MAX_LOST_FRACTION = 0.01   # more lost samples than this: the step is not analysed


def fill_lost_samples(step: Trace) -> Trace:
    """Put a recorded step back on its regular sample grid.

    Samples lost on the bus leave gaps in the ``sample`` counter; a sample whose SYNC went
    out late (the master caught up after a late wake-up) was taken when it arrived, off
    the grid by more than half a period — its value belongs to another instant, so it is
    treated as lost too. Up to 1 % of a step is filled by linear interpolation (the counts
    go into ``meta``) so the derivative filters stay aligned; more than that is refused,
    never hidden.
    """
    if "sample" not in step or len(step) < 2:
        return step
    idx = np.asarray(step["sample"], dtype=np.int64)
    t = np.asarray(step.time_s, dtype=float)
    per = float(np.median(np.diff(t) / np.maximum(np.diff(idx), 1)))   # the period (few are off)
    offset = float(np.median(t - idx * per))
    dev = np.abs(t - (offset + idx * per))
    # only a drive time base (index x period, exact) says a sample is off the grid; a file's
    # host timestamps jitter, and are left as they are
    on_grid = dev <= per / 2 if np.median(dev) <= 1e-6 * per else np.ones(len(t), bool)
    full = np.arange(idx[0], idx[-1] + 1)
    off = int(np.count_nonzero(~on_grid))
    missing = len(full) - len(idx) + off
    if missing == 0:
        return step
    if missing > MAX_LOST_FRACTION * len(full) or np.count_nonzero(on_grid) < 2:
        raise TraceError(f"step {step.source}: {missing} of {len(full)} samples were lost on the "
                         f"bus or sampled off the grid (SYNC sent late); check the bus load/wiring "
                         f"and the tester PC's load, and repeat the step")
    keep = on_grid
    cols = {n: np.interp(full, idx[keep], np.asarray(step[n], float)[keep])
            for n in step.names if n != "sample"}
    meta = dict(step.meta, interpolated_samples=int(missing))
    if off:
        meta["off_grid_samples"] = off
    return Trace(offset + full * per, {"sample": full, **cols}, meta, step.source)


def calibrate(unloaded: Trace, loaded: Trace, *, motor: str, disk_kgm2: float,
              method: str = "default", disk_std_kgm2: float = 0.0, disk_name: str = "",
              sampling: dict | None = None, rated_current_a: float | None = None,
              current_limit_a: float | None = None) -> MotorCalibration:
    """Kt, J, D, Tc of ``motor`` from its unloaded and disk runs (corrected eq. 17);
    ``disk_std_kgm2`` (the disk's standard uncertainty) enters Kt's uncertainty and
    ``disk_name`` records which disk (motors sharing one share its error); ``sampling``
    (the profile's ``motors.<m>.sampling``) says how the drive samples. Kt's constancy over
    the runs' currents is checked (``model_check.calibration_linearity``; the rated current
    and the drive's limit go into its message) and recorded in ``fit``."""
    fu, fl = fill_lost_samples(unloaded), fill_lost_samples(loaded)
    u, l_ = motor_trace(fu, motor), motor_trace(fl, motor)
    u.source, l_.source = f"step {unloaded.source}", f"step {loaded.source}"
    if sampling:
        # the drive's limit with its sampling: kicks are not added where it clips
        # (``identify.samples._below_current_limit``), as the analysis reads it from a trace
        limit = {} if current_limit_a is None else {"current_limit_a": float(current_limit_a)}
        u.meta["drive"] = l_.meta["drive"] = {**dict(sampling), **limit}
    cal = calibrate_motor(u, l_, disk_kgm2, method=method, disk_std_kgm2=disk_std_kgm2, disk_name=disk_name)
    lin = calibration_linearity(u, l_, kt=cal.Kt, kt_ci95=cal.Kt_ci95, motor=motor,
                                rated_current_a=rated_current_a, current_limit_a=current_limit_a)
    cal = replace(cal, fit=with_linearity(cal.fit, lin))
    # interpolated samples are stated with the result they entered (positions: result.json lost_at_sample)
    filled = fu.meta.get("interpolated_samples", 0) + fl.meta.get("interpolated_samples", 0)
    return replace(cal, motor=motor, interpolated_samples=filled)


def efficiency(step: Trace, motor_in: MotorCalibration, motor_out: MotorCalibration, *,
               ratio: float | None, settle_s: float, speed_setpoint_rad_s: float,
               skip_samples: int = 0, windows: list[tuple[int, int]] | None = None,
               incremental: str = "auto", inertia_corrected: bool = False,
               ripple_corrected: bool = False) -> EfficiencyResult:
    """Efficiency points of one recorded efficiency segment (eq. 18 and P_out/P_in), each
    stamped with the commanded speed. ``windows``: the steady ranges as drive
    sample-counter values [first, last) (an adaptive run's settled levels); they survive
    filled-in lost samples. ``inertia_corrected``: window means of the currents less each
    rotor's inertial part (as the adaptive staircase stopped on them); ``ripple_corrected``:
    the input current less its speed loop's quantisation ripple (a drive that samples its
    current at one instant, ``ripple.ripple_corrected_current``)."""
    filled = fill_lost_samples(step)
    trimmed = filled.slice(skip_samples, None)
    ranges = None
    if windows is not None:
        counter = np.asarray(trimmed["sample"], dtype=np.int64)
        ranges = [(int(np.searchsorted(counter, a)), int(np.searchsorted(counter, b))) for a, b in windows]
    bench = bench_trace(trimmed)
    bench.source = f"step {step.source}"
    res = _efficiency(bench, motor_in, motor_out, ratio=ratio, settle_s=settle_s, windows=ranges,
                      incremental=incremental, inertia_corrected=inertia_corrected,
                      ripple_corrected=ripple_corrected)
    n_filled = filled.meta.get("interpolated_samples", 0)
    return replace(res, points=tuple(replace(p, speed_setpoint_rad_s=speed_setpoint_rad_s,
                                             interpolated_samples=n_filled) for p in res.points))
