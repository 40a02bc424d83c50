"""The proof's comparison: the run's results beside the twin's, the twin's pooled over
several noise draws.

One noisy re-simulation of the twin is one draw of the analysis' scatter, and the run is
another: even the hidden bench's *truth*, re-simulated with another noise seed, parted
from its own run by 11.8 % in η at 300 rad/s where the run's interval is ±8 % (cvt seed 41;
the truth re-simulated with the run's own seed reproduced it to 0.3 %). The twin's draws
are pooled (``pool_draws``: mean and sample standard deviation of each result), and the
twin is within when the run's value and the draws' mean agree within the run's interval
and the mean's own uncertainty (``within``). The draws' spread also tells where the run's
interval is narrower than the analysis' scatter on the twin (``understated``): a
parametric bootstrap of the analysis (Efron & Tibshirani 1993, ch. 6).
"""
from __future__ import annotations

import math

import numpy as np

Z95 = 1.96
PROOF_DRAWS = 5   # noise draws of the twin in the proof (their mean and spread; ~1 s of analysis each)


def _pooled(values: list) -> tuple[float | None, float | None]:
    """(mean, sample standard deviation) of the draws' values that exist (None: none do)."""
    v = np.array([x for x in values if x is not None], float)
    if not len(v):
        return None, None
    return float(v.mean()), (float(v.std(ddof=1)) if len(v) > 1 else None)


def pool_draws(draws: list[dict]) -> dict:
    """One summary (the shape of ``summary``) from the summaries of several
    noise draws: each Kt, the ratio and each η their mean over the draws, with ``<key>_sd``
    their sample standard deviation and ``draws`` their number; a limit's verdict and the
    status are the majority's, with ``passed_draws`` the number of draws that passed."""
    first = draws[0]
    out = {"draws": len(draws), "reason": first.get("reason")}
    statuses = [d.get("status") for d in draws]
    out["status"] = max(set(statuses), key=statuses.count)
    out["ratio"], out["ratio_sd"] = _pooled([d.get("ratio") for d in draws])
    out["motors"] = {}
    for m in first.get("motors") or {}:
        mean, sd = _pooled([(d["motors"].get(m) or {}).get("Kt") for d in draws])
        out["motors"][m] = {"Kt": mean, "Kt_sd": sd, "Kt_ci95": first["motors"][m].get("Kt_ci95")}
    n_eff = min(len(d.get("efficiency") or []) for d in draws)
    out["efficiency"] = []
    for i in range(n_eff):
        e = dict(first["efficiency"][i])
        for q in ("eta_incremental", "eta_absolute"):
            e[q], e[q + "_sd"] = _pooled([d["efficiency"][i].get(q) for d in draws])
        out["efficiency"].append(e)
    out["limits"] = []
    for i, lim in enumerate(first.get("limits") or []):
        votes = [bool(d["limits"][i].get("passed")) for d in draws if i < len(d.get("limits") or [])]
        out["limits"].append({"name": lim["name"], "value": lim.get("value"),
                              "passed": 2 * sum(votes) > len(votes), "passed_draws": sum(votes)})
    return out


def half_width(real_ci, twin_sd: float | None, draws: int) -> float | None:
    """The half-width within which the run's value and the mean of ``draws`` twin draws agree
    at 95 % when both come from one plant: √(h² + (1.96·s/√k)²), h the run's half-width, s
    the draws' standard deviation (the difference of two independent estimates; without s,
    h alone). None when the run has no interval."""
    if not real_ci:
        return None
    h = (real_ci[1] - real_ci[0]) / 2
    if twin_sd is None or not draws:
        return h
    return math.hypot(h, Z95 * twin_sd / math.sqrt(draws))


def within(real: float | None, twin: float | None, real_ci, twin_sd: float | None = None,
           draws: int = 1) -> str:
    """"yes"/"NO" by ``half_width``; "" when a value or the run's interval is missing."""
    hw = half_width(real_ci, twin_sd, draws)
    if real is None or twin is None or hw is None:
        return ""
    return "yes" if abs(real - twin) <= hw else "NO"


def understated(real_ci, twin_sd: float | None) -> bool:
    """Whether the run's 95 % half-width is narrower than 1.96× the analysis' scatter over
    the twin's noise draws."""
    return bool(real_ci) and twin_sd is not None and (real_ci[1] - real_ci[0]) / 2 < Z95 * twin_sd


def verdict_among_draws(run_passed: bool, twin_limit: dict, draws: int) -> bool:
    """Whether the run's verdict of a limit is one the twin gives in at least one of its
    ``draws`` noise draws (``passed_draws``; a single draw: its ``passed``). A limit the
    draws split on is one the noise decides, on the bench as on the twin."""
    if not twin_limit:
        return False
    passed = twin_limit.get("passed_draws", draws if twin_limit.get("passed") else 0)
    return passed > 0 if run_passed else passed < draws


def summary(r: dict) -> dict:
    motors = {m: {"Kt": v.get("Kt"), "Kt_ci95": v.get("Kt_ci95")} for m, v in (r.get("motors") or {}).items()}
    eff = [{"speed_in_rad_s": e.get("speed_in_rad_s"), "torque_out_nm": e.get("torque_out_nm"),
            "eta_incremental": e.get("eta_incremental"), "eta_incremental_ci95": e.get("eta_incremental_ci95"),
            "eta_absolute": e.get("eta_absolute"), "eta_absolute_ci95": e.get("eta_absolute_ci95")}
           for e in r.get("efficiency") or []]
    limits = [{"name": lim["name"], "value": lim.get("value"), "passed": lim.get("passed")}
              for lim in r.get("limits") or []]
    return {"status": r.get("status"), "reason": r.get("reason"), "motors": motors,
            "ratio": r.get("ratio"), "efficiency": eff, "limits": limits}


def proof_rows(pr: dict) -> list[tuple]:
    """(label, real, its interval, twin mean, twin sd) of every Kt and efficiency."""
    real, twin = pr["real"], pr["twin"]
    rows = [(f"Kt {m}", v["Kt"], v.get("Kt_ci95"), (twin["motors"].get(m) or {}).get("Kt"),
             (twin["motors"].get(m) or {}).get("Kt_sd")) for m, v in real["motors"].items()]
    for e, f in zip(real["efficiency"], twin["efficiency"]):
        for q in ("eta_incremental", "eta_absolute"):
            rows.append((f"{q} at {e['speed_in_rad_s']:.0f} rad/s, {e['torque_out_nm']:.3f} N m",
                         e[q], e.get(q + "_ci95"), f[q], f.get(q + "_sd")))
    return rows


def limit_pairs(pr: dict) -> list[tuple[dict, dict]]:
    """(run's limit, twin's) in the same order (the efficiency limits are labelled with the
    torque each run measured, so their names differ in the last digit between run and twin)."""
    real, twin = pr["real"], pr["twin"]
    same_order = len(twin["limits"]) == len(real["limits"])
    tl = {lim["name"]: lim for lim in twin["limits"]}
    return [(lim, twin["limits"][i] if same_order else tl.get(lim["name"], {}))
            for i, lim in enumerate(real["limits"])]
