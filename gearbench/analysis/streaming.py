"""Estimates updated while acquiring, for measurements that stop once they are known.

Pure functions and small accumulators, no I/O; the sequencer feeds them the samples
recorded so far every few hundred milliseconds. They decide *when to stop*; the
reported results still come from the full analysis of the recorded run
(``calibration``, ``efficiency``).

``StreamingB2``  one calibration run's b2 = Kt/J and its standard error from per-block
                 sufficient statistics: each new block of filtered samples adds its
                 Gram matrix G_b = X_b X_bᵀ and X_b y_b; the estimate is β = (ΣG_b)⁻¹ Σ X_b y_b
                 and its covariance the block sandwich (ΣG)⁻¹ Σ S_b S_bᵀ (ΣG)⁻¹ with
                 S_b = X_b y_b − G_b β — the same form as ``uncertainty.block_covariance``,
                 so no sample is ever re-filtered. The regression is the default method's
                 base model (current, speed, Coulomb sign through the same FIR and
                 second-difference match); cogging, current lag and the errors-in-variables
                 correction are left out: they move b2 by fractions of its error but not
                 its variance much, and an unmodelled term only makes the residual, and so
                 the interval, larger (the stop comes later, never earlier).
``LevelMean``    a steady level's tapered mean with its settling found in the data
                 (``LevelMean.settle_chunk``), the white-noise standard error of the
                 settled mean (from per-chunk second differences) and a steadiness check.
``kt_share``     how much of Kt's relative error one run's b2 error makes (eq. 17).
``slope_fit``    weighted straight line through level means (eq. 18 as a slope).
``slope_dof``    the degrees of freedom of that slope's standard error (Welch–Satterthwaite).
"""
from __future__ import annotations

import numpy as np

from . import derivatives as dv
from .uncertainty import effective_dof
from .windows import taper

Z95 = 1.959963984540054
BLOCK_FILTER_LENGTHS = 2     # a block spans two FIR lengths: residuals correlate over about one
MIN_BLOCKS = 4               # fewer blocks: the spread of their scores says nothing yet
SETTLE_MARGIN = 2            # the window starts at twice the point found steady
MIN_SETTLED_CHUNKS = 8       # settled chunks before a level may stop
SPEED_TOLERANCE = 0.01       # a settled level's mean input speed within 1 % of its command
STEADY_SIGMAS = 2.0          # the settled window's halves must agree within 2 sigma
TAPER_VARIANCE = 1.22        # white-noise variance factor of the Tukey-tapered mean (efficiency.taper)


class StreamingB2:
    """b2 = Kt/J of one run from the samples acquired so far (module docstring)."""

    def __init__(self, dt_s: float, *, cutoff_hz: float | None = None):
        rate = 1.0 / dt_s
        self.dt_s = dt_s
        self.taps = dv.lowpass_fir(cutoff_hz or min(40.0, rate / 10.0), rate)
        self.block = BLOCK_FILTER_LENGTHS * len(self.taps)
        self._next = 0               # first raw sample of the next block
        self._G: list[np.ndarray] = []
        self._c: list[np.ndarray] = []

    def update(self, position_rad: np.ndarray, current_a: np.ndarray, n: int) -> None:
        """Take every complete block within the first ``n`` samples of the run's arrays."""
        span = self.block + len(self.taps) + 1      # raw samples behind one block of outputs
        while self._next + span <= n:
            a = self._next
            th = np.asarray(position_rad[a:a + span], float)
            i = np.asarray(current_a[a:a + span], float)
            sign = np.sign(dv.smooth_velocity(th - th[0], self.dt_s))
            f = dv.consistent_derivatives(th, {"current": i, "sign": sign}, self.dt_s, self.taps)
            # the current-loop lag column i' (as ``identify`` fits it): left out, a 0.5 ms lag
            # leaves a residual that inflates the interval several times
            X = np.vstack([f["current"], f["velocity"], f["sign"], np.gradient(f["current"], self.dt_s)])
            y = f["acceleration"]
            self._G.append(X @ X.T)
            self._c.append(X @ y)
            self._next += self.block

    @property
    def blocks(self) -> int:
        return len(self._G)

    def estimate(self) -> tuple[float, float, int] | None:
        """(b2, its standard error, degrees of freedom) or None before ``MIN_BLOCKS``."""
        nb = len(self._G)
        if nb < MIN_BLOCKS:
            return None
        G = np.sum(self._G, axis=0)
        c = np.sum(self._c, axis=0)
        d = np.sqrt(np.diag(G))
        if np.any(d == 0):
            return None
        # solve on the column-normalised Gram matrix: a constant sign column (one rotation
        # direction) is then just an intercept, and a dead column does not blow up
        Gn = G / np.outer(d, d)
        try:
            Ginv = np.linalg.pinv(Gn, rcond=1e-10) / np.outer(d, d)
        except np.linalg.LinAlgError:
            return None
        beta = Ginv @ c
        S = np.array([cb - Gb @ beta for Gb, cb in zip(self._G, self._c)])
        omega = S.T @ S * nb / (nb - 1)
        cov = Ginv @ omega @ Ginv
        return float(beta[0]), float(np.sqrt(max(cov[0, 0], 0.0))), nb - 1


def kt_share_unloaded(b2_unloaded: float, kt_guess: float, disk_kgm2: float) -> float:
    """∂ln Kt/∂ln b2~ in magnitude: J/j = Kt/(b2~ j) (eq. 17; Kt's guess is enough here)."""
    return abs(kt_guess / (b2_unloaded * disk_kgm2))


def kt_share_loaded(b2_unloaded: float, b2_loaded: float) -> float:
    """∂ln Kt/∂ln b2^ in magnitude: (J + j)/j = b2~/(b2~ − b2^) (eq. 17)."""
    diff = b2_unloaded - b2_loaded
    return abs(b2_unloaded / diff) if diff > 0 else float("inf")


class LevelMean:
    """One steady level of the input and output currents, accumulated chunk by chunk.

    Per chunk (``add_chunk``) it keeps the chunk's samples and the sum of squared second
    differences of each current (for
    the white-noise level: var(Δ²x) = 6σ² for white noise, while a smooth ripple or
    drift barely shows in a second difference). ``stats`` gives the Tukey-tapered mean
    of the settled samples (as the final analysis weights a window, ``efficiency.taper``)
    with the standard error white noise leaves in it, σ·√(1.22/n), and a check that the
    settled window is steady: the tapered means of its two halves agree within noise.
    A periodic ripple (CVT pulsation, cogging of either shaft) leaves almost nothing in a
    tapered mean once the window holds a few of its periods; until then the halves
    disagree and the level goes on.
    """

    def __init__(self, settle_floor_chunks: int = 0, margin: float = SETTLE_MARGIN,
                 speed_rad_s: float | None = None, dt_s: float = 1e-3):
        self.margin = margin
        # the commanded input speed: a level counts as settled only where the measured
        # speed is back at it (a slow speed loop sags for long after a braking step, and
        # the efficiency belongs to the commanded operating point)
        self.speed = speed_rad_s
        self.travel: list[float] = []       # input angle travelled per chunk (rad)
        self.dt_s = dt_s
        self.n: list[int] = []
        self.d2_in: list[float] = []
        self.d2_out: list[float] = []
        self.raw_in: list[np.ndarray] = []
        self.raw_out: list[np.ndarray] = []
        # never settled earlier than this (what an earlier level of the same drive needed):
        # on a short window the halves test is weak against a slow loop's tail
        self._settled_at = settle_floor_chunks

    def add_chunk(self, current_in_a: np.ndarray, current_out_a: np.ndarray, travel_rad: float = 0.0) -> None:
        xi, xo = np.asarray(current_in_a, float).copy(), np.asarray(current_out_a, float).copy()
        self.travel.append(float(travel_rad))
        self.n.append(len(xi))
        self.d2_in.append(float(np.sum(np.diff(xi, 2) ** 2)))
        self.d2_out.append(float(np.sum(np.diff(xo, 2) ** 2)))
        self.raw_in.append(xi)
        self.raw_out.append(xo)

    def settle_chunk(self) -> int:
        """Where the level has settled: the first chunk j (searched from the last answer
        on, every other chunk) such that the samples from j on are steady — the
        Tukey-tapered means of their two halves agree within ``STEADY_SIGMAS`` of white
        noise (``_steady``). A transient (the speed loop recovering from the load step,
        slow on a low-bandwidth drive) makes the early half differ, however long it
        lasts; no fixed settle time and no drive model are needed."""
        k = len(self.n)
        j = self._settled_at
        while k - j >= MIN_SETTLED_CHUNKS:
            if self._steady(j):
                self._settled_at = j
                return j
            j += 2
        return k

    def _sigma(self, j: int) -> tuple[float, float]:
        cnt = max(sum(self.n[j:]) - 2 * (len(self.n) - j), 1)
        return (float(np.sqrt(sum(self.d2_in[j:]) / (6.0 * cnt))),
                float(np.sqrt(sum(self.d2_out[j:]) / (6.0 * cnt))))

    def _speed_ok(self, j: int) -> bool:
        """The mean input speed from chunk j on within ``SPEED_TOLERANCE`` of the command."""
        if not self.speed:
            return True
        w = sum(self.travel[j:]) / (sum(self.n[j:]) * self.dt_s)
        return abs(w - self.speed) <= SPEED_TOLERANCE * abs(self.speed)

    def _steady(self, j: int) -> bool:
        if not self._speed_ok(j):
            return False
        xi = np.concatenate(self.raw_in[j:])
        h = len(xi) // 2
        # the halves' noise from the window's own batch means (coloured: a speed loop's
        # response to cogging and ripple is several times what white noise would leave),
        # by successive differences so a decaying tail does not pass for noise
        half_se = _long_run_sigma(xi) * np.sqrt(TAPER_VARIANCE / max(h, 1))
        return abs(_tapered_mean(xi[:h]) - _tapered_mean(xi[h:])) <= STEADY_SIGMAS * np.sqrt(2.0) * half_se

    def stats(self) -> dict | None:
        """Settled tapered means, their white-noise standard errors and the number of
        settled samples, or None while the level has not settled over at least
        ``MIN_SETTLED_CHUNKS`` chunks."""
        # the steadiness test finds where a decaying tail drops below the noise of the
        # halves; as long again lets it decay as far once more (a speed loop's recovery
        # is close to exponential), so what is left of it in the mean is below the noise
        steady = self.settle_chunk()
        j = int(round(self.margin * steady))
        if len(self.n) - j < MIN_SETTLED_CHUNKS:
            return None
        xi, xo = np.concatenate(self.raw_in[j:]), np.concatenate(self.raw_out[j:])
        return {"settle_chunk": j, "steady_chunk": steady, "samples": len(xi), "steady": True,
                **window_stats(xi, xo)}


def tapered_mean_sem(x: np.ndarray, blocks: int = 10) -> tuple[float, float, float]:
    """Tukey-weighted mean (see ``taper``), its standard error and that error's degrees
    of freedom: the block-means standard error of the flat mean (robust to coloured
    noise, blocks − 1 dof) times the taper's white-noise variance factor. The final
    analysis's window means (``efficiency.measure_windows``) and the adaptive levels'
    stopping both use it."""
    w = taper(len(x))
    m = float(w @ x / w.sum())
    inflate = np.sqrt(len(x) * float(w @ w)) / float(w.sum())
    bm = _block_means(x, blocks)
    if bm is None:
        return (m, inflate * float(np.std(x) / np.sqrt(max(len(x) - 1, 1))),
                float(max(len(x) - 1, 1)))
    return m, inflate * float(np.std(bm, ddof=1) / np.sqrt(len(bm))), float(len(bm) - 1)


def _block_means(x: np.ndarray, blocks: int) -> np.ndarray | None:
    """Means of ``blocks`` equal consecutive blocks of ``x`` (at least 10 samples each;
    the tail that does not fill a block is left out), or None when fewer than 3 fit."""
    nb = min(blocks, len(x) // 10)
    if nb < 3:
        return None
    size = len(x) // nb
    return x[: nb * size].reshape(nb, size).mean(axis=1)


def window_stats(current_in_a: np.ndarray, current_out_a: np.ndarray) -> dict:
    """Tapered means of a level's settled window with the standard errors and degrees of
    freedom the final analysis gives them (``tapered_mean_sem``: block means, robust to
    coloured noise), so a level stops on the interval its result will carry."""
    mi, si, di = tapered_mean_sem(np.asarray(current_in_a, float))
    mo, so, do = tapered_mean_sem(np.asarray(current_out_a, float))
    return {"mean_in": mi, "mean_out": mo, "sem_in": si, "sem_out": so, "dof": min(di, do)}


def _long_run_sigma(x: np.ndarray, blocks: int = 10) -> float:
    """Per-sample noise level that the mean of ``x`` sees: √(block length) times the spread
    of ``blocks`` block means from the median of their successive differences (von Neumann,
    made robust), so coloured noise counts as it acts on a mean while a slow trend or a
    transient's first block barely does; the white-noise level from second differences
    when the window is too short for blocks."""
    bm = _block_means(x, blocks)
    if bm is None:
        return float(np.sqrt(np.mean(np.diff(x, 2) ** 2) / 6.0)) if len(x) > 2 else 0.0
    size = len(x) // len(bm)
    # median absolute successive difference (normal: 0.6745·√2·σ): the one step a
    # transient's first block makes does not pass for noise
    return float(np.median(np.abs(np.diff(bm))) / (0.6745 * np.sqrt(2.0)) * np.sqrt(size))


def _tapered_mean(x: np.ndarray) -> float:
    w = taper(len(x))
    return float(w @ x / w.sum())


def slope_fit(x: np.ndarray, y: np.ndarray, sem_y: np.ndarray, sem_x: np.ndarray | None = None):
    """Weighted straight line y = a + b x through level means with known standard errors.

    The x errors enter through the slope (effective variance σ² = σ_y² + b² σ_x², two
    passes): the staircase's input current on output current, whose slope is eq. 18's
    incremental efficiency.

    Parameters
    ----------
    x, y : ndarray
        Level means (A).
    sem_y : ndarray
        Standard errors of ``y``.
    sem_x : ndarray, optional
        Standard errors of ``x`` (default 0).

    Returns
    -------
    a, b, sem_b : float
        Intercept, slope, and the slope's standard error (NaN, NaN, inf when x does not vary).

    References
    ----------
    J. R. Taylor, *An Introduction to Error Analysis*, 2nd ed., sec. 8.4 (errors in
    both variables, effective variance); T. Yukawa et al., "Estimation of gear
    efficiency in reduction gears", eq. 18.

    Examples
    --------
    >>> import numpy as np
    >>> a, b, sb = slope_fit(np.array([0., 1, 2, 3]), np.array([1., 3, 5, 7]), np.full(4, 0.1))
    >>> round(a, 6), round(b, 6)
    (1.0, 2.0)
    """
    x, y, sy = (np.asarray(v, float) for v in (x, y, sem_y))
    sx = np.zeros_like(x) if sem_x is None else np.asarray(sem_x, float)
    b = 0.0
    for _ in range(2):
        w = 1.0 / np.maximum(sy ** 2 + (b * sx) ** 2, 1e-300)
        xm, ym = float(w @ x / w.sum()), float(w @ y / w.sum())
        sxx = float(w @ (x - xm) ** 2)
        if sxx <= 0:
            return float("nan"), float("nan"), float("inf")
        b = float(w @ ((x - xm) * (y - ym)) / sxx)
    return ym - b * xm, b, float(np.sqrt(1.0 / sxx))


def slope_dof(x: np.ndarray, sem: np.ndarray, dof) -> float:
    """Degrees of freedom of a weighted slope's standard error (``slope_fit``) whose level
    means carry errors ``sem`` known to ``dof`` each: Welch–Satterthwaite over the levels'
    shares of Var(b), w_k·d_k²/Sxx² with w_k = 1/σ_k² and d_k = x_k − x̄_w — not the
    smallest level's dof, which ignores that the slope pools them.

    Parameters
    ----------
    x, sem, dof : array_like
        The levels' x (output current means), their (effective) standard errors and
        those errors' degrees of freedom.

    Returns
    -------
    float

    References
    ----------
    B. L. Welch (1947), F. E. Satterthwaite (1946); JCGM 100:2008 (GUM) G.4.

    Examples
    --------
    >>> import numpy as np
    >>> round(slope_dof(np.array([0., 1, 2, 3]), np.full(4, 0.1), np.full(4, 4.0)), 1)
    9.8
    """
    x, sem = np.asarray(x, float), np.asarray(sem, float)
    w = 1.0 / np.maximum(sem ** 2, 1e-300)
    d = x - float(w @ x) / float(w.sum())
    return effective_dof(list(w * d * d), list(np.asarray(dof, float)))


def slope_target_sem(eta_pp: float, eta: float, slope: float, x_levels: np.ndarray,
                     level: int | None = None) -> float:
    """Standard error a level mean (σ_y² + b²σ_x²) may have for the staircase's slope to
    reach a 95 % half-width of ``eta_pp`` percentage points on η = −K_out/(n K_in b):
    Δη/η = σ_b/|b|, so Var(b) ≤ V = ((eta_pp/100)·|b|/(1.96 η))².

    Var(b) = Σ w_k² σ_k² with w_k = d_k/Sxx, d_k = x_k − x̄. For a given total time (σ_k² ∝
    1/t_k) it is smallest with t_k ∝ |d_k|: the end levels carry the slope, the middle ones
    little. That allocation meets V with σ_k² = V·Sxx²/(|d_k|·Σ|d_j|) for ``level`` k
    (|d_k| floored at a tenth of the largest, so no level is let off entirely); without
    ``level``, the equal-time bound σ² = V·Sxx."""
    x = np.asarray(x_levels, float)
    d = np.abs(x - x.mean())
    sxx = float(np.sum(d ** 2))
    v = ((eta_pp / 100.0) * abs(slope) / (Z95 * max(abs(eta), 1e-6))) ** 2
    if level is None or sxx <= 0:
        return float(np.sqrt(v * sxx))
    dk = max(float(d[level]), 0.1 * float(d.max()))
    return float(np.sqrt(v * sxx ** 2 / (dk * float(d.sum()))))
