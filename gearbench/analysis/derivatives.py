"""Derivatives of sampled encoder angles, and the matching filters for other signals.

Two families:

* ``forward_differences`` — the paper's Euler differences (Yukawa et al., sec. 2.3):
  velocity and acceleration one and two samples ahead of the current they are paired
  with. Kept for the ``paper`` method only.
* ``consistent_derivatives`` — the default: one zero-phase low-pass FIR ``F`` applied
  to every signal, central differences of the angle, and a 3-tap kernel on the
  non-differentiated signals that matches the central second difference's own
  response (``(sin(x/2)/(x/2))**2`` ≈ ``(10 + 2 cos x)/12`` to O(x⁴)). Because ``F``
  is linear and time-invariant, ``J θ'' + D θ' + Tc s(θ') = Kt i`` still holds
  *exactly* between the filtered signals: the filter removes noise, never scales
  or shifts one side against the other.
"""
from __future__ import annotations

import numpy as np
from scipy import signal

# Central second difference ≈ this kernel applied to the sampled acceleration.
SECOND_DIFFERENCE_MATCH = np.array([1.0, 10.0, 1.0]) / 12.0


def forward_differences(position_rad: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Euler forward differences (paper sec. 2.3).

    Returns ``(velocity, acceleration)`` of length ``len(position) - 2``, aligned with
    ``position[:-2]``: ``ω_k = (θ_{k+1} - θ_k)/dt`` and ``α_k = (ω_{k+1} - ω_k)/dt``.
    """
    w = np.diff(position_rad) / dt_s
    a = np.diff(w) / dt_s
    return w[:-1], a


def lowpass_fir(cutoff_hz: float, rate_hz: float, *, transition_hz: float | None = None) -> np.ndarray:
    """Symmetric (linear-phase) Blackman-windowed sinc low-pass, unit DC gain.

    The Blackman window keeps the stop band below about -70 dB, which matters because
    encoder-quantisation noise in a second difference grows as f²: a filter with
    poor side lobes (Savitzky–Golay) lets that noise through.
    """
    nyq = rate_hz / 2.0
    cutoff_hz = min(cutoff_hz, 0.8 * nyq)
    transition_hz = transition_hz or cutoff_hz
    # Blackman main lobe ≈ 5.5 fs / N wide.
    ntaps = int(np.ceil(5.5 * rate_hz / transition_hz)) | 1
    ntaps = max(ntaps, 5)
    taps = signal.firwin(ntaps, cutoff_hz, window="blackman", fs=rate_hz)
    return taps / taps.sum()


def filter_valid(x: np.ndarray, taps: np.ndarray) -> np.ndarray:
    """``x`` convolved with ``taps``, 'valid' part only (no edge padding: edges would
    break the exact linear relation between filtered signals)."""
    if len(x) < len(taps):
        return np.empty(0)
    if len(taps) <= 16:
        return np.convolve(x, taps, mode="valid")
    return signal.oaconvolve(x, taps, mode="valid")


def consistent_derivatives(position_rad: np.ndarray, others: dict[str, np.ndarray],
                           dt_s: float, taps: np.ndarray) -> dict[str, np.ndarray]:
    """Filtered angle, velocity, acceleration and other signals, all aligned.

    Parameters
    ----------
    position_rad : sampled angle.
    others : further sampled signals (current, friction regressors...) that enter the
        motor equation undifferentiated; each gets the 3-tap second-difference match
        and the same FIR.
    dt_s : sample period.
    taps : FIR from :func:`lowpass_fir`.

    Returns
    -------
    dict with ``position``, ``velocity``, ``acceleration`` and each key of ``others``;
    every array has ``len(position) - 2 - len(taps) + 1`` samples, sample ``m`` centred
    on raw sample ``m + 1 + (len(taps) - 1)//2``.

    Filtering and differencing are both LTI, so they commute; the angle is filtered
    once and differenced afterwards (cheaper: one FFT convolution per signal). The
    angle's mean ramp is removed first (a symmetric unit-gain FIR passes a ramp
    unchanged) so no float cancellation can creep into the second difference.
    """
    th = np.asarray(position_rad, float)
    n = len(th)
    k = np.arange(n, dtype=float)
    slope = (th[-1] - th[0]) / max(n - 1, 1)
    detrended = th - th[0] - slope * k
    names = list(others)
    stack = np.vstack([detrended, *[np.asarray(others[m], float) for m in names]])
    if stack.shape[1] < len(taps) + 2:
        empty = np.empty(0)
        return {m: empty for m in ["position", "velocity", "acceleration", *names]}
    filt = signal.oaconvolve(stack, taps[None, :], mode="valid", axes=1)
    f = filt[0]
    half = (len(taps) - 1) // 2
    centre = k[half + 1: half + 1 + len(f) - 2]            # raw index of each output
    out = {
        "position": f[1:-1] + th[0] + slope * centre,
        "velocity": (f[2:] - f[:-2]) / (2.0 * dt_s) + slope / dt_s,
        "acceleration": (f[2:] - 2.0 * f[1:-1] + f[:-2]) / (dt_s * dt_s),
    }
    c = SECOND_DIFFERENCE_MATCH
    for j, m in enumerate(names, start=1):
        g = filt[j]
        out[m] = c[0] * g[2:] + c[1] * g[1:-1] + c[2] * g[:-2]
    return out
