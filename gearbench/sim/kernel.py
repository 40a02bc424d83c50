"""Compiled inner loop of the simulated bench (numba ``@njit(cache=True)``).

Everything lives in flat float64 vectors so that one call crosses the Python/numba
boundary with few arguments (``BenchWorld.step`` must be cheap):

* ``pp``   parameters: two motor blocks of ``MP`` entries (axis 0 = "in",
  1 = "out") followed by the plant block at ``PB`` (indices below);
* ``st``   state: two axis blocks of ``SS`` entries, then the global block at ``GB``;
* ``hist`` (2, HIST) ring buffer of true current per sample, for the measurement delay.

One sample period is ``NSUB`` substeps of ``DT``. Each substep: drive loops tick
(every ``LOOPK`` substeps: encoder-difference velocity estimate, low-pass, PI or
torque command), first-order current lag (exact exponential), electromagnetic torque,
then a linearly-implicit Euler step for the mechanics (friction's slope treated
implicitly so the smoothed sign stays stable for small eps), symplectic for springs.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

# ---- motor block (per axis, base a*MP)
KT, J, D, C, TC, TS, WS, EPS, COG_A, COG_N, RIP_A, RIP_N, KSAT, OFF, GAIN, NOISE, RES, \
    Q, BETA, DELAY, KSH, CSH, BL, JD, DISK, KP, KI, ILIM, WLIM, LOOPK, VALPHA, LOOPT, \
    MODE, SP_INTERP, NAVG, TCA, DA, TPA, TPN = range(39)
MP = 40
# ---- plant block (base PB)
PB = 2 * MP
COUPLING, RATIO, ETA0, ETA_SLOPE, ETA_MIN, DRAG_TC, DRAG_D, PULS_A, PULS_K, MESH_K, \
    MESH_C, MESH_BL, NSUB, DT, DRAG_EPS, PERIOD = range(16)
NPP = PB + 20
# ---- state (per axis, base a*SS)
TH, W, THD, WD, I, ICMD, INT, VEST, CPREV, SP, SPA, IACC, IMEAN = range(13)
SS = 14
GB = 2 * SS
SUB, THOUT_OFF, E_IN, E_OUT = range(4)
NST = GB + 8
HIST = 256
# ---- measurement row
(M_POS_IN, M_VEL_IN, M_CUR_IN, M_CMD_IN, M_POS_OUT, M_VEL_OUT, M_CUR_OUT, M_CMD_OUT,
 M_TH_IN, M_W_IN, M_I_IN, M_TH_OUT, M_W_OUT, M_I_OUT, M_P_IN, M_P_OUT) = range(16)
NOUT = 16

MODE_OFF, MODE_VELOCITY, MODE_TORQUE = 0.0, 1.0, 2.0
COUPLING_NONE, COUPLING_RIGID, COUPLING_BACKLASH = 0.0, 1.0, 2.0
DISK_NONE, DISK_RIGID, DISK_TWO_MASS = 0.0, 1.0, 2.0


@njit(cache=True)
def _friction(w, tc, ts, ws, eps, d):
    """Coulomb + Stribeck (smoothed sign) + viscous friction and its slope d f/d ω."""
    th = math.tanh(w / eps)
    s = tc
    ds = 0.0
    if ts > 0.0:
        e = math.exp(-(w / ws) ** 2)
        s += ts * e
        ds = ts * e * (-2.0 * w / (ws * ws))
    f = s * th + d * w
    df = ds * th + s * (1.0 - th * th) / eps + d
    return f, max(df, 0.0)


@njit(cache=True)
def _motor_friction(pp, b, w, th):
    """Friction of one motor; optional direction-dependent Coulomb/viscous parts
    (Tc ± TCA, D ± DA) and a Coulomb torque varying with the rotor angle
    (Tc·(1 + TPA·sin(TPN·θ))) — all off (0) by default."""
    f, df = _friction(w, pp[b + TC], pp[b + TS], pp[b + WS], pp[b + EPS], pp[b + D])
    tca = pp[b + TCA]
    da = pp[b + DA]
    tpa = pp[b + TPA]
    if tca != 0.0 or da != 0.0 or tpa != 0.0:
        eps = pp[b + EPS]
        t = math.tanh(w / eps)
        dt_ = (1.0 - t * t) / eps
        p = pp[b + TC] * tpa * math.sin(pp[b + TPN] * th) if tpa > 0.0 else 0.0
        f += tca * t * t + da * t * w + p * t
        df = max(df + 2.0 * tca * t * dt_ + da * (t + w * dt_) + p * dt_, 0.0)
    return f, df


@njit(cache=True)
def _em_torque(pp, b, th, i):
    """Kt_eff(i)·i·(1 + ripple) − cogging − C θ: every rotor torque but friction."""
    kt = pp[b + KT]
    ks = pp[b + KSAT]
    if ks > 0.0:
        kt = kt / (1.0 + (i / ks) ** 2)
    t = kt * i
    if pp[b + RIP_A] > 0.0:
        t *= 1.0 + pp[b + RIP_A] * math.sin(pp[b + RIP_N] * th)
    if pp[b + COG_A] > 0.0:
        t -= pp[b + COG_A] * math.sin(pp[b + COG_N] * th)
    if pp[b + C] > 0.0:
        t -= pp[b + C] * th
    return t


@njit(cache=True)
def _gap_torque(delta, ddelta, k, c, gap):
    """Spring-damper through a dead zone of total width ``gap``; contact cannot pull."""
    if gap <= 0.0:
        return k * delta + c * ddelta
    half = 0.5 * gap
    if delta > half:
        t = k * (delta - half) + c * ddelta
        return max(t, 0.0)
    if delta < -half:
        t = k * (delta + half) + c * ddelta
        return min(t, 0.0)
    return 0.0


@njit(cache=True)
def _drive_tick(pp, st, a, frac):
    """One period of the drive's own loop: velocity estimate from the quantised
    encoder (count difference, first-order low-pass), then the current command.

    ``frac`` is how far the SYNC period will be at the *next* loop tick (0..1]: in
    velocity mode with ``SP_INTERP`` the setpoint ramps linearly from the previous
    SYNC setpoint (``SPA``) to the new one (``SP``), reaching it at the period's last
    tick, as cyclic-synchronous drives interpolate; otherwise it is applied as a step."""
    b = a * MP
    s = a * SS
    q = pp[b + Q]
    c = math.floor(st[s + TH] / q)
    vraw = (c - st[s + CPREV]) * q / pp[b + LOOPT]
    st[s + CPREV] = c
    st[s + VEST] += pp[b + VALPHA] * (vraw - st[s + VEST])
    v = st[s + VEST]
    lim = pp[b + ILIM]
    wlim = pp[b + WLIM]
    mode = pp[b + MODE]
    if mode == MODE_VELOCITY:
        sp = st[s + SP]
        if pp[b + SP_INTERP] > 0.0:
            sp = st[s + SPA] + (sp - st[s + SPA]) * frac
        sp = min(max(sp, -wlim), wlim)
        e = sp - v
        new_int = st[s + INT] + pp[b + KI] * e * pp[b + LOOPT]
        u = pp[b + KP] * e + new_int
        # anti-windup: stop integrating while saturated in the direction of the error
        if not (abs(u) > lim and u * e > 0.0):
            st[s + INT] = new_int
        icmd = min(max(pp[b + KP] * e + st[s + INT], -lim), lim)
    elif mode == MODE_TORQUE:
        icmd = min(max(st[s + SP], -lim), lim)
        # torque mode folds the current back above the speed limit (as drives do)
        if v > wlim:
            icmd = min(icmd, pp[b + KP] * (wlim - v))
        elif v < -wlim:
            icmd = max(icmd, pp[b + KP] * (-wlim - v))
        icmd = min(max(icmd, -lim), lim)
    else:
        icmd = 0.0
        st[s + INT] = 0.0
    st[s + ICMD] = icmd


@njit(cache=True)
def _free_axis(pp, st, a, te, dt):
    """One uncoupled motor, optionally with a disk (rigid or on a compliant/gapped shaft)."""
    b = a * MP
    s = a * SS
    w = st[s + W]
    f, df = _motor_friction(pp, b, w, st[s + TH])
    disk = pp[b + DISK]
    if disk == DISK_TWO_MASS:
        tau = _gap_torque(st[s + TH] - st[s + THD], w - st[s + WD], pp[b + KSH], pp[b + CSH],
                          pp[b + BL])
        w_new = w + dt * (te - f - tau) / (pp[b + J] + dt * df)
        wd_new = st[s + WD] + dt * tau / pp[b + JD]
        st[s + W] = w_new
        st[s + TH] += dt * w_new
        st[s + WD] = wd_new
        st[s + THD] += dt * wd_new
    else:
        jt = pp[b + J] + (pp[b + JD] if disk == DISK_RIGID else 0.0)
        w_new = w + dt * (te - f) / (jt + dt * df)
        st[s + W] = w_new
        st[s + TH] += dt * w_new
        st[s + WD] = w_new
        st[s + THD] = st[s + TH]


@njit(cache=True)
def _mesh_eta(pp, w):
    eta = pp[PB + ETA0] - pp[PB + ETA_SLOPE] * abs(w)
    return min(max(eta, pp[PB + ETA_MIN]), 1.0)


@njit(cache=True)
def _drag(pp, w):
    t = math.tanh(w / pp[PB + DRAG_EPS])
    return (pp[PB + DRAG_TC] * t + pp[PB + DRAG_D] * w,
            pp[PB + DRAG_TC] * (1.0 - t * t) / pp[PB + DRAG_EPS] + pp[PB + DRAG_D])


@njit(cache=True)
def _kinematics(pp, th):
    """Ratio r = dθ_out/dθ_in, its derivative dr/dθ_in and θ_out(θ_in) − offset."""
    n = pp[PB + RATIO]
    a = pp[PB + PULS_A]
    if a > 0.0:
        k = pp[PB + PULS_K]
        return ((1.0 + a * math.sin(k * th)) / n, a * k * math.cos(k * th) / n,
                (th + a / k * (1.0 - math.cos(k * th))) / n)
    return 1.0 / n, 0.0, th / n


@njit(cache=True)
def _rigid_reducer(pp, st, te_in, te_out, dt):
    """Single degree of freedom θ_in (output reflected through r(θ_in)).

    Input: J_in ω̇ = Te_in − f_in − T_a; output: J_out ω̇_out = T_b + Te_out − f_out with
    ω_out = r ω, mesh T_b = e (T_a − drag) / r, e = η when power flows in → out, else 1/η.
    Eliminating T_a, T_b: ω̇ (e J_in + r² J_out) = e X + r Y − r r' J_out ω²,
    X = Te_in − f_in − drag, Y = Te_out − f_out. The sign of T_b (for r' = 0) does not
    depend on e, so the power-flow direction is decided before choosing e.
    """
    bi = 0
    bo = MP
    th = st[TH]
    w = st[W]
    r, rp, _ = _kinematics(pp, th)
    eta = _mesh_eta(pp, w)
    fi, dfi = _motor_friction(pp, bi, w, th)
    dr, ddr = _drag(pp, w)
    fo, dfo = _motor_friction(pp, bo, r * w, st[SS + TH])
    jin = pp[bi + J]
    jout = pp[bo + J]
    x = te_in - fi - dr
    y = te_out - fo
    # direction from the quasi-static balance (sign of T_b without the pulsation's
    # inertial term): the CVT's periodic inertial power then passes with the same
    # factor both ways, so it nets to zero and the mean efficiency is exactly η(ω_in)
    sgn = x * r * jout - jin * y
    e = eta if sgn * w >= 0.0 else 1.0 / eta
    force = e * x + r * y - r * rp * jout * w * w
    mass = e * jin + r * r * jout
    damp = e * (dfi + ddr) + r * r * dfo
    w_new = w + dt * force / (mass + dt * damp)
    dw = w_new - w
    # shaft torques with the same linearised friction, for P_in / P_out at the reducer shafts
    ta = te_in - (fi + dfi * dw) - jin * dw / dt
    tb = e * (ta - (dr + ddr * dw)) / r
    th_new = th + dt * w_new
    r2, _, kin = _kinematics(pp, th_new)
    st[GB + E_IN] += ta * w_new * dt
    st[GB + E_OUT] += tb * r * w_new * dt
    st[TH] = th_new
    st[W] = w_new
    st[SS + TH] = st[GB + THOUT_OFF] + kin
    st[SS + W] = r2 * w_new
    for s in (0, SS):
        st[s + THD] = st[s + TH]
        st[s + WD] = st[s + W]


@njit(cache=True)
def _backlash_reducer(pp, st, te_in, te_out, dt):
    """Two masses (input rotor, output rotor) through a gapped mesh spring at the
    input shaft; the output side receives n·e·T_mesh (e as in ``_rigid_reducer``)."""
    n = pp[PB + RATIO]
    wi = st[W]
    wo = st[SS + W]
    delta = st[TH] - n * (st[SS + TH] - st[GB + THOUT_OFF])
    tm = _gap_torque(delta, wi - n * wo, pp[PB + MESH_K], pp[PB + MESH_C], pp[PB + MESH_BL])
    eta = _mesh_eta(pp, wi)
    e = eta if tm * wi >= 0.0 else 1.0 / eta
    fi, dfi = _motor_friction(pp, 0, wi, st[TH])
    dr, ddr = _drag(pp, wi)
    fo, dfo = _motor_friction(pp, MP, wo, st[SS + TH])
    wi_new = wi + dt * (te_in - fi - dr - tm) / (pp[J] + dt * (dfi + ddr))
    wo_new = wo + dt * (te_out - fo + n * e * tm) / (pp[MP + J] + dt * dfo)
    st[GB + E_IN] += (tm + dr + ddr * (wi_new - wi)) * wi_new * dt
    st[GB + E_OUT] += n * e * tm * wo_new * dt
    st[W] = wi_new
    st[TH] += dt * wi_new
    st[SS + W] = wo_new
    st[SS + TH] += dt * wo_new
    for s in (0, SS):
        st[s + THD] = st[s + TH]
        st[s + WD] = st[s + W]


@njit(cache=True)
def _advance(pp, st):
    """Advance one sample period (NSUB substeps)."""
    dt = pp[PB + DT]
    nsub = int(pp[PB + NSUB])
    coupling = pp[PB + COUPLING]
    for a in range(2):
        st[a * SS + IACC] = 0.0
    for m in range(nsub):
        sub = st[GB + SUB]
        for a in range(2):
            loopk = pp[a * MP + LOOPK]
            if sub % loopk == 0.0:
                _drive_tick(pp, st, a, min(1.0, (m + loopk) / nsub))
        st[GB + SUB] = sub + 1.0
        for a in range(2):
            s = a * SS
            st[s + I] += (st[s + ICMD] - st[s + I]) * pp[a * MP + BETA]
            # the drive reports the mean current of its last current-loop cycle(s)
            if m >= nsub - min(pp[a * MP + NAVG], nsub):
                st[s + IACC] += st[s + I]
        te_in = _em_torque(pp, 0, st[TH], st[I])
        te_out = _em_torque(pp, MP, st[SS + TH], st[SS + I])
        if coupling == COUPLING_RIGID:
            _rigid_reducer(pp, st, te_in, te_out, dt)
        elif coupling == COUPLING_BACKLASH:
            _backlash_reducer(pp, st, te_in, te_out, dt)
        else:
            _free_axis(pp, st, 0, te_in, dt)
            _free_axis(pp, st, 1, te_out, dt)
    for a in range(2):
        s = a * SS
        st[s + SPA] = st[s + SP]
        st[s + IMEAN] = st[s + IACC] / min(pp[a * MP + NAVG], nsub)


@njit(cache=True)
def measure(pp, st, hist, k, noise, out):
    """What the drives report at sample index ``k`` (state as it is now).

    Encoder: floor to a count. Current: the mean true current over the period's last
    ``NAVG`` substeps (the drive's current-loop cycle), ``DELAY`` samples ago,
    ·gain + offset + noise, rounded to the resolution. Also the true values and the
    mean shaft powers over the last period (for truth checks); resets the energy sums.
    """
    for a in range(2):
        b = a * MP
        s = a * SS
        q = pp[b + Q]
        hist[a, k % HIST] = st[s + IMEAN]
        d = int(pp[b + DELAY])
        i_d = hist[a, (k - d) % HIST] if k - d >= 0 else 0.0
        im = pp[b + GAIN] * i_d + pp[b + OFF] + noise[a] * pp[b + NOISE]
        res = pp[b + RES]
        if res > 0.0:
            im = math.floor(im / res + 0.5) * res
        o = 4 * a
        out[o + 0] = math.floor(st[s + TH] / q) * q
        out[o + 1] = st[s + VEST]
        out[o + 2] = im
        out[o + 3] = st[s + ICMD]
        o = 8 + 3 * a
        out[o + 0] = st[s + TH]
        out[o + 1] = st[s + W]
        out[o + 2] = st[s + I]
    period = pp[PB + PERIOD]
    out[M_P_IN] = st[GB + E_IN] / period
    out[M_P_OUT] = st[GB + E_OUT] / period
    st[GB + E_IN] = 0.0
    st[GB + E_OUT] = 0.0


@njit(cache=True)
def run(pp, st, hist, setpoints, noise, k0, out):
    """For each row j: apply ``setpoints[j]`` (in, out), advance one period, measure
    sample ``k0 + j + 1`` with ``noise[j]`` into ``out[j]``."""
    for j in range(setpoints.shape[0]):
        st[SP] = setpoints[j, 0]
        st[SS + SP] = setpoints[j, 1]
        _advance(pp, st)
        measure(pp, st, hist, k0 + j + 1, noise[j], out[j])


def new_state() -> tuple[np.ndarray, np.ndarray]:
    return np.zeros(NST), np.zeros((2, HIST))
