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

import queue
import threading
from dataclasses import dataclass, field
from typing import Callable, Iterable

import numpy as np

from ..analysis.calibration import MotorCalibration
from ..analysis.efficiency import EfficiencyPoint as AnalysedPoint


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
    """A motor's identification (``gearbench.analysis.calibration.MotorCalibration``)."""

    motor: str
    result: MotorCalibration
    kind = "calibration"

    @property
    def params(self) -> dict:
        """As written out (result.json ``motors.<m>``)."""
        return self.result.to_dict()


@dataclass(frozen=True)
class EfficiencyPoint(Record):
    """One operating point (``gearbench.analysis.efficiency.EfficiencyPoint``: eq. 18's
    incremental and the absolute efficiency, with intervals)."""

    result: AnalysedPoint
    kind = "efficiency_point"

    @property
    def point(self) -> dict:
        """As written out (one entry of result.json ``efficiency``)."""
        return self.result.to_dict()


@dataclass(frozen=True)
class LimitResult(Record):
    """One profile limit judged on one value (efficiency limits: one per point)."""

    name: str
    value: float | None
    low: float | None
    high: float | None
    passed: bool
    quantity: str = ""
    # why a verdict failed that its value alone would pass (a model check: Kt not constant
    # over current, an efficiency above 1); empty otherwise
    reason: str = ""
    kind = "limit"

    def to_dict(self) -> dict:
        """As written out (one entry of result.json ``limits``)."""
        return dict(name=self.name, quantity=self.quantity, value=self.value, low=self.low,
                    high=self.high, passed=self.passed, **({"reason": self.reason} if self.reason else {}))

    @classmethod
    def from_dict(cls, d: dict) -> "LimitResult":
        return cls(d["name"], d.get("value"), d.get("low"), d.get("high"), bool(d["passed"]),
                   d.get("quantity", ""), d.get("reason", ""))


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


class OutputFailure(Exception):
    """A required output (traces, result, station database) failed: the run cannot pass."""


class _Lane:
    """One writer thread with a bounded queue, delivering records to its subscribers in order."""

    def __init__(self, name: str, subscribers: list, maxsize: int, required: bool, on_error):
        self.subscribers = subscribers
        self.required = required
        self.queue: queue.Queue = queue.Queue(maxsize)
        self.dropped = 0
        self._on_error = on_error
        self._thread = threading.Thread(target=self._run, name=f"records-{name}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            record = self.queue.get()
            try:
                if record is None:
                    return
                for sub in list(self.subscribers):
                    try:
                        sub(record)
                    except Exception as exc:
                        self.subscribers.remove(sub)
                        self._on_error(sub, exc, self.required, record)
            finally:
                self.queue.task_done()

    def put(self, record, *, block: bool) -> bool:
        try:
            self.queue.put(record, block=block)
            return True
        except queue.Full:
            return False

    def join(self) -> None:
        self.queue.join()

    def stop(self) -> None:
        self.queue.put(None)
        self._thread.join(timeout=30)


class RecordStream:
    """Fan-out of records to subscribers, off the acquisition thread.

    ``emit`` only puts the record on a queue (the acquisition loop does acquisition
    only); writer threads deliver it, in order. Two lanes (the bluesky way: the run
    engine never waits for a slow callback, but it knows when one failed):

    - **required** subscribers (trace recorder, result writer, station database): a
      failure is an ``OutputFailure`` — the next ``emit`` raises it (the sequencer
      turns it into a bench fault: drives stopped, exit 3), and a ``RunStop`` that
      arrives after it carries status ``fault``, so no unit passes without its
      traces. A queue that fills (the writer cannot keep up) is a failure too when
      ``realtime`` is set; otherwise (lockstep, nothing to miss) emit waits.
    - **best-effort** subscribers (live view, progress display, callers' extras): a
      failure is reported once in ``errors`` and the subscriber dropped; when their
      queue is full, sample batches and progress for them are dropped (counted).
    """

    REQUIRED_QUEUE = 4000     # records (a SampleBatch is 200 samples: ~13 min at 1 kHz)
    LOCKSTEP_QUEUE = 2        # lockstep waits for the writer instead: a failure is seen within ~600 samples
    BEST_EFFORT_QUEUE = 200
    DROPPABLE = ("sample_batch", "progress")

    def __init__(self, subscribers: Iterable[Callable[[Record], None]] = (), *,
                 required: Iterable[Callable[[Record], None]] = (), realtime: bool = False):
        self.errors: list[str] = []
        self.failure: str | None = None
        self._raised = False
        self._lock = threading.Lock()
        self.required = _Lane("required", list(required), self.REQUIRED_QUEUE, True, self._failed)
        self.best_effort = _Lane("best-effort", list(subscribers), self.BEST_EFFORT_QUEUE, False, self._failed)
        self.realtime = realtime

    @property
    def realtime(self) -> bool:
        return self._realtime

    @realtime.setter
    def realtime(self, on: bool) -> None:
        """Real drives: a deep queue absorbs disk hiccups, overflow is a fault. Lockstep: a
        shallow one that emit waits on, so an output failure stops the bench promptly."""
        self._realtime = bool(on)
        self.required.queue.maxsize = self.REQUIRED_QUEUE if on else self.LOCKSTEP_QUEUE

    @property
    def subscribers(self) -> list:
        return self.required.subscribers + self.best_effort.subscribers

    def subscribe(self, sub: Callable[[Record], None], *, required: bool = False) -> None:
        (self.required if required else self.best_effort).subscribers.append(sub)

    def _failed(self, sub, exc, required: bool, record) -> None:
        text = f"{type(sub).__name__}: {exc}"
        with self._lock:
            self.errors.append(text)
            if required and self.failure is None:
                self.failure = f"{text} (while handling {record.kind})"
        if required and isinstance(record, RunStop):
            self._mark_fault(record)    # the subscribers after this one see a fault

    def emit(self, record: Record) -> None:
        if isinstance(record, RunStop):
            self._emit_run_stop(record)
            return
        if not self.required.put(record, block=not self.realtime):
            with self._lock:
                self.failure = self.failure or (f"the record writer cannot keep up: {self.REQUIRED_QUEUE} "
                                                f"records queued (slow or stalled disk?)")
            if not self._raised:       # fail fast: the drives are stopped first, then the samples kept
                self.raise_if_failed()
            self.required.put(record, block=True)   # on the stopping path: every sample is kept
        if not self.best_effort.put(record, block=record.kind not in self.DROPPABLE):
            self.best_effort.dropped += 1
        self.raise_if_failed()

    def _emit_run_stop(self, record: RunStop) -> None:
        """The run's end: written only after everything before it, and truthful about outputs.
        Required subscribers get it first (the result writer last of them, so a database
        that failed on it still makes result.json say fault), then the best-effort ones."""
        self.flush()
        record = self._mark_fault(record)
        failed_before = self.failure
        self.required.put(record, block=True)
        self.required.join()
        if self.failure and not failed_before:
            # a required output failed on the RunStop itself (result.json on a folder gone
            # read-only): the ones that already stored "passed" store the fault instead
            # (RunStop handling is idempotent: files rewritten, database rows replaced)
            self.required.put(self._mark_fault(record), block=True)
            self.required.join()
        self.best_effort.put(self._mark_fault(record), block=True)
        self.best_effort.join()

    __call__ = emit

    def raise_if_failed(self) -> None:
        """Raise ``OutputFailure`` once, on the first call after a required output failed."""
        if self.failure and not self._raised:
            self._raised = True
            raise OutputFailure(self.failure)

    def _mark_fault(self, record: RunStop) -> RunStop:
        """A run whose required outputs failed is a fault, whatever its measurements say.
        The result dict is updated in place (it is what the caller returns)."""
        if not self.failure:
            return record
        r = record.result
        r["output_failure"] = self.failure
        if r.get("status") in ("passed", "failed"):
            r.update(status="fault", passed=False, exit_code=3, reason=f"output failed: {self.failure}")
        return RunStop(r.get("status", "fault"), int(r.get("exit_code", 3)), str(r.get("reason", "")), r)

    def flush(self) -> None:
        """Wait until every record emitted so far has been delivered."""
        self.required.join()
        self.best_effort.join()

    def close(self) -> None:
        self.flush()
        for lane in (self.required, self.best_effort):
            lane.stop()
            for sub in lane.subscribers:
                close = getattr(sub, "close", None)
                if close:
                    try:
                        close()
                    except Exception as exc:
                        self._failed(sub, exc, lane.required, RunStop("", 0))
        if self.best_effort.dropped:
            self.errors.append(f"{self.best_effort.dropped} sample batches/progress records not shown "
                               f"by the live view/progress display (they could not keep up)")
