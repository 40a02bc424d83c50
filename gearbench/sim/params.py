"""Physical constants of the simulated bench: one motor + drive + sensors
(``MotorParams``), the link-mechanism CVT (``CvtParams``) and the two-motor reducer
bench (``PlantParams``). SI units throughout; all frozen dataclasses.

``PlantParams.from_dict`` parses a profile's ``simulation:`` section and names the
dotted path of any bad key (``simulation.motors.in.Kt_typo: unknown key; ...``).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any, Mapping

from ..errors import ProfileError


@dataclass(frozen=True)
class MotorParams:
    """One servo motor with its drive (velocity PI / current loop) and its sensors.

    Motor equation (paper eq. 1-2 plus switchable effects)::

        J θ'' + D θ' + C θ = Kt_eff(i)·i·(1 + ripple_amp·sin(ripple_order·θ))
                             − (Tc + Ts·exp(−(ω/ws)²))·tanh(ω/friction_eps_rad_s)
                             − cog_amp·sin(cog_order·θ)  (+ coupling/load torque)

    with ``Kt_eff(i) = Kt / (1 + (i/kt_sat_a)²)`` when ``kt_sat_a > 0``.
    Effects are off when their amplitude is 0.

    The drive behaves like a cyclic-synchronous servo drive sampled by a bus master:
    in velocity mode each SYNC setpoint is ramped to linearly over the period
    (``setpoint_interpolation``; steps would kick the current at every sample), and
    the reported current is the mean of its current-loop samples over the last
    ``current_avg_s`` (default: the whole 1 ms period; an instantaneous sample aliases
    the 4 kHz velocity-loop ripple into ±1 mA errors of 0.25 s means).
    """

    Kt: float = 0.0527              # N m/A (Crouzet 82800502, the paper's motor)
    J: float = 1.5e-5               # kg m^2 rotor
    D: float = 2.0e-6               # N m s/rad viscous
    C: float = 0.0                  # N m/rad spring to ground (paper's model; 0 for a real motor)
    Tc: float = 0.008               # N m Coulomb friction (smoothed sign)
    Ts: float = 0.0                 # N m extra static (Stribeck) friction
    ws: float = 5.0                 # rad/s Stribeck speed
    friction_eps_rad_s: float = 0.01  # smoothing of sign(ω): tanh(ω/eps)
    Tc_asym: float = 0.0            # N m: Coulomb is Tc + Tc_asym turning forward, Tc − Tc_asym back
    D_asym: float = 0.0             # N m s/rad: viscous is D + D_asym forward, D − D_asym back
    Tc_pos_amp: float = 0.0         # Coulomb varies with angle: Tc·(1 + amp·sin(order·θ))
    Tc_pos_order: int = 1           # periods of that variation per revolution
    cog_amp: float = 0.002          # N m cogging amplitude
    cog_order: int = 6              # cogging periods per revolution
    ripple_amp: float = 0.0         # commutation torque ripple, fraction of Kt*i
    ripple_order: int = 6           # ripple periods per revolution
    kt_sat_a: float = 0.0           # 0 = off; else Kt_eff = Kt / (1 + (i/kt_sat_a)^2)
    current_offset_a: float = 0.0   # current-sensor offset
    current_gain: float = 1.0       # current-sensor gain
    current_noise_a: float = 0.004  # current-sensor white noise, std
    current_resolution_a: float = 0.001  # current-sensor quantum (0 = none)
    counts_per_rev: int = 10000     # encoder counts per revolution (after x4 decoding)
    current_lag_s: float = 0.0005   # first-order current loop time constant (0 = ideal)
    delay_samples: int = 0          # transport delay of the measured current, in samples
    shaft_stiffness: float = 0.0    # N m/rad; 0 = disk rigidly attached; >0 = compliant shaft
    shaft_damping: float = 0.0      # N m s/rad across the disk shaft
    backlash_rad: float = 0.0       # total gap of the disk coupling (dead zone)
    contact_stiffness: float = 100.0  # N m/rad in contact when backlash_rad > 0 and shaft_stiffness == 0
    setpoint_interpolation: int = 1  # velocity mode: 1 = ramp linearly between SYNC setpoints
    #                                  (cyclic-synchronous drives), 0 = apply each as a step
    current_avg_s: float = 1e-3     # reported current = mean over this last span before the
    #                                  sample, at most one period (0 = the instantaneous value)
    vel_kp: float = 0.04            # drive velocity PI: A per rad/s
    vel_ki: float = 1.4             # drive velocity PI: A per rad
    loop_period_s: float = 2.5e-4   # drive velocity-loop period
    vel_filter_s: float = 5e-4      # low-pass time constant of the drive's velocity estimate
    current_limit_a: float = 3.0    # drive current limit (also limits torque-mode setpoints)
    rated_current_a: float = 1.0
    speed_limit_rad_s: float = 420.0  # velocity setpoints are clipped; torque mode folds back above it

    def __post_init__(self) -> None:
        self.check("MotorParams")

    def check(self, where: str) -> None:
        """Raise ProfileError naming ``where.field`` for a value out of range."""
        positive = ("Kt", "J", "ws", "friction_eps_rad_s", "counts_per_rev", "loop_period_s",
                    "current_limit_a", "rated_current_a", "speed_limit_rad_s", "current_gain",
                    "contact_stiffness")
        non_negative = ("D", "C", "Tc", "Ts", "cog_amp", "ripple_amp", "kt_sat_a",
                        "current_noise_a", "current_resolution_a", "current_lag_s",
                        "delay_samples", "shaft_stiffness", "shaft_damping", "backlash_rad",
                        "vel_kp", "vel_ki", "vel_filter_s", "cog_order", "ripple_order",
                        "current_avg_s", "Tc_pos_amp")
        _check_numbers(self, where)
        for name in positive:
            if not getattr(self, name) > 0:
                raise ProfileError(f"{where}.{name}: must be > 0 (got {getattr(self, name)!r})")
        for name in non_negative:
            if not getattr(self, name) >= 0:
                raise ProfileError(f"{where}.{name}: must be >= 0 (got {getattr(self, name)!r})")
        if self.delay_samples > 255:
            raise ProfileError(f"{where}.delay_samples: at most 255 (got {self.delay_samples})")
        if self.setpoint_interpolation not in (0, 1):
            raise ProfileError(f"{where}.setpoint_interpolation: 1 (linear between SYNC "
                               f"setpoints) or 0 (steps), got {self.setpoint_interpolation!r}")
        if abs(self.Tc_asym) > self.Tc or abs(self.D_asym) > self.D:
            raise ProfileError(f"{where}.Tc_asym/D_asym: at most Tc / D in size (friction "
                               f"cannot push the motor)")
        if self.Tc_pos_amp > 1 or self.Tc_pos_order < 1:
            raise ProfileError(f"{where}.Tc_pos_amp: at most 1; Tc_pos_order: at least 1")
        if self.ripple_amp >= 1:
            raise ProfileError(f"{where}.ripple_amp: a fraction of Kt*i, must be < 1")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None, where: str = "motor") -> "MotorParams":
        """Build from a mapping of field names; unknown key → ProfileError naming it."""
        kw = _parse_fields(cls, d or {}, where)
        obj = object.__new__(cls)  # validate with the dotted path, not the class name
        for k, v in asdict(cls()).items():
            object.__setattr__(obj, k, kw.get(k, v))
        obj.check(where)
        return obj

    def truth(self) -> dict:
        """The paper's identified quantities, for checking identification."""
        return {"Kt": self.Kt, "J": self.J, "D": self.D, "Tc": self.Tc}


@dataclass(frozen=True)
class CvtParams:
    """Link-mechanism CVT: settable mean ratio (``PlantParams.ratio``), efficiency
    falling with input speed and an output speed that pulsates with input angle::

        η(ω_in) = clip(eta_max − eta_slope_per_rad_s·|ω_in|, eta_min, 1)
        ω_out   = ω_in / n · (1 + pulsation_amp·sin(pulsation_order·θ_in))
    """

    eta_max: float = 0.85
    eta_slope_per_rad_s: float = 5e-4
    eta_min: float = 0.3
    pulsation_amp: float = 0.05
    pulsation_order: int = 4        # pulsations per input revolution (number of links)
    ratio_min: float = 2.0
    ratio_max: float = 30.0

    def __post_init__(self) -> None:
        self.check("CvtParams")

    def check(self, where: str) -> None:
        _check_numbers(self, where)
        if not 0 < self.eta_min <= self.eta_max <= 1:
            raise ProfileError(f"{where}: need 0 < eta_min <= eta_max <= 1 "
                               f"(got eta_min={self.eta_min}, eta_max={self.eta_max})")
        if self.eta_slope_per_rad_s < 0:
            raise ProfileError(f"{where}.eta_slope_per_rad_s: must be >= 0")
        if not 0 <= self.pulsation_amp < 1:
            raise ProfileError(f"{where}.pulsation_amp: must be in [0, 1)")
        if self.pulsation_order < 1:
            raise ProfileError(f"{where}.pulsation_order: must be >= 1")
        if not 0 < self.ratio_min <= self.ratio_max:
            raise ProfileError(f"{where}: need 0 < ratio_min <= ratio_max")

    def efficiency(self, speed_in_rad_s: float) -> float:
        """Mesh efficiency at input speed ω_in."""
        eta = self.eta_max - self.eta_slope_per_rad_s * abs(speed_in_rad_s)
        return float(min(1.0, max(self.eta_min, eta)))

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None, where: str = "cvt") -> "CvtParams":
        kw = _parse_fields(cls, d or {}, where)
        obj = object.__new__(cls)
        for k, v in asdict(cls()).items():
            object.__setattr__(obj, k, kw.get(k, v))
        obj.check(where)
        return obj


@dataclass(frozen=True)
class PlantParams:
    """The two-motor reducer bench: input motor → reducer (ratio n) → output motor.

    Mesh efficiency acts in the direction of power flow: input driving,
    T_out_shaft = n·η·(T_in_shaft − drag); output driving, T_out_shaft = n·(T_in_shaft − drag)/η.
    Drag (Coulomb ``drag_torque_nm`` + ``drag_viscous``·ω) acts at the input shaft.
    ``backlash_rad`` > 0 (at the input shaft) switches to a two-mass mesh with stiffness
    ``mesh_stiffness`` and damping ``mesh_damping`` (both at the input shaft).
    """

    motor_in: MotorParams = field(default_factory=MotorParams)
    motor_out: MotorParams = field(default_factory=MotorParams)
    ratio: float = 10.0             # n: input speed / output speed
    eta_mesh: float = 0.9           # mesh efficiency (plain reducer)
    drag_torque_nm: float = 0.02    # reducer Coulomb drag at the input shaft
    drag_viscous: float = 0.0       # reducer viscous drag at the input shaft, N m s/rad
    backlash_rad: float = 0.0       # reducer backlash at the input shaft (total gap)
    mesh_stiffness: float = 50.0    # N m/rad at the input shaft (used with backlash)
    mesh_damping: float = 2e-4      # N m s/rad at the input shaft (used with backlash)
    cvt: CvtParams | None = None    # link-mechanism CVT instead of a plain reducer
    period_s: float = 1e-3          # sample period of the drives
    seed: int = 0

    def __post_init__(self) -> None:
        self.check("PlantParams")

    def check(self, where: str) -> None:
        _check_numbers(self, where, skip=("motor_in", "motor_out", "cvt"))
        for name in ("ratio", "mesh_stiffness", "period_s"):
            if not getattr(self, name) > 0:
                raise ProfileError(f"{where}.{name}: must be > 0 (got {getattr(self, name)!r})")
        for name in ("drag_torque_nm", "drag_viscous", "backlash_rad", "mesh_damping"):
            if not getattr(self, name) >= 0:
                raise ProfileError(f"{where}.{name}: must be >= 0 (got {getattr(self, name)!r})")
        if not 0 < self.eta_mesh <= 1:
            raise ProfileError(f"{where}.eta_mesh: must be in (0, 1] (got {self.eta_mesh!r})")
        if self.cvt is not None:
            if self.backlash_rad > 0:
                raise ProfileError(f"{where}: cvt and backlash_rad cannot be combined; "
                                   f"set backlash_rad: 0 for the CVT")
            if not self.cvt.ratio_min <= self.ratio <= self.cvt.ratio_max:
                raise ProfileError(f"{where}.ratio: {self.ratio} is outside the CVT range "
                                   f"[{self.cvt.ratio_min}, {self.cvt.ratio_max}]")

    def mesh_efficiency(self, speed_in_rad_s: float) -> float:
        """η at input speed ω_in: constant ``eta_mesh``, or the CVT's η(ω_in)."""
        return self.cvt.efficiency(speed_in_rad_s) if self.cvt else self.eta_mesh

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None, where: str = "simulation") -> "PlantParams":
        """Parse a profile's ``simulation:`` section.

        Keys: ``motors: {in: {MotorParams fields}, out: {...}}``, ``ratio``,
        ``eta_mesh``, ``drag_torque_nm``, ``drag_viscous``, ``backlash_rad``,
        ``mesh_stiffness``, ``mesh_damping``, ``cvt: {CvtParams fields}``,
        ``period_s``, ``seed``. An unknown key raises ProfileError with its dotted path.
        """
        d = _mapping(d or {}, where)
        scalar_keys = [f.name for f in fields(cls) if f.name not in ("motor_in", "motor_out", "cvt")]
        known = ["motors", "cvt", *scalar_keys]
        for k in d:
            if k not in known:
                raise ProfileError(f"{where}.{k}: unknown key; known keys: {', '.join(known)}")
        motors = _mapping(d.get("motors") or {}, f"{where}.motors")
        for k in motors:
            if k not in ("in", "out"):
                raise ProfileError(f"{where}.motors.{k}: unknown key; known keys: in, out")
        kw: dict[str, Any] = {
            "motor_in": MotorParams.from_dict(motors.get("in"), f"{where}.motors.in"),
            "motor_out": MotorParams.from_dict(motors.get("out"), f"{where}.motors.out"),
            "cvt": (CvtParams.from_dict(d["cvt"], f"{where}.cvt")
                    if d.get("cvt") is not None else None),
        }
        defaults = {f.name: f.default for f in fields(cls) if f.name in scalar_keys}
        for k in scalar_keys:
            if k in d:
                kw[k] = _coerce(d[k], defaults[k], f"{where}.{k}")
        obj = object.__new__(cls)
        for f in fields(cls):
            object.__setattr__(obj, f.name, kw.get(f.name, defaults.get(f.name)))
        obj.check(where)
        return obj

    def truth(self) -> dict:
        """Known truth for checking identification and efficiency."""
        t = {"motors": {"in": self.motor_in.truth(), "out": self.motor_out.truth()},
             "ratio": self.ratio, "eta_mesh": self.eta_mesh,
             "drag_torque_nm": self.drag_torque_nm, "drag_viscous": self.drag_viscous}
        if self.cvt is not None:
            t["cvt"] = asdict(self.cvt)
        return t

    def with_(self, **changes) -> "PlantParams":
        """Copy with some fields changed (``dataclasses.replace``)."""
        return replace(self, **changes)


# --------------------------------------------------------------------- helpers
def _mapping(d: Any, where: str) -> Mapping[str, Any]:
    if not isinstance(d, Mapping):
        raise ProfileError(f"{where}: expected a mapping of keys, got {type(d).__name__}")
    return d


def _coerce(value: Any, default: Any, where: str) -> Any:
    """Convert a profile value to the field's type (int or float); name the key on failure."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ProfileError(f"{where}: expected a number, got {value!r}")
    if isinstance(default, int) and not isinstance(default, bool):
        if float(value) != int(value):
            raise ProfileError(f"{where}: expected a whole number, got {value!r}")
        return int(value)
    return float(value)


def _parse_fields(cls, d: Mapping[str, Any], where: str) -> dict[str, Any]:
    d = _mapping(d, where)
    defaults = asdict(cls())
    for k in d:
        if k not in defaults:
            raise ProfileError(f"{where}.{k}: unknown key; known keys: {', '.join(defaults)}")
    return {k: _coerce(v, defaults[k], f"{where}.{k}") for k, v in d.items()}


def _check_numbers(obj, where: str, skip: tuple[str, ...] = ()) -> None:
    for f in fields(obj):
        if f.name in skip:
            continue
        v = getattr(obj, f.name)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ProfileError(f"{where}.{f.name}: expected a finite number, got {v!r}")
