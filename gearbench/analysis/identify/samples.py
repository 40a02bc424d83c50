"""Which samples enter the equation: stuck and breakaway stretches weighted out
(``equation_weight``), standstill and top speed, reversals, encoder resolution."""
from __future__ import annotations


import numpy as np
from scipy import ndimage

from .. import derivatives as dv


# No threshold is in the user's position unit (rad, deg, mm, m are all valid): speeds
# come from the encoder step, the sample rate and the run's own speed range.
STANDSTILL_COUNTS_PER_SAMPLE = 1 / 6   # slower than 1 count per 6 samples (>= 3 samples): sticks
STANDSTILL_TOP_FRACTION = 3e-4  # without a visible encoder step: this share of the top speed
# A reversal is a dwell below this share of the top speed too, whatever the encoder: a 20-bit
# encoder resolves the creep while the current swings through the friction's transition,
# which sign(ω) does not describe (robustness seeds 7/8, every encoder at 2^20 counts/rev,
# ``--encoder-counts 1048576``: plants meeting every target 56/65 -> 64/71 %, reversing
# ones 29/14 -> 53/43 %, biased 14/8 -> 8/8 %, exceptions 1/1 -> 0/0; D of the reversing
# motors 1.37x its truth (median) before; encoders as drawn: seed 7 unchanged, seed 8
# 85 -> 84 % (case 13's output Kt -0.18 -> -0.25 ± 0.19 %)). A start from rest keeps the
# encoder's band: its acceleration is the run's information.
CREEP_TOP_FRACTION = 1e-3
SHORT_SPEED_SPAN = 6          # samples: the standstill speed's own window (equation_weight)
STICK_BAND = 3.0            # x the standstill speed: the slow stretch around a dwell, left out
STICK_MARGIN_S = 0.01       # ... widened by this on each side (presliding, breakaway),
STICK_MARGIN_SAMPLES = 2     # and by at least this many samples (100 Hz: 10 ms is 1 sample)
STUCK_CURRENT_SIGMAS = 4.0   # a dwell is stuck only while the drive pushes: |running mean i| > this x its noise
PUSHED_MIN_SAMPLES = 5       # ... over the margin's samples, at least this many
REVERSAL_TOP_FRACTION = 0.02  # a run "reverses" if >5 % of it is beyond ±this share of top speed


def _reverses(w_smooth: np.ndarray) -> bool:
    """A run "reverses" where over 5 % of it is beyond ±REVERSAL_TOP_FRACTION of its top
    speed in each direction."""
    w_rev = REVERSAL_TOP_FRACTION * top_speed(w_smooth)
    return bool(np.mean(w_smooth > w_rev) > 0.05 and np.mean(w_smooth < -w_rev) > 0.05)


def _below_current_limit(current_a: np.ndarray, limit_a: float | None,
                         noise_std_a: float) -> np.ndarray:
    """1 where the current sample is below the drive's limit, 0 where it sits at it (within
    3 noise std), all 1 without a limit.

    Why: where the drive holds its current command at the limit the whole SYNC period,
    the setpoint step adds no kick (its speed loop's P part is clipped away), so the
    sample is the period mean and ``_setpoint_steps``'s term c·Δcmd is 0 there. A run
    that sits at the limit on half its samples (the loaded one: it needs more current)
    otherwise shares one c with a run that hardly does (robustness seed 11 case 8's
    output motor: at the limit on 66 % of the loaded and 20 % of the unloaded samples,
    Kt −0.55 ± 0.11 %; with the term zeroed there −0.01 ± 0.08 %; an unlimited drive
    +0.15 %)."""
    if not limit_a:
        return np.ones_like(current_a)
    return (np.abs(current_a) < limit_a - 3.0 * noise_std_a).astype(float)


def equation_weight(velocity: np.ndarray, standstill_speed_: float, dt_s: float, *,
                    current: np.ndarray | None = None, current_noise: float = 0.0,
                    angle: np.ndarray | None = None, creep_speed: float = 0.0) -> np.ndarray:
    """Per raw sample, 1 where the motor equation is fitted, 0 where it is left out.

    Left out: every dwell (at least 3 samples below the standstill speed), extended to
    the stretch around it slower than ``STICK_BAND`` x that speed (the rotor sticks or
    creeps: static friction takes any value up to the breakaway, so the current there
    says nothing about Kt, J or the sliding friction), widened by ``STICK_MARGIN_S``
    (at least ``STICK_MARGIN_SAMPLES``) on each side (presliding and the
    breakaway transition, which sign(ω) does not describe), then rising to 1 over as
    many samples again (raised cosine). A dwell where the drive pushes (``_pushed``:
    the current's running mean beyond noise) on fewer than ``STICK_MARGIN_S`` worth of
    samples (at least ``PUSHED_MIN_SAMPLES``, at most half the dwell) is a rotor at
    rest that nothing pushes (before a speed step from rest): J θ'' = Kt i = 0 holds
    there, it stays in (weight 1; the caller sets its friction to zero). The weight multiplies
    the raw equation before the filter (``derivatives.weighted_derivatives``), so
    the fit stays exact on what remains; the intervals then count only what remains.

    Parameters
    ----------
    velocity : zero-phase speed at every sample.
    standstill_speed_ : ``standstill_speed`` of the run.
    dt_s : sample period.
    current : raw current (A); None: every dwell counts as stuck.
    current_noise : its white-noise std (A).
    creep_speed : a reversal slower than this for at least 3 samples is a dwell too,
        its slow stretch ``STICK_BAND`` x this (``CREEP_TOP_FRACTION``: a fine encoder
        resolves the creep through the friction's transition; a start from rest keeps the
        encoder's band, its acceleration is information).
    angle : the sampled angle; given, a dwell is also found (and the slow stretch
        measured) on its difference over ``SHORT_SPEED_SPAN`` samples
        (``_short_speed``): the smoothed speed rings across a touch-and-go stop (seed 3
        case 62's input motor at 80,000 counts/rev: ±0.2 rad/s where the rotor stood
        at 0.003 rad/s for 12 ms while the current ramped to the breakaway; a false
        double reversal flipped the Coulomb term, b2 +1.8 %).

    Returns
    -------
    numpy.ndarray, 0..1

    References
    ----------
    M. Gautier and W. Khalil, "On the identification of the inertial parameters of robots", Proc. 27th IEEE CDC, 1988 (data selection); B. Armstrong-Hélouvry, P. Dupont and C. Canudas de Wit, "A survey of models, analysis tools and compensation methods for the control of machines with friction", Automatica 30(7), 1994, pp. 1083-1138 (presliding, breakaway)

    Examples
    --------
    >>> equation_weight(np.r_[np.ones(6), np.zeros(3), np.ones(6)], 0.1, 1e-2).round(2)
    array([1.  , 1.  , 0.75, 0.25, 0.  , 0.  , 0.  , 0.  , 0.  , 0.  , 0.  ,
           0.25, 0.75, 1.  , 1.  ])
    """
    w = np.asarray(velocity, float)
    current = None if current is None else np.asarray(current, float)
    core = dv.standstill(w, standstill_speed_) > 0
    if angle is not None:
        # the smoother rings across a touch-and-go stop; the angle's own count says it
        w_short = _short_speed(angle, dt_s)
        core |= dv.standstill(w_short, standstill_speed_) > 0
        # ... and so does an angle held over the whole standstill window, every sample of
        # it: the centred difference above needs 3 samples more before it calls a dwell,
        # and at 100 Hz it missed the 54-68 ms stops (6-8 readings) at every reversal of
        # a stick-slip joint (Fc +2.8 %, Fv -6.6 % on one run)
        core |= _held(angle, SHORT_SPEED_SPAN + 1)
        w = np.where(np.abs(w_short) < np.abs(w), w_short, w)
    stuck = np.zeros(len(w), bool)
    creeping = (_reversing_stretches(w, STICK_BAND * creep_speed) if creep_speed > standstill_speed_
                else np.zeros(len(w), bool))
    core |= creeping & (dv.standstill(w, creep_speed) > 0)
    if core.any():
        # each dwell widened to the slow stretch around it (hysteresis) and the margin; a
        # fast crossing (below the standstill speed for fewer than 3 samples) is no dwell
        # and stays in: its reversal and acceleration are information, not breakaway
        # (left out too, a 2,000-count encoder's 1.5 rad/s band cost seed 0 case 2's
        # heavy output motor 3x its Kt interval; seeds 0/7/8/9 biased 7/3/3/8 % vs 4/3/7/8 %)
        margin = max(int(round(STICK_MARGIN_S / dt_s)), STICK_MARGIN_SAMPLES)
        slow = (np.abs(w) < STICK_BAND * standstill_speed_) | creeping
        # pushed for the margin's time (at least PUSHED_MIN_SAMPLES: at 100 Hz a 2-sample
        # mean beyond 4 of its sigmas twice in a row is no rare event over a long dwell)
        width = max(margin, PUSHED_MIN_SAMPLES)
        pushed = None if current is None else _pushed(current, current_noise, width)
        for a, b in dv.runs(slow):
            if core[a:b].any() and (pushed is None
                                    or np.count_nonzero(pushed[a:b]) >= min(width, (b - a) / 2)):
                stuck[a:b] = True
        if stuck.any() and margin > 0:
            # the margin, then a raised-cosine ramp as long: a hard edge lets the raw
            # second difference's quantisation noise through the filter (its partial sums
            # no longer telescope; seed 0 case 31: r² 0.9974 with, 0.99989 without)
            dist = ndimage.distance_transform_edt(~stuck) - margin
            ramp = 0.5 - 0.5 * np.cos(np.pi * np.clip(dist, 0, margin + 1) / (margin + 1))
            return np.where(stuck, 0.0, ramp)
    return 1.0 - stuck.astype(float)


def _reversing_stretches(w: np.ndarray, speed: float) -> np.ndarray:
    """True on every stretch slower than ``speed`` inside which the speed changes sign.

    >>> _reversing_stretches(np.array([2., .5, -.5, -2., -.5, -.6, -2.]), 1.0)
    array([False,  True,  True, False, False, False, False])
    """
    slow = np.abs(w) < speed
    out = np.zeros(len(w), bool)
    for a, b in dv.runs(slow):
        seg = w[a:b]
        if seg.max() > 0 > seg.min() or (a > 0 and b < len(w) and w[a - 1] * w[b] < 0):
            out[a:b] = True
    return out


def _short_speed(angle: np.ndarray, dt_s: float) -> np.ndarray:
    """The angle's central difference over ``SHORT_SPEED_SPAN`` samples (ends: one-sided):
    below the standstill speed (1 count per 6 samples) exactly when no count changed."""
    th = np.asarray(angle, float)
    h = SHORT_SPEED_SPAN // 2
    if len(th) <= 2 * h:
        return np.gradient(th, dt_s)
    idx = np.arange(len(th))
    hi, lo = np.minimum(idx + h, len(th) - 1), np.maximum(idx - h, 0)
    return (th[hi] - th[lo]) / ((hi - lo) * dt_s)


def _held(angle: np.ndarray, samples: int) -> np.ndarray:
    """True on every sample of a stretch of at least ``samples`` equal angle readings (no
    encoder count changed).

    >>> _held(np.array([0., 1., 1., 1., 2.]), 3)
    array([False,  True,  True,  True, False])
    """
    th = np.asarray(angle, float)
    # runs of zero steps (the standstill finder on the one-sample difference): n readings
    # are n - 1 steps, and a step's run holds the readings on both its sides
    still = dv.standstill(np.diff(th), np.finfo(float).tiny, min_samples=samples - 1) > 0
    held = np.zeros(len(th), bool)
    held[:-1] |= still
    held[1:] |= still
    return held


def _pushed(current: np.ndarray, current_noise: float, width: int) -> np.ndarray:
    """Samples where the drive pushes: the current's running mean over ``width`` samples
    beyond ``STUCK_CURRENT_SIGMAS`` x its own noise (current_noise / sqrt(width)).

    Why the running mean, not the dwell's median |i|: static friction holds any current
    below the breakaway, and a dwell whose current passes through zero (a reversing
    speed loop ramping from +16 mA to the −79 mA breakaway over 65 ms, robustness seed 3
    case 62's input motor, noise 7 mA) had a median within 3 sigma and stayed in with
    zero friction: a residual of up to 60 mA, correlated over the dwell (Kt ±1.7 %)."""
    m = max(int(width), 1)
    mean = ndimage.uniform_filter1d(np.asarray(current, float), m, mode="nearest")
    return np.abs(mean) > STUCK_CURRENT_SIGMAS * current_noise / np.sqrt(m)


def smoothing_half_width(dt_s: float) -> int:
    """Half-width (samples) of the zero-phase speed estimate near reversals: 10 ms of
    data (10 samples at 1 kHz, as tuned there), at least 3 samples. A fixed 10 samples
    spans 210 ms at 100 Hz, smears a joint's dwell at a reversal into the motion on
    either side and misplaces the Coulomb step: Fc −6 %, Fv +14 % on the robot-joint
    traces of ``bench accuracy`` (with 10 ms: see its real section).

    Parameters
    ----------
    dt_s : sample period.

    Returns
    -------
    int

    References
    ----------
    A. Savitzky and M. J. E. Golay, "Smoothing and differentiation of data by simplified least squares procedures", Anal. Chem. 36(8), 1964, pp. 1627-1639

    Examples
    --------
    >>> smoothing_half_width(1e-3), smoothing_half_width(1e-2)
    (10, 3)

    """
    return max(3, int(round(0.010 / dt_s)))


def count_reversals(velocity: np.ndarray, moving: np.ndarray | None = None) -> int:
    """Speed sign changes between moving stretches (a dwell's chatter counts once).

    Parameters
    ----------
    velocity : the run's speed.
    moving : 0 while sticking (those samples are skipped).

    Returns
    -------
    int

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md)

    Examples
    --------
    >>> count_reversals([1.0, 1.0, -1.0, -1.0, 1.0])
    2

    """
    w = np.asarray(velocity, float)
    if moving is not None:
        w = w[moving > 0]
    s = np.sign(w[np.abs(w) > 0.02 * top_speed(w)]) if len(w) else w
    return int(np.sum(s[1:] != s[:-1])) if len(s) > 1 else 0


def top_speed(velocity: np.ndarray) -> float:
    """The run's top speed (99.5th percentile of |w|), in the trace's own units.

    Parameters
    ----------
    velocity : speeds (any unit).

    Returns
    -------
    float

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md)

    Examples
    --------
    >>> top_speed([0.0, 1.0, -2.0]) > 1.9
    True

    """
    return max(float(np.percentile(np.abs(velocity), 99.5)), 1e-300)


def standstill_speed(position: np.ndarray, velocity: np.ndarray, dt_s: float) -> float:
    """Speed below which the rotor counts as sticking: 1 encoder count per 6 samples
    (the encoder step read from the data), else a small share of the top speed.

    Parameters
    ----------
    position, velocity : angle and speed (the trace's units).
    dt_s : sample period.

    Returns
    -------
    float
        Speed threshold in the trace's unit per second.

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md)

    Examples
    --------
    >>> standstill_speed(th, w, 1e-3)   # doctest: +SKIP

    """
    q = encoder_resolution(position)
    if q > 0:
        return STANDSTILL_COUNTS_PER_SAMPLE * q / dt_s
    return STANDSTILL_TOP_FRACTION * top_speed(velocity)


def _white_noise_variance(x: np.ndarray) -> float:
    """White-noise variance from the second difference (var = 6σ² for white noise),
    with a robust (MAD) scale so steps and spikes do not inflate it."""
    d2 = x[2:] - 2 * x[1:-1] + x[:-2]
    mad = float(np.median(np.abs(d2 - np.median(d2))))
    return (1.4826 * mad) ** 2 / 6.0


def _encoder_accel_noise(th: np.ndarray, dt: float, taps: np.ndarray) -> float:
    """rms acceleration that encoder quantisation alone produces after the filter."""
    q = encoder_resolution(th)
    h = np.convolve([1.0, -2.0, 1.0], taps) / dt ** 2
    return q / np.sqrt(12.0) * float(np.sqrt(h @ h))


def speed_range(velocity_rad_s: np.ndarray) -> list[float]:
    """[low, high] speed a run covered (0.5th/99.5th percentiles, so a glitch does not
    stretch it): where its friction losses D ω + Tc s(ω) were actually identified.

    Parameters
    ----------
    velocity_rad_s : the run's speeds.

    Returns
    -------
    list of two float
        [low, high].

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md)

    Examples
    --------
    >>> speed_range([1.0, 2.0, 3.0])[1] <= 3.0
    True

    """
    lo, hi = np.percentile(velocity_rad_s, [0.5, 99.5])
    return [float(lo), float(hi)]


def encoder_resolution(position_rad: np.ndarray) -> float:
    """Encoder step (rad) from the gaps between distinct angle increments; 0 if the
    angle does not look quantised.

    Parameters
    ----------
    position_rad : sampled angle.

    Returns
    -------
    float
        The encoder step (0: not quantised).

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md)

    Examples
    --------
    >>> import numpy as np
    >>> round(encoder_resolution(np.arange(100) * 0.01), 6)
    0.0
    >>> q = 2 * np.pi / 2**17                 # a 17-bit encoder, printed to 1e-8 rad
    >>> th = np.round(np.round(np.cumsum(np.random.default_rng(0).integers(-3, 4, 500)) * q, 8), 8)
    >>> round(encoder_resolution(th) / q, 3)
    1.0

    """
    steps = np.diff(np.asarray(position_rad[:200_000], float))
    scale = float(np.max(np.abs(steps))) if len(steps) else 0.0
    if scale == 0:
        return 0.0
    # relative rounding: the position's unit is the user's (rad, deg, mm, m)
    d = np.unique(np.round(steps / scale, 9)) * scale
    gaps = np.diff(d)
    gaps = gaps[gaps > 1e-8 * scale]
    if not len(gaps):
        return 0.0
    digit = float(gaps.min())
    # A file that prints the angle with fixed decimals (k·q rounded to 1e-8 rad) rounds each
    # step by up to two of its digits: the increments then sit in narrow clusters one
    # encoder step apart, and the smallest gap is the print's digit, not the encoder's
    # step (a 2^17-count joint encoder read as 1e-8 rad: its standstill band 300x too narrow)
    edges = np.flatnonzero(np.diff(d) > 3 * digit)
    centres = np.array([c.mean() for c in np.split(d, edges + 1)])
    if len(centres) < 2:
        return digit
    q = float(np.diff(centres).min())
    if q < 20 * digit:
        return digit
    k = np.round(centres / q)           # refined over every cluster: one step's centre is off by a digit
    q = float(np.sum(k * centres) / np.sum(k * k))
    off = np.abs(steps / q - np.round(steps / q)) * q
    return q if np.mean(off <= 2.5 * digit) >= 0.99 else digit
