"""Identifiability: can this trace reveal each candidate effect at all?

Computed from the trace alone (never from what was injected).  An effect is
*testable* when the excitation puts its signature where the diagnoser can see it,
above the data's own noise and not collinear with the nominal model:

* friction / offset: a constant or sign-like torque must not be a linear mix of the
  nominal's regressors Kt/J i and D/J w (a constant-acceleration ramp makes the
  current affine in speed, so a constant torque is absorbed) — the *unique share*
  of the effect's integrated regressor after projecting out the nominal's
  (Frisch-Waugh-Lovell), on a current smoothed of its white noise;
  Coulomb vs offset additionally needs velocity reversals;
* Stribeck friction: time at low but non-zero speed (|w| <= W_STRIBECK_MAX);
* cogging / ripple: rotor angle covered where the order-6 (lowest order of a
  three-phase motor's cogging and commutation ripple) pattern is slow enough for the
  velocity estimate to pass it (<= fs/20); ripple also needs current there;
* time delay: current change per sample above the current noise left after a horizon;
* kt saturation: current well above its noise, with a cubic term not collinear;
* shaft compliance: the quasi-static signature of a two-mass resonance (the motion's
  jerk over w_r^2, its part not mimicked by the nominal's regressors) above the floor
  for a disk as large as the motor at F_SHAFT_MIN (a resonance shows well below its
  frequency; checked against injected cases in the scorecard);
* backlash: torque (acceleration) reversals to cross the gap; the smallest gap that
  shows above the floor from the jerk at reversals (``_smallest_gap``);
* encoder quantisation: angles on a lattice, the step's noise material vs the floor;
* inertia mismatch: only against a given model (an identified one absorbs J).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import savgol_filter, welch

from .nominal import Signals, Windows, integrated_rows
from .simerror import BLOCK_S, NoiseFloor, end_noise_var, lattice_step

#: Smallest unique share (after projecting out the nominal's regressors) that counts.
U_MIN = 0.05
#: Smallest participation ratio of that unique part over the trace's windows.
MIN_SPREAD = 0.25
#: Share of the trace needed at low speed for Stribeck friction.
MIN_LOW_SHARE = 0.02
#: Highest Stribeck speed considered, as a fraction of the trace's top speed (a
#: Stribeck speed near the top speed is Coulomb friction by another name).
W_STRIBECK_FRACTION = 0.03
#: Share of the trace needed moving in each direction for direction-dependent friction.
MIN_DIRECTION_SHARE = 0.05
#: Lowest order of cogging / commutation ripple in a three-phase motor.
ORDER_MIN = 6
#: Rotor revolutions needed at a slow enough speed for an angle pattern.
MIN_REVS = 1.0
#: Current over the covered angle must be this many times the current noise (ripple).
RIPPLE_CURRENT_SNR = 10.0
#: Current must exceed its noise this many times (99th percentile) for saturation.
SAT_CURRENT_SNR = 20.0
#: Lowest plausible resonance of a shaft-mounted disk or coupling, Hz.
F_SHAFT_MIN = 20.0
#: The shaft's jerk signature must reach the noise floor (rms) times this.
SHAFT_SNR = 1.0
#: PSD of the current above this multiple of the white-noise PSD counts as excitation.
PSD_SNR = 10.0
#: Acceleration reversals needed to cross a backlash gap repeatedly.
MIN_TORQUE_REVERSALS = 4
#: Effects that physically cannot act on a trace judged untestable for them (a gap is
#: only crossed at torque reversals): never named there, whatever their fit does.
PREREQUISITE = ("backlash",)

EXPERIMENTS = {
    "load_torque": "move the load over at least a quarter of a revolution (state the "
                   "position unit as an angle and the gear ratio, --ratio)",
    "presliding_friction": "add velocity reversals (slow ones show the friction build-up)",
    "coulomb_friction": "add velocity reversals or speed steps at different speeds "
                        "(Coulomb friction is a constant torque in one direction)",
    "current_offset": "vary the current level, e.g. acceleration steps or a multisine "
                      "speed command (a constant torque is absorbed by Kt/J on a ramp)",
    "stribeck_friction": "add slow motion: speed steps at 0.2-3 % of the top speed or "
                         "slow reversals",
    "direction_friction": "move in both directions for a similar time (reversing speed "
                          "command at several speeds)",
    "position_friction": "reverse the motion at several positions over the travel (a "
                         "friction that varies with position needs both directions there)",
    "cogging": "add a slow sweep (below ~fs/20 / 6 rev/s, several revolutions)",
    "torque_ripple": "add slow revolutions under load (e.g. slow reversals with "
                     "acceleration), so the current is well above its noise",
    "time_delay": "excite faster current changes: speed steps or a multisine up to 10+ Hz",
    "kt_saturation": "repeat with larger accelerations so the current spans most of "
                     "the drive's range",
    "shaft_compliance": "add a broadband speed excitation (chirp or PRBS up to "
                        f"{2 * F_SHAFT_MIN:g}+ Hz) to excite the shaft resonance",
    "backlash": "add torque reversals (an oscillating multisine or reversing speed "
                "command) so the coupling crosses its gap",
    "encoder_quantization": "record the raw encoder counts (positions here are not on "
                            "a lattice) or a trace at lower speed",
    "inertia_mismatch": "give the nominal model (--model MODEL.json) from an earlier "
                        "calibration: an identified model absorbs any inertia",
}


@dataclass(frozen=True)
class Testability:
    """Whether the trace can reveal an effect, why, and what would test it if not;
    ``min_amplitude``: the smallest amplitude that would show above the floor, where
    cheap to estimate (a smaller one is not testable on this trace either)."""

    testable: bool
    why: str
    experiment: str | None = None
    min_amplitude: dict | None = None

    def as_dict(self) -> dict:
        return {"testable": self.testable, "why": self.why,
                "min_amplitude": self.min_amplitude}


def _smallest_gap(acc: np.ndarray, n_rev: int, duration_s: float, floor_mse: float,
                  dt: float) -> float:
    """Smallest backlash gap whose signature reaches the noise floor.

    At a torque reversal the disk (inertia ratio ~1) leaves its contact and the motor,
    its acceleration ramping at the jerk j, crosses the gap g in t = (6 g / j)^(1/3),
    reaching v = j t^2 / 2; the model error meanwhile rises to ~v/2 (then the impact
    shares the momentum back), so each reversal adds ~(v/2)^2 t / 3 of squared error.
    Over R reversals per second that is R j^(1/3) (6 g)^(5/3) / 48 — set equal to the
    floor's MSE and solved for g."""
    if n_rev == 0:
        return float("inf")
    s = np.sign(acc)
    k = np.flatnonzero(s[1:] * s[:-1] < 0)
    if not k.size:
        return float("inf")
    jerk = float(np.median(np.abs(acc[k + 1] - acc[k]))) / dt
    rate = n_rev / duration_s
    if jerk <= 0:
        return float("inf")
    return float((48 * floor_mse / (rate * jerk ** (1 / 3))) ** 0.6 / 6)


def _unique_share(sig: Signals, win: Windows, basis: np.ndarray,
                  col: np.ndarray) -> tuple[float, float]:
    """How far the integrated regressor ``col`` is from the span of ``basis``.

    Returns (share, spread): share = |P_perp e| / |e|; spread = the participation
    ratio (sum E_b)^2 / (B sum E_b^2) of the energy E_b of r = P_perp e in each of the
    B held-out blocks — near 1 when the unique part runs through the trace, ~k/B when
    it sits in k blocks (a start-up transient), which held-out scoring cannot confirm."""
    X = integrated_rows(sig, np.column_stack([basis, col]), win)[0]
    B, e = X[:, :-1], X[:, -1]
    ne = float(np.linalg.norm(e))
    if ne == 0:
        return 0.0, 0.0
    Q, _ = np.linalg.qr(B / np.maximum(np.linalg.norm(B, axis=0), 1e-300))
    r = e - Q @ (Q.T @ e)
    blocks = (win.start * sig.dt_s // BLOCK_S).astype(int)
    eb = np.bincount(blocks - blocks.min(), weights=r ** 2)
    eb = eb[np.bincount(blocks - blocks.min()) > 0]
    spread = float(eb.sum() ** 2 / (len(eb) * float((eb ** 2).sum()))) if eb.any() else 0.0
    return float(np.linalg.norm(r) / ne), spread


def _reversals(x: np.ndarray, band: float) -> int:
    """Sign changes of ``x`` between excursions beyond +-band (hysteresis)."""
    s = np.sign(x) * (np.abs(x) > band)
    s = s[s != 0]
    return int(np.sum(s[1:] != s[:-1]))


def _bandwidth_hz(sig: Signals, noise_a: float) -> float:
    """Highest frequency where the current PSD exceeds PSD_SNR x its white noise."""
    f, p = welch(sig.current_a, fs=1.0 / sig.dt_s, nperseg=min(len(sig), 2048))
    above = f[(p > PSD_SNR * 2 * sig.dt_s * noise_a ** 2) & (f > 0)]
    return float(above.max()) if above.size else 0.0


def assess(sig: Signals, floor: NoiseFloor, win: Windows, horizon: int,
           given_model: bool) -> dict[str, Testability]:
    """Testability of every effect in the library on this trace (see module doc)."""
    n = len(sig)
    w, th = sig.velocity_rad_s, sig.position_rad
    s_i, s_w = floor.current_noise_a, floor.velocity_noise_rad_s
    # current noise and the loop's reaction to it smoothed away over a horizon (the
    # scoring averages over horizons): collinearity is a property of the excitation
    i_s = savgol_filter(sig.current_a, min(2 * horizon + 1, n - (1 - n % 2)), 2)
    w_top = float(np.percentile(np.abs(w), 99.5))
    w_mov = max(5 * s_w, 0.02 * w_top)
    out: dict[str, Testability] = {}

    def put(name, ok, why):
        out[name] = Testability(bool(ok), why, None if ok else EXPERIMENTS[name])

    basis = np.column_stack([i_s, w])
    n_rev = _reversals(w, w_mov)
    u_const, p_const = _unique_share(sig, win, basis, np.ones(n))
    w_top_all = max(float(np.percentile(np.abs(w), 99.5)), 1e-300)
    sgn = np.tanh(w / (1e-3 * w_top_all))      # the Coulomb regressor at its middle width
    u_coul, p_coul = _unique_share(sig, win, basis, sgn)

    def seen(u, p):
        return u >= U_MIN and p >= MIN_SPREAD

    def unique(u, p):
        text = f"{u:.0%} unique against the nominal's regressors, spread {p:.2f}"
        if u < U_MIN:
            return text + " — absorbed by Kt/J and D/J (current affine in speed)"
        return text + (f" — only in a few windows (needs {MIN_SPREAD:g})" if p < MIN_SPREAD else "")

    put("current_offset", seen(u_const, p_const), "a constant torque is " + unique(u_const, p_const)
        + ("" if n_rev else "; without reversals it looks like Coulomb friction"))
    put("coulomb_friction", seen(u_coul, p_coul),
        f"{n_rev} velocity reversals; friction torque " + unique(u_coul, p_coul)
        + ("" if n_rev else "; one direction only: the same regressor as a current offset"))
    # presliding shows only where the motion reverses (friction builds up again)
    put("presliding_friction", n_rev > 0 and seen(u_coul, p_coul),
        f"{n_rev} velocity reversals (presliding friction shows only at reversals)")

    moving = np.abs(w) > 3 * s_w
    w_strib = W_STRIBECK_FRACTION * w_top_all
    low = float(np.mean(moving & (np.abs(w) <= w_strib)))
    put("stribeck_friction", low >= MIN_LOW_SHARE,
        f"{low:.1%} of the trace at 0 < |w| <= {w_strib:.3g} (units/s; "
        f"{W_STRIBECK_FRACTION:.0%} of the top speed; needs {MIN_LOW_SHARE:.0%})")

    fwd, back = float(np.mean(w > w_mov)), float(np.mean(w < -w_mov))
    basis_c = np.column_stack([i_s, w, sgn])
    u_dir, p_dir = _unique_share(sig, win, basis_c, np.abs(w))
    put("direction_friction", min(fwd, back) >= MIN_DIRECTION_SHARE and seen(u_dir, p_dir),
        f"{fwd:.0%} of the trace forward, {back:.0%} backward (needs "
        f"{MIN_DIRECTION_SHARE:.0%} each); direction-dependent viscous torque "
        + unique(u_dir, p_dir))
    x = th - th.min()
    x = 2.0 * x / (np.ptp(x) or 1.0) - 1.0
    u_pos, p_pos = _unique_share(sig, win, basis_c, sgn * x)
    put("position_friction", n_rev >= 1 and seen(u_pos, p_pos),
        f"{n_rev} velocity reversals; friction varying along the travel "
        + unique(u_pos, p_pos))

    out.update(_angles(sig, i_s, s_i))

    di = float(np.sqrt(np.mean(np.diff(i_s) ** 2)))
    need = 2 * s_i / np.sqrt(horizon)
    put("time_delay", di >= need,
        f"current changes {di * 1e3:.2g} mA per sample (rms) vs {need * 1e3:.2g} mA of "
        f"current noise left over a horizon")

    i99 = float(np.percentile(np.abs(i_s), 99))
    u_cub, p_cub = _unique_share(sig, win, basis, i_s ** 3)
    # a cubic term peaks with the current, so its spread is naturally low: not required
    put("kt_saturation", i99 >= SAT_CURRENT_SNR * s_i and u_cub >= U_MIN,
        f"current up to {i99:.3g} A ({i99 / max(s_i, 1e-12):.0f}x its noise, needs "
        f"{SAT_CURRENT_SNR:g}x); a cubic term is {u_cub:.0%} unique against the nominal's "
        f"regressors")

    out.update(_mechanical(sig, win, basis_c, floor, s_i, s_w))
    out.update(_sensing(sig, floor, given_model))
    return out


def _mechanical(sig: Signals, win: Windows, basis_c: np.ndarray, floor: NoiseFloor,
                s_i: float, s_w: float) -> dict[str, Testability]:
    """Shaft compliance and backlash (see the module doc)."""
    n, dt, th, w = len(sig), sig.dt_s, sig.position_rad, sig.velocity_rad_s
    out: dict[str, Testability] = {}
    # A two-mass resonance shows well below its frequency: the disk lags the motor by
    # ~acc/w_d^2, so the coupling torque is the disk's inertia (absorbed by Kt/J) plus
    # r th^(4)/w_d^2 (r = J_disk/J), whose velocity error over a horizon is ~r jerk/w_d^2.
    # Testable when, for a disk as large as the motor (r = 1) at the lowest plausible
    # resonance, the part of that jerk signature no nominal regressor mimics reaches the
    # noise floor — checked against injected two-mass cases (a 0.3-6 Hz multisine
    # reveals 16-60 Hz shafts there), unlike the former rule "excitation bandwidth must
    # reach the resonance", which hid them.  min_amplitude: the highest resonance
    # (mildest shaft, r = 1) this trace still shows.
    jerk = savgol_filter(th, min(51, n - (1 - n % 2)), 3, deriv=3, delta=dt)
    u_j, p_j = _unique_share(sig, win, basis_c, jerk)
    sig_rms = u_j * float(np.sqrt(np.mean(jerk ** 2)))
    f_top = float(np.sqrt(sig_rms / (SHAFT_SNR * np.sqrt(floor.mse))) / (2 * np.pi))
    fbw = _bandwidth_hz(sig, s_i)
    ok = f_top >= F_SHAFT_MIN and p_j >= MIN_SPREAD
    out["shaft_compliance"] = Testability(
        ok, f"a two-mass resonance shows below its frequency through the jerk: here up to "
            f"~{f_top:.0f} Hz for a disk as large as the motor (needs {F_SHAFT_MIN:g} Hz; jerk "
            f"{u_j:.0%} unique against the nominal's regressors, spread {p_j:.2f}; current "
            f"excited up to {fbw:.1f} Hz)",
        None if ok else EXPERIMENTS["shaft_compliance"], {"highest_resonance_hz": f_top})

    acc = savgol_filter(w, min(51, n - (1 - n % 2)), 2, deriv=1, delta=dt)
    a_band = 5 * s_w / (25 * dt)
    n_trev = _reversals(acc, a_band)
    g_min = _smallest_gap(acc, n_trev, n * dt, floor.mse, dt)
    out["backlash"] = Testability(
        n_trev >= MIN_TORQUE_REVERSALS,
        f"{n_trev} torque (acceleration) reversals (needs {MIN_TORQUE_REVERSALS}); "
        f"smallest gap that shows above the floor ~{g_min:.2g} rad",
        None if n_trev >= MIN_TORQUE_REVERSALS else EXPERIMENTS["backlash"],
        {"gap_rad": g_min})

    return out


def _sensing(sig: Signals, floor: NoiseFloor, given_model: bool) -> dict[str, Testability]:
    """Encoder quantisation and inertia mismatch (see the module doc)."""
    dt, th = sig.dt_s, sig.position_rad
    out: dict[str, Testability] = {}

    def put(name, ok, why):
        out[name] = Testability(bool(ok), why, None if ok else EXPERIMENTS[name])

    q = lattice_step(th)
    if q:
        qn = np.sqrt(end_noise_var(q / np.sqrt(12), dt))
        put("encoder_quantization", qn ** 2 >= 0.1 * floor.mse,
            f"angles on a lattice of {q:.3g} rad ({2 * np.pi / q:.0f} counts/rev): "
            f"quantisation noise {qn:.3g} rad/s vs floor {np.sqrt(floor.mse):.3g} rad/s")
    else:
        put("encoder_quantization", False, "angles are not on a lattice (interpolated or "
            "filtered positions): the encoder step cannot be checked")

    put("inertia_mismatch", given_model,
        "against the given model" if given_model else
        "no model given: the nominal identified on this trace absorbs any inertia")
    return out


def _angles(sig: Signals, i_s: np.ndarray, s_i: float) -> dict[str, Testability]:
    """Cogging, torque ripple (motor-angle orders) and the load torque (load angle)."""
    dt, th, w = sig.dt_s, sig.position_rad, sig.velocity_rad_s
    out: dict[str, Testability] = {}

    def put(name, ok, why):
        out[name] = Testability(bool(ok), why, None if ok else EXPERIMENTS[name])

    # angle covered where the order-6 pattern is at most fs/20 (>= 20 samples/period);
    # in radians of rotor angle: orders are per revolution, so the position unit must
    # be known as an angle (or a lead given) — never assumed
    k_ang = sig.rad_per_unit or 0.0
    dth = np.abs(np.diff(th)) * k_ang
    slow = ORDER_MIN * np.abs(w[1:]) * k_ang / (2 * np.pi) <= 0.05 / dt
    revs = float(np.sum(dth[slow]) / (2 * np.pi))
    strong = np.abs(i_s[1:]) >= RIPPLE_CURRENT_SNR * s_i
    revs_i = float(np.sum(dth[slow & strong]) / (2 * np.pi))
    w_slow = 0.05 / dt * 2 * np.pi / ORDER_MIN
    top_order = int(0.05 / dt * 2 * np.pi / max(float(np.percentile(np.abs(w), 5)) * k_ang, 1e-9))
    w_slow_u = w_slow / k_ang if k_ang else float("nan")   # in the trace's unit/s
    if not k_ang:
        why = ("the position unit is not an angle and no travel per motor revolution was "
               "given: orders per revolution cannot be tested")
        for name in ("cogging", "torque_ripple"):
            out[name] = Testability(False, why, "state the position unit (e.g. "
                                    "--position-unit deg) or, for a linear axis, the travel "
                                    "per motor revolution (--travel-per-rev LEAD)")
    else:
        put("cogging", revs >= MIN_REVS,
            f"{revs:.1f} revolutions at |w| <= {w_slow_u:.3g} units/s, where order-{ORDER_MIN} "
            f"patterns stay below fs/20 (orders up to ~{min(top_order, 999)} at the slowest 5 %)")
        put("torque_ripple", revs_i >= MIN_REVS,
            f"{revs_i:.1f} revolutions at |w| <= {w_slow_u:.3g} units/s with |i| >= "
            f"{RIPPLE_CURRENT_SNR:g}x the current noise ({RIPPLE_CURRENT_SNR * s_i * 1e3:.0f} mA)")

    # a load torque (gravity, unbalance): the load angle must sweep far enough that
    # sin and cos of it are not a constant and a ramp (the candidate's own grid)
    k_load = (sig.rad_per_unit / (sig.load_ratio or 1.0)) if sig.rad_per_unit else 0.0
    sweep = float(np.ptp(th)) * k_load
    put("load_torque", sweep >= 0.5 * np.pi,
        f"the load angle sweeps {sweep:.2f} rad (needs a quarter revolution, "
        f"{0.5 * np.pi:.2f} rad; position unit and gear ratio as stated)"
        if k_load else "the position is not a known angle")

    return out
