"""The record stream: required outputs can fail a run, best-effort ones cannot, and
the acquisition thread never waits on a file."""
import threading
import time

import pytest

from gearbench.station.records import (Message, OutputFailure, RecordStream, RunStop, SampleBatch, StepStart,
                               Subscriber)


class Collect(Subscriber):
    def __init__(self):
        self.kinds, self.threads = [], set()

    def __call__(self, record):
        self.kinds.append(record.kind)
        self.threads.add(threading.current_thread().name)


class Breaks(Subscriber):
    def __init__(self, on: str):
        self.on = on

    def __call__(self, record):
        if record.kind == self.on:
            raise OSError(28, "No space left on device")


def batch():
    return SampleBatch("s", [1], [0.0], {})


def run_stop():
    return RunStop("passed", 0, "", {"status": "passed", "passed": True, "exit_code": 0, "reason": ""})


def test_records_are_delivered_in_order_off_the_emitting_thread():
    req, best = Collect(), Collect()
    stream = RecordStream([best], required=[req])
    for rec in (StepStart("s", "calibrate", "", 1), batch(), Message("hi"), run_stop()):
        stream.emit(rec)
    stream.close()
    assert req.kinds == best.kinds == ["step_start", "sample_batch", "message", "run_stop"]
    assert threading.current_thread().name not in req.threads | best.threads


def test_a_required_output_that_fails_fails_the_run():
    """Disk full in the recorder: the next emit raises OutputFailure (once), and the
    run's result says fault, exit 3, naming the output, whatever was measured."""
    writer = Collect()
    stream = RecordStream(required=[Breaks("sample_batch"), writer])
    stream.emit(StepStart("s", "calibrate", "", 1))
    stream.emit(batch())
    stream.flush()
    with pytest.raises(OutputFailure, match="No space left"):
        stream.emit(Message("next"))
    stream.emit(Message("after"))             # raised once; the path that ends the run goes on
    stop = run_stop()
    stream.emit(stop)
    stream.close()
    assert stop.result["status"] == "fault" and stop.result["exit_code"] == 3 and not stop.result["passed"]
    assert "No space left" in stop.result["reason"]
    assert writer.kinds[-1] == "run_stop"     # the result writer still wrote the (fault) result


def test_a_required_output_failing_on_the_run_stop_marks_it_for_the_ones_after_it():
    seen = []

    class Writer(Subscriber):
        def on_run_stop(self, rec):
            seen.append(dict(rec.result))

    stop = run_stop()
    stream = RecordStream(required=[Breaks("run_stop"), Writer()])
    stream.emit(stop)
    stream.close()
    assert seen[0]["status"] == "fault" and stop.result["exit_code"] == 3


def test_a_best_effort_output_that_fails_is_a_warning_only():
    stream = RecordStream([Breaks("sample_batch")], required=[Collect()])
    stream.emit(batch())
    stream.flush()
    stream.emit(Message("next"))               # no exception
    stop = run_stop()
    stream.emit(stop)
    stream.close()
    assert stop.result["status"] == "passed"
    assert any("No space left" in e for e in stream.errors)


def test_a_writer_that_cannot_keep_up_is_a_fault_against_real_drives(monkeypatch):
    """Real time: the emitting thread never waits for a slow disk; a full queue is a
    failure (not lost samples). Lockstep would wait instead (nothing can be missed)."""
    monkeypatch.setattr(RecordStream, "REQUIRED_QUEUE", 3)
    release = threading.Event()

    class Slow(Subscriber):
        def __call__(self, record):
            release.wait(5)

    stream = RecordStream(required=[Slow()], realtime=True)
    t0 = time.monotonic()
    with pytest.raises(OutputFailure, match="cannot keep up"):
        for _ in range(10):
            stream.emit(batch())
    assert time.monotonic() - t0 < 1.0, "emit must not block on a slow writer in real time"
    release.set()
    stream.close()


def test_an_output_failing_on_the_run_stop_is_amended_in_the_ones_before_it():
    """The station database stored 'passed', then result.json could not be written (folder
    gone read-only): the database is told again, with the fault."""
    stored = []

    class Database(Subscriber):
        def on_run_stop(self, rec):
            stored.append(rec.result["status"])

    stop = run_stop()
    stream = RecordStream(required=[Database(), Breaks("run_stop")])
    stream.emit(stop)
    stream.close()
    assert stored == ["passed", "fault"] and stop.result["exit_code"] == 3
