"""The speed loop's quantisation ripple in an instant-sampled current (analysis.ripple):
against the simulator's own truth, the same run with the drive reporting its period mean."""
from dataclasses import replace

import numpy as np
import pytest

from gearbench.analysis.efficiency import efficiency
from gearbench.analysis.ripple import ripple_corrected_current
from gearbench.analysis.windows import taper
from gearbench.benchmarks.robustness import draw_case
from gearbench.errors import TraceError
from gearbench.sim import simulate_motor

from test_efficiency import M_IN, M_OUT, hand_bench


def _level_errors(motor, speeds, *, n=2000, level=500):
    """Tapered means of the last ``level`` samples at each held speed, raw and corrected,
    less the same run's period-mean current (same seed: the same motion), in A."""
    raw, cor = [], []
    for k, w in enumerate(speeds):
        cmd = np.minimum(np.arange(n) * 1e-3 * 2000.0, w)          # ramp, then hold
        inst = simulate_motor(motor, cmd, seed=k, period_s=1e-3)
        mean = simulate_motor(replace(motor, current_avg_s=1e-3), cmd, seed=k, period_s=1e-3)
        cur, _ = ripple_corrected_current(inst["current_a"], inst["velocity_rad_s"],
                                          inst["position_rad"], 1e-3)
        wts = taper(level)
        m = lambda x: float(np.sum(wts * x[-level:]) / np.sum(wts))   # noqa: E731
        truth = m(mean["current_a"])
        raw.append(m(inst["current_a"]) - truth)
        cor.append(m(cur) - truth)
    return np.sqrt(np.mean(np.square(raw))), np.sqrt(np.mean(np.square(cor)))


@pytest.mark.parametrize("seed,index", [(0, 1), (0, 14)])
def test_correction_brings_level_means_to_the_period_mean(seed, index):
    # drawn drives with a stiff speed loop (Kp 0.13 and 0.07 A s/rad, 2566 and 3759 counts):
    # ripple of tens of mA in every sample (measured: level-mean error rms 0.74 -> 0.36 mA
    # and 0.27 -> 0.13 mA over these speeds). Only for such drives: a period-mean drive's
    # samples hold the ripple's mean, real current, which the correction would move (0.36 mA)
    motor = draw_case(index, seed).plant.motor_in
    assert motor.current_avg_s == 0.0
    raw, cor = _level_errors(motor, np.linspace(90.0, 290.0, 8))
    assert cor < 0.7 * raw, (raw, cor)


def test_needs_the_drive_speed_column():
    trace, _, _ = hand_bench()
    with pytest.raises(TraceError, match="in_velocity_rad_s"):
        efficiency(trace, M_IN, M_OUT, ripple_corrected=True)
