"""Calibration excitation designed for the Kt estimate (optimal input design).

Kt comes from two velocity-mode runs of the same speed command, motor alone (b2~ =
Kt/J) and with the disk j (b2^ = Kt/(J + j)), each fitted by ``identify_default``:

    θ'' = b2 i − (D/J) θ' − (Tc/J) s(θ') + τ b2 i' (+ cogging)          (regression)

after one low-pass FIR F (cutoff f_c) on every signal. This module predicts, for a
candidate multisine, the variance of that least-squares estimate before anything
moves, and chooses the multisine that makes Kt's variance per bench second smallest
within the drive's limits. No I/O.

Noise (the equation error, in rad/s², per sample, two-sided power spectral density
s_e(ν), ν = f·T cycles per sample, T the sample period):

    s_e(ν) = (q²/12)·(2 − 2 cos 2πν)²/T⁴  +  b2²·(σ_i² + r_i²/12)·((10 + 2 cos 2πν)/12)²

* encoder quantisation q = 2π/counts_per_rev (white, q²/12) through the central second
  difference, which grows as (2πf)⁴ — double differentiation;
* current noise σ_i and current quantum r_i through the 3-tap match the analysis
  applies to the current, scaled to acceleration by b2 (b2·i is what the angle sees).

Information (Fisher information of the regression, Mehra 1974; Goodwin & Payne,
*Dynamic System Identification*, 1977, ch. 6; Pintelon & Schoukens, *System
Identification: A Frequency Domain Approach*, 2nd ed., 2012, ch. 5): in velocity mode
i = ((J + j)·a + D ω + Tc)/Kt. The speed, Coulomb (constant: forward rotation only)
and lag columns take away the D ω and Tc parts and almost nothing of the inertial
part (a is orthogonal to ω and to a' over whole periods), so the regressor that
carries b2 is i⊥ ≈ a/b2. For a periodic excitation with acceleration tones of power
P_k (amplitude²/2) at f_k, N samples and the filter's gain F_k, the least-squares
(sandwich) variance the analysis itself reports is

    Var(b2)/b2² = Σ_k F_k⁴ P_k s_e(ν_k) / (N (Σ_k F_k² P_k)²)                (eq. D1)

(LS weighs tones by power, not by P_k/s_e as the Cramér–Rao bound would; this is
the estimator that runs). Below the encoder/current noise crossover (tens of Hz for
typical servo motors) s_e is flat and eq. D1 is σ_i²/(N·rms(i⊥)²): **the information
is the rms inertial current**. The two runs combine by the corrected eq. 17,

    Var(Kt)/Kt² = (J/j)²·r~² + ((J + j)/j)²·r^²                             (eq. D2)

r~, r^ the runs' relative b2 standard deviations.

Design rule (``design_multisine``): the peak current is Kt i = (J + j)·a + D ω + Tc
≤ peak_current_fraction·current_limit_a·Kt for the heavier (disk) run, the rms current
≤ rms_current_fraction·rated_current_a, and the speed stays in (min_speed, max_speed)
so it never reverses (Coulomb stays a constant the sign column absorbs). With the
current limit binding, rms(a) = a_peak/CF_a: minimise the acceleration's crest factor
CF_a — equal acceleration per tone (speed tones ∝ 1/f) with phases from iterative
clipping (Van der Ouderaa, Schoukens & Renneboog 1988; better than Schroeder 1970's
for the acceleration). With the speed range binding (low tones), a = 2πf·ω̃: raise the
band until the current limit binds, i.e. put the band just above the corner
f* ≈ a_max/(2π·Δω) where both limits bind. Above the corner more bandwidth buys no
information (flat s_e) but costs tracking (the drive's speed loop) and model error,
so among candidates within ``TIE_REL`` of the best the lowest band wins. Whole
periods fit the run (period_s divides duration_s) so no tone leaks.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from . import waveforms as wf
from ..analysis import derivatives as dv

TIE_REL = 0.03               # candidates this close to the best variance count as equal
PERIOD_RANGE_S = (0.25, 2.0)  # multisine periods searched (whole periods per run)
MAX_DESIGN_TONES = 16
FADE_CHOICES_S = (0.2, 0.3, 0.5, 0.75, 1.0, 1.5, 2.0)
STAGE2 = 8                    # candidates refined with clipped phases
COVER_MARGIN = 0.025          # a covering sweep reaches this share of its span beyond the cover


@dataclass(frozen=True)
class MotorCase:
    """What the design assumes about one motor, its drive, sensors and disk (SI units).

    Limits: ``peak_current_a`` (design ceiling for |i|), ``rms_current_a`` (None: no
    thermal ceiling), ``min_speed_rad_s``/``max_speed_rad_s`` (forward-only band)."""

    kt_nm_a: float
    rotor_inertia_kgm2: float
    disk_inertia_kgm2: float
    peak_current_a: float
    min_speed_rad_s: float
    max_speed_rad_s: float
    rms_current_a: float | None = None
    viscous_nms_rad: float = 0.0
    friction_nm: float = 0.0
    current_noise_a: float = 0.004
    current_resolution_a: float = 0.0
    counts_per_rev: int = 10000
    name: str = "motor"


@dataclass(frozen=True)
class Prediction:
    """Predicted outcome of one calibration (two runs of ``duration_s``) on one motor."""

    b2_rel_std_unloaded: float
    b2_rel_std_loaded: float
    kt_rel_std: float                  # statistical part, both runs
    kt_rel_std_per_sqrt_s: float       # kt_rel_std · sqrt(bench seconds of both runs)
    peak_current_a: float              # loaded run (the heavier), incl. the fade-in
    rms_current_a: float               # loaded run, one steady period
    speed_range_rad_s: tuple[float, float]
    duration_s: float

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}


@dataclass(frozen=True)
class Design:
    """A designed multisine: ``params`` in the profile's multisine vocabulary (complete),
    the prediction per motor case, and which limit set the amplitude."""

    params: dict
    predictions: dict                  # case name -> Prediction
    binding: str                       # "peak current" | "rms current" | "speed range"
    acceleration_crest_factor: float
    candidates: int
    notes: tuple = field(default_factory=tuple)


# --------------------------------------------------------------------------- noise
def equation_error_psd(freq_hz, *, b2: float, current_noise_a: float, counts_per_rev: int,
                       period_s: float, current_resolution_a: float = 0.0) -> np.ndarray:
    """s_e(ν) of the module docstring, (rad/s²)² per unit ν (two-sided, per sample)."""
    x = 2 * np.pi * np.asarray(freq_hz, float) * period_s
    q = 2 * np.pi / counts_per_rev
    enc = q * q / 12.0 * (2 - 2 * np.cos(x)) ** 2 / period_s ** 4
    cur = b2 * b2 * (current_noise_a ** 2 + current_resolution_a ** 2 / 12.0) \
        * ((10 + 2 * np.cos(x)) / 12.0) ** 2
    return enc + cur


def analysis_filter(period_s: float, cutoff_hz: float | None = None) -> np.ndarray:
    """The FIR a calibration applies (``calibration.calibrate_motor``: min(40 Hz, rate/10))."""
    rate = 1.0 / period_s
    return dv.lowpass_fir(cutoff_hz or dv.rate_cutoff(rate), rate)


def filter_gain(taps: np.ndarray, freq_hz, period_s: float) -> np.ndarray:
    """|F(f)| of the zero-phase FIR."""
    x = 2 * np.pi * np.asarray(freq_hz, float)[..., None] * period_s
    n = np.arange(len(taps)) - (len(taps) - 1) / 2
    return np.abs(np.cos(x * n) @ taps)


def tone_b2_rel_variance(freq_hz, accel_power, *, b2: float, n_samples: int, case: MotorCase,
                         period_s: float, gain=None) -> float:
    """Eq. D1: Var(b2)/b2² from the acceleration tones' powers P_k (amplitude²/2)."""
    p = np.asarray(accel_power, float)
    g2 = np.ones_like(p) if gain is None else np.asarray(gain, float) ** 2
    s = equation_error_psd(freq_hz, b2=b2, current_noise_a=case.current_noise_a,
                           counts_per_rev=case.counts_per_rev, period_s=period_s,
                           current_resolution_a=case.current_resolution_a)
    den = float(np.sum(g2 * p)) ** 2 * n_samples
    return float(np.sum(g2 * g2 * p * s)) / den if den > 0 else math.inf


def kt_rel_variance(b2_rel_var_unloaded: float, b2_rel_var_loaded: float, rotor_inertia_kgm2: float,
                    disk_inertia_kgm2: float) -> float:
    """Eq. D2 (first-order propagation through the corrected eq. 17)."""
    J, j = rotor_inertia_kgm2, disk_inertia_kgm2
    return (J / j) ** 2 * b2_rel_var_unloaded + ((J + j) / j) ** 2 * b2_rel_var_loaded


# ---------------------------------------------------------------- time-domain check
def run_b2_rel_std(speed_rad_s: np.ndarray, period_s: float, case: MotorCase, *, loaded: bool,
                   cutoff_hz: float | None = None) -> float:
    """Relative std of b2 for one run of ``speed_rad_s`` (tracked ideally), through the
    analysis's own filter and regressor set (current, speed, Coulomb, lag), with the
    coloured equation error s_e: Var = r'Σr/(r'r)², r the filtered current's part not
    explained by the other columns (Frisch–Waugh), r'Σr from its spectrum."""
    J = case.rotor_inertia_kgm2 + (case.disk_inertia_kgm2 if loaded else 0.0)
    b2 = case.kt_nm_a / J
    w = np.asarray(speed_rad_s, float)
    a = np.gradient(w, period_s)
    i = (J * a + case.viscous_nms_rad * w + case.friction_nm * np.sign(w)) / case.kt_nm_a
    taps = analysis_filter(period_s, cutoff_hz)
    if len(w) < len(taps) + 50:
        return math.inf
    cols = [dv.filter_valid(x, taps) for x in (i, w, np.sign(w))]
    cols.append(np.gradient(cols[0], period_s))
    X = np.vstack(cols[1:]).T
    r = cols[0] - X @ np.linalg.lstsq(X, cols[0], rcond=None)[0]
    n = len(r)
    R2 = np.abs(np.fft.rfft(r)) ** 2
    f = np.fft.rfftfreq(n, period_s)
    s = equation_error_psd(f, b2=b2, current_noise_a=case.current_noise_a,
                           counts_per_rev=case.counts_per_rev, period_s=period_s,
                           current_resolution_a=case.current_resolution_a)
    s = s * filter_gain(taps, f, period_s) ** 2
    weight = np.full(len(f), 2.0)          # rfft: every bin but DC (and Nyquist) twice
    weight[0] = 1.0
    if n % 2 == 0:
        weight[-1] = 1.0
    num = float(np.sum(weight * R2 * s)) / n
    den = float(r @ r) ** 2
    return math.sqrt(num / den) / b2 if den > 0 else math.inf


def predict_calibration(kind: str, params: dict, case: MotorCase, *, duration_s: float,
                        period_s: float, cutoff_hz: float | None = None) -> Prediction:
    """Predicted Kt relative std of a calibration with the waveform ``kind``/``params``
    (profile vocabulary) run ``duration_s`` alone and ``duration_s`` with the disk."""
    n = int(round(duration_s / period_s))
    w = wf.render(kind, params, np.arange(n) * period_s)
    return predict_command(w, case, period_s=period_s, natural_period_s=wf.natural_period_s(kind, params),
                           cutoff_hz=cutoff_hz)


def predict_command(w: np.ndarray, case: MotorCase, *, period_s: float,
                    natural_period_s: float | None = None, cutoff_hz: float | None = None) -> Prediction:
    """``predict_calibration`` for a speed command given sample by sample."""
    duration_s = len(w) * period_s
    ru = run_b2_rel_std(w, period_s, case, loaded=False, cutoff_hz=cutoff_hz)
    rl = run_b2_rel_std(w, period_s, case, loaded=True, cutoff_hz=cutoff_hz)
    kt = math.sqrt(kt_rel_variance(ru * ru, rl * rl, case.rotor_inertia_kgm2, case.disk_inertia_kgm2))
    i = _current(w, period_s, case, loaded=True)
    nat = natural_period_s
    last = slice(-int(round(nat / period_s)), None) if nat and nat < duration_s else slice(None)
    return Prediction(ru, rl, kt, kt * math.sqrt(2 * duration_s), float(np.max(np.abs(i))),
                      float(np.sqrt(np.mean(i[last] ** 2))),
                      (float(np.min(w[last])), float(np.max(w))), duration_s)


def _current(w, period_s, case: MotorCase, *, loaded: bool) -> np.ndarray:
    J = case.rotor_inertia_kgm2 + (case.disk_inertia_kgm2 if loaded else 0.0)
    a = np.gradient(w, period_s)
    return (J * a + case.viscous_nms_rad * w + case.friction_nm * np.sign(w)) / case.kt_nm_a


# ------------------------------------------------------------------------- design
@dataclass(frozen=True)
class _Shape:
    """A unit multisine over one period: speed u (peak 1) and du/dt per s."""

    harmonics: tuple
    spectrum: str
    phases: str
    period_s: float
    u: np.ndarray
    du: np.ndarray
    accel_amp: np.ndarray            # per tone, for A = 1


def _shape(harmonics: np.ndarray, period: float, spectrum: str, phases: str) -> _Shape:
    p = {"spectrum": spectrum, "phases": phases, "seed": 0}
    k = np.asarray(harmonics)
    wts = wf.multisine_weights(p, k)
    phi = wf.multisine_phases(p, k)
    m = int(2 ** math.ceil(math.log2(max(512, 16 * int(k.max())))))
    spec = np.zeros(m // 2 + 1, complex)
    # speed: sum w sin(2 pi k u + phi) = Re sum w e^{i(2 pi k u + phi - pi/2)}
    spec[k] = wts * np.exp(1j * (phi - np.pi / 2)) * (m / 2)
    u = np.fft.irfft(spec, m)
    spec[k] = spec[k] * (1j * 2 * np.pi * k / period)
    du = np.fft.irfft(spec, m)
    peak = float(np.max(np.abs(u)))
    return _Shape(tuple(int(x) for x in k), spectrum, phases, period, u / peak, du / peak,
                  wts / peak * 2 * np.pi * k / period)


def _amplitude(shape: _Shape, cases, offset: float, half_range: float):
    """Largest amplitude within every case's limits, and which limit set it."""
    best, why = half_range, "speed range"
    for c in cases:
        Jt = c.rotor_inertia_kgm2 + c.disk_inertia_kgm2
        base = (c.friction_nm + c.viscous_nms_rad * offset) / c.kt_nm_a   # at A = 0
        slope = (Jt * shape.du + c.viscous_nms_rad * shape.u) / c.kt_nm_a  # per unit A
        top = float(np.max(np.abs(slope)))
        if top > 0:
            a_peak = (c.peak_current_a - base) / top
            if a_peak < best:
                best, why = a_peak, "peak current"
        if c.rms_current_a is not None:
            # mean((base + A s)^2) = rms^2  ->  A (s > 0 root of a quadratic)
            m2 = float(np.mean(slope * slope))
            m1 = float(np.mean(slope)) * base
            disc = m1 * m1 - m2 * (base * base - c.rms_current_a ** 2)
            if m2 > 0 and disc >= 0:
                a_rms = (-m1 + math.sqrt(disc)) / m2
                if a_rms < best:
                    best, why = a_rms, "rms current"
    return best, why


def _place(shape: _Shape, cases, w_lo: float, w_hi: float, cover):
    """Amplitude, limiting limit and offset of ``shape`` inside the band [w_lo, w_hi]:
    offset at the band's centre; or, with ``cover`` = (lo, hi), speeds the run must
    sweep through (the efficiency map's, so no motor loss is extrapolated there), the
    offset moved as little as the cover needs and the amplitude lowered where the sweep
    would leave the band below the cover. None when the current-limited swing cannot
    cover it."""
    offset, half = (w_lo + w_hi) / 2, (w_hi - w_lo) / 2
    amp, why = _amplitude(shape, cases, offset, half)
    if cover is None or amp <= 0:
        return amp, why, offset
    # extremes of the unit shape, 0.5 % wide: the rendered command peaks a little past the grid's
    u_lo, u_hi = 1.005 * float(np.min(shape.u)), 1.005 * float(np.max(shape.u))
    # the swept range counts as covered COVER_MARGIN of its span inside its ends (coverage.MARGIN)
    c_lo, c_hi = u_lo + COVER_MARGIN * (u_hi - u_lo), u_hi - COVER_MARGIN * (u_hi - u_lo)
    # offset o with cover[1] <= o + A c_hi, o + A c_lo <= cover[0], w_lo <= o + A u_lo, o + A u_hi <= w_hi
    room = min((cover[0] - w_lo) / (c_lo - u_lo), (w_hi - w_lo) / (u_hi - u_lo))
    if room < amp:
        amp, why = room, "speed range"
    for _ in range(2):     # the offset moves the friction part of the peak current: twice
        if amp * (c_hi - c_lo) < cover[1] - cover[0]:
            return None
        o_lo = max(cover[1] - amp * c_hi, w_lo - amp * u_lo)
        o_hi = min(cover[0] - amp * c_lo, w_hi - amp * u_hi)
        offset = float(np.clip((w_lo + w_hi) / 2, o_lo, min(o_hi, max(o_lo, o_hi))))
        amp2, why2 = _amplitude(shape, cases, offset, math.inf)
        if amp2 >= amp * (1 - 1e-9):
            return amp, why, offset
        amp, why = amp2, why2
    return None


def _objective(shape: _Shape, amplitude: float, cases, duration_s, period_s, taps) -> float:
    """max over cases of predicted Var(Kt)/Kt² · bench seconds (eq. D1, D2)."""
    freqs = np.asarray(shape.harmonics) / shape.period_s
    power = (amplitude * shape.accel_amp) ** 2 / 2
    gain = filter_gain(taps, freqs, period_s)
    n = int(round(duration_s / period_s)) - len(taps)
    worst = 0.0
    for c in cases:
        r = []
        for jt in (c.rotor_inertia_kgm2, c.rotor_inertia_kgm2 + c.disk_inertia_kgm2):
            r.append(tone_b2_rel_variance(freqs, power, b2=c.kt_nm_a / jt, n_samples=n, case=c,
                                          period_s=period_s, gain=gain))
        worst = max(worst, kt_rel_variance(r[0], r[1], c.rotor_inertia_kgm2, c.disk_inertia_kgm2)
                    * 2 * duration_s)
    return worst


def candidate_periods(duration_s: float, also_fit_s=()) -> list[float]:
    """Periods that fit a whole number of times into the run (and into each of
    ``also_fit_s``), within ``PERIOD_RANGE_S``."""
    lo, hi = PERIOD_RANGE_S
    out = [duration_s / m for m in range(1, int(duration_s / lo) + 1)
           if lo - 1e-9 <= duration_s / m <= hi + 1e-9]
    fits = [p for p in out if all(abs(d / p - round(d / p)) < 1e-6 for d in also_fit_s)]
    return fits or out or [duration_s]


def design_multisine(cases, *, duration_s: float, period_s: float, max_tone_hz: float = 10.0,
                     min_fade_s: float = 0.2, cutoff_hz: float | None = None,
                     also_fit_s=(), cover_rad_s: tuple | None = None, min_tones: int = 2) -> Design:
    """The multisine (velocity command) with the smallest predicted Var(Kt) per bench
    second for every case in ``cases`` (one waveform, several motors: every case's
    limits hold, the worst case's variance is minimised). Search: period (whole
    periods per run), contiguous band k_lo..k_hi of its harmonics up to
    ``max_tone_hz``, tone spectrum (equal speed or equal acceleration); amplitude from
    the limits (``_amplitude``), offset at the centre of the common speed range; then
    the best ``STAGE2`` get clipped (crest-minimised) phases, ties go to the lowest
    band, and the raised-cosine fade-in is lengthened until the start-up also stays
    within the peak current. ``also_fit_s``: other run lengths the period must divide.
    ``cover_rad_s`` = (lo, hi): speeds every steady period must sweep through (the map's,
    ``coverage.map_speed_range``): candidates whose current-limited swing cannot are
    dropped, the offset moves off the band's centre as far as the cover needs (``_place``).
    ``min_tones``: fewest tones per candidate (a few more than two spread the fit's model
    error over more frequencies). Raises ValueError naming an impossible limit."""
    cases = list(cases)
    w_lo = max(c.min_speed_rad_s for c in cases)
    w_hi = min(c.max_speed_rad_s for c in cases)
    if not w_hi > w_lo:
        raise ValueError(f"no speed band: min speed {w_lo:g} rad/s is not below max speed {w_hi:g} rad/s")
    for c in cases:
        if c.friction_nm + c.viscous_nms_rad * w_hi >= c.peak_current_a * c.kt_nm_a:
            raise ValueError(f"{c.name}: the expected friction alone needs the whole peak current")
    if cover_rad_s is not None:
        cover_rad_s = (float(min(cover_rad_s)), float(max(cover_rad_s)))
        if not (w_lo <= cover_rad_s[0] and cover_rad_s[1] <= w_hi):
            raise ValueError(f"the speeds to cover, {cover_rad_s[0]:g}-{cover_rad_s[1]:g} rad/s, are not "
                             f"inside the speed band {w_lo:g}-{w_hi:g} rad/s")
    nyq = 0.5 / period_s
    top_hz = min(max_tone_hz, 0.45 * (cutoff_hz or min(40.0, 0.1 / period_s)), 0.9 * nyq)
    taps = analysis_filter(period_s, cutoff_hz)
    scored = []
    for period in candidate_periods(duration_s, also_fit_s):
        kmax = int(math.floor(top_hz * period + 1e-9))
        for k_lo in range(1, kmax):
            for k_hi in range(k_lo + max(min_tones, 2) - 1, min(kmax, k_lo + MAX_DESIGN_TONES - 1) + 1):
                for spectrum in ("acceleration", "speed"):
                    sh = _shape(np.arange(k_lo, k_hi + 1), period, spectrum, "schroeder")
                    placed = _place(sh, cases, w_lo, w_hi, cover_rad_s)
                    if placed is None or placed[0] <= 0:
                        continue
                    scored.append((_objective(sh, placed[0], cases, duration_s, period_s, taps), sh))
    if not scored:
        need = (f" sweeping {cover_rad_s[0]:g}-{cover_rad_s[1]:g} rad/s within the current limit"
                if cover_rad_s else "")
        raise ValueError(f"no multisine fits{need}: tones up to {top_hz:g} Hz and periods "
                         f"{PERIOD_RANGE_S[0]:g}-{PERIOD_RANGE_S[1]:g} s need a longer run")
    scored.sort(key=lambda x: x[0])
    refined = []
    for _, sh in scored[:STAGE2]:
        for phases in ("clipped", "schroeder"):
            s2 = _shape(np.asarray(sh.harmonics), sh.period_s, sh.spectrum, phases)
            placed = _place(s2, cases, w_lo, w_hi, cover_rad_s)
            if placed is None or placed[0] <= 0:
                continue
            amp, why, off = placed
            refined.append((_objective(s2, amp, cases, duration_s, period_s, taps), s2, amp, why, off))
    best = min(r[0] for r in refined)
    ties = [r for r in refined if r[0] <= best * (1 + TIE_REL)]
    _, sh, amp, why, offset = min(ties, key=lambda r: (max(r[1].harmonics) / r[1].period_s, r[0]))
    params = {"offset": float(offset), "amplitude": float(amp), "period_s": float(sh.period_s),
              "f_min_hz": min(sh.harmonics) / sh.period_s, "f_max_hz": max(sh.harmonics) / sh.period_s,
              "freqs_hz": None,
              "phases": sh.phases, "seed": 0, "spectrum": sh.spectrum, "fade_in_s": min_fade_s}
    params["fade_in_s"], fade_ok = _fade(params, cases, duration_s, period_s, min_fade_s)
    notes = () if fade_ok else (f"the fade-in cannot keep the start-up below the peak current "
                                f"within {FADE_CHOICES_S[-1]:g} s",)
    preds = {c.name: predict_calibration("multisine", params, c, duration_s=duration_s,
                                         period_s=period_s, cutoff_hz=cutoff_hz) for c in cases}
    acc = sh.du
    return Design(params, preds, why, float(np.max(np.abs(acc)) / np.sqrt(np.mean(acc * acc))),
                  len(scored), notes)


def _fade(params, cases, duration_s, period_s, min_fade_s):
    """Shortest fade-in (from ``FADE_CHOICES_S``, at least ``min_fade_s`` and at most half
    the run) whose start-up stays within every case's peak current."""
    choices = [f for f in FADE_CHOICES_S if f >= min_fade_s - 1e-12] or [min_fade_s]
    choices = [f for f in choices if f <= 0.5 * duration_s] or [min_fade_s]
    for fade in choices:
        p = {**params, "fade_in_s": fade}
        n = int(round(min(duration_s, fade + params["period_s"]) / period_s))
        w = wf.render("multisine", p, np.arange(n) * period_s)
        if all(np.max(np.abs(_current(w, period_s, c, loaded=True))) <= c.peak_current_a * (1 + 1e-6)
               for c in cases):
            return fade, True
    return choices[-1], False


def multisine_summary(params: dict) -> str:
    """One line: the multisine in profile words."""
    k = wf.multisine_harmonics(params)
    band = f"{k.min() / params['period_s']:g}-{k.max() / params['period_s']:g} Hz ({len(k)} tones)"
    return (f"offset {params['offset']:.4g} rad/s, amplitude {params['amplitude']:.4g} rad/s, "
            f"period {params['period_s']:g} s, tones {band}, phases {params['phases']}, "
            f"spectrum {params.get('spectrum', 'speed')}, fade-in {params.get('fade_in_s', 0):g} s")

