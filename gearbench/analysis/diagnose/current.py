"""Current-sensing and timing candidates: a current offset, a measurement delay,
Kt saturation, an inertia different from a given model's, encoder quantisation."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .base import Effect, _pm, split_timing
from .nominal import Term


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

    def inadmissible(self, sig, model, base, hp):
        # a sensor offset outside the measured current's range would leave a true
        # current that never changes sign while the motor is driven both ways (an
        # offset of 18 A on a current within -3.5..6.8 A was reported on a real joint)
        off = self.describe(model, base, hp)["offset_a"]
        lo, hi = float(np.min(sig.current_a)), float(np.max(sig.current_a))
        if not lo < off < hi:
            return (f"offset {off:.4g} A outside the measured current's range "
                    f"{lo:.4g}..{hi:.4g} A (the true current would never change sign)")
        return None


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
    """Kt_eff = Kt / (1 + (i/i_sat)^2): torque constant falling at high current.

    The trace shows the fall of Kt up to its largest current, not i_sat itself (the
    current at which Kt has halved): reported is the fall at the largest measured
    current, and i_sat marked extrapolated when it lies beyond the data (19.96 A was
    reported bare on a real joint whose current stays within +-4.4 A: a 4.6 % fall).
    The scan keeps i_sat up to 4.5x the largest current: the injected-effect scorecard's
    saturations (0.8-3 A on currents within 0.34 A, a 1-15 % fall) are real and found."""

    name = "kt_saturation"
    continuous = ("kt_sat_a",)

    def grid(self, sig, base):
        imax = float(np.max(np.abs(sig.current_a)))
        return [{"kt_sat_a": imax * f, "largest_current_a": imax}
                for f in (0.3, 0.45, 0.6, 0.8, 1.0, 1.3, 1.7, 2.2, 3.0, 4.5)]

    def build(self, sig, base, hp):
        return base.terms(sat_a=hp["kt_sat_a"], sat_off=hp.get("kt_sat_offset_a", 0.0)), base.fixed()

    def describe(self, model, base, hp):
        out = dict(hp)
        imax = hp.get("largest_current_a")
        if imax:
            out["kt_fall_at_largest_current"] = float(1.0 - 1.0 / (1.0 + (imax / hp["kt_sat_a"]) ** 2))
            out["kt_sat_extrapolated"] = bool(hp["kt_sat_a"] > imax)
            out["kt_deficit_at_largest_current_a"] = float(imax * out["kt_fall_at_largest_current"])
        return out

    def inadmissible(self, sig, model, base, hp):
        """Judged by what the trace can show — the torque Kt's fall takes away at the
        largest measured current, as a current (i_max * fall) — not by the knee i_sat,
        which only the curve's continuation beyond the data would show.  A deficit
        below the trace's own current noise (per sample) is invisible in it: refused.
        A knee above the largest current with a visible fall is kept (marked
        extrapolated): the fall within the range is what was measured."""
        why = super().inadmissible(sig, model, base, hp)
        d = self.describe(model, base, hp)
        deficit = d.get("kt_deficit_at_largest_current_a")
        if why is None and deficit is not None:
            from .simerror import current_noise
            noise = current_noise(sig)
            if deficit < noise:
                why = (f"Kt falls {d['kt_fall_at_largest_current']:.1%} at the largest "
                       f"current {hp['largest_current_a']:.3g} A: {1e3 * deficit:.2g} mA of "
                       f"torque-current, below the current noise {1e3 * noise:.2g} mA — "
                       f"not visible in this trace")
        return why


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


class EncoderQuantization(Effect):
    """A coarse encoder: the angle sits on a lattice of step q; the velocity estimate
    then carries uniform quantisation noise.  Nothing to refit in the dynamics — the
    candidate explains that noise's share of the simulation error (see verdict)."""

    name = "encoder_quantization"

    def describe(self, model, base, hp):
        return dict(hp)
