"""Mechanical candidates: a disk on a compliant shaft (two-mass) and a disk behind a
backlash gap (rigid contact)."""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numba
import numpy as np

from . import fastsim as fs
from .base import Effect, _pm
from .friction import speed_scale
from .nominal import Signals, Term


# ------------------------------------------------------------ disk on a shaft
# The disk's equation is linear: th2'' = wn^2 (th - th2) + 2 zeta wn (w - w2).  Both the
# disk tracked from the measured motion and the simulated two-mass system are stepped
# with its exact solution over a sample (matrix exponentials).  Explicit steps of a
# lightly damped mode are not good enough: explicit motor velocity + trapezoid angle
# gained (h w)^2/2 of energy per step, and a symplectic track's disk velocity is the
# interval mean, half a step late: with them the true model of an injected shaft sat at
# 1.8-7.4x the noise floor on held-out horizons (exact steps: 0.6-0.75x).
def _expm(a: np.ndarray) -> np.ndarray:
    """exp(a) of a small matrix: Taylor series after scaling to norm <= 1/2, then
    squaring (scipy.linalg.expm took ~7 ms a call on these 4x4s: hundreds per scan)."""
    s = max(0, int(np.ceil(np.log2(np.abs(a).sum(axis=1).max() + 1e-300))) + 1)
    a = a / 2.0 ** s
    e = t = np.eye(len(a))
    for k in range(1, 15):
        t = t @ a / k
        e = e + t
    for _ in range(s):
        e = e @ e
    return e


def _disk_matrix(wn: float, zeta: float, dt: float) -> np.ndarray:
    """Transition over one step of (th2, w2, th, s): the disk driven by a motor angle
    th + s t that is linear between samples (s = its slope, held)."""
    a = np.zeros((4, 4))
    a[0, 1] = a[2, 3] = 1.0
    a[1] = [-wn * wn, -2.0 * zeta * wn, wn * wn, 2.0 * zeta * wn]
    return _expm(a * dt)


@functools.lru_cache(maxsize=64)
def two_mass_step(k_over_j: float, c_over_j: float, wn: float, zeta: float,
                  dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact step of motor and disk, z = (th, w, th2, w2), with the motor's other
    torques held over the step as an acceleration u:  z1 = A z0 + b u, from
        th'' = u - k/J (th - th2) - c/J (w - w2),  th2'' = wn^2 (th - th2) + 2 zeta wn (w - w2)."""
    m = np.zeros((5, 5))
    m[0, 1] = m[2, 3] = m[1, 4] = 1.0
    m[1, :4] = [-k_over_j, -c_over_j, k_over_j, c_over_j]
    m[3, :4] = [wn * wn, 2.0 * zeta * wn, -wn * wn, -2.0 * zeta * wn]
    e = _expm(m * dt)
    return e[:4, :4], e[:4, 4]


@numba.njit(cache=True)
def _disk_track(theta, dt, e):  # pragma: no cover - compiled
    """Disk driven through the shaft by the measured motor angle, linear between
    samples (``e`` = ``_disk_matrix``): th2[k], w2[k] at the sample instants."""
    n = theta.shape[0]
    th2 = np.empty(n)
    w2 = np.empty(n)
    a, b = theta[0], (theta[1] - theta[0]) / dt
    for k in range(n):
        th2[k] = a
        w2[k] = b
        if k + 1 < n:
            s = (theta[k + 1] - theta[k]) / dt
            a, b = (e[0, 0] * a + e[0, 1] * b + e[0, 2] * theta[k] + e[0, 3] * s,
                    e[1, 0] * a + e[1, 1] * b + e[1, 2] * theta[k] + e[1, 3] * s)
    return th2, w2


@dataclass(frozen=True)
class DiskTerm(Term):
    """Coupling torque of a disk on a compliant shaft, -k/J (th - th2) - c/J (w - w2);
    the disk obeys th2'' = wn^2 (th - th2) + 2 zeta wn (w - w2).  In simulation the
    coupling is integrated exactly with the motor (``advance``, see two_mass_step)."""

    names: tuple[str, ...] = ("k_over_j", "c_over_j_shaft")
    wn: float = 200.0
    zeta: float = 0.1

    def _track(self, sig):
        # one slot: a scan visits hundreds of disks, each a trace long
        key = (self.wn, self.zeta)
        slot = sig.cache.get("disk")
        if slot is None or slot[0] != key:
            e = _disk_matrix(self.wn, self.zeta, sig.dt_s)
            slot = (key, _disk_track(sig.position_rad, sig.dt_s, e))
            sig.cache["disk"] = slot
        return slot[1]

    def measured(self, sig):
        th2, w2 = self._track(sig)
        return [th2 - sig.position_rad, w2 - sig.velocity_rad_s]

    def init_state(self, sig, idx):
        th2, w2 = self._track(sig)
        return [th2[idx].copy(), w2[idx].copy()]

    def simulate(self, sig, theta, omega, idx, state):
        return [state[0] - theta, state[1] - omega]

    def advance(self, state, coef, theta, omega, u, dt):
        """Motor and disk after one step, the other torques held as acceleration ``u``:
        (theta, omega, state)."""
        a, b = two_mass_step(float(coef[0]), float(coef[1]), self.wn, self.zeta, dt)
        z = a @ np.array([theta, omega, state[0], state[1]]) + b[:, None] * u
        return z[0], z[1], [z[2], z[3]]


def _wn_grid(sig, n):
    top = 0.25 * np.pi / sig.dt_s  # well below Nyquist (a mode the samples can show)
    return np.geomspace(20.0, top, n)


class ShaftCompliance(Effect):
    name = "shaft_compliance"
    continuous = ("wn_rad_s", "zeta")
    #: a disk needs k > 0: with k < 0 a stiff "disk" acts as a predictor of the motion
    #: that equation error (not simulation) rewards, e.g. on a strongly excited resonance
    positive = ("k_over_j",)

    def grid(self, sig, base):
        # a lightly damped disk is tracked open loop, so the fit is sharp in wn:
        # 1.4 % steps when lightly damped (Nelder-Mead refines), 6 % when well damped
        return ([{"wn_rad_s": float(w), "zeta": 0.02} for w in _wn_grid(sig, 260)]
                + [{"wn_rad_s": float(w), "zeta": 0.3} for w in _wn_grid(sig, 60)])

    def extra(self, hp):
        return [DiskTerm(wn=hp["wn_rad_s"], zeta=hp["zeta"])]

    def describe(self, model, base, hp):
        k, kh = _pm(model, "k_over_j")
        return {"k_over_j": k, "k_over_j_pm": kh,
                "disk_over_motor_inertia": k / hp["wn_rad_s"] ** 2, **hp}


@numba.njit(cache=True)
def _gap_track(theta, omega, dt, gap):  # pragma: no cover - compiled
    """A free disk in a gap, driven by the given motor motion through rigid contact:
    it coasts inside the gap and, when the gap closes while closing, takes the motor's
    velocity (a plastic impact; held while the motor keeps pushing)."""
    n = theta.shape[0]
    th2 = np.empty(n)
    w2 = np.empty(n)
    a, b = theta[0], omega[0]
    half = 0.5 * gap
    for k in range(n):
        th2[k] = a
        w2[k] = b
        if k + 1 < n:
            a = a + dt * b
            d = theta[k + 1] - a
            s = 1.0 if d > 0 else -1.0
            if abs(d) >= half and s * (omega[k + 1] - b) > 0.0:
                b = omega[k + 1]
                a = theta[k + 1] - s * half
    return th2, w2


@dataclass(frozen=True)
class RigidGapTerm(Term):
    """A disk (inertia ratio r = J_disk/J, the one coefficient) behind a gap, rigid
    contact: J th'' = ... - J_disk th2'', the disk's acceleration being the contact's
    only torque on it.  Equation error uses the disk tracked from the measured motion
    (``_gap_track``); simulation coasts the disk in the gap and, on contact, shares
    momentum: w = (w_free + r w2) / (1 + r) (``couple``, called by simerror.simulate)."""

    names: tuple[str, ...] = ("disk_over_motor_inertia",)
    gap: float = 0.01

    def _track(self, sig):
        key = ("gap", self.gap)
        slot = sig.cache.get("disk")
        if slot is None or slot[0] != key:
            slot = (key, _gap_track(sig.position_rad, sig.velocity_rad_s, sig.dt_s, self.gap))
            sig.cache["disk"] = slot
        return slot[1]

    def measured(self, sig):
        w2 = self._track(sig)[1]
        return [-np.append(np.diff(w2), 0.0) / sig.dt_s]

    def init_state(self, sig, idx):
        th2, w2 = self._track(sig)
        return [th2[idx].copy(), w2[idx].copy()]

    def simulate(self, sig, theta, omega, idx, state):
        return [np.zeros_like(omega)]     # acts through ``couple``

    def fast(self, sig):
        return [(None, [(fs.GAP, 1.0, self.gap)])]

    def fast_track(self, sig):
        return 1, self._track(sig)

    def couple(self, state, r, theta, omega, new, dt):
        th2, w2 = state
        r = max(float(r), 0.0)
        th2 = th2 + dt * w2
        d = theta + 0.5 * dt * (omega + new) - th2
        s = np.where(d > 0, 1.0, -1.0)
        hit = (np.abs(d) >= 0.5 * self.gap) & (s * (new - w2) > 0)
        wc = (new + r * w2) / (1.0 + r)
        new = np.where(hit, wc, new)
        w2 = np.where(hit, wc, w2)
        th2 = np.where(hit, theta + 0.5 * dt * (omega + new) - s * 0.5 * self.gap, th2)
        return new, [th2, w2]


def _gap_grid(sig: Signals) -> np.ndarray:
    """Gaps scanned: from 1/300 to 1/3 of the distance the axis covers in one sample
    at top speed (unit-free)."""
    step = speed_scale(sig) * sig.dt_s
    return np.geomspace(step / 300, step / 3, 9)


class Backlash(Effect):
    """A disk behind a gap with rigid contact (impacts share momentum): the gap is
    scanned, the inertia ratio J_disk/J is the one linear coefficient.  (A stiff
    contact's ~kHz ringing is beyond 1 kHz sampling; a spring-damper disk cannot be
    simulated stably at that stiffness.)"""

    name = "backlash"
    continuous = ("gap_rad", "disk_over_motor_inertia")
    #: scanned and refined on simulation error: as a regressor the disk's acceleration
    #: in contact is the motor's own (the output), which equation error cannot use
    by_simulation = True

    def grid(self, sig, base):
        return [{"gap_rad": float(g), "disk_over_motor_inertia": float(r)}
                for g in _gap_grid(sig) for r in (0.2, 0.5, 1.0, 2.0)]

    def build(self, sig, base, hp):
        terms = base.terms()
        fixed = {**base.fixed(), sum(len(t.names) for t in terms): hp["disk_over_motor_inertia"]}
        return terms + [RigidGapTerm(gap=hp["gap_rad"])], fixed

    def chain_terms(self, hp):
        return [RigidGapTerm(gap=hp["gap_rad"])], {0: hp["disk_over_motor_inertia"]}

    def describe(self, model, base, hp):
        return dict(hp)
