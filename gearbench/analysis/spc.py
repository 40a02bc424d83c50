"""Statistical process control: individuals / moving-range charts and run rules.

Pure functions, no I/O. A tester calibrates its own motors every run, so their Kt,
J, friction, a reference unit's ratio and the units' efficiency per operating
point form time series; a chart says when one stops behaving like its baseline.

Limits come from a baseline (phase I: the first ``baseline`` points, 30 by default)
and are applied to every point:

- individuals: centre = baseline mean, sigma = MR-bar / d2 (d2 = 1.128 for n = 2),
  limits centre ± 3 sigma;
- moving range: centre MR-bar, upper limit D4 · MR-bar (D4 = 3.267).

Rules (Western Electric 1-4, Nelson 3), each flagging the point that completes it:

- ``1``  one point beyond 3 sigma;
- ``2``  2 of 3 consecutive points beyond 2 sigma, same side;
- ``3``  4 of 5 consecutive points beyond 1 sigma, same side;
- ``4``  8 consecutive points on one side of the centre;
- ``5``  6 consecutive points steadily increasing or decreasing (a trend);
- ``MR`` a moving range above its upper limit (a jump).

Together the rules raise a false alarm on about 4 % of in-control points (each
rule 0.3-1.3 %, measured in tests/test_spc.py with a 50-run baseline): on a tester
making hundreds of runs a day, pick the rules (``rules=``) and act on persistent
flags, not on one.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import GearbenchError

D2 = 1.128
D4 = 3.267
DEFAULT_BASELINE = 30
MIN_POINTS = 5

RULES = {
    "1": "beyond 3 sigma",
    "2": "2 of 3 beyond 2 sigma, same side",
    "3": "4 of 5 beyond 1 sigma, same side",
    "4": "8 in a row on one side of the centre",
    "5": "6 in a row steadily rising or falling",
    "MR": "moving range above its limit (a jump)",
}


@dataclass(frozen=True)
class ControlChart:
    quantity: str
    values: np.ndarray
    center: float
    sigma: float
    moving_range: np.ndarray          # |x[i] - x[i-1]|, NaN at 0
    mr_center: float
    baseline_n: int
    flags: dict[int, list[str]] = field(default_factory=dict)   # point index -> rule ids

    @property
    def ucl(self) -> float:
        return self.center + 3 * self.sigma

    @property
    def lcl(self) -> float:
        return self.center - 3 * self.sigma

    @property
    def mr_ucl(self) -> float:
        return D4 * self.mr_center

    @property
    def in_control(self) -> bool:
        return not self.flags


def _windows(mask: np.ndarray, length: int, need: int) -> np.ndarray:
    """Indices i where at least ``need`` of mask[i-length+1 .. i] are true and mask[i] is."""
    out = np.zeros(len(mask), bool)
    if len(mask) >= length:
        counts = np.convolve(mask.astype(int), np.ones(length, int), "valid")
        out[length - 1:] = (counts >= need) & mask[length - 1:]
    return out


def run_rules(z: np.ndarray, mr: np.ndarray | None = None, mr_ucl: float | None = None) -> dict[int, list[str]]:
    """Rule violations of standardised values ``z`` ((x - centre) / sigma)."""
    z = np.asarray(z, float)
    hits: dict[str, np.ndarray] = {"1": np.abs(z) > 3}
    hits["2"] = _windows(z > 2, 3, 2) | _windows(z < -2, 3, 2)
    hits["3"] = _windows(z > 1, 5, 4) | _windows(z < -1, 5, 4)
    hits["4"] = _windows(z > 0, 8, 8) | _windows(z < 0, 8, 8)
    d = np.diff(z)
    hits["5"] = np.concatenate([[False], _windows(d > 0, 5, 5) | _windows(d < 0, 5, 5)])
    if mr is not None and mr_ucl is not None:
        hits["MR"] = np.nan_to_num(np.asarray(mr, float), nan=0.0) > mr_ucl
    flags: dict[int, list[str]] = {}
    for rule, mask in hits.items():
        for i in np.flatnonzero(mask):
            flags.setdefault(int(i), []).append(rule)
    return dict(sorted(flags.items()))


def individuals_chart(values, *, quantity: str = "", baseline: int | None = None,
                      rules: tuple[str, ...] | None = None) -> ControlChart:
    """An individuals / moving-range chart of ``values`` in time order.

    Limits from the first ``baseline`` points (phase I): centre = their mean, sigma =
    MR-bar/d2, limits centre ± 3 sigma; moving-range limit D4·MR-bar (module docstring).

    Parameters
    ----------
    values : array_like
        The quantity per run, in time order (at least ``MIN_POINTS``, all finite).
    quantity : str, optional
        Its name, for messages and the chart.
    baseline : int, optional
        Points that set the limits (default ``DEFAULT_BASELINE``, at most all).
    rules : tuple of str, optional
        Which of ``RULES`` to flag (default: all).

    Returns
    -------
    ControlChart
        Centre, limits and the rules each point breaks.

    References
    ----------
    Western Electric Co., *Statistical Quality Control Handbook*, 1956 (rules 1-4);
    L. S. Nelson, "The Shewhart control chart — tests for special causes", J. Quality
    Technology 16(4), 1984 (rule 5); D. C. Montgomery, *Introduction to Statistical
    Quality Control*, 7th ed., sec. 6.4 (individuals and moving-range charts, d2, D4).

    Examples
    --------
    >>> import numpy as np
    >>> x = np.r_[np.random.default_rng(0).normal(1.0, 0.01, 30), 1.1]
    >>> chart = individuals_chart(x, quantity="Kt")
    >>> 30 in chart.flags and "1" in chart.flags[30]
    True
    """
    x = np.asarray(values, float)
    if len(x) < MIN_POINTS or not np.all(np.isfinite(x)):
        raise GearbenchError(f"{quantity or 'series'}: {len(x)} finite values; a control chart needs "
                             f"at least {MIN_POINTS} runs")
    nb = min(len(x), baseline or DEFAULT_BASELINE)
    if nb < MIN_POINTS:
        raise GearbenchError(f"{quantity}: baseline of {nb} runs; use at least {MIN_POINTS}")
    mr = np.concatenate([[np.nan], np.abs(np.diff(x))])
    center = float(np.mean(x[:nb]))
    mr_center = float(np.mean(mr[1:nb]))
    # a perfectly constant baseline still needs a scale: the value's own resolution
    sigma = max(mr_center / D2, 1e-12 * max(abs(center), 1e-300))
    flags = run_rules((x - center) / sigma, mr, D4 * mr_center if mr_center > 0 else None)
    if rules is not None:
        unknown = set(rules) - set(RULES)
        if unknown:
            raise GearbenchError(f"--rules {','.join(sorted(unknown))}: unknown; use some of "
                                 f"{','.join(RULES)}")
        flags = {i: [r for r in f if r in rules] for i, f in flags.items()}
        flags = {i: f for i, f in flags.items() if f}
    return ControlChart(quantity, x, center, sigma, mr, mr_center, nb, flags)
