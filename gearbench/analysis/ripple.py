"""The speed loop's quantisation ripple in a current sampled at one instant.

A drive's speed loop differentiates encoder counts every loop tick (4 per 1 ms SYNC
here); the count's quantum puts an error e on its speed estimate and the P gain turns
it into current, ``-Kp·e`` through the current loop. A drive whose current object is
the period mean averages that out; one that reports a single current-loop instant
passes it on, aliased into the fit band and the level means (cycle_time
``--drive-current mean``: the largest single cause of random plants missing the bench
time bound). The drive also reports the speed estimate it acted on (CiA 402 0x606C,
recorded as ``velocity_rad_s``), so e is known up to the true speed, which the encoder
gives smoothly over a few tens of samples: the ripple is regressed on e and taken out.
"""
from __future__ import annotations

import numpy as np

RIPPLE_SPEED_SPAN_S = 0.02   # true speed: the angle travelled over 20 ms (quantum / 20 ms << e)
RIPPLE_CHUNK_S = 0.02        # the gain is fitted within chunks: their own means (levels, ramps) drop out


def speed_estimate_error(drive_velocity_rad_s: np.ndarray, position_rad: np.ndarray,
                         period_s: float) -> np.ndarray:
    """e_k = v_drive,k − (θ_{k+h} − θ_{k−h}) / (2h T), the drive's reported speed less the
    speed the encoder shows over ``RIPPLE_SPEED_SPAN_S`` (0 where that span does not fit)."""
    v = np.asarray(drive_velocity_rad_s, float)
    th = np.asarray(position_rad, float)
    h = max(1, int(round(RIPPLE_SPEED_SPAN_S / 2 / period_s)))
    e = np.zeros_like(th)
    if len(th) > 2 * h:
        e[h:len(th) - h] = v[h:len(th) - h] - (th[2 * h:] - th[:-2 * h]) / (2 * h * period_s)
    return e


def ripple_gain(current_a: np.ndarray, error_rad_s: np.ndarray, chunk: int,
                ranges: list[tuple[int, int]] | None = None) -> float:
    """Least-squares gain β (A per rad/s) of i = c_j + β e within chunks j of ``chunk``
    samples (each chunk its own constant c_j): the pooled within-chunk regression slope;
    only chunks inside ``ranges`` (index pairs [a, b)) where given."""
    i = np.asarray(current_a, float)
    e = np.asarray(error_rad_s, float)
    spans = ranges if ranges is not None else [(0, len(i))]
    starts = [a + k * chunk for a, b in spans for k in range(max(b - a, 0) // chunk)]
    if len(starts) < 2:
        return 0.0
    idx = np.asarray(starts)[:, None] + np.arange(chunk)
    ic, ec = i[idx], e[idx]
    ic = ic - ic.mean(axis=1, keepdims=True)
    ec = ec - ec.mean(axis=1, keepdims=True)
    sxx = float(np.sum(ec * ec))
    return float(np.sum(ec * ic) / sxx) if sxx > 0 else 0.0


def ripple_corrected_current(current_a: np.ndarray, drive_velocity_rad_s: np.ndarray,
                             position_rad: np.ndarray, period_s: float,
                             gain: float | None = None,
                             ranges: list[tuple[int, int]] | None = None) -> tuple[np.ndarray, float]:
    """i − β·e: the current less the speed loop's quantisation ripple (module docstring),
    β fitted on these samples (``ripple_gain``, within ``ranges`` where given) unless given.
    Returns (current, β).

    Examples
    --------
    >>> t = np.arange(2000) * 1e-3
    >>> e = np.sign(np.sin(2 * np.pi * 37.0 * t))       # the drive's estimate error
    >>> i, b = ripple_corrected_current(1.0 - 0.05 * e, 100.0 + e, 100.0 * t, 1e-3)
    >>> round(b, 3), float(np.abs(i[20:-20] - 1.0).max().round(3))
    (-0.05, 0.0)
    """
    e = speed_estimate_error(drive_velocity_rad_s, position_rad, period_s)
    if gain is None:
        gain = ripple_gain(current_a, e, max(2, int(round(RIPPLE_CHUNK_S / period_s))), ranges)
    return np.asarray(current_a, float) - gain * e, float(gain)
