"""``diagnose(trace)``: where the paper's model misses, which effect explains it, how far
adding it closes the gap — all scored on held-out data against the data's noise floor."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize

from ...trace import Trace
from . import simerror, verdict as vd, where as wh
from .effects import LIBRARY, Base, Effect, EncoderQuantization, InertiaMismatch
from .nominal import (GivenModel, Model, Signals, fit_model, fit_windows, physical,
                      prepare)


@dataclass(frozen=True)
class Diagnosis:
    """The where / which / how-far answer for one trace."""

    nominal: dict
    where: list[dict]
    candidates: list[vd.Score]
    verdict: vd.Verdict
    residuals: dict = field(repr=False, default_factory=dict)   # arrays for plots/rerun

    def as_dict(self) -> dict:
        return {"nominal": self.nominal, "where": self.where,
                "candidates": [c.as_dict() for c in self.candidates],
                "verdict": self.verdict.as_dict()}


def _fit_effect(sig, base, effect: Effect, win):
    """Scan the effect's grid by equation-error RSS, then refine its continuous
    settings (Nelder-Mead in log space) — resonances are sharp, grids are coarse."""
    def fit(hp):
        terms, fixed = effect.build(sig, base, hp)
        model, rss = fit_model(sig, terms, win, fixed)
        return hp, model, rss

    grid = effect.grid(sig, base)
    best = min((fit(hp) for hp in grid), key=lambda r: r[2])
    if effect.continuous:
        keys = effect.continuous
        x0 = np.log([best[0][k] for k in keys])
        bounds = [(np.log(min(g[k] for g in grid)), np.log(max(g[k] for g in grid)))
                  for k in keys]

        def cost(x):
            hp = {**best[0], **{k: float(np.exp(v)) for k, v in zip(keys, x)}}
            return fit(hp)[2]

        res = minimize(cost, x0, method="Nelder-Mead", bounds=bounds,
                       options={"maxfev": 40 * len(keys), "xatol": 1e-3, "fatol": 1e-9})
        if res.fun < best[2]:
            best = fit({**best[0], **{k: float(np.exp(v)) for k, v in zip(keys, res.x)}})
    return best


def _n_settings(effect: Effect, sig, base) -> int:
    grid = effect.grid(sig, base)
    return len([k for k in grid[0] if len({g[k] for g in grid}) > 1])


def _n_free(model: Model, base: Base, effect: Effect | None) -> int:
    fixed = 1 if (base.given is not None and not isinstance(effect, InertiaMismatch)) else 0
    return len(model.coef) - fixed


def diagnose(trace: Trace, model: GivenModel | None = None) -> Diagnosis:
    """Diagnose one single-motor trace (columns position_rad, current_a).

    1. nominal: the paper's model (C = 0 unless a spring shows on held-out data),
       identified by integrated equation error on the fit blocks, or ``model``;
    2. where: residual maps of simulation and equation error vs the noise floor;
    3. which / how far: each effect in the library fitted as an augmentation (its
       settings scanned), scored by held-out simulation error (see verdict.py).
    """
    sig = prepare(trace)
    sp = simerror.split(sig)
    win = fit_windows(sig, sp.fit_mask)
    starts, H = sp.score_starts, sp.horizon
    v_rms = float(np.sqrt(np.mean(sig.velocity_rad_s[np.add.outer(starts, np.arange(1, H + 1))] ** 2)))
    v_rms = max(v_rms, 1e-9)

    base = Base(given=model)
    nom, _ = fit_model(sig, base.terms(), win, base.fixed())
    err_nom = simerror.simulate(sig, nom, starts, H)
    mse_nom = simerror.horizon_mse(err_nom)
    floor = simerror.noise_floor(sig, base.kt_over_j(nom), H)

    if model is None:  # keep the paper's spring only if it predicts held-out data better
        spring_base = Base(spring=True)
        nom_c, _ = fit_model(sig, spring_base.terms(), win)
        mse_c = simerror.horizon_mse(simerror.simulate(sig, nom_c, starts, H))
        s = vd.score("spring", {}, mse_nom, mse_c, 1, floor.mse, v_rms)
        if s.significant:
            base, nom, mse_nom = spring_base, nom_c, mse_c
            err_nom = simerror.simulate(sig, nom, starts, H)

    nominal_phys = physical(nom) if model is None else {
        "kt_over_j": base.kt_over_j(nom), "d_over_j": model.d_over_j,
        "c_over_j": model.c_over_j, "hold_fraction": nom.params()["hold"]}

    scores = []
    for effect in LIBRARY:
        if isinstance(effect, EncoderQuantization):
            scores.append(_score_quantization(sig, floor, mse_nom, v_rms))
            continue
        hp, m, _ = _fit_effect(sig, base, effect, win)
        after = simerror.horizon_mse(simerror.simulate(sig, m, starts, H))
        # scanned settings count as parameters too (Occam between look-alikes)
        k_extra = _n_free(m, base, effect) - _n_free(nom, base, None) + _n_settings(effect, sig, base)
        phys = physical(m) if model is None else {"kt_over_j": base.kt_over_j(m)}
        shift = {k: (phys[k] - nominal_phys[k]) / nominal_phys[k]
                 for k in ("kt_over_j", "d_over_j") if k in phys and nominal_phys.get(k)}
        scores.append(vd.score(effect.name, effect.describe(m, base, hp), mse_nom, after,
                               max(k_extra, 1), floor.mse, v_rms, shift))
    ranked = vd.rank(scores)
    verdict = vd.verdict(ranked)

    where_cells, maps = wh.breakdown(sig, nom, err_nom, starts, floor)
    fit = {"sim_rms_rad_s": float(np.sqrt(np.mean(mse_nom))),
           "noise_floor_rad_s": float(np.sqrt(floor.mse)),
           "gap_ratio": float(np.sqrt(np.mean(mse_nom) / floor.mse)),
           "nrmse": float(np.sqrt(np.mean(mse_nom))) / v_rms,
           "current_noise_a": floor.current_noise_a,
           "velocity_noise_rad_s": floor.velocity_noise_rad_s,
           "horizon_s": H * sig.dt_s, "held_out_horizons": int(len(starts)),
           "spring_kept": bool(base.spring), "given_model": model is not None}
    nominal = {"params": {**nominal_phys, **_sigmas(nom, model)}, "fit": fit}
    return Diagnosis(nominal, where_cells, ranked, verdict, maps)


def _sigmas(nom: Model, model) -> dict:
    if model is not None:
        return {}
    sd = nom.sigma()
    return {"kt_over_j_pm": 1.96 * float(np.hypot(sd.get("a0", 0), sd.get("a1", 0))),
            "d_over_j_pm": 1.96 * sd.get("d_over_j", 0.0)}


def _score_quantization(sig: Signals, floor: simerror.NoiseFloor, mse_nom, v_rms) -> vd.Score:
    """The share of the error that the encoder's quantisation noise explains.

    It counts (``significant``) only when quantisation noise in the velocity estimate
    exceeds the current-noise part of the floor and the nominal error lies
    significantly above the floor a continuous sensor would give.
    """
    q = simerror.lattice_step(sig.position_rad)
    params = {"step_rad": q, "counts_per_rev": (2 * np.pi / q) if q else None}
    if not q:
        return vd.score("encoder_quantization", params, mse_nom, mse_nom, 1, floor.mse, v_rms)
    quant_var = 2 * simerror.velocity_noise(q / np.sqrt(12), sig.dt_s) ** 2
    current_part = float(np.mean(floor.floor_var - 2 * floor.velocity_noise_rad_s ** 2))
    floor_cont = floor.mse - quant_var
    after = np.maximum(mse_nom - quant_var, 0.0)
    s = vd.score("encoder_quantization", params, mse_nom, after, 1, max(floor_cont, 1e-300), v_rms)
    dominant = quant_var > current_part
    above = vd.paired_t(mse_nom, np.full_like(mse_nom, max(floor_cont, 0.0))) > 5.0
    return vd.Score(**{**s.__dict__, "significant": bool(s.significant and dominant and above)})
