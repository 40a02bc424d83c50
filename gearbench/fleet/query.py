"""One query API over a station SQLite and the central PostgreSQL.

    from gearbench.fleet.query import RunQuery, open_results
    with open_results("results/station.sqlite") as db:            # or "postgresql://..."
        runs = db.runs(RunQuery(serial="SN12345", verdict="failed", since="2026-10-01"))

Each run is a dict with the same keys and values on both (``run_id, station,
serial, profile, started_utc, status, passed, exit_code, ratio, bench_time_s,
out_dir, trace_uri, measurements``; ``result`` too with ``with_result=True``).
"""
from __future__ import annotations

import json
import sqlite3
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from ..errors import GearbenchError
from ..station.database import connect as sqlite_connect, station_id
from ..station.config import target_name
from .migrations import require_current
from .push import connect as pg_connect
from ..station.database import measurements_of

VERDICTS = ("passed", "failed", "fault", "aborted")


@dataclass(frozen=True)
class RunQuery:
    serial: str | None = None
    station: str | None = None
    profile: str | None = None
    since: str | None = None        # ISO date or time (UTC if no zone), inclusive
    until: str | None = None        # exclusive
    verdict: str | None = None      # passed | failed | fault | aborted
    golden: bool | None = None
    newest_first: bool = True
    limit: int | None = None


def iso_utc(text: str | datetime | None, what: str = "time") -> str | None:
    """A time as the runs record it: ``2026-11-29T13:40:13.682+00:00``."""
    if text is None:
        return None
    if isinstance(text, datetime):
        dt = text
    else:
        try:
            dt = datetime.fromisoformat(str(text).replace("Z", "+00:00"))
        except ValueError:
            raise GearbenchError(f"--{what} '{text}': not a date/time; write e.g. 2026-11-01 "
                                 f"or 2026-11-01T08:00:00Z") from None
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=timezone.utc)
    return dt.astimezone(timezone.utc).isoformat(timespec="milliseconds")


def _where(q: RunQuery, ph: str, station_col: str | None) -> tuple[str, list]:
    if q.verdict is not None and q.verdict not in VERDICTS:
        raise GearbenchError(f"--verdict '{q.verdict}': use one of {', '.join(VERDICTS)}")
    conds, args = [], []
    for col, val in (("serial", q.serial), ("profile", q.profile), ("status", q.verdict)):
        if val is not None:
            conds.append(f"r.{col} = {ph}")
            args.append(val)
    if q.station is not None and station_col:
        conds.append(f"{station_col} = {ph}")
        args.append(q.station)
    if q.since:
        conds.append(f"r.started_utc >= {ph}")
        args.append(iso_utc(q.since, "since"))
    if q.until:
        conds.append(f"r.started_utc < {ph}")
        args.append(iso_utc(q.until, "until"))
    sql = (" WHERE " + " AND ".join(conds)) if conds else ""
    sql += f" ORDER BY r.started_utc {'DESC' if q.newest_first else 'ASC'}, r.run_id"
    if q.limit:
        sql += f" LIMIT {int(q.limit)}"
    return sql, args


class SqliteResults:
    """A station database (its station is the one it belongs to)."""

    def __init__(self, path: str | Path):

        self.path = Path(path)
        if not self.path.exists():
            raise GearbenchError(f"{self.path}: no station database here; pass --db PATH "
                                 f"(gearbench run writes it next to its output folder)")
        self.con = sqlite_connect(self.path)
        self.con.row_factory = sqlite3.Row
        self.station = station_id(self.con, self.path)
        golden = {tuple(r) for r in self.con.execute("SELECT serial, profile FROM golden")}
        self._golden = golden

    def runs(self, q: RunQuery = RunQuery(), *, with_result: bool = False) -> list[dict]:
        # a station is asked for by its id or by its bench's name (the profile's bench.name)
        by_bench = q.station is not None and q.station != self.station
        where, args = _where(q, "?", None)
        rows = self.con.execute(
            "SELECT r.run_id, r.serial, r.profile, r.started_utc, r.status, r.passed, r.exit_code, "
            "r.ratio, r.bench_time_s, r.out_dir, r.result_json FROM runs r" + where, args).fetchall()
        out = []
        for r in rows:
            d = dict(r)
            result_json = d.pop("result_json")
            if by_bench and ((json.loads(result_json or "{}").get("station") or {}).get("name")
                             != q.station):
                continue
            golden = (d["serial"], d["profile"]) in self._golden
            if q.golden is not None and golden != q.golden:
                continue
            d.update(station=self.station, passed=bool(d["passed"]), trace_uri=d["out_dir"], golden=golden)
            d["measurements"] = [dict(m) for m in self.con.execute(
                "SELECT name, value, low, high, passed, unit FROM measurements WHERE run_id = ?",
                (d["run_id"],))]
            if with_result:
                d["result"] = json.loads(result_json)
            out.append(d)
        return out

    def close(self) -> None:
        self.con.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class CentralResults:
    """The central PostgreSQL database."""

    def __init__(self, url: str):

        self.name = target_name(url)
        self.conn = pg_connect(url)
        require_current(self.conn, self.name)

    def runs(self, q: RunQuery = RunQuery(), *, with_result: bool = False) -> list[dict]:

        where, args = _where(q, "%s", "r.station_id")
        if q.golden is not None:
            where = (where.replace(" WHERE ", " WHERE r.golden = %s AND ", 1) if " WHERE " in where
                     else " WHERE r.golden = %s" + where)
            args = [q.golden, *args]
        rows = self.conn.execute(
            "SELECT r.run_id, r.station_id, r.serial, r.profile, r.started_utc, r.status, r.passed, "
            "r.exit_code, r.ratio, r.bench_time_s, r.out_dir, r.trace_uri, r.golden, r.result FROM runs r"
            + where, args).fetchall()
        out = []
        for (run_id, station, serial, profile, started, status, passed, exit_code, ratio, bench_s,
             out_dir, trace_uri, golden, result) in rows:
            d = dict(run_id=run_id, serial=serial, profile=profile, started_utc=iso_utc(started) if started else None,
                     status=status, passed=bool(passed), exit_code=exit_code, ratio=ratio,
                     bench_time_s=bench_s, out_dir=out_dir, station=station, trace_uri=trace_uri,
                     golden=bool(golden))
            d["measurements"] = [dict(zip(("name", "value", "low", "high", "passed", "unit"), m))
                                 for m in measurements_of(result)]
            if with_result:
                d["result"] = result
            out.append(d)
        return out

    def close(self) -> None:
        self.conn.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def open_results(target: str | Path):
    """A station SQLite path or a ``postgresql://`` URL."""
    if str(target).startswith(("postgresql://", "postgres://")):
        return CentralResults(str(target))
    return SqliteResults(target)
