"""The speed loop's quantisation ripple in an instant-sampled current, in the calibration.

A drive whose speed loop differentiates encoder counts puts the count quantum's error on
its speed estimate, and its P gain turns that into current. A drive that reports one
current-loop instant (not the period mean) passes that ripple on, aliased into the fit
band, where it correlates with the motion: Kt came out 0.2–0.5 % off on noise-free
forward runs of random plants. The drive also reports the speed it acted on; the ripple's
regressor (``identify.SPEED_ERR``) with one gain shared by both runs takes it out.
"""
from dataclasses import replace

import pytest

from gearbench.analysis.calibration import calibrate_motor
from gearbench.analysis.identify import SPEED_ERR
from gearbench.benchmarks import robustness as rb
from gearbench.sim import simulate_motor

# forward plants of the robustness draw whose noise-free Kt the ripple moved by > 0.2 %
CASES = [(7, 16, "in"), (8, 63, "out"), (7, 46, "out")]


def _runs(seed, index, side, **change):
    case = rb.draw_case(index, seed, duration_s=3.0, dwell_s=4.0)
    motor = replace(getattr(case.plant, f"motor_{side}"), current_noise_a=0.0, **change)
    s = case.seed + (0 if side == "in" else 10)
    runs = [simulate_motor(motor, case.commands[side], disk_kgm2=d, seed=s + k,
                           period_s=rb.PERIOD_S)
            for k, d in enumerate((0.0, case.disks_kgm2[side]))]
    for t in runs:
        t.meta["drive"] = rb.drive_description(motor)
    return motor, runs, case.disks_kgm2[side]


@pytest.mark.parametrize("seed,index,side", CASES)
def test_the_ripple_term_takes_the_aliased_ripple_out_of_kt(seed, index, side):
    motor, runs, disk = _runs(seed, index, side)
    assert runs[0].meta["drive"]["current"] == "instant"
    without = calibrate_motor(*runs, disk, speed_error=False, model_variants=False)
    with_term = calibrate_motor(*runs, disk, model_variants=False)
    err_without = abs(without.Kt / motor.Kt - 1)
    err_with = abs(with_term.Kt / motor.Kt - 1)
    assert err_without > 0.002                 # the ripple's bias, noise-free
    assert err_with < 0.001
    assert with_term.fit["speed_error"]["coefficient_a_s_per_rad"] < 0   # −Kp-like: e raises v, lowers i
    # the same plant whose drive reports the period mean has no such bias and no term
    motor_mean, runs_mean, _ = _runs(seed, index, side, current_avg_s=rb.PERIOD_S)
    mean = calibrate_motor(*runs_mean, disk, model_variants=False)
    assert "speed_error" not in mean.fit
    assert abs(mean.Kt / motor_mean.Kt - 1) < 0.001


def test_a_fine_encoder_shows_the_cause():
    """With a 2^24-count encoder the drive's speed estimate has no quantum: no bias to take out."""
    motor, runs, disk = _runs(7, 16, "in", counts_per_rev=2 ** 24)
    without = calibrate_motor(*runs, disk, speed_error=False, model_variants=False)
    assert abs(without.Kt / motor.Kt - 1) < 0.0005


def test_reversing_runs_and_mixed_pairs_leave_the_term_out():
    case = next(c for c in (rb.draw_case(k, 7, duration_s=3.0, dwell_s=4.0) for k in range(40))
                if c.reversing and c.plant.motor_in.current_avg_s == 0.0)
    motor = case.plant.motor_in
    runs = [simulate_motor(motor, case.commands["in"], disk_kgm2=d, seed=case.seed + k,
                           period_s=rb.PERIOD_S)
            for k, d in enumerate((0.0, case.disks_kgm2["in"]))]
    for t in runs:
        t.meta["drive"] = rb.drive_description(motor)
    cal = calibrate_motor(*runs, case.disks_kgm2["in"], model_variants=False)
    assert "speed_error" not in cal.fit
    assert SPEED_ERR not in cal.fit["unloaded"]["params"]
