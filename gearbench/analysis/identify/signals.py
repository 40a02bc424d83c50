"""One run's signals through one zero-phase FIR (``_prepare``) and the cutoff chosen
from the motion's own band (``default_cutoff``)."""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ...errors import TraceError
from .. import derivatives as dv
from .drive_loop import _period_kick_current, _setpoint_steps
from .samples import (CREEP_TOP_FRACTION, _below_current_limit, _encoder_accel_noise, _reverses,
                      _white_noise_variance, equation_weight, smoothing_half_width, speed_range,
                      standstill_speed, top_speed)


# The common filter's cutoff: at most 40 Hz and a tenth of the rate, and no more than
# MOTION_BAND_FACTOR x the motion's own band (``default_cutoff``). Under a position or speed
# loop what lies above the motion's band is the loop's answer to disturbances, which
# correlates with the equation error (closed-loop bias); the motion itself lies below
# (a decade holds the odd harmonics a Coulomb sign adds up to the 9th; the IDIM practice).
MOTION_BAND_FACTOR = 10.0
MOTION_BAND_SHARE = 0.99       # the band: below it this share of the velocity's variance
MIN_FILTER_RUNS = 8            # the filter at most 1/8 of the run (its taps ≈ 5.5·rate/cutoff)


@dataclass
class _Signals:
    """One run's filtered, aligned signals (``_prepare``)."""

    th: np.ndarray              # angle, first sample subtracted
    dt: float
    cutoff_hz: float
    taps: np.ndarray
    w_smooth: np.ndarray        # speed at every raw sample
    moving: np.ndarray          # equation weight: 0 on stuck/breakaway stretches, else 1
    fs: dict                    # filtered signals, ``consistent_derivatives`` layout
    reverses: bool
    noise_var_raw: float        # white current-noise variance, A²
    source: str
    i_raw: np.ndarray | None = None   # raw current (weighted form: the lag refit filters it again)
    current_mean: bool = False        # each current sample the mean over the period ending at it

    @property
    def n(self) -> int:
        return len(self.fs["acceleration"])

    @property
    def at(self) -> slice:
        """Raw samples under the filtered ones."""
        half = (len(self.taps) - 1) // 2
        return slice(half + 1, half + 1 + self.n)

    def matched(self, rows: np.ndarray, match=dv.match_samples) -> np.ndarray:
        """Rows through ``match``, the equation weight and the FIR (as ``fs``)."""
        if self.i_raw is None:
            return dv.matched_filter(rows * self.moving, self.taps)
        x = match(np.atleast_2d(rows)) * self.moving
        return dv.filter_valid_rows(x, self.taps)[:, 1:-1]

    def matched_current(self, rows: np.ndarray) -> np.ndarray:
        """Current-like rows through the current's match (``current_mean``:
        ``derivatives.match_period_means``), the equation weight and the FIR."""
        return self.matched(rows, dv.match_period_means if self.current_mean else dv.match_samples)

    @property
    def current_match(self) -> np.ndarray:
        return dv.PERIOD_MEAN_MATCH if self.current_mean else dv.SECOND_DIFFERENCE_MATCH

    @cached_property
    def speed_range(self) -> list[float]:
        """Speeds the run covered (once per run: a percentile of n samples is not free)."""
        return speed_range(self.w_smooth)

    @cached_property
    def accel_noise(self) -> float:
        """rms acceleration encoder quantisation alone produces after the filter."""
        return _encoder_accel_noise(self.th, self.dt, self.taps)


def _prepare(t, th, i, *, cutoff_hz, friction_width_rad_s, command, source,
             current_limit_a=None, kick_a_per_rad_s=None, drive_velocity=None,
             current_mean=False, period_kick=None) -> _Signals:
    """Filter every signal with one zero-phase FIR (``derivatives.consistent_derivatives``).

    The Coulomb step is integrated at its sub-sample reversal instant as the angle's second
    difference sees it (``derivatives.coulomb_regressor``). While the rotor sticks
    static friction balances whatever the drive gives (any value up to the breakaway),
    and sign(θ') does not describe the breakaway either: those samples, with a margin,
    are weighted out of the raw equation before the filter (``equation_weight``,
    ``derivatives.weighted_derivatives``), so the filtered equation stays exact on the
    rest. A stuck stretch carries no Kt information; the intervals count what remains.
    A rotor at rest with no current (before a speed step from rest) is not stuck: it
    stays in with its friction term 0."""
    dt = float(np.median(np.diff(t)))
    rate = 1.0 / dt
    cutoff_hz = cutoff_hz or default_cutoff(t, th)
    taps = dv.lowpass_fir(cutoff_hz, rate)
    if len(t) < len(taps) + 50:
        raise TraceError(f"{source}: only {len(t)} samples, need at least {len(taps) + 50} "
                         f"at {rate:.4g} Hz for the {cutoff_hz:.3g} Hz filter; record a longer run")
    th = th - th[0]
    hw = smoothing_half_width(dt)
    w_smooth = dv.smooth_velocity(th, dt, half_width=hw)
    extra = {} if command is None else {"command": np.asarray(command, float)}
    reverses = _reverses(w_smooth)
    if kick_a_per_rad_s and command is not None:
        # the current the sampled equation holds for (``kick_coefficient``; spreading each
        # kick over the equations it reaches moved Kt < 0.04 %, D < 4 % of itself)
        i = np.asarray(i, float) + kick_a_per_rad_s * dt * _setpoint_steps(
            extra["command"], dt) * _below_current_limit(
            i, current_limit_a, float(np.sqrt(_white_noise_variance(i))))
    noise_var = _white_noise_variance(i)     # once: a robust scale of n samples is not free
    if friction_width_rad_s:
        # Legacy: smoothed sign of the raw speed, sampled, then 3-tap matched.
        w_raw = np.empty_like(th)
        w_raw[1:-1] = (th[2:] - th[:-2]) / (2 * dt)
        w_raw[0], w_raw[-1] = w_raw[1], w_raw[-2]
        moving = np.ones_like(th)
        fs = dv.consistent_derivatives(
            th, {"current": i, "sign": np.tanh(w_raw / friction_width_rad_s), "moving": moving,
                 **extra}, dt, taps)
    else:
        w_still = standstill_speed(th, w_smooth, dt)
        moving = equation_weight(w_smooth, w_still, dt, current=i,
                                 current_noise=float(np.sqrt(noise_var)),
                                 angle=th, creep_speed=CREEP_TOP_FRACTION * top_speed(w_smooth))
        # a rotor at rest that nothing pushes stays in the equation (J θ'' = Kt i = 0, a
        # speed step from rest), its friction is zero there, not ±Tc
        sliding = 1.0 - (dv.standstill(w_smooth, w_still) > 0) * (moving == 1.0)
        matched = {"sign": dv.coulomb_regressor(
            th, dt, velocity=dv.refine_reversals(th, w_smooth, half_width=hw)) * sliding}
        if command is not None:
            matched["command_sign"] = np.sign(extra["command"]) * sliding
            matched["setpoint_step"] = _setpoint_steps(extra["command"], dt) * _below_current_limit(
                i, current_limit_a, float(np.sqrt(noise_var)))
        # the masked offset column is needed only where an offset is fitted (reversing)
        others = {"current": i, **({"moving": np.ones_like(th)} if reverses else {})}
        kicks = period_kick is not None and command is not None
        if current_mean or kicks:
            # the current matched here (period means: ``derivatives.match_period_means``)
            # where it is not the instant samples' plain match: kicks are added to it
            match = dv.match_period_means if current_mean else dv.match_samples
            matched["current"] = match(others.pop("current"))
        if kicks:
            # what the match cannot see of the setpoint's shape within each period (a
            # stepping drive's front-loaded kicks, an interpolating one's kinks:
            # ``declared_period_kick``); none where the drive sits at its current limit
            # (``_below_current_limit``). Kept apart too: the lag refit re-matches the raw
            # current and adds it back
            kick = _period_kick_current(np.asarray(period_kick, float), extra["command"]) * (
                _below_current_limit(i, current_limit_a, float(np.sqrt(noise_var))))
            matched["current"] = matched["current"] + kick
            matched["current_kick"] = kick
        if drive_velocity is not None:
            others["drive_velocity"] = np.asarray(drive_velocity, float)
        fs = dv.weighted_derivatives(th, others, dt, taps, moving, matched=matched,
                                     unweighted=extra)
        return _Signals(th, dt, cutoff_hz, taps, w_smooth, moving, fs, reverses,
                        noise_var, source, i_raw=np.asarray(i, float),
                        current_mean=bool(current_mean))
    return _Signals(th, dt, cutoff_hz, taps, w_smooth, moving, fs, reverses,
                    noise_var, source)


def motion_band_hz(time_s: np.ndarray, position: np.ndarray, share: float = MOTION_BAND_SHARE) -> float:
    """The frequency below which ``share`` of the velocity's variance lies: the motion's band.

    Periodogram of the angle's first difference (Hann window, its mean removed); any
    angle unit. Stick-slip and steps spread the velocity's power, so their band is wide.

    Parameters
    ----------
    time_s, position : the run's samples.
    share : the share of the variance below the band's edge.

    Returns
    -------
    float
        Hz (0 for a run that does not move).

    References
    ----------
    P. Stoica and R. Moses, *Spectral Analysis of Signals*, Prentice Hall 2005, sec. 2.6 (windowed periodogram)

    Examples
    --------
    >>> t = np.arange(6000) * 0.01
    >>> round(motion_band_hz(t, np.sin(2 * np.pi * 0.5 * t)), 1)   # the window's leakage
    0.5
    """
    t = np.asarray(time_s, float)
    dt = float(np.median(np.diff(t)))
    w = np.diff(np.asarray(position, float)) / dt
    if len(w) < 8 or not np.any(w != w[0]):
        return 0.0
    w = w - w.mean()
    power = np.abs(np.fft.rfft(w * np.hanning(len(w)))) ** 2
    power[0] = 0.0
    cum = np.cumsum(power)
    f = np.fft.rfftfreq(len(w), dt)
    return float(f[min(int(np.searchsorted(cum, share * cum[-1])), len(f) - 1)])


def default_cutoff(time_s: np.ndarray, position: np.ndarray) -> float:
    """The common filter's default cutoff: min(40 Hz, rate/10, MOTION_BAND_FACTOR × the
    motion's band), never so low that the filter exceeds 1/MIN_FILTER_RUNS of the run.

    Above the motion's band a closed loop (the position loop of a robot joint, the speed
    loop of a drive) puts its answer to disturbances into the angle and the current; that
    content correlates with the equation error and biases least squares (measured on the
    second joint simulator's PID-loop wrist at 100 Hz: J −4.6 % at 10 Hz, −3.2 % at its
    motion-band cutoff 5.5 Hz; the first simulator's wrist −6.2 % → −2.0 %). A multisine
    calibration up to 10 Hz, or any run faster than 4 Hz, keeps 40 Hz.

    Parameters
    ----------
    time_s, position : the run's samples.

    Returns
    -------
    float
        Hz.

    References
    ----------
    M. Gautier, "Dynamic identification of robots with power model", Proc. IEEE ICRA 1997
    (the filter's cutoff about ten times the joint dynamics' band in inverse-dynamics
    least squares); U. Forssell and L. Ljung, "Closed-loop identification revisited",
    Automatica 35, 1999 (the bias of direct least squares under feedback).

    Examples
    --------
    >>> t = np.arange(6000) * 0.01
    >>> round(default_cutoff(t, np.sin(2 * np.pi * 0.5 * t)))   # a 0.5 Hz sine at 100 Hz
    5
    >>> round(default_cutoff(t, np.sin(2 * np.pi * 8 * t)), 1)  # rate/10
    10.0
    """
    t = np.asarray(time_s, float)
    rate = 1.0 / float(np.median(np.diff(t)))
    cutoff = dv.rate_cutoff(rate)
    band = motion_band_hz(t, position)
    if band > 0:
        shortest = 5.5 * rate * MIN_FILTER_RUNS / max(len(t), 1)
        cutoff = min(cutoff, max(MOTION_BAND_FACTOR * band, shortest))
    return float(cutoff)
