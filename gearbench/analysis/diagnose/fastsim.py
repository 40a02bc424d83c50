"""Compiled short-horizon simulation (numba) for models whose terms can describe
themselves as feature specs (``Term.fast``); stateful terms (a disk on a shaft, a disk
in a gap, Dahl's state) keep the numpy path in simerror.simulate.

Profiled on EMPS's 25 s, 1 kHz train trace, the numpy simulation (a Python loop over
the horizon's steps, every term's features as small array operations, the friction in
8 sub-steps each) took most of the diagnosis's 333 CPU-seconds; the same arithmetic
per horizon in compiled loops is ~50x faster.  Same equations as simerror.simulate:
Euler velocity, trapezoid angle, friction sub-stepped and linearly implicit in its
slope, the error seen through the SG velocity estimator.
"""
from __future__ import annotations

import numba
import numpy as np

# rigid kinds: evaluated at the step's start (theta, omega, sample index); DAHL is
# -z of a Dahl state, GAP a disk in a backlash gap (acts through rigid contact)
VISC, SPRING, SIN, COS, RSIN, RCOS, DAHL, GAP = 1, 2, 3, 4, 5, 6, 7, 8
# friction kinds: velocity function + shape of the angle (kind = VEL + SHAPE)
F_TANH, F_STRIBECK, F_ABSTANH, F_ABSW = 10, 20, 30, 40
S_ONE, S_SIN, S_COS, S_LEG1, S_LEG2 = 0, 1, 2, 3, 4


def plan(sig, model):
    """The model as arrays for ``run`` or None when a term has no spec.

    Returns (U, rigid kinds, rigid coefficients, rigid params, friction kinds,
    friction coefficients, friction params, state tracks): U the state-free
    acceleration over the whole trace (current taps, constants), each spec's
    coefficient the model's; the tracks (Dahl's z, a gap disk's angle and velocity,
    from the measured motion) start each horizon's states."""
    n = len(sig)
    U = np.zeros(n)
    rk, rc, rp, fk, fc, fp = [], [], [], [], [], []
    tracks = np.zeros((3, 1))
    j = 0
    for t in model.terms:
        spec = t.fast(sig)
        if spec is None:
            return None
        track = t.fast_track(sig) if hasattr(t, "fast_track") else None
        if track is not None:
            if tracks.shape[1] == 1:
                tracks = np.zeros((3, n))
            row, arrays = track
            tracks[row:row + len(arrays)] = arrays
        for (free, parts), c in zip(spec, model.coef[j:j + len(t.names)]):
            c = float(c)
            if free is not None:
                U += c * free
            for kind, mult, *p in parts:
                p = (list(p) + [0.0, 0.0, 0.0, 0.0])[:4]
                if kind >= F_TANH:
                    fk.append(kind), fc.append(c * mult), fp.append(p)
                else:
                    rk.append(kind), rc.append(c * mult), rp.append(p)
        j += len(t.names)
    as2 = lambda p: np.asarray(p, float).reshape(-1, 4)     # noqa: E731
    if rk.count(DAHL) > 1 or rk.count(GAP) > 1:
        return None
    return (U, np.asarray(rk, np.int64), np.asarray(rc, float), as2(rp),
            np.asarray(fk, np.int64), np.asarray(fc, float), as2(fp), tracks)


@numba.njit(cache=True)
def _shape(kind, p, th):  # pragma: no cover - compiled
    s = kind % 10
    if s == S_ONE:
        return 1.0
    if s == S_SIN:
        return np.sin(p[2] * th)
    if s == S_COS:
        return np.cos(p[2] * th)
    x = 2.0 * (th - p[2]) / p[3] - 1.0
    if s == S_LEG1:
        return x
    return 1.5 * x * x - 0.5


@numba.njit(cache=True)
def run(pos, cur, w0, U, starts, horizon, half, dt, h, rk, rc, rp, fk, fc, fp, tracks,
        substeps):  # pragma: no cover - compiled
    """Velocity error (len(starts), horizon) of every horizon (see simerror.simulate).

    One loop nest on purpose (just over 100 lines): the per-step term kinds, the
    friction sub-steps and the contacts share the horizon's scalar state, and a
    compiled kernel split into calls would pass that state back and forth."""
    n = pos.shape[0]
    R = starts.shape[0]
    steps = horizon + half
    nf = fk.shape[0]
    g = np.empty(nf)
    err = np.zeros((R, horizon))
    eth = np.zeros(half + 1 + steps)
    hs = dt / substeps
    for r in range(R):
        s0 = starts[r]
        th = pos[s0]
        w = w0[s0]
        z = tracks[0, s0] if tracks.shape[1] > 1 else 0.0      # Dahl state
        th2 = tracks[1, s0] if tracks.shape[1] > 1 else 0.0    # gap disk
        w2 = tracks[2, s0] if tracks.shape[1] > 1 else 0.0
        for q in range(half + 1):
            eth[q] = 0.0
        for m in range(steps):
            idx = min(s0 + m, n - 2)
            a = U[idx]
            for f in range(rk.shape[0]):
                k = rk[f]
                if k == VISC:
                    a -= rc[f] * w
                elif k == SPRING:
                    a -= rc[f] * th
                elif k == SIN or k == COS:
                    # rp[f, 0] = 1: the mean over the step (periodic.interval_sin_cos)
                    x = rp[f, 2] * th
                    sc = 1.0
                    if rp[f, 0] > 0.0:
                        da = rp[f, 2] * w * dt
                        x += 0.5 * da
                        sc = np.sinc(da / (2.0 * np.pi))
                    a += rc[f] * sc * (np.sin(x) if k == SIN else np.cos(x))
                elif k == RSIN:
                    a += rc[f] * cur[idx] * np.sin(rp[f, 2] * th)
                elif k == RCOS:
                    a += rc[f] * cur[idx] * np.cos(rp[f, 2] * th)
                elif k == DAHL:
                    a -= rc[f] * z
            if nf:
                for f in range(nf):
                    g[f] = fc[f] * _shape(fk[f], fp[f], th)
                v = w
                for _ in range(substeps):
                    fr = 0.0
                    sl = 0.0
                    for f in range(nf):
                        vel = fk[f] - fk[f] % 10
                        eps = fp[f, 0]
                        if vel == F_ABSW:
                            fr -= g[f] * abs(v)
                            sl -= g[f] * (1.0 if v > 0 else (-1.0 if v < 0 else 0.0))
                            continue
                        x = v / eps
                        if x > 19.0 or x < -19.0:   # tanh is +-1 to double precision
                            t = 1.0 if x > 0 else -1.0
                            ds = 0.0
                        else:
                            t = np.tanh(x)
                            ds = (1.0 - t * t) / eps
                        if vel == F_TANH:
                            fr -= g[f] * t
                            sl -= g[f] * ds
                        elif vel == F_STRIBECK:
                            ws = fp[f, 1]
                            e = np.exp(-(v / ws) ** 2)
                            fr -= g[f] * t * e
                            sl -= g[f] * (ds - 2.0 * v / ws ** 2 * t) * e
                        else:
                            sg = 1.0 if v > 0 else (-1.0 if v < 0 else 0.0)
                            fr -= g[f] * abs(t)
                            sl -= g[f] * sg * ds
                    v = v + hs * (a + fr) / (1.0 - hs * min(sl, 0.0))
                new = v
            else:
                new = w + dt * a
            for f in range(rk.shape[0]):
                if rk[f] == GAP:     # rigid contact across the gap (RigidGapTerm.couple)
                    rr = max(rc[f], 0.0)
                    gap = rp[f, 0]
                    th2 = th2 + dt * w2
                    d = th + 0.5 * dt * (w + new) - th2
                    sd = 1.0 if d > 0 else -1.0
                    if abs(d) >= 0.5 * gap and sd * (new - w2) > 0:
                        new = (new + rr * w2) / (1.0 + rr)
                        w2 = new
                        th2 = th + 0.5 * dt * (w + new) - sd * 0.5 * gap
                elif rk[f] == DAHL:  # Dahl's state over the step (DahlTerm.step_state)
                    dx = w * dt
                    if dx != 0.0:
                        sz = 1.0 if dx > 0 else -1.0
                        z = sz + (z - sz) * np.exp(-abs(dx) / rp[f, 0])
            th = th + 0.5 * dt * (w + new)
            w = new
            eth[half + 1 + m] = th - pos[idx + 1]
        for k in range(horizon):
            acc = 0.0
            for jj in range(h.shape[0]):
                acc += h[jj] * eth[1 + jj + k]
            err[r, k] = acc
    return err
