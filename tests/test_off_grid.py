"""A sample whose SYNC went out late was taken when it arrived, not on the grid: the
analysis treats it as lost (interpolated within 1 %, refused beyond), never as on time."""
import numpy as np
import pytest

from gearbench.errors import TraceError
from gearbench.station.analyse import fill_lost_samples
from gearbench.trace import Trace


def _step(n=4000, period=1e-3):
    idx = np.arange(n)
    t = idx * period
    pos = 300.0 * t                       # 300 rad/s: a 5 ms late sample is 1.5 rad off
    return idx, t, pos


def test_a_burst_sent_late_is_taken_out_and_filled_from_its_neighbours():
    idx, t, pos = _step()
    t, pos = t.copy(), pos.copy()
    burst = np.arange(1000, 1006)         # six SYNCs sent together, 5..0 ms behind
    sent = t[burst[-1]] + 0.0002
    t[burst[:-1]] = sent
    pos[burst[:-1]] = 300.0 * sent        # the drives sampled when the SYNC arrived
    out = fill_lost_samples(Trace(t, {"sample": idx, "in.position_rad": pos}, {}, "burst"))
    assert out.meta["off_grid_samples"] == 5 and out.meta["interpolated_samples"] == 5
    np.testing.assert_allclose(out.time_s, idx * 1e-3, atol=1e-12)
    np.testing.assert_allclose(out["in.position_rad"], 300.0 * idx * 1e-3, atol=1e-9)
    # stamped on the grid instead (what the master did before), the same samples are 1.5 rad off
    assert np.max(np.abs(pos - 300.0 * idx * 1e-3)) > 1.0


def test_too_many_samples_off_the_grid_are_refused():
    idx, t, pos = _step()
    t = t.copy()
    t[1000:1100] += 0.003
    with pytest.raises(TraceError, match="off the grid"):
        fill_lost_samples(Trace(t, {"sample": idx, "in.position_rad": pos}, {}, "stall"))


def test_host_timestamps_that_jitter_are_left_alone():
    idx, t, pos = _step()
    t = t + np.random.default_rng(0).normal(0, 3e-4, len(t))
    step = Trace(t, {"sample": idx, "in.position_rad": pos}, {}, "host clock")
    assert fill_lost_samples(step) is step
