"""The candidate library: effects the paper's model ``J th'' + D th' + C th = Kt i`` lacks.

Each effect is one small class: ``grid`` (values of its nonlinear settings to scan —
a cogging order, a delay, a Stribeck speed...), ``build`` (the nominal terms plus its
own, linear in their coefficients) and ``describe`` (fitted parameters with 95 %
intervals, torques as current equivalents ``*_a`` = torque / Kt).  Coefficients are
per unit inertia (N m / J), so a torque T appears as T/J = (T/Kt) * (Kt/J).

Vocabulary: coulomb_friction, stribeck_friction, direction_friction,
position_friction, presliding_friction, cogging, torque_ripple,
current_offset, time_delay, kt_saturation, shaft_compliance, backlash,
encoder_quantization, inertia_mismatch.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, replace

import numba
import numpy as np

from . import fastsim as fs
from .nominal import GivenModel, GivenNominal, Model, Signals, Term, nominal_terms
from .nominal import kt_over_j as _kt_over_j

Z95 = 1.96
#: A feature must be material (mean magnitude) on at least this share of the trace
#: for its effect to be testable at all.
MIN_SUPPORT = 0.02


# ------------------------------------------------------------------- the nominal
@dataclass(frozen=True)
class Base:
    """The nominal model effects augment: identified (refitted with the effect) or
    given (kept fixed; only the effect's own coefficients are fitted).

    ``chosen``: effects already added by the diagnosis chain, ``((effect, hp), ...)``
    in the order added; their terms (and nominal settings such as a delay) are part
    of this base, so a new candidate is fitted together with all of them."""

    given: GivenModel | None = None
    spring: bool = False
    chosen: tuple = ()
    #: the current's hold fraction h (share of i[k+1] driving sample k), fixed once
    #: chosen on simulation error (simerror.refine); None: two free taps.  Integrated
    #: equation error sees h only at its windows' ends and misjudges it, which biased
    #: every candidate fitted that way (kt saturation behind an offset came out worse
    #: than none)
    hold: float | None = None

    def with_effect(self, effect: "Effect", hp: dict) -> "Base":
        return replace(self, chosen=(*self.chosen, (effect, dict(hp))))

    def with_settings(self, name: str, hp: dict) -> "Base":
        """The chosen effect ``name`` at new settings, in its place in the chain."""
        return replace(self, chosen=tuple((e, dict(hp)) if e.name == name else (e, h)
                                          for e, h in self.chosen))

    def settings(self, name: str) -> dict:
        return next(dict(h) for e, h in self.chosen if e.name == name)

    def without(self, name: str) -> "Base":
        return replace(self, chosen=tuple(c for c in self.chosen if c[0].name != name))

    @property
    def chosen_names(self) -> tuple[str, ...]:
        return tuple(e.name for e, _ in self.chosen)

    def _settings(self) -> tuple[int, float, float | None, float]:
        delay, sat, hold, off = 0, 0.0, self.hold, 0.0
        for _, hp in self.chosen:
            if "delay_tau" in hp:
                delay, hold = split_timing(hp["delay_tau"])
            sat = float(hp.get("kt_sat_a", sat))
            off = float(hp.get("kt_sat_offset_a", off))
        return delay, sat, hold, off

    def _core(self, delay: int | None, sat_a: float | None,
              hold: float | None = None, sat_off: float | None = None) -> list[Term]:
        d0, s0, h0, off = self._settings()
        off = off if sat_off is None else sat_off
        if delay is None:
            delay, hold = d0, h0
        sat_a = s0 if sat_a is None else sat_a
        if self.given is None:
            return nominal_terms(self.spring, delay, sat_a, hold, off)
        g = self.given
        return [GivenNominal(kt_over_j=g.kt_over_j, d_over_j=g.d_over_j,
                             c_over_j=g.c_over_j, delay=delay, sat_a=sat_a, sat_off=off)]

    def terms(self, delay: int | None = None, sat_a: float | None = None,
              hold: float | None = None, sat_off: float | None = None) -> list[Term]:
        terms = self._core(delay, sat_a, hold, sat_off)
        for effect, hp in self.chosen:
            terms += effect.chain_terms(hp)[0]
        return terms

    def fixed(self, free_scale: bool = False) -> dict[int, float]:
        free_scale = free_scale or "inertia_mismatch" in self.chosen_names
        out = {} if (self.given is None or free_scale) else {0: 1.0}
        j = sum(len(t.names) for t in self._core(None, None))
        for effect, hp in self.chosen:
            terms, fx = effect.chain_terms(hp)
            out.update({j + k: v for k, v in fx.items()})
            j += sum(len(t.names) for t in terms)
        return out

    def kt_over_j(self, model: Model) -> float:
        if self.given is None:
            return _kt_over_j(model)
        return self.given.kt_over_j * model.params()["scale"]


def _pm(model: Model, name: str, scale: float = 1.0) -> tuple[float, float]:
    p, s = model.params(), model.sigma()
    return p[name] * scale, Z95 * s.get(name, float("nan")) * abs(scale)


def _amp_phase(model: Model, ns: str, nc: str, scale: float) -> tuple[float, float, float]:
    """Amplitude (with 95 % half-width) and phase of s*sin + c*cos."""
    p, sd = model.params(), model.sigma()
    s, c = p[ns], p[nc]
    amp = float(np.hypot(s, c))
    half = Z95 * float(np.hypot(sd.get(ns, 0.0), sd.get(nc, 0.0))) / np.sqrt(2)
    return amp * scale, half * abs(scale), float(np.arctan2(c, s))


class Effect:
    """One candidate: scan ``grid``, fit ``build``'s terms, report ``describe``."""

    name = ""
    #: own coefficients that must come out > 0 (else the setting is rejected)
    positive: tuple[str, ...] = ()
    #: settings refined (in log space) after the grid scan
    continuous: tuple[str, ...] = ()

    def grid(self, sig: Signals, base: Base) -> list[dict]:
        return [{}]

    def build(self, sig: Signals, base: Base, hp: dict) -> tuple[list[Term], dict[int, float]]:
        return base.terms() + self.extra(hp), base.fixed()

    def extra(self, hp: dict) -> list[Term]:
        return []

    def chain_terms(self, hp: dict) -> tuple[list[Term], dict[int, float]]:
        """Terms this effect leaves in the model once the chain has chosen it, with
        any coefficients held (index within these terms -> value)."""
        return self.extra(hp), {}

    #: can the chain add this effect to the model (and then look for more)?
    chainable = True

    def describe(self, model: Model, base: Base, hp: dict) -> dict:
        return dict(hp)


# ------------------------------------------------------------------- friction
def _logcosh(x):
    x = np.abs(x)
    return x + np.log1p(np.exp(-2.0 * x)) - np.log(2.0)


def _interval_mean(antiderivative, value, a, b, eps: float):
    """Mean of value(w/eps) while w goes linearly from a to b, from eps *
    antiderivative(w/eps); the midpoint value where a and b nearly coincide."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    d = b - a
    wide = np.abs(d) > 1e-3 * eps
    safe = np.where(wide, d, 1.0)
    exact = eps * (antiderivative(b / eps) - antiderivative(a / eps)) / safe
    return np.where(wide, exact, value(0.5 * (a + b) / eps))


def mean_tanh(a, b, eps: float):
    """Mean of tanh(w/eps) while w goes linearly from a to b (one sample interval).

    Friction acts over the whole interval a feature stands for; evaluated at its start
    it is half a sample early, and at a reversal (a torque step of 2 Tc) that timing
    error is an impulse the fit mends by shifting the current — a spurious delay."""
    return _interval_mean(_logcosh, np.tanh, a, b, eps)


def interval_velocities(sig):
    """(w[q], w[q+1]) of the velocity estimate: the ends of each sample interval."""
    w = sig.velocity_rad_s
    return w, np.append(w[1:], w[-1])


class FrictionTerm(Term):
    """A friction torque -sum c_j g_j(theta) s(omega) that opposes motion.

    Simulated over each step's interval (simerror.simulate, sub-stepped, linearly
    implicit: it stops motion without chattering, and a reversal happens within the
    step, not at its end); measured as the interval mean (``mean_tanh``), so equation
    and simulation error see the same timing."""

    opposes_motion = True

    def measured(self, sig):
        a, b = interval_velocities(sig)
        th = sig.position_rad
        s = mean_tanh(a, b, self.eps)
        return [-s * g for g in self.shape(sig, th, 0.5 * (a + b))]

    def simulate(self, sig, theta, omega, idx, state):
        s = np.tanh(omega / self.eps)
        return [-s * g for g in self.shape(sig, theta, omega)]

    def value_slope(self, sig, theta, omega):
        """Features and their slopes d feature / d omega (for the implicit step)."""
        t = np.tanh(omega / self.eps)
        ds = (1.0 - t * t) / self.eps
        g = self.shape(sig, theta, omega)
        return [-t * x for x in g], [-ds * x for x in g]

    def shape(self, sig, theta, omega):
        return [np.ones_like(omega)]

    def fast(self, sig):
        return [(None, [(fs.F_TANH + fs.S_ONE, 1.0, self.eps)])]


@dataclass(frozen=True)
class CoulombTerm(FrictionTerm):
    """-Tc/J * tanh(omega/eps): Coulomb friction, smoothed sign."""

    names: tuple[str, ...] = ("tc_over_j",)
    eps: float = 0.3


@dataclass(frozen=True)
class StribeckTerm(FrictionTerm):
    """-Ts/J * tanh(omega/eps) exp(-(omega/ws)^2): static friction above Coulomb."""

    names: tuple[str, ...] = ("ts_over_j",)
    ws: float = 5.0
    eps: float = 0.3

    def shape(self, sig, theta, omega):
        return [np.exp(-(omega / self.ws) ** 2)]

    def value_slope(self, sig, theta, omega):
        t = np.tanh(omega / self.eps)
        e = np.exp(-(omega / self.ws) ** 2)
        return [-t * e], [-((1.0 - t * t) / self.eps - 2.0 * omega / self.ws ** 2 * t) * e]

    def fast(self, sig):
        return [(None, [(fs.F_STRIBECK + fs.S_ONE, 1.0, self.eps, self.ws)])]


def speed_scale(sig: Signals) -> float:
    """Top speed of the trace (99.5th percentile of |w|): widths and speeds of the
    friction models are fractions of it, so a trace in rad, deg, mm or m gives the
    same fit scaled (no threshold in the user's position unit)."""
    v = sig.cache.get("speed_scale")
    if v is None:
        v = float(np.percentile(np.abs(sig.velocity_rad_s), 99.5)) or 1e-300
        sig.cache["speed_scale"] = v
    return v


#: Coulomb smoothing widths scanned, as fractions of the top speed (then refined).
EPS_FRACTIONS = (2e-4, 1e-3, 7e-3)


def _eps_grid(sig: Signals) -> list[float]:
    return [f * speed_scale(sig) for f in EPS_FRACTIONS]


def _chosen_eps(sig: Signals, base: Base) -> float | None:
    for e, hp in base.chosen:
        if "eps_rad_s" in hp:
            return float(hp["eps_rad_s"])
    return None


class CoulombFriction(Effect):
    name = "coulomb_friction"
    continuous = ("eps_rad_s",)

    def grid(self, sig, base):
        return [{"eps_rad_s": e} for e in _eps_grid(sig)]

    def extra(self, hp):
        return [CoulombTerm(eps=hp["eps_rad_s"])]

    def describe(self, model, base, hp):
        v, h = _pm(model, "tc_over_j", 1.0 / base.kt_over_j(model))
        return {"Tc_a": v, "Tc_a_pm": h, **hp}


class StribeckFriction(Effect):
    name = "stribeck_friction"
    continuous = ("ws_rad_s",)

    def grid(self, sig, base):
        # Stribeck friction is a low-speed effect: ws up to a quarter of the top speed
        # (beyond that it is Coulomb friction by another name), and only where the trace
        # has low-speed motion to see it — else the regressor is ~0 and any fit is noise
        w = np.abs(sig.velocity_rad_s)
        top = 0.25 * float(np.max(w))
        # the sign's smoothing: a chosen Coulomb term's, else scanned like Coulomb's
        # (a fixed width would be a speed in the user's unit)
        eps = _chosen_eps(sig, base)
        grid = [{"ws_rad_s": float(ws), "eps_rad_s": e}
                for ws in np.geomspace(top / 500, top, 7)
                for e in ([eps] if eps else _eps_grid(sig))]
        return [g for g in grid if np.mean(np.exp(-(w / g["ws_rad_s"]) ** 2)) > MIN_SUPPORT]

    def extra(self, hp):
        return [StribeckTerm(ws=hp["ws_rad_s"], eps=hp["eps_rad_s"])]

    def describe(self, model, base, hp):
        v, h = _pm(model, "ts_over_j", 1.0 / base.kt_over_j(model))
        return {"Ts_a": v, "Ts_a_pm": h, **hp}


# ------------------------------------------------------- position-periodic torques
@dataclass(frozen=True)
class CoggingTerm(Term):
    """Cogging torque / J = s sin(N th) + c cos(N th), independent of current."""

    names: tuple[str, ...] = ("cog_sin", "cog_cos")
    order: int = 6

    def simulate(self, sig, theta, omega, idx, state):
        a = self.order * sig.rad_per_unit * theta
        return [np.sin(a), np.cos(a)]

    def fast(self, sig):
        a = self.order * sig.rad_per_unit
        return [(None, [(fs.SIN, 1.0, 0.0, 0.0, a)]), (None, [(fs.COS, 1.0, 0.0, 0.0, a)])]


@dataclass(frozen=True)
class RippleTerm(Term):
    """Commutation ripple: Kt i (s sin(N th) + c cos(N th)) / J, proportional to current."""

    names: tuple[str, ...] = ("rip_sin", "rip_cos")
    order: int = 6

    def simulate(self, sig, theta, omega, idx, state):
        i = sig.current_a[idx]
        a = self.order * sig.rad_per_unit * theta
        return [i * np.sin(a), i * np.cos(a)]

    def fast(self, sig):
        a = self.order * sig.rad_per_unit
        return [(None, [(fs.RSIN, 1.0, 0.0, 0.0, a)]), (None, [(fs.RCOS, 1.0, 0.0, 0.0, a)])]


MAX_ORDER = 36


class Cogging(Effect):
    name = "cogging"

    def grid(self, sig, base):
        # orders are per motor revolution: only where the position unit is known as an
        # angle (or a lead was given) — see Signals.rad_per_unit
        if sig.rad_per_unit is None:
            return []
        return [{"cog_order": n} for n in range(1, MAX_ORDER + 1)]

    def extra(self, hp):
        return [CoggingTerm(order=hp["cog_order"])]

    def describe(self, model, base, hp):
        amp, h, ph = _amp_phase(model, "cog_sin", "cog_cos", 1.0 / base.kt_over_j(model))
        return {"cog_amp_a": amp, "cog_amp_a_pm": h, "cog_phase_rad": ph, **hp}


class TorqueRipple(Effect):
    name = "torque_ripple"

    def grid(self, sig, base):
        if sig.rad_per_unit is None:
            return []
        return [{"ripple_order": n} for n in range(1, MAX_ORDER + 1)]

    def extra(self, hp):
        return [RippleTerm(order=hp["ripple_order"])]

    def describe(self, model, base, hp):
        amp, h, ph = _amp_phase(model, "rip_sin", "rip_cos", 1.0 / base.kt_over_j(model))
        return {"ripple_amp": amp, "ripple_amp_pm": h, "ripple_phase_rad": ph, **hp}


# ------------------------------------------------------------- current sensing
@dataclass(frozen=True)
class ConstantTerm(Term):
    """-Kt/J * offset: the current sensor reads i + offset."""

    names: tuple[str, ...] = ("offset_over_j",)

    def simulate(self, sig, theta, omega, idx, state):
        return [-np.ones_like(omega)]

    def fast(self, sig):
        return [(-np.ones(len(sig)), [])]


class CurrentOffset(Effect):
    name = "current_offset"

    def extra(self, hp):
        return [ConstantTerm()]

    def describe(self, model, base, hp):
        v, h = _pm(model, "offset_over_j", 1.0 / base.kt_over_j(model))
        return {"offset_a": v, "offset_a_pm": h}


def split_timing(tau: float) -> tuple[int, float]:
    """Current timing tau (samples; 0..1 is the nominal's hold) -> whole samples of
    delay and the hold fraction within the sample."""
    d = int(np.floor(tau))
    return d, float(tau - d)


class TimeDelay(Effect):
    """The measured current lags the torque-producing one: the torque over sample
    interval k is driven by the current reported tau samples later (the nominal's hold
    covers 0 <= tau <= 1).  Scanned and refined on simulation error: integrated
    equation error sees current timing only at its windows' ends."""

    name = "time_delay"
    continuous = ("delay_tau",)
    by_simulation = True

    def grid(self, sig, base):
        return [{"delay_tau": float(t)} for t in np.arange(1.0, 11.01, 0.5)]

    def build(self, sig, base, hp):
        d, h = split_timing(hp["delay_tau"])
        if base.given is None:
            return base.terms(delay=d, hold=h), base.fixed()
        return base.terms(delay=d), {**base.fixed(), 1: h}

    def describe(self, model, base, hp):
        # the delay beyond the hold the model had before (the sampler's own timing)
        h0 = base.hold if base.hold is not None else 0.0
        return {"delay_samples": int(round(hp["delay_tau"] - h0)),
                "current_timing_samples": float(hp["delay_tau"]),
                "hold_fraction_before": float(h0)}


class KtSaturation(Effect):
    """Kt_eff = Kt / (1 + (i/i_sat)^2): torque constant falling at high current."""

    name = "kt_saturation"
    continuous = ("kt_sat_a",)

    def grid(self, sig, base):
        imax = float(np.max(np.abs(sig.current_a)))
        return [{"kt_sat_a": imax * f} for f in (0.3, 0.45, 0.6, 0.8, 1.0, 1.3, 1.7, 2.2, 3.0, 4.5)]

    def build(self, sig, base, hp):
        return base.terms(sat_a=hp["kt_sat_a"], sat_off=hp.get("kt_sat_offset_a", 0.0)), base.fixed()


class InertiaMismatch(Effect):
    """J differs from the given model's (J_true = J_model / scale).

    Only meaningful against a given model: an identified nominal absorbs any
    inertia, so then the candidate is the nominal itself (no shrink).
    """

    name = "inertia_mismatch"

    def build(self, sig, base, hp):
        return base.terms(), base.fixed(free_scale=True)

    def describe(self, model, base, hp):
        if base.given is None:
            return {"J_ratio": 1.0, "note": "nominal identified on this trace absorbs J"}
        v, h = _pm(model, "scale")
        return {"J_ratio": 1.0 / v if v else float("nan"),
                "J_ratio_pm": h / v ** 2 if v else float("nan")}


# ------------------------------------------------------------ disk on a shaft
# The disk's equation is linear: th2'' = wn^2 (th - th2) + 2 zeta wn (w - w2).  Both the
# disk tracked from the measured motion and the simulated two-mass system are stepped
# with its exact solution over a sample (matrix exponentials).  Explicit steps of a
# lightly damped mode are not good enough: explicit motor velocity + trapezoid angle
# gained (h w)^2/2 of energy per step, and a symplectic track's disk velocity is the
# interval mean, half a step late: with them the true model of an injected shaft sat at
# 1.8-7.4x the noise floor on held-out horizons (exact steps: 0.6-0.75x).
def _expm(a: np.ndarray) -> np.ndarray:
    """exp(a) of a small matrix: Taylor series after scaling to norm <= 1/2, then
    squaring (scipy.linalg.expm took ~7 ms a call on these 4x4s: hundreds per scan)."""
    s = max(0, int(np.ceil(np.log2(np.abs(a).sum(axis=1).max() + 1e-300))) + 1)
    a = a / 2.0 ** s
    e = t = np.eye(len(a))
    for k in range(1, 15):
        t = t @ a / k
        e = e + t
    for _ in range(s):
        e = e @ e
    return e


def _disk_matrix(wn: float, zeta: float, dt: float) -> np.ndarray:
    """Transition over one step of (th2, w2, th, s): the disk driven by a motor angle
    th + s t that is linear between samples (s = its slope, held)."""
    a = np.zeros((4, 4))
    a[0, 1] = a[2, 3] = 1.0
    a[1] = [-wn * wn, -2.0 * zeta * wn, wn * wn, 2.0 * zeta * wn]
    return _expm(a * dt)


@functools.lru_cache(maxsize=64)
def two_mass_step(k_over_j: float, c_over_j: float, wn: float, zeta: float,
                  dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact step of motor and disk, z = (th, w, th2, w2), with the motor's other
    torques held over the step as an acceleration u:  z1 = A z0 + b u, from
        th'' = u - k/J (th - th2) - c/J (w - w2),  th2'' = wn^2 (th - th2) + 2 zeta wn (w - w2)."""
    m = np.zeros((5, 5))
    m[0, 1] = m[2, 3] = m[1, 4] = 1.0
    m[1, :4] = [-k_over_j, -c_over_j, k_over_j, c_over_j]
    m[3, :4] = [wn * wn, 2.0 * zeta * wn, -wn * wn, -2.0 * zeta * wn]
    e = _expm(m * dt)
    return e[:4, :4], e[:4, 4]


@numba.njit(cache=True)
def _disk_track(theta, dt, e):  # pragma: no cover - compiled
    """Disk driven through the shaft by the measured motor angle, linear between
    samples (``e`` = ``_disk_matrix``): th2[k], w2[k] at the sample instants."""
    n = theta.shape[0]
    th2 = np.empty(n)
    w2 = np.empty(n)
    a, b = theta[0], (theta[1] - theta[0]) / dt
    for k in range(n):
        th2[k] = a
        w2[k] = b
        if k + 1 < n:
            s = (theta[k + 1] - theta[k]) / dt
            a, b = (e[0, 0] * a + e[0, 1] * b + e[0, 2] * theta[k] + e[0, 3] * s,
                    e[1, 0] * a + e[1, 1] * b + e[1, 2] * theta[k] + e[1, 3] * s)
    return th2, w2


@dataclass(frozen=True)
class DiskTerm(Term):
    """Coupling torque of a disk on a compliant shaft, -k/J (th - th2) - c/J (w - w2);
    the disk obeys th2'' = wn^2 (th - th2) + 2 zeta wn (w - w2).  In simulation the
    coupling is integrated exactly with the motor (``advance``, see two_mass_step)."""

    names: tuple[str, ...] = ("k_over_j", "c_over_j_shaft")
    wn: float = 200.0
    zeta: float = 0.1

    def _track(self, sig):
        # one slot: a scan visits hundreds of disks, each a trace long
        key = (self.wn, self.zeta)
        slot = sig.cache.get("disk")
        if slot is None or slot[0] != key:
            e = _disk_matrix(self.wn, self.zeta, sig.dt_s)
            slot = (key, _disk_track(sig.position_rad, sig.dt_s, e))
            sig.cache["disk"] = slot
        return slot[1]

    def measured(self, sig):
        th2, w2 = self._track(sig)
        return [th2 - sig.position_rad, w2 - sig.velocity_rad_s]

    def init_state(self, sig, idx):
        th2, w2 = self._track(sig)
        return [th2[idx].copy(), w2[idx].copy()]

    def simulate(self, sig, theta, omega, idx, state):
        return [state[0] - theta, state[1] - omega]

    def advance(self, state, coef, theta, omega, u, dt):
        """Motor and disk after one step, the other torques held as acceleration ``u``:
        (theta, omega, state)."""
        a, b = two_mass_step(float(coef[0]), float(coef[1]), self.wn, self.zeta, dt)
        z = a @ np.array([theta, omega, state[0], state[1]]) + b[:, None] * u
        return z[0], z[1], [z[2], z[3]]


def _wn_grid(sig, n):
    top = 0.25 * np.pi / sig.dt_s  # well below Nyquist (a mode the samples can show)
    return np.geomspace(20.0, top, n)


class ShaftCompliance(Effect):
    name = "shaft_compliance"
    continuous = ("wn_rad_s", "zeta")
    #: a disk needs k > 0: with k < 0 a stiff "disk" acts as a predictor of the motion
    #: that equation error (not simulation) rewards, e.g. on a strongly excited resonance
    positive = ("k_over_j",)

    def grid(self, sig, base):
        # a lightly damped disk is tracked open loop, so the fit is sharp in wn:
        # 1.4 % steps when lightly damped (Nelder-Mead refines), 6 % when well damped
        return ([{"wn_rad_s": float(w), "zeta": 0.02} for w in _wn_grid(sig, 260)]
                + [{"wn_rad_s": float(w), "zeta": 0.3} for w in _wn_grid(sig, 60)])

    def extra(self, hp):
        return [DiskTerm(wn=hp["wn_rad_s"], zeta=hp["zeta"])]

    def describe(self, model, base, hp):
        k, kh = _pm(model, "k_over_j")
        return {"k_over_j": k, "k_over_j_pm": kh,
                "disk_over_motor_inertia": k / hp["wn_rad_s"] ** 2, **hp}


@numba.njit(cache=True)
def _gap_track(theta, omega, dt, gap):  # pragma: no cover - compiled
    """A free disk in a gap, driven by the given motor motion through rigid contact:
    it coasts inside the gap and, when the gap closes while closing, takes the motor's
    velocity (a plastic impact; held while the motor keeps pushing)."""
    n = theta.shape[0]
    th2 = np.empty(n)
    w2 = np.empty(n)
    a, b = theta[0], omega[0]
    half = 0.5 * gap
    for k in range(n):
        th2[k] = a
        w2[k] = b
        if k + 1 < n:
            a = a + dt * b
            d = theta[k + 1] - a
            s = 1.0 if d > 0 else -1.0
            if abs(d) >= half and s * (omega[k + 1] - b) > 0.0:
                b = omega[k + 1]
                a = theta[k + 1] - s * half
    return th2, w2


@dataclass(frozen=True)
class RigidGapTerm(Term):
    """A disk (inertia ratio r = J_disk/J, the one coefficient) behind a gap, rigid
    contact: J th'' = ... - J_disk th2'', the disk's acceleration being the contact's
    only torque on it.  Equation error uses the disk tracked from the measured motion
    (``_gap_track``); simulation coasts the disk in the gap and, on contact, shares
    momentum: w = (w_free + r w2) / (1 + r) (``couple``, called by simerror.simulate)."""

    names: tuple[str, ...] = ("disk_over_motor_inertia",)
    gap: float = 0.01

    def _track(self, sig):
        key = ("gap", self.gap)
        slot = sig.cache.get("disk")
        if slot is None or slot[0] != key:
            slot = (key, _gap_track(sig.position_rad, sig.velocity_rad_s, sig.dt_s, self.gap))
            sig.cache["disk"] = slot
        return slot[1]

    def measured(self, sig):
        w2 = self._track(sig)[1]
        return [-np.append(np.diff(w2), 0.0) / sig.dt_s]

    def init_state(self, sig, idx):
        th2, w2 = self._track(sig)
        return [th2[idx].copy(), w2[idx].copy()]

    def simulate(self, sig, theta, omega, idx, state):
        return [np.zeros_like(omega)]     # acts through ``couple``

    def fast(self, sig):
        return [(None, [(fs.GAP, 1.0, self.gap)])]

    def fast_track(self, sig):
        return 1, self._track(sig)

    def couple(self, state, r, theta, omega, new, dt):
        th2, w2 = state
        r = max(float(r), 0.0)
        th2 = th2 + dt * w2
        d = theta + 0.5 * dt * (omega + new) - th2
        s = np.where(d > 0, 1.0, -1.0)
        hit = (np.abs(d) >= 0.5 * self.gap) & (s * (new - w2) > 0)
        wc = (new + r * w2) / (1.0 + r)
        new = np.where(hit, wc, new)
        w2 = np.where(hit, wc, w2)
        th2 = np.where(hit, theta + 0.5 * dt * (omega + new) - s * 0.5 * self.gap, th2)
        return new, [th2, w2]


def _gap_grid(sig: Signals) -> np.ndarray:
    """Gaps scanned: from 1/300 to 1/3 of the distance the axis covers in one sample
    at top speed (unit-free)."""
    step = speed_scale(sig) * sig.dt_s
    return np.geomspace(step / 300, step / 3, 9)


class Backlash(Effect):
    """A disk behind a gap with rigid contact (impacts share momentum): the gap is
    scanned, the inertia ratio J_disk/J is the one linear coefficient.  (A stiff
    contact's ~kHz ringing is beyond 1 kHz sampling; a spring-damper disk cannot be
    simulated stably at that stiffness.)"""

    name = "backlash"
    continuous = ("gap_rad", "disk_over_motor_inertia")
    #: scanned and refined on simulation error: as a regressor the disk's acceleration
    #: in contact is the motor's own (the output), which equation error cannot use
    by_simulation = True

    def grid(self, sig, base):
        return [{"gap_rad": float(g), "disk_over_motor_inertia": float(r)}
                for g in _gap_grid(sig) for r in (0.2, 0.5, 1.0, 2.0)]

    def build(self, sig, base, hp):
        terms = base.terms()
        fixed = {**base.fixed(), sum(len(t.names) for t in terms): hp["disk_over_motor_inertia"]}
        return terms + [RigidGapTerm(gap=hp["gap_rad"])], fixed

    def chain_terms(self, hp):
        return [RigidGapTerm(gap=hp["gap_rad"])], {0: hp["disk_over_motor_inertia"]}

    def describe(self, model, base, hp):
        return dict(hp)


# ------------------------------------------------- direction / position friction
def mean_abs_tanh(a, b, eps: float):
    """Mean of |tanh(w/eps)| while w goes linearly from a to b (antiderivative
    eps sgn(w) log cosh(w/eps))."""
    return _interval_mean(lambda x: np.sign(x) * _logcosh(x), lambda x: np.abs(np.tanh(x)),
                          a, b, eps)


@dataclass(frozen=True)
class DirectionTerm(FrictionTerm):
    """Direction-dependent friction on top of Coulomb + viscous:
    -dTc/J |tanh(w/eps)| - dD/J |w|, so forward Tc+ = Tc + dTc, D+ = D + dD and
    backward Tc- = Tc - dTc, D- = D - dD.  Part of the friction integrated over the
    step (its |sign| notch at a reversal is timed like the Coulomb term's switch)."""

    names: tuple[str, ...] = ("dtc_over_j", "dd_over_j")
    eps: float = 0.3

    @property
    def _coulomb(self) -> bool:     # names ("dd_over_j",): the viscous part only
        return "dtc_over_j" in self.names

    def measured(self, sig):
        a, b = interval_velocities(sig)
        out = [-0.5 * (np.abs(a) + np.abs(b))]
        return [-mean_abs_tanh(a, b, self.eps), *out] if self._coulomb else out

    def simulate(self, sig, theta, omega, idx, state):
        out = [-np.abs(omega)]
        return [-np.abs(np.tanh(omega / self.eps)), *out] if self._coulomb else out

    def value_slope(self, sig, theta, omega):
        t = np.tanh(omega / self.eps)
        s = np.sign(omega)
        if not self._coulomb:
            return [-np.abs(omega)], [-s]
        return ([-np.abs(t), -np.abs(omega)], [-s * (1.0 - t * t) / self.eps, -s])

    def fast(self, sig):
        out = [(None, [(fs.F_ABSW + fs.S_ONE, 1.0, self.eps)])]
        return ([(None, [(fs.F_ABSTANH + fs.S_ONE, 1.0, self.eps)]), *out] if self._coulomb
                else out)


class DirectionFriction(Effect):
    """Separate Coulomb and viscous friction per direction (ball screws, seals and
    preloaded gears often differ forward and back).  Adds its own Coulomb term when
    the chain has none yet.  With a current offset in the chain, only the viscous part
    is added: while moving, the Coulomb part (-dTc |sign w|) and the offset are one
    column, and fitted together they cancel in huge opposite coefficients that blow up
    on held-out reversals (held-out shrink -1.3 to -6.7 after Coulomb + offset); the
    offset then carries the Coulomb asymmetry (dTc = offset, reported so)."""

    name = "direction_friction"

    def grid(self, sig, base):
        eps = _chosen_eps(sig, base)
        coulomb = "coulomb_friction" not in base.chosen_names
        offset = "current_offset" in base.chosen_names
        return [{"eps_rad_s": e, "with_coulomb": coulomb, "viscous_only": offset}
                for e in ([eps] if eps else _eps_grid(sig))]

    def extra(self, hp):
        t = [DirectionTerm(names=("dd_over_j",), eps=hp["eps_rad_s"]) if hp.get("viscous_only")
             else DirectionTerm(eps=hp["eps_rad_s"])]
        return ([CoulombTerm(eps=hp["eps_rad_s"])] + t) if hp["with_coulomb"] else t

    def describe(self, model, base, hp):
        p, kj = model.params(), base.kt_over_j(model)
        tc, d = p.get("tc_over_j", 0.0), p.get("d_over_j", 0.0)
        dtc = _pm(model, "offset_over_j" if hp.get("viscous_only") else "dtc_over_j", 1.0 / kj)
        dd = _pm(model, "dd_over_j", 1.0 / kj)
        return {"Tc_forward_a": (tc / kj + dtc[0]), "Tc_backward_a": (tc / kj - dtc[0]),
                "dTc_a_pm": dtc[1],
                "D_forward_a_per_speed": (d / kj + dd[0]), "D_backward_a_per_speed": (d / kj - dd[0]),
                "dD_a_per_speed_pm": dd[1], "eps_rad_s": hp["eps_rad_s"],
                **({"coulomb_asymmetry": "the chain's current_offset"}
                   if hp.get("viscous_only") else {})}


@dataclass(frozen=True)
class PositionFrictionTerm(FrictionTerm):
    """Coulomb friction whose level varies with position: -tanh(w/eps) (s g1 + c g2)/J
    with (g1, g2) = (sin, cos)(N th) over the rotor angle, or Legendre P1, P2 of the
    position over the travel (unit-free: normalised to the trace's range)."""

    names: tuple[str, ...] = ("pf1_over_j", "pf2_over_j")
    eps: float = 0.3
    order: int = 0          # 0: along the travel
    lo: float = 0.0
    span: float = 1.0

    def shape(self, sig, theta, omega):
        if self.order:
            a = self.order * sig.rad_per_unit * theta
            return [np.sin(a), np.cos(a)]
        x = 2.0 * (theta - self.lo) / self.span - 1.0
        return [x, 1.5 * x * x - 0.5]

    def fast(self, sig):
        if self.order:
            a = self.order * sig.rad_per_unit
            return [(None, [(fs.F_TANH + fs.S_SIN, 1.0, self.eps, 0.0, a)]),
                    (None, [(fs.F_TANH + fs.S_COS, 1.0, self.eps, 0.0, a)])]
        return [(None, [(fs.F_TANH + s, 1.0, self.eps, 0.0, self.lo, self.span)])
                for s in (fs.S_LEG1, fs.S_LEG2)]


#: Rotor-angle orders scanned for position-dependent friction (eccentric screws,
#: seals and gears: low orders).
POS_FRICTION_ORDERS = 8


class PositionFriction(Effect):
    name = "position_friction"

    def grid(self, sig, base):
        eps = _chosen_eps(sig, base) or _eps_grid(sig)[1]
        lo, span = float(np.min(sig.position_rad)), float(np.ptp(sig.position_rad)) or 1.0
        g = [{"order": 0, "eps_rad_s": eps, "lo": lo, "span": span}]
        if sig.rad_per_unit is None:    # rotor-angle orders need an angle (see Signals)
            return g
        return g + [{"order": n, "eps_rad_s": eps, "lo": lo, "span": span}
                    for n in range(1, POS_FRICTION_ORDERS + 1)]

    def extra(self, hp):
        return [PositionFrictionTerm(eps=hp["eps_rad_s"], order=hp["order"], lo=hp["lo"],
                                     span=hp["span"])]

    def describe(self, model, base, hp):
        amp, h, ph = _amp_phase(model, "pf1_over_j", "pf2_over_j", 1.0 / base.kt_over_j(model))
        where = ("along the travel (P1, P2 of position)" if not hp["order"]
                 else f"order {hp['order']} of the rotor angle")
        return {"variation_a": amp, "variation_a_pm": h, "pattern": where,
                "order": hp["order"], "eps_rad_s": hp["eps_rad_s"]}


# ------------------------------------------------- presliding (Dahl) friction
@numba.njit(cache=True)
def _dahl_track(theta, xs):  # pragma: no cover - compiled
    """Dahl's friction state z along a position track: dz/dx = (1 - z sgn(dx)) / xs, solved
    exactly per step (z relaxes towards the sign of motion over the presliding distance
    xs, whatever the speed: rate-independent hysteresis at every reversal)."""
    n = theta.shape[0]
    z = np.empty(n)
    zk = 0.0
    for k in range(n):
        z[k] = zk
        if k + 1 < n:
            dx = theta[k + 1] - theta[k]
            if dx != 0.0:
                s = 1.0 if dx > 0 else -1.0
                zk = s + (zk - s) * np.exp(-abs(dx) / xs)
    return z


@dataclass(frozen=True)
class DahlTerm(Term):
    """-Tp/J * z: friction that builds up over a presliding distance after each
    reversal (Dahl 1968; the LuGre model without its Stribeck part), instead of
    switching with the sign of the speed.  Added beside the chain's Coulomb term, the
    fit shares the friction level between them; the difference shows at reversals."""

    names: tuple[str, ...] = ("tp_over_j",)
    xs: float = 0.01

    def _track(self, sig):
        key = ("dahl", self.xs)
        if key not in sig.cache:
            sig.cache[key] = _dahl_track(sig.position_rad, self.xs)
        return sig.cache[key]

    def measured(self, sig):
        z = self._track(sig)
        return [-0.5 * (z + np.append(z[1:], z[-1]))]

    def init_state(self, sig, idx):
        return [self._track(sig)[idx].copy()]

    def simulate(self, sig, theta, omega, idx, state):
        return [-state[0]]

    def fast(self, sig):
        return [(None, [(fs.DAHL, 1.0, self.xs)])]

    def fast_track(self, sig):
        return 0, [self._track(sig)]

    def step_state(self, state, theta, omega, dt):
        dx = omega * dt
        s = np.sign(dx)
        z = state[0]
        return [np.where(s != 0, s + (z - s) * np.exp(-np.abs(dx) / self.xs), z)]


class PreslidingFriction(Effect):
    """Presliding friction (Dahl): the friction level is reached over a distance after
    each reversal.  Offered once Coulomb friction is in the chain (it refines how that
    friction switches); the distance is scanned from 1/300 to 30 times the travel of one
    sample at top speed (unit-free), then refined."""

    name = "presliding_friction"
    continuous = ("presliding_distance",)

    def grid(self, sig, base):
        step = speed_scale(sig) * sig.dt_s
        return [{"presliding_distance": float(x)} for x in np.geomspace(step / 300, 30 * step, 10)]

    def extra(self, hp):
        return [DahlTerm(xs=hp["presliding_distance"])]

    def describe(self, model, base, hp):
        v, h = _pm(model, "tp_over_j", 1.0 / base.kt_over_j(model))
        return {"Tp_a": v, "Tp_a_pm": h, **hp}


class EncoderQuantization(Effect):
    """A coarse encoder: the angle sits on a lattice of step q; the velocity estimate
    then carries uniform quantisation noise.  Nothing to refit in the dynamics — the
    candidate explains that noise's share of the simulation error (see verdict)."""

    name = "encoder_quantization"

    def describe(self, model, base, hp):
        return dict(hp)


LIBRARY: tuple[Effect, ...] = (
    CoulombFriction(), StribeckFriction(), DirectionFriction(), PositionFriction(),
    PreslidingFriction(), Cogging(), TorqueRipple(), CurrentOffset(),
    TimeDelay(), KtSaturation(), ShaftCompliance(), Backlash(), EncoderQuantization(),
    InertiaMismatch(),
)
NAMES = tuple(e.name for e in LIBRARY)
