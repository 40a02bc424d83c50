"""A run as a stream of records (bluesky-style documents).

The sequencer emits records; the Parquet recorder, the Rerun live view, the
station database, the JSON/JUnit writers and the progress display subscribe.
None of them is called from inside the sequencer's logic: adding an output is
adding a subscriber.

Order within a run::

    RunStart, (StepStart, SampleBatch*, StepStop, Calibration | EfficiencyPoint*)*,
    Message* anywhere, LimitResult*, RunStop
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Iterable

import numpy as np


@dataclass(frozen=True)
class Record:
    kind = "record"


@dataclass(frozen=True)
class RunStart(Record):
    run_id: str
    serial: str
    profile_name: str
    profile_path: str
    profile_sha256: str
    started_utc: str
    sim: bool
    motors: tuple[str, ...]
    period_s: float
    out_dir: str
    kind = "run_start"


@dataclass(frozen=True)
class StepStart(Record):
    """One acquisition segment, e.g. ``calibrate-in-unloaded`` or ``efficiency``."""

    name: str
    step_kind: str          # calibrate | load | efficiency
    description: str = ""
    planned_samples: int = 0
    kind = "step_start"


@dataclass(frozen=True)
class SampleBatch(Record):
    """Consecutive samples of one step: ``sample`` (drive sample counter),
    ``time_s`` (drive time base) and columns ``<motor>.<quantity>`` in SI."""

    step: str
    sample: np.ndarray
    time_s: np.ndarray
    columns: dict[str, np.ndarray] = field(default_factory=dict)
    kind = "sample_batch"


@dataclass(frozen=True)
class StepStop(Record):
    name: str
    status: str             # ok | aborted | fault
    n_samples: int
    lost_samples: int = 0
    kind = "step_stop"


@dataclass(frozen=True)
class Message(Record):
    """Operator prompts, progress and notices (level: info | prompt | warning | error)."""

    text: str
    level: str = "info"
    step: str = ""
    kind = "message"


@dataclass(frozen=True)
class Progress(Record):
    """Where the run is: for progress bars (fractions 0..1, ETA in wall seconds)."""

    step: str
    point: str
    fraction_step: float
    fraction_run: float
    eta_s: float | None = None
    kind = "progress"


@dataclass(frozen=True)
class Calibration(Record):
    """A motor's identified parameters: keys Kt, Kt_ci95, J, D, Tc, method, fit."""

    motor: str
    params: dict
    kind = "calibration"


@dataclass(frozen=True)
class EfficiencyPoint(Record):
    """One operating point: speed_in_rad_s, torque_out_nm, eta_incremental,
    eta_absolute and intervals."""

    point: dict
    kind = "efficiency_point"


@dataclass(frozen=True)
class LimitResult(Record):
    name: str
    value: float | None
    low: float | None
    high: float | None
    passed: bool
    quantity: str = ""
    kind = "limit"


@dataclass(frozen=True)
class RunStop(Record):
    """End of a run. ``status``: passed | failed | aborted | fault; ``result`` is the
    content of result.json."""

    status: str
    exit_code: int
    reason: str = ""
    result: dict = field(default_factory=dict)
    kind = "run_stop"


class Subscriber:
    """Base for record consumers: override ``on_<kind>`` methods you care about."""

    def __call__(self, record: Record) -> None:
        handler = getattr(self, f"on_{record.kind}", None)
        if handler is not None:
            handler(record)

    def close(self) -> None:
        """Release files/connections; called once, also after faults."""


class RecordStream:
    """Fan-out of records to subscribers; a subscriber's failure is reported once
    and the subscriber is dropped, so an output problem never stops the drives
    uncontrolled (the sequencer still reaches its safe stop)."""

    def __init__(self, subscribers: Iterable[Callable[[Record], None]] = ()):
        self.subscribers: list[Callable[[Record], None]] = list(subscribers)
        self.errors: list[str] = []

    def subscribe(self, sub: Callable[[Record], None]) -> None:
        self.subscribers.append(sub)

    def emit(self, record: Record) -> None:
        for sub in list(self.subscribers):
            try:
                sub(record)
            except Exception as exc:  # an output must not take the bench down
                self.errors.append(f"{type(sub).__name__}: {exc}")
                self.subscribers.remove(sub)

    __call__ = emit

    def close(self) -> None:
        for sub in self.subscribers:
            close = getattr(sub, "close", None)
            if close:
                try:
                    close()
                except Exception as exc:
                    self.errors.append(f"{type(sub).__name__}.close: {exc}")
