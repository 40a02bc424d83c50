"""Command waveforms for excitation and bench steps: pure functions of a time base.

Each function takes ``time_s`` (1-D array of sample times, seconds) and keyword
parameters with physical meaning, and returns an array of the same length (a speed
setpoint in rad/s or a current in A — the caller decides). ``from_dict`` builds one
from a profile mapping ``{kind: multisine, amplitude: ..., ...}``.
"""
from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np

from ..errors import ProfileError


def time_base(duration_s: float, period_s: float = 1e-3) -> np.ndarray:
    """``round(duration_s/period_s)`` sample times k·period_s starting at 0."""
    if not (duration_s > 0 and period_s > 0):
        raise ProfileError(f"waveform: duration_s and period_s must be > 0 "
                           f"(got {duration_s}, {period_s})")
    return np.arange(int(round(duration_s / period_s))) * period_s


def _t(time_s) -> np.ndarray:
    t = np.asarray(time_s, dtype=float)
    if t.ndim != 1:
        raise ProfileError("waveform: time_s must be a 1-D array")
    return t


def step(time_s, *, amplitude: float, t_step_s: float = 0.0, offset: float = 0.0) -> np.ndarray:
    """``offset`` before ``t_step_s``, ``offset + amplitude`` from then on (the paper's step)."""
    t = _t(time_s)
    return offset + amplitude * (t >= t_step_s)


def staircase(time_s, *, levels, dwell_s: float, t0_s: float = 0.0) -> np.ndarray:
    """Hold each of ``levels`` for ``dwell_s`` starting at ``t0_s`` (first level before
    ``t0_s``, last level after the end) — e.g. the bench's braking-current levels."""
    t = _t(time_s)
    lv = np.asarray(levels, dtype=float)
    if lv.ndim != 1 or lv.size == 0:
        raise ProfileError("staircase: levels must be a non-empty list of numbers")
    if not dwell_s > 0:
        raise ProfileError(f"staircase: dwell_s must be > 0 (got {dwell_s})")
    idx = np.clip(np.floor((t - t0_s) / dwell_s).astype(int), 0, lv.size - 1)
    return lv[idx]


def ramp(time_s, *, slope: float, t0_s: float = 0.0, offset: float = 0.0,
         final: float | None = None) -> np.ndarray:
    """``offset`` until ``t0_s``, then rising at ``slope`` per second, held at ``final`` if given."""
    t = _t(time_s)
    y = offset + slope * np.clip(t - t0_s, 0.0, None)
    if final is not None:
        y = np.minimum(y, final) if slope >= 0 else np.maximum(y, final)
    return y


def trapezoid(time_s, *, amplitude: float, ramp_s: float, hold_s: float, t0_s: float = 0.0,
              offset: float = 0.0, repeat_s: float | None = None) -> np.ndarray:
    """Ramp from ``offset`` to ``offset + amplitude`` in ``ramp_s``, hold ``hold_s``, ramp back;
    repeated every ``repeat_s`` if given (a negative amplitude reverses direction)."""
    t = _t(time_s)
    if ramp_s < 0 or hold_s < 0:
        raise ProfileError("trapezoid: ramp_s and hold_s must be >= 0")
    width = 2 * ramp_s + hold_s
    if repeat_s is not None and repeat_s < width:
        raise ProfileError(f"trapezoid: repeat_s ({repeat_s}) must be >= 2*ramp_s + hold_s ({width})")
    tau = t - t0_s
    if repeat_s is not None:
        tau = np.where(tau >= 0, np.mod(tau, repeat_s), tau)
    if ramp_s > 0:
        up = np.clip(tau / ramp_s, 0, 1)
        down = np.clip((width - tau) / ramp_s, 0, 1)
        shape = np.minimum(up, down)
    else:
        shape = ((tau >= 0) & (tau < hold_s)).astype(float)
    return offset + amplitude * shape


def multisine(time_s, *, amplitude: float, freqs_hz, offset: float = 0.0,
              phases: str = "schroeder", seed: int = 0) -> np.ndarray:
    """Sum of sines at ``freqs_hz`` with Schroeder (or ``"random"``) phases, scaled so
    the peak deviation from ``offset`` over the time base is ``amplitude``."""
    t = _t(time_s)
    f = np.atleast_1d(np.asarray(freqs_hz, dtype=float))
    if f.size == 0 or (f <= 0).any():
        raise ProfileError("multisine: freqs_hz must be a non-empty list of positive frequencies")
    k = np.arange(1, f.size + 1)
    if phases == "schroeder":
        ph = -np.pi * k * (k - 1) / f.size
    elif phases == "random":
        ph = np.random.default_rng(seed).uniform(0, 2 * np.pi, f.size)
    else:
        raise ProfileError(f"multisine: phases '{phases}' unknown; use 'schroeder' or 'random'")
    y = np.sin(2 * np.pi * f[None, :] * t[:, None] + ph[None, :]).sum(axis=1)
    peak = np.abs(y).max() if y.size else 1.0
    return offset + amplitude * y / (peak if peak > 0 else 1.0)


def chirp(time_s, *, amplitude: float, f0_hz: float, f1_hz: float, offset: float = 0.0,
          method: str = "linear", t1_s: float | None = None) -> np.ndarray:
    """Sine sweep from ``f0_hz`` at t = 0 to ``f1_hz`` at ``t1_s`` (default: the last sample);
    ``method`` ``"linear"`` or ``"log"`` (exponential)."""
    t = _t(time_s)
    if not (f0_hz > 0 and f1_hz > 0):
        raise ProfileError("chirp: f0_hz and f1_hz must be > 0")
    t1 = float(t1_s if t1_s is not None else (t[-1] if t.size and t[-1] > 0 else 1.0))
    if method == "linear":
        phase = 2 * np.pi * (f0_hz * t + 0.5 * (f1_hz - f0_hz) / t1 * t ** 2)
    elif method == "log":
        if f1_hz == f0_hz:
            phase = 2 * np.pi * f0_hz * t
        else:
            beta = t1 / math.log(f1_hz / f0_hz)
            phase = 2 * np.pi * f0_hz * beta * (np.power(f1_hz / f0_hz, t / t1) - 1)
    else:
        raise ProfileError(f"chirp: method '{method}' unknown; use 'linear' or 'log'")
    return offset + amplitude * np.sin(phase)


# taps of maximal-length Fibonacci LFSRs (x^order + x^tap + 1)
_PRBS_TAPS = {5: 3, 6: 5, 7: 6, 9: 5, 10: 7, 11: 9, 15: 14, 17: 14, 20: 17, 23: 18}


def prbs_bits(order: int = 9, seed: int = 1) -> np.ndarray:
    """One period (2^order − 1 bits, 0/1) of a maximal-length sequence."""
    if order not in _PRBS_TAPS:
        raise ProfileError(f"prbs: order {order} unsupported; use one of {sorted(_PRBS_TAPS)}")
    tap = _PRBS_TAPS[order]
    state = (seed % ((1 << order) - 1)) + 1     # any non-zero start
    n = (1 << order) - 1
    bits = np.empty(n, dtype=np.int8)
    for k in range(n):
        bit = ((state >> (order - 1)) ^ (state >> (tap - 1))) & 1
        bits[k] = state & 1
        state = ((state << 1) | bit) & n
    return bits


def prbs(time_s, *, amplitude: float, bit_s: float, order: int = 9, offset: float = 0.0,
         seed: int = 1) -> np.ndarray:
    """Pseudo-random binary sequence: ``offset ± amplitude``, one bit every ``bit_s``."""
    t = _t(time_s)
    if not bit_s > 0:
        raise ProfileError(f"prbs: bit_s must be > 0 (got {bit_s})")
    bits = prbs_bits(order, seed)
    idx = np.floor(np.maximum(t - t[0] if t.size else t, 0) / bit_s + 1e-9).astype(int) % bits.size
    return offset + amplitude * (2.0 * bits[idx] - 1.0)


KINDS = {"step": step, "staircase": staircase, "ramp": ramp, "trapezoid": trapezoid,
         "multisine": multisine, "chirp": chirp, "prbs": prbs}


def from_dict(spec: Mapping[str, Any], time_s, where: str = "waveform") -> np.ndarray:
    """Build a waveform from ``{kind: <name>, <parameters>...}``; errors name ``where.key``."""
    if not isinstance(spec, Mapping) or "kind" not in spec:
        raise ProfileError(f"{where}: expected a mapping with 'kind' (one of {', '.join(KINDS)})")
    kind = spec["kind"]
    fn = KINDS.get(kind)
    if fn is None:
        raise ProfileError(f"{where}.kind: '{kind}' unknown; use one of {', '.join(KINDS)}")
    import inspect

    params = [p for p in inspect.signature(fn).parameters if p != "time_s"]
    kw = {k: v for k, v in spec.items() if k != "kind"}
    for k in kw:
        if k not in params:
            raise ProfileError(f"{where}.{k}: unknown key for {kind}; known keys: {', '.join(params)}")
    try:
        return fn(time_s, **kw)
    except TypeError as exc:
        raise ProfileError(f"{where}: {kind}: {exc}") from None
