"""The effect chain: each candidate the block switched off tried by its held-out gain, the
best added and the model refitted (``add_effects``)."""
from __future__ import annotations

import copy
import math

import numpy as np

from ..gap import MAX_ORDER
from ..replay import AXES
from .lm import MODEL_LIMITED_S_N, _jacobian, _projected, fit, set_intervals
from .params import Param, _clip, _kts, candidates, get_value, ripple_cogging_ambiguity, set_value, with_params, written_values
from .problem import Problem, folds, start_values
from .profiles import apply_profiles
from .smoothness import correct_smoothing_shift, settle, update_events


MIN_DROP = 25.0        # held-out S must fall by this many floors² ...
MIN_SHRINK = 0.05      # ... and by this fraction of itself (a stalled fit leaves a few % to any candidate)
# ... or, once the model is at the noise (S/n ≤ MODEL_LIMITED_S_N), by more than this many s²
# (s² = held-out S/n): a small effect beside the noise (an input ripple of the cogging's order
# and phase, separable only where the current varies at one angle, gained 1.3 % of S, 650 s²
# over 55,000 held-out residuals, on a hidden cvt run; a candidate the runs do not show gains
# under 0.0005 floors² a sample, < 100 s²). A model still far from the data gains a few % on
# any candidate: there only MIN_SHRINK counts
STRONG_DROP = 300.0
# a candidate whose linearised step promises less than this many s² on the held-out fold
# is not replayed (``_predicted_heldout``): two replays saved per candidate the run does not show
PRESCREEN = 5.0
ORDERS_TRIED = 3      # ripple orders replayed per axis, best linearised held-out gain first (``residual_orders``)
# a scan whose best S (others linearised) is under this fraction of the fit's S is screened
# by a short refit, not one Gauss-Newton step (``add_effects``)
SCAN_REFIT = 0.5
REFIT_ITERATIONS = 10   # LM iterations of the chain's refit after an effect is added
DEBUG = False


def ripple_regressors(prob: Problem, axis: str, k: int) -> np.ndarray:
    """Linearised columns of a torque ripple of order ``k`` on ``axis`` (no replay): the
    ripple torque Kt·i·a·sin(kθ) is taken up by whichever drive holds the speed, so the
    current residual of that drive moves with i·sin(kθ) and i·cos(kθ) of the ripple's motor
    (cos: the speed loop's phase at k·ω). Four columns: on the motor's own current where it
    is speed-controlled, and on the other motor's current where the reducer couples them
    and the ripple's motor is torque-controlled (cyclo's output in the efficiency map); rows
    of the stacked residual (``Problem.residual_vector``), zero off the current rows."""
    segs = {s.name: s for s in prob.segments}
    cols = []
    for key in prob.residual_keys():
        seg = segs[key[0]]
        n = len(seg.trace)
        block = np.zeros((n, 4))
        if key[2] == "current_a" and f"{axis}.position_rad" in seg.trace and f"{axis}.current_a" in seg.trace:
            th = np.asarray(seg.trace[f"{axis}.position_rad"], float)
            cur = np.asarray(seg.trace[f"{axis}.current_a"], float)
            own = key[1] == axis and seg.modes.get(axis) == "velocity"
            coupled = (key[1] != axis and seg.coupling == "reducer" and seg.modes.get(key[1]) == "velocity"
                       and seg.modes.get(axis) == "torque")
            if own or coupled:
                j = 0 if own else 2
                block[:, j], block[:, j + 1] = cur * np.sin(k * th), cur * np.cos(k * th)
        cols.append(block)
    return np.concatenate(cols) if cols else np.zeros((0, 4))


def residual_orders(prob: Problem, r: np.ndarray, fit_fold: np.ndarray, held: np.ndarray) -> dict:
    """Per axis the ``ORDERS_TRIED`` angle orders k (1..``MAX_ORDER``) of a torque ripple
    whose linearised step (``ripple_regressors``, fitted on the fit fold) removes the most
    of the held-out S, best first; orders that remove nothing are left out. Every order is
    screened (a ranking by the residual's correlation with i·sin(kθ) of the motor's own
    current put a hidden cyclo run's order-4 output ripple fourteenth: the output motor is
    torque-controlled in the efficiency map, where its ripple shows in the input current)."""
    orders = {}
    for a in AXES:
        gains = []
        for k in range(1, MAX_ORDER + 1):
            X = ripple_regressors(prob, a, k)
            used = np.any(X != 0, axis=0)
            if not used.any():
                continue
            X = X[:, used]
            beta = np.linalg.lstsq(X[fit_fold], r[fit_fold], rcond=None)[0]
            rh = r[held]
            e = rh - X[held] @ beta
            gains.append((float(rh @ rh - e @ e), k))
        orders[a] = [k for g, k in sorted(gains, reverse=True)[:ORDERS_TRIED] if g > 0]
    return orders


def add_effects(prob: Problem, params: list[Param], *, max_effects: int = 4, verbose=None,
                last: dict | None = None) -> list[dict]:
    """The effect chain (module docstring). Mutates ``prob.block`` (fixed settings of
    the added effects) and ``params`` (their parameters appended); returns one dict per
    step: effect, parameters, held_out_shrink, significant, remaining (S/n after).
    ``last``: ``fit``'s return at the params' values (its residual and fresh Jacobian are
    reused instead of replayed)."""
    chain = []
    fit_fold, held = folds(prob)
    tried_out: set = set()
    refitted = False
    for _ in range(max_effects):
        u = np.array([p.value for p in params])
        if last is not None and last.get("jac") is not None and last["jac"].shape[1] == len(params) \
                and np.array_equal(last["u"], u):
            r, jac = last["r"], last["jac"]
        else:
            r = prob.residual_vector(with_params(prob.block, params, u))
            jac = _jacobian(prob, params, u, r)
        Sh0 = float(r[held] @ r[held])
        nh = int(held.sum())
        # the current model's own step on the fit fold, for a fair held-out baseline
        Sh_base = min(Sh0, _gn_heldout(prob, params, u, jac, r, fit_fold, held, prob.block))
        orders = residual_orders(prob, r, fit_fold, held)
        results = []
        have = {p.path for p in params}
        s2 = Sh_base / nh
        base_refit = None    # the model's own short refit's held-out S (for refit-screened candidates)
        for name, extra, fixed in candidates(prob.block, orders, prob.peak_currents(),
                                             backlash_scan(prob), prob.turning()):
            key = (name, tuple(p.path for p in extra), tuple(fixed.items()))
            if key in tried_out or have & {p.path for p in extra}:
                # already in the chain (its parameters are fitted, not yet in the block). A
                # candidate that gained nothing in one round is screened again in the next:
                # on the hidden cvt run the current offset gained +0.002 beside the missing Kt
                # saturation and +0.32 once it was in (skipping it lost the offset)
                continue
            block = copy.deepcopy(prob.block)
            for k, v in fixed.items():
                set_value(block, k, v)
            extra = [copy.copy(p) for p in extra]
            allp = params + extra
            sub = Problem(prob.segments, block, prob.quanta, prob.floors, signals=prob.signals).share_cache(prob)
            scanned = ""
            anchor = None
            if len(extra) == 1 and extra[0].scan:
                # a nonlinear effect: start from the best of its scan (the others linearised)
                anchors = [u] + ([start_values(prob, params)] if Sh_base / nh > MODEL_LIMITED_S_N else [])
                extra[0].value, table, k = scan_start(sub, params, anchors, jac, fit_fold, extra[0])
                prob.evaluations += sub.evaluations
                sub.evaluations = 0
                best = min(S for _, S in table) if table else float("inf")
                nf = int(fit_fold.sum())
                if k > 0 and best / nf < SCAN_REFIT * float(r[fit_fold] @ r[fit_fold]) / nf:
                    # the scan from the profile's values promises most of S: the fit had
                    # compensated the effect elsewhere, and one linear step from the fit cannot
                    # undo that: screen it by a short refit from the profile's values. From the
                    # fit's own values the one-step screen stays: a 2-iteration refit from there
                    # (the alt cyclo run's 3 A saturation) left the chain's refit stuck at S/n
                    # 603, the one-step screen's refit reached S/n 33 in 6 iterations
                    anchor = anchors[k]
                scanned = (f", started at {extra[0].written(None, _kts(params)):.4g} by a scan"
                           + (" from the profile's values" if k else ""))
                if verbose and DEBUG:
                    verbose("    scan " + ", ".join(f"{extra[0].written(v):.4g}: {S / nf:.4f}" for v, S in table))
            if len(extra) == 1 and (extra[0].screen_refit or anchor is not None):
                # a candidate that switches the model's structure (the backlash: rigid ->
                # compliant mesh) costs S until the other parameters follow, so a one-step
                # screen misses it: a short refit of every parameter on the fit fold instead
                trial = [copy.copy(p) for p in allp]
                if anchor is not None:
                    for q, v in zip(trial, anchor):
                        q.value = float(v)
                tr = fit(sub, trial, iterations=max(extra[0].screen_refit, 2), mask=fit_fold, intervals=False,
                         max_fresh=1)
                rt = tr["r"]
                prob.evaluations += sub.evaluations
                if rt is None:
                    continue
                Sh = float(rt[held] @ rt[held])
                extra[0].value = trial[-1].value
                if Sh_base - Sh > MIN_DROP and (Sh_base - Sh) / Sh_base > MIN_SHRINK / 2 and base_refit is None:
                    # fair to the model without it: its own short refit (a model not yet at its
                    # minimum gains from any refit: a backlash "gained" 49 % on a hidden cyclo run
                    # whose refit after a Kt saturation had stopped at S/n 33, still falling)
                    trial0 = [copy.copy(p) for p in params]
                    t0 = fit(prob, trial0, iterations=max(extra[0].screen_refit, 2), mask=fit_fold,
                             intervals=False, max_fresh=1)
                    base_refit = float(t0["r"][held] @ t0["r"][held]) if t0["r"] is not None else Sh_base
                    if verbose:
                        verbose(f"  (the model's own {max(extra[0].screen_refit, 2)}-iteration refit: "
                                f"held-out S/n {base_refit / nh:.3f})")
                Sh_ref = min(Sh_base, base_refit if base_refit is not None else Sh_base)
                shrink = (Sh_ref - Sh) / Sh_base
                # if added, the chain's refit starts from this refit (values and Jacobian)
                results.append((Sh_ref - Sh, shrink, name, extra, fixed, key, (trial, tr["jac"])))
                if verbose:
                    verbose(f"  try {name:<19} {extra[0].path:<40} held-out S/n {Sh / nh:8.3f} "
                            f"(now {Sh_base / nh:.3f}), shrink {shrink:+.3f} (after a {max(extra[0].screen_refit, 2)}-iteration "
                            f"refit on the fit fold{scanned})")
                continue
            ua = np.array([p.value for p in allp])
            ra = sub.residual_vector(with_params(block, allp, ua))
            if ra is None:
                continue
            ja = np.zeros((len(ra), len(allp)))
            ja[:, :len(params)] = jac
            if extra:
                ja[:, len(params):] = _jacobian(sub, allp, ua, ra, cols=range(len(params), len(allp)))[:, len(params):]
            Sh_start = float(ra[held] @ ra[held])
            own = list(range(len(params), len(allp)))
            if extra and not scanned and _predicted_heldout(allp, ja, ra, fit_fold, held, own) > Sh_start - PRESCREEN * s2:
                # the linearised step promises less than PRESCREEN·s² on the held-out fold:
                # not worth its two replays (a candidate the run does not show)
                Sh = Sh_start
            else:
                Sh = _gn_heldout(sub, allp, ua, ja, ra, fit_fold, held, block, own=own)
                Sh = min(Sh, Sh_start)
            prob.evaluations += sub.evaluations
            shrink = (Sh_base - Sh) / Sh_base
            # the candidate's own columns, kept for the refit's first iteration if it is added
            results.append((Sh_base - Sh, shrink, name, extra, fixed, key, ja[:, len(params):].copy()))
            if name == "torque_ripple":
                amb = ripple_cogging_ambiguity(params, ja, extra[0], fixed, prob.block)
                if amb and amb not in prob.ambiguities:
                    prob.ambiguities.append(amb)
            if verbose:
                where = ", ".join([p.path for p in extra] + [f"{k}={v}" for k, v in fixed.items()])
                verbose(f"  try {name:<19} {where:<40} held-out S/n {Sh / nh:8.3f} "
                        f"(now {Sh_base / nh:.3f}), shrink {shrink:+.3f}{scanned}")
        if not results:
            break
        results.sort(key=lambda t: -t[0])
        drop, shrink, name, extra, fixed, key, cols = results[0]
        significant = drop > MIN_DROP and (shrink > MIN_SHRINK or (drop > STRONG_DROP * s2
                                                                 and s2 <= MODEL_LIMITED_S_N))
        if not significant:
            chain.append({"effect": name, "parameters": [p.path for p in extra] + list(fixed),
                          "held_out_shrink": shrink, "significant": False,
                          "remaining": Sh_base / nh})
            break
        tried_out.add(key)
        for k, v in fixed.items():
            set_value(prob.block, k, v)
        params.extend(extra)
        if isinstance(cols, tuple):       # a candidate screened by a refit: start from it
            for p, q in zip(params, cols[0]):
                p.value = q.value
            jac0 = cols[1]
        else:
            jac0 = np.hstack([jac, cols]) if cols is not None else None
        if name == "kt_saturation" and Sh_base / nh > MODEL_LIMITED_S_N:
            # the fit had compensated the missing saturation (a lower Kt, a higher η): refit
            # from the profile's values on velocity and current first (``angle_free_prefit``)
            angle_free_prefit(prob, params, jac, fit_fold, verbose=verbose)
            jac0 = None
        # a fresh Jacobian per iteration after the first: an added effect can move the others
        # far (the hidden cvt run's Kt saturation: S/n 4.76 -> 0.90 in 6 iterations on
        # Broyden's update alone, still falling)
        # up to REFIT_ITERATIONS; the fit's own stop ends it sooner near the minimum (a
        # saturation switched on from a stalled fit: S/n 6,000 -> 33 in 5 iterations, falling)
        res = last = fit(prob, params, iterations=REFIT_ITERATIONS, verbose=verbose, intervals=False, jac0=jac0)
        if update_events(prob, params, verbose=verbose) and res.get("jac") is not None:
            # an effect with contact (the backlash) brought samples S now leaves out: the
            # refit again on what is left, from its own Jacobian with those rows zeroed
            jm = res["jac"].copy()
            jm[prob.events] = 0.0
            res = last = fit(prob, params, iterations=REFIT_ITERATIONS, verbose=verbose, intervals=False,
                             jac0=jm)
        refitted = True
        chain.append({"effect": name, "parameters": [p.path for p in extra] + list(fixed),
                      "values": {k: v for k, v in written_values(params).items()
                                 if k in {p.path for p in extra}} | dict(fixed),
                      "held_out_shrink": shrink, "significant": True,
                      "remaining": res["S"] / res["n"]})
    u = np.array([p.value for p in params])
    if refitted:   # the refits inside the chain skip the intervals: once, at the end
        jac, r = _jacobian(prob, params, last["u"], last["r"]), last["r"]
        set_intervals(prob, params, jac, r)
    elif last is not None and last.get("jac") is not None and last["jac"].shape[1] == len(params) \
            and np.array_equal(last["u"], u):
        jac, r = last["jac"], last["r"]
    else:
        jac = None
    if jac is not None:
        r = settle(prob, params, jac, r, verbose=verbose)
    if jac is not None and any(p.profile for p in params):
        # the parameters whose local Jacobian is not to be trusted: their profile
        prob.profiles = apply_profiles(prob, params, jac, r, verbose=verbose)
    if jac is not None:
        correct_smoothing_shift(prob, params, verbose=verbose)
    return chain


def angle_free_prefit(prob: Problem, params: list[Param], jac: np.ndarray, fold: np.ndarray,
                      verbose=None) -> None:
    """Start of the chain's refit after a Kt saturation (the last of ``params``) is added to
    a fit far from the noise: a fit on velocity and current alone, from the profile's
    values with the saturation at the best of its scan from there (``scan_start``); the
    params take its values when it ends below the screen's start in the whole S.

    Why: a saturating drive clips at its current limit, and the angle integrates every
    clipped interval's speed error over the rest of the step (and the steps after it, at
    rest): far from the minimum S of the angles has other minima. On the alt cyclo run (3 A
    saturation, the input's current limit) the refit from the screen, and one from the
    profile's values, both stopped in one (in.Kt −6…−13 %, η +5…+12 %, S/n 1.18 where the
    hidden truth has 0.85); from the profile's values on velocity and current it reached
    in.Kt −0.6 %, η +0.5 %, the saturation +0.6 % (S/n 0.75 on every signal). Velocity
    and current errors do not accumulate: their S is local in time."""
    sat = params[-1]
    base = params[:-1]
    u_screen = np.array([p.value for p in params])
    r_screen = prob.residual_vector(with_params(prob.block, params, u_screen))
    sv = start_values(prob, base)
    trial = [copy.copy(p) for p in params]
    for q, v in zip(trial, sv):
        q.value = float(v)
    trial[-1].value = scan_start(prob, base, [sv], jac, fold, trial[-1])[0]
    angle_free = prob.signal_mask(exclude=("position_rad",))
    tr = fit(prob, trial, iterations=REFIT_ITERATIONS, mask=angle_free, intervals=False, verbose=verbose)
    if tr["r"] is None:
        return
    S_new = float(tr["r"] @ tr["r"])
    S_old = float(r_screen @ r_screen) if r_screen is not None else float("inf")
    if verbose:
        verbose(f"  angle-free refit of {sat.path} from the profile's values: S/n {S_new / len(tr['r']):.4f} "
                f"on every signal (the screen's start: {S_old / len(tr['r']):.4f})"
                + ("; kept" if S_new < S_old else "; not kept"))
    if S_new < S_old:
        for p, q in zip(params, trial):
            p.value = q.value


def _predicted_heldout(params, jac, r, fit_fold, held, own: list[int] | None = None) -> float:
    """Held-out S the linearised model predicts after the Gauss-Newton step fitted on the
    fit fold (no replay): ||r_h + J_h·δ||², δ = argmin ||r_f + J_f·δ||² (damped); with
    ``own`` (a candidate's columns) the better of that and the step in those alone, the two
    steps ``_gn_heldout`` replays: the prescreen gates those replays, so it judges the same
    steps (a full step that overshoots in the others must not drop the candidate before them)."""
    sc = np.array([p.scale for p in params])
    best = float("inf")
    for cols, lam in [(np.arange(len(params)), 1e-3)] + ([(np.asarray(own), 1e-6)] if own else []):
        J = jac[fit_fold][:, cols] * sc[cols]
        H = J.T @ J
        d = np.diag(H).copy()
        d[d <= 0] = 1.0
        delta = np.linalg.lstsq(H + lam * np.diag(d), -(J.T @ r[fit_fold]), rcond=1e-12)[0]
        lin = r[held] + (jac[held][:, cols] * sc[cols]) @ delta
        best = min(best, float(lin @ lin))
    return best


def scan_start(prob: Problem, params: list[Param], anchors: list[np.ndarray], jac: np.ndarray,
               fold: np.ndarray, extra: Param) -> tuple[float, list, int]:
    """Start of a nonlinear effect: the best of its ``scan`` grid, each value replayed
    once with the other parameters at an anchor (the current fit; also the starting block
    when the fit is far from the noise: a fit that compensated a missing saturation with a
    lower Kt is the wrong place to switch it on) and their effect projected out by their
    Jacobian ``jac`` (S with them linearised, on ``fold``). One replay per value and anchor.

    Returns (best value, [(value, S)], index of its anchor)."""
    sc = np.array([p.scale for p in params])
    J = jac[fold] * sc
    table = []
    for k, u in enumerate(anchors):
        for v in extra.scan:
            e = copy.copy(extra)
            e.value = float(v)
            rv = prob.residual_vector(with_params(prob.block, params + [e], np.r_[u, v]))
            if rv is None:
                continue
            table.append((float(v), _projected(J, rv[fold])[0], k))
    if not table:
        return extra.value, table, 0
    best = min(table, key=lambda t: t[1])
    return best[0], [t[:2] for t in table], best[2]


def backlash_scan(prob: Problem) -> tuple:
    """The gaps the backlash's scan tries (rad at the input shaft): log-spaced from two
    input encoder counts (a smaller gap is below what the angles resolve) to 0.2 rad
    (11°), 12 values."""
    cpr = get_value(prob.block, "motors.in.counts_per_rev") or 10000
    lo = 2 * 2 * math.pi / float(cpr)
    return tuple(np.geomspace(lo, 0.2, 12)) if lo < 0.2 else ()


def _gn_heldout(prob, params, u, jac, r, fit_fold, held, block, own: list[int] | None = None) -> float:
    """S on the held-out fold after one damped Gauss–Newton step fitted on the fit fold:
    the better of a step in every parameter and, for a candidate, a step in its own
    parameters only (a full step from a fit still far from the data can overshoot in the
    others and hide what the candidate alone explains); without a candidate, a full step
    at two dampings. Each is one replay."""
    sc = np.array([p.scale for p in params])
    J, rr = jac[fit_fold] * sc, r[fit_fold]
    best = float("inf")
    trials = [(None, 1e-3)] + ([(own, 1e-6)] if own else [(None, 1e-1)])
    for cols, lam in trials:
        idx = np.arange(len(params)) if cols is None else np.asarray(cols)
        Jc = J[:, idx]
        H = Jc.T @ Jc
        d = np.diag(H).copy()
        d[d <= 0] = 1.0
        try:
            sub = np.linalg.lstsq(H + lam * np.diag(d), -(Jc.T @ rr), rcond=1e-12)[0]
        except np.linalg.LinAlgError:
            continue
        step = np.zeros(len(params))
        step[idx] = sub
        step *= sc
        un = _clip(params, u + step)
        rn = prob.residual_vector(with_params(block, params, un))
        if rn is not None:
            best = min(best, float(rn[held] @ rn[held]))
    return best
