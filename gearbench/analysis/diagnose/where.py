"""Where the nominal model misses: residual breakdown against the noise floor.

Two residuals of the nominal model:
  * simulation error e (velocity, short re-initialised horizons over the whole trace),
    whose floor at horizon step m is var e(m) from simerror.noise_floor;
  * equation error r = alpha_meas - alpha_model (SG second derivative of the angle),
    whose floor is the current noise through Kt/J plus the angle noise through the
    second-derivative filter.
Cells: time window, speed band (near zero, reversals, low/mid/high), rotor-angle
order (position-periodic content of r), frequency band (r's spectrum), current
level and acceleration level.  ``ratio`` = rms / floor; ``above_floor`` = ratio > 1.5.
"""
from __future__ import annotations

import numpy as np
from scipy.signal import savgol_filter, welch

from . import simerror
from .effects import Base
from .nominal import VELOCITY_WINDOW, Model, Signals, measured_features

ABOVE = 1.5
ORDERS = 36
BANDS_HZ = (0.0, 1.0, 5.0, 20.0, 50.0, 150.0, np.inf)


def _cell(dim, label, e2, floor2, n=None) -> dict:
    rms, fl = float(np.sqrt(np.mean(e2))), float(np.sqrt(np.mean(floor2)))
    ratio = rms / fl if fl > 0 else float("inf")
    return {"dimension": dim, "label": label, "n": int(n if n is not None else np.size(e2)),
            "rms": rms, "floor": fl, "ratio": ratio, "above_floor": bool(ratio > ABOVE)}


def _terciles(x):
    q = np.quantile(x, [1 / 3, 2 / 3])
    return [("low", x <= q[0]), ("mid", (x > q[0]) & (x <= q[1])), ("high", x > q[1])]


def breakdown(sig: Signals, nom: Model, err_score, score_starts, floor: simerror.NoiseFloor):
    """Residual cells (list of dicts) and 2-D maps for plotting."""
    n, dt = len(sig), sig.dt_s
    H = err_score.shape[1]
    starts = np.arange(0, n - H - 1, H)
    err = simerror.simulate(sig, nom, starts, H)
    idx = (starts[:, None] + 1 + np.arange(H)[None, :]).ravel()
    e2 = err.ravel() ** 2
    f2 = np.broadcast_to(floor.floor_var[None, :], err.shape).ravel()
    w, i, th = sig.velocity_rad_s[idx], sig.current_a[idx], sig.position_rad[idx]
    acc_all = savgol_filter(sig.position_rad, VELOCITY_WINDOW, 2, deriv=2, delta=dt)
    acc = acc_all[idx]
    cells = []

    # time windows
    edges = np.linspace(sig.time_s[0], sig.time_s[-1], 11)
    t = sig.time_s[idx]
    for a, b in zip(edges[:-1], edges[1:]):
        m = (t >= a) & (t < b)
        if m.any():
            cells.append(_cell("time", f"{a:.2f}-{b:.2f} s", e2[m], f2[m]))

    # speed bands, near zero and reversals first
    wmax = float(np.max(np.abs(sig.velocity_rad_s)))
    near = np.abs(w) < max(5 * floor.velocity_noise_rad_s, 0.02 * wmax)
    sgn = np.sign(sig.velocity_rad_s)
    rev_idx = np.flatnonzero(sgn[1:] * sgn[:-1] < 0)
    rev = np.zeros(n, bool)
    half = int(round(0.025 / dt))
    for r in rev_idx:
        rev[max(r - half, 0):r + half + 1] = True
    rev = rev[idx]
    if near.any():
        cells.append(_cell("speed", "near zero", e2[near], f2[near]))
    if rev.any():
        cells.append(_cell("speed", "reversals (+-25 ms)", e2[rev], f2[rev]))
    rest = ~(near | rev)
    if rest.sum() > 30:
        aw = np.abs(w[rest])
        for lab, m in _terciles(aw):
            cells.append(_cell("speed", f"|w| {lab} ({aw[m].min():.3g}-{aw[m].max():.3g} units/s)",
                               e2[rest][m], f2[rest][m]))

    # current and acceleration level
    for dim, x in (("current", np.abs(i)), ("acceleration", np.abs(acc))):
        for lab, m in _terciles(x):
            cells.append(_cell(dim, f"{lab} ({x[m].min():.3g}-{x[m].max():.3g})", e2[m], f2[m]))

    # equation error: rotor-angle orders and frequency bands
    F = measured_features(sig, nom.terms)
    r = acc_all - F @ nom.coef
    r = r[VELOCITY_WINDOW:-VELOCITY_WINDOW - 1]
    # rotor angle in radians (orders are per revolution); none when the unit is unknown
    k_ang = sig.rad_per_unit
    theta = sig.position_rad[VELOCITY_WINDOW:-VELOCITY_WINDOW - 1] * (k_ang or 0.0)
    kt_j = abs(Base(given=None).kt_over_j(nom)) if "scale" not in nom.names else abs(
        nom.terms[0].kt_over_j * nom.params()["scale"])
    h2 = savgol_filter(np.eye(VELOCITY_WINDOW)[VELOCITY_WINDOW // 2], VELOCITY_WINDOW, 2,
                       deriv=2) / dt ** 2
    s_th = floor.velocity_noise_rad_s / simerror.velocity_noise(1.0, dt)
    freqs, psd = welch(r, fs=1 / dt, nperseg=min(len(r), 2048))
    h2f = np.abs(np.fft.rfft(h2, n=2 * (len(freqs) - 1)))[:len(freqs)]
    floor_psd = 2 * dt * ((kt_j * floor.current_noise_a) ** 2 + (s_th * h2f) ** 2)
    df = freqs[1] - freqs[0]
    for a, b in zip(BANDS_HZ[:-1], BANDS_HZ[1:]):
        m = (freqs >= a) & (freqs < b)
        if m.any():
            cells.append(_cell("frequency", f"{a:g}-{b:g} Hz", [np.sum(psd[m]) * df],
                               [np.sum(floor_psd[m]) * df], n=int(m.sum())))
    # position-periodic content: amplitude of order N vs what white residual would give
    rv = float(np.var(r))
    expected = np.sqrt(rv * 2.0 / len(r)) * np.sqrt(np.pi / 2)  # mean Rayleigh amplitude
    amps = []
    for N in range(1, ORDERS + 1):
        c = 2 * np.mean(r * np.exp(-1j * N * theta))
        amps.append(abs(c))
    amps = np.array(amps)
    for N in (np.argsort(amps)[::-1][:5] + 1 if k_ang else ()):
        cells.append(_cell("angle_order", f"order {N}", [amps[N - 1] ** 2], [expected ** 2]))

    maps = {"horizon_error_rad_s": err,
            "speed_angle_rms": _map2(np.abs(w), np.mod(th * (k_ang or 1.0), 2 * np.pi), e2, 24, 36),
            "speed_current_rms": _map2(np.abs(w), i, e2, 24, 24),
            "floor_rad_s": np.sqrt(floor.mse),
            # value ranges the map bins span (axes of the report's heat maps)
            "speed_range_rad_s": _range(np.abs(w)), "angle_range_rad": _range(np.mod(th * (k_ang or 1.0), 2 * np.pi)),
            "current_range_a": _range(i),
            "sample_index": idx, "error_flat": err.ravel(), "time_s": sig.time_s[idx],
            "equation_error": r, "ee_time_s": sig.time_s[VELOCITY_WINDOW:-VELOCITY_WINDOW - 1]}
    return cells, maps


def _range(x) -> tuple[float, float]:
    return (float(np.min(x)), float(np.max(x))) if np.size(x) else (0.0, 1.0)


def _map2(x, y, v, nx, ny):
    """RMS of v binned on (x, y): rows = y bins, columns = x bins; NaN where empty."""
    xi = np.clip(((x - x.min()) / (np.ptp(x) or 1) * nx).astype(int), 0, nx - 1)
    yi = np.clip(((y - y.min()) / (np.ptp(y) or 1) * ny).astype(int), 0, ny - 1)
    s = np.zeros((ny, nx))
    c = np.zeros((ny, nx))
    np.add.at(s, (yi, xi), v)
    np.add.at(c, (yi, xi), 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(s / c)
