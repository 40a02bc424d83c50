"""Measured signals, linear-in-parameters motor models and the paper's nominal model.

The paper's model (eqs. 1-5) with current as input is

    theta'' = (Kt/J) i - (D/J) theta' - (C/J) theta.

Every model here is written the same way, as an acceleration that is linear in its
coefficients, ``alpha = sum_j coef_j * feature_j(theta, omega, current, state)``; a
candidate effect adds features (or replaces the current features).  Coefficients are
fitted by *integrated* equation error: the velocity change over a short window
against the window sums of the features (paper eq. 10's least squares, integrated so
that no twice-differentiated angle enters).  How current is held between samples is
fitted as two taps ``a0 i[k] + a1 i[k+1]`` (hold fraction ``a1/(a0+a1)``).
"""
from __future__ import annotations

import json
from collections import OrderedDict
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import scipy.linalg
from scipy.signal import savgol_filter

from ..calibration import with_short_keys
from ...errors import ProfileError, TraceError
from ...trace import Trace
from .fastsim import SPRING, VISC

#: Savitzky-Golay window for the velocity estimate, in samples (odd).
VELOCITY_WINDOW = 9
#: Integration window of the equation-error fit, in seconds.
FIT_WINDOW_S = 0.02


@dataclass(frozen=True)
class Signals:
    """One single-motor trace, ready for analysis (SI units, regular sampling)."""

    time_s: np.ndarray
    position_rad: np.ndarray
    velocity_rad_s: np.ndarray      # Savitzky-Golay derivative of the encoder angle
    current_a: np.ndarray
    dt_s: float
    source: str = "<array>"
    #: radians of rotor angle per position unit (1 for rad, pi/180 for deg, 2 pi / lead
    #: for a linear axis with a known lead); None: the unit is not an angle and no lead
    #: was given, so nothing periodic in the rotor angle (cogging, ripple orders) can be
    #: tested — never assumed
    rad_per_unit: float | None = 1.0
    #: motor revolutions per load revolution (the gear ratio between this motor and
    #: its load); None: not given — the position is then taken as the load's angle
    load_ratio: float | None = None
    # per-trace memo (current maps, window rows, disk tracks): tied to this object, so
    # nothing computed for one trace can leak into another's diagnosis
    cache: dict = field(default_factory=dict, compare=False, repr=False)

    def __len__(self) -> int:
        return len(self.time_s)


#: Position units the diagnoser accepts -> radians of motor angle per unit (None: a
#: length, whose relation to the motor angle only a lead can give).
POSITION_UNITS: dict[str, float | None] = {
    "rad": 1.0, "deg": np.pi / 180.0, "rev": 2.0 * np.pi,
    "m": None, "mm": None, "um": None}


def angle_scale(unit: str = "rad", travel_per_rev: float | None = None) -> float | None:
    """Radians of motor angle per position unit, from what the user stated: the unit
    and, for a linear axis (or a gear between motor and encoder), the travel per motor
    revolution in that unit.  None when the unit is a length and no lead is given."""
    if unit not in POSITION_UNITS:
        raise TraceError(f"position unit {unit!r} unknown; use one of "
                         f"{', '.join(POSITION_UNITS)}")
    if travel_per_rev is not None:
        if not (np.isfinite(travel_per_rev) and travel_per_rev > 0):
            raise TraceError(f"travel per revolution must be a positive number of {unit} "
                             f"per motor revolution (got {travel_per_rev!r})")
        return 2.0 * np.pi / float(travel_per_rev)
    return POSITION_UNITS[unit]


def prepare(trace: Trace, rad_per_unit: float | None = 1.0,
            load_ratio: float | None = None) -> Signals:
    """Validate a single-motor trace and estimate velocity (SG derivative, order 2).
    ``rad_per_unit``, ``load_ratio``: see ``Signals`` (from the user's stated position
    unit and gear ratio)."""
    if load_ratio is not None and not (np.isfinite(load_ratio) and load_ratio > 0):
        raise TraceError(f"gear ratio must be a positive number of motor revolutions per "
                         f"load revolution (got {load_ratio!r})")
    trace.validate(("position_rad", "current_a"), min_samples=200)
    dt = trace.dt_s
    theta = np.asarray(trace["position_rad"], float)
    current = np.asarray(trace["current_a"], float)
    if np.ptp(theta) == 0.0:
        raise TraceError(f"{trace.source}: column 'position_rad' never changes; the motor did "
                         f"not move — record a run with motion")
    if np.ptp(current) == 0.0:
        raise TraceError(f"{trace.source}: column 'current_a' is constant; check the current "
                         f"channel and its scaling")
    omega = savgol_filter(theta, VELOCITY_WINDOW, 2, deriv=1, delta=dt)
    return Signals(trace.time_s, theta, omega, current, dt, trace.source, rad_per_unit,
                   None if load_ratio is None else float(load_ratio))


# --------------------------------------------------------------------- model terms
@dataclass(frozen=True)
class Term:
    """A group of features of a linear-in-parameters acceleration model.

    ``measured(sig)`` gives the features along the whole trace from measured
    signals (for the equation-error fit); ``simulate(sig, theta, omega, idx, state)``
    gives them along a simulation (vectors over horizons, ``idx`` = sample index).
    Stateful terms (a disk on a shaft) also implement ``init_state``/``step_state``.
    """

    names: tuple[str, ...] = ()

    def measured(self, sig: Signals) -> list[np.ndarray]:
        return self.simulate(sig, sig.position_rad, sig.velocity_rad_s,
                             np.arange(len(sig)), None)

    def simulate(self, sig, theta, omega, idx, state) -> list[np.ndarray]:
        raise NotImplementedError

    def init_state(self, sig: Signals, idx: np.ndarray):
        return None

    def fast(self, sig: Signals) -> list | None:
        """Per coefficient: (state-free feature over the whole trace or None, parts
        [(kind, multiplier, *params)]) for the compiled simulation (fastsim); None when
        the term needs the numpy path (a state of its own)."""
        return None

    def step_state(self, state, theta, omega, dt_s: float):
        return state


def current_map(sig: Signals, delay: int = 0, sat_a: float = 0.0,
                sat_off: float = 0.0) -> np.ndarray:
    """Current driving the torque: measured current advanced by ``delay`` samples
    (undoing a measurement delay) and optionally saturated, i/(1+(i/i_sat)^2)."""
    i = sig.current_a
    if delay:
        i = np.concatenate([i[delay:], np.full(delay, i[-1])])
    if sat_a > 0:
        # the motor saturates on its true current: the measured one less a sensor
        # offset ``sat_off`` (the offset term itself stays a separate constant)
        t = i - sat_off
        i = t / (1.0 + (t / sat_a) ** 2) + sat_off
    return i


@dataclass(frozen=True)
class CurrentTaps(Term):
    """Kt/J * current, held between samples: a0 i[k] + a1 i[k+1] (paper eq. 5, B~)."""

    names: tuple[str, ...] = ("a0", "a1")
    delay: int = 0
    sat_a: float = 0.0
    sat_off: float = 0.0

    def _i(self, sig):
        return held_current(sig, self.delay, self.sat_a, self.sat_off)

    def simulate(self, sig, theta, omega, idx, state):
        i0, i1 = self._i(sig)
        return [i0[idx], i1[idx]]

    def fast(self, sig):
        i0, i1 = self._i(sig)
        return [(i0, []), (i1, [])]


def held_current(sig: Signals, delay: int = 0, sat_a: float = 0.0, sat_off: float = 0.0):
    """(i[k], i[k+1]) of the mapped current, memoised on the trace."""
    key = ("current", delay, sat_a, sat_off)
    if key not in sig.cache:
        i = current_map(sig, delay, sat_a, sat_off)
        sig.cache[key] = (i, np.append(i[1:], i[-1]))
    return sig.cache[key]


@dataclass(frozen=True)
class HeldCurrent(Term):
    """Kt/J * ((1-h) i[k] + h i[k+1]) with the hold fraction h fixed in [0, 1]: used when
    the free taps would put h outside [0, 1], i.e. extrapolate the current — a causal
    sampler cannot, and free taps would silently absorb a measurement delay."""

    names: tuple[str, ...] = ("a",)
    hold: float = 0.5
    delay: int = 0
    sat_a: float = 0.0
    sat_off: float = 0.0

    def simulate(self, sig, theta, omega, idx, state):
        i0, i1 = held_current(sig, self.delay, self.sat_a, self.sat_off)
        return [(1.0 - self.hold) * i0[idx] + self.hold * i1[idx]]

    def fast(self, sig):
        i0, i1 = held_current(sig, self.delay, self.sat_a, self.sat_off)
        return [((1.0 - self.hold) * i0 + self.hold * i1, [])]


@dataclass(frozen=True)
class Viscous(Term):
    """-D/J * omega."""

    names: tuple[str, ...] = ("d_over_j",)

    def simulate(self, sig, theta, omega, idx, state):
        return [-omega]

    def fast(self, sig):
        return [(None, [(VISC, 1.0)])]


@dataclass(frozen=True)
class Spring(Term):
    """-C/J * theta (the paper's spring to ground)."""

    names: tuple[str, ...] = ("c_over_j",)

    def simulate(self, sig, theta, omega, idx, state):
        return [-theta]

    def fast(self, sig):
        return [(None, [(SPRING, 1.0)])]


@dataclass(frozen=True)
class Model:
    """Terms + coefficients; ``fixed`` marks coefficients not refitted."""

    terms: tuple[Term, ...]
    coef: np.ndarray = field(default_factory=lambda: np.zeros(0))
    cov: np.ndarray | None = None

    @property
    def names(self) -> list[str]:
        return [n for t in self.terms for n in t.names]

    def params(self) -> dict[str, float]:
        return {n: float(c) for n, c in zip(self.names, self.coef)}

    def sigma(self) -> dict[str, float]:
        if self.cov is None:
            return {}
        return {n: float(np.sqrt(max(v, 0.0))) for n, v in zip(self.names, np.diag(self.cov))}


def measured_features(sig: Signals, terms) -> np.ndarray:
    cols = [f for t in terms for f in t.measured(sig)]
    return np.column_stack(cols) if cols else np.zeros((len(sig), 0))


@dataclass(frozen=True)
class Windows:
    """Start indices of the equation-error integration windows (all inside a mask)."""

    start: np.ndarray
    length: int
    key: int = 0        # content hash, for memoising rows on the trace


def fit_windows(sig: Signals, mask: np.ndarray) -> Windows:
    """Windows of FIT_WINDOW_S, stride a quarter window, lying wholly where ``mask``."""
    n = len(sig)
    L = max(4, int(round(FIT_WINDOW_S / sig.dt_s)))
    stride = max(1, L // 4)
    starts = np.arange(0, n - L - 1, stride)
    bad = np.concatenate([[0], np.cumsum(~mask)])
    ok = bad[starts + L + 1] - bad[starts] == 0
    return Windows(starts[ok], L, hash((L, starts[ok].tobytes())))


@lru_cache(maxsize=8)
def _sg_derivative_kernel(dt_s: float) -> np.ndarray:
    from scipy.signal import savgol_coeffs

    h = savgol_coeffs(VELOCITY_WINDOW, 2, deriv=1, delta=dt_s, use="dot")
    h.setflags(write=False)
    return h


def sg_derivative_kernel(dt_s: float) -> np.ndarray:
    """Dot-product weights of the SG velocity estimate on theta[k-W//2 .. k+W//2]."""
    return _sg_derivative_kernel(float(dt_s)).copy()


def sg_interval_kernel() -> np.ndarray:
    """Weights c_m (m = -W//2 .. W//2-1) with w_sg[k] = sum c_m * mean velocity over
    [t_{k+m}, t_{k+m+1}]: the SG derivative as a smoother of interval velocities.

    The SG estimate attenuates fast motion (~10 % at 40 Hz); an equation error that
    compares it with unsmoothed model accelerations reads that loss as a model error
    (it hid shaft resonances).  Smoothing the features with c_m makes both sides alike.
    """
    h = sg_derivative_kernel(1.0)
    half = VELOCITY_WINDOW // 2
    # theta[k+j] - theta[k] = sum of the intervals between: c_m = sum_{j>m} h_j (m >= 0),
    # -sum_{j<=m} h_j (m < 0); the c_m sum to 1
    js = np.arange(-half, half + 1)
    return np.array([h[js > m].sum() if m >= 0 else -h[js <= m].sum()
                     for m in range(-half, half)])


@lru_cache(maxsize=1)
def _velocity_smoothing_kernel() -> np.ndarray:
    c = sg_interval_kernel()
    k = 0.5 * (np.append(c, 0.0) + np.insert(c, 0, 0.0))
    k.setflags(write=False)
    return k


def velocity_smoothing_kernel() -> np.ndarray:
    """Centred weights (m = -W//2 .. W//2) that smooth per-sample velocity changes
    F[q] = (w[q+1] - w[q]) / dt like the SG estimate: c_m convolved with [1/2, 1/2]
    (a change of interval-mean velocity spans two such steps, half each)."""
    return _velocity_smoothing_kernel().copy()


def _window_operator(n: int, win: Windows, dt_s: float):
    """Sparse (windows x samples) matrix A with A @ F = the smoothed window sums of
    ``integrated_rows``: each row is the box of length L convolved with the smoothing
    kernel (starts clipped to the trace at its ends, as a sum of shifted boxes)."""
    from scipy.sparse import csr_matrix

    L, s = win.length, win.start
    kern = _velocity_smoothing_kernel()
    half = VELOCITY_WINDOW // 2
    shifts = np.arange(len(kern)) - half
    inner = (s - half >= 0) & (s + shifts[-1] <= n - L)
    # interior rows: one combined kernel of length L + W - 1 starting at s - half
    w = np.convolve(kern, np.ones(L))
    ri = np.flatnonzero(inner)
    rows = [np.repeat(ri, len(w))]
    cols = [(s[ri, None] - half + np.arange(len(w))).ravel()]
    data = [np.tile(w, len(ri))]
    for r in np.flatnonzero(~inner):      # the few rows at the trace's ends
        for k, km in enumerate(kern):
            a = int(np.clip(s[r] + shifts[k], 0, n - L))
            rows.append(np.full(L, r))
            cols.append(np.arange(a, a + L))
            data.append(np.full(L, km))
    A = csr_matrix((np.concatenate(data) * dt_s, (np.concatenate(rows), np.concatenate(cols))),
                   shape=(len(s), n))
    A.sum_duplicates()
    return A


def integrated_rows(sig: Signals, F: np.ndarray, win: Windows):
    """Rows of the integrated equation error: dw = dt * sum(F) over each window, with
    F smoothed like the SG velocity estimate (so w_sg's own attenuation cancels).
    Smoothing commutes with the window sums, so rows are one sparse product with the
    window operator (memoised per window set on the trace)."""
    L, s = win.length, win.start
    F = np.asarray(F, float).reshape(len(sig), -1)
    key = ("window_op", win.key, L)
    A = sig.cache.get(key) if win.key else None
    if A is None:
        A = _window_operator(F.shape[0], win, sig.dt_s)
        if win.key:
            sig.cache[key] = A
    X = np.asarray(A @ F)
    y = sig.velocity_rad_s[s + L] - sig.velocity_rad_s[s]
    return X, y


#: Integrated rows of this many recent non-nominal terms kept per trace (the chain's
#: chosen effects enter every later fit; scanned terms are many, so bounded).
ROWS_LRU = 256


def _term_rows(sig: Signals, term: Term, win: Windows):
    """Integrated rows of one term, memoised on the trace: grid scans reuse the
    nominal's columns (kept), and the chain's chosen effects' (least recently used
    dropped first: an EMPS diagnosis recomputed a friction term's interval means
    ~10,000 times)."""
    key = ("rows", win.key, term)
    rows = sig.cache.get(key)
    if rows is not None:
        return rows
    lru = sig.cache.setdefault("rows_lru", OrderedDict())
    rows = lru.get(key)
    if rows is not None:
        lru.move_to_end(key)
        return rows
    rows = integrated_rows(sig, measured_features(sig, [term]), win)
    if isinstance(term, (CurrentTaps, HeldCurrent, Viscous, Spring, GivenNominal)):
        sig.cache[key] = rows
    else:
        lru[key] = rows
        if len(lru) > ROWS_LRU:
            lru.popitem(last=False)
    return rows


def solve(X: np.ndarray, y: np.ndarray, overlap: float = 4.0):
    """Least squares with a covariance inflated for overlapping windows."""
    scale = np.sqrt((X ** 2).sum(0))
    scale[scale == 0] = 1.0
    Xs = X / scale
    # normal equations of the column-scaled problem when well conditioned (a few k x k
    # products: lstsq's SVD of the windows x k matrix took ~5 ms a call, thousands of
    # calls a diagnosis); the SVD where conditioning would cost digits
    G = Xs.T @ Xs
    if np.linalg.cond(G) < 1e8:
        coef = np.linalg.solve(G, Xs.T @ y)
    else:   # complete orthogonal factorisation: minimum norm, cheaper than the SVD
        coef = scipy.linalg.lstsq(Xs, y, lapack_driver="gelsy", check_finite=False)[0]
    coef = coef / scale
    r = y - X @ coef
    dof = max(len(y) - X.shape[1], 1)
    s2 = float(r @ r) / dof * overlap
    try:
        cov = s2 * np.linalg.pinv(X.T @ X)
    except np.linalg.LinAlgError:  # pragma: no cover - pinv rarely fails
        cov = None
    return coef, float(r @ r), cov


def fit_model(sig: Signals, terms, win: Windows, fixed: dict[int, float] | None = None) -> tuple[Model, float]:
    """Fit the coefficients of ``terms`` by integrated equation error on ``win``.

    ``fixed`` maps coefficient index -> value kept constant (a given nominal model).
    Returns the model and the residual sum of squares (for grid scans).
    """
    parts = [_term_rows(sig, t, win) for t in terms]
    X = np.hstack([p[0] for p in parts])
    y = parts[0][1]
    fixed = dict(fixed or {})
    model, rss = _fit_linear(X, y, terms, fixed)
    # a hold fraction outside [0, 1] extrapolates the current (see HeldCurrent): pin it
    h = hold_fraction(model)
    if np.isfinite(h) and not 0.0 <= h <= 1.0:
        hc = float(np.clip(h, 0.0, 1.0))
        t0 = terms[0]
        if isinstance(t0, CurrentTaps):
            terms = [HeldCurrent(hold=hc, delay=t0.delay, sat_a=t0.sat_a, sat_off=t0.sat_off),
                     *terms[1:]]
            return fit_model(sig, terms, win, {j - 1: v for j, v in fixed.items() if j > 1})
        if isinstance(t0, GivenNominal) and 1 not in fixed:
            return fit_model(sig, terms, win, {**fixed, 1: hc})
    return model, rss


def _fit_linear(X, y, terms, fixed):
    free = [j for j in range(X.shape[1]) if j not in fixed]
    coef = np.zeros(X.shape[1])
    for j, v in fixed.items():
        coef[j] = v
        y = y - X[:, j] * v
    cov = np.zeros((X.shape[1], X.shape[1]))
    if free:
        c, rss, cv = solve(X[:, free], y)
        coef[free] = c
        if cv is not None:
            cov[np.ix_(free, free)] = cv
    else:
        rss = float(y @ y)
    return Model(tuple(terms), coef, cov), rss


# ------------------------------------------------------------------ nominal model
def nominal_terms(spring: bool = False, delay: int = 0, sat_a: float = 0.0,
                  hold: float | None = None, sat_off: float = 0.0,
                  drag: bool = True) -> list[Term]:
    """Current (free taps, or a fixed hold fraction), viscous friction (``drag``: D is
    fitted; False: D held at 0, its bound, when the free fit came out negative), the
    spring."""
    cur = (CurrentTaps(delay=delay, sat_a=sat_a, sat_off=sat_off) if hold is None else
           HeldCurrent(hold=float(hold), delay=delay, sat_a=sat_a, sat_off=sat_off))
    terms: list[Term] = [cur, Viscous()] if drag else [cur]
    if spring:
        terms.append(Spring())
    return terms


@dataclass(frozen=True)
class GivenModel:
    """A nominal model from a file: Kt/J, D/J, C/J (1/s^2 per A, 1/s, 1/s^2)."""

    kt_over_j: float
    d_over_j: float
    c_over_j: float = 0.0
    source: str = "<model>"


def load_model(path: str | Path) -> GivenModel:
    """Read MODEL.json: ``{"Kt": N m/A, "J": kg m^2, "D": N m s/rad[, "C": N m/rad]}``
    (optionally under ``"params"``), or the ratios ``kt_over_j``, ``d_over_j``."""
    p = Path(path)
    try:
        data = json.loads(p.read_text())
    except FileNotFoundError:
        raise ProfileError(f"{p}: model file not found; check the --model path") from None
    except (OSError, json.JSONDecodeError) as exc:
        raise ProfileError(f"{p}: not valid JSON ({exc}); write the model as "
                           f'{{"Kt": ..., "J": ..., "D": ...}}') from None
    if isinstance(data, dict) and isinstance(data.get("params"), dict):
        data = data["params"]
    if not isinstance(data, dict):
        raise ProfileError(f"{p}: expected a JSON object with Kt, J, D")
    # calibrate --json writes J_kgm2, D_nm_s_per_rad (older files J, D)
    data = with_short_keys(data)
    try:
        if "kt_over_j" in data:
            g = GivenModel(float(data["kt_over_j"]), float(data.get("d_over_j", 0.0)),
                           float(data.get("c_over_j", 0.0)), str(p))
        else:
            J = float(data["J"])
            if J <= 0:
                raise ProfileError(f"{p}: field 'J' must be > 0 (kg m^2)")
            g = GivenModel(float(data["Kt"]) / J, float(data.get("D", 0.0)) / J,
                           float(data.get("C", 0.0)) / J, str(p))
    except KeyError as exc:
        raise ProfileError(f"{p}: missing field {exc}; give Kt (N m/A), J (kg m^2) and D "
                           f"(N m s/rad), or kt_over_j and d_over_j") from None
    except (TypeError, ValueError):
        raise ProfileError(f"{p}: Kt, J, D must be numbers") from None
    # a non-physical model is refused, never used silently (issue 24)
    if not g.kt_over_j > 0:
        raise ProfileError(f"{p}: Kt/J = {g.kt_over_j:.4g} must be > 0 (Kt > 0, J > 0)")
    if g.d_over_j < 0 or g.c_over_j < 0:
        raise ProfileError(f"{p}: D and C must be >= 0 (got D/J = {g.d_over_j:.4g}, "
                           f"C/J = {g.c_over_j:.4g})")
    return g


def kt_over_j(model: Model) -> float:
    """Kt/J of an identified model (free taps or a pinned hold)."""
    p = model.params()
    return p["a"] if "a" in p else p.get("a0", 0.0) + p.get("a1", 0.0)


def hold_fraction(model: Model) -> float:
    """Share of i[k+1] in the current driving sample k (0 = zero-order hold)."""
    t0 = model.terms[0] if model.terms else None
    p = model.params()
    if isinstance(t0, HeldCurrent):
        return t0.hold
    if isinstance(t0, GivenNominal):
        return p["hold"]
    a = kt_over_j(model)
    return p.get("a1", 0.0) / a if a else float("nan")


def physical(model: Model) -> dict[str, float]:
    """Nominal parameters as the paper writes them (ratios to J) plus the hold fraction."""
    p = model.params()
    return {"kt_over_j": kt_over_j(model), "d_over_j": p.get("d_over_j", 0.0),
            "c_over_j": p.get("c_over_j", 0.0), "hold_fraction": hold_fraction(model)}


@dataclass(frozen=True)
class GivenNominal(Term):
    """A given nominal model as one feature with coefficient ``scale`` (1 = as given;
    free = an inertia mismatch, J_true = J/scale) plus a fitted current hold."""

    names: tuple[str, ...] = ("scale", "hold")
    kt_over_j: float = 0.0
    d_over_j: float = 0.0
    c_over_j: float = 0.0
    delay: int = 0
    sat_a: float = 0.0
    sat_off: float = 0.0

    def simulate(self, sig, theta, omega, idx, state):
        i0, i1 = held_current(sig, self.delay, self.sat_a, self.sat_off)
        base = self.kt_over_j * i0[idx] - self.d_over_j * omega - self.c_over_j * theta
        return [base, self.kt_over_j * (i1[idx] - i0[idx])]

    def fast(self, sig):
        i0, i1 = held_current(sig, self.delay, self.sat_a, self.sat_off)
        return [(self.kt_over_j * i0, [(VISC, self.d_over_j), (SPRING, self.c_over_j)]),
                (self.kt_over_j * (i1 - i0), [])]


# ------------------------------------------------------------- batched grid scans
def _batched_rss(Xb: np.ndarray, y: np.ndarray, fixed: dict[int, float], E: np.ndarray,
                 k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """RSS, base coefficients and the candidates' own coefficients (G, k) of G
    least-squares fits [Xb | E_g] at once.

    ``E`` holds the G candidates' k columns side by side (m, G*k).  The free base
    columns are projected out once (QR), so each candidate is a k-column fit to the
    projected target — the same RSS as ``fit_model`` on the stacked matrix (Frisch-
    Waugh-Lovell), for a grid in one pass instead of G rebuilt fits.
    """
    y0 = y - sum((Xb[:, j] * v for j, v in fixed.items()), np.zeros_like(y))
    free = [j for j in range(Xb.shape[1]) if j not in fixed]
    G = E.shape[1] // k
    esc = np.sqrt((E ** 2).sum(0))
    esc[esc == 0] = 1.0
    Es = E / esc
    if free:
        bsc = np.sqrt((Xb[:, free] ** 2).sum(0))
        bsc[bsc == 0] = 1.0
        Q, R = np.linalg.qr(Xb[:, free] / bsc)
        qy, qE = Q.T @ y0, Q.T @ Es
        yr, Er = y0 - Q @ qy, Es - Q @ qE
    else:
        yr, Er = y0, Es
    Eg = Er.reshape(len(y), G, k).transpose(1, 0, 2)            # (G, m, k)
    # normal equations per candidate (k x k: a batched pinv of the (m, k) stacks took
    # ~75 ms a scan), pseudo-inverted so a degenerate candidate stays finite
    EtE = np.einsum("gmk,gml->gkl", Eg, Eg)
    beta = np.einsum("gkl,gl->gk", np.linalg.pinv(EtE), np.einsum("gmk,m->gk", Eg, yr))
    resid = yr[None, :] - np.einsum("gmk,gk->gm", Eg, beta)
    rss = np.einsum("gm,gm->g", resid, resid)
    coef = np.zeros((G, Xb.shape[1]))
    for j, v in fixed.items():
        coef[:, j] = v
    if free:
        rhs = qy[None, :] - np.einsum("pgk,gk->gp", qE.reshape(len(free), G, k), beta)
        coef[:, free] = np.linalg.solve(R, rhs.T).T / bsc
    return rss, coef, beta / esc.reshape(G, k)


def scan_rss(sig: Signals, base_terms, win: Windows, fixed: dict[int, float] | None,
             E: np.ndarray, k: int, positive: tuple[int, ...] = ()) -> np.ndarray:
    """Equation-error RSS of ``base_terms`` + each of G candidates' k extra columns
    (``E``: integrated rows, (m, G*k)), exactly as ``fit_model`` would score each —
    including its pinning of a hold fraction outside [0, 1] to the nearer bound.
    Candidates whose extra coefficients listed in ``positive`` come out <= 0 (a
    non-physical negative stiffness) score +inf."""
    parts = [_term_rows(sig, t, win) for t in base_terms]
    Xb, y = np.hstack([p[0] for p in parts]), parts[0][1]
    fixed = dict(fixed or {})
    rss, coef, beta = _batched_rss(Xb, y, fixed, E, k)
    if positive:
        rss = np.where(np.all(beta[:, list(positive)] > 0, axis=1), rss, np.inf)
    t0 = base_terms[0]
    if isinstance(t0, CurrentTaps):
        a = coef[:, 0] + coef[:, 1]
        with np.errstate(invalid="ignore", divide="ignore"):
            h = np.where(a != 0, coef[:, 1] / a, np.nan)
    elif isinstance(t0, GivenNominal) and 1 not in fixed:
        h = coef[:, 1]
    else:
        return rss
    for hc, bad in ((0.0, h < 0.0), (1.0, h > 1.0)):
        g = np.flatnonzero(bad)
        if not g.size:
            continue
        cols = (g[:, None] * k + np.arange(k)).ravel()
        if isinstance(t0, CurrentTaps):   # HeldCurrent(hold=hc): one column
            Xp = np.column_stack([(1.0 - hc) * Xb[:, 0] + hc * Xb[:, 1], Xb[:, 2:]])
            fp = {j - 1: v for j, v in fixed.items() if j > 1}
        else:
            Xp, fp = Xb, {**fixed, 1: hc}
        rss[g] = np.where(np.isfinite(rss[g]), _batched_rss(Xp, y, fp, E[:, cols], k)[0], np.inf)
    return rss
