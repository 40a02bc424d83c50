"""``Trace``: the one columnar type that flows through gearbench.

A trace is a time base (``time_s``, seconds, strictly increasing) plus named
columns of equal length (SI units, unit suffix in the name: ``current_a``,
``position_rad``) and a metadata dict. It reads and writes CSV (for data from any
rig) and Parquet (what the sequencer records).

Standard column sets::

    single motor:  time_s, position_rad, current_a [, command, velocity_rad_s]
    bench:         time_s, in_position_rad, in_current_a, out_position_rad,
                   out_current_a, in_command, out_command
"""
from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np

from .errors import TraceError

SINGLE_MOTOR_COLUMNS = ("position_rad", "current_a")
SINGLE_MOTOR_OPTIONAL = ("command", "velocity_rad_s")
BENCH_COLUMNS = ("in_position_rad", "in_current_a", "out_position_rad",
                 "out_current_a", "in_command", "out_command")

_PARQUET_META_KEY = b"gearbench"


@dataclass
class Trace:
    """Time base + named columns + metadata.

    Parameters
    ----------
    time_s : array of float, strictly increasing sample times in seconds.
    columns : mapping name -> 1-D array, same length as ``time_s``.
    meta : free-form JSON-serialisable metadata (units, motor, step, truth...).
    source : where the trace came from (a file path); used in error messages.
    """

    time_s: np.ndarray
    columns: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict = field(default_factory=dict)
    source: str = "<array>"

    def __post_init__(self) -> None:
        self.time_s = np.asarray(self.time_s, dtype=float)
        if self.time_s.ndim != 1:
            raise TraceError(f"{self.source}: time_s must be one-dimensional")
        cols = {}
        for name, values in dict(self.columns).items():
            arr = np.asarray(values)
            if arr.dtype.kind not in "fiub":
                raise TraceError(f"{self.source}: column '{name}' is not numeric")
            arr = arr.astype(float) if arr.dtype.kind in "fb" else arr
            if arr.shape != self.time_s.shape:
                raise TraceError(
                    f"{self.source}: column '{name}' has {arr.shape[0] if arr.ndim else 0} "
                    f"samples but time_s has {self.time_s.shape[0]}")
            cols[name] = arr
        self.columns = cols

    # ------------------------------------------------------------------ access
    def __len__(self) -> int:
        return int(self.time_s.shape[0])

    def __contains__(self, name: str) -> bool:
        return name == "time_s" or name in self.columns

    def __getitem__(self, name: str) -> np.ndarray:
        if name == "time_s":
            return self.time_s
        try:
            return self.columns[name]
        except KeyError:
            raise TraceError(
                f"{self.source}: missing column '{name}' (has: "
                f"{', '.join(['time_s', *self.columns]) or 'none'}); "
                f"rename the column in the file or export it from your rig") from None

    @property
    def names(self) -> list[str]:
        return list(self.columns)

    @property
    def dt_s(self) -> float:
        """Median sample period in seconds."""
        if len(self) < 2:
            raise TraceError(f"{self.source}: fewer than 2 samples; record a longer run")
        return float(np.median(np.diff(self.time_s)))

    @property
    def rate_hz(self) -> float:
        return 1.0 / self.dt_s

    def get(self, name: str, default=None):
        return self.columns.get(name, default)

    def require(self, *names: str) -> "Trace":
        """Raise a TraceError naming the first missing column; return self."""
        for n in names:
            self[n]
        return self

    # ----------------------------------------------------------- derivations
    def slice(self, start: int | None = None, stop: int | None = None) -> "Trace":
        """Rows ``start:stop`` (index based), same metadata."""
        s = slice(start, stop)
        return Trace(self.time_s[s].copy(), {k: v[s].copy() for k, v in self.columns.items()},
                     dict(self.meta), self.source)

    def window(self, t0_s: float, t1_s: float) -> "Trace":
        """Rows with t0_s <= time_s < t1_s."""
        i0, i1 = np.searchsorted(self.time_s, [t0_s, t1_s])
        return self.slice(int(i0), int(i1))

    def with_columns(self, **cols: Iterable[float]) -> "Trace":
        new = dict(self.columns)
        new.update({k: np.asarray(v) for k, v in cols.items()})
        return Trace(self.time_s, new, dict(self.meta), self.source)

    def select(self, names: Iterable[str], rename: Mapping[str, str] | None = None) -> "Trace":
        """Keep ``names`` (optionally renamed), e.g. one motor out of a bench trace."""
        rename = dict(rename or {})
        return Trace(self.time_s, {rename.get(n, n): self[n] for n in names},
                     dict(self.meta), self.source)

    # ----------------------------------------------------------- validation
    def validate(self, required: Iterable[str] = (), *, min_samples: int = 20,
                 regular: bool = True, rel_jitter: float = 0.05) -> "Trace":
        """Check a trace is usable for analysis; raise TraceError saying the fix.

        Checks: required columns present, enough samples, finite values, strictly
        increasing time and (``regular``) a constant sample period within
        ``rel_jitter`` of the median.
        """
        self.require(*required)
        n = len(self)
        if n < min_samples:
            raise TraceError(f"{self.source}: only {n} samples, need at least {min_samples}; "
                             f"record a longer run")
        for name in ["time_s", *required]:
            arr = self[name]
            bad = ~np.isfinite(arr.astype(float))
            if bad.any():
                i = int(np.argmax(bad))
                raise TraceError(f"{self.source}: column '{name}' has a non-finite value "
                                 f"(NaN/inf) at row {i + 1}{self._line_hint(i)}; "
                                 f"remove or fill the gap before analysis")
        d = np.diff(self.time_s)
        if (d <= 0).any():
            i = int(np.argmax(d <= 0)) + 1
            raise TraceError(f"{self.source}: time_s is not strictly increasing at row "
                             f"{i + 1}{self._line_hint(i)}; sort the rows or fix the time stamps")
        if regular:
            med = float(np.median(d))
            dev = np.abs(d - med) > rel_jitter * med
            if dev.any():
                i = int(np.argmax(dev)) + 1
                raise TraceError(
                    f"{self.source}: irregular sampling at row {i + 1}{self._line_hint(i)} "
                    f"(step {d[i - 1]:.6g} s vs median {med:.6g} s); resample to a constant "
                    f"period or fix the lost samples")
        return self

    def _line_hint(self, row: int) -> str:
        first = self.meta.get("_csv_first_data_line")
        return f" (file line {first + row})" if first else ""

    # -------------------------------------------------------------------- I/O
    @classmethod
    def read(cls, path: str | Path) -> "Trace":
        """Read a ``.csv`` or ``.parquet`` trace (by suffix)."""
        p = Path(path)
        if not p.exists():
            raise TraceError(f"{p}: file not found; check the path")
        if p.suffix.lower() in (".parquet", ".pq"):
            return cls.read_parquet(p)
        return cls.read_csv(p)

    def write(self, path: str | Path) -> Path:
        p = Path(path)
        if p.suffix.lower() in (".parquet", ".pq"):
            return self.write_parquet(p)
        return self.write_csv(p)

    @classmethod
    def read_csv(cls, path: str | Path) -> "Trace":
        """Read CSV with a header row; ``#`` lines before the header carry JSON meta.

        A first column named ``time_s`` is the time base. Every other column must be
        numeric; the error names the file line and column of the first bad cell.
        """
        p = Path(path)
        try:
            text = p.read_text(encoding="utf-8-sig")
        except (OSError, UnicodeDecodeError) as exc:
            raise TraceError(f"{p}: cannot read file ({exc.__class__.__name__}: {exc}); "
                             f"check the path and that it is a text CSV") from None
        meta: dict = {}
        lines = text.splitlines()
        li = 0
        while li < len(lines) and (lines[li].startswith("#") or not lines[li].strip()):
            line = lines[li].lstrip("#").strip()
            if line.startswith("{"):
                try:
                    meta.update(json.loads(line))
                except json.JSONDecodeError:
                    pass
            li += 1
        if li >= len(lines):
            raise TraceError(f"{p}: no header row; the first line must name the columns, "
                             f"e.g. 'time_s,position_rad,current_a'")
        header = [h.strip() for h in next(csv.reader([lines[li]]))]
        header_line = li + 1
        if "time_s" not in header:
            raise TraceError(f"{p}: line {header_line}: no 'time_s' column (header: "
                             f"{', '.join(header)}); name the time column 'time_s' in seconds")
        if len(set(header)) != len(header):
            dup = sorted({h for h in header if header.count(h) > 1})
            raise TraceError(f"{p}: line {header_line}: duplicate column(s) {', '.join(dup)}; "
                             f"give each column a unique name")
        body = lines[li + 1:]
        ncol = len(header)
        data = np.empty((len(body), ncol))
        rows = 0
        for k, line in enumerate(body):
            if not line.strip() or line.startswith("#"):
                continue
            cells = line.split(",")
            if len(cells) != ncol:
                raise TraceError(f"{p}: line {header_line + 1 + k}: {len(cells)} cells, header "
                                 f"has {ncol}; fix the row")
            try:
                data[rows] = [float(c) if c.strip() else math.nan for c in cells]
            except ValueError:
                for j, c in enumerate(cells):
                    try:
                        float(c)
                    except ValueError:
                        raise TraceError(
                            f"{p}: line {header_line + 1 + k}, column '{header[j]}': "
                            f"'{c.strip()}' is not a number; fix the value") from None
            rows += 1
        data = data[:rows]
        meta["_csv_first_data_line"] = header_line + 1
        ti = header.index("time_s")
        cols = {h: data[:, j] for j, h in enumerate(header) if j != ti}
        return cls(data[:, ti], cols, meta, str(p))

    def write_csv(self, path: str | Path) -> Path:
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        names = ["time_s", *self.columns]
        arr = np.column_stack([self.time_s, *[self.columns[n] for n in self.columns]])
        meta = {k: v for k, v in self.meta.items() if not k.startswith("_")}
        header = (f"# {json.dumps(meta, default=_json_default)}\n" if meta else "") + ",".join(names)
        np.savetxt(p, arr, delimiter=",", header=header, comments="", fmt="%.10g")
        return p

    @classmethod
    def read_parquet(cls, path: str | Path) -> "Trace":
        import pyarrow.parquet as pq

        p = Path(path)
        try:
            table = pq.read_table(p)
        except Exception as exc:  # pyarrow raises several types for bad files
            raise TraceError(f"{p}: not a readable Parquet file ({exc}); "
                             f"re-export it or use CSV") from None
        md = table.schema.metadata or {}
        meta = json.loads(md[_PARQUET_META_KEY]) if _PARQUET_META_KEY in md else {}
        if "time_s" not in table.column_names:
            raise TraceError(f"{p}: no 'time_s' column; name the time column 'time_s'")
        cols = {n: table.column(n).to_numpy() for n in table.column_names if n != "time_s"}
        return cls(table.column("time_s").to_numpy(), cols, meta, str(p))

    def write_parquet(self, path: str | Path) -> Path:
        import pyarrow as pa
        import pyarrow.parquet as pq

        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        arrays = {"time_s": self.time_s, **self.columns}
        table = pa.table({k: pa.array(v) for k, v in arrays.items()})
        meta = {k: v for k, v in self.meta.items() if not k.startswith("_")}
        table = table.replace_schema_metadata(
            {_PARQUET_META_KEY: json.dumps(meta, default=_json_default).encode()})
        pq.write_table(table, p)
        return p

    @classmethod
    def concat(cls, traces: list["Trace"]) -> "Trace":
        if not traces:
            raise TraceError("no traces to concatenate")
        names = traces[0].names
        return cls(np.concatenate([t.time_s for t in traces]),
                   {n: np.concatenate([t[n] for t in traces]) for n in names},
                   dict(traces[0].meta), traces[0].source)


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
