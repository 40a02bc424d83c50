"""The output-error fit: Levenberg-Marquardt on a forward-difference Jacobian with Broyden
steps (``fit``), and the 95 % intervals from the largest of three covariances (``set_intervals``)."""
from __future__ import annotations

import math

import numpy as np

from ...errors import ProfileError
from .params import Param, Z95, _clip, with_params
from .problem import BLOCK_S, Problem


INTERVAL_BLOCK_S = 0.5  # longest time block of the intervals' sandwich (a model's misfit is
#                         coloured over tenths of a second); the 0.1 s folds' blocks are the other
FD_REL = 0.005         # forward-difference step, fraction of the parameter's scale
# Parameters whose effect on the replay is small beside its numerical jitter (the drive's
# loop runs on encoder counts even in the smoothed replay: a tiny change flips count
# sequences) get a longer difference step, × this on FD_REL·scale. Measured on the hidden
# cyclo twin, correlation of the forward and backward difference columns at 0.5 % / 5 %:
# out.D −0.92 / −0.11 (+0.62 between 5 % and 20 %), in.D +0.07 / +0.97, in.current_lag_s
# +0.25 / +0.93, eta_mesh −0.38 / +0.80, ripple_amp −0.39 / +0.78, while Tc, J, drag and the
# gains are +0.8…+1.0 at 0.5 %. A noise-made column inflated JᵀJ: D stalled 27–82 % off
# with intervals of 3–6 % (the "D off 40–60 %" of the first version).
# ``fit``: Broyden (secant) steps after each fresh Jacobian, and the stop: an iteration that
# moved every parameter by less than this fraction of its 95 % half-width
SECANT_STEPS = 3
STOP_FRACTION = 0.1
# ... or gained less than this fraction of S: with n ~ 4·10⁵ residuals that is ~10 s², a step
# of ~3 white-noise σ, a fraction of the intervals (which the coloured residual widens 10-25x);
# the first version (1e-6) took 2-3 more fresh Jacobians (20 replays each) on a hidden cyclo
# run for S/n 1.2816 -> 1.2815
STOP_GAIN = 3e-5
# an iteration that gained less than this fraction of S is followed by one on Broyden's
# update of its Jacobian, not a fresh one (21-23 replays): near the minimum the Jacobian
# hardly changes; a fresh one is taken when the carried one fails, and before the fit stops
REFRESH_GAIN = 0.01
# S/n (in noise floors², 1 = noise only) above which the remaining gap is mostly structure:
# the intervals hold the noise and the smoothing's error, not a model wrong in structure
MODEL_LIMITED_S_N = 1.5


def _jacobian(prob: Problem, params: list[Param], u: np.ndarray, r0: np.ndarray, cols=None,
              fd: float = FD_REL) -> np.ndarray:
    """Forward-difference Jacobian of the smoothed residual at ``u`` (``r0`` = its residual
    there): one replay per column in ``cols`` (default all)."""
    cols = range(len(params)) if cols is None else cols
    jac = np.zeros((len(r0), len(params)))
    for i in cols:
        h = fd * params[i].scale * params[i].fd_factor
        uu = u.copy()
        uu[i] += h
        r = prob.residual_vector(with_params(prob.block, params, uu), smooth=True)
        if r is None:
            uu[i] -= 2 * h
            r = prob.residual_vector(with_params(prob.block, params, uu), smooth=True)
            h = -h
        jac[:, i] = 0.0 if r is None else (r - r0) / h
    return jac


def _broyden(jac: np.ndarray, sc: np.ndarray, step: np.ndarray, dr: np.ndarray) -> np.ndarray:
    """Broyden's rank-one update of the Jacobian after an accepted step (Broyden 1965,
    "A class of methods for solving nonlinear simultaneous equations", Math. Comp. 19):
    J += (Δr − J·Δu)·Δuᵀ/(Δuᵀ·Δu), in units of each parameter's scale (``sc``), so that
    the secant is not dominated by the parameters with the largest SI values."""
    js, ds = jac * sc, step / sc
    js = js + np.outer(dr - js @ ds, ds) / float(ds @ ds)
    return js / sc


def fit(prob: Problem, params: list[Param], *, iterations: int = 8, mask: np.ndarray | None = None,
        verbose=None, intervals: bool = True, jac0: np.ndarray | None = None,
        max_fresh: int | None = None) -> dict:
    """Levenberg–Marquardt from the params' values; updates them (value, interval).

    The forward-difference Jacobian costs one replay per parameter and is the whole cost
    of the fit, so each of the ``iterations`` (one fresh Jacobian each) is followed by up
    to ``SECANT_STEPS`` further steps on Broyden's rank-one update of it (``_broyden``,
    one replay each) while they keep gaining. The fit stops when an iteration moved no
    parameter by more than ``STOP_FRACTION`` of its current 95 % half-width 1.96·σ
    (``_covariances``, no replay): iterating on changes nothing the intervals can tell
    (the first version ran its 12 iterations to S/n changes in the 4th decimal).

    Returns {"S": final S, "n": residual count, "S0": starting S, "jac": a fresh
    Jacobian at the final values, "r": residuals, "u": values, "iterations"}. ``mask``
    restricts the residuals fitted (a fold); ``intervals=False`` skips the intervals and
    the final Jacobian (a screen's short refit, a refit inside the effect chain);
    ``jac0`` is a Jacobian near the start used for the first iteration instead of a
    fresh one (the screen's, when the chain adds the effect it screened); ``max_fresh``
    caps the fresh Jacobians (None: one per iteration): past it the iterations go on
    Broyden's update alone and the fit stops at the first step it cannot improve (the
    refits inside the effect chain, which start next to their minimum)."""
    u = np.array([p.value for p in params], float)
    r = prob.residual_vector(with_params(prob.block, params, u))
    if r is None:
        raise ProfileError("simulation: the starting block is not a valid plant")
    sel = np.ones(len(r), bool) if mask is None else mask
    S0 = S = float(r[sel] @ r[sel])
    sc = np.array([p.scale for p in params])
    lam = 1e-3
    fd = FD_REL
    jac, at_u, done, n_fresh, need_fresh = None, False, 0, 0, True
    carry = False     # the next iteration on the Broyden-updated Jacobian (REFRESH_GAIN)

    def step_from(jac, lam):
        # in units of each parameter's scale: H spans 1e-10..1e20 in SI and loses the step
        J = jac[sel] * sc
        H = J.T @ J
        d = np.diag(H).copy()
        d[d <= 0] = 1.0
        return np.linalg.lstsq(H + lam * np.diag(d), -(J.T @ r[sel]), rcond=1e-12)[0] * sc

    for it in range(iterations):
        if it == 0 and jac0 is not None and jac0.shape == (len(r), len(params)):
            jac, at_u = jac0, False
        elif jac is None or (need_fresh and (max_fresh is None or n_fresh < max_fresh)) \
                or (max_fresh is None and not carry):
            jac, at_u = _jacobian(prob, params, u, r, fd=fd), True
            n_fresh += 1
        fresh_now = at_u
        u_start, S_start = u.copy(), S
        improved, predicted = False, None
        for _ in range(5):
            try:
                un = _clip(params, u + step_from(jac, lam))
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            if predicted is None:   # the decrease of S the linear model promises
                lin = r[sel] + jac[sel] @ (un - u)
                predicted = S - float(lin @ lin)
            rn = prob.residual_vector(with_params(prob.block, params, un))
            if rn is not None and float(rn[sel] @ rn[sel]) < S:
                jac = _broyden(jac, sc, un - u, rn - r)
                u, r, S, improved, at_u = un, rn, float(rn[sel] @ rn[sel]), True, False
                lam = max(lam / 5, 1e-7)
                break
            lam *= 8
        gain = S_start - S
        for _ in range(SECANT_STEPS if improved else 0):
            # the secant steps: go on while each gains at least a quarter of the one before
            un = _clip(params, u + step_from(jac, lam))
            rn = prob.residual_vector(with_params(prob.block, params, un))
            if rn is None or S - float(rn[sel] @ rn[sel]) < 0.25 * gain:
                break
            jac = _broyden(jac, sc, un - u, rn - r)
            gain = S - float(rn[sel] @ rn[sel])
            u, r, S = un, rn, S - gain
        done = it + 1
        if verbose:
            verbose(f"  iteration {it + 1}: S/n = {S / sel.sum():.4f} (lambda {lam:.1e})")
        need_fresh = False
        if not improved and not fresh_now and (max_fresh is None or n_fresh < max_fresh):
            need_fresh = True   # the carried Jacobian failed: the next iteration takes a fresh one
            continue
        if not improved and fd > FD_REL / 50 and (predicted or 0.0) > 1e-4 * S and fresh_now \
                and (max_fresh is None or n_fresh < max_fresh):
            # a stall with the damping rising, where the Jacobian promised a real gain, is a
            # Jacobian that does not see the way down (the replay is not smooth at this step
            # size): retry once with finer differences. A stall with nothing promised is the
            # minimum.
            fd, lam = fd / 10, 1e-3
            continue
        if not improved:
            break
        covs = _covariances(prob, jac[sel] * sc, r[sel], sel)[0]
        half = Z95 * np.sqrt(np.maximum(np.max([np.diag(c) for c in covs], axis=0), 0.0)) * sc
        # the intervals tell nothing while the model is far from the data (S/n ≫ 1): there only
        # the gain stops it (a Kt saturation's refit on a hidden cyclo run stopped at S/n 603,
        # its misfit's intervals wider than the steps still to take)
        near = S / max(int(sel.sum()), 1) <= MODEL_LIMITED_S_N
        stop = (near and np.all(np.abs(u - u_start) <= STOP_FRACTION * half)) or (S_start - S) / S_start < STOP_GAIN
        if stop and not fresh_now and max_fresh is None:
            # a carried Jacobian's small step is no proof of the minimum: one fresh Jacobian first
            carry = False
            continue
        if stop:
            break
        carry = (S_start - S) / S_start < REFRESH_GAIN
    for p, v in zip(params, u):
        p.value = float(v)
    out = {"S": S, "S0": S0, "n": int(sel.sum()), "jac": jac, "r": r, "u": u, "iterations": done}
    if not intervals:
        return out
    if not at_u or fd != FD_REL:
        # the intervals' Jacobian fresh at the final values and at the steps whose columns are
        # known to be clean (FD_WEAK), not a stall's 10x finer retry. The first version took
        # the last iteration's, at the values before its step: on a clean run of the hidden
        # cyclo twin 14/22 within, drag +0.32 % for ±0.08 %, viscous drag −1.42 % for ±0.15 %;
        # a fresh fit with the fresh final Jacobian: +0.14 % ±0.15 %, −0.72 % ±1.06 %
        out["jac"] = jac = _jacobian(prob, params, u, r)
    set_intervals(prob, params, jac, r, sel)
    return out


def set_intervals(prob: Problem, params: list[Param], jac: np.ndarray, r: np.ndarray,
                  sel: np.ndarray | None = None) -> None:
    """The params' 95 % intervals (``_intervals``) at their values, from a fresh Jacobian
    ``jac`` and the smoothed residual ``r`` there; one replay (the exact one, for b)."""
    sel = np.ones(len(r), bool) if sel is None else sel
    r_exact = prob.residual_vector(with_params(prob.block, params), smooth=False)
    _intervals(prob, params, jac[sel], r[sel], None if r_exact is None else r_exact[sel], sel)


def _covariances(prob, Js, r, sel) -> tuple[list[np.ndarray], np.ndarray]:
    """(the three covariances of the estimate in units of the parameters' scales — white,
    block sandwich over ``BLOCK_S`` and over ``INTERVAL_BLOCK_S`` (module docstring) —,
    (JᵀJ)⁻¹) from the scaled Jacobian ``Js`` and the residual ``r`` on ``sel``."""
    H = Js.T @ Js
    Hi = np.linalg.pinv(H, rcond=1e-12)
    s2 = float(r @ r) / max(len(r) - Js.shape[1], 1)
    covs = [Hi * s2]
    for span in (BLOCK_S, INTERVAL_BLOCK_S):
        _, inv = np.unique(prob.blocks(span)[sel], return_inverse=True)
        G = np.zeros((inv.max() + 1, Js.shape[1]))
        np.add.at(G, inv, Js * r[:, None])
        covs.append(Hi @ (G.T @ G) @ Hi)
    return covs, Hi


def _intervals(prob, params, J, r, r_exact, sel) -> None:
    """95 % intervals: 1.96·σ + |b| (module docstring), set on each Param (``interval``,
    ``sigma``, ``model_bias``) in the block's SI values by the delta method."""
    sc = np.array([p.scale for p in params])
    Js = J * sc
    covs, Hi = _covariances(prob, Js, r, sel)
    covs = [c * np.outer(sc, sc) for c in covs]
    # b: the exact replay's residual minus the smoothed one, projected on the parameters
    bias = (-(Hi @ (Js.T @ (r_exact - r))) * sc) if r_exact is not None else np.zeros(len(params))
    kt_index = {p.path.split(".")[1]: i for i, p in enumerate(params) if p.path.endswith(".Kt")}
    for i, p in enumerate(params):
        grad = np.zeros(len(params))
        if p.transform.startswith("per_kt:") and p.transform[7:] in kt_index:
            k = kt_index[p.transform[7:]]
            grad[i], grad[k] = params[k].value, p.value
        elif p.transform.startswith("per_kt:"):
            grad[i] = p.kt0          # Kt held at the block's value
        elif p.transform == "invsq":
            # kt_sat_a = p^(-1/2): d/dp = -p^(-3/2)/2
            grad[i] = -0.5 * p.value ** -1.5 if p.value > 0 else 0.0
        else:
            grad[i] = 1.0
        p.sigma = float(math.sqrt(max(max(grad @ c @ grad for c in covs), 0.0) + p.jitter ** 2))
        p.model_bias = float(grad @ bias)
        if p.path == "ratio":
            # plus the angles' resolution, added linearly like the bias (``ratio_resolution``)
            p.resolution = abs(p.value) * prob.ratio_resolution()
        p.interval = p.half_width()


def _projected(J: np.ndarray, r: np.ndarray, lam: float = 1e-6) -> tuple[float, np.ndarray]:
    """(min over δ of ||r + J·δ||², δ): the residual with the columns of J fitted out
    (variable projection, Golub & Pereyra 1973), J scaled, lightly damped."""
    H = J.T @ J
    d = np.diag(H).copy()
    d[d <= 0] = 1.0
    delta = np.linalg.lstsq(H + lam * np.diag(d), -(J.T @ r), rcond=1e-12)[0]
    lin = r + J @ delta
    return float(lin @ lin), delta


def model_limited(s_per_n: float) -> str:
    """A note when the remaining gap is structure rather than noise (``MODEL_LIMITED_S_N``),
    else ""."""
    if s_per_n <= MODEL_LIMITED_S_N:
        return ""
    return (f"the remaining gap is not noise (S/n {s_per_n:.3g}, 1 = the noise floor): the model is not "
            f"the one that made the data, and the intervals (noise and smoothing only) understate the error")
