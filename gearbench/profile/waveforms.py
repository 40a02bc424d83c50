"""Command waveforms a profile can name: parameter tables and pure renderers.

Every waveform is a function of time only (``render(params, time_s) -> array``), so
the sequencer, the emulator and the tests produce the same command for the same
profile. Values are in the unit of the step's mode: rad/s for a velocity command,
A for a current command. ``fade_in_s`` (all kinds) multiplies the whole signal by a
raised-cosine ramp so a run starts from rest instead of jumping.

Kinds: constant, step, ramp, trapezoid, multisine (Schroeder-phased periodic
multisine, Schroeder 1970), chirp (linear or logarithmic sweep), prbs (maximum-
length LFSR sequence).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

REQUIRED = object()


@dataclass(frozen=True)
class Param:
    """One waveform parameter: type, default, bounds and what it means (for errors/docs)."""

    type: str                 # "number" | "int" | "choice" | "bool"
    default: object = REQUIRED
    gt: float | None = None
    ge: float | None = None
    le: float | None = None
    choices: tuple = ()
    meaning: str = ""


_COMMON = {"fade_in_s": Param("number", 0.0, ge=0.0, meaning="raised-cosine start-up time in s")}

PARAMS: dict[str, dict[str, Param]] = {
    "constant": {"value": Param("number", meaning="the constant command (rad/s or A)")},
    "step": {
        "initial": Param("number", 0.0, meaning="command before the step"),
        "final": Param("number", meaning="command after the step"),
        "step_time_s": Param("number", 0.0, ge=0.0, meaning="time of the step in s"),
    },
    "ramp": {
        "start": Param("number", 0.0, meaning="command at the ramp start"),
        "end": Param("number", meaning="command at the ramp end, then held"),
        "delay_s": Param("number", 0.0, ge=0.0, meaning="time before the ramp starts in s"),
        "ramp_time_s": Param("number", gt=0.0, meaning="duration of the ramp in s"),
    },
    "trapezoid": {
        "level": Param("number", meaning="plateau command"),
        "low": Param("number", 0.0, meaning="command between plateaus"),
        "rise_s": Param("number", gt=0.0, meaning="rise time in s"),
        "hold_s": Param("number", 0.0, ge=0.0, meaning="plateau time in s"),
        "fall_s": Param("number", gt=0.0, meaning="fall time in s"),
        "pause_s": Param("number", 0.0, ge=0.0, meaning="time at 'low' before repeating in s"),
        "repeat": Param("bool", True, meaning="repeat the trapezoid periodically"),
        "alternate": Param("bool", False, meaning="flip the sign of every second trapezoid (reversals)"),
    },
    "multisine": {
        "offset": Param("number", 0.0, meaning="mean command"),
        "amplitude": Param("number", gt=0.0, meaning="peak deviation from the offset"),
        "period_s": Param("number", 1.0, gt=0.0, meaning="period; tones are multiples of 1/period_s"),
        "f_min_hz": Param("number", gt=0.0, meaning="lowest tone in Hz"),
        "f_max_hz": Param("number", gt=0.0, meaning="highest tone in Hz"),
        "phases": Param("choice", "schroeder", choices=("schroeder", "random"),
                        meaning="tone phases (Schroeder: low crest factor)"),
        "seed": Param("int", 0, ge=0, meaning="seed for random phases"),
    },
    "chirp": {
        "offset": Param("number", 0.0, meaning="mean command"),
        "amplitude": Param("number", gt=0.0, meaning="sine amplitude"),
        "f0_hz": Param("number", gt=0.0, meaning="start frequency in Hz"),
        "f1_hz": Param("number", gt=0.0, meaning="end frequency in Hz"),
        "sweep_s": Param("number", gt=0.0, meaning="duration of one sweep in s"),
        "method": Param("choice", "linear", choices=("linear", "logarithmic"), meaning="sweep law"),
        "repeat": Param("bool", True, meaning="repeat the sweep; else hold the offset after it"),
    },
    "prbs": {
        "offset": Param("number", 0.0, meaning="mean command"),
        "amplitude": Param("number", gt=0.0, meaning="the command is offset +/- amplitude"),
        "order": Param("int", 7, ge=3, le=16, meaning="LFSR length; the sequence repeats after 2^order-1 bits"),
        "bit_period_s": Param("number", gt=0.0, meaning="duration of one bit in s"),
        "seed": Param("int", 1, ge=1, meaning="non-zero LFSR start state"),
    },
}
for _table in PARAMS.values():
    _table.update(_COMMON)

KINDS = tuple(PARAMS)


def natural_period_s(kind: str, p: dict) -> float | None:
    """The length a run needs to contain one full period of the waveform, or None."""
    if kind == "multisine":
        return p["period_s"]
    if kind == "chirp":
        return p["sweep_s"]
    if kind == "prbs":
        return p["bit_period_s"] * (2 ** p["order"] - 1)
    if kind == "trapezoid":
        return p["rise_s"] + p["hold_s"] + p["fall_s"] + p["pause_s"]
    return None


def check(kind: str, p: dict, period_s: float) -> tuple[str, str, str] | None:
    """Cross-parameter checks; returns (param, problem, fix) or None when fine."""
    nyquist = 0.5 / period_s
    if kind == "multisine":
        if p["f_min_hz"] > p["f_max_hz"]:
            return "f_min_hz", f"must be <= f_max_hz ({p['f_max_hz']:g})", "swap or fix the tone range"
        if p["f_max_hz"] >= nyquist:
            return "f_max_hz", f"must be below the Nyquist frequency {nyquist:g} Hz", "lower f_max_hz"
        if len(multisine_harmonics(p)) == 0:
            return "period_s", (f"no tone k/period_s falls in [{p['f_min_hz']:g}, {p['f_max_hz']:g}] Hz"),\
                "lengthen period_s or widen the tone range"
    if kind == "chirp":
        for name in ("f0_hz", "f1_hz"):
            if p[name] >= nyquist:
                return name, f"must be below the Nyquist frequency {nyquist:g} Hz", f"lower {name}"
        if p["method"] == "logarithmic" and p["f0_hz"] == p["f1_hz"]:
            return "f1_hz", "must differ from f0_hz for a logarithmic sweep", "use method: linear or change f1_hz"
    if kind == "prbs":
        if p["bit_period_s"] < period_s * (1 - 1e-9):
            return "bit_period_s", f"must be >= the sample period {period_s:g} s", "lengthen bit_period_s"
        if p["seed"] >= 2 ** p["order"]:
            return "seed", f"must be < 2^order = {2 ** p['order']}", "use a smaller seed"
    return None


def render(kind: str, p: dict, time_s: np.ndarray) -> np.ndarray:
    """The command at each time in ``time_s`` (any shape), as float64."""
    t = np.asarray(time_s, dtype=float)
    out = _RENDER[kind](p, t)
    fade = p.get("fade_in_s", 0.0)
    if fade > 0:
        w = np.where(t < fade, 0.5 * (1.0 - np.cos(np.pi * np.clip(t, 0.0, fade) / fade)), 1.0)
        out = out * w
    return np.asarray(out, dtype=float)


def _constant(p, t):
    return np.full_like(t, p["value"])


def _step(p, t):
    return np.where(t < p["step_time_s"], p["initial"], p["final"]).astype(float)


def _ramp(p, t):
    frac = np.clip((t - p["delay_s"]) / p["ramp_time_s"], 0.0, 1.0)
    return p["start"] + (p["end"] - p["start"]) * frac


def _trapezoid(p, t):
    rise, hold, fall, pause = p["rise_s"], p["hold_s"], p["fall_s"], p["pause_s"]
    period = rise + hold + fall + pause
    tau = np.mod(t, period) if p["repeat"] else np.clip(t, 0.0, period)
    frac = np.interp(tau, [0.0, rise, rise + hold, rise + hold + fall, period], [0.0, 1.0, 1.0, 0.0, 0.0])
    level = np.full_like(t, p["level"])
    if p["alternate"]:
        level = np.where(np.floor(t / period).astype(np.int64) % 2 == 1, -level, level)
    return p["low"] + (level - p["low"]) * frac


def multisine_harmonics(p: dict) -> np.ndarray:
    """Harmonic numbers k with k/period_s in [f_min_hz, f_max_hz]."""
    period = p["period_s"]
    k_lo = math.ceil(p["f_min_hz"] * period - 1e-9)
    k_hi = math.floor(p["f_max_hz"] * period + 1e-9)
    k_lo = max(k_lo, 1)
    return np.arange(k_lo, k_hi + 1) if k_hi >= k_lo and k_hi - k_lo < 100_000 else np.arange(0)


def _multisine_phases(p: dict, n: int) -> np.ndarray:
    if p["phases"] == "random":
        return np.random.default_rng(p["seed"]).uniform(-np.pi, np.pi, n)
    k = np.arange(1, n + 1)
    return -np.pi * k * (k - 1) / n    # Schroeder (1970), low crest factor


def _multisine_unit(p, t):
    """Sum of equal-amplitude tones, scaled so its peak over one period is 1."""
    k = multisine_harmonics(p)
    phi = _multisine_phases(p, len(k))
    w = 2 * np.pi * k / p["period_s"]
    grid = np.linspace(0.0, p["period_s"], max(4096, min(200_000, 40 * int(k[-1]))), endpoint=False)
    peak = np.max(np.abs(np.sin(np.outer(grid, w) + phi).sum(axis=1)))
    flat = t.reshape(-1)
    acc = np.zeros_like(flat)
    for wk, ph in zip(w, phi):   # loop over tones: memory stays O(len(t))
        acc += np.sin(wk * flat + ph)
    return (acc / peak).reshape(t.shape)


def _multisine(p, t):
    return p["offset"] + p["amplitude"] * _multisine_unit(p, t)


def _chirp(p, t):
    s, f0, f1 = p["sweep_s"], p["f0_hz"], p["f1_hz"]
    tau = np.mod(t, s) if p["repeat"] else np.clip(t, 0.0, s)
    if p["method"] == "logarithmic":
        ratio = f1 / f0
        phase = 2 * np.pi * f0 * s / math.log(ratio) * (np.power(ratio, tau / s) - 1.0)
    else:
        phase = 2 * np.pi * (f0 * tau + (f1 - f0) * tau ** 2 / (2 * s))
    out = p["offset"] + p["amplitude"] * np.sin(phase)
    if not p["repeat"]:
        out = np.where(t > s, p["offset"], out)
    return out


# Maximal-length Fibonacci LFSR taps (XOR of these bit positions, 1-based).
_TAPS = {3: (3, 2), 4: (4, 3), 5: (5, 3), 6: (6, 5), 7: (7, 6), 8: (8, 6, 5, 4), 9: (9, 5),
         10: (10, 7), 11: (11, 9), 12: (12, 11, 10, 4), 13: (13, 12, 11, 8), 14: (14, 13, 12, 2),
         15: (15, 14), 16: (16, 15, 13, 4)}


def prbs_bits(order: int, seed: int = 1) -> np.ndarray:
    """One period (2^order - 1 bits, 0/1) of a maximum-length sequence."""
    n = 2 ** order - 1
    state = seed & n or 1
    bits = np.empty(n, dtype=np.int8)
    taps = _TAPS[order]
    for i in range(n):
        bits[i] = state & 1
        fb = 0
        for tap in taps:
            fb ^= (state >> (order - tap)) & 1
        state = (state >> 1) | (fb << (order - 1))
    return bits


def _prbs(p, t):
    bits = prbs_bits(p["order"], p["seed"])
    idx = np.floor(np.maximum(t, 0.0) / p["bit_period_s"] + 1e-9).astype(np.int64) % len(bits)
    return p["offset"] + p["amplitude"] * (2.0 * bits[idx] - 1.0)


_RENDER = {"constant": _constant, "step": _step, "ramp": _ramp, "trapezoid": _trapezoid,
           "multisine": _multisine, "chirp": _chirp, "prbs": _prbs}
