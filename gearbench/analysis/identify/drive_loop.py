"""What a drive's declared loop adds to its current: the setpoint-step kick, its period-mean
and interpolated forms, the speed loop's ripple, read from a trace's drive description."""
from __future__ import annotations


import numpy as np

from ...errors import TraceError
from .. import derivatives as dv
from .samples import _white_noise_variance, encoder_resolution


def kick_coefficient(kp_a_s_per_rad: float, current_lag_s: float, period_s: float,
                     loop_period_s: float) -> float:
    """The current kick of a drive that steps its speed setpoint each SYNC and samples its
    current at the SYNC instant, c in A per rad/s of setpoint step (ī = i + c·Δcmd).

    Derivation (the discrete loop within one period T): the sampled equation
    J Δ²θ_k = Kt ∫ i(t) tri(t − t_k) dt − … holds for the triangle-weighted current
    ĩ_k (``derivatives.match_samples`` takes it from samples of a piecewise-linear
    current). Against a drive that ramps to the new setpoint (reaching it at the last
    of its M = T/T_loop speed-loop ticks), stepping adds the P-command pulse
    Kp·Δcmd·p_m, p_m = 1 − (m+1)/M at tick m, through the first-order current loop
    (time constant τ) as g(u). The samples see g(nT), n ≥ 1 (the sample at t_k is taken
    before the period's first tick), the triangles its area: summed over the periods a
    kick reaches,

        c/Kp = (1/T)∫g du − Σ_{n≥1} g(nT) = mean_m p_m − g(T)/(1 − e^{−T/τ}),
        g(T) = Σ_m p_m (e^{−(T − t_{m+1})/τ} − e^{−(T − t_m)/τ}),  t_m = m T/M.

    The speed's own response to the kick within the period changes c by O(x·τ/T),
    x = Kp·Kt·T/J: with τ = 0 it is c/Kp = 1/x − 1/(e^x − 1) = 1/2 − x/12 + …, with
    τ ≥ 0.3 T the simulated drive's c/Kp stays within 0.6 % over x = 0.01–0.2, so one
    c serves both calibration runs. Noise-free (robustness seeds 4, 5: 15 forward
    drives) this c, instead of one fitted from the runs (``calibration.calibrate_motor``,
    current delay fitted), takes Kt from +0.10 ± 0.13 % (mean, rms) to +0.01 ± 0.04 %;
    Kp 10 % off moved Kt by 0.02–0.04 %. τ = 0: g is the pulse itself
    (c/Kp = (M−1)/(2M)).

    Examples
    --------
    >>> round(kick_coefficient(1.0, 0.6e-3, 1e-3, 0.25e-3), 3)
    0.124
    """
    m = max(1, int(round(period_s / loop_period_s)))
    p = 1.0 - (np.arange(m) + 1.0) / m
    if current_lag_s <= 0:
        return float(kp_a_s_per_rad * np.mean(p))
    t_m = np.arange(m + 1) * period_s / m
    g_t = float(np.sum(p * (np.exp(-(period_s - t_m[1:]) / current_lag_s)
                            - np.exp(-(period_s - t_m[:-1]) / current_lag_s))))
    return float(kp_a_s_per_rad * (np.mean(p) - g_t / -np.expm1(-period_s / current_lag_s)))


PERIOD_KICK_PERIODS = 8     # periods a step's pulse is followed over (the current loop's τ ≤ T here)
PERIOD_KICK_FINE = 64       # sub-steps per speed-loop tick for the pulse's shape


def period_mean_kick_weights(kp_a_s_per_rad: float, current_lag_s: float, period_s: float,
                             loop_period_s: float) -> np.ndarray:
    """What the period means' match misses of a drive that steps its speed setpoint each
    SYNC and reports its current as the period mean: weights w_n, n = −2 … 7 (A per rad/s
    of the setpoint step of the period ending n samples before), so that

        ĩ_k = match(m)_k + Σ_n w_n Δcmd_{k−n}.

    Derivation: the sampled equation J Δ²θ_k = Kt ∫ i(t) tri(t − t_k) dt − … holds for the
    triangle-weighted current ĩ_k; ``derivatives.PERIOD_MEAN_MATCH`` rebuilds it from the
    period means m_k, exactly for a current smooth across periods. Stepping adds in each
    period the P pulse Kp·Δcmd·p_m, p_m = 1 − (m+1)/M at tick m (against a drive that
    ramps, as ``kick_coefficient``), through the first-order current loop (τ): g(u), front-
    loaded in its period. With its period means G_n and the triangle's rising halves
    R_n = (1/T)∫ g·(u − nT)/T over period n (falling halves F_n = G_n − R_n),

        w_n = R_n + F_{n+1} − (−G_{n−1} + 13 G_n + 13 G_{n+1} − G_{n+2})/24.

    Σ w_n = 0: a steady acceleration's kicks are matched; a changing one's are not, and the
    closed loop's phase puts part of that in phase with θ''. At 250 Hz (robustness seed 8
    case 58's input drive, noise-free, 2^20 counts) b2 came out −0.151 % without the
    correction and −0.000 % with it (the exact triangle: +0.02 %), in both runs alike (x =
    Kp·Kt·T/J 0.63 and 0.20: the speed's own response within the period is left out); the
    bias grew with Kp (−0.06/−0.15/−0.26 % at Kp ×½/1/2), and at 1 kHz it is ≤ 0.02 %.

    Examples
    --------
    >>> w = period_mean_kick_weights(0.09, 0.42e-3, 4e-3, 0.25e-3)
    >>> len(w), abs(float(w.sum())) < 1e-12
    (10, True)
    """
    m = max(1, int(round(period_s / loop_period_s)))
    # a step against a ramp: the pulse 1 − (m+1)/M over one period, nothing after
    return _match_error(1.0 - (np.arange(m) + 1.0) / m, 0.0, "mean", kp_a_s_per_rad,
                        current_lag_s, period_s, loop_period_s)


def interpolated_kink_weights(kp_a_s_per_rad: float, current_lag_s: float, period_s: float,
                              loop_period_s: float) -> np.ndarray:
    """What the 3-tap match of instant current samples misses of a drive that ramps its
    speed setpoint linearly over each SYNC period: weights w_n, n = −2 … 7 (A per rad/s of
    the setpoint's rise over the period ending n samples before), so that

        ĩ_k = match(i)_k + Σ_n w_n Δcmd_{k−n}.

    Why: the ramps join with a kink at every SYNC, where the setpoint's slope changes by
    Δ²cmd/T; the speed loop's P gain passes the kinks into the current, and through the
    current loop (τ) the sample at the period's end sees them at one phase while the
    rotor integrates them over the triangle about it. ``derivatives.SECOND_DIFFERENCE_MATCH``
    ([1, 10, 1]/12, exact for a current smooth across samples) cannot see that. The
    weights are a unit ramp's P current (held per speed-loop tick, through τ) taken as the
    rotor sees it (triangle) less as the match sees it (samples at period ends); their
    steady part Σw — a smooth setpoint's hold and lag, a delay that the fitted current
    delay already takes for the whole current — is taken out, so Σw = 0.

    Measured noise-free (robustness seed 7 cases 1, 37 and 52, interpolating drives with
    instant current, 2^20 counts, no cogging): at 250 Hz b2 −0.157/−0.089/−0.144 % without,
    −0.004/−0.003/−0.015 % with them, unchanged at 1 kHz (≤ 0.014 % either way); at 100 Hz
    −1.12 % → −0.03 %; the same at Kp ×½ and ×2 and a 0.1 ms loop. A drive with no current
    lag (τ = 0) keeps −0.2 % at 250 Hz: its samples sit on the knots, and what remains is
    not this.

    Examples
    --------
    >>> w = interpolated_kink_weights(0.005, 0.3e-3, 4e-3, 0.25e-3)
    >>> len(w), abs(float(w.sum())) < 1e-12
    (10, True)
    """
    m = max(1, int(round(period_s / loop_period_s)))
    w = _match_error((np.arange(m) + 1.0) / m, 1.0, "instant", kp_a_s_per_rad,
                     current_lag_s, period_s, loop_period_s)
    steady = float(w.sum())
    w[1:3] -= steady / 2.0        # n = −1, 0: the slope at t_k, from the periods either side
    return w


def _match_error(first: np.ndarray, hold: float, current: str, kp_a_s_per_rad: float,
                 current_lag_s: float, period_s: float, loop_period_s: float) -> np.ndarray:
    """Triangle-weighted current less the match of its samples, n = −2 … 7, for a setpoint
    that is ``first`` (per speed-loop tick) over period 0 and ``hold`` after, times Kp,
    through a first-order current loop. ``current``: "mean" (period means, the 4-tap
    ``PERIOD_MEAN_MATCH``) or "instant" (the value at each period's end, the 3-tap match)."""
    from scipy.signal import lfilter

    m = len(first)
    per = m * PERIOD_KICK_FINE
    x = np.concatenate([np.repeat(first, PERIOD_KICK_FINE), np.full(per * (PERIOD_KICK_PERIODS - 1), hold)])
    if current_lag_s > 0:
        a = -np.expm1(-(loop_period_s / PERIOD_KICK_FINE) / current_lag_s)
        g = lfilter([a], [1.0, a - 1.0], x)
    else:
        g = x
    g = kp_a_s_per_rad * g.reshape(PERIOD_KICK_PERIODS, per)
    G = g.mean(axis=1)
    R = (g * ((np.arange(per) + 0.5) / per)).mean(axis=1)
    F = G - R
    E = g[:, -1]

    def pad(v):   # v_n at [n + 3]; before the step nothing, after it what it settled to
        return np.concatenate([np.zeros(3), v, np.full(3, v[-1])])
    Gp, Rp, Fp, Ep = pad(G), pad(R), pad(F), pad(E)
    n = np.arange(-2, PERIOD_KICK_PERIODS)
    tri = Rp[n + 3] + Fp[n + 4]
    # both matches start at sample k − 1
    seen, kernel = (Gp, dv.PERIOD_MEAN_MATCH) if current == "mean" else (Ep, dv.SECOND_DIFFERENCE_MATCH)
    return tri - sum(c * seen[n + 2 + j] for j, c in enumerate(kernel))


# drive kinds (setpoint, current) whose declared loop gives weights (``declared_period_kick``),
# and every kind whose loop the analysis uses (``declared_kick``: step, instant)
PERIOD_KICK_WEIGHTS = {("step", "mean"): period_mean_kick_weights,
                       ("interpolated", "instant"): interpolated_kink_weights}
LOOP_DRIVE_KINDS = (("step", "instant"), *PERIOD_KICK_WEIGHTS)


def _period_kick_current(weights: np.ndarray, command: np.ndarray) -> np.ndarray:
    """Σ_n w_n Δcmd_{k−n} (``period_mean_kick_weights``), Δcmd_k the setpoint step of the
    period ending at sample k: command[k] is applied during [t_k, t_{k+1}), so that step is
    command[k−1] − command[k−2]."""
    step = np.zeros(len(command))
    step[2:] = command[1:-1] - command[:-2]
    return np.convolve(step, weights)[2:2 + len(step)]


def _setpoint_steps(command: np.ndarray, dt: float) -> np.ndarray:
    """The speed setpoint's step at each SYNC, Δcmd_k / dt (rad/s², first sample 0).

    Why (a drive that steps its setpoint and samples its current at one instant):
    the rotor integrates the current over the period, J Δω = Kt ∫ i dt − ∫ f dt, so the
    torque equation holds for the period-mean current ī_k. With its speed loop ticking
    at t_m = t_{k−1} + m T/M (m = 0..M−1), a drive that applies each setpoint as a step
    commands Kp·Δcmd_k·(1 − (m+1)/M) more current at tick m than one that ramps to it
    (the P part of the error it sees); through a first-order current loop (time
    constant τ) that periodic kick has a period mean and an end-of-period value both
    proportional to Kp·Δcmd_k, with factors set by τ/T and M alone. A sample at the SYNC
    instant sees the kick's end value, the rotor its mean, hence to first order

        ī_k = i_k + c·Δcmd_k,   c = Kp·(h̄(τ/T, M) − h_T(τ/T, M)),

    with the same c for every run on that drive: the speed's own response to the kick
    within the period changes c by O(x), x = Kp·Kt·T/J (ideal current loop:
    c/Kp = 1/x − 1/(e^x − 1) = 1/2 − x/12 + …), but behind a current loop of τ ≥ 0.3 T
    c/Kp stays within 0.6 % over x = 0.01–0.2 (simulated steady speed ramp). Combined,
    Kt still comes out high by about x/100 of itself, x of the unloaded run (noise-free,
    robustness seeds 4+5, 15 forward drives: +0.03/+0.08/+0.22 % mean for x below 0.05,
    0.05–0.1, above 0.1), and the cause is the fitted c, not the relation: with the
    exact triangle-weighted current (no kick left) each run's fit still finds
    c ≈ 0.03 Kp and b2 low by up to 0.55 % (0.02 % without the term), and a drive
    that interpolates gets 0.07–0.10 Kp: nearly collinear with θ'', the term takes up
    misfit that differs between the runs. Where the drive declares its loop (Kp, τ,
    loop period), ``kick_coefficient`` gives c in closed form and it is added to the
    current, not fitted; the current delay is then fitted, as D and Tc need it even
    from the exact current (4 seed-7 motors noise-free: D +33…+212 % without, within
    5 % with): those 15 drives +0.005/−0.001/+0.045 %, and with the drawn noise 69
    forward kick motors of seeds 7+8 from +0.09 ± 0.14 % (mean, rms) to +0.02 ± 0.09 %.
    Without the declared loop (or on a reversing run, where the fitted term also takes
    up the zero crossing's misfit) Δcmd/T follows θ'' within one run (the loop follows
    its command), so ``calibration.share_setpoint_step``
    fits one c for both runs of a motor and Kt from their difference. An interpolating
    drive (c = 0) or a period-averaged current (the sample is ī_k) has no such term
    (robustness benchmark, seed 8 case 11 input: b2 of the unloaded run +0.87 % from
    the sample, +0.04 % from the period mean)."""
    d = np.zeros_like(command)
    d[1:] = np.diff(command) / dt
    return d


def drive_sampling(trace) -> str | None:
    """How the trace's drive sampled, as its description says (``meta["drive"]``:
    ``setpoint`` ``step``/``interpolated``, ``current`` ``instant``/``mean``): ``"kick"``
    when it steps its speed setpoint each SYNC *and* samples its current at one instant
    (``_setpoint_steps``: a setpoint-step term belongs in the model), ``"plain"`` when it
    says otherwise, None when it does not say. An optional ``current_limit_a`` (the
    current the drive clamps at) is read by ``calibration.calibrate_motor``.

    Raises TraceError naming the field for a value it does not know."""
    drive = trace.meta.get("drive")
    if not drive:
        return None
    known = {"setpoint": ("step", "interpolated"), "current": ("instant", "mean")}
    for key, values in known.items():
        v = drive.get(key)
        if v is not None and v not in values:
            raise TraceError(f"{trace.source}: meta drive.{key} is {v!r}; use one of "
                             f"{', '.join(values)} (or leave it out)")
    if drive.get("setpoint") is None or drive.get("current") is None:
        return None
    return "kick" if (drive["setpoint"], drive["current"]) == ("step", "instant") else "plain"


DRIVE_LOOP_KEYS = ("speed_kp_a_s_per_rad", "current_loop_time_constant_s", "speed_loop_period_s")


def speed_ripple_to_noise(trace) -> float | None:
    """How far the speed loop's quantisation ripple stands out of the current's noise.

    A drive that estimates its speed from the encoder's counts per loop period T sees
    one count q as a speed step q/T, which its P gain Kp turns into current: a ripple of
    rms Kp·q/(T·√12) (uniform quantisation error). Its ratio to the rest of the
    current's white noise (``_white_noise_variance`` of the recorded current, the ripple's
    own share taken out), or None where the drive does not declare its loop
    (``speed_kp_a_s_per_rad``, ``speed_loop_period_s``) or the angle shows no count.

    >>> speed_ripple_to_noise(trace)            # doctest: +SKIP
    5.8
    """
    drive = trace.meta.get("drive") or {}
    try:
        kp, period = float(drive["speed_kp_a_s_per_rad"]), float(drive["speed_loop_period_s"])
    except (KeyError, TypeError, ValueError):
        return None
    q = encoder_resolution(np.asarray(trace["position_rad"], float))
    if not (kp > 0 and period > 0 and q > 0):
        return None
    ripple_var = (kp * q / period) ** 2 / 12.0
    rest = _white_noise_variance(np.asarray(trace["current_a"], float)) - ripple_var
    return float("inf") if rest <= 0 else float(np.sqrt(ripple_var / rest))


def _declared_loop(trace) -> dict | None:
    """The speed loop a drive's description (``meta["drive"]``) declares,
    ``DRIVE_LOOP_KEYS`` → float, or None where it does not declare all three.

    Raises TraceError naming a declared value that is not a number ≥ 0 (> 0 for the gain
    and the loop period)."""
    drive = trace.meta.get("drive") or {}
    if not all(k in drive for k in DRIVE_LOOP_KEYS):
        return None
    values = {}
    for k in DRIVE_LOOP_KEYS:
        try:
            values[k] = float(drive[k])
        except (TypeError, ValueError):
            values[k] = float("nan")
        low_ok = values[k] >= 0 if k == "current_loop_time_constant_s" else values[k] > 0
        if not (np.isfinite(values[k]) and low_ok):
            raise TraceError(f"{trace.source}: meta drive.{k} is {drive[k]!r}; give a number "
                             f"{'>= 0' if k == 'current_loop_time_constant_s' else '> 0'} "
                             f"in SI units (or leave the drive's loop out)")
    return values


def declared_kick(trace) -> float | None:
    """The setpoint-step kick c (A per rad/s, ``kick_coefficient``) of a drive whose
    description (``meta["drive"]``) declares its loop: ``speed_kp_a_s_per_rad`` (speed-loop
    P gain), ``current_loop_time_constant_s`` and ``speed_loop_period_s``; None where it
    declares no kick (``drive_sampling``) or not all three.

    Raises TraceError naming a declared value that is not a number ≥ 0 (> 0 for the gain
    and the loop period)."""
    loop = _declared_loop(trace) if drive_sampling(trace) == "kick" else None
    if loop is None:
        return None
    period_s = float(np.median(np.diff(trace.time_s)))
    return kick_coefficient(loop["speed_kp_a_s_per_rad"], loop["current_loop_time_constant_s"],
                            period_s, loop["speed_loop_period_s"])


def kick_speed_response(trace, b2: float) -> float:
    """The relative size of what ``kick_coefficient`` leaves out on this run's drive: the
    speed's own response to the kick within the period, in its τ = 0 limit

        ε(x) = 1 − 2 (1/x − 1/(eˣ − 1)),   x = Kp·(Kt/J)·T

    (c/Kp is 1/x − 1/(eˣ − 1) there against the model's ½; x/6 for small x). 0 where the
    drive declares no loop. At 1 kHz x ≤ 0.2 (ε ≤ 0.033); at 100 Hz x reaches 1–2 (ε 0.16–
    0.31), and stepping, instant-sampling drives' Kt came out +0.8 … +5.5 % (robustness
    seeds 7 / 8, all positive, growing with x): ``calibration`` counts ε as part of the
    kick's relative uncertainty.

    Parameters
    ----------
    trace : a run whose ``meta["drive"]`` declares its loop.
    b2 : the run's Kt/J (rad/s² per A).

    Returns
    -------
    float

    Examples
    --------
    >>> round(float(1 - 2 * (1 / 1.75 - 1 / np.expm1(1.75))), 2)     # x = 1.75
    0.28
    """
    loop = _declared_loop(trace)
    if loop is None or not (np.isfinite(b2) and b2 > 0):
        return 0.0
    x = loop["speed_kp_a_s_per_rad"] * b2 * float(np.median(np.diff(trace.time_s)))
    return float(1.0 - 2.0 * (1.0 / x - 1.0 / np.expm1(x))) if x > 1e-9 else 0.0


def declared_period_kick(trace) -> np.ndarray | None:
    """The weights of what the current's match misses of the setpoint's shape within each
    period, where the drive's description declares its loop and says it steps its setpoint
    and reports the period mean (``period_mean_kick_weights``) or ramps it and reports an
    instant (``interpolated_kink_weights``); else None. Raises TraceError as
    ``declared_kick``."""
    drive = trace.meta.get("drive") or {}
    weights = PERIOD_KICK_WEIGHTS.get((drive.get("setpoint"), drive.get("current")))
    if drive_sampling(trace) != "plain" or weights is None:
        return None
    loop = _declared_loop(trace)
    if loop is None:
        return None
    period_s = float(np.median(np.diff(trace.time_s)))
    return weights(loop["speed_kp_a_s_per_rad"], loop["current_loop_time_constant_s"],
                   period_s, loop["speed_loop_period_s"])


def is_speed_command(trace) -> bool:
    """A ``command`` column is a speed setpoint when the trace says so (``meta`` mode
    ``velocity``, as the simulator and the station write it)."""
    mode = (trace.meta.get("sim") or {}).get("mode") or trace.meta.get("mode")
    return mode == "velocity"
