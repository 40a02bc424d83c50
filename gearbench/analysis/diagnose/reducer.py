"""The reducer too: where a measured two-motor bench trace and the simulated reducer
(constant efficiency, ideal ratio, Coulomb + viscous drag) disagree, which reducer effect
explains it, and how far adding it closes the gap on held-out data (issue 13).

Two relations the simulated reducer fixes, each linear in its parameters:

* kinematics — the output angle is the input angle over an ideal ratio:
  ``th_out = c + th_in / n``;
* torque balance at the input shaft — the input current carries the load reflected
  at constant efficiency, a Coulomb drag and the inertia:
  ``i_in = p (-i_out) + d sign(w_in) + v w_in + m a_in + c``.

Candidates add columns: ``ratio_ripple`` (sin/cos of k th_in, k scanned: CVT links,
eccentric gears), ``torsional_compliance`` (twist proportional to the transmitted
torque), ``backlash`` (lost motion that flips with the torque's sign),
``speed_losses`` (churning drag, w_in |w_in|), ``load_losses`` (mesh efficiency that
changes with load, i_out |i_out|) and ``speed_load_losses`` (efficiency falling with
speed, w_in i_out).  All signals go through one moving average (the relation stays
exact for its linear terms; angles stay raw) and both relations are scored like the motor diagnosis:
two-fold cross-fitting over alternating blocks, held-out MSE per smoother support
against the data's own noise floor, forward selection with the same significance test
(verdict.score).  Thresholds come from the data (encoder steps, current noise,
speed and current ranges), never from the user's units.

With both motors' calibrations ``i_in`` is the input shaft torque and ``i_out`` the
output's mesh torque with its sign flipped (its motor's torque less its friction and
its inertia's J_out a_out): the mesh's efficiency then acts on the output's inertial
torque as on its load, as it does in the simulated reducer (``sim.kernel``).

The noise floor is what a right model scores on noise alone (``held_out_floor``): the
white current noise through the relation's smoother, plus what that noise does to the
other fold's fitted coefficients.  It assumes white current noise on both currents
(the output's entering through the load ratio), noise-free angles in the torque
balance and independent folds.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..calibration import with_short_keys
from ...errors import TraceError
from ...trace import Trace
from . import verdict as vd
from .simerror import _hf_noise, lattice_step

BENCH_COLUMNS = ("in_position_rad", "in_current_a", "out_position_rad", "out_current_a")
#: Moving-average length, seconds (removes white noise; the same on every signal).
SMOOTH_S = 0.025
#: Held-out blocks alternate between two folds; each block is this long, seconds.
BLOCK_S = 0.25
#: Orders of the input angle scanned for ratio ripple (per input revolution).
RIPPLE_ORDERS = 12
MAX_CHAIN = 4
#: Share of the trace a column must vary over (its unique part) to be testable.
U_MIN = 0.05

KINEMATICS, TORQUE = "kinematics", "torque"
EXPERIMENTS = {
    frozenset({"torsional_compliance", "backlash"}):
        "load in both directions at small torque: backlash shows a dead band at each "
        "torque reversal, a compliant shaft stays linear through zero",
    frozenset({"speed_losses", "speed_load_losses"}):
        "repeat the speed sweep at no load and at full load: drag does not depend on "
        "the load, a speed-dependent efficiency does",
    frozenset({"load_losses", "speed_load_losses"}):
        "repeat the load steps at two input speeds: a load-dependent efficiency is the "
        "same at both",
}


@dataclass(frozen=True)
class _Sig:
    t: np.ndarray
    th_in: np.ndarray
    th_out: np.ndarray
    w_in: np.ndarray
    a_in: np.ndarray
    i_in: np.ndarray
    i_out: np.ndarray
    blocks: np.ndarray          # block index per sample
    floor: dict                 # relation -> per-sample noise MSE after smoothing
    #: relation -> (white variance of the raw noise, autocorrelation of the filter it
    #: goes through): what ``held_out_floor`` propagates through the other fold's fit
    noise_model: dict
    #: scoring groups: the smoother's support (2 L samples) — the held-out errors of
    #: one group share their noise, of two groups hardly (what n counts in the tests)
    chunks: np.ndarray
    noise: dict
    #: the raw angles (whole trace) and the smoother (length, kept range), for columns
    #: that must be smoothed like the currents (a motor's cogging torque)
    raw: tuple = ()

    def smoothed(self, x: np.ndarray) -> np.ndarray:
        """A whole-trace signal through the relation's smoother (twice), kept range."""
        _, _, L, cut = self.raw
        return _smooth(_smooth(x, L), L)[cut]


def _smooth(x: np.ndarray, L: int) -> np.ndarray:
    return np.convolve(x, np.ones(L) / L, mode="same")


#: Fields of a motor calibration (what ``gearbench calibrate --json`` prints, or a
#: run's result.json ``motors.<name>``): SI units.
CALIBRATION_FIELDS = ("Kt", "J", "D", "Tc")


def calibration(data: dict, source: str = "<calibration>") -> dict:
    """A motor calibration as {Kt, J, D, Tc} (N m/A, kg m^2, N m s/rad, N m), checked
    physical: Kt > 0, J > 0, D >= 0, Tc >= 0.  Accepts ``calibrate --json``'s object
    (optionally under ``params``) or a result.json ``motors.<name>`` entry."""
    if isinstance(data, dict) and isinstance(data.get("params"), dict) and "Kt" not in data:
        data = data["params"]
    if not isinstance(data, dict):
        raise TraceError(f"{source}: expected a JSON object with Kt, J, D, Tc")
    # result.json and calibrate --json write J_kgm2, D_nm_s_per_rad, Tc_nm; older files J, D, Tc
    data = with_short_keys(data)
    try:
        cal = {k: float(data.get(k, 0.0) if k in ("D", "Tc") else data[k])
               for k in CALIBRATION_FIELDS}
    except KeyError as exc:
        raise TraceError(f"{source}: missing field {exc}; give the motor's calibration as "
                         f"'gearbench calibrate --json' prints it (Kt, J, D, Tc)") from None
    except (TypeError, ValueError):
        raise TraceError(f"{source}: Kt, J, D, Tc must be numbers") from None
    bad = [f"{k} = {cal[k]:.4g}" for k, ok in (("Kt", cal["Kt"] > 0), ("J", cal["J"] > 0),
                                               ("D", cal["D"] >= 0), ("Tc", cal["Tc"] >= 0))
           if not ok]
    if bad:
        raise TraceError(f"{source}: not physical ({', '.join(bad)}); Kt and J must be > 0, "
                         f"D and Tc >= 0")
    return cal


def _shaft_torque(i, w, cal: dict, w_top: float) -> np.ndarray:
    """Torque a calibrated motor puts on its shaft less its inertia's and its viscous
    friction's: Kt i - Tc sgn(w) (``prepare_bench`` takes D w off after smoothing, with
    the relation's own smoothed speed: linear, so exact).  The inertia stays in the
    relation's fitted inertia column: taking J a off with a twice-differentiated encoder
    angle added noise the floor does not count (a clean control's torque relation went
    from 1.09x to 1.36x the floor)."""
    sgn = np.tanh(w / (0.01 * w_top))
    return cal["Kt"] * i - cal["Tc"] * sgn


def _sign_speed(th: np.ndarray, dt: float, L: int) -> np.ndarray:
    """Speed for a calibrated motor's Coulomb sign: the raw central difference through
    a short moving average (L/5, edges held), so that the sign goes through the
    currents' smoother once like every other term of the relation.  At the relation's
    smoothed speed it was smoothed twice more and read the smoother's zero-padded
    edges; the raw difference alone flips the sign on encoder steps near zero speed."""
    from scipy.ndimage import uniform_filter1d

    return uniform_filter1d(np.gradient(th, dt), max(3, L // 5), mode="nearest")


#: Current timings tried (share of the next sample's current at each sample; see
#: ``prepare_bench``), chosen on the nominal torque relation's held-out error.
HOLDS = (0.0, 0.25, 0.5, 0.75, 1.0)


def _held(i: np.ndarray, hold: float) -> np.ndarray:
    """(1 - h) i[k] + h i[k+1]: the current at the angle's sample instant k when each
    current sample is the drive's mean over the period ending at it (h = 0.5) or an
    instantaneous value (h = 0)."""
    return (1.0 - hold) * i + hold * np.append(i[1:], i[-1])


def prepare_bench(trace: Trace, motor_in: dict | None = None,
                  motor_out: dict | None = None, hold: float = 0.0) -> _Sig:
    """Validate and smooth a bench trace.  With both motors' calibrations the currents
    become the torques the motors put on the reducer's shafts (their own friction taken
    off, Kt applied), so the relation is in N m and its drag is the reducer's; without
    them they are in amps and the nominal absorbs the motors' losses (offset, drag of
    motors and reducer together).  Inertia is fitted either way (motors + reducer)."""
    trace.validate(BENCH_COLUMNS, min_samples=400)
    dt = trace.dt_s
    th_in = np.asarray(trace["in_position_rad"], float)
    th_out = np.asarray(trace["out_position_rad"], float)
    i_in = np.asarray(trace["in_current_a"], float)
    i_out = np.asarray(trace["out_current_a"], float)
    if np.ptp(th_in) == 0 or np.ptp(th_out) == 0:
        raise TraceError(f"{trace.source}: a shaft never turns (in_position_rad or "
                         f"out_position_rad constant); record a run with motion")
    L = max(3, int(round(SMOOTH_S / dt)))
    # every signal through the same smoother, twice: the acceleration is the derivative
    # of the once-smoothed velocity of the once-smoothed angle, so the currents must be
    # smoothed twice too — once smoothed they led the acceleration through every speed
    # ramp (our own --sim efficiency steps: 37x the floor at the run-up, 1-4x elsewhere)
    kernel = np.convolve(np.convolve(np.ones(L), np.ones(L)) / L ** 2, [1.0 - hold, hold])
    h2 = float(np.sum(kernel ** 2))               # sum of the smoother's squares
    s_iin, s_iout = _hf_noise(i_in, 7, 2), _hf_noise(i_out, 7, 2)
    # the timing after the noise estimate (on the raw samples); the blend is part of the
    # relation's filter (``kernel``), so the floor carries it
    i_in, i_out = _held(i_in, hold), _held(i_out, hold)
    q_in, q_out = lattice_step(th_in) or 0.0, lattice_step(th_out) or 0.0
    s_th_in = max(_hf_noise(th_in, 9, 3), q_in / np.sqrt(12))
    s_th_out = max(_hf_noise(th_out, 9, 3), q_out / np.sqrt(12))
    w = np.gradient(_smooth(_smooth(th_in, L), L), dt)
    a = np.gradient(_smooth(np.gradient(_smooth(th_in, L), dt), L), dt)
    cut = slice(2 * L, len(th_in) - 2 * L)       # the smoothing's edges
    unit = "A"
    if motor_in is not None and motor_out is not None:
        # the motors' Coulomb friction at a lightly smoothed speed, so that it goes
        # through the currents' smoother once like every other term (_sign_speed);
        # their viscous friction after smoothing.  At the smoothed speed the sign was
        # smoothed twice more and read the smoother's zero-padded edges, whose 33,000
        # rad/s (of a 25 rad/s output) also set the sign's width: the first and last
        # blocks of our own --sim steps, the run-up and run-down, sat 2-6x the floor
        # with the true model, noise-free
        w_o = np.gradient(_smooth(_smooth(th_out, L), L), dt)
        top_in = float(np.percentile(np.abs(w[cut]), 99.5)) or 1.0
        top_out = float(np.percentile(np.abs(w_o[cut]), 99.5)) or 1.0
        i_in = _shaft_torque(i_in, _sign_speed(th_in, dt, L), motor_in, top_in)
        i_out = _shaft_torque(i_out, _sign_speed(th_out, dt, L), motor_out, top_out)
        s_iin, s_iout = s_iin * motor_in["Kt"], s_iout * motor_out["Kt"]
        unit = "N m"
    n_ratio = np.ptp(th_in) / np.ptp(th_out)
    # angles are not smoothed (a ratio ripple of order k at speed w would average out)
    floor = {KINEMATICS: s_th_out ** 2 + (s_th_in / n_ratio) ** 2,
             TORQUE: s_iin ** 2 * h2}
    noise_model = {KINEMATICS: (floor[KINEMATICS], np.ones(1)),
                   TORQUE: (s_iin ** 2, np.convolve(kernel, kernel[::-1]))}
    per = max(L * 4, int(round(BLOCK_S / dt)))
    blocks = np.arange(len(th_in))[cut] // per
    # blocks dealt to the two folds by how much the speed changes in them, alternately
    # (as simerror.split): an efficiency step holds one speed but for its run-up and
    # run-down, and plain alternation could leave both in one fold — the other, fitted
    # at one speed, cannot tell viscous from Coulomb drag and extrapolated 250x the
    # floor onto the run-up of our own --sim steps
    b0 = blocks - blocks.min()
    energy = np.bincount(b0, np.append(np.diff(w[cut]), 0.0) ** 2) / np.bincount(b0)
    rank = np.empty(len(energy), int)
    rank[np.argsort(-energy, kind="stable")] = np.arange(len(energy))
    blocks = rank[b0]
    i_in, i_out = _smooth(_smooth(i_in, L), L), _smooth(_smooth(i_out, L), L)
    if unit == "N m":
        i_in = i_in - motor_in["D"] * w
        # the output's mesh torque: what its motor puts on the shaft less what its own
        # inertia takes (J_out from its calibration): the mesh passes the output's
        # inertial torque through the efficiency like the load, so a speed-dependent
        # efficiency scales both (a CVT's run-down left 2.9x the floor, noise-free,
        # with J_out in the fitted inertia)
        a_o = np.gradient(_smooth(np.gradient(_smooth(th_out, L), dt), L), dt)
        i_out = i_out - motor_out["D"] * w_o - motor_out["J"] * a_o
    return _Sig(trace.time_s[cut], th_in[cut], th_out[cut], w[cut],
                a[cut], i_in[cut], i_out[cut], blocks, floor, noise_model,
                np.arange(len(th_in))[cut] // (2 * L),
                {"in_current_a": s_iin, "out_current_a": s_iout, "in_angle": s_th_in,
                 "out_angle": s_th_out, "ratio_estimate": float(n_ratio),
                 "torque_unit": unit, "current_hold": float(hold)}, (th_in, th_out, L, cut))


# ---------------------------------------------------------------- relations
def _nominal(s: _Sig, rel: str) -> tuple[np.ndarray, np.ndarray, list[str]]:
    one = np.ones_like(s.t)
    if rel == KINEMATICS:
        return s.th_out, np.column_stack([one, s.th_in]), ["offset", "inv_ratio"]
    w_top = max(float(np.percentile(np.abs(s.w_in), 99.5)), 1e-300)
    sgn = np.tanh(s.w_in / (0.01 * w_top))
    # the simulated reducer's own losses: constant efficiency, Coulomb and viscous drag
    # (PlantParams drag_torque_nm, drag_viscous; the motors' viscous friction is the
    # same column)
    # constant efficiency acts with the power flow: eta braking, 1/eta driving — one
    # load ratio per direction of the output torque
    brake = s.i_out * s.w_in < 0
    return (s.i_in, np.column_stack([one, -s.i_out * brake, -s.i_out * ~brake, sgn, s.w_in,
                                     s.a_in]),
            ["offset_a", "load_ratio_braking", "load_ratio_driving", "drag_a",
             "viscous_a_per_speed", "inertia_a_s2"])


class _Cand:
    name, relation = "", ""

    def grid(self, s: _Sig) -> list[dict]:
        return [{}]

    def cols(self, s: _Sig, hp: dict) -> np.ndarray:
        raise NotImplementedError

    def describe(self, coef: np.ndarray, s: _Sig, hp: dict) -> dict:
        return {**hp, "coef": [float(c) for c in coef]}

    def inadmissible(self, coef: np.ndarray, s: _Sig, hp: dict) -> str | None:
        """Why the fitted size is not physical (None: admissible)."""
        return None


class RatioRipple(_Cand):
    name, relation = "ratio_ripple", KINEMATICS

    def grid(self, s):
        return [{"order": k} for k in range(1, RIPPLE_ORDERS + 1)]

    def cols(self, s, hp):
        k = hp["order"]
        return np.column_stack([np.sin(k * s.th_in), np.cos(k * s.th_in)])

    def describe(self, coef, s, hp):
        amp = float(np.hypot(*coef))
        # output angle ripple amp -> ratio ripple amplitude k*amp*n (fraction of 1/n)
        return {"order_per_input_rev": hp["order"], "angle_amplitude": amp,
                "ratio_ripple_fraction": amp * hp["order"] * s.noise["ratio_estimate"]}


class Compliance(_Cand):
    name, relation = "torsional_compliance", KINEMATICS

    def cols(self, s, hp):
        return s.i_out[:, None]

    def describe(self, coef, s, hp):
        return {"twist_per_out_current": float(coef[0])}


class Backlash(_Cand):
    name, relation = "backlash", KINEMATICS

    def grid(self, s):
        top = max(float(np.percentile(np.abs(s.i_out), 99)), 1e-300)
        return [{"width_a": f * top} for f in (0.01, 0.05, 0.2)]

    def cols(self, s, hp):
        return np.tanh(s.i_out / hp["width_a"])[:, None]

    def describe(self, coef, s, hp):
        return {"gap_out_angle": float(2 * abs(coef[0])), **hp}


class SpeedLosses(_Cand):
    """Churning: drag growing with the square of speed (the simulated reducer's drag
    is Coulomb + viscous, linear in speed)."""

    name, relation = "speed_losses", TORQUE

    def cols(self, s, hp):
        return (s.w_in * np.abs(s.w_in))[:, None]

    def describe(self, coef, s, hp):
        return {"churning_a_per_speed2": float(coef[0])}

    def inadmissible(self, coef, s, hp):
        return "negative drag (churning < 0)" if coef[0] < 0 else None


class LoadLosses(_Cand):
    name, relation = "load_losses", TORQUE

    def cols(self, s, hp):
        return (s.i_out * np.abs(s.i_out))[:, None]

    def describe(self, coef, s, hp):
        return {"quadratic_load_a_per_a2": float(-coef[0])}


class SpeedLoadLosses(_Cand):
    name, relation = "speed_load_losses", TORQUE

    def cols(self, s, hp):
        return (-s.w_in * s.i_out)[:, None]

    def describe(self, coef, s, hp):
        return {"load_ratio_change_per_in_speed": float(coef[0])}


class MotorCogging(_Cand):
    """A motor's cogging torque, order k of its own rotor angle, in the torque balance:
    not the reducer's, and not in a calibration (Kt, J, D, Tc) — on our own --sim
    efficiency steps the output motor's order-6 cogging (12 Hz at 100 rad/s input
    through the 8:1 CVT, below what the smoother removes) left 3-6x the floor at every
    load level.  Smoothed like the currents."""

    name, relation = "motor_cogging", TORQUE

    def grid(self, s):
        from .periodic import MAX_ORDER
        return [{"motor": m, "order": k} for m in ("out", "in") for k in range(1, MAX_ORDER + 1)]

    def cols(self, s, hp):
        th = s.raw[0] if hp["motor"] == "in" else s.raw[1]
        a = hp["order"] * th
        return np.column_stack([s.smoothed(np.sin(a)), s.smoothed(np.cos(a))])

    def describe(self, coef, s, hp):
        unit = s.noise["torque_unit"]
        return {"motor": hp["motor"], "order_per_motor_rev": hp["order"],
                "amplitude_at_input": float(np.hypot(*coef)), "unit": unit}


CANDIDATES = (RatioRipple(), Compliance(), Backlash(), SpeedLosses(), LoadLosses(),
              SpeedLoadLosses(), MotorCogging())


# ---------------------------------------------------------------- scoring
def _block_mse(r: np.ndarray, blocks: np.ndarray) -> np.ndarray:
    b = blocks - blocks.min()
    cnt = np.bincount(b)
    return (np.bincount(b, r * r) / np.maximum(cnt, 1))[cnt > 0]


def _held_out(y, X, blocks) -> tuple[np.ndarray, np.ndarray]:
    """Residuals of two-fold cross-fitting (odd blocks by the even fit, and back);
    returns (held-out residual, all-data coefficients)."""
    r = np.empty_like(y)
    scale = np.sqrt((X ** 2).sum(0))
    scale[scale == 0] = 1
    for parity in (0, 1):
        fit = blocks % 2 == parity
        c = np.linalg.lstsq(X[fit] / scale, y[fit], rcond=None)[0] / scale
        r[~fit] = y[~fit] - X[~fit] @ c
    c = np.linalg.lstsq(X / scale, y, rcond=None)[0] / scale
    return r, c


def held_out_floor(X: np.ndarray, blocks: np.ndarray, white: float,
                   rho: np.ndarray, groups: np.ndarray | None = None) -> float:
    """What the two-fold held-out error of a right model is, from the noise alone.

    A held-out sample's residual is its own noise minus what the other fold's noise
    did to the fitted coefficients: ``r_k = n_k - x_k^T A_f n_f`` with
    ``A_f = (X_f^T X_f)^+ X_f^T``.  With noise of white variance ``white`` through a
    filter of autocorrelation ``rho`` (Σ = white · toeplitz(rho)) its expectation is::

        E r_k^2 = white rho_0 + x_k^T A_f Σ_ff A_f^T x_k

    (the two folds' noises taken independent; their correlation across a block
    boundary only lowers it).  The second term is the prediction variance of the
    regression (e.g. Seber & Lee, *Linear Regression Analysis*, 2nd ed., §5.3); it
    grows with the columns and with the leverage of the held-out samples — a speed
    ramp predicted from the other fold's one ramp.  Without it the true model sat at
    1.07-1.14x the floor on our own --sim steps.

    Parameters
    ----------
    X : (n, p) array
        The relation's columns; ``blocks`` the block of each sample (folds by parity).
    white : float
        Variance of the raw (per-sample) noise.
    rho : (2m+1,) array
        Autocorrelation of the filter the noise goes through (``[1]``: none).

    Returns
    -------
    float
        Expected held-out MSE averaged like ``_block_mse`` (per group — ``groups``,
        default the blocks — then over groups).
    """
    n, p = X.shape
    e = np.full(n, white * float(rho[len(rho) // 2]))
    scale = np.sqrt((X ** 2).sum(0))
    scale[scale == 0] = 1
    for parity in (0, 1):
        fit = blocks % 2 == parity
        if not fit.any() or fit.all():
            continue
        # A_f = V S^-1 U^T (the rank lstsq uses); the quadratic form as z M z^T with
        # M = U^T Σ U positive semi-definite (G^T Σ G in one piece cancelled to < 0)
        U, sv, Vt = np.linalg.svd(X[fit] / scale, full_matrices=False)
        keep = sv > sv[0] * max(fit.sum(), p) * np.finfo(float).eps
        U, sv, Vt = U[:, keep], sv[keep], Vt[keep]
        if len(rho) > 1:
            g = np.zeros((n, U.shape[1]))
            g[fit] = U
            SU = np.column_stack([np.convolve(g[:, j], rho, mode="same")[fit]
                                  for j in range(U.shape[1])])
        else:
            SU = U * rho[0]
        M = white * (U.T @ SU)
        Z = (X[~fit] / scale) @ Vt.T / sv
        e[~fit] += np.einsum("ij,jk,ik->i", Z, M, Z)
    g = blocks if groups is None else groups
    return float(np.mean(_block_mse(np.sqrt(np.maximum(e, 0.0)), g)))


def _unique_share(X: np.ndarray, E: np.ndarray) -> float:
    Q, _ = np.linalg.qr(X / np.maximum(np.linalg.norm(X, axis=0), 1e-300))
    R = E - Q @ (Q.T @ E)
    return float(np.linalg.norm(R) / max(np.linalg.norm(E), 1e-300))


@dataclass(frozen=True)
class BenchDiagnosis:
    nominal: dict
    candidates: list
    chain: list
    remaining: dict

    def as_dict(self) -> dict:
        return {"nominal": self.nominal, "candidates": self.candidates, "chain": self.chain,
                "remaining": self.remaining,
                "verdict": {"effect": self.chain[0]["effect"] if self.chain else None}}


def _physical_nominal(params: dict, s: _Sig, brake_share: float) -> dict:
    """Efficiencies implied by the torque relation's load ratios (calibrated motors:
    torques in N m) and what is not physical about them: an efficiency above 1, a
    negative drag.  Forward (input drives): eta = 1 / (n p_braking); backward (output
    drives): eta = n p_driving — each only where the trace has that power flow."""
    n = s.noise["ratio_estimate"]
    out, problems = {}, []
    if brake_share > 0.02 and params["load_ratio_braking"] > 0:
        out["efficiency_forward"] = 1.0 / (n * params["load_ratio_braking"])
    if 1 - brake_share > 0.02:
        out["efficiency_backward"] = n * params["load_ratio_driving"]
    for k in ("efficiency_forward", "efficiency_backward"):
        if k in out and not 0 < out[k] <= 1:
            problems.append(f"{k} {out[k]:.3f} outside (0, 1]")
    # only where the trace has that power flow (an unused column's coefficient is noise)
    if (brake_share > 0.02 and params["load_ratio_braking"] <= 0) or (
            1 - brake_share > 0.02 and params["load_ratio_driving"] < 0):
        problems.append("a negative load ratio (the load would help the input)")
    w_top = max(float(np.percentile(np.abs(s.w_in), 99.5)), 1e-300)
    if abs(float(np.mean(np.tanh(s.w_in / (0.01 * w_top))))) > 0.99:
        # the input never reverses: its Coulomb drag and a current offset are one
        # column (the fit splits them evenly); only their sum is measured
        out["drag_plus_offset"] = params["drag_a"] + params["offset_a"]
        out["note"] = ("the input turns one way only: drag and offset are one column, "
                       "their sum is the drag; reverse the input to separate them")
        drag = out["drag_plus_offset"]
    else:
        drag = params["drag_a"]
    if drag < 0:
        problems.append("negative drag")
    return {**out, "ok": not problems, "problems": problems}


def _score(s: _Sig, state: dict, cand: _Cand):
    """One candidate added to its relation's current model: its best grid setting by
    held-out error, scored (significant only if testable and physical)."""
    st = state[cand.relation]
    y = _nominal(s, cand.relation)[0]
    best = None
    for hp in cand.grid(s):
        E = cand.cols(s, hp)
        X = np.column_stack([st["X"], E])
        r, c = _held_out(y, X, s.blocks)
        mse = _block_mse(r, s.chunks)
        if best is None or mse.mean() < best[0].mean():
            best = (mse, hp, E, c)
    mse, hp, E, c = best
    # the floor of the larger model: its extra columns carry the other fold's noise too
    f = held_out_floor(np.column_stack([st["X"], E]), s.blocks, st["white"],
                       s.noise_model[cand.relation][1], s.chunks)
    why_not = cand.inadmissible(c[-E.shape[1]:], s, hp)
    params = cand.describe(c[-E.shape[1]:], s, hp)
    if why_not:
        params["not_physical"] = why_not
    sc = vd.score(cand.name, params, st["mse"], mse,
                  E.shape[1] + (len(cand.grid(s)) > 1), f, 1.0)
    u = _unique_share(st["X"], E)
    testable = u >= U_MIN
    sc = vd.Score(**{**sc.__dict__, "significant": bool(sc.significant and testable
                                                        and not why_not),
                     "testable": testable,
                     "why": f"{u:.0%} of the candidate's columns unique against the "
                            f"model's (needs {U_MIN:.0%})"})
    return sc, E


def diagnose_bench(trace: Trace, max_chain: int = MAX_CHAIN, motor_in: dict | None = None,
                   motor_out: dict | None = None) -> BenchDiagnosis:
    """Diagnose a two-motor reducer bench trace against the simulated reducer.

    Parameters
    ----------
    trace : Trace
        ``in_/out_ position_rad, current_a`` of both motors.
    max_chain : int
        Most effects the forward selection adds.
    motor_in, motor_out : dict, optional
        Both motors' calibrations (``calibration``): the relation is then in the
        torques on the reducer's shafts, its parameters the reducer's alone, and the
        efficiencies they imply are checked physical.

    Returns
    -------
    BenchDiagnosis
        Nominal per relation, candidates, chain and what remains (see module doc).
    """
    # the current's timing (what a sample means: HOLDS) is a setting of the nominal,
    # chosen by the torque balance's held-out error at the end of the chain — chosen on
    # the bare nominal an unmodelled motor cogging pulled it to 0 where the drive
    # averages (our own --sim efficiency step: 3.5x the floor at 0, 1.2x at 0.5)
    # (compared as multiples of each timing's own floor: the blend filters the noise)
    runs = [_diagnose_signals(prepare_bench(trace, motor_in, motor_out, h), max_chain)
            for h in HOLDS]
    return min(runs, key=lambda r: r[1])[0]


def _diagnose_signals(s: _Sig, max_chain: int) -> tuple[BenchDiagnosis, float]:
    """The bench diagnosis of prepared signals and its torque balance's final
    held-out MSE over its floor."""
    state = {}
    nominal = {}
    for rel in (KINEMATICS, TORQUE):
        y, X, names = _nominal(s, rel)
        r, c = _held_out(y, X, s.blocks)
        mse = _block_mse(r, s.chunks)
        white, rho = s.noise_model[rel]
        if rel == TORQUE:
            # the output current's noise enters through the load ratio (which the fit
            # has just measured): per sample p^2 s_out^2 on top of the input's
            p = np.where(s.i_out * s.w_in < 0, c[1], c[2])
            scale = (s.noise["out_current_a"] / s.noise["in_current_a"]) ** 2 \
                if s.noise["in_current_a"] > 0 else 0.0
            white = white * (1.0 + scale * float(np.mean(p ** 2)))
        f = held_out_floor(X, s.blocks, white, rho, s.chunks)
        state[rel] = {"X": X, "mse": mse, "mse0": mse, "white": white, "floor": f,
                      "floor0": f}
        nominal[rel] = {"params": dict(zip(names, map(float, c))),
                        "rms": float(np.sqrt(np.mean(mse))), "noise_floor": float(np.sqrt(f)),
                        "noise_floor_no_fit": float(np.sqrt(white * rho[len(rho) // 2])),
                        "gap_ratio": float(np.sqrt(np.mean(mse) / f))}
    nominal["noise"] = s.noise
    brake_share = float(np.mean(s.i_out * s.w_in < 0))
    nominal["physical"] = _physical_nominal(nominal[TORQUE]["params"], s, brake_share)
    chain, first = [], None
    chosen: set[str] = set()
    for step in range(max_chain):
        scores = [_score(s, state, cand) for cand in CANDIDATES if cand.name not in chosen]
        ranked = sorted(scores, key=lambda p: (not p[0].significant, p[0].delta_bic))
        if first is None:
            first = [dict(p[0].as_dict(), relation=next(c.relation for c in CANDIDATES
                                                         if c.name == p[0].effect))
                     for p in ranked]
        if not ranked or not ranked[0][0].significant:
            break
        sc, E = ranked[0]
        rel = next(c.relation for c in CANDIDATES if c.name == sc.effect)
        st = state[rel]
        gap0 = vd.excess(float(np.mean(st["mse0"])), st["floor0"])
        st["X"] = np.column_stack([st["X"], E])
        st["mse"] = sc.mse_h
        st["floor"] = held_out_floor(st["X"], s.blocks, st["white"], s.noise_model[rel][1],
                                     s.chunks)
        gap = vd.excess(float(np.mean(sc.mse_h)), st["floor"])
        alike = [p[0].effect for p in ranked[1:] if p[0].significant and
                 vd.paired_t(p[0].mse_h, sc.mse_h) < vd.T_CONFUSED and
                 frozenset({p[0].effect, sc.effect}) in EXPERIMENTS]
        chain.append({"effect": sc.effect, "relation": rel, "params": sc.params,
                      "shrink_heldout": float(sc.shrink),
                      "cumulative_shrink": float(1 - gap / gap0) if gap0 > 0 else 0.0,
                      "significant": True, "delta_bic": float(sc.delta_bic),
                      "gap_ratio_after": float(np.sqrt(np.mean(sc.mse_h) / st["floor"])),
                      "confused_with": alike,
                      "experiment": "; ".join(EXPERIMENTS[frozenset({a, sc.effect})]
                                              for a in alike) or None})
        chosen.add(sc.effect)
    remaining = {}
    for rel in (KINEMATICS, TORQUE):
        st, f = state[rel], state[rel]["floor"]
        g0 = vd.excess(float(np.mean(st["mse0"])), st["floor0"])
        g = vd.excess(float(np.mean(st["mse"])), f)
        at_floor = float(np.mean(st["mse"])) <= (1 + vd.MATERIAL) * f
        t = vd.paired_t(st["mse"], np.full_like(st["mse"], f))
        remaining[rel] = {"share_of_gap": float(g / g0) if g0 > 0 else 0.0,
                          "gap_ratio": float(np.sqrt(np.mean(st["mse"]) / f)),
                          "at_noise_floor": bool(at_floor),
                          "unknown_effect": bool(not at_floor and t > vd.T_CRIT
                                                 and len(chain) < max_chain)}
    return (BenchDiagnosis(nominal, first or [], chain, remaining),
            float(np.mean(state[TORQUE]["mse"])) / state[TORQUE]["floor"])
