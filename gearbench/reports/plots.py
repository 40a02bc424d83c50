"""Figures for reports (matplotlib, Agg backend: no display needed).

Each ``*_png`` function takes plain numbers and returns PNG bytes; nothing here
reads or writes files. Axes carry quantity and unit, every figure a legend or a
colour bar.
"""
from __future__ import annotations

import io
import math
from typing import Iterable, Sequence

import matplotlib

matplotlib.use("Agg")   # before pyplot: reports are drawn on headless testers and CI
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

SPEED_COLOURS = ("#1b6ca8", "#d95f02", "#1b9e77", "#7570b3", "#e7298a", "#66a61e", "#a6761d")
# each speed its own marker and dash too: lines that coincide (a harmonic drive's efficiency
# barely depends on speed) stay distinguishable, and are drawn side by side (DODGE_REL)
SPEED_MARKERS = ("o", "s", "^", "D", "v", "P", "X")
SPEED_DASHES = ("-", "--", "-.", ":", (0, (5, 1)), (0, (3, 1, 1, 1)), (0, (1, 1)))
DODGE_REL = 0.012           # horizontal offset per speed, relative to the torque span
MOTOR_COLOURS = {"in": "#1b6ca8", "out": "#d95f02"}
DPI = 100


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


def _finite(v) -> float | None:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def torque_fit_png(runs: Sequence[tuple[str, object]], *, motor: str, kt: float,
                   kt_ci95: Sequence[float] | None) -> bytes:
    """Identification fit of one motor: measured torque Kt·i against the model's
    J θ'' + D θ' + Tc sign θ' for each calibration run (``(label, TorqueBalance)``)."""
    fig, axes = plt.subplots(len(runs), 1, figsize=(9.5, 2.4 * len(runs)), squeeze=False,
                             sharex=False)
    for ax, (label, b) in zip(axes[:, 0], runs):
        ax.plot(b.time_s, 1e3 * b.measured_nm, color="#444444", lw=1.2, label="measured Kt·i")
        ax.plot(b.time_s, 1e3 * b.model_nm, color="#d95f02", lw=1.0,
                ls="--", label="model J·θ'' + D·θ' + Tc·sign θ'")
        ax.plot(b.time_s, 1e3 * (b.measured_nm - b.model_nm), color="#7570b3", lw=0.8,
                label="measured − model")
        ax.set_ylabel("torque [mN·m]")
        ax.set_title(f"motor {motor}, {label}: R² = {b.r2:.4f}, rms error {1e3 * b.rms_error_nm:.3g} mN·m",
                     fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    axes[-1, 0].set_xlabel("time [s] (drive time base)")
    ci = "" if not kt_ci95 else f" [{kt_ci95[0]:.5g}, {kt_ci95[1]:.5g}] (95 %)"
    fig.suptitle(f"Kt = {kt:.5g} N·m/A{ci}", fontsize=10)
    fig.tight_layout()
    return _png(fig)


def efficiency_map_png(points: Iterable[dict], limits: Sequence[dict] = (),
                       keys: Sequence[str] = ("eta_incremental", "eta_absolute")) -> bytes:
    """Incremental and absolute efficiency versus output torque, one line per input
    speed, 95 % intervals as error bars, the profile's limits as dashed lines.

    ``points``: result.json ``efficiency`` entries; ``limits``: result.json ``limits``
    (those on ``efficiency.eta_*`` are drawn on their panel)."""
    pts = [p for p in points if _finite(p.get("torque_out_nm")) is not None]
    titles = {"eta_incremental": "incremental efficiency (eq. 18)",
              "eta_absolute": "absolute efficiency P_out / P_in"}
    fig, axes = plt.subplots(1, len(keys), figsize=(5 * len(keys), 4.6), squeeze=False)
    speeds = sorted({round(float(p.get("speed_setpoint_rad_s") or p["speed_in_rad_s"]), 6) for p in pts})
    torques = [float(p["torque_out_nm"]) for p in pts]
    dodge = DODGE_REL * (max(torques) - min(torques) or max(abs(t) for t in torques) or 1.0)
    for ax, key in zip(axes[0], keys):
        title = titles.get(key, key)
        for k, s in enumerate(speeds):
            row = sorted((p for p in pts if round(float(p.get("speed_setpoint_rad_s") or p["speed_in_rad_s"]), 6) == s
                          and _finite(p.get(key)) is not None), key=lambda p: p["torque_out_nm"])
            if not row:
                continue
            x = np.array([p["torque_out_nm"] for p in row]) + (k - (len(speeds) - 1) / 2) * dodge
            y = 100 * np.array([p[key] for p in row])
            lo, hi = [], []
            for p, yy in zip(row, y):
                ci = p.get(f"{key}_ci95")
                if isinstance(ci, (list, tuple)) and len(ci) == 2 and None not in ci:
                    lo.append(max(yy - 100 * ci[0], 0.0))
                    hi.append(max(100 * ci[1] - yy, 0.0))
                elif _finite(ci) is not None:      # a half-width
                    lo.append(100 * abs(ci))
                    hi.append(100 * abs(ci))
                else:
                    lo.append(0.0)
                    hi.append(0.0)
            ax.errorbar(x, y, yerr=[lo, hi], marker=SPEED_MARKERS[k % len(SPEED_MARKERS)], ms=5,
                        capsize=3, lw=1.4, ls=SPEED_DASHES[k % len(SPEED_DASHES)], mfc="white", mew=1.3,
                        color=SPEED_COLOURS[k % len(SPEED_COLOURS)], label=f"ω_in = {s:.4g} rad/s")
        drawn = False
        for lim in limits:
            if lim.get("quantity") != f"efficiency.{key}" or drawn:
                continue
            for bound, name in ((lim.get("low"), "low"), (lim.get("high"), "high")):
                if _finite(bound) is not None:
                    ax.axhline(100 * bound, color="#b2182b", ls=":", lw=1.2,
                               label=f"limit {name} {100 * bound:.4g} %")
            drawn = True   # one efficiency limit spans every point; draw it once
        ax.set_xlabel("output torque T_out [N·m]")
        ax.set_ylabel("efficiency [%]")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=9, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=3)
    fig.suptitle("Efficiency map, error bars: 95 % intervals", fontsize=10)
    fig.tight_layout()
    return _png(fig)


def trace_thumbnail_png(time_s, columns: dict[str, np.ndarray], *, title: str,
                        max_points: int = 1500) -> bytes:
    """One recorded step, small: velocity and current of each motor on their own axes."""
    t = np.asarray(time_s, float)
    step = max(1, len(t) // max_points)
    fig, axes = plt.subplots(2, 1, figsize=(4.2, 3.0), sharex=True)
    for ax, qty, unit in ((axes[0], "velocity_rad_s", "ω [rad/s]"), (axes[1], "current_a", "i [A]")):
        for name, v in columns.items():
            motor, _, q = name.partition(".")
            if q == qty:
                ax.plot(t[::step], np.asarray(v, float)[::step], lw=0.8,
                        color=MOTOR_COLOURS.get(motor), label=f"motor {motor}")
        ax.set_ylabel(unit, fontsize=9)
        ax.tick_params(labelsize=8)
        ax.grid(alpha=0.3)
    # the legend above the plot, full size: readable on a printed thumbnail
    axes[0].legend(fontsize=9, loc="lower right", bbox_to_anchor=(1.0, 1.0), ncol=2, frameon=False,
                   borderaxespad=0.1, handlelength=1.2, columnspacing=0.8)
    axes[1].set_xlabel("time [s]", fontsize=9)
    axes[0].set_title(title, fontsize=9, loc="left")
    fig.tight_layout()
    return _png(fig)


def heatmap_png(values, *, x_extent: tuple[float, float], y_extent: tuple[float, float],
                xlabel: str, ylabel: str, title: str, colorbar_label: str,
                vmin: float | None = None, vmax: float | None = None) -> bytes:
    """A 2-D map (rows = y bins bottom-up, columns = x bins) with axes and a colour bar;
    empty (NaN) cells are left blank."""
    v = np.ma.masked_invalid(np.asarray(values, float))
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    im = ax.imshow(v, origin="lower", aspect="auto", cmap="viridis", vmin=vmin, vmax=vmax,
                   extent=(x_extent[0], x_extent[1], y_extent[0], y_extent[1]), interpolation="nearest")
    cb = fig.colorbar(im, ax=ax)
    cb.set_label(colorbar_label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return _png(fig)
