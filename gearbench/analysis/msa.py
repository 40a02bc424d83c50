"""Measurement-system analysis: gauge R&R and the type-1 gauge study. Pure numerics.

References (equation and table numbers of AIAG, *Measurement Systems Analysis*,
Reference Manual, 4th ed., 2010 — "MSA4"):

- ``anova_gauge_rr``: the ANOVA method for a crossed study (MSA4 ch. III sec. B,
  "Analysis of Variance (ANOVA) Method", Tables III-B 4/5; Appendix A, Tables A 1-A 5).
  n parts × k appraisers (here: test stations) × r trials, balanced.
- ``range_gauge_rr``: the average-and-range method (MSA4 ch. III sec. B, "Average and
  Range Method", Fig. III-B 16/17 data sheet and report), used as a cross-check.
- ``type1_study``: one reference measured repeatedly on one gauge — bias and its
  t-test (MSA4 ch. III sec. B, "Bias", independent-sample method) and the capability
  indices Cg / Cgk of a type-1 study (VDA 5 / Bosch booklet 10; K = 20 %, 6 s).

Verdicts follow MSA4 ch. II sec. D: %GRR < 10 % acceptable, 10-30 % may be acceptable
(marginal), > 30 % unacceptable; ndc >= 5.

Input is an array ``x[part, appraiser, trial]``; ``crossed_array`` builds it from
``(part, appraiser, value)`` records and says which cell is missing when it cannot.
Degenerate input (fewer than 2 trials or parts, an unbalanced design, no variation,
a non-finite value) raises ``GearbenchError`` naming what is wrong and what to do.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from ..errors import GearbenchError

STUDY_SIGMAS = 6.0          # MSA4: the study variation and %P/T use 6σ (older editions 5.15σ)
NDC_FACTOR = 1.41           # MSA4: ndc = 1.41 (PV / GRR), truncated to an integer
ALPHA_INTERACTION = 0.05    # MSA4 Appendix A: interaction tested at α = 0.05, pooled when not significant
GRR_ACCEPTABLE_PCT = 10.0
GRR_MARGINAL_PCT = 30.0
NDC_MIN = 5

# 1/d2* of MSA4's data sheet: K1 by trials (ranges of r trials, g = n·k large),
# K2 by appraisers (one range of k averages), K3 by parts (one range of n averages).
K1 = {2: 0.8862, 3: 0.5908}
K2 = {2: 0.7071, 3: 0.5231}
K3 = {2: 0.7071, 3: 0.5231, 4: 0.4467, 5: 0.4030, 6: 0.3742, 7: 0.3534, 8: 0.3375,
      9: 0.3249, 10: 0.3146}


# ------------------------------------------------------------------ the design
def crossed_array(records, *, what: str = "measurement") -> tuple[np.ndarray, list, list]:
    """``x[part, appraiser, trial]`` from ``(part, appraiser, value)`` records in trial order.

    Every part must be measured the same number of times (>= 2) by every appraiser;
    otherwise ``GearbenchError`` names the first cell that differs."""
    parts: list = []
    appraisers: list = []
    cells: dict[tuple, list[float]] = {}
    for part, appr, value in records:
        if part not in parts:
            parts.append(part)
        if appr not in appraisers:
            appraisers.append(appr)
        v = float(value) if value is not None else float("nan")
        if not math.isfinite(v):
            raise GearbenchError(f"{what}: part {part} at {appr} has a missing or non-finite value; "
                                 f"re-measure it or leave that run out")
        cells.setdefault((part, appr), []).append(v)
    if len(parts) < 2:
        raise GearbenchError(f"{what}: {len(parts)} part(s); a gauge R&R needs at least 2 parts "
                             f"(AIAG uses 10) — measure more units")
    counts = {(p, a): len(cells.get((p, a), ())) for p in parts for a in appraisers}
    tally = np.bincount(list(counts.values()))
    r = int(np.flatnonzero(tally == tally.max())[-1])     # the usual number of trials
    for (p, a), n in counts.items():
        if n != r:
            todo = f"measure it {r - n} more time(s)" if n < r else f"leave {n - r} of its runs out"
            raise GearbenchError(f"{what}: unbalanced design — part {p} at {a} has {n} trial(s), "
                                 f"the other cells {r}; {todo}")
    if r < 2:
        raise GearbenchError(f"{what}: 1 trial per part and station; repeatability needs at least "
                             f"2 (AIAG uses 2-3) — measure each part again")
    x = np.array([[cells[(p, a)] for a in appraisers] for p in parts], dtype=float)
    return x, parts, appraisers


def _check(x: np.ndarray, what: str) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    if x.ndim != 3:
        raise GearbenchError(f"{what}: expected data as [part, appraiser, trial]")
    n, k, r = x.shape
    if n < 2 or k < 1 or r < 2:
        raise GearbenchError(f"{what}: {n} part(s), {k} station(s), {r} trial(s); need >= 2 parts, "
                             f">= 1 station and >= 2 trials")
    if not np.all(np.isfinite(x)):
        raise GearbenchError(f"{what}: a value is missing or non-finite; re-measure it")
    if float(np.ptp(x)) == 0.0:
        raise GearbenchError(f"{what}: every value is identical ({x.flat[0]:.6g}); no variation to "
                             f"analyse — check the quantity is really measured (resolution, units)")
    return x


# ------------------------------------------------------------------- results
@dataclass(frozen=True)
class AnovaRow:
    source: str
    df: int
    ss: float
    ms: float
    f: float | None = None
    p: float | None = None


@dataclass(frozen=True)
class GaugeRR:
    """One crossed gauge R&R study. Standard deviations (σ), in the quantity's units.

    ``pct_*`` are 100·σ/TV (MSA4 "% total variation"); ``pct_tolerance`` is %P/T =
    100·6·GRR/tolerance, ``None`` without a two-sided tolerance."""
    method: str                      # "anova" | "range"
    n_parts: int
    n_appraisers: int
    n_trials: int
    ev: float                        # repeatability (equipment variation)
    av: float                        # reproducibility (appraiser = station variation)
    interaction: float               # part × station interaction (0 when pooled)
    grr: float
    pv: float                        # part variation
    tv: float                        # total variation
    tolerance: float | None = None
    interaction_p: float | None = None
    interaction_pooled: bool | None = None
    anova: tuple[AnovaRow, ...] = field(default=(), repr=False)
    notes: tuple[str, ...] = ()

    @property
    def pct_ev(self) -> float:
        return 100.0 * self.ev / self.tv

    @property
    def pct_av(self) -> float:
        return 100.0 * self.av / self.tv

    @property
    def pct_grr(self) -> float:
        return 100.0 * self.grr / self.tv

    @property
    def pct_pv(self) -> float:
        return 100.0 * self.pv / self.tv

    @property
    def pct_tolerance(self) -> float | None:
        """%P/T = 100·6·GRR / tolerance (MSA4: %GRR against the tolerance)."""
        if not self.tolerance:
            return None
        return 100.0 * STUDY_SIGMAS * self.grr / self.tolerance

    @property
    def ndc(self) -> int | None:
        """Number of distinct categories, 1.41·PV/GRR truncated (None when GRR = 0)."""
        if self.grr <= 0:
            return None
        return int(math.floor(NDC_FACTOR * self.pv / self.grr))

    @property
    def verdict(self) -> str:
        return grr_verdict(self.pct_grr, self.pct_tolerance, self.ndc)

    def as_dict(self) -> dict:
        d = dict(method=self.method, parts=self.n_parts, stations=self.n_appraisers,
                 trials=self.n_trials, ev=self.ev, av=self.av, interaction=self.interaction,
                 grr=self.grr, pv=self.pv, tv=self.tv, pct_ev=self.pct_ev, pct_av=self.pct_av,
                 pct_grr=self.pct_grr, pct_pv=self.pct_pv, tolerance=self.tolerance,
                 pct_tolerance=self.pct_tolerance, ndc=self.ndc, verdict=self.verdict,
                 notes=list(self.notes))
        if self.method == "anova":
            d.update(interaction_p=self.interaction_p, interaction_pooled=self.interaction_pooled,
                     anova=[dict(source=a.source, df=a.df, ss=a.ss, ms=a.ms, p=a.p,
                                 f=a.f if a.f is None or math.isfinite(a.f) else "inf")   # JSON has no inf
                            for a in self.anova])
        return d


def grr_verdict(pct_grr_tv: float, pct_tolerance: float | None, ndc: int | None) -> str:
    """MSA4 ch. II D: judged on the larger of %GRR (of TV) and %P/T, and on ndc >= 5.

    The larger one, because a line releases parts against the tolerance but also sorts
    them: a gauge must be good enough for both wherever both are known."""
    pct = max(pct_grr_tv, pct_tolerance if pct_tolerance is not None else 0.0)
    if pct > GRR_MARGINAL_PCT:
        return "unacceptable"
    if pct >= GRR_ACCEPTABLE_PCT or (ndc is not None and ndc < NDC_MIN):
        return "marginal"
    return "acceptable"


# -------------------------------------------------------------------- ANOVA
def anova_gauge_rr(x, *, tolerance: float | None = None, alpha: float = ALPHA_INTERACTION,
                   what: str = "measurement") -> GaugeRR:
    """Crossed gauge R&R by two-way random-effects ANOVA with interaction (MSA4 Appendix A).

    Sums of squares (Table A 1): SS_P = k r Σ(x̄_i.. − x̄)², SS_A = n r Σ(x̄_.j. − x̄)²,
    SS_E = ΣΣΣ(x_ijm − x̄_ij.)², SS_AP = SS_T − SS_P − SS_A − SS_E. Variance
    components (Table A 2): EV² = MS_E, INT² = (MS_AP − MS_E)/r,
    AV² = (MS_A − MS_AP)/(n r), PV² = (MS_P − MS_AP)/(k r); negative estimates are set
    to 0 (MSA4). The interaction is tested by F = MS_AP/MS_E; when not significant at
    ``alpha`` it is pooled into the error (MS_pool = (SS_AP + SS_E)/(df_AP + df_E)),
    which is how MSA4 Table A 5 reports its example. GRR² = EV² + AV² + INT²,
    TV² = GRR² + PV². With one station (k = 1) AV and INT are not estimable and are 0:
    a repeatability-and-part study, said in ``notes``.

    Parameters
    ----------
    x : array_like, shape (n parts, k appraisers, r trials)
        Balanced crossed study (``crossed_array`` builds it from records).
    tolerance : float, optional
        Tolerance width, for %GRR of tolerance.
    alpha : float, optional
        Significance of the interaction test before pooling.
    what : str, optional
        The measured quantity's name, for messages.

    Returns
    -------
    GaugeRR
        Variance components, %GRR of total variation (and of tolerance), ndc, the
        ANOVA table, verdict and notes.

    References
    ----------
    AIAG, *Measurement Systems Analysis*, Reference Manual, 4th ed., 2010, ch. III
    sec. B and Appendix A, Tables A 1-A 5.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(1)
    >>> parts = np.linspace(0.70, 0.80, 10)[:, None, None]
    >>> x = parts + rng.normal(0, 0.002, (10, 3, 2))
    >>> g = anova_gauge_rr(x, what="eta")
    >>> bool(g.pct_grr < 10)
    True
    """
    x = _check(x, what)
    n, k, r = x.shape
    grand = x.mean()
    part_m = x.mean(axis=(1, 2))
    appr_m = x.mean(axis=(0, 2))
    cell_m = x.mean(axis=2)
    ss_t = float(((x - grand) ** 2).sum())
    ss_p = float(k * r * ((part_m - grand) ** 2).sum())
    ss_a = float(n * r * ((appr_m - grand) ** 2).sum())
    ss_e = float(((x - cell_m[:, :, None]) ** 2).sum())
    ss_ap = max(0.0, ss_t - ss_p - ss_a - ss_e)
    df_p, df_a, df_ap, df_e = n - 1, k - 1, (n - 1) * (k - 1), n * k * (r - 1)
    ms_p = ss_p / df_p
    ms_e = ss_e / df_e
    notes: list[str] = []
    if k == 1:
        notes.append("one station: reproducibility (AV) not estimable; GRR = repeatability only")
        ev2, pv2 = ms_e, (ms_p - ms_e) / r
        rows = (AnovaRow("part", df_p, ss_p, ms_p, _f(ms_p, ms_e), _p(ms_p, ms_e, df_p, df_e)),
                AnovaRow("repeatability", df_e, ss_e, ms_e), AnovaRow("total", n * r - 1, ss_t, ss_t / (n * r - 1)))
        return _components("anova", n, k, r, ev2, 0.0, 0.0, pv2, tolerance, None, None, rows, notes)
    ms_a = ss_a / df_a
    ms_ap = ss_ap / df_ap
    f_ap = _f(ms_ap, ms_e)
    p_ap = _p(ms_ap, ms_e, df_ap, df_e)
    pooled = p_ap is not None and p_ap >= alpha
    if pooled:
        df_pool = df_ap + df_e
        ms_pool = (ss_ap + ss_e) / df_pool
        ev2, int2 = ms_pool, 0.0
        av2 = (ms_a - ms_pool) / (n * r)
        pv2 = (ms_p - ms_pool) / (k * r)
        notes.append(f"part×station interaction not significant (p = {p_ap:.3g} >= {alpha}): "
                     f"pooled into repeatability")
        rows = (AnovaRow("part", df_p, ss_p, ms_p, _f(ms_p, ms_pool), _p(ms_p, ms_pool, df_p, df_pool)),
                AnovaRow("station", df_a, ss_a, ms_a, _f(ms_a, ms_pool), _p(ms_a, ms_pool, df_a, df_pool)),
                AnovaRow("part×station", df_ap, ss_ap, ms_ap, f_ap, p_ap),
                AnovaRow("repeatability (pooled)", df_pool, ss_ap + ss_e, ms_pool),
                AnovaRow("total", n * k * r - 1, ss_t, ss_t / (n * k * r - 1)))
    else:
        ev2 = ms_e
        int2 = (ms_ap - ms_e) / r
        av2 = (ms_a - ms_ap) / (n * r)
        pv2 = (ms_p - ms_ap) / (k * r)
        notes.append("part×station interaction significant" +
                     (f" (p = {p_ap:.3g} < {alpha})" if p_ap is not None else " (no repeatability error)") +
                     ": kept in GRR")
        rows = (AnovaRow("part", df_p, ss_p, ms_p, _f(ms_p, ms_ap), _p(ms_p, ms_ap, df_p, df_ap)),
                AnovaRow("station", df_a, ss_a, ms_a, _f(ms_a, ms_ap), _p(ms_a, ms_ap, df_a, df_ap)),
                AnovaRow("part×station", df_ap, ss_ap, ms_ap, f_ap, p_ap),
                AnovaRow("repeatability", df_e, ss_e, ms_e),
                AnovaRow("total", n * k * r - 1, ss_t, ss_t / (n * k * r - 1)))
    return _components("anova", n, k, r, ev2, av2, int2, pv2, tolerance, p_ap, pooled, rows, notes)


def _f(num: float, den: float) -> float | None:
    if den > 0:
        return num / den
    return math.inf if num > 0 else None


def _p(num: float, den: float, df1: int, df2: int) -> float | None:
    if df1 <= 0 or df2 <= 0:
        return None
    if den > 0:
        return float(stats.f.sf(num / den, df1, df2))
    return 0.0 if num > 0 else None     # zero error: any effect is infinitely significant


def _components(method, n, k, r, ev2, av2, int2, pv2, tolerance, p_ap, pooled, rows, notes) -> GaugeRR:
    ev2, av2, int2, pv2 = (max(0.0, float(v)) for v in (ev2, av2, int2, pv2))
    grr2 = ev2 + av2 + int2
    tv2 = grr2 + pv2
    if tv2 <= 0:
        raise GearbenchError("measurement: no variation at all (TV = 0); nothing to analyse")
    if tolerance is not None and not (math.isfinite(tolerance) and tolerance > 0):
        raise GearbenchError(f"tolerance {tolerance!r}: must be a positive number (upper − lower limit)")
    return GaugeRR(method, n, k, r, math.sqrt(ev2), math.sqrt(av2), math.sqrt(int2), math.sqrt(grr2),
                   math.sqrt(pv2), math.sqrt(tv2), tolerance, p_ap, pooled, tuple(rows), tuple(notes))


# ---------------------------------------------------------- average and range
def range_gauge_rr(x, *, tolerance: float | None = None, what: str = "measurement") -> GaugeRR | None:
    """The average-and-range method (MSA4 Fig. III-B 17): EV = R̿·K1, AV =
    √((X̄_diff·K2)² − EV²/(n r)), PV = R_p·K3, GRR = √(EV² + AV²). ``None`` where MSA4's
    K constants are not tabulated (trials not 2-3, stations not 1-3, parts not 2-10)."""
    x = _check(x, what)
    n, k, r = x.shape
    if r not in K1 or (k > 1 and k not in K2) or n not in K3:
        return None
    ev = float(np.ptp(x, axis=2).mean()) * K1[r]
    av2 = 0.0
    if k > 1:
        x_diff = float(np.ptp(x.mean(axis=(0, 2))))
        av2 = (x_diff * K2[k]) ** 2 - ev ** 2 / (n * r)
    pv = float(np.ptp(x.mean(axis=(1, 2)))) * K3[n]
    notes = ("one station: AV not estimable",) if k == 1 else ()
    return _components("range", n, k, r, ev ** 2, av2, 0.0, pv ** 2, tolerance, None, None, (), list(notes))


# ------------------------------------------------------------ type-1 study
@dataclass(frozen=True)
class Type1:
    """Type-1 gauge study: one reference measured ``n`` times on one gauge."""
    n: int
    mean: float
    s: float                          # repeatability standard deviation
    reference: float | None = None    # true value (the simulated plant's; a calibrated master)
    tolerance: float | None = None
    alpha: float = 0.05

    @property
    def bias(self) -> float | None:
        return None if self.reference is None else self.mean - self.reference

    @property
    def bias_t(self) -> float | None:
        """t = bias / (s/√n), n − 1 degrees of freedom (MSA4 bias, independent sample)."""
        if self.bias is None or self.s <= 0:
            return None
        return self.bias / (self.s / math.sqrt(self.n))

    @property
    def bias_p(self) -> float | None:
        t = self.bias_t
        return None if t is None else float(2 * stats.t.sf(abs(t), self.n - 1))

    @property
    def bias_ci95(self) -> tuple[float, float] | None:
        """MSA4: bias ± t(α/2, n−1)·s/√n; bias is acceptable when 0 lies inside."""
        if self.bias is None:
            return None
        h = float(stats.t.ppf(1 - self.alpha / 2, self.n - 1)) * self.s / math.sqrt(self.n)
        return (self.bias - h, self.bias + h)

    @property
    def bias_significant(self) -> bool | None:
        ci = self.bias_ci95
        return None if ci is None else not (ci[0] <= 0.0 <= ci[1])

    @property
    def cg(self) -> float | None:
        """Cg = (0.2·T) / (6·s)  (K = 20 %, L = 6; capable at >= 1.33)."""
        if self.tolerance is None or self.s <= 0:
            return None
        return 0.2 * self.tolerance / (STUDY_SIGMAS * self.s)

    @property
    def cgk(self) -> float | None:
        """Cgk = (0.1·T − |bias|) / (3·s)."""
        if self.tolerance is None or self.s <= 0 or self.bias is None:
            return None
        return (0.1 * self.tolerance - abs(self.bias)) / (STUDY_SIGMAS / 2 * self.s)

    @property
    def verdict(self) -> str:
        """capable (Cg and, with a reference, Cgk >= 1.33) | not capable | no tolerance."""
        if self.cg is None:
            return "no tolerance: repeatability only"
        worst = min(v for v in (self.cg, self.cgk) if v is not None)
        return "capable" if worst >= 1.33 else "not capable"

    def as_dict(self) -> dict:
        return dict(n=self.n, mean=self.mean, s=self.s, reference=self.reference, bias=self.bias,
                    bias_t=self.bias_t, bias_p=self.bias_p, bias_ci95=self.bias_ci95,
                    bias_significant=self.bias_significant, tolerance=self.tolerance,
                    cg=self.cg, cgk=self.cgk, verdict=self.verdict)


def type1_study(values, *, reference: float | None = None, tolerance: float | None = None,
                what: str = "measurement") -> Type1:
    """Repeatability, bias (with ``reference``) and Cg/Cgk (with ``tolerance``) of one gauge."""
    v = np.asarray(values, dtype=float)
    if v.ndim != 1 or len(v) < 2:
        raise GearbenchError(f"{what}: {v.size} value(s); a type-1 study needs at least 2 "
                             f"repeated measurements (VDA 5 uses 25-50)")
    if not np.all(np.isfinite(v)):
        raise GearbenchError(f"{what}: a value is missing or non-finite; re-measure it")
    if tolerance is not None and not (math.isfinite(tolerance) and tolerance > 0):
        raise GearbenchError(f"{what}: tolerance {tolerance!r} must be a positive number")
    if float(np.ptp(v)) == 0.0:
        raise GearbenchError(f"{what}: all {len(v)} values are identical ({v[0]:.6g}); no "
                             f"repeatability to estimate — check the value is really measured")
    return Type1(len(v), float(v.mean()), float(v.std(ddof=1)), reference, tolerance)
