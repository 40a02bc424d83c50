"""The gap between a recorded run and its replay, in units of the measurement's noise floor.

Noise floor of a signal (per axis, over the whole run):

* position: the encoder quantum q over √12 (uniform quantisation error), q the smallest
  step the recorded position makes;
* velocity and current: the white part of the recorded signal, estimated from second
  differences, σ ≈ 1.4826·MAD(Δ²x)/√6 (Δ² of white noise has variance 6σ²; the MAD is
  robust to the steps and transients the signal itself has). The quantum over √12 is the
  lower bound where the estimate gives less.

The gap of a signal on a step is rms(measured − replay)/floor (angles from the step's
first sample): 1 means the replay is at the
noise floor, i.e. the twin explains everything but the noise. *Where* it lies: the same
ratio over time (tenths of the step), input speed bands, load (output current command)
levels, near reversals (|ω| below 5 % of the step's top speed) and the residual's
strongest angle order (projection on sin/cos(kθ), k = 1..36, of the motor's own angle).
"""
from __future__ import annotations

import math

import numpy as np

from .replay import AXES, SIGNALS, Segment, measured, simulated

MAX_ORDER = 36


def _quantum(x: np.ndarray) -> float:
    d = np.abs(np.diff(x))
    d = d[d > 1e-12]
    return float(d.min()) if d.size else 0.0


def noise_floors(segments: list[Segment]) -> dict[tuple[str, str], float]:
    """Noise floor per (axis, signal) from the recorded traces (see module docstring)."""
    floors = {}
    for a in AXES:
        for s in SIGNALS:
            ests, qs = [], []
            for seg in segments:
                if f"{a}.{s}" not in seg.trace:
                    continue
                x = measured(seg, a, s)
                if len(x) < 10:
                    continue
                qs.append(_quantum(x))
                if s != "position_rad":
                    d2 = np.diff(x, 2)
                    ests.append(1.4826 * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6))
            q = min((v for v in qs if v > 0), default=0.0)
            floor = q / math.sqrt(12)
            if ests:
                floor = max(floor, float(np.median(ests)))
            floors[(a, s)] = floor if floor > 0 else 1e-9
    return floors


def residuals(rows: dict[str, np.ndarray], segments: list[Segment], floors: dict) -> dict:
    """{(step, axis, signal): (measured − replay)/floor} at the recorded samples."""
    res = {}
    for seg in segments:
        for a in AXES:
            for s in SIGNALS:
                if f"{a}.{s}" in seg.trace:
                    d = measured(seg, a, s) - simulated(rows[seg.name], seg, a, s)
                    if s == "position_rad":
                        # angles within the step: separately recorded steps (another
                        # session, a rig that zeroes its encoder) have their own origin
                        d = d - d[0]
                    res[(seg.name, a, s)] = d / floors[(a, s)]
    return res


def _rms(x) -> float:
    x = np.asarray(x, float)
    return float(np.sqrt(np.mean(x * x))) if x.size else float("nan")


def gap_table(rows: dict, segments: list[Segment], floors: dict) -> list[dict]:
    """One row per step and signal: rms gap in noise floors, mean (bias) and where it is largest."""
    res = residuals(rows, segments, floors)
    out = []
    for seg in segments:
        for a in AXES:
            for s in SIGNALS:
                r = res.get((seg.name, a, s))
                if r is None:
                    continue
                out.append({"step": seg.name, "axis": a, "signal": s, "gap": _rms(r),
                            "bias": float(np.mean(r)), "floor": floors[(a, s)],
                            "where": where(r, seg, a, rows[seg.name])})
    return out


def where(r: np.ndarray, seg: Segment, axis: str, rows: np.ndarray) -> dict:
    """Where a step's residual (in floors) lies: time tenths, speed bands, load levels,
    reversals and the strongest angle order."""
    n = len(r)
    ax = "in" if seg.coupling == "reducer" else axis
    if f"{ax}.velocity_rad_s" in seg.trace:
        w = measured(seg, ax, "velocity_rad_s")
    else:   # a rig that records no velocity: the encoder's difference
        w = np.gradient(measured(seg, ax, "position_rad"), seg.trace.time_s)
    theta = measured(seg, axis, "position_rad")
    parts = {}
    tenths = np.array_split(np.arange(n), 10)
    parts["time"] = [round(_rms(r[i]), 2) for i in tenths]
    top = float(np.max(np.abs(w))) if n else 0.0
    if top > 0:
        bands = np.linspace(0, top, 5)
        parts["speed"] = [{"from_rad_s": round(float(lo), 1), "to_rad_s": round(float(hi), 1),
                           "gap": round(_rms(r[(np.abs(w) >= lo) & (np.abs(w) <= hi)]), 2)}
                          for lo, hi in zip(bands[:-1], bands[1:])
                          if np.any((np.abs(w) >= lo) & (np.abs(w) <= hi))]
        rev = np.abs(w) < 0.05 * top
        parts["reversals"] = round(_rms(r[rev]), 2) if rev.any() else None
        parts["moving"] = round(_rms(r[~rev]), 2) if (~rev).any() else None
    if seg.coupling == "reducer" and "out.command" in seg.trace:
        load = np.asarray(seg.trace["out.command"], float)
        levels = np.unique(np.round(load, 4))
        if 1 < len(levels) <= 12:
            parts["load"] = [{"out_command": float(v), "gap": round(_rms(r[np.round(load, 4) == v]), 2)}
                             for v in levels]
    parts["angle_order"] = angle_order(r, theta)
    return parts


def angle_order(r: np.ndarray, theta: np.ndarray) -> dict | None:
    """Strongest order k of the residual against the angle: amplitude of the least-squares
    sin/cos(kθ) fit, k = 1..36, in floors (white noise gives about 2/√n)."""
    if len(r) < 100 or np.ptp(theta) < 4 * math.pi:
        return None
    best = None
    rc = r - r.mean()
    for k in range(1, MAX_ORDER + 1):
        s, c = np.sin(k * theta), np.cos(k * theta)
        amp = 2 * math.hypot(float(rc @ s), float(rc @ c)) / len(r)
        if best is None or amp > best[1]:
            best = (k, amp)
    return {"order": best[0], "amplitude": round(best[1], 3),
            "white_level": round(2 * _rms(rc) / math.sqrt(len(r)), 3)}


def total_gap(rows: dict, segments: list[Segment], floors: dict, signals=SIGNALS) -> float:
    """rms over every recorded sample of every signal, in floors."""
    res = residuals(rows, segments, floors)
    parts = [v for (st, a, s), v in res.items() if s in signals]
    return _rms(np.concatenate(parts)) if parts else float("nan")
