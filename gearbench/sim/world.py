"""``BenchWorld``: one physics world with two drive axes, "in" and "out", advanced one
sample period per ``step()`` — what the emulated drives put behind CANopen/Modbus.

Batch runs (``simulate_motor``, ``simulate_bench``) use ``BenchWorld.run`` on the
same compiled kernel and the same noise stream, so they give identical numbers to
stepping for a seed.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import ProfileError
from . import kernel as K
from .params import PlantParams

AXES = ("in", "out")
MODES = {"off": K.MODE_OFF, "velocity": K.MODE_VELOCITY, "torque": K.MODE_TORQUE}
COUPLINGS = ("none", "reducer")
NOISE_BLOCK = 4096          # noise rows drawn per block (same for batch and stepping)
MAX_SUBSTEP_S = 5e-5        # finest internal step needed by lag and friction
MAX_SUBSTEPS = 20000        # per sample; beyond that the stiffness is unreasonable


@dataclass(frozen=True, slots=True)
class AxisMeasurement:
    """What one drive measures at a sample instant."""

    position_rad: float          # encoder-quantised
    velocity_rad_s: float        # drive's velocity estimate
    current_a: float             # measured current (noise, offset, resolution, delay)
    current_cmd_a: float         # current command from the drive loop


class BenchWorld:
    """Two motors behind their drives, independent (``mount("none")``, optionally
    each with an inertia disk) or joined by the reducer (``mount("reducer")``).

    Parameters
    ----------
    plant : PlantParams
    seed : noise seed; ``None`` uses ``plant.seed``.
    """

    def __init__(self, plant: PlantParams, *, seed: int | None = None):
        if not isinstance(plant, PlantParams):
            raise TypeError("BenchWorld needs a PlantParams")
        self.plant = plant
        self.seed = plant.seed if seed is None else int(seed)
        self.period_s = float(plant.period_s)
        self.sample_index = 0
        self._rng = np.random.default_rng(self.seed)
        self._noise = np.empty((0, 2))
        self._st, self._hist = K.new_state()
        self._pp = np.zeros(K.NPP)
        self._modes = {"in": "off", "out": "off"}
        self._coupling = "none"
        self._disks = {"in": 0.0, "out": 0.0}
        self._ratio = float(plant.ratio)
        self._build()
        self._last = np.zeros(K.NOUT)
        K.measure(self._pp, self._st, self._hist, 0, self._noise_rows(0, 1)[0], self._last)
        self._sp = np.zeros((1, 2))
        self._out1 = np.zeros((1, K.NOUT))

    # ----------------------------------------------------------------- control
    @property
    def time_s(self) -> float:
        return self.sample_index * self.period_s

    @property
    def coupling(self) -> str:
        return self._coupling

    @property
    def ratio(self) -> float:
        return self._ratio

    def mount(self, *, coupling: str = "none", disk_kgm2: dict[str, float] | None = None) -> None:
        """Change what is mounted: ``"none"`` = motors independent, each optionally with
        a disk of ``disk_kgm2[axis]``; ``"reducer"`` = the reducer joins in → out."""
        if coupling not in COUPLINGS:
            raise ProfileError(f"mount: coupling '{coupling}' unknown; use one of {', '.join(COUPLINGS)}")
        disks = {"in": 0.0, "out": 0.0}
        for axis, j in (disk_kgm2 or {}).items():
            self._axis(axis)
            if not (isinstance(j, (int, float)) and math.isfinite(j) and j >= 0):
                raise ProfileError(f"mount: disk_kgm2.{axis} must be a number >= 0 (got {j!r})")
            disks[axis] = float(j)
        if coupling == "reducer" and any(disks.values()):
            raise ProfileError("mount: disks are for calibration; use coupling='none' with disk_kgm2")
        self._coupling = coupling
        self._disks = disks
        self._build()
        st = self._st
        st[K.THD], st[K.WD] = st[K.TH], st[K.W]
        st[K.SS + K.THD], st[K.SS + K.WD] = st[K.SS + K.TH], st[K.SS + K.W]
        self._couple_output()

    def set_mode(self, axis: str, mode: str) -> None:
        """``"off"`` (no torque), ``"velocity"`` or ``"torque"``; the setpoint resets to 0."""
        a = self._axis(axis)
        if mode not in MODES:
            raise ProfileError(f"set_mode: mode '{mode}' unknown; use one of {', '.join(MODES)}")
        self._modes[axis] = mode
        self._pp[a * K.MP + K.MODE] = MODES[mode]
        self._st[a * K.SS + K.INT] = 0.0
        self._st[a * K.SS + K.SP] = 0.0
        self._st[a * K.SS + K.SPA] = 0.0

    def set_setpoint(self, axis: str, value: float) -> None:
        """rad/s in velocity mode, A in torque mode (clipped to the drive's limits)."""
        a = self._axis(axis)
        v = float(value)
        if not math.isfinite(v):
            raise ProfileError(f"set_setpoint: {axis} setpoint must be finite (got {value!r})")
        self._st[a * K.SS + K.SP] = v

    def set_ratio(self, ratio: float) -> None:
        """CVT only: set the mean ratio n (within the CVT's range); output speed follows."""
        cvt = self.plant.cvt
        if cvt is None:
            raise ProfileError("set_ratio: only a CVT has a settable ratio (plant has no cvt)")
        if not cvt.ratio_min <= ratio <= cvt.ratio_max:
            raise ProfileError(f"set_ratio: {ratio} outside [{cvt.ratio_min}, {cvt.ratio_max}]")
        self._ratio = float(ratio)
        self._pp[K.PB + K.RATIO] = self._ratio
        self._couple_output()

    def mode(self, axis: str) -> str:
        return self._modes[self._axis_name(axis)]

    # --------------------------------------------------------------- stepping
    def step(self) -> dict[str, AxisMeasurement]:
        """Advance one period; return what each drive measures at the new sample instant."""
        self._sp[0, 0] = self._st[K.SP]
        self._sp[0, 1] = self._st[K.SS + K.SP]
        k = self.sample_index
        K.run(self._pp, self._st, self._hist, self._sp, self._noise_rows(k + 1, 1), k, self._out1)
        self.sample_index = k + 1
        self._last = self._out1[0]
        return self.measurement()

    def measurement(self) -> dict[str, AxisMeasurement]:
        """The measurement at the current sample index (index 0 before any step)."""
        o = self._last.tolist()
        return {"in": AxisMeasurement(o[0], o[1], o[2], o[3]),
                "out": AxisMeasurement(o[4], o[5], o[6], o[7])}

    def run(self, in_setpoints: np.ndarray, out_setpoints: np.ndarray) -> np.ndarray:
        """Batch stepping: row j applies the setpoints, advances one period and holds the
        measurement of the next sample (columns ``gearbench.sim.kernel.M_*``, 16 wide:
        measured pos/vel/current/cmd per axis, true θ/ω/i per axis, mean P_in/P_out at
        the reducer shafts over the period)."""
        sp = np.ascontiguousarray(np.column_stack([np.asarray(in_setpoints, float),
                                                   np.asarray(out_setpoints, float)]))
        n = sp.shape[0]
        out = np.zeros((n, K.NOUT))
        if n == 0:
            return out
        if not np.isfinite(sp).all():
            raise ProfileError("simulation: setpoints contain NaN/inf; give finite commands")
        k = self.sample_index
        K.run(self._pp, self._st, self._hist, sp, self._noise_rows(k + 1, n), k, out)
        self.sample_index = k + n
        self._last = out[-1].copy()
        self._st[K.SP], self._st[K.SS + K.SP] = sp[-1]
        return out

    def last_row(self) -> np.ndarray:
        """The full 16-column measurement row of the current sample (truth included)."""
        return self._last.copy()

    # ---------------------------------------------------------------- internal
    def _axis_name(self, axis: str) -> str:
        if axis not in AXES:
            raise ProfileError(f"axis '{axis}' unknown; use 'in' or 'out'")
        return axis

    def _axis(self, axis: str) -> int:
        return AXES.index(self._axis_name(axis))

    def _noise_rows(self, k: int, n: int) -> np.ndarray:
        """Standard-normal rows for sample indices k..k+n-1, drawn in fixed blocks."""
        while self._noise.shape[0] < k + n:
            self._noise = np.concatenate([self._noise, self._rng.standard_normal((NOISE_BLOCK, 2))])
        return self._noise[k:k + n]

    def _couple_output(self) -> None:
        """Make the output shaft consistent with the input when the reducer is mounted."""
        st = self._st
        if self._pp[K.PB + K.COUPLING] == K.COUPLING_RIGID:
            r, _, kin = _kinematics_py(self._pp, st[K.TH])
            st[K.GB + K.THOUT_OFF] = st[K.SS + K.TH] - kin
            st[K.SS + K.W] = r * st[K.W]
        elif self._pp[K.PB + K.COUPLING] == K.COUPLING_BACKLASH:
            st[K.GB + K.THOUT_OFF] = st[K.SS + K.TH] - st[K.TH] / self._ratio

    def _build(self) -> None:
        """Fill the flat parameter vector for the kernel from the plant and the mount."""
        p = self.plant
        pp = self._pp
        pp[:] = 0.0
        reducer = self._coupling == "reducer"
        if not reducer:
            pp[K.PB + K.COUPLING] = K.COUPLING_NONE
        elif p.backlash_rad > 0:
            pp[K.PB + K.COUPLING] = K.COUPLING_BACKLASH
        else:
            pp[K.PB + K.COUPLING] = K.COUPLING_RIGID
        dt = _substep(p, self._coupling, self._disks, self._ratio)
        nsub = int(round(p.period_s / dt))
        pp[K.PB + K.NSUB] = nsub
        pp[K.PB + K.DT] = p.period_s / nsub
        dt = p.period_s / nsub
        pp[K.PB + K.PERIOD] = p.period_s
        pp[K.PB + K.RATIO] = self._ratio
        if p.cvt is not None:
            pp[K.PB + K.ETA0] = p.cvt.eta_max
            pp[K.PB + K.ETA_SLOPE] = p.cvt.eta_slope_per_rad_s
            pp[K.PB + K.ETA_MIN] = p.cvt.eta_min
            pp[K.PB + K.PULS_A] = p.cvt.pulsation_amp
            pp[K.PB + K.PULS_K] = p.cvt.pulsation_order
        else:
            pp[K.PB + K.ETA0] = p.eta_mesh
            pp[K.PB + K.ETA_MIN] = p.eta_mesh
        pp[K.PB + K.DRAG_TC] = p.drag_torque_nm
        pp[K.PB + K.DRAG_D] = p.drag_viscous
        pp[K.PB + K.DRAG_EPS] = p.motor_in.friction_eps_rad_s
        pp[K.PB + K.MESH_K] = p.mesh_stiffness
        pp[K.PB + K.MESH_C] = p.mesh_damping
        pp[K.PB + K.MESH_BL] = p.backlash_rad
        for a, (axis, m) in enumerate((("in", p.motor_in), ("out", p.motor_out))):
            b = a * K.MP
            for idx, val in ((K.KT, m.Kt), (K.J, m.J), (K.D, m.D), (K.C, m.C), (K.TC, m.Tc),
                             (K.TS, m.Ts), (K.WS, m.ws), (K.EPS, m.friction_eps_rad_s),
                             (K.COG_A, m.cog_amp), (K.COG_N, m.cog_order),
                             (K.RIP_A, m.ripple_amp), (K.RIP_N, m.ripple_order),
                             (K.KSAT, m.kt_sat_a), (K.OFF, m.current_offset_a),
                             (K.GAIN, m.current_gain), (K.NOISE, m.current_noise_a),
                             (K.RES, m.current_resolution_a), (K.DELAY, m.delay_samples),
                             (K.CSH, m.shaft_damping), (K.BL, m.backlash_rad),
                             (K.KP, m.vel_kp), (K.KI, m.vel_ki), (K.ILIM, m.current_limit_a),
                             (K.WLIM, m.speed_limit_rad_s), (K.MODE, MODES[self._modes[axis]]),
                             (K.TCA, m.Tc_asym), (K.DA, m.D_asym), (K.TPA, m.Tc_pos_amp),
                             (K.TPN, m.Tc_pos_order)):
                pp[b + idx] = val
            pp[b + K.SP_INTERP] = float(m.setpoint_interpolation)
            pp[b + K.NAVG] = max(1, int(round(m.current_avg_s / dt)))
            pp[b + K.Q] = 2 * math.pi / m.counts_per_rev
            pp[b + K.BETA] = 1.0 - math.exp(-dt / m.current_lag_s) if m.current_lag_s > 0 else 1.0
            jd = self._disks[axis]
            pp[b + K.JD] = jd
            k_shaft = _disk_stiffness(m)
            if jd <= 0:
                pp[b + K.DISK] = K.DISK_NONE
            elif k_shaft > 0:
                pp[b + K.DISK] = K.DISK_TWO_MASS
                pp[b + K.KSH] = k_shaft
            else:
                pp[b + K.DISK] = K.DISK_RIGID
            loopk = max(1, int(round(m.loop_period_s / dt)))
            pp[b + K.LOOPK] = loopk
            pp[b + K.LOOPT] = loopk * dt
            pp[b + K.VALPHA] = (1.0 - math.exp(-loopk * dt / m.vel_filter_s)
                                if m.vel_filter_s > 0 else 1.0)
            s = a * K.SS
            self._st[s + K.CPREV] = math.floor(self._st[s + K.TH] / pp[b + K.Q])


def _disk_stiffness(m) -> float:
    """Stiffness of the disk coupling: the shaft's, or the contact's when only a gap is set."""
    if m.shaft_stiffness > 0:
        return m.shaft_stiffness
    return m.contact_stiffness if m.backlash_rad > 0 else 0.0


def _substep(p: PlantParams, coupling: str, disks: dict, ratio: float) -> float:
    """Largest substep ≤ MAX_SUBSTEP_S that keeps the springs accurate (ω_n·dt ≤ 0.3)
    and the explicit dampers stable (c·dt ≤ 0.5·J_reduced)."""
    dt = MAX_SUBSTEP_S
    pairs = []
    if coupling == "reducer" and p.backlash_rad > 0:
        pairs.append((p.mesh_stiffness, p.mesh_damping, p.motor_in.J, p.motor_out.J / ratio ** 2))
    for axis, m in (("in", p.motor_in), ("out", p.motor_out)):
        if coupling == "none" and disks[axis] > 0 and _disk_stiffness(m) > 0:
            pairs.append((_disk_stiffness(m), m.shaft_damping, m.J, disks[axis]))
    for k, c, j1, j2 in pairs:
        jr = j1 * j2 / (j1 + j2)
        dt = min(dt, 0.3 / math.sqrt(k / jr))
        if c > 0:
            dt = min(dt, 0.5 * jr / c)
    nsub = math.ceil(p.period_s / dt - 1e-9)
    if nsub > MAX_SUBSTEPS:
        raise ProfileError(f"simulation: stiffness/damping needs {nsub} substeps per sample "
                           f"(max {MAX_SUBSTEPS}); lower shaft_stiffness/mesh_stiffness or damping")
    return p.period_s / nsub


def _kinematics_py(pp: np.ndarray, th: float) -> tuple[float, float, float]:
    r, rp, kin = K._kinematics(pp, th)
    return float(r), float(rp), float(kin)

