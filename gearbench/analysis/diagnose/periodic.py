"""Torques periodic in an angle: cogging and commutation ripple (orders of the motor
angle) and a position-dependent load torque (gravity, unbalance, an eccentric load:
order 1 of the load angle)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import fastsim as fs
from .base import Effect, _amp_phase
from .nominal import Term


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
