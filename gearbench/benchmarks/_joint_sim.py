"""Simulated robot-joint traces with known truth (for ``bench accuracy``'s real section).

An industrial arm's joint moved alone, as the held-out robot data of issue 23 describes:
a motor behind a gear of ratio N drives the joint through a cascade position loop
(position P → speed PI → current loop, 1 kHz), slow reversing motion (a dozen
reversals, up to ~1 rad/s at the joint), Coulomb friction at least half the rms
current, gravity on some joints, a few % of torque ripple in the motor angle and a
coloured (low-pass) disturbance torque that no model term describes. Recorded: the
*joint* (load-side) angle on a 2^17-count encoder and the motor current with noise,
both at 100 Hz. Truth is in the joint's frame: J (reflected inertia, kg m²), Fv, Fc
(N m s/rad, N m) and the torque per ampere N·Kt the user knows from the drive's data.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Joint:
    name: str
    J: float                 # kg m², reflected to the joint
    Fv: float                # N m s/rad at the joint
    Fc: float                # N m at the joint
    gravity_nm: float        # m g l: gravity torque G cos(q)
    gain_nm_a: float         # N·Kt, joint torque per ampere
    ripple: float = 0.03     # torque ripple, fraction of the motor torque, order 6 per motor rev
    ratio: float = 100.0
    disturbance: float = 0.03  # rms coloured disturbance, fraction of the rms motor torque


JOINTS = (
    Joint("base", J=6.0, Fv=25.0, Fc=40.0, gravity_nm=0.0, gain_nm_a=60.0),
    Joint("shoulder", J=4.0, Fv=20.0, Fc=35.0, gravity_nm=25.0, gain_nm_a=60.0),
    Joint("wrist", J=0.05, Fv=0.8, Fc=1.5, gravity_nm=0.4, gain_nm_a=4.0),
)


def reference(t: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Slow reversing joint reference (rad) and its speed: two sines, ~1 rad/s peak."""
    rng = np.random.default_rng(seed)
    f1, f2 = 0.2 * rng.uniform(0.9, 1.1), 0.53 * rng.uniform(0.9, 1.1)
    a1, a2 = 0.55, 0.12
    p2 = rng.uniform(0, 2 * np.pi)
    q = a1 * np.sin(2 * np.pi * f1 * t) + a2 * np.sin(2 * np.pi * f2 * t + p2)
    w = a1 * 2 * np.pi * f1 * np.cos(2 * np.pi * f1 * t) + a2 * 2 * np.pi * f2 * np.cos(2 * np.pi * f2 * t + p2)
    return q, w


def simulate_joint(joint: Joint, *, duration_s: float = 40.0, rate_hz: float = 100.0,
                   seed: int = 0) -> dict:
    """One run → {time_s, position_rad (joint), current_a, command (speed reference, rad/s), truth}."""
    rng = np.random.default_rng([seed, 23])
    dt = 1e-3
    n = int(round(duration_s / dt))
    t = np.arange(n) * dt
    q_ref, w_ref = reference(t, seed)
    # loop gains from the inertia: speed loop ~8 Hz, position loop ~2 Hz
    wc = 2 * np.pi * 8.0
    kv = wc * joint.J / joint.gain_nm_a          # A per rad/s
    ki = kv * wc / 4.0
    kp = 2 * np.pi * 2.0
    tau_i = 0.5e-3
    eps = 1e-3
    # coloured disturbance: first-order low-pass (0.5 s) white noise, scaled after a first pass
    white = rng.standard_normal(n)
    dist = np.empty(n)
    acc = 0.0
    a_lp = math.exp(-dt / 0.5)
    for k in range(n):
        acc = a_lp * acc + math.sqrt(1 - a_lp * a_lp) * white[k]
        dist[k] = acc
    typical = math.hypot(joint.Fc, joint.gravity_nm) + joint.Fv * 0.7
    dist *= joint.disturbance * typical
    q, w, i, integ = q_ref[0], 0.0, 0.0, 0.0
    Q, I = np.empty(n), np.empty(n)
    G, N = joint.gravity_nm, joint.ratio
    for k in range(n):
        Q[k], I[k] = q, i
        v_cmd = w_ref[k] + kp * (q_ref[k] - q)
        err = v_cmd - w
        integ += ki * err * dt
        i_cmd = kv * err + integ
        i += (i_cmd - i) * dt / tau_i if tau_i > dt else (i_cmd - i)
        torque = joint.gain_nm_a * i * (1.0 + joint.ripple * math.sin(6 * N * q))
        fr = joint.Fc * math.tanh(w / eps) + joint.Fv * w
        acc_ = (torque - fr - G * math.cos(q) - dist[k]) / joint.J
        # stiction: a stopped joint stays until the drive beats Coulomb friction
        if abs(w) < 1e-6 and abs(torque - G * math.cos(q) - dist[k]) <= joint.Fc:
            w_new = 0.0
        else:
            w_new = w + acc_ * dt
            if w != 0.0 and w_new * w < 0 and abs(torque - G * math.cos(q) - dist[k]) <= joint.Fc:
                w_new = 0.0
        q += 0.5 * (w + w_new) * dt
        w = w_new
    step = max(1, int(round(1.0 / (rate_hz * dt))))
    counts = 2 ** 17 / (2 * np.pi)
    qs = np.round(Q[::step] * counts) / counts
    i_noise = 0.01 * float(np.max(np.abs(I)))
    cur = I[::step] + rng.normal(0, i_noise, len(qs))
    cur = np.round(cur / 1e-3) * 1e-3
    return {"time_s": t[::step], "position_rad": qs, "current_a": cur, "command": w_ref[::step],
            "truth": {"J": joint.J, "Fv": joint.Fv, "Fc": joint.Fc, "gain_nm_a": joint.gain_nm_a,
                      "gravity_nm": joint.gravity_nm,
                      "coulomb_share_of_rms_current": float(joint.Fc / joint.gain_nm_a
                                                            / np.sqrt(np.mean(I ** 2)))}}
