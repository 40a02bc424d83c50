"""A second robot-joint simulator, written apart from ``_joint_sim`` and unlike it, for
``bench accuracy``'s real section: a family the identification was not developed on.

Where ``_joint_sim`` has a cascade position → speed → current loop, a tanh-smoothed
Coulomb sign, two-sine motion and ripple, this one has:

* **stiction** (Karnopp: the joint sticks while |applied torque| < Fs and only then
  breaks away; friction never reverses the motion within a step),
* **Stribeck friction** (Fc + (Fs − Fc)·exp(−(ω/ωs)²), optional: the model's sign(θ')
  does not hold it, so Fv and Fc are biased by it, J should not be),
* a **PID position loop** with feed-forward-free tracking of either two sines or
  **point-to-point trapezoidal moves with dwells** (the joint sits stuck between moves),
* a first-order current loop and a coloured (Ornstein-Uhlenbeck) disturbance torque,
  gravity G·cos(q), a 2^17-count joint encoder, white current noise, recorded at 100 Hz.

Truth is in the joint's frame: J, Fv, Fc (sliding Coulomb level) and the torque per
ampere the user knows from the drive's data.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class StickJoint:
    name: str
    J: float              # kg m² at the joint
    Fv: float             # N m s/rad
    Fc: float             # N m, sliding Coulomb level
    Fs: float             # N m, breakaway (static) level; Fs > Fc adds Stribeck
    gravity_nm: float     # G in G cos(q)
    gain_nm_a: float      # joint torque per ampere
    stribeck_rad_s: float = 0.05


STICK_JOINTS = (
    StickJoint("wrist", J=0.05, Fv=0.8, Fc=1.5, Fs=1.5, gravity_nm=0.4, gain_nm_a=4.0),
    StickJoint("shoulder", J=4.0, Fv=20.0, Fc=35.0, Fs=35.0, gravity_nm=25.0, gain_nm_a=60.0),
    StickJoint("base+Stribeck", J=6.0, Fv=25.0, Fc=40.0, Fs=48.0, gravity_nm=0.0, gain_nm_a=60.0),
)


def _two_sines(t: np.ndarray, rng) -> tuple[np.ndarray, np.ndarray]:
    f1, f2, p = rng.uniform(0.15, 0.25), rng.uniform(0.4, 0.6), rng.uniform(0, 2 * np.pi)
    q = 0.6 * np.sin(2 * np.pi * f1 * t) + 0.12 * np.sin(2 * np.pi * f2 * t + p)
    w = 0.6 * 2 * np.pi * f1 * np.cos(2 * np.pi * f1 * t) + 0.12 * 2 * np.pi * f2 * np.cos(2 * np.pi * f2 * t + p)
    return q, w


def _point_to_point(t: np.ndarray, rng) -> tuple[np.ndarray, np.ndarray]:
    """Trapezoidal-velocity moves to random targets in ±0.8 rad, 0.2-0.8 s dwells between."""
    q, w = np.zeros_like(t), np.zeros_like(t)
    pos, start = 0.0, 0.5
    while start < t[-1]:
        target = rng.uniform(-0.8, 0.8)
        vmax, amax = rng.uniform(0.4, 1.0), rng.uniform(1.5, 4.0)
        dist, sgn = abs(target - pos), math.copysign(1.0, target - pos)
        ta = vmax / amax
        if dist < vmax * ta:                       # triangular move
            ta = math.sqrt(dist / amax)
            vmax, tc = amax * ta, 0.0
        else:
            tc = (dist - vmax * ta) / vmax
        tau = t - start
        m = tau >= 0
        tau = tau[m]
        td = tau - ta - tc
        v = np.where(tau < ta, amax * tau, np.where(td < 0, vmax, np.maximum(vmax - amax * td, 0.0)))
        x = np.where(tau < ta, 0.5 * amax * tau ** 2,
                     np.where(td < 0, 0.5 * amax * ta ** 2 + vmax * (tau - ta),
                              0.5 * amax * ta ** 2 + vmax * tc
                              + np.where(td < ta, vmax * td - 0.5 * amax * td ** 2, 0.5 * vmax * ta)))
        q[m], w[m] = pos + sgn * x, sgn * v
        pos, start = target, start + 2 * ta + tc + rng.uniform(0.2, 0.8)
    return q, w


def simulate_stick_joint(joint: StickJoint, *, motion: str = "sine", duration_s: float = 60.0,
                         rate_hz: float = 100.0, seed: int = 0) -> dict:
    """One run → {time_s, position_rad (joint), current_a, command (the speed reference,
    rad/s), truth}; ``motion`` is ``sine``
    (two sines, ~1 rad/s) or ``p2p`` (point-to-point moves with dwells)."""
    rng = np.random.default_rng([seed, 2317])
    dt = 5e-4
    n = int(round(duration_s / dt))
    t = np.arange(n) * dt
    q_ref, w_ref = (_two_sines if motion == "sine" else _point_to_point)(t, rng)
    J, g = joint.J, joint.gain_nm_a
    wn = 2 * np.pi * 6.0                           # position loop ~6 Hz, PID on the joint
    kp, kd, ki = J * wn ** 2, 2 * 0.8 * J * wn, J * wn ** 3 / 8
    a_cur = dt / 1e-3                              # current loop, 1 ms
    ou_a, ou_s = dt / 0.3, 0.06 * joint.Fc * math.sqrt(dt)
    noise = rng.standard_normal(n)
    q = w = integ = cur = dist = 0.0
    Q, I = np.empty(n), np.empty(n)
    for k in range(n):
        e = q_ref[k] - q
        integ += e * dt
        cur += ((kp * e + kd * (w_ref[k] - w) + ki * integ) / g - cur) * a_cur
        dist += -dist * ou_a + ou_s * noise[k]
        applied = g * cur + dist - joint.gravity_nm * math.cos(q)
        if w == 0.0 and abs(applied) <= joint.Fs:
            pass                                   # stuck: static friction balances it
        else:
            s = math.copysign(1.0, w if w != 0.0 else applied)
            fr = joint.Fv * w + s * (joint.Fc + (joint.Fs - joint.Fc)
                                     * math.exp(-(w / joint.stribeck_rad_s) ** 2))
            w_new = w + (applied - fr) / J * dt
            w = 0.0 if w != 0.0 and w_new * w < 0 else w_new   # friction stops, never reverses
        q += w * dt
        Q[k], I[k] = q, cur
    step = int(round(1.0 / (rate_hz * dt)))
    counts = 2 * np.pi / 2 ** 17
    current = I[::step] + rng.normal(0.0, 0.01 * float(np.std(I)), len(I[::step]))
    return {"time_s": t[::step], "position_rad": np.round(Q[::step] / counts) * counts,
            "current_a": current, "command": w_ref[::step],
            "truth": {"J": joint.J, "Fv": joint.Fv, "Fc": joint.Fc}}
