"""The validated profile: plain frozen dataclasses, SI units, no YAML left in them.

``gearbench.profile.load_profile`` builds these; the sequencer only reads them.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Union

import numpy as np

from . import waveforms as _wf
from ..analysis.uncertainty import tolerance_std


@dataclass(frozen=True)
class BusSpec:
    """Where the drives are: a CAN bus (``cia402``) or a Modbus TCP endpoint (``modbus``)."""
    family: str                      # "cia402" | "modbus" | a plugin family name
    interface: str | None = None     # cia402: "udp_multicast" | "socketcan" | "virtual"
    channel: str | None = None       # cia402: "can0", "vcan0", a multicast group; None = interface default
    host: str | None = None          # modbus: IP or host name
    port: int | None = None          # modbus: TCP port (default 502)
    options: dict = field(default_factory=dict)   # passed through to the drive family


@dataclass(frozen=True)
class BenchSpec:
    name: str
    bus: BusSpec
    period_s: float = 1e-3           # sample (SYNC) period
    # Before the reducer is mounted the motors are mechanically independent: calibrate
    # steps of different motors next to each other run at once (one unloaded run for
    # both, one prompt to mount both disks, one run with both disks).
    parallel_calibration: bool = False


@dataclass(frozen=True)
class MotorSpec:
    """One motor + drive. ``drive`` is the resolved absolute path of its description file."""
    name: str                        # "in" | "out"
    drive: str
    address: int                     # CANopen node id / Modbus unit id
    kt_datasheet: float              # N m/A
    rated_current_a: float
    current_limit_a: float
    speed_limit_rad_s: float
    counts_per_rev: int = 10000
    rotor_inertia_kgm2: float | None = None   # datasheet value; used only for feasibility checks
    # how the drive samples, as its set-up says: {"setpoint": "step"|"interpolated",
    # "current": "instant"|"mean"} (identify.drive_sampling); None = not said
    sampling: dict | None = None

    @property
    def current_instant(self) -> bool:
        """The drive reports its current as one current-loop instant (``sampling.current``):
        its speed loop's quantisation ripple is in the samples (``analysis.ripple``)."""
        return (self.sampling or {}).get("current") == "instant"


@dataclass(frozen=True)
class ReducerSpec:
    name: str
    ratio: float | None              # n = input speed / output speed; None = "measure"
    cvt_setting: float | None        # CVT adjuster position, fraction of travel (0, 1]
    efficiency_range: tuple[float, float]


@dataclass(frozen=True)
class DiskSpec:
    """An inertia disk: its inertia and how well that is known.

    ``inertia_tolerance_rel`` is read by ``inertia_source`` (``datasheet``: ± limits,
    rectangular; ``measured``: expanded uncertainty at 95 %, k = 2); ``inertia_std_kgm2``
    is the standard uncertainty it implies (``gearbench.analysis.uncertainty``)."""
    name: str
    inertia_kgm2: float
    inertia_tolerance_rel: float = 0.0
    inertia_source: str = "datasheet"

    @property
    def inertia_std_kgm2(self) -> float:

        return tolerance_std(self.inertia_tolerance_rel * self.inertia_kgm2, self.inertia_source)


@dataclass(frozen=True)
class WaveformSpec:
    """A named command waveform; ``params`` are complete (defaults filled in) and validated."""
    name: str
    kind: str                        # one of gearbench.profile.waveforms.KINDS
    params: dict
    design: object = None            # design: optimal: the excitation_design.Design behind params

    def render(self, time_s: np.ndarray) -> np.ndarray:
        """The command (rad/s in velocity mode, A in current mode) at each time."""
        return _wf.render(self.kind, self.params, time_s)

    @property
    def natural_period_s(self) -> float | None:
        """Length of one full period (multisine, chirp sweep, PRBS, trapezoid), else None."""
        return _wf.natural_period_s(self.kind, self.params)


@dataclass(frozen=True)
class CalibrateStep:
    """Run ``motor`` alone with ``waveform`` for ``duration_s``, prompt to mount ``disk``,
    run again, prompt to remove it (Kt from two inertias, paper eq. 17 corrected)."""
    motor: str
    disk: str
    waveform: str
    duration_s: float
    prompt: str
    name: str = ""
    mode: str = "velocity"           # the waveform is a velocity (rad/s) or a current (A) command
    remove_prompt: str = ""
    # Adaptive (both set, with profile ``targets.kt_rel``): each run lasts until Kt's
    # statistical 95 % interval meets the target, at least ``min_s``, at most ``max_s``;
    # ``duration_s`` is then ``max_s``.
    min_s: float | None = None
    max_s: float | None = None

    @property
    def adaptive(self) -> bool:
        return self.min_s is not None and self.max_s is not None

    @property
    def bench_time_s(self) -> float:
        return 2.0 * (self.max_s if self.adaptive else self.duration_s)


@dataclass(frozen=True)
class LoadStep:
    """The operator mounts the reducer between the motors (sim: coupling="reducer")."""
    prompt: str
    name: str = "load"

    @property
    def bench_time_s(self) -> float:
        return 0.0


@dataclass(frozen=True)
class EfficiencyStep:
    """Efficiency map: input motor in speed control, output motor brakes in current control.

    For each speed: a zero-load level, each braking torque, zero-load again (when
    ``include_zero_load``); every level is held ``settle_s`` then measured ``measure_s``.

    Adaptive (``min_s``/``max_s`` set, with profile ``targets.eta_pp``): per speed one
    continuous staircase — zero load, then each braking torque — each level held until
    its settling is seen in the data and its mean is known well enough for the speed's
    incremental-efficiency slope to meet the target (at least ``min_s``, at most
    ``max_s`` per level, settling included); eq. 18 becomes the regression slope of
    input on output torque over the staircase (``gearbench.analysis.efficiency``).
    """
    speeds_in_rad_s: list[float]
    torques_out_nm: list[float]
    settle_s: float
    measure_s: float
    include_zero_load: bool = True
    name: str = "efficiency"
    min_s: float | None = None
    max_s: float | None = None

    @property
    def adaptive(self) -> bool:
        return self.min_s is not None and self.max_s is not None

    def levels(self) -> list[tuple[float, float]]:
        """The (input speed rad/s, output braking torque N m) levels in run order."""
        out = []
        for speed in self.speeds_in_rad_s:
            seq = list(self.torques_out_nm)
            if self.adaptive:
                seq = [0.0] + seq                  # staircase: one zero-load level first
            elif self.include_zero_load:
                seq = [0.0] + seq + [0.0]
            out += [(speed, torque) for torque in seq]
        return out

    @property
    def operating_points(self) -> int:
        return len(self.speeds_in_rad_s) * len(self.torques_out_nm)

    @property
    def bench_time_s(self) -> float:
        if self.adaptive:                          # upper bound: every level at max_s
            return len(self.levels()) * self.max_s
        return len(self.levels()) * (self.settle_s + self.measure_s)


Step = Union[CalibrateStep, LoadStep, EfficiencyStep]


@dataclass(frozen=True)
class LimitSpec:
    """Pass/fail on one result quantity; ``None`` bound = unbounded on that side.

    quantity: ``motors.<m>.Kt`` | ``motors.<m>.Kt_rel_datasheet`` | ``motors.<m>.J`` |
    ``motors.<m>.D`` | ``motors.<m>.Tc`` | ``ratio`` | ``efficiency.eta_incremental`` |
    ``efficiency.eta_absolute`` (efficiency limits apply to every operating point).
    """
    name: str
    quantity: str
    low: float | None
    high: float | None

    def passed(self, value: float) -> bool:
        if value != value:  # NaN never passes
            return False
        return (self.low is None or value >= self.low) and (self.high is None or value <= self.high)


@dataclass(frozen=True)
class Targets:
    """What an adaptive measurement stops on (95 % half-widths of the statistical part,
    the part acquisition time shrinks): ``kt_rel`` relative on Kt, ``eta_pp`` on the
    incremental efficiency in percentage points. Fixed terms (the disk's tolerance, the
    b2 model term) are not shrunk by time and are not targeted (docs/profile-format.md)."""
    kt_rel: float | None = None
    eta_pp: float | None = None


@dataclass(frozen=True)
class Outputs:
    """Files written with every run besides result.json, junit.xml and the traces:
    ``mdf`` the traces as ASAM MDF4 (``traces.mf4``, as ``gearbench export --mdf``)."""

    mdf: bool = False


@dataclass(frozen=True)
class Profile:
    path: Path
    sha256: str
    name: str
    description: str
    bench: BenchSpec
    motors: dict[str, MotorSpec]
    reducer: ReducerSpec | None
    disks: dict[str, DiskSpec]
    waveforms: dict[str, WaveformSpec]
    steps: list[Step]
    limits: list[LimitSpec]
    simulation: dict | None
    raw: dict
    targets: Targets = Targets()
    outputs: "Outputs" = None

    def __post_init__(self):
        if self.outputs is None:
            object.__setattr__(self, "outputs", Outputs())

    @property
    def operating_points(self) -> int:
        return sum(s.operating_points for s in self.steps if isinstance(s, EfficiencyStep))

    def drive_modes(self, motor: str) -> set[str]:
        """'velocity'/'torque': the drive modes this profile's steps need from ``motor``."""
        kinds = set()
        for s in self.steps:
            if isinstance(s, CalibrateStep) and s.motor == motor:
                kinds.add(s.mode)
            elif isinstance(s, EfficiencyStep):
                kinds.add("velocity" if motor == "in" else "torque")
        return kinds

    @property
    def estimated_bench_time_s(self) -> float:
        """Motor-running time on a real tester: 2 runs per calibration + every efficiency
        level's settle and measure (adaptive steps: at their max_s, an upper bound;
        calibrate steps run at once with ``bench.parallel_calibration`` count once).
        Speed ramps, operator prompts and drive start-up are not included."""
        total, group = 0.0, []
        for s in self.steps + [None]:
            if (self.bench.parallel_calibration and isinstance(s, CalibrateStep)
                    and s.motor not in {g.motor for g in group}):
                group.append(s)
                continue
            total += self._group_time_s(group)
            group = [s] if (self.bench.parallel_calibration and isinstance(s, CalibrateStep)) else []
            if s is not None and not group:
                total += s.bench_time_s
        return float(total)

    def _group_time_s(self, group: list) -> float:
        """Calibrate steps run at once: the runs alone together, then the disk runs together
        (a disk per motor) or one after another (one disk shared)."""
        if not group:
            return 0.0
        run = max(g.bench_time_s for g in group) / 2.0
        shared = len({g.disk for g in group}) < len(group)
        return run + (sum(g.bench_time_s / 2.0 for g in group) if shared else run)
