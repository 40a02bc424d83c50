"""Cogging harmonics: the orders screened from the rotor angle (``cogging_order_scores``)
and kept by their Wald test at the BIC price (``_select_cogging``)."""
from __future__ import annotations


import numpy as np

from ..uncertainty import block_covariance
from .solve import _fit, _harmonic_columns


MAX_COGGING_ORDER = 64       # cogging periods per revolution scanned
COGGING_CANDIDATES = 4       # orders tried in the regression after the screen
COGGING_SCREEN = 8.0         # screen: score > 8x the median score (white noise: 1/256 per order)
MIN_SCREEN_ORDERS = 8        # visible orders needed for the median to mean anything
# Cogging shows only near reversals, a few dozen events per run, so the block covariance
# under-states its pair's variance and W of a spurious order reaches tens. Floor chosen on
# robustness seed 0 (spurious W <= 40, real >= 89, 0.6 mN m), checked on seed 2 (<= 21, >= 96).
COGGING_MIN_WALD = 80.0


def _select_cogging(sig, cols, form, fit, cogging, rad_per_unit, lag, eiv, block):
    """Cogging orders: screened on the residual (``cogging_order_scores``), kept when the
    pair's Wald statistic beats the BIC price 2 ln n_eff and ``COGGING_MIN_WALD``
    (backward elimination: the weakest order dropped and the rest refitted, one at a
    time). Returns (fit, orders)."""
    if cogging is False or cogging is None or rad_per_unit is None:
        return fit, ()
    ang = sig.th * rad_per_unit                     # motor angle, rad: orders per revolution
    if cogging is True:
        scores = cogging_order_scores(ang[sig.at], sig.w_smooth[sig.at] * rad_per_unit,
                                      fit.residual, cutoff_hz=sig.cutoff_hz)
        orders = cogging_candidates(scores)
    else:
        orders = tuple(int(k) for k in cogging)
    n_base = len(cols)
    base_fit = fit
    while orders:
        fit = _fit(sig, cols + _harmonic_columns(sig, "cog", ang, orders, form), form,
                   lag=lag, eiv=eiv)
        if cogging is not True:
            return fit, orders
        cov, _, n_eff = block_covariance(fit.Xt, fit.residual, fit.A, block=block, Z=fit.Z)
        wald = []
        for j in range(len(orders)):
            sl = slice(n_base + 2 * j, n_base + 2 * j + 2)
            try:
                wald.append(float(fit.beta[sl] @ np.linalg.solve(cov[sl, sl], fit.beta[sl])))
            except np.linalg.LinAlgError:
                wald.append(0.0)
        price = max(2.0 * np.log(max(n_eff, 2.0)), COGGING_MIN_WALD)
        if min(wald) > price:
            return fit, orders
        # backward elimination, the weakest order first: neighbouring orders of a run
        # over few revolutions are nearly collinear, and dropping every order short of
        # the price at once dropped the true one with them (seed 7 case 61's loaded
        # output motor: orders 19-22 screened, each pair's Wald < 80 jointly, order 21
        # alone 1148; without it b2 +1.57 %, with it +0.15 %)
        orders = tuple(k for j, k in enumerate(orders) if j != int(np.argmin(wald)))
    return base_fit, ()


def cogging_order_scores(position_rad: np.ndarray, velocity_rad_s: np.ndarray,
                         residual: np.ndarray, *, cutoff_hz: float,
                         max_order: int = MAX_COGGING_ORDER, bins: int = 2048) -> np.ndarray:
    """Screen of cogging orders on the rotor angle: for k = 1…``max_order``

        z_k = |Σ_t e_t exp(−i k θ_t)|² / Σ_t e_t²   over samples with k·|ω_t| < 2π f_c,

    the angle-domain periodogram of the residual e, restricted to the samples where the
    low-pass (cutoff f_c) lets order k through (elsewhere the filtered cogging is zero
    and those samples only add noise); NaN for an order no sample can show. White
    residual: E z_k = 1. O(n) in one pass: per speed class (limits 2π f_c/2^j) a
    histogram of e over ``bins`` angle bins, then one FFT per class.
    Returns ``z`` (index k − 1).

    Parameters
    ----------
    position_rad, velocity_rad_s : rotor angle and speed under the residual's samples.
    residual : the base fit's residual.
    cutoff_hz : the fit's low-pass cutoff.
    max_order, bins : orders screened; angle bins of the histogram.

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md); cogging as a periodic rotor-angle torque

    Examples
    --------
    >>> z = cogging_order_scores(th, w, e, cutoff_hz=40.0)   # doctest: +SKIP

    """
    th = np.asarray(position_rad, float)
    e = np.asarray(residual, float)
    speed = np.abs(np.asarray(velocity_rad_s, float))
    nclass = int(np.ceil(np.log2(max_order))) + 1
    # class j: 2π fc / 2^(j+1) <= |ω| < 2π fc / 2^j  (last class: everything slower)
    with np.errstate(divide="ignore"):
        level = np.floor(np.log2(2 * np.pi * cutoff_hz / np.maximum(speed, 1e-12)))
    ok = level >= 0
    cls = np.minimum(level[ok], nclass - 1).astype(np.int64)
    b = (np.mod(th[ok], 2 * np.pi) * (bins / (2 * np.pi))).astype(np.int64) % bins
    eo = e[ok]
    S = np.bincount(cls * bins + b, eo, minlength=nclass * bins).reshape(nclass, bins)
    E2 = np.bincount(cls, eo * eo, minlength=nclass)
    # order k needs |ω| < 2π fc / k: classes j >= ceil(log2 k); sum them from the slow end
    S = np.cumsum(S[::-1], axis=0)[::-1]
    E2 = np.cumsum(E2[::-1])[::-1]
    F = np.fft.rfft(S, axis=1)
    orders = np.arange(1, max_order + 1)
    j = np.ceil(np.log2(orders)).astype(int)
    power = np.abs(F[j, orders]) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(E2[j] > 0, power / E2[j], np.nan)


def cogging_candidates(scores: np.ndarray) -> tuple[int, ...]:
    """Orders worth a regression test: at most ``COGGING_CANDIDATES`` whose score beats
    ``COGGING_SCREEN`` x the median score of the orders the run can show. The median
    calibrates out the residual's colour; with fewer than ``MIN_SCREEN_ORDERS`` visible
    orders (a fast run: the filter hides all but the lowest) there is nothing to
    compare with and no cogging can bias the fit, so none are tried.

    Parameters
    ----------
    scores : ``cogging_order_scores`` output.

    Returns
    -------
    tuple of int
        Orders to test in the regression (at most ``COGGING_CANDIDATES``).

    References
    ----------
    T. Yukawa et al., "Estimation of gear efficiency in reduction gears", Iwate University (the reference paper; shared/reference/PAPER-NOTES.md)

    Examples
    --------
    >>> import numpy as np
    >>> s = np.ones(64); s[5] = 100.0
    >>> cogging_candidates(s)
    (6,)

    """
    visible = np.isfinite(scores)
    if visible.sum() < MIN_SCREEN_ORDERS:
        return ()
    screen = COGGING_SCREEN * float(np.median(scores[visible]))
    z = np.where(visible, scores, -np.inf)
    ranked = np.argsort(z)[::-1][:COGGING_CANDIDATES]
    return tuple(int(k) + 1 for k in ranked if z[k] > screen)
