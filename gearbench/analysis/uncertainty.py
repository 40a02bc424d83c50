"""One convention for uncertainties (GUM, JCGM 100:2008), used by every result.

- Every result carries its **standard uncertainty** ``std`` (1 sigma) and its
  **degrees of freedom** ``dof``; both are computed and stored, never read back
  from an interval.
- Inputs combine to first order: u² = Σ (∂f/∂x_i · u_i)² (correlated inputs as a
  covariance block).
- ``dof`` is the Welch–Satterthwaite effective value ν = u⁴ / Σ (u_i⁴/ν_i); type B
  inputs (tolerances, model-error terms) count as known exactly (ν_i = ∞).
- Every interval is the **95 % coverage interval** value ± k·u with
  k = t₀.₉₇₅(ν) (Student-t; 1.96 only when ν is infinite).
- A tolerance read from a profile or a command line is converted to a standard
  uncertainty by its source: ``datasheet`` = limits ±a that the value lies within
  (rectangular distribution, u = a/√3, GUM 4.3.7); ``measured`` = the expanded
  uncertainty at 95 % of a measurement (calibration certificate, k = 2, u = a/2).
"""
from __future__ import annotations

import math

import numpy as np

from scipy import fft as sp_fft
from scipy import stats

COVERAGE = 0.95
DOF_MAX = 1e6                  # "infinite": JSON has no inf, and t(1e6) = 1.95997
TOLERANCE_SOURCES = {
    "datasheet": math.sqrt(3.0),   # ± limits, rectangular
    "measured": 2.0,               # expanded uncertainty, k = 2 (95 %)
}
BLOCK_CORRELATION_TIMES = 8.0   # window length / the residual's integrated correlation time
MIN_BLOCKS = 16


def coverage_factor(dof: float, level: float = COVERAGE) -> float:
    """k for a ``level`` coverage interval with ``dof`` degrees of freedom (Student-t).

    Parameters
    ----------
    dof : degrees of freedom (>= DOF_MAX: normal).
    level : coverage.

    Returns
    -------
    float

    References
    ----------
    JCGM 100:2008, "Evaluation of measurement data — Guide to the expression of uncertainty in measurement" (GUM), G.3

    Examples
    --------
    >>> round(coverage_factor(1e6), 2)
    1.96

    """
    dof = float(dof)
    if not dof >= 1.0:
        dof = 1.0
    if dof >= DOF_MAX:
        return float(stats.norm.ppf(0.5 + level / 2))
    return float(stats.t.ppf(0.5 + level / 2, dof))


def interval(value: float, std: float, dof: float, level: float = COVERAGE) -> tuple[float, float]:
    """The ``level`` coverage interval value ± k(dof)·std.

    Parameters
    ----------
    value, std, dof : estimate, standard uncertainty, degrees of freedom.
    level : coverage.

    Returns
    -------
    tuple of float

    References
    ----------
    JCGM 100:2008, "Evaluation of measurement data — Guide to the expression of uncertainty in measurement" (GUM), 6.2

    Examples
    --------
    >>> interval(1.0, 0.0, 10)
    (1.0, 1.0)

    """
    half = coverage_factor(dof, level) * std
    return float(value - half), float(value + half)


def effective_dof(variances, dofs) -> float:
    """Welch–Satterthwaite: ν = (Σ v_i)² / Σ (v_i²/ν_i) over the contributions' variances
    v_i; a contribution with ν_i = inf (or ≥ DOF_MAX) is known exactly. Capped at DOF_MAX.

    Parameters
    ----------
    variances, dofs : each contribution's variance and degrees of freedom.

    Returns
    -------
    float

    References
    ----------
    JCGM 100:2008, "Evaluation of measurement data — Guide to the expression of uncertainty in measurement" (GUM), G.4 (Welch-Satterthwaite)

    Examples
    --------
    >>> effective_dof([1.0], [5])
    5.0

    """
    total = 0.0
    denom = 0.0
    for v, nu in zip(variances, dofs):
        v = float(v)
        total += v
        if v > 0 and nu < DOF_MAX:
            denom += v * v / max(float(nu), 1.0)
    if denom <= 0:
        return DOF_MAX
    return float(min(total * total / denom, DOF_MAX))


def tolerance_std(tolerance: float, source: str) -> float:
    """Standard uncertainty of a value known to ± ``tolerance`` from ``source``
    (``datasheet``: limits, u = a/√3; ``measured``: 95 % expanded uncertainty, u = a/2).

    Parameters
    ----------
    tolerance : the ± value.
    source : ``datasheet`` or ``measured``.

    Returns
    -------
    float

    References
    ----------
    JCGM 100:2008, "Evaluation of measurement data — Guide to the expression of uncertainty in measurement" (GUM), 4.3.7

    Examples
    --------
    >>> tolerance_std(2.0, "measured")
    1.0

    """
    try:
        return float(tolerance) / TOLERANCE_SOURCES[source]
    except KeyError:
        raise ValueError(f"tolerance source must be one of {', '.join(TOLERANCE_SOURCES)}, "
                         f"got {source!r}") from None


def coverage_acceptance(trials: int, level: float = COVERAGE, alpha: float = 2e-3) -> tuple[int, int]:
    """Two-sided binomial acceptance range for the number of intervals (out of ``trials``
    independent ones) that hold the truth when their true coverage is ``level``: a count
    outside [low, high] has probability <= ``alpha`` (half on each side). Intervals too
    wide fall above it, too narrow below it.

    Parameters
    ----------
    trials : independent intervals.
    level : their nominal coverage.
    alpha : two-sided risk.

    Returns
    -------
    tuple of int
        (low, high) counts.

    References
    ----------
    JCGM 100:2008, "Evaluation of measurement data — Guide to the expression of uncertainty in measurement" (GUM)

    Examples
    --------
    >>> low, high = coverage_acceptance(100); low < 95 < high
    True

    """
    low = int(stats.binom.ppf(alpha / 2, trials, level))
    high = int(stats.binom.isf(alpha / 2, trials, level))
    return low, high


def design_effect(hits: np.ndarray, trials: np.ndarray) -> float:
    """Kish design effect of a coverage count whose intervals come in clusters (e.g. the
    efficiency points of one plant share its calibration, so they hold or miss the truth
    together): the cluster-robust variance of the pooled proportion over the binomial one.

    deff = Var_cluster(p̂) / (p̂ (1 − p̂) / N),  Var_cluster(p̂) = Σ_c (h_c − p̂ m_c)² / N²

    with h_c hits of m_c intervals in cluster c, N = Σ m_c (clusters of one give exactly 1). Independent intervals
    give deff ≈ 1; dividing the trials by deff gives the effective number of independent
    intervals for :func:`coverage_acceptance`. Never below 1 (a clustered count is never
    better determined than independent trials); 1 when every interval holds or none does.

    Parameters
    ----------
    hits : intervals holding the truth, per cluster.
    trials : intervals, per cluster.

    Returns
    -------
    float
        The design effect, ≥ 1.

    References
    ----------
    L. Kish, *Survey Sampling*, Wiley 1965, sec. 5.4 (design effect of cluster samples).

    Examples
    --------
    >>> design_effect(np.array([4, 4, 0, 4]), np.array([4, 4, 4, 4])) > 3
    True
    >>> design_effect(np.array([1, 1, 0, 1]), np.array([1, 1, 1, 1]))
    1.0

    """
    hits, trials = np.asarray(hits, float), np.asarray(trials, float)
    n = trials.sum()
    p = hits.sum() / n
    if len(trials) < 2 or p <= 0.0 or p >= 1.0:
        return 1.0
    var_cluster = np.sum((hits - p * trials) ** 2) / n**2
    return max(1.0, float(var_cluster / (p * (1 - p) / n)))


def covariance_block(residual: np.ndarray, filter_taps: int) -> int:
    """Window length (samples) of the overlapping block covariance: twice the FIR's length
    (a filtered white residual is correlated over less), or ``BLOCK_CORRELATION_TIMES``
    x the residual's integrated autocorrelation time τ = 1 + 2 Σ ρ_k (summed while
    ρ_k > 0) where model error correlates it for longer, capped at n / ``MIN_BLOCKS``.

    Parameters
    ----------
    residual : the fit's residual.
    filter_taps : length of the FIR applied to the signals.

    Returns
    -------
    int

    References
    ----------
    W. K. Newey and K. D. West, "A simple, positive semi-definite, heteroskedasticity and autocorrelation consistent covariance matrix", Econometrica 55(3), 1987, pp. 703-708; A. Sokal, "Monte Carlo methods in statistical mechanics", 1997 (integrated autocorrelation time)

    Examples
    --------
    >>> import numpy as np
    >>> covariance_block(np.random.default_rng(0).normal(size=6400), 11)
    22
    """
    n = len(residual)
    # the correlation time from at most 2^16 samples (a long run's is the same)
    e = np.asarray(residual[:1 << 16], float)
    e = e - np.mean(e)
    base = 2 * int(filter_taps)
    if len(e) < 4 or not np.any(e):
        return base
    m = sp_fft.next_fast_len(2 * len(e), real=True)
    f = sp_fft.rfft(e, m)
    acf = sp_fft.irfft(f * np.conj(f), m)[:len(e)]
    acf = acf / acf[0]
    neg = np.nonzero(acf[1:] <= 0)[0]
    stop = int(neg[0]) + 1 if len(neg) else len(e)
    tau = 1.0 + 2.0 * float(np.sum(acf[1:stop]))
    return int(min(max(base, BLOCK_CORRELATION_TIMES * tau), max(n // MIN_BLOCKS, base)))


def block_covariance(Xt: np.ndarray, e: np.ndarray, A: np.ndarray, *, block: int,
                      Z: np.ndarray | None = None):
    """Sandwich covariance A⁻¹ Ω A⁻ᵀ, Ω from overlapping block sums of the scores
    s_t = z_t e_t (z = x for least squares, the instruments for IV; A = X'X or Z'X):
    Ω = n/(n−L+1) · n/(n−L) · (1/L) Σ_t S_t S_tᵀ, S_t = Σ_{i=t}^{t+L−1} s_i, every window of
    L = ``block`` samples (overlapping batch means, a Bartlett-kernel HAC estimate:
    honest for residuals correlated over less than L samples). n/(n−L) is Meketon and
    Schmeiser's normalisation for a mean estimated from the same data (the scores of a
    fit sum to zero): without it Ω is low by the factor 1 − L/n (a run's b2 spread over
    24-30 noise draws against its mean σ: 250 Hz, L/n ≈ 0.18, 1.11/1.18 → 1.02/1.08 with
    it; 1 kHz, eight runs of four motors, median 1.13 → 1.06). Overlapping windows use
    the data ~1.5x better than disjoint blocks: with disjoint blocks of 4 filter lengths
    a 3 s run had 5 blocks, 4 degrees of freedom and a standard uncertainty that was
    itself uncertain by ±35 %. Degrees of freedom ν = 1.5 (n/L − 1) (Meketon & Schmeiser
    1984) for the t quantile. Also returns an effective sample count.

    References: W. K. Newey and K. D. West, Econometrica 55(3), 1987; M. S. Meketon and
    B. Schmeiser, "Overlapping batch means", Proc. Winter Simulation Conf. 1984."""
    W = Xt if Z is None else Z
    k, n = W.shape
    L = int(min(max(block, 1), max(n // 2, 1)))
    scores = W * e[None, :]
    c = np.zeros((k, n + 1))
    np.cumsum(scores, axis=1, out=c[:, 1:])
    # every window starting a step apart (L/8: as good as all of them, 8x cheaper)
    step = max(1, L // 8)
    S = c[:, L::step] - c[:, :n + 1 - L:step]         # window sums
    omega = (S @ S.T) / L * n / S.shape[1] * n / (n - L)      # Meketon-Schmeiser normalisation
    Ainv = np.linalg.inv(A)
    cov = Ainv @ omega @ Ainv.T
    # Effective n: how many white samples would give the same first-parameter variance.
    white = float(e @ e) / max(n - k, 1) * (Ainv @ (W @ W.T) @ Ainv.T)[0, 0]
    n_eff = float(n * white / cov[0, 0]) if cov[0, 0] > 0 else float(n)
    dof = max(int(1.5 * (n / L - 1.0)), 1)
    return cov, dof, min(n_eff, float(n))
