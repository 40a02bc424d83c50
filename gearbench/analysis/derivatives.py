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
# The same match for samples that are each the mean over the period ending at them (a
# drive's period-mean current): the central second difference weights the acceleration
# by a triangle about the sample instant, boxcar ∗ boxcar, so the period means' own mean
# over the next period is the match; from the samples, the fourth-order cell average
# (−m₋₁ + 13 m₀ + 13 m₁ − m₂)/24. The 3-tap match on period means instead, with the half
# period left to the fitted current delay, put Kt 0.03-0.05 % high on noise-free random
# plants (a magnitude error ~x², x = πfT, that a delay cannot take).
PERIOD_MEAN_MATCH = np.array([-1.0, 13.0, 13.0, -1.0]) / 24.0


def forward_differences(position_rad: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Euler forward differences (paper sec. 2.3).

    Returns ``(velocity, acceleration)`` of length ``len(position) - 2``, aligned with
    ``position[:-2]``: ``ω_k = (θ_{k+1} - θ_k)/dt`` and ``α_k = (ω_{k+1} - ω_k)/dt``.

    Parameters
    ----------
    position_rad : sampled angle.
    dt_s : sample period.

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md), sec. 2.3

    Examples
    --------
    >>> import numpy as np
    >>> forward_differences(np.array([0.0, 1.0, 4.0]), 1.0)[1]
    array([2.])

    """
    w = np.diff(position_rad) / dt_s
    a = np.diff(w) / dt_s
    return w[:-1], a


def rate_cutoff(rate_hz: float) -> float:
    """min(40 Hz, rate/10): the common filter's cutoff from the sample rate alone (a
    calibration's, and the excitation design's model of it; ``identify.default_cutoff``
    also holds it below the motion's band).

    Parameters
    ----------
    rate_hz : the sample rate.

    Returns
    -------
    float
        Hz.

    Examples
    --------
    >>> rate_cutoff(1000.0), rate_cutoff(100.0)
    (40.0, 10.0)
    """
    return float(min(40.0, rate_hz / 10.0))


def lowpass_fir(cutoff_hz: float, rate_hz: float, *, transition_hz: float | None = None) -> np.ndarray:
    """Symmetric (linear-phase) Blackman-windowed sinc low-pass, unit DC gain.

    The Blackman window keeps the stop band below about -70 dB, which matters because
    encoder-quantisation noise in a second difference grows as f²: a filter with
    poor side lobes (Savitzky–Golay) lets that noise through.

    Parameters
    ----------
    cutoff_hz, rate_hz : cutoff and sample rate.
    transition_hz : main-lobe width (default: the cutoff).

    Returns
    -------
    numpy.ndarray
        Odd-length symmetric taps summing to 1.

    References
    ----------
    A. V. Oppenheim and R. W. Schafer, "Discrete-Time Signal Processing", 3rd ed., Pearson 2010, sec. 7.5 (window method)

    Examples
    --------
    >>> bool(abs(lowpass_fir(40.0, 1000.0).sum() - 1) < 1e-12)
    True

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
    break the exact linear relation between filtered signals).

    Parameters
    ----------
    x : signal.
    taps : FIR.

    Returns
    -------
    numpy.ndarray
        ``len(x) - len(taps) + 1`` samples.

    References
    ----------
    A. V. Oppenheim and R. W. Schafer, "Discrete-Time Signal Processing", 3rd ed., Pearson 2010, sec. 7.5 (window method)

    Examples
    --------
    >>> import numpy as np
    >>> filter_valid(np.ones(5), np.ones(3) / 3)
    array([1., 1., 1.])

    """
    if len(x) < len(taps):
        return np.empty(0)
    if len(taps) <= 16:
        return np.convolve(x, taps, mode="valid")
    return signal.oaconvolve(x, taps, mode="valid")


def smooth_velocity(position_rad: np.ndarray, dt_s: float, *, half_width: int = 10) -> np.ndarray:
    """Zero-phase velocity at every sample: Savitzky–Golay (cubic) derivative over
    ``2·half_width + 1`` samples. Precise enough near zero speed to place a reversal
    within a few % of a sample even at 2,000 counts/rev, where a single difference is
    off by a whole encoder count per sample.

    Parameters
    ----------
    position_rad : sampled angle.
    dt_s : sample period.
    half_width : samples on each side.

    Returns
    -------
    numpy.ndarray
        Speed at every sample.

    References
    ----------
    A. Savitzky and M. J. E. Golay, "Smoothing and differentiation of data by simplified least squares procedures", Anal. Chem. 36(8), 1964, pp. 1627-1639

    Examples
    --------
    >>> import numpy as np
    >>> float(round(smooth_velocity(np.arange(50) * 0.5, 1.0)[25], 9))
    0.5

    """
    th = np.asarray(position_rad, float)
    n = len(th)
    L = 2 * half_width + 1
    if n < L + 2:
        return np.gradient(th, dt_s)
    k = np.arange(n, dtype=float)
    slope = (th[-1] - th[0]) / max(n - 1, 1)
    v = signal.savgol_filter(th - th[0] - slope * k, L, 3, deriv=1, delta=dt_s, mode="interp")
    return v + slope / dt_s


def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """The ``(start, stop)`` slices of every stretch where ``mask`` is True.

    >>> runs(np.array([False, True, True, False, True]))
    [(1, 3), (4, 5)]
    """
    edges = np.diff(np.concatenate([[0], np.asarray(mask).astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()))


def standstill(velocity: np.ndarray, speed_rad_s: float, *, min_samples: int = 3) -> np.ndarray:
    """1.0 on samples inside a dwell of at least ``min_samples`` with |ω| < ``speed_rad_s``
    (the rotor sticking at a reversal), else 0.0. A fast reversal crosses the band
    between two samples and is not a dwell.

    Parameters
    ----------
    velocity : speed.
    speed_rad_s : threshold.
    min_samples : shortest dwell.

    Returns
    -------
    numpy.ndarray of 0.0/1.0

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md)

    Examples
    --------
    >>> standstill([1.0, 0.0, 0.0, 0.0, 1.0], 0.1)
    array([0., 1., 1., 1., 0.])

    """
    slow = np.abs(velocity) < speed_rad_s
    if not slow.any():
        return np.zeros(len(velocity))
    out = np.zeros(len(velocity))
    for a, b in runs(slow):
        if b - a >= min_samples:
            out[a:b] = 1.0
    return out


def coulomb_regressor(position_rad: np.ndarray, dt_s: float, *, velocity: np.ndarray | None = None,
                      half_width: int = 10) -> np.ndarray:
    """sign(ω) as the central second difference of the angle sees it.

    ``θ_{k+1} − 2θ_k + θ_{k−1} = ∫ (dt − |s|) θ''(t_k + s) ds``: the acceleration, and so
    every torque, enters sample ``k`` as a triangle-weighted mean over ``[t_{k−1}, t_{k+1}]``.
    For Coulomb friction, a step at each reversal, sampling sign(ω) and applying the
    3-tap match is wrong by up to a whole step for one or two samples per reversal,
    which biases Kt/J by ~1 % on reversing runs. Here the speed is taken linear between
    samples (``smooth_velocity``), each reversal is placed at its sub-sample instant
    ``u_c = ω_j/(ω_j − ω_{j+1})``, and the triangle-weighted mean is integrated exactly:
    an interval with sign σ before the crossing adds ``σ(u_c² − 1/2)`` to the sample on
    its right and ``σ(2u_c − u_c² − 1/2)`` to the one on its left (``σ/2`` each without a
    crossing). Returns one value per sample, already matched: pass it to
    ``consistent_derivatives`` in ``matched``, not in ``others``.

    Parameters
    ----------
    position_rad : sampled angle.
    dt_s : sample period.
    velocity : speed at every sample (default ``smooth_velocity``).
    half_width : of ``smooth_velocity`` when computed here.

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md); M. Gautier and W. Khalil, "On the identification of the inertial parameters of robots", Proc. 27th IEEE Conf. Decision and Control, 1988, pp. 2264-2269

    Examples
    --------
    >>> s = coulomb_regressor(theta, 1e-3)   # doctest: +SKIP

    """
    w = smooth_velocity(position_rad, dt_s, half_width=half_width) if velocity is None else velocity
    wa, wb = w[:-1], w[1:]
    sig = np.where(wa != 0, np.sign(wa), -np.sign(wb))
    cross = (np.sign(wa) != np.sign(wb))
    with np.errstate(invalid="ignore", divide="ignore"):
        uc = np.where(cross, wa / np.where(cross, wa - wb, 1.0), 0.0)
    uc = np.clip(uc, 0.0, 1.0)
    right = np.where(cross, sig * (uc * uc - 0.5), 0.5 * sig)      # to sample j + 1
    left = np.where(cross, sig * (2 * uc - uc * uc - 0.5), 0.5 * sig)  # to sample j
    out = np.empty_like(w)
    out[1:-1] = right[:-1] + left[1:]
    out[0], out[-1] = np.sign(w[0]), np.sign(w[-1])
    return out


def consistent_derivatives(position_rad: np.ndarray, others: dict[str, np.ndarray],
                           dt_s: float, taps: np.ndarray, *,
                           matched: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """Filtered angle, velocity, acceleration and other signals, all aligned.

    Parameters
    ----------
    position_rad : sampled angle.
    others : further sampled signals (current, friction regressors...) that enter the
        motor equation undifferentiated; each gets the 3-tap second-difference match
        and the same FIR.
    dt_s : sample period.
    taps : FIR from :func:`lowpass_fir`.
    matched : signals already in the second difference's triangle-weighted form (e.g.
        :func:`coulomb_regressor`); they get the FIR only.

    Returns
    -------
    dict with ``position``, ``velocity``, ``acceleration`` and each key of ``others``;
    every array has ``len(position) - 2 - len(taps) + 1`` samples, sample ``m`` centred
    on raw sample ``m + 1 + (len(taps) - 1)//2``.

    Filtering and differencing are both LTI, so they commute; the angle is filtered
    once and differenced afterwards (cheaper: one FFT convolution per signal). The
    angle's mean ramp is removed first (a symmetric unit-gain FIR passes a ramp
    unchanged) so no float cancellation can creep into the second difference.

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md); A. V. Oppenheim and R. W. Schafer, "Discrete-Time Signal Processing", 3rd ed., Pearson 2010, sec. 7.5 (window method)

    Examples
    --------
    >>> fs = consistent_derivatives(theta, {"current": i}, 1e-3, lowpass_fir(40, 1000))   # doctest: +SKIP

    """
    th = np.asarray(position_rad, float)
    n = len(th)
    k = np.arange(n, dtype=float)
    slope = (th[-1] - th[0]) / max(n - 1, 1)
    detrended = th - th[0] - slope * k
    matched = matched or {}
    names = list(others)
    mnames = list(matched)
    stack = np.vstack([detrended, *[np.asarray(others[m], float) for m in names],
                       *[np.asarray(matched[m], float) for m in mnames]])
    if stack.shape[1] < len(taps) + 2:
        empty = np.empty(0)
        return {m: empty for m in ["position", "velocity", "acceleration", *names, *mnames]}
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
    for j, m in enumerate(mnames, start=1 + len(names)):
        out[m] = filt[j][1:-1]
    return out


def matched_filter(signals: np.ndarray, taps: np.ndarray) -> np.ndarray:
    """Rows of ``signals`` (k x n) through the 3-tap second-difference match and the FIR,
    aligned exactly as the ``others`` outputs of :func:`consistent_derivatives` (for
    regressors added after the main filtering, e.g. cogging harmonics).

    Parameters
    ----------
    signals : k x n rows.
    taps : FIR.

    Returns
    -------
    numpy.ndarray
        k x (n − len(taps) − 1).

    References
    ----------
    A. V. Oppenheim and R. W. Schafer, "Discrete-Time Signal Processing", 3rd ed., Pearson 2010, sec. 7.5 (window method)

    Examples
    --------
    >>> import numpy as np
    >>> matched_filter(np.ones((1, 10)), np.ones(3) / 3).shape
    (1, 6)

    """
    x = np.atleast_2d(np.asarray(signals, float))
    if x.shape[1] < len(taps) + 2:
        return np.empty((x.shape[0], 0))
    g = signal.oaconvolve(x, taps[None, :], mode="valid", axes=1)
    c = SECOND_DIFFERENCE_MATCH
    return c[0] * g[:, 2:] + c[1] * g[:, 1:-1] + c[2] * g[:, :-2]


def refine_reversals(position_rad: np.ndarray, velocity: np.ndarray, *, half_width: int = 10,
                     steps: int = 60) -> np.ndarray:
    """``velocity`` with each zero crossing moved to where the angle itself puts it.

    A smoothing differentiator (``smooth_velocity``) misplaces a reversal by a fraction
    of a sample: Coulomb friction flips there, so the acceleration jumps by 2·Tc/J and
    the speed has a kink that a cubic fit over 21 samples smears — enough to bias Kt/J
    by ~1 % on light rotors with strong friction. Around each crossing the angle is
    instead fitted (least squares, ``2·half_width + 2`` samples) by the motion the motor
    equation allows there: an extremum at t_c with its own acceleration and jerk on
    each side,

        θ(t) = c + ½ a± (t − t_c)² + ⅙ j± (t − t_c)³      (± : after/before t_c),

    t_c by a grid of ``steps`` points per sample over [−1, 2] samples from the crossing,
    refined by a parabola through the best three. The returned speed is a unit-slope
    line through t_c on the four samples around it, so ``coulomb_regressor``'s linear
    crossing ``u_c = ω_j/(ω_j − ω_{j+1})`` lands on t_c. Crossings within
    ``2·half_width`` samples of another (a dwell's chatter, masked by ``standstill``
    anyway) or of the ends are left as they are.

    Parameters
    ----------
    position_rad : sampled angle.
    velocity : speed at every sample.
    half_width : samples each side of a crossing.
    steps : grid points per sample.

    Returns
    -------
    numpy.ndarray
        ``velocity`` with refined crossings.

    References
    ----------
    A. Savitzky and M. J. E. Golay, "Smoothing and differentiation of data by simplified least squares procedures", Anal. Chem. 36(8), 1964, pp. 1627-1639

    Examples
    --------
    >>> w = refine_reversals(theta, smooth_velocity(theta, 1e-3))   # doctest: +SKIP

    """
    th = np.asarray(position_rad, float)
    w = np.array(velocity, float)
    n = len(w)
    H = half_width
    j = np.flatnonzero((np.sign(w[:-1]) != np.sign(w[1:])) & (w[:-1] != 0))
    if len(j) == 0:
        return w
    ok = (j >= H + 1) & (j + H + 2 < n)
    gaps = np.diff(j)
    ok &= np.concatenate([[True], gaps > 2 * H]) & np.concatenate([gaps > 2 * H, [True]])
    j = j[ok]
    if len(j) == 0:
        return w
    idx = j[:, None] + np.arange(-H, H + 2)[None, :]             # C x W window samples
    y = th[idx] - th[j][:, None]
    grid = np.linspace(-1.0, 2.0, 3 * steps + 1)
    sse = np.empty((len(grid), len(j)))
    offs = np.arange(-H, H + 2, dtype=float)
    for g, u in enumerate(grid):
        s = offs - u                                              # samples from t_c
        after = s >= 0
        X = np.stack([np.ones_like(s), 0.5 * s * s * ~after, 0.5 * s * s * after,
                      s ** 3 / 6 * ~after, s ** 3 / 6 * after], axis=1)   # W x 5
        P = X @ np.linalg.pinv(X)                                 # hat matrix, same for all
        r = y - y @ P.T
        sse[g] = np.einsum("cw,cw->c", r, r)
    b = np.clip(np.argmin(sse, axis=0), 1, len(grid) - 2)
    c = np.arange(len(j))
    s0, s1, s2 = sse[b - 1, c], sse[b, c], sse[b + 1, c]
    den = s0 - 2 * s1 + s2
    shift = np.where(den > 0, 0.5 * (s0 - s2) / np.where(den > 0, den, 1.0), 0.0)
    tc = j + grid[b] + np.clip(shift, -1, 1) * (grid[1] - grid[0])
    direction = np.sign(w[j + 1] - w[j])
    for k in range(-1, 3):
        w[j + k] = direction * (j + k - tc)
    return w


def weighted_derivatives(position_rad: np.ndarray, others: dict[str, np.ndarray], dt_s: float,
                         taps: np.ndarray, weight: np.ndarray, *,
                         matched: dict[str, np.ndarray] | None = None,
                         unweighted: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """``consistent_derivatives`` of the motor equation multiplied sample by sample by
    ``weight`` before the filter: F[w·θ''], F[w·θ'], F[w·M i], … with θ'' and θ' the
    central differences of the angle and M the 3-tap second-difference match.

    If ``J θ''_k + D θ'_k + … = Kt (M i)_k`` holds on every sample with w_k ≠ 0, it
    holds exactly between the filtered, weighted signals, whatever happens where
    w_k = 0 (a stuck rotor, a friction transition the model lacks): samples are
    dropped from the equation without cutting the filter's window. With w ≡ 1 this
    is ``consistent_derivatives`` (filtering and differencing commute).

    Parameters
    ----------
    position_rad : sampled angle.
    others : undifferentiated signals (3-tap match, weight, FIR).
    dt_s : sample period.
    taps : FIR from :func:`lowpass_fir`.
    weight : per raw sample, 0..1.
    matched : signals already in the second difference's form (weight, FIR).
    unweighted : signals filtered as ``consistent_derivatives`` does (instruments).

    Returns
    -------
    dict laid out as :func:`consistent_derivatives` (``position`` unweighted).

    References
    ----------
    A. V. Oppenheim and R. W. Schafer, "Discrete-Time Signal Processing", 3rd ed., Pearson 2010, sec. 7.5; M. Gautier and W. Khalil, "On the identification of the inertial parameters of robots", Proc. 27th IEEE CDC, 1988 (data selection for IDIM-LS)

    Examples
    --------
    >>> fs = weighted_derivatives(theta, {"current": i}, 1e-3, taps, w)   # doctest: +SKIP

    """
    th = np.asarray(position_rad, float)
    n = len(th)
    w = np.asarray(weight, float)
    out = consistent_derivatives(th, dict(unweighted or {}), dt_s, taps)
    if n < len(taps) + 2:
        return {**out, **{m: np.empty(0) for m in [*others, *(matched or {})]}}
    d1 = np.zeros(n)
    d2 = np.zeros(n)
    d1[1:-1] = (th[2:] - th[:-2]) / (2.0 * dt_s)
    d2[1:-1] = (th[2:] - 2.0 * th[1:-1] + th[:-2]) / (dt_s * dt_s)
    rows = {"velocity": d1, "acceleration": d2}
    for m, x in others.items():
        rows[m] = match_samples(np.asarray(x, float))
    for m, x in (matched or {}).items():
        rows[m] = np.asarray(x, float)
    names = list(rows)
    stack = np.empty((len(names), n))        # weighted in place: one k x n array, not two
    for j, m in enumerate(names):
        np.multiply(rows[m], w, out=stack[j])
    filt = signal.oaconvolve(stack, taps[None, :], mode="valid", axes=1)
    for j, m in enumerate(names):
        out[m] = filt[j][1:-1]
    return out


def match_samples(x: np.ndarray) -> np.ndarray:
    """The 3-tap second-difference match at each raw sample (ends copied).

    Parameters
    ----------
    x : rows (..., n).

    Returns
    -------
    numpy.ndarray, same shape.

    References
    ----------
    A. V. Oppenheim and R. W. Schafer, "Discrete-Time Signal Processing", 3rd ed., Pearson 2010, sec. 7.5

    Examples
    --------
    >>> import numpy as np
    >>> match_samples(np.ones(4))
    array([1., 1., 1., 1.])
    """
    x = np.asarray(x, float)
    c = SECOND_DIFFERENCE_MATCH
    out = x.copy()
    out[..., 1:-1] = c[0] * x[..., :-2] + c[1] * x[..., 1:-1] + c[2] * x[..., 2:]
    return out


def match_period_means(x: np.ndarray) -> np.ndarray:
    """``PERIOD_MEAN_MATCH`` at each raw sample (samples k−1…k+2; ends copied): the
    triangle-weighted value about sample k of a signal sampled as means over the period
    ending at each sample.

    Parameters
    ----------
    x : rows (..., n) of period means.

    Returns
    -------
    numpy.ndarray, same shape.

    References
    ----------
    C.-W. Shu, "Essentially non-oscillatory and weighted essentially non-oscillatory
    schemes for hyperbolic conservation laws", NASA/CR-97-206253 (1997), sec. 2.1 (cell
    averages and point values)

    Examples
    --------
    >>> import numpy as np
    >>> t = np.arange(8.0)
    >>> m = ((t + 0.5) ** 2 * 0 + t - 0.5)      # period means of a ramp v(t) = t
    >>> match_period_means(m)[1:-2]              # triangle about k of a ramp: v(k)
    array([1., 2., 3., 4., 5.])
    """
    x = np.asarray(x, float)
    c = PERIOD_MEAN_MATCH
    out = x.copy()
    if x.shape[-1] >= 4:
        out[..., 1:-2] = (c[0] * x[..., :-3] + c[1] * x[..., 1:-2] + c[2] * x[..., 2:-1]
                          + c[3] * x[..., 3:])
    return out


def shift_samples(x: np.ndarray, shift: float) -> np.ndarray:
    """x at k + ``shift`` samples, by 4-point (cubic) Lagrange interpolation (ends held).

    Linear interpolation at a fraction f of a sample scales a tone of x = πfT by about
    1 − 2f(1−f)x²: at half a sample and 10 Hz content of a 1 kHz run that is −0.05 %, the
    size of the Kt errors it caused; the cubic's error is of order x⁴.

    Parameters
    ----------
    x : samples (n,).
    shift : samples (any real).

    Returns
    -------
    numpy.ndarray (n,).

    References
    ----------
    T. I. Laakso, V. Välimäki, M. Karjalainen and U. K. Laine, "Splitting the unit delay",
    IEEE Signal Processing Magazine 13(1), 1996, pp. 30-60 (Lagrange fractional delay)

    Examples
    --------
    >>> import numpy as np
    >>> shift_samples(np.arange(6.0) ** 3, 0.5)[1:4]
    array([ 3.375, 15.625, 42.875])
    """
    x = np.asarray(x, float)
    n = len(x)
    base = int(np.floor(shift))
    f = float(shift - base)
    w = np.array([-f * (f - 1) * (f - 2) / 6, (f + 1) * (f - 1) * (f - 2) / 2,
                  -(f + 1) * f * (f - 2) / 2, (f + 1) * f * (f - 1) / 6])
    pad = abs(base) + 2
    xp = np.pad(x, pad, mode="edge")
    out = np.zeros(n)
    for j, wj in zip((-1, 0, 1, 2), w):
        out += wj * xp[pad + base + j:pad + base + j + n]
    return out


def filter_valid_rows(x: np.ndarray, taps: np.ndarray) -> np.ndarray:
    """Rows of ``x`` (k x n) through the FIR, 'valid' part (``filter_valid`` per row).

    Parameters
    ----------
    x : k x n rows.
    taps : FIR.

    Returns
    -------
    numpy.ndarray, k x (n − len(taps) + 1).

    References
    ----------
    A. V. Oppenheim and R. W. Schafer, "Discrete-Time Signal Processing", 3rd ed., Pearson 2010, sec. 7.5

    Examples
    --------
    >>> import numpy as np
    >>> filter_valid_rows(np.ones((2, 5)), np.ones(3) / 3).shape
    (2, 3)
    """
    x = np.atleast_2d(np.asarray(x, float))
    if x.shape[1] < len(taps):
        return np.empty((x.shape[0], 0))
    return signal.oaconvolve(x, taps[None, :], mode="valid", axes=1)
