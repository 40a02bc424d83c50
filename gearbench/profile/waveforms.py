"""Command waveforms a profile can name: parameter tables and pure renderers.

Every waveform is a function of time only (``render(params, time_s) -> array``), so
the sequencer, the emulator and the tests produce the same command for the same
profile. Values are in the unit of the step's mode: rad/s for a velocity command,
A for a current command. Rendering is pointwise in time (no normalisation over the
array passed in), so a command rendered in chunks equals one rendered whole; this is
why these renderers are not ``gearbench.sim.waveforms``, whose multisine and PRBS
depend on the time array. Parameter names follow that module. ``fade_in_s`` (all kinds) multiplies the whole signal by a
raised-cosine ramp so a run starts from rest instead of jumping.

Kinds: constant, step, ramp, trapezoid, multisine (Schroeder-phased periodic
multisine, Schroeder 1970), chirp (linear or logarithmic sweep), prbs (maximum-
length LFSR sequence).
"""
from __future__ import annotations

import functools
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
_OPTIONAL = None  # a Param default of None: the parameter may be left out

# Parameter names follow gearbench.sim.waveforms where the meaning is the same.
PARAMS: dict[str, dict[str, Param]] = {
    "constant": {"value": Param("number", meaning="the constant command (rad/s or A)")},
    "step": {
        "offset": Param("number", 0.0, meaning="command before the step"),
        "amplitude": Param("number", meaning="size of the step (command after = offset + amplitude)"),
        "t_step_s": Param("number", 0.0, ge=0.0, meaning="time of the step in s"),
    },
    "ramp": {
        "offset": Param("number", 0.0, meaning="command before the ramp"),
        "slope": Param("number", meaning="rate of change per second (rad/s^2 or A/s), not 0"),
        "t0_s": Param("number", 0.0, ge=0.0, meaning="time the ramp starts in s"),
        "final": Param("number", _OPTIONAL, meaning="command held once reached (optional)"),
    },
    "trapezoid": {
        "offset": Param("number", 0.0, meaning="command outside the plateaus"),
        "amplitude": Param("number", meaning="plateau height above offset (negative = reverse)"),
        "ramp_s": Param("number", gt=0.0, meaning="rise time = fall time in s"),
        "hold_s": Param("number", ge=0.0, meaning="plateau time in s"),
        "t0_s": Param("number", 0.0, ge=0.0, meaning="start of the first trapezoid in s"),
        "repeat_s": Param("number", _OPTIONAL, gt=0.0, meaning="repeat period in s (optional)"),
        "alternate": Param("bool", False, meaning="flip the sign of every second repetition (reversals)"),
    },
    "multisine": {
        "offset": Param("number", 0.0, meaning="mean command"),
        "amplitude": Param("number", gt=0.0, meaning="peak deviation from the offset"),
        "period_s": Param("number", 1.0, gt=0.0, meaning="period; every tone is a multiple of 1/period_s"),
        "f_min_hz": Param("number", _OPTIONAL, gt=0.0, meaning="lowest tone in Hz (with f_max_hz)"),
        "f_max_hz": Param("number", _OPTIONAL, gt=0.0, meaning="highest tone in Hz (with f_min_hz)"),
        "freqs_hz": Param("list", _OPTIONAL, gt=0.0, meaning="explicit tones in Hz, multiples of 1/period_s"),
        "phases": Param("choice", "schroeder", choices=("schroeder", "random", "clipped"),
                        meaning="tone phases (Schroeder: low crest factor; clipped: lower still, "
                                "for the acceleration)"),
        "seed": Param("int", 0, ge=0, meaning="seed for random phases"),
        "spectrum": Param("choice", "speed", choices=("speed", "acceleration"),
                          meaning="equal tone amplitudes of the speed, or of its derivative "
                                  "(speed tones ~ 1/f: the same current per tone)"),
        "design": Param("choice", "none", choices=("none", "optimal"),
                        meaning="optimal: band, amplitude, offset, period and phases designed from "
                                "the motors' limits (docs/excitation-design.md)"),
        "peak_current_fraction": Param("number", 0.65, gt=0.0, le=1.0,
                                       meaning="design: peak current as a share of current_limit_a"),
        "rms_current_fraction": Param("number", 1.0, gt=0.0, le=2.0,
                                      meaning="design: rms current as a share of rated_current_a"),
        "min_speed_rad_s": Param("number", _OPTIONAL, gt=0.0,
                                 meaning="design: lowest speed (default 10 % of speed_limit_rad_s)"),
        "max_speed_rad_s": Param("number", _OPTIONAL, gt=0.0,
                                 meaning="design: highest speed (default 90 % of speed_limit_rad_s)"),
        "friction_nm": Param("number", _OPTIONAL, ge=0.0,
                             meaning="design: expected friction torque (default 10 % of kt_datasheet "
                                     "x rated_current_a)"),
        "current_noise_a": Param("number", 0.004, gt=0.0,
                                 meaning="design: expected current-measurement noise, std in A"),
        "max_tone_hz": Param("number", 10.0, gt=0.0,
                             meaning="design: highest tone (keep it inside the drive's speed-loop "
                                     "bandwidth)"),
    },
    "chirp": {
        "offset": Param("number", 0.0, meaning="mean command"),
        "amplitude": Param("number", gt=0.0, meaning="sine amplitude"),
        "f0_hz": Param("number", gt=0.0, meaning="start frequency in Hz"),
        "f1_hz": Param("number", gt=0.0, meaning="end frequency in Hz"),
        "t1_s": Param("number", gt=0.0, meaning="duration of one sweep in s"),
        "method": Param("choice", "linear", choices=("linear", "log"), meaning="sweep law"),
        "repeat": Param("bool", True, meaning="repeat the sweep; else hold the offset after it"),
    },
    "prbs": {
        "offset": Param("number", 0.0, meaning="mean command"),
        "amplitude": Param("number", gt=0.0, meaning="the command is offset +/- amplitude"),
        "bit_s": Param("number", gt=0.0, meaning="duration of one bit in s"),
        "order": Param("int", 9, ge=3, le=16, meaning="LFSR length; the sequence repeats after 2^order-1 bits"),
        "seed": Param("int", 0, ge=0, meaning="selects the LFSR start state"),
    },
}
for _table in PARAMS.values():
    _table.update(_COMMON)

KINDS = tuple(PARAMS)
MAX_TONES = 200   # more tones add nothing to an identification run and cost render time
# Multisine keys a designed waveform (``design: optimal``) chooses itself, and the keys
# that only mean something to the design.
DESIGNED_KEYS = ("offset", "amplitude", "period_s", "f_min_hz", "f_max_hz", "freqs_hz", "phases",
                 "seed", "spectrum")
DESIGN_ONLY_KEYS = ("peak_current_fraction", "rms_current_fraction", "min_speed_rad_s",
                    "max_speed_rad_s", "friction_nm", "current_noise_a", "max_tone_hz")


def natural_period_s(kind: str, p: dict) -> float | None:
    """The length a run needs to contain one full period of the waveform, or None."""
    if kind == "multisine":
        return p["period_s"]
    if kind == "chirp":
        return p["t1_s"]
    if kind == "prbs":
        return p["bit_s"] * (2 ** p["order"] - 1)
    if kind == "trapezoid" and p["repeat_s"] is not None:
        return p["repeat_s"]
    return None


def check(kind: str, p: dict, period_s: float) -> tuple[str, str, str] | None:
    """Cross-parameter checks; returns (param, problem, fix) or None when fine."""
    nyquist = 0.5 / period_s
    if kind == "ramp" and p["final"] is not None and (p["final"] - p["offset"]) * p["slope"] <= 0:
        return "slope", "must point from offset toward final", "change the sign of slope or fix final"
    if kind == "ramp" and p["slope"] == 0:
        return "slope", "must not be 0", "use kind: constant for a constant command"
    if kind == "trapezoid":
        width = 2 * p["ramp_s"] + p["hold_s"]
        if p["repeat_s"] is not None and p["repeat_s"] < width:
            return "repeat_s", f"must be >= 2*ramp_s + hold_s ({width:g} s)", "lengthen repeat_s"
        if p["alternate"] and p["repeat_s"] is None:
            return "alternate", "needs repeat_s", "add repeat_s (the repetition period)"
    if kind == "multisine":
        has_range = p["f_min_hz"] is not None or p["f_max_hz"] is not None
        if (p["freqs_hz"] is None) == (not has_range) or (has_range and None in (p["f_min_hz"], p["f_max_hz"])):
            return "freqs_hz", "give either freqs_hz or both f_min_hz and f_max_hz", \
                "e.g. f_min_hz: 0.5, f_max_hz: 8"
        if p["freqs_hz"] is not None:
            if max(p["freqs_hz"]) >= nyquist:
                return "freqs_hz", f"must be below the Nyquist frequency {nyquist:g} Hz", "lower the highest tone"
            if len(p["freqs_hz"]) > MAX_TONES:
                return "freqs_hz", f"more than {MAX_TONES} tones", "use fewer tones"
            for f in p["freqs_hz"]:
                k = round(f * p["period_s"])
                if k < 1 or abs(k - f * p["period_s"]) > 1e-6:
                    return "freqs_hz", f"{f:g} Hz is not a multiple of 1/period_s = {1 / p['period_s']:g} Hz", \
                        "use multiples of 1/period_s so the multisine is periodic"
        else:
            if p["f_min_hz"] > p["f_max_hz"]:
                return "f_min_hz", f"must be <= f_max_hz ({p['f_max_hz']:g})", "swap or fix the tone range"
            if p["f_max_hz"] >= nyquist:
                return "f_max_hz", f"must be below the Nyquist frequency {nyquist:g} Hz", "lower f_max_hz"
            if (p["f_max_hz"] - p["f_min_hz"]) * p["period_s"] > MAX_TONES:
                return "period_s", f"gives more than {MAX_TONES} tones", "shorten period_s or narrow the tone range"
            if len(multisine_harmonics(p)) == 0:
                return "period_s", f"no tone k/period_s falls in [{p['f_min_hz']:g}, {p['f_max_hz']:g}] Hz", \
                    "lengthen period_s or widen the tone range"
    if kind == "chirp":
        for name in ("f0_hz", "f1_hz"):
            if p[name] >= nyquist:
                return name, f"must be below the Nyquist frequency {nyquist:g} Hz", f"lower {name}"
    if kind == "prbs" and p["bit_s"] < period_s * (1 - 1e-9):
        return "bit_s", f"must be >= the sample period {period_s:g} s", "lengthen bit_s"
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
    return p["offset"] + p["amplitude"] * (t >= p["t_step_s"])


def _ramp(p, t):
    y = p["offset"] + p["slope"] * np.clip(t - p["t0_s"], 0.0, None)
    if p["final"] is not None:
        y = np.minimum(y, p["final"]) if p["slope"] > 0 else np.maximum(y, p["final"])
    return y


def _trapezoid(p, t):
    ramp, hold, t0, rep = p["ramp_s"], p["hold_s"], p["t0_s"], p["repeat_s"]
    width = 2 * ramp + hold
    tau = t - t0
    sign = np.ones_like(t)
    if rep is not None:
        if p["alternate"]:
            sign = np.where(np.floor(np.maximum(tau, 0.0) / rep).astype(np.int64) % 2 == 1, -1.0, 1.0)
        tau = np.where(tau >= 0, np.mod(tau, rep), tau)
    shape = np.interp(tau, [0.0, ramp, ramp + hold, width], [0.0, 1.0, 1.0, 0.0], left=0.0, right=0.0)
    return p["offset"] + p["amplitude"] * sign * shape


def multisine_harmonics(p: dict) -> np.ndarray:
    """Harmonic numbers k with k/period_s in [f_min_hz, f_max_hz]."""
    period = p["period_s"]
    if p.get("freqs_hz") is not None and (p["f_min_hz"] is not None or p["f_max_hz"] is not None):
        return np.arange(0)  # ambiguous: check() reports it
    if p.get("freqs_hz") is not None:
        return np.array(sorted({int(round(f * period)) for f in p["freqs_hz"]}))
    k_lo = math.ceil(p["f_min_hz"] * period - 1e-9)
    k_hi = math.floor(p["f_max_hz"] * period + 1e-9)
    k_lo = max(k_lo, 1)
    return np.arange(k_lo, k_hi + 1) if k_hi >= k_lo else np.arange(0)


def multisine_weights(p: dict, harmonics: np.ndarray) -> np.ndarray:
    """Relative speed amplitude of each tone: 1 (``spectrum: speed``) or k_min/k
    (``spectrum: acceleration``: every tone asks the same acceleration, so the same current)."""
    k = np.asarray(harmonics, float)
    if p.get("spectrum", "speed") == "acceleration" and len(k):
        return k.min() / k
    return np.ones(len(k))


def multisine_phases(p: dict, harmonics: np.ndarray) -> np.ndarray:
    """Tone phases (speed tones are sin(2 pi k t / period + phi_k); their derivatives
    cos(... + phi_k) share them)."""
    n = len(harmonics)
    if p["phases"] == "random":
        return np.random.default_rng(p["seed"]).uniform(-np.pi, np.pi, n)
    if p["phases"] == "clipped":
        k = tuple(int(x) for x in harmonics)
        w = multisine_weights(p, harmonics) * np.asarray(harmonics, float)   # acceleration amplitudes
        return np.array(clipped_phases(k, tuple(float(x) for x in w / w.max())))
    k = np.arange(1, n + 1)
    return -np.pi * k * (k - 1) / n    # Schroeder (1970), low crest factor


def schroeder_phases(power: np.ndarray) -> np.ndarray:
    """Schroeder (1970) phases for tones with relative powers ``power`` (any spectrum):
    phi_k = -2 pi sum_{l<k} (k - l) p_l, p normalised to sum 1 (flat: -pi k (k-1)/n)."""
    p = np.asarray(power, float) / np.sum(power)
    n = len(p)
    return np.array([-2 * np.pi * sum((k - l) * p[l] for l in range(k)) for k in range(n)])


@functools.lru_cache(maxsize=256)
def clipped_phases(harmonics: tuple, amplitudes: tuple, iterations: int = 300) -> tuple:
    """Phases minimising the crest factor of ``sum a_k cos(2 pi k u + phi_k)`` by iterative
    clipping (Van der Ouderaa, Schoukens & Renneboog 1988; Pintelon & Schoukens,
    *System Identification: A Frequency Domain Approach*, 2nd ed., sec. 5.4): start at
    Schroeder's phases, clip the signal at a level just below its peak, keep the phases
    of the clipped signal's excited harmonics (amplitudes unchanged), repeat; the best
    iterate is kept. Deterministic, so a profile renders the same command everywhere."""
    k = np.asarray(harmonics, int)
    a = np.asarray(amplitudes, float)
    if len(k) < 2:
        return tuple(0.0 for _ in k)
    m = int(2 ** np.ceil(np.log2(max(1024, 16 * int(k.max())))))
    phi = schroeder_phases(a * a)
    best, best_cf = phi.copy(), np.inf
    spec = np.zeros(m // 2 + 1, complex)
    level = 0.95
    for _ in range(iterations):
        spec[:] = 0
        spec[k] = a * np.exp(1j * phi) * (m / 2)
        x = np.fft.irfft(spec, m)
        peak = float(np.max(np.abs(x)))
        cf = peak / float(np.sqrt(np.mean(x * x)))
        if cf < best_cf - 1e-9:
            best, best_cf = phi.copy(), cf
        else:
            level = max(0.7, level - 0.01)   # stalled: clip harder
        phi = np.angle(np.fft.rfft(np.clip(x, -level * peak, level * peak))[k])
    return tuple(float(x) for x in best)


@functools.lru_cache(maxsize=64)
def _multisine_peak(harmonics: tuple, phases: tuple, weights: tuple | None = None) -> float:
    """Peak of sum_k w_k sin(2 pi k u + phi_k) over one period u in [0, 1) (independent of period_s)."""
    u = np.linspace(0.0, 1.0, min(200_000, max(4096, 40 * max(harmonics))), endpoint=False)
    acc = np.zeros_like(u)
    weights = weights or (1.0,) * len(harmonics)
    for k, ph, w in zip(harmonics, phases, weights):
        acc += w * np.sin(2 * np.pi * k * u + ph)
    return float(np.max(np.abs(acc)))


def _multisine_unit(p, t):
    """Sum of the tones (relative amplitudes ``multisine_weights``), scaled so its peak
    over one period is 1."""
    k = multisine_harmonics(p)
    phi = multisine_phases(p, k)
    w = multisine_weights(p, k)
    wt = None if np.all(w == 1.0) else tuple(float(x) for x in w)
    peak = _multisine_peak(tuple(int(x) for x in k), tuple(float(x) for x in phi), wt)
    acc = np.zeros_like(t)
    for kk, ph, ww in zip(k, phi, w):   # loop over tones: memory stays O(len(t))
        acc += ww * np.sin(2 * np.pi * kk * t / p["period_s"] + ph)
    return acc / peak


def _multisine(p, t):
    return p["offset"] + p["amplitude"] * _multisine_unit(p, t)


def _chirp(p, t):
    s, f0, f1 = p["t1_s"], p["f0_hz"], p["f1_hz"]
    tau = np.mod(t, s) if p["repeat"] else np.clip(t, 0.0, s)
    if p["method"] == "log" and f1 != f0:
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


@functools.lru_cache(maxsize=16)
def prbs_bits(order: int, seed: int = 0) -> np.ndarray:
    """One period (2^order - 1 bits, 0/1) of a maximum-length sequence (read-only, cached)."""
    n = 2 ** order - 1
    state = seed % n + 1   # any non-zero start state
    bits = np.empty(n, dtype=np.int8)
    taps = _TAPS[order]
    for i in range(n):
        bits[i] = state & 1
        fb = 0
        for tap in taps:
            fb ^= (state >> (order - tap)) & 1
        state = (state >> 1) | (fb << (order - 1))
    bits.setflags(write=False)
    return bits


def _prbs(p, t):
    bits = prbs_bits(p["order"], p["seed"])
    idx = np.floor(np.maximum(t, 0.0) / p["bit_s"] + 1e-9).astype(np.int64) % len(bits)
    return p["offset"] + p["amplitude"] * (2.0 * bits[idx] - 1.0)


_RENDER = {"constant": _constant, "step": _step, "ramp": _ramp, "trapezoid": _trapezoid,
           "multisine": _multisine, "chirp": _chirp, "prbs": _prbs}
