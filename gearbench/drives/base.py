"""The drive protocol the sequencer talks to.

A ``DriveNetwork`` is one connection (a CAN bus, a Modbus TCP endpoint) carrying
one or more ``Drive`` axes. The public methods do the shared work (SI scaling,
sample bookkeeping, lost-sample counting); families implement a few hooks.
Families are registered by name in ``gearbench.drives.registry`` and third parties
add theirs through the ``gearbench.drives`` entry-point group.

Units at this interface are SI only: rad, rad/s, A. Conversion to drive units
(counts, per-mille of rated current, ...) happens inside the family, from the
device description in ``drivers/``.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from enum import Enum


class Mode(str, Enum):
    """Operating modes the sequencer uses (CiA 402 names in brackets)."""

    VELOCITY = "velocity"   # profile velocity (3) / cyclic sync velocity (9); setpoint rad/s
    TORQUE = "torque"       # profile torque (4) / cyclic sync torque (10); setpoint A (motor current)


@dataclass(frozen=True)
class Sample:
    """One synchronous sample of one drive, in SI units.

    ``index`` is the drive-side sample counter (SYNC counter for CANopen, the
    drive's counter register for Modbus); ``time_s`` = index x period, the drive's
    time base, never the host clock — except where a SYNC went out late (a paced master
    that woke late catches up): the drives sampled when it arrived, so ``time_s`` is
    that instant, off the grid (the analysis treats such a sample as lost).
    """

    index: int
    time_s: float
    position_rad: float
    velocity_rad_s: float
    current_a: float
    status: int = 0
    fault: bool = False


@dataclass
class AxisConfig:
    """What the profile says about one axis; families read what they need."""

    name: str                      # "in" / "out"
    address: int                   # CANopen node id or Modbus unit id
    description: str               # path to the device description in drivers/
    rated_current_a: float = 1.0
    current_limit_a: float = 3.0
    speed_limit_rad_s: float = 400.0
    counts_per_rev: int = 10000
    extra: dict = field(default_factory=dict)


class Drive(ABC):
    """One servo axis on a network."""

    def __init__(self, config: AxisConfig):
        self.config = config
        self.name = config.name

    @abstractmethod
    def enable(self, mode: Mode) -> None:
        """Go to operation enabled in ``mode`` (setpoint reset to zero first)."""

    @abstractmethod
    def set_setpoint(self, value: float) -> None:
        """Target velocity (rad/s) or target current (A), by the enabled mode."""

    @abstractmethod
    def quick_stop(self) -> None:
        """CiA 402 quick stop: decelerate and hold zero torque; must not block long."""

    @abstractmethod
    def disable(self) -> None:
        """Remove power from the motor (switch on disabled / ready to switch on)."""

    @abstractmethod
    def reset_fault(self) -> None:
        """Acknowledge a fault (CiA 402 fault reset)."""


class DriveNetwork(ABC):
    """A bus or endpoint with its drives; a context manager that always disables.

    Lifecycle: ``open()`` -> ``add_drive()`` per axis -> ``start(period_s)`` ->
    repeated ``sample()`` -> ``close()`` (which disables every drive).
    """

    family: str = "abstract"
    #: Optional features, declared here so callers never probe with getattr:
    #: ``lockstep`` - the drives are an emulated plant that advances one period per sample
    #: (nothing can be missed: writers may block instead of dropping); real drives are paced
    #: by the wall clock. Families set it per instance.
    lockstep: bool = False

    def __init__(self, **options):
        self.options = options
        self.drives: dict[str, Drive] = {}
        self.period_s: float = 1e-3
        self.lost_samples = 0
        self.stop_report = ""
        self.stop_failed: list[str] = []
        self._last_index: int | None = None

    @abstractmethod
    def open(self) -> None: ...

    @abstractmethod
    def add_drive(self, config: AxisConfig) -> Drive: ...

    @abstractmethod
    def start(self, period_s: float) -> None:
        """Configure synchronous sampling at ``period_s``."""

    @abstractmethod
    def _sample(self) -> dict[str, Sample]:
        """Family hook: one synchronous sample of all drives."""

    @abstractmethod
    def _close(self) -> None: ...

    def sample(self) -> dict[str, Sample]:
        """One synchronous sample of every drive, keyed by axis name.

        Counts lost samples from gaps in the drive sample counter.
        """
        samples = self._sample()
        idx = next(iter(samples.values())).index if samples else None
        if idx is not None and self._last_index is not None:
            if idx <= self._last_index:   # a repeated or backward counter is never a new sample
                from ..errors import BenchFault
                self.stop_all()
                raise BenchFault(f"sample counter went from {self._last_index} to {idx}: a drive "
                                 f"repeated or reordered a sample; {self.stop_report}")
            self.lost_samples += idx - self._last_index - 1
        self._last_index = idx
        return samples

    def watch_process(self, pid: int) -> None:
        """The drives are emulated by process ``pid`` on this host (``--sim``): a family whose
        supervision measures silence treats that process's CPU starvation as a host stall.
        Default: nothing to watch."""

    def mount(self, *, coupling: str, disk_kgm2: dict[str, float]) -> None:
        """Mount the reducer / disks itself (an in-process simulated family does); real
        drives cannot, a person or a fixture does. See ``mounts_itself``."""
        raise NotImplementedError(f"drive family '{self.family}' cannot mount a reducer or disks itself")

    @property
    def mounts_itself(self) -> bool:
        """True where the family overrides ``mount`` (then it is the run's fixture)."""
        return type(self).mount is not DriveNetwork.mount

    def discard_backlog(self) -> None:
        """Samples taken before now are not the next acquisition's: a paced network keeps
        sampling between segments (SYNC never stops), so the next ``sample()`` starts from
        the first sample after this call, and the SYNCs in between are not counted lost."""
        self._last_index = None
        self._discard_backlog()

    def _discard_backlog(self) -> None:
        """Family hook: drop samples queued but not yet taken."""

    def supervision(self) -> dict:
        """What supervision saw (host stalls tolerated, frames dropped...); families extend it."""
        return {}

    def acquisition_threads(self) -> list[int]:
        """Native ids of the family's threads on the acquisition path (e.g. the bus
        receiver); they get the acquisition thread's priority while it samples."""
        return []

    def stop_all(self) -> str:
        """Quick stop then disable every drive, verified; never raises (used on faults).

        Every drive gets both commands even if another one fails. ``disable()`` reads
        the drive's state back, so the returned sentence is true: either every drive
        was seen disabled, or each one that was not is named with what went wrong.
        The same sentence is kept in ``stop_report``.
        """
        failed: dict[str, str] = {}
        for d in self.drives.values():
            try:
                d.quick_stop()
            except Exception as exc:   # keep going: the other drives must still stop
                failed[d.name] = f"quick stop not sent ({exc})"
        for d in self.drives.values():
            try:
                d.disable()
            except Exception as exc:
                failed[d.name] = f"{failed[d.name]}; " if d.name in failed else ""
                failed[d.name] += f"did NOT reach a disabled state ({exc})"
        if not self.drives:
            report = "no drive to stop"
        elif failed:
            report = "; ".join(f"drive '{n}' {why}" for n, why in failed.items())
            ok = [n for n in self.drives if n not in failed]
            if ok:
                report += f"; drive(s) {', '.join(repr(n) for n in ok)} stopped and disabled (read back)"
        else:
            report = "drives stopped and disabled (state read back)"
        self.stop_report = report
        self.stop_failed = sorted(failed)
        return report

    def close(self) -> None:
        try:
            self.stop_all()
        finally:
            self._close()

    def __enter__(self):
        self.open()
        return self

    def __exit__(self, *exc):
        self.close()
        return False
