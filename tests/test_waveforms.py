"""Command waveforms: shapes, amplitudes, spectra, PRBS properties, profile parsing."""
from __future__ import annotations

import numpy as np
import pytest

from gearbench.errors import ProfileError
from gearbench.sim import waveforms as wf


def test_time_base():
    t = wf.time_base(1.5, 1e-3)
    assert t.size == 1500 and t[0] == 0 and t[-1] == pytest.approx(1.499)
    with pytest.raises(ProfileError):
        wf.time_base(0.0)


def test_step_and_staircase():
    t = wf.time_base(1.0)
    y = wf.step(t, amplitude=100.0, t_step_s=0.25, offset=5.0)
    assert y[249] == 5.0 and y[250] == 105.0 and y[-1] == 105.0
    s = wf.staircase(t, levels=[0.0, -0.5, -1.0], dwell_s=0.3)
    assert s[0] == 0.0 and s[299] == 0.0 and s[300] == -0.5 and s[600] == -1.0 and s[-1] == -1.0
    with pytest.raises(ProfileError):
        wf.staircase(t, levels=[], dwell_s=0.3)


def test_ramp_and_trapezoid():
    t = wf.time_base(2.0)
    r = wf.ramp(t, slope=100.0, t0_s=0.5, final=80.0)
    assert r[500] == 0.0 and r[900] == pytest.approx(40.0) and r[-1] == 80.0
    z = wf.trapezoid(t, amplitude=50.0, ramp_s=0.2, hold_s=0.3, repeat_s=1.0)
    assert z[0] == 0.0 and z[100] == pytest.approx(25.0) and z[300] == 50.0
    assert z[600] == pytest.approx(25.0) and z[800] == 0.0 and z[1300] == 50.0
    with pytest.raises(ProfileError):
        wf.trapezoid(t, amplitude=1.0, ramp_s=0.5, hold_s=0.5, repeat_s=1.0)


def test_multisine_peak_and_spectrum():
    t = wf.time_base(10.0)
    freqs = [1.0, 3.0, 7.0, 13.0]
    y = wf.multisine(t, amplitude=40.0, offset=100.0, freqs_hz=freqs)
    assert np.abs(y - 100.0).max() == pytest.approx(40.0)
    spec = np.abs(np.fft.rfft(y - y.mean()))
    f = np.fft.rfftfreq(t.size, 1e-3)
    top = sorted(f[np.argsort(spec)[-4:]])
    assert top == pytest.approx(freqs)
    rnd = wf.multisine(t, amplitude=1.0, freqs_hz=freqs, phases="random", seed=3)
    assert np.abs(rnd).max() == pytest.approx(1.0)
    assert not np.allclose(rnd, (y - 100.0) / 40.0)
    with pytest.raises(ProfileError):
        wf.multisine(t, amplitude=1.0, freqs_hz=[-1.0])


def test_chirp_frequency_sweeps():
    t = wf.time_base(4.0)
    y = wf.chirp(t, amplitude=1.0, f0_hz=1.0, f1_hz=20.0)
    crossings = np.flatnonzero(np.diff(np.signbit(y)))
    early = np.sum(crossings < 500)
    late = np.sum(crossings > t.size - 500)
    assert early < late                       # frequency rises
    assert late / 2 / 0.5 == pytest.approx(19.5, abs=2.0)
    ylog = wf.chirp(t, amplitude=2.0, f0_hz=1.0, f1_hz=20.0, method="log", offset=1.0)
    assert ylog.max() <= 3.0 + 1e-12 and ylog.min() >= -1.0 - 1e-12


def test_prbs_is_maximal_length():
    for order in (5, 7, 9):
        bits = wf.prbs_bits(order)
        n = 2 ** order - 1
        assert bits.size == n and bits.sum() == 2 ** (order - 1)   # one more 1 than 0s
        # maximal-length: the sequence is not periodic with any shorter divisor period
        for p in range(1, n):
            if n % p == 0:
                assert not np.array_equal(bits, np.roll(bits, p))
    t = wf.time_base(1.0)
    y = wf.prbs(t, amplitude=0.5, bit_s=0.01, order=7, offset=1.0)
    assert set(np.unique(y)) == {0.5, 1.5}
    assert (y[:10] == y[0]).all()             # held for one bit
    with pytest.raises(ProfileError):
        wf.prbs_bits(8)


def test_from_dict():
    t = wf.time_base(1.0)
    y = wf.from_dict({"kind": "step", "amplitude": 2.0, "t_step_s": 0.5}, t)
    np.testing.assert_array_equal(y, wf.step(t, amplitude=2.0, t_step_s=0.5))
    with pytest.raises(ProfileError, match=r"steps\[0\]\.excitation\.amplitud: unknown key"):
        wf.from_dict({"kind": "step", "amplitud": 2.0}, t, "steps[0].excitation")
    with pytest.raises(ProfileError, match=r"\.kind: 'sawtooth' unknown"):
        wf.from_dict({"kind": "sawtooth"}, t)
    with pytest.raises(ProfileError, match="amplitude"):
        wf.from_dict({"kind": "step"}, t)
