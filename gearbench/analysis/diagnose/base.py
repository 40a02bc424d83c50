"""The nominal model effects augment (``Base``) and the interface of one candidate
effect (``Effect``): ``grid`` (values of its nonlinear settings to scan — a cogging
order, a delay, a Stribeck speed...), ``build`` (the nominal terms plus its own,
linear in their coefficients), ``describe`` (fitted parameters with 95 % intervals,
torques as current equivalents ``*_a`` = torque / Kt) and ``inadmissible`` (why a fit
is not physical).  Coefficients are per unit inertia (N m / J), so a torque T appears
as T/J = (T/Kt) * (Kt/J)."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .nominal import GivenModel, GivenNominal, Model, Signals, Term, nominal_terms
from .nominal import kt_over_j as _kt_over_j

Z95 = 1.96
#: A feature must be material (mean magnitude) on at least this share of the trace
#: for its effect to be testable at all.
MIN_SUPPORT = 0.02


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
    #: viscous drag fitted (False: D held at 0, the bound of D >= 0, after a free fit
    #: came out negative)
    drag: bool = True

    def with_effect(self, effect: "Effect", hp: dict) -> "Base":
        base = effect.adjust_base(self, hp)
        return replace(base, chosen=(*base.chosen, (effect, dict(hp))))

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
            return nominal_terms(self.spring, delay, sat_a, hold, off, self.drag)
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
        base = self.adjust_base(base, hp)
        return base.terms() + self.extra(hp), base.fixed()

    def adjust_base(self, base: Base, hp: dict) -> Base:
        """The model this effect augments with settings of earlier effects that its
        own ``hp`` re-chooses (default: none)."""
        return base

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

    def inadmissible(self, sig: Signals, model: Model, base: Base, hp: dict) -> str | None:
        """Why the fitted effect is not physical or lies outside what the trace can
        show (None: admissible).  Such a fit is never chosen, whatever it closes.

        Parameters
        ----------
        sig : Signals
            The trace.
        model : Model
            The nominal refitted with the effect at settings ``hp``.
        base, hp
            The model it augments and the effect's settings.
        """
        p = model.params()
        bad = [n for n in self.positive if not p.get(n, 1.0) > 0]
        return f"fitted {', '.join(bad)} <= 0 (not physical)" if bad else None


def split_timing(tau: float) -> tuple[int, float]:
    """Current timing tau (samples; 0..1 is the nominal's hold) -> whole samples of
    delay and the hold fraction within the sample."""
    d = int(np.floor(tau))
    return d, float(tau - d)
