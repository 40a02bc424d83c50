"""Friction candidates: Coulomb, Stribeck, direction- and position-dependent, and
presliding (Dahl) friction — all integrated over the sample interval in equation
error (interval means) and sub-stepped in simulation (simerror, fastsim)."""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from ..derivatives import runs
from . import fastsim as fs
from .base import MIN_SUPPORT, Base, Effect, _amp_phase, _pm
from .nominal import Signals, Term


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


#: Shortest standstill (samples the encoder does not move while current flows) that
#: bounds the Coulomb width.
MIN_STUCK_SAMPLES = 8


def stuck_width_bound(sig: Signals) -> float | None:
    """Widest Coulomb smoothing the trace's own standstills allow, or None.

    A smoothed sign tanh(w/eps) is not static friction: below breakaway it lets the
    rotor creep at w = eps atanh(T/Tc), i.e. at about eps when the drive torque is
    three quarters of Tc.  Where the encoder stays on one count for L samples while
    current flows, the rotor crept less than one count q: eps <= q / (L dt).  (On our
    own --sim out-motor disk calibration the rotor stands 20 ms while the current rises
    to breakaway; a width of 2 rad/s, chosen because its creep stood in for the missing
    cogging, kept cogging from fitting: 2.8x the floor, 1.35x at widths the standstill
    allows.)

    Parameters
    ----------
    sig : Signals
        The trace (encoder angles on a lattice; without one nothing is bounded).

    Returns
    -------
    float or None
        q / (L dt) for the longest standstill with current above 3x its noise of at
        least ``MIN_STUCK_SAMPLES`` samples; None without one.
    """
    if "stuck_width" in sig.cache:
        return sig.cache["stuck_width"]
    from .simerror import current_noise, lattice_step

    out = None
    q = lattice_step(sig.position_rad)
    if q:
        moved = np.abs(np.diff(sig.position_rad)) > 0.5 * q
        i_min = 3.0 * current_noise(sig)
        # stretches of steps without a count (a run of n steps holds n + 1 readings)
        held = [e - s for s, e in runs(~moved) if e - s >= MIN_STUCK_SAMPLES
                and float(np.mean(np.abs(sig.current_a[s:e + 1]))) > i_min]
        if held:
            out = float(q / (max(held) * sig.dt_s))
    sig.cache["stuck_width"] = out
    return out


def _eps_grid(sig: Signals) -> list[float]:
    """Coulomb widths scanned: fractions of the top speed, none wider than the trace's
    standstills allow (``stuck_width_bound``)."""
    grid = [f * speed_scale(sig) for f in EPS_FRACTIONS]
    cap = stuck_width_bound(sig)
    if cap is None:
        return grid
    return sorted({min(e, cap) for e in grid})


def _mid_eps(sig: Signals) -> float:
    grid = _eps_grid(sig)
    return grid[len(grid) // 2]


def narrower_widths(sig: Signals, base: Base) -> list[float | None]:
    """Coulomb widths a position-periodic candidate is fitted with: the narrowest
    scanned one (closest to static friction's sign) when the chain chose a wider one,
    else the chain's own (None).

    A wide width creeps at low speed and so stands in for a torque that pulls the
    rotor there (cogging at a slow roll-back): chosen before cogging, 2.3 rad/s on our
    own --sim disk calibration left cogging nothing to close (shrink 0), and cogging
    never entered to let the width be re-chosen (retune does so once it is in)."""
    eps = _chosen_eps(sig, base) if "coulomb_friction" in base.chosen_names else None
    if eps is None:
        return [None]
    narrow = min(_eps_grid(sig))
    return [narrow] if narrow < 0.5 * eps else [None]


def with_width(base: Base, hp: dict) -> Base:
    """``base`` with the chosen Coulomb width replaced by ``hp["coulomb_eps_rad_s"]``."""
    eps = hp.get("coulomb_eps_rad_s")
    if eps is None or "coulomb_friction" not in base.chosen_names:
        return base
    return base.with_settings("coulomb_friction",
                              {**base.settings("coulomb_friction"), "eps_rad_s": float(eps)})


def _chosen_eps(sig: Signals, base: Base) -> float | None:
    for e, hp in base.chosen:
        if "eps_rad_s" in hp:
            return float(hp["eps_rad_s"])
    return None


class CoulombFriction(Effect):
    name = "coulomb_friction"
    continuous = ("eps_rad_s",)
    #: friction opposes motion: Tc > 0
    positive = ("tc_over_j",)

    def grid(self, sig, base):
        return [{"eps_rad_s": e} for e in _eps_grid(sig)]

    def extra(self, hp):
        return [CoulombTerm(eps=hp["eps_rad_s"])]

    def describe(self, model, base, hp):
        v, h = _pm(model, "tc_over_j", 1.0 / base.kt_over_j(model))
        return {"Tc_a": v, "Tc_a_pm": h, **hp}

    def inadmissible(self, sig, model, base, hp):
        why = super().inadmissible(sig, model, base, hp)
        d = self.describe(model, base, hp)
        # a friction level within its own 95 % interval of zero is no friction: with a
        # tiny width it only re-times the reversals (a cogging trace took one with
        # Tc = 0.09 +- 0.26 mA as a second effect)
        if why is None and np.isfinite(d["Tc_a_pm"]) and abs(d["Tc_a"]) <= d["Tc_a_pm"]:
            why = f"Tc {d['Tc_a']:.3g} A within its 95 % interval of 0 (+-{d['Tc_a_pm']:.3g} A)"
        return why


class StribeckFriction(Effect):
    name = "stribeck_friction"
    continuous = ("ws_rad_s",)
    #: static friction above Coulomb's: Ts > 0
    positive = ("ts_over_j",)

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
        eps = _chosen_eps(sig, base) or _mid_eps(sig)
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
    positive = ("tp_over_j",)

    def grid(self, sig, base):
        step = speed_scale(sig) * sig.dt_s
        return [{"presliding_distance": float(x)} for x in np.geomspace(step / 300, 30 * step, 10)]

    def extra(self, hp):
        return [DahlTerm(xs=hp["presliding_distance"])]

    def describe(self, model, base, hp):
        v, h = _pm(model, "tp_over_j", 1.0 / base.kt_over_j(model))
        return {"Tp_a": v, "Tp_a_pm": h, **hp}
