"""Short-horizon simulation error, the held-out split and the data's noise floor.

Simulation (output) error: from the measured state at the start of each horizon
(``HORIZON_S`` long), the model's velocity is simulated forward from the measured
current alone and compared with the measured velocity.  Unlike equation error it is
not dominated by twice-differentiated encoder noise, so it does not credit spurious
effects on clean data.

Noise floor: what a perfect model would still show, from the data's own noise —
the current-measurement noise integrated through Kt/J (a random walk, variance
growing with the step m in the horizon) plus the velocity estimates' noise at both
ends:  var e(m) = m (Kt/J dt s_i)^2 + s_w0^2 + s_w^2 (s_w0: the initial estimate's).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import savgol_filter

from . import fastsim
from .nominal import VELOCITY_WINDOW, Model, Signals, sg_derivative_kernel

#: Simulation horizon (re-initialised from the measured state), seconds.
HORIZON_S = 0.1
#: Blocks alternate between the two folds; each block is this long, seconds.
BLOCK_S = 0.5
#: Held-out horizons start every HORIZON_S / OVERLAP (they overlap; the significance
#: test in verdict.py widens its variance for that).
OVERLAP = 4


@dataclass(frozen=True)
class Fold:
    """One way of splitting: fit on ``fit_mask`` (horizons ``fit_starts``),
    score on horizons ``score_starts`` that lie wholly in the other blocks."""

    fit_mask: np.ndarray
    fit_starts: np.ndarray
    score_starts: np.ndarray


@dataclass(frozen=True)
class Split:
    """Two-fold cross-fitting over alternating blocks: every block is held out once,
    so the whole trace is scored, always by a model fitted without it."""

    folds: tuple[Fold, ...]
    horizon: int
    stride: int

    @property
    def score_starts(self) -> np.ndarray:
        return np.concatenate([f.score_starts for f in self.folds])


def split(sig: Signals) -> Split:
    """Blocks dealt to the two folds by excitation: ranked by how hard the motor
    accelerates in them, alternately — so each fold holds half of the transients.
    Plain alternation put every step of a 1 s square wave (a reversing speed command)
    into the even blocks: the odd fold, fitted on steady speed alone, could not know
    Kt/J and its held-out error on the steps left a Coulomb trace at 6x the floor."""
    n = len(sig)
    H = max(5, int(round(HORIZON_S / sig.dt_s)))
    per_block = max(2 * H, int(round(BLOCK_S / sig.dt_s)))
    if n < 8 * per_block:  # short trace: shrink blocks to keep >= 8 of them
        per_block = max(2 * H, n // 8)
    block = np.arange(n) // per_block
    # excitation per block: mean squared change of velocity (the same ranking in any unit)
    dw2 = np.append(np.diff(sig.velocity_rad_s), 0.0) ** 2
    energy = np.bincount(block, dw2) / np.bincount(block)
    rank = np.empty(len(energy), int)
    rank[np.argsort(-energy, kind="stable")] = np.arange(len(energy))
    block = rank[block]          # fold = rank parity (below): every other block by excitation
    stride = max(1, H // OVERLAP)
    # the velocity estimate is one-sided within half its window of either end
    edge = VELOCITY_WINDOW
    starts = np.arange(edge, n - H - 1 - edge, stride)
    inside = block[starts] == block[starts + H]
    folds = []
    for parity in (0, 1):
        fit_mask = block % 2 == parity
        # fit horizons overlap like the scored ones: on a 2 s trace the disjoint ones
        # were 9 per fold, too few to choose a cogging order on (one fold took 3 for a
        # true 6) or to refine on; the same data, every start used
        folds.append(Fold(fit_mask, starts[inside & fit_mask[starts]],
                          starts[inside & ~fit_mask[starts]]))
    return Split(tuple(folds), H, stride)


def simulate(sig: Signals, model: Model, starts: np.ndarray, horizon: int) -> np.ndarray:
    """Velocity error, shape (len(starts), horizon): the SG derivative of the angle error
    theta_sim - theta_meas (0 before the start), i.e. the simulated angle seen through the
    same velocity estimator as the measurement — so the estimator's attenuation of fast
    motion (a shaft resonance) is not counted as model error.

    Euler for the velocity, trapezoid for the angle (exact for the held current); a disk
    on a shaft (a term with ``advance``) is stepped exactly with the motor, the other
    torques held over the step (effects.two_mass_step): an explicit step of the lightly
    damped two-mass mode gains energy.  All horizons advance together.
    """
    dt = sig.dt_s
    n = len(sig)
    half = VELOCITY_WINDOW // 2
    h = sg_derivative_kernel(dt)
    plan = fastsim.plan(sig, model) if COMPILED else None
    if plan is not None:      # the same steps, compiled (fastsim)
        return fastsim.run(sig.position_rad, sig.current_a, model_initial_velocity(sig, model),
                           *plan[:1],
                           np.asarray(starts, np.int64), int(horizon), half, dt, h,
                           *plan[1:], FRICTION_SUBSTEPS)
    theta = sig.position_rad[starts].astype(float)
    omega = model_initial_velocity(sig, model)[starts]
    states = [t.init_state(sig, starts) for t in model.terms]
    steps = horizon + half
    eth = np.zeros((len(starts), half + 1 + steps))   # angle error from start - half
    coef = model.coef
    first = np.cumsum([0] + [len(t.names) for t in model.terms])
    shaft = next(((ti, first[ti]) for ti, t in enumerate(model.terms)
                  if hasattr(t, "advance")), None)
    for m in range(steps):
        idx = np.minimum(starts + m, n - 2)
        alpha = np.zeros_like(omega)
        coupling = np.zeros_like(omega)    # a shaft's torque at the step's start
        j = 0
        friction = []
        for t, st in zip(model.terms, states):
            k = len(t.names)
            if getattr(t, "opposes_motion", False):
                friction.append((t, st, coef[j:j + k]))
            else:
                for c, f in zip(coef[j:j + k], t.simulate(sig, theta, omega, idx, st)):
                    alpha += c * f
                    if hasattr(t, "advance"):
                        coupling += c * f
            j += k
        new = omega + dt * alpha
        if friction:
            new = _friction_step(sig, friction, theta, omega, alpha, idx, dt)
        j = 0
        for ti, t in enumerate(model.terms):   # rigid contacts (a disk in a gap)
            if hasattr(t, "couple"):
                new, states[ti] = t.couple(states[ti], coef[j], theta, omega, new, dt)
            j += len(t.names)
        states = [t.step_state(st, theta, omega, dt) for t, st in zip(model.terms, states)]
        if shaft is not None:   # the rest (current, friction...) held as the mean acceleration u
            ti, j = shaft
            u = (new - omega) / dt - coupling
            theta, new, states[ti] = model.terms[ti].advance(states[ti], coef[j:j + 2],
                                                             theta, omega, u, dt)
        else:
            theta = theta + 0.5 * dt * (omega + new)
        omega = new
        eth[:, half + 1 + m] = theta - sig.position_rad[idx + 1]
    # err[:, k-1] = sum_j h_j eth(k + j), k = 1..horizon
    err = np.zeros((len(starts), horizon))
    for jj, hj in enumerate(h):
        err += hj * eth[:, 1 + jj:1 + jj + horizon]
    return err


#: Simulate through the compiled path (fastsim) whenever every term has a spec.
COMPILED = True

#: Sub-steps of the friction within one sample step.  A sign-like friction flips within
#: the step where the velocity crosses zero; evaluated once per step (at its start or
#: end) the flip is up to a sample early or late, and on a fast reversal that error
#: (~Tc/J dt/2 of velocity) outweighs the noise floor — the fit then mends it with a
#: spurious current delay.
FRICTION_SUBSTEPS = 8


def _friction_step(sig, friction, theta, omega, alpha, idx, dt):
    """Velocity after one step with the other torques' acceleration ``alpha`` held and
    the friction terms integrated in sub-steps, linearly implicit in the friction's
    slope: a near-sign friction (Tc/J dt >> eps) stops the motion without chattering
    and sticks while the other torques are below it."""
    h = dt / FRICTION_SUBSTEPS
    w = omega
    for _ in range(FRICTION_SUBSTEPS):
        fr = np.zeros_like(omega)
        sl = np.zeros_like(omega)
        for t, st, cs in friction:
            for c, f, g in zip(cs, *t.value_slope(sig, theta, w)):
                fr += c * f
                sl += c * g
        w = w + h * (alpha + fr) / (1.0 - h * np.minimum(sl, 0.0))
    return w


@dataclass(frozen=True)
class NoiseFloor:
    """Noise levels estimated from the data and the floor of the simulation error."""

    current_noise_a: float
    velocity_noise_rad_s: float
    floor_var: np.ndarray          # per horizon step m = 1..H, (rad/s)^2

    @property
    def mse(self) -> float:
        return float(self.floor_var.mean())


def _hf_noise(x: np.ndarray, window: int, order: int) -> float:
    """Std of white noise on ``x`` from its residual about a local polynomial fit."""
    resid = x - savgol_filter(x, window, order)
    # residual variance = noise var * (1 - h0) for an SG smoother with centre weight h0
    h0 = savgol_filter(np.eye(window)[window // 2], window, order)[window // 2]
    mad = 1.4826 * np.median(np.abs(resid - np.median(resid)))
    sd = min(mad, float(np.std(resid)))
    return float(sd / np.sqrt(max(1.0 - h0, 1e-6)))


def lattice_step(theta: np.ndarray, max_divisor: int = 64) -> float | None:
    """The encoder's step if every angle is a multiple of one (None otherwise).

    The largest q = dmin/k (dmin the smallest non-zero change) that all samples sit on.
    """
    # relative tolerances only: the unit of the angle is the user's (rad, deg, m...)
    scale = float(np.max(np.abs(theta))) or 1.0
    steps = np.abs(np.diff(theta))
    steps = steps[steps > 1e-12 * scale]
    if not steps.size:
        return None
    dmin = float(np.min(steps))
    x = theta - theta[0]
    for k in range(1, max_divisor + 1):
        q = dmin / k
        if q < 1e-9 * scale:    # finer than float64 CSV digits can hold a lattice
            break
        for span in (1e3, 1e5, np.inf):  # refine q on ever wider ranges (file rounding)
            near = np.abs(x / q) < span
            n = np.round(x[near] / q)
            if np.any(n):
                q = float(np.sum(x[near] * n) / np.sum(n * n))
        frac = x / q - np.round(x / q)
        if np.max(np.abs(frac)) < 0.05:
            return q
    return None


#: Polynomial order of the velocity estimate that starts each horizon.  The order-2
#: estimate (VELOCITY_WINDOW samples) loses 12 % of a 40 Hz and 42 % of an 80 Hz motion;
#: started from it, a clean broadband (chirp) trace sat at 4.5x its noise floor.  The
#: order-4 estimate over the same window passes those (at ~2.9x the noise gain).
INIT_ORDER = 4


def initial_velocity(sig: Signals) -> np.ndarray:
    """Velocity each simulated horizon starts from (order-INIT_ORDER SG derivative)."""
    w = sig.cache.get("initial_velocity")
    if w is None:
        w = savgol_filter(sig.position_rad, VELOCITY_WINDOW, INIT_ORDER, deriv=1,
                          delta=sig.dt_s)
        sig.cache["initial_velocity"] = w
    return w


def model_initial_velocity(sig: Signals, model: Model) -> np.ndarray:
    """Each horizon's starting velocity with what the estimator cannot see added back.

    The SG estimate (``initial_velocity``) passes slow motion but not a fast periodic
    ripple (cogging at order 6 and 300 rad/s is 290 Hz, where the order-4 estimate
    keeps a fraction G of it): started from it, every horizon carries the missing
    (1 - G) of the ripple velocity as a constant error — 2.3x the floor on our own
    --sim calibration with the cogging in the model.  Terms that know their ripple
    (``ripple_velocity``) return it per coefficient; it is added here, so fit and
    score see the state the model itself implies."""
    w = initial_velocity(sig)
    first = 0
    for t in model.terms:
        k = len(t.names)
        cols = t.ripple_velocity(sig) if hasattr(t, "ripple_velocity") else None
        if cols is not None:
            w = w + sum(c * x for c, x in zip(model.coef[first:first + k], cols))
        first += k
    return w


def missed_share(ripple_rad_s: np.ndarray, dt_s: float) -> np.ndarray:
    """1 - G: the share of a sinusoidal velocity at ``ripple_rad_s`` (angular frequency)
    that the INIT_ORDER SG derivative misses; G = sum_j h_j sin(W dt j) / (W dt)."""
    from scipy.signal import savgol_coeffs

    h = savgol_coeffs(VELOCITY_WINDOW, INIT_ORDER, deriv=1, use="dot")
    j = np.arange(len(h)) - len(h) // 2
    x = np.abs(np.asarray(ripple_rad_s, float)) * dt_s
    g = np.ones_like(x)
    ok = x > 1e-9
    g[ok] = np.sin(np.outer(x[ok], j)) @ h / x[ok]
    return 1.0 - g


def velocity_noise(angle_noise_rad: float, dt_s: float, order: int = 2) -> float:
    """Std of the SG velocity estimate for white angle noise (noise gain ||h||/dt)."""
    from scipy.signal import savgol_coeffs

    h = savgol_coeffs(VELOCITY_WINDOW, order, deriv=1)
    return float(angle_noise_rad * np.sqrt(np.sum(h ** 2)) / dt_s)


def end_noise_var(angle_noise_rad: float, dt_s: float) -> float:
    """Velocity-noise variance a simulated horizon's error carries from its two ends:
    the initial estimate (INIT_ORDER) and the measured one it is compared with (2)."""
    return (velocity_noise(angle_noise_rad, dt_s, INIT_ORDER) ** 2
            + velocity_noise(angle_noise_rad, dt_s) ** 2)


def current_noise(sig: Signals) -> float:
    """Std of the current's white measurement noise (memoised on the trace)."""
    if "current_noise" not in sig.cache:
        sig.cache["current_noise"] = _hf_noise(sig.current_a, 7, 2)
    return sig.cache["current_noise"]


def noise_floor(sig: Signals, kt_over_j: float, horizon: int) -> NoiseFloor:
    """Floor of the simulation error from the current and angle noise in the data."""
    s_i = current_noise(sig)
    s_th = _hf_noise(sig.position_rad, 9, 3)
    q = lattice_step(sig.position_rad)
    if q:  # a quantised angle: uniform noise of one step (the residual misses it at low speed)
        s_th = max(s_th, q / np.sqrt(12.0))
    s_w = velocity_noise(s_th, sig.dt_s)
    m = np.arange(1, horizon + 1)
    var = m * (kt_over_j * sig.dt_s * s_i) ** 2 + end_noise_var(s_th, sig.dt_s)
    return NoiseFloor(s_i, float(s_w), var)


def horizon_mse(err: np.ndarray) -> np.ndarray:
    """Mean squared error of each horizon."""
    return np.mean(err ** 2, axis=1)


#: Most fit horizons used when refining coefficients on simulation error (speed).
REFINE_HORIZONS = 120


def refine(sig: Signals, model: Model, starts: np.ndarray, horizon: int,
           fixed: tuple[int, ...] = ()) -> Model:
    """Refine the coefficients of ``model`` on simulation error over the fit horizons
    ``starts``: Gauss-Newton from the equation-error fit (diagnosis notes: fit by
    equation error, refine on simulation error), a numerical Jacobian and a halving
    line search.  No trust region: the equation-error fit can sit many of its own
    standard errors away — the current's hold fraction, which integrated equation error
    sees only at window ends, came out 0.1-0.4 where simulation error says 1, and a
    trust region sized in those standard errors never got there (a spurious current
    delay then "explained" the rest).  A hold fraction stays within [0, 1] (a causal
    sampler cannot extrapolate).  ``fixed`` coefficient indices are left alone.
    Deterministic."""
    if len(starts) > REFINE_HORIZONS:  # evenly thinned, not random
        starts = starts[np.linspace(0, len(starts) - 1, REFINE_HORIZONS).round().astype(int)]
    if len(starts) < 3:
        return model
    c0 = np.asarray(model.coef, float)
    free = [j for j in range(len(c0)) if j not in fixed]
    if not free:
        return model
    scale = np.abs(c0[free]) + 1e-12
    if model.cov is not None:
        scale = np.maximum(scale * 1e-3, np.sqrt(np.abs(np.diag(model.cov)))[free] + 1e-12)
    taps = (type(model.terms[0]).__name__ == "CurrentTaps" and 0 in free and 1 in free)

    def coef(x):
        c = c0.copy()
        c[free] = c0[free] + x * scale
        if taps:   # keep the hold fraction a1 / (a0 + a1) in [0, 1]
            a = c[0] + c[1]
            h = np.clip(c[1] / a, 0.0, 1.0) if a else 0.5
            c[0], c[1] = a * (1.0 - h), a * h
        return c

    def resid(x):
        e = simulate(sig, Model(model.terms, coef(x), model.cov), starts, horizon)
        return np.nan_to_num(e.ravel(), nan=1e6, posinf=1e6, neginf=-1e6)

    x = np.zeros(len(free))
    r = resid(x)
    cost0 = cost = float(r @ r)
    step = 1e-3
    for _ in range(GN_ITERATIONS):
        J = np.column_stack([(resid(x + step * e) - r) / step for e in np.eye(len(free))])
        dx = np.linalg.lstsq(J, -r, rcond=None)[0]
        for t in (1.0, 0.5, 0.25):
            rt = resid(x + t * dx)
            ct = float(rt @ rt)
            if ct < cost:
                break
        else:
            break
        done = ct > (1.0 - 1e-4) * cost
        x, r, cost = x + t * dx, rt, ct
        if done:
            break
    if not cost < cost0:
        return model
    # the equation-error estimate is kept unless the simulation error shows its bias:
    # fitting noise alone lowers the cost by ~k of n horizons' worth; BIC charges that
    # (Schwarz 1978).  On a 2 s trace (9 fit horizons) a free refinement of cogging
    # fitted the noise of the fit fold and left held-out error 2.5x the floor where the
    # equation-error fit left 1.1x.  The current's hold fraction is always refined:
    # equation error sees it only at window ends and is known to be biased there
    n = independent_horizons(starts, horizon)
    if not taps and n * np.log(cost / cost0) + len(free) * np.log(max(n, 2.0)) > 0:
        return model
    return Model(model.terms, coef(x), model.cov)


def independent_horizons(starts: np.ndarray, horizon: int) -> float:
    """How many disjoint horizons' worth of data overlapping ``starts`` cover."""
    gaps = np.minimum(np.diff(np.sort(np.asarray(starts))), horizon)
    return float((np.sum(gaps) + horizon) / horizon) if len(starts) else 0.0


#: Gauss-Newton iterations of ``refine`` (the simulation error is nearly linear in the
#: coefficients: one step does most of it).
GN_ITERATIONS = 3
