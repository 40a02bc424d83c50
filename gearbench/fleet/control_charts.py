"""Tester health: SPC charts of a station's own calibrations and of its units.

Series come from the runs (station SQLite or central PostgreSQL, through the one
query API); the charts are ``gearbench.analysis.spc``; this module only groups
values and draws the PNG.

Quantities (``fnmatch`` patterns select them, e.g. ``motors.*.Kt``):

- ``motors.<m>.Kt|J|D|Tc``: the station's motors, calibrated in every run;
- ``ratio@<serial>``: a reference (golden) unit's measured ratio;
- ``<profile>:efficiency[<speed>rad_s,<torque>Nm].eta_incremental``: the units'
  efficiency at each operating point of a profile.
"""
from __future__ import annotations

import fnmatch
from collections import defaultdict

from ..analysis.spc import ControlChart, individuals_chart
from ..errors import GearbenchError

MOTOR_KEYS = ("Kt", "J", "D", "Tc")


def series(runs: list[dict]) -> dict[tuple[str, str], list[tuple[dict, float]]]:
    """(station, quantity) -> [(run, value)] in time order; runs carry ``result``."""
    out: dict[tuple[str, str], list] = defaultdict(list)
    labels: dict[tuple[str, str, int], str] = {}
    for run in sorted(runs, key=lambda r: (r["started_utc"] or "", r["run_id"])):
        res, st = run["result"], run["station"]
        if run["status"] not in ("passed", "failed"):
            continue                       # an aborted/faulted run measured nothing complete
        for m, p in (res.get("motors") or {}).items():
            for k in MOTOR_KEYS:
                if isinstance(p.get(k), (int, float)):
                    out[(st, f"motors.{m}.{k}")].append((run, float(p[k])))
        if run.get("golden") and isinstance(res.get("ratio"), (int, float)):
            out[(st, f"ratio@{run['serial']}")].append((run, float(res["ratio"])))
        for i, pt in enumerate(res.get("efficiency") or []):
            key = (st, run["profile"], i)
            if key not in labels:
                labels[key] = (f"{run['profile']}:efficiency[{pt.get('speed_setpoint_rad_s', pt.get('speed_in_rad_s', 0)):.0f}"
                               f"rad_s,{pt.get('torque_out_nm', 0):.3g}Nm]")
            if isinstance(pt.get("eta_incremental"), (int, float)):
                out[(st, labels[key] + ".eta_incremental")].append((run, float(pt["eta_incremental"])))
    return dict(out)


def charts(runs: list[dict], patterns: list[str] | None = None, *, baseline: int | None = None,
           rules: tuple[str, ...] | None = None) -> list[tuple[str, ControlChart, list[dict]]]:
    """(station, chart, runs of its points) for every selected quantity with enough runs."""
    found = []
    for (station, q), pts in sorted(series(runs).items()):
        if patterns and not any(fnmatch.fnmatchcase(q, p) for p in patterns):
            continue
        if len(pts) < 5:
            continue
        found.append((station, individuals_chart([v for _, v in pts], quantity=q, baseline=baseline,
                                                 rules=rules), [r for r, _ in pts]))
    return found


def write_png(path, station: str, items: list[tuple[str, ControlChart, list[dict]]]) -> None:
    """One row per quantity: the individuals chart (left) and its moving range (right);
    flagged points in red, labelled with their rules."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    n = len(items)
    fig, axes = plt.subplots(n, 2, figsize=(13, 2.4 * n + 0.6), squeeze=False,
                             gridspec_kw={"width_ratios": [3, 1.4]})
    for row, (_, c, _) in enumerate(items):
        ax, axm = axes[row]
        k = np.arange(len(c.values))
        ax.plot(k, c.values, ".-", color="0.3", lw=0.8, ms=4)
        for y, style in ((c.center, "-"), (c.ucl, "--"), (c.lcl, "--")):
            ax.axhline(y, color="tab:blue", ls=style, lw=0.9)
        ax.axvspan(-0.5, c.baseline_n - 0.5, color="tab:blue", alpha=0.06, lw=0)
        bad = np.array(sorted(c.flags), dtype=int)
        if len(bad):
            ax.plot(bad, c.values[bad], "o", color="tab:red", ms=5)
            for i in bad[:20]:
                ax.annotate(",".join(c.flags[i]), (i, c.values[i]), fontsize=6, color="tab:red",
                            xytext=(2, 4), textcoords="offset points")
        ax.set_title(f"{station}  {c.quantity}  (centre {c.center:.5g}, 3σ ±{3 * c.sigma:.3g}, "
                     f"{len(c.flags)} flagged)", fontsize=8, loc="left")
        ax.tick_params(labelsize=7)
        axm.plot(k, c.moving_range, ".-", color="0.3", lw=0.8, ms=3)
        axm.axhline(c.mr_center, color="tab:blue", lw=0.9)
        axm.axhline(c.mr_ucl, color="tab:blue", ls="--", lw=0.9)
        axm.set_title("moving range", fontsize=8, loc="left")
        axm.tick_params(labelsize=7)
    axes[-1][0].set_xlabel("run (time order); shaded: baseline", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def require_charts(found, source: str) -> None:
    if not found:
        raise GearbenchError(f"{source}: no quantity has 5 or more completed runs to chart; "
                             f"widen --since/--station/--quantity or wait for more runs")
