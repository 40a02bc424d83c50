"""Candidates scored against the chain's current model: each effect's settings
scanned and refined, fitted per fold, scored on the other fold's held-out horizons
by simulation error, against a null of random smooth regressors."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import minimize

from . import simerror, testability, verdict as vd
from .effects import LIBRARY, Base, Effect, EncoderQuantization, InertiaMismatch
from .nominal import (GivenModel, Model, Signals, Term, Windows, fit_model, integrated_rows,
                      measured_features, physical, scan_rss)


@dataclass(frozen=True)
class Context:
    """What every step of one diagnosis shares (one object instead of the ten values
    once passed positionally): the trace, its two-fold split, the fit windows of each
    fold and of the whole trace, the time order of the held-out horizons, the noise
    floor, the measured velocity's rms over them, how many held-out horizons overlap
    each sample, the given nominal (None: identified) and the testability verdicts."""

    sig: Signals
    sp: simerror.Split
    wins: tuple[Windows, ...]
    win_all: Windows
    order: np.ndarray
    floor: simerror.NoiseFloor | None = None
    v_rms: float = 1.0
    ov: int = 1
    given: GivenModel | None = None
    tests: dict = None

    @property
    def horizon(self) -> int:
        return self.sp.horizon

    @property
    def starts(self) -> np.ndarray:
        """Held-out horizon starts in time order."""
        return self.sp.score_starts[self.order]


@dataclass
class State:
    """The model the chain has built so far: one base per fold (each fold's nonlinear
    settings chosen on its own fit blocks, so held-out scoring stays honest), one for
    all the data (fold 0's settings; for reporting), its held-out errors and the
    per-fold refined models."""

    bases: list
    base_all: Base
    folds: list
    mse: np.ndarray
    model_all: Model
    noise_removed: float = 0.0     # quantisation noise variance explained (per horizon)


@dataclass(frozen=True)
class NullTerm(Term):
    """Two random smooth torques with no physics in them: the chain's null candidate.
    What fitting them closes on held-out data is what any flexible regressor would;
    an effect must do significantly better than that to be added."""

    names: tuple[str, ...] = ("null_1", "null_2")
    seed: int = 0

    def _cols(self, sig):
        key = ("null", self.seed)
        if key not in sig.cache:
            rng = np.random.default_rng(self.seed)
            n = len(sig)
            # varies on the scale of half a horizon, like the effects' signatures
            width = max(3, int(round(0.5 * simerror.HORIZON_S / sig.dt_s)))
            k = np.ones(width) / width
            cols = []
            for _ in self.names:
                x = np.convolve(rng.standard_normal(n + width), k, mode="valid")[:n]
                cols.append(x / (np.std(x) or 1.0))
            sig.cache[key] = cols
        return sig.cache[key]

    def simulate(self, sig, theta, omega, idx, state):
        return [c[idx] for c in self._cols(sig)]

    def fast(self, sig):
        return [(c, []) for c in self._cols(sig)]


#: Most trace samples x grid columns featurised at once in a batched scan (memory).
SCAN_CHUNK = 4_000_000


#: Fit horizons a simulation-error scan uses (evenly thinned; speed).
SCAN_HORIZONS = 60


def sim_cost(sig, effect: Effect, base, win, starts, horizon):
    """hp -> (model, simulation MSE on the fit horizons ``starts``) for effects scanned
    by simulation error (``effect.by_simulation``): the nominal refitted by equation
    error with the effect's settings held, the score taken from simulation."""
    if len(starts) > SCAN_HORIZONS:
        starts = starts[np.linspace(0, len(starts) - 1, SCAN_HORIZONS).round().astype(int)]

    def cost(hp):
        terms, fixed = effect.build(sig, base, hp)
        model = fit_model(sig, terms, win, fixed)[0]
        e = simerror.simulate(sig, model, starts, horizon)
        return model, float(np.nan_to_num(np.mean(e ** 2), nan=1e300, posinf=1e300))
    return cost


def _scan(sig, bases, effect: Effect, wins, sims=None) -> list[dict]:
    """Best grid setting per fit window set (``bases[i]`` the model augmented for
    window set ``wins[i]``), by equation-error RSS.

    Effects that only add columns to the nominal (``extra``) are scanned in batches:
    each grid point's features are computed once for all folds, and every fold's
    grid is solved in one projection (nominal.scan_rss); effects that change the
    nominal's own columns (delay, saturation) are refitted per grid point."""
    if not isinstance(bases, (list, tuple)):
        bases = [bases] * len(wins)
    grid = effect.grid(sig, bases[0])
    if sims is not None:
        return [min(grid, key=lambda hp: c(hp)[1]) for c in sims]
    k = sum(len(t.names) for t in effect.extra(grid[0]))
    if type(effect).build is not Effect.build or k == 0:
        def rss_at(hp, w, base):
            terms, fixed = effect.build(sig, base, hp)
            model, rss = fit_model(sig, terms, w, fixed)
            return rss if _physical(model, effect) else np.inf
        return [min(grid, key=lambda hp: rss_at(hp, w, b)) for w, b in zip(wins, bases)]
    names = [n for t in effect.extra(grid[0]) for n in t.names]
    positive = tuple(names.index(p) for p in effect.positive)
    rss = np.empty((len(wins), len(grid)))
    per = max(1, SCAN_CHUNK // (len(sig) * k))
    for a in range(0, len(grid), per):
        F = measured_features(sig, [t for hp in grid[a:a + per] for t in effect.extra(hp)])
        for i, (w, b) in enumerate(zip(wins, bases)):
            E = integrated_rows(sig, F, w)[0]
            rss[i, a:a + per] = scan_rss(sig, b.terms(), w, b.fixed(), E, k, positive)
    return [grid[int(np.argmin(r))] for r in rss]


def _physical(model: Model, effect: Effect) -> bool:
    p = model.params()
    return all(p.get(n, 1.0) > 0 for n in effect.positive)


def fit_effect(sig, base, effect: Effect, win, hp0: dict | None = None, sim=None):
    """Fit the effect at grid setting ``hp0`` (the scan's best; scanned here if not
    given), then refine its continuous settings (Nelder-Mead in log space) —
    resonances are sharp, grids are coarse.  ``sim``: score by simulation error."""
    def fit(hp):
        if sim is not None:
            return (hp, *sim(hp))
        terms, fixed = effect.build(sig, base, hp)
        model, rss = fit_model(sig, terms, win, fixed)
        # a large finite cost, not inf: Nelder-Mead subtracts costs
        return hp, model, (rss if _physical(model, effect) else 1e300)

    grid = effect.grid(sig, base)
    if hp0 is None:
        hp0 = _scan(sig, base, effect, [win])[0]
    best = fit(hp0)
    # settings the grid holds at one value (a Coulomb width a standstill bounds) stay
    keys = tuple(k for k in effect.continuous if len({g[k] for g in grid}) > 1)
    if keys:
        x0 = np.log([best[0][k] for k in keys])
        bounds = [(np.log(min(g[k] for g in grid)), np.log(max(g[k] for g in grid)))
                  for k in keys]

        # relative to the start: an RSS is in the user's position unit squared, and
        # an absolute tolerance stopped the search early in metres, late in degrees
        c0 = best[2] if 0 < best[2] < 1e300 else 1.0

        def cost(x):
            hp = {**best[0], **{k: float(np.exp(v)) for k, v in zip(keys, x)}}
            return fit(hp)[2] / c0

        res = minimize(cost, x0, method="Nelder-Mead", bounds=bounds,
                       options={"maxfev": 40 * len(keys), "xatol": 1e-3, "fatol": 1e-9})
        if res.fun * c0 < best[2]:
            best = fit({**best[0], **{k: float(np.exp(v)) for k, v in zip(keys, res.x)}})
    return best


def n_settings(effect: Effect, sig, base) -> int:
    grid = effect.grid(sig, base)
    keys = dict.fromkeys(k for g in grid for k in g)     # a setting some points leave out
    return len([k for k in keys if len({g.get(k) for g in grid}) > 1])


def _n_free(model: Model, base: Base, effect: Effect | None) -> int:
    fixed = 1 if (base.given is not None and not isinstance(effect, InertiaMismatch)) else 0
    return len(model.coef) - fixed


#: How many leading candidates are refined on simulation error.
N_REFINE = 3


def held_out(ctx: Context, models) -> np.ndarray:
    """Per-horizon MSE on the held-out horizons of every fold, each scored by the model
    fitted on the other fold; in time order (``ctx.order`` sorts the concatenated starts)."""
    sp = ctx.sp
    mse = [simerror.horizon_mse(simerror.simulate(ctx.sig, m, f.score_starts, sp.horizon))
           for m, f in zip(models, sp.folds)]
    return np.concatenate(mse)[ctx.order]


def evaluate(ctx: Context, st: State, err_cur, exclude=()):
    """Score every candidate not yet chosen against the current model ``st``.

    Returns (scores ranked, per-effect fold fits, per-effect refined fold models)."""
    sig, sp, wins, win_all = ctx.sig, ctx.sp, ctx.wins, ctx.win_all
    floor, v_rms, ov, given = ctx.floor, ctx.v_rms, ctx.ov, ctx.given
    H = sp.horizon
    cur_phys = physical(st.model_all) if given is None else {
        "kt_over_j": st.base_all.kt_over_j(st.model_all)}
    scores, refits, rejected = [], {}, {}
    base0 = st.bases[0]
    for effect in LIBRARY:
        if effect.name in exclude:
            continue
        if isinstance(effect, EncoderQuantization):
            scores.append(_score_quantization(sig, floor, st.mse, v_rms, ov, err_cur))
            continue
        if not effect.grid(sig, base0):  # nothing on this trace can show the effect
            scores.append(vd.score(effect.name, {"note": "not testable on this trace "
                                                 "(no motion where the effect acts)"},
                                   st.mse, st.mse, 1, floor.mse, v_rms, overlap=ov))
            continue
        sims = ([sim_cost(sig, effect, b, w, f.fit_starts, H)
                 for b, w, f in zip(st.bases, wins, sp.folds)]
                if getattr(effect, "by_simulation", False) else [None] * len(wins))
        hps = _scan(sig, st.bases, effect, wins, sims if sims[0] is not None else None)
        fits = [fit_effect(sig, b, effect, w, hp, c)
                for b, w, hp, c in zip(st.bases, wins, hps, sims)]
        after = held_out(ctx, [m for _, m, _ in fits])
        after = np.maximum(after - st.noise_removed, 0.0)
        refits[effect.name] = (effect, fits)
        # parameters reported from all the data, at the first fold's settings
        hp = fits[0][0]
        terms, fixed = effect.build(sig, st.base_all, hp)
        m, _ = fit_model(sig, terms, win_all, fixed)
        # scanned settings count as parameters too (Occam between look-alikes)
        k_extra = (_n_free(m, st.base_all, effect) - _n_free(st.model_all, st.base_all, None)
                   + n_settings(effect, sig, base0))
        why_not = effect.inadmissible(sig, m, st.base_all, hp)
        if why_not:
            rejected[effect.name] = why_not
        phys = physical(m) if given is None else {"kt_over_j": st.base_all.kt_over_j(m)}
        shift = {k: (phys[k] - cur_phys[k]) / cur_phys[k]
                 for k in ("kt_over_j", "d_over_j") if k in phys and cur_phys.get(k)}
        sc = vd.score(effect.name, effect.describe(m, st.base_all, hp), st.mse, after,
                      max(k_extra, 1), floor.mse, v_rms, shift, overlap=ov)
        scores.append(sc)
    # the leading candidates are refined on simulation error too (the nominal was), so
    # none wins only because equation error left the nominal biased
    ranked = vd.rank(scores)
    refined_folds = {}
    for i, sc in enumerate(ranked[:N_REFINE]):
        if sc.effect not in refits:
            continue
        effect, fits = refits[sc.effect]
        models = []
        for (hp, m, _), b, f in zip(fits, st.bases, sp.folds):
            fixed = tuple(effect.build(sig, b, hp)[1])
            models.append(simerror.refine(sig, m, f.fit_starts, H, fixed))
        if not all(_physical(m, effect) for m in models):
            continue     # the sign constraint holds in refinement too: keep the fits
        after = np.maximum(held_out(ctx, models) - st.noise_removed, 0.0)
        refined_folds[sc.effect] = models
        ranked[i] = vd.rescore(sc, st.mse, after, floor.mse, v_rms)
    # the null: random smooth regressors fitted and scored the same way; a candidate is
    # significant only if it beats them too (paired t on held-out horizons, and a
    # larger shrink) — flexible candidates soak up structure any regressor would
    null_mse = _null_mse(ctx, st)
    null = vd.score("null", {}, st.mse, null_mse, 2, floor.mse, v_rms, overlap=ov)
    ranked = [sc if sc.effect == "encoder_quantization" else
              vd.against_null(sc, null_mse, null.shrink) for sc in ranked]
    # a fit outside what is physical or what the trace can show is never chosen
    ranked = vd.rank([replace(sc, significant=False,
                              params={**sc.params, "not_physical": rejected[sc.effect]})
                      if sc.effect in rejected else sc for sc in ranked])
    return ranked, refits, refined_folds


def fit_bases(ctx: Context, bases, noise_removed: float = 0.0):
    """Per-fold models for ``bases`` (fitted on each fold, refined on simulation error)
    and their held-out per-horizon MSE."""
    sig, sp = ctx.sig, ctx.sp
    folds = []
    for b, w, f in zip(bases, ctx.wins, sp.folds):
        m = fit_model(sig, b.terms(), w, b.fixed())[0]
        folds.append(simerror.refine(sig, m, f.fit_starts, sp.horizon, tuple(b.fixed())))
    mse = np.maximum(held_out(ctx, folds) - noise_removed, 0.0)
    return folds, mse


def _null_mse(ctx: Context, st: State) -> np.ndarray:
    bases = [_NullBase(b) for b in st.bases]
    return fit_bases(ctx, bases, st.noise_removed)[1]


@dataclass(frozen=True)
class _NullBase:
    """A base with the null's random regressors appended."""

    base: Base

    def terms(self):
        return self.base.terms() + [NullTerm(seed=0)]

    def fixed(self):
        return self.base.fixed()




def gate(ranked, tests):
    """Testability decides — with the held-out evidence as the last word.

    An effect the excitation check (testability.py, a prior judged from the trace's
    regressors) calls untestable is never significant, except the largest significant
    improvement on held-out data: that one the trace did show, and "not testable" on
    it contradicted the numbers (Coulomb friction on a real robot joint: shrink 60 %,
    dBIC -875, Tc within 9 % of the published value, marked "only in a few windows").
    Effects that physically cannot act on the excitation (testability.PREREQUISITE: a
    gap is crossed only at torque reversals) stay gated."""
    shown = [sc for sc in ranked if sc.significant]
    best = max(shown, key=lambda sc: sc.shrink) if shown else None
    # ... and clearly better than every testable candidate: an untestable effect that a
    # testable one matches is its look-alike on this excitation (position friction on
    # one-way motion is cogging), and stays gated
    top = best.effect if best is not None and all(
        vd.paired_t(sc.mse_h, best.mse_h, best.overlap) > vd.T_CONFUSED
        and best.shrink > sc.shrink + vd.SHRINK_CONFUSED
        for sc in shown if sc is not best and tests.get(sc.effect) is not None
        and tests[sc.effect].testable) else None
    out = []
    for sc in ranked:
        t = tests.get(sc.effect)
        if t is None:
            out.append(sc)
            continue
        ok = t.testable or (sc.effect == top and sc.effect not in testability.PREREQUISITE)
        why = t.why if t.testable or not ok else (
            "shown on held-out data (the largest significant improvement); the "
            f"excitation check alone said: {t.why}")
        out.append(replace(sc, testable=bool(ok), why=why, min_detectable=t.min_amplitude,
                           significant=sc.significant and ok))
    return vd.rank(out)


def _score_quantization(sig: Signals, floor: simerror.NoiseFloor, mse_nom, v_rms, ov,
                        err_nom: np.ndarray) -> vd.Score:
    """The share of the error that the encoder's quantisation noise explains.

    The nominal's error variance per horizon step m is fitted as a + b m (a = velocity
    noise at both ends, b = what accumulates: current noise and model error).  The
    encoder is the cause when it sits on a lattice of step q, its quantisation noise
    2 (q/sqrt(12) g)^2 (g = SG noise gain) explains the measured intercept a (at least
    half of it) and outweighs what accumulates over the horizon (b * mean m) — then
    removing it brings the error to the floor of a continuous sensor, whose current
    part is the smaller of b and the current-noise estimate (real high-frequency current
    from the drive reacting to coarse counts inflates the latter)."""
    q = simerror.lattice_step(sig.position_rad)
    k = sig.rad_per_unit
    params = {"step_rad": q, "counts_per_rev": (2 * np.pi / (q * k)) if q and k else None}
    if not q:
        return vd.score("encoder_quantization", params, mse_nom, mse_nom, 1, floor.mse, v_rms,
                        overlap=ov)
    H = err_nom.shape[1]
    m = np.arange(1, H + 1)
    a, b = np.polynomial.polynomial.polyfit(m, np.mean(err_nom ** 2, axis=0), 1)
    quant_var = simerror.end_noise_var(q / np.sqrt(12), sig.dt_s)
    s_th = floor.velocity_noise_rad_s / simerror.velocity_noise(1.0, sig.dt_s)
    current_part = float(np.mean(floor.floor_var - simerror.end_noise_var(s_th, sig.dt_s)))
    growth = max(min(b * m.mean(), current_part), 0.0)
    floor_cont = max(growth, 1e-300)
    after = np.maximum(mse_nom - quant_var, 0.0)
    s = vd.score("encoder_quantization", {**params, "intercept_rad_s": float(np.sqrt(max(a, 0))),
                                          "quantisation_rad_s": float(np.sqrt(quant_var))},
                 mse_nom, after, 1, floor_cont, v_rms, overlap=ov)
    explains = quant_var > 0.5 * a and quant_var > max(b, 0.0) * m.mean()
    return vd.Score(**{**s.__dict__, "significant": bool(s.significant and explains)})
