"""Torques periodic in an angle: cogging and commutation ripple (orders of the motor
angle) and a position-dependent load torque (gravity, unbalance, an eccentric load:
order 1 of the load angle)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import fastsim as fs
from .base import Effect, _amp_phase
from .nominal import Term


def interval_sin_cos(a0, a1):
    """Means of sin(a) and cos(a) while the angle a goes linearly from a0 to a1.

    mean sin = sin(a_mid) sinc(da/2), mean cos = cos(a_mid) sinc(da/2), with
    a_mid = (a0 + a1)/2, da = a1 - a0 (exact for a constant speed over the step).
    A cogging torque turns N times a revolution: at 200 rad/s, order 6, 1 kHz, its
    phase moves 1.2 rad within one sample, and taken at the step's start it is 0.6 rad
    early and 6 % too large, by amounts that vary with speed — no single fitted phase
    mends that (our own --sim disk calibration kept its order-6 cogging unexplained)."""
    mid = 0.5 * (a0 + a1)
    k = np.sinc((a1 - a0) / (2.0 * np.pi))        # np.sinc(x) = sin(pi x)/(pi x)
    return np.sin(mid) * k, np.cos(mid) * k


@dataclass(frozen=True)
class CoggingTerm(Term):
    """Cogging torque / J = s sin(N th) + c cos(N th), independent of current, taken as
    its mean over each sample interval (``interval_sin_cos``)."""

    names: tuple[str, ...] = ("cog_sin", "cog_cos")
    order: int = 6

    def measured(self, sig):
        a = self.order * sig.rad_per_unit * sig.position_rad
        return list(interval_sin_cos(a, np.append(a[1:], a[-1])))

    def simulate(self, sig, theta, omega, idx, state):
        a = self.order * sig.rad_per_unit * theta
        return list(interval_sin_cos(a, a + self.order * sig.rad_per_unit * omega * sig.dt_s))

    def fast(self, sig):
        a = self.order * sig.rad_per_unit
        return [(None, [(fs.SIN, 1.0, 1.0, 0.0, a)]), (None, [(fs.COS, 1.0, 1.0, 0.0, a)])]

    def ripple_velocity(self, sig):
        """Velocity ripple per coefficient that the horizon's initial estimate misses:
        at a steady speed w, s sin(phi) + c cos(phi) (phi = N th) integrates to
        (-s cos(phi) + c sin(phi)) / (N w), of which the estimator keeps G
        (simerror.missed_share).  Where the motor is slow the ripple is slow too and
        the estimator sees it (1 - G -> 0 faster than 1/w grows)."""
        key = ("cog_ripple", self.order)
        if key not in sig.cache:
            from .simerror import missed_share
            n = self.order * sig.rad_per_unit
            a = n * sig.position_rad
            rate = n * sig.velocity_rad_s
            miss = missed_share(rate, sig.dt_s)
            safe = np.where(np.abs(rate) > 1e-12, rate, 1.0)
            f = np.where(np.abs(rate) > 1e-12, miss / safe, 0.0)
            sig.cache[key] = (-np.cos(a) * f, np.sin(a) * f)
        return sig.cache[key]


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
    #: the order chosen on simulation error: equation error (twice-differentiated
    #: angle) hardly sees a 200-300 Hz cogging and picked order 5 for a true 6 on our
    #: own --sim calibration, which then closed nothing significant
    by_simulation = True

    def grid(self, sig, base):
        # orders are per motor revolution: only where the position unit is known as an
        # angle (or a lead was given) — see Signals.rad_per_unit
        if sig.rad_per_unit is None:
            return []
        from .friction import narrower_widths

        # with a narrower Coulomb width too: a wide one's creep stands in for cogging
        return [{"cog_order": n} if e is None else {"cog_order": n, "coulomb_eps_rad_s": e}
                for e in narrower_widths(sig, base) for n in range(1, MAX_ORDER + 1)]

    def adjust_base(self, base, hp):
        from .friction import with_width

        return with_width(base, hp)

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


@dataclass(frozen=True)
class LoadTorqueTerm(Term):
    """Position-dependent load torque / J = s sin(th_L) + c cos(th_L), th_L the load's
    angle = th * rad_per_unit / ratio: gravity on an arm (m g l sin), an unbalanced or
    eccentric load — one period per load revolution, independent of current."""

    names: tuple[str, ...] = ("load_sin", "load_cos")
    #: radians of load angle per position unit
    scale: float = 1.0

    def simulate(self, sig, theta, omega, idx, state):
        a = self.scale * theta
        return [np.sin(a), np.cos(a)]

    def fast(self, sig):
        return [(None, [(fs.SIN, 1.0, 0.0, 0.0, self.scale)]),
                (None, [(fs.COS, 1.0, 0.0, 0.0, self.scale)])]


def load_angle_scale(sig) -> float | None:
    """Radians of load angle per position unit: the motor angle over the gear ratio
    (``Signals.load_ratio``; not given: the position is taken as the load's angle, as
    on a robot joint's angle or a direct drive).  None when the position is not an
    angle and no lead was given."""
    if sig.rad_per_unit is None:
        return None
    return sig.rad_per_unit / (sig.load_ratio or 1.0)


class LoadTorque(Effect):
    """A load torque that varies with the load's angle, order 1 of it (gravity,
    unbalance, an eccentric load).  Distinct from cogging, which has orders of the
    *motor* angle: with the gear ratio known (``--ratio``) they are different columns;
    without it, order 1 of the position is both, reported as alike (the simpler
    load torque named, the experiment that separates them given).  A real robot
    joint's gravity came out as "cogging order 1" of 102 N m before this candidate."""

    name = "load_torque"

    def grid(self, sig, base):
        k = load_angle_scale(sig)
        if k is None:
            return []
        # the load must turn far enough for sin and cos of its angle to differ from a
        # constant and a ramp (a quarter of a load revolution)
        if np.ptp(sig.position_rad) * k < 0.5 * np.pi:
            return []
        return [{"load_scale_rad_per_unit": float(k)}]

    def extra(self, hp):
        return [LoadTorqueTerm(scale=hp["load_scale_rad_per_unit"])]

    def describe(self, model, base, hp):
        amp, h, ph = _amp_phase(model, "load_sin", "load_cos", 1.0 / base.kt_over_j(model))
        return {"load_amp_a": amp, "load_amp_a_pm": h, "load_phase_rad": ph,
                "pattern": "order 1 of the load angle (position / gear ratio)",
                "load_rad_per_position_unit": hp["load_scale_rad_per_unit"]}
