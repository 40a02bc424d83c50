"""Crash-safe trace recorder: a subscriber that writes each step's samples as they come.

While a step acquires, its batches are appended to ``trace-<step>.arrows`` (an
Arrow IPC stream, flushed after every batch), so after ``kill -9`` every flushed
sample is readable (``read_partial``). When the step stops the stream is turned
into ``trace-<step>.parquet`` and the stream file removed. A fault mid-step still
finalises the Parquet file with everything recorded before it.
"""
from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from .records import SampleBatch, StepStart, StepStop, Subscriber
from ..trace import Trace


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name)


class ParquetRecorder(Subscriber):
    def __init__(self, out_dir: str | Path):
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self._writer = None
        self._sink = None
        self._schema = None
        self._step: str | None = None
        self.files: dict[str, Path] = {}

    def stream_path(self, step: str) -> Path:
        return self.out_dir / f"trace-{_safe(step)}.arrows"

    def parquet_path(self, step: str) -> Path:
        return self.out_dir / f"trace-{_safe(step)}.parquet"

    def on_step_start(self, rec: StepStart) -> None:
        self._finish()
        self._step = rec.name

    def on_sample_batch(self, rec: SampleBatch) -> None:
        import pyarrow as pa

        cols = {"sample": pa.array(np.asarray(rec.sample, dtype=np.int64)),
                "time_s": pa.array(np.asarray(rec.time_s, dtype=float))}
        cols.update({k: pa.array(np.asarray(v, dtype=float)) for k, v in rec.columns.items()})
        batch = pa.record_batch(cols)
        if self._writer is None:
            self._step = rec.step
            self._schema = batch.schema
            self._sink = pa.OSFile(str(self.stream_path(rec.step)), "wb")
            self._writer = pa.ipc.new_stream(self._sink, self._schema)
        self._writer.write_batch(batch)
        self._sink.flush()
        if os.fstat(self._sink.fileno()).st_nlink == 0:
            # the folder was removed under us: writes "succeed" into a file nobody can read
            raise FileNotFoundError(f"{self.stream_path(rec.step)} was removed while recording "
                                    f"(output folder deleted or unmounted?)")

    def on_step_stop(self, rec: StepStop) -> None:
        self._finish()

    def _finish(self) -> None:
        if self._writer is None:
            return
        import pyarrow.parquet as pq

        self._writer.close()
        self._sink.close()
        src = self.stream_path(self._step)
        table = read_partial(src)
        pq.write_table(table, self.parquet_path(self._step))
        src.unlink()
        self.files[self._step] = self.parquet_path(self._step)
        self._writer = self._sink = None

    def close(self) -> None:
        self._finish()


def read_partial(path: str | Path):
    """Read an Arrow IPC stream up to its last complete batch (after a crash)."""
    import pyarrow as pa

    batches = []
    with pa.OSFile(str(path), "rb") as f:
        try:
            reader = pa.ipc.open_stream(f)
        except pa.ArrowInvalid:
            return pa.table({"sample": pa.array([], pa.int64()), "time_s": pa.array([], pa.float64())})
        schema = reader.schema
        while True:
            try:
                batches.append(reader.read_next_batch())
            except (StopIteration, pa.ArrowInvalid, OSError):
                break
    return pa.Table.from_batches(batches, schema=schema)


def load_step_trace(path: str | Path) -> Trace:
    """A recorded step as a Trace (Parquet, or a partial ``.arrows`` stream)."""
    p = Path(path)
    if p.suffix == ".arrows":
        table = read_partial(p)
        cols = {n: table.column(n).to_numpy() for n in table.column_names if n != "time_s"}
        return Trace(table.column("time_s").to_numpy(), cols, {}, str(p))
    return Trace.read_parquet(p)


def motor_trace(step: Trace, motor: str) -> Trace:
    """One motor's columns of a recorded step, as a single-motor trace
    (``position_rad, current_a, command, velocity_rad_s``)."""
    prefix = f"{motor}."
    names = [n for n in step.names if n.startswith(prefix)]
    return step.select(names, rename={n: n[len(prefix):] for n in names})


def bench_trace(step: Trace, motor_in: str = "in", motor_out: str = "out") -> Trace:
    """A recorded efficiency step in the two-motor bench CSV layout."""
    cols = {}
    for side, m in (("in", motor_in), ("out", motor_out)):
        for q in ("position_rad", "current_a", "command", "velocity_rad_s"):
            if f"{m}.{q}" in step:
                cols[f"{side}_{q}"] = step[f"{m}.{q}"]
    return Trace(step.time_s, cols, dict(step.meta), step.source)
