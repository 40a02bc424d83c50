"""The Monte Carlo check of the window standard error (benchmarks/window_errors.py)."""
import numpy as np

from gearbench.benchmarks.window_errors import window_error_ratio


def test_window_error_matches_the_spread_of_window_means_for_white_noise():
    x = np.random.default_rng(1).normal(0.0, 0.01, 200 * 500)
    est, true, n = window_error_ratio(x, 500)
    assert n == 200 and 0.85 < est / true < 1.18


def test_a_ripple_near_a_block_length_inflates_the_window_error():
    # 15.3 Hz in 0.5 s windows of 1 kHz samples: 0.77 periods per 50 ms block of the
    # block means, which keep most of it; the tapered mean of 7.7 periods all but cancels it
    rng = np.random.default_rng(2)
    t = np.arange(200 * 500) * 1e-3
    x = rng.normal(0.0, 0.002, t.size) + 0.01 * np.sin(2 * np.pi * 15.3 * t)
    est, true, _ = window_error_ratio(x, 500)
    assert est / true > 2.0
