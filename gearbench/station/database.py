"""The station database: embedded SQLite, one row per run and per measurement.

Queryable by serial (``gearbench history SN``). Written once per run at RunStop,
in one transaction, so a crash never leaves half a run.
"""
from __future__ import annotations

import json
import os
import sqlite3
from pathlib import Path

from ..analysis.calibration import motor_value
from ..errors import GearbenchError
from .limits import point_name
from .records import RunStop, Subscriber
from .results import round_floats
from .config import default_station, station_config

SCHEMA = """
CREATE TABLE IF NOT EXISTS runs (
    run_id TEXT PRIMARY KEY, serial TEXT NOT NULL, profile TEXT, profile_sha256 TEXT,
    started_utc TEXT, finished_utc TEXT, status TEXT, passed INTEGER, exit_code INTEGER,
    ratio REAL, bench_time_s REAL, wall_time_s REAL, out_dir TEXT, result_json TEXT);
CREATE INDEX IF NOT EXISTS runs_serial ON runs(serial);
CREATE TABLE IF NOT EXISTS measurements (
    run_id TEXT NOT NULL REFERENCES runs(run_id), name TEXT NOT NULL, value REAL,
    low REAL, high REAL, passed INTEGER, unit TEXT);
CREATE INDEX IF NOT EXISTS measurements_run ON measurements(run_id);
-- the outbox: a run is pending for a central database until a row here says it landed
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT);
CREATE TABLE IF NOT EXISTS central_pushes (
    run_id TEXT NOT NULL, target TEXT NOT NULL, pushed_utc TEXT, PRIMARY KEY (run_id, target));
-- reference ("golden") units of this station and their stored baseline run
CREATE TABLE IF NOT EXISTS golden (
    serial TEXT NOT NULL, profile TEXT NOT NULL, baseline_run_id TEXT, set_utc TEXT,
    PRIMARY KEY (serial, profile));
"""


def connect(path: str | Path) -> sqlite3.Connection:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    con = sqlite3.connect(p)
    con.executescript(SCHEMA)
    return con


def check_writable(path: str | Path) -> None:
    """Refuse, before anything moves, a station database that cannot be written (a
    read-only folder, a read-only file): a probe row is written and rolled back, which
    needs the journal file beside it. Raises GearbenchError (exit 2) naming the path."""
    p = Path(path)
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        con = sqlite3.connect(p)
        try:
            con.executescript(SCHEMA)
            con.execute("BEGIN IMMEDIATE")
            con.execute("INSERT OR REPLACE INTO meta VALUES ('write_probe', '1')")
            con.rollback()
        finally:
            con.close()
    except (OSError, sqlite3.Error) as exc:
        raise GearbenchError(
            f"{p}: cannot write the station database ({exc}); the folder it is in must be "
            f"writable (SQLite keeps its journal beside it): choose another --out or --db, "
            f"or fix the permissions") from None


def station_id(con: sqlite3.Connection, db_path: str | Path | None = None,
               bench_name: str | None = None) -> str:
    """The station this database belongs to, fixed when first asked: $GEARBENCH_STATION,
    else the station config's ``station:``, else the name of the bench of its first run
    (the profile's ``bench.name``, what the people at the line call it), else the host name."""
    row = con.execute("SELECT value FROM meta WHERE key = 'station'").fetchone()
    if row:
        return row[0]

    explicit = os.environ.get("GEARBENCH_STATION") or str(station_config(db_path).get("station") or "")
    sid = explicit or bench_name or default_station(db_path)
    with con:
        con.execute("INSERT OR IGNORE INTO meta VALUES ('station', ?)", (sid,))
    return con.execute("SELECT value FROM meta WHERE key = 'station'").fetchone()[0]


def measurements_of(result: dict) -> list[tuple]:
    """Flatten a result into (name, value, low, high, passed, unit) rows."""
    rows = []
    limits = {lim["name"]: lim for lim in result.get("limits", [])}
    for motor, p in (result.get("motors") or {}).items():
        for key, unit in (("Kt", "N m/A"), ("J", "kg m^2"), ("D", "N m s/rad"), ("Tc", "N m")):
            if motor_value(p, key) is not None:
                rows.append((f"motors.{motor}.{key}", motor_value(p, key), None, None, None, unit))
    if result.get("ratio") is not None:
        rows.append(("ratio", result["ratio"], None, None, None, ""))
    for i, pt in enumerate(result.get("efficiency") or []):
        tag = f"efficiency[{i}]@{point_name('', pt)[1:-1]}"   # the commanded point
        for key in ("eta_incremental", "eta_absolute"):
            rows.append((f"{tag}.{key}", pt.get(key), None, None, None, ""))
    for name, lim in limits.items():
        rows.append((f"limit.{name}", lim.get("value"), lim.get("low"), lim.get("high"),
                     int(bool(lim.get("passed"))), ""))
    return rows


def store_run(path: str | Path, result: dict) -> None:
    result = round_floats(result)   # the numbers result.json and the central database hold
    con = connect(path)
    try:
        # a station database knows its station before its first run
        station_id(con, path, (result.get("station") or {}).get("name"))
        with con:
            con.execute(
                "INSERT OR REPLACE INTO runs VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
                (result.get("run_id"), result.get("serial"), result.get("profile"),
                 result.get("profile_sha256"), result.get("started_utc"), result.get("finished_utc"),
                 result.get("status"), int(bool(result.get("passed"))), result.get("exit_code"),
                 result.get("ratio"), result.get("bench_time_s"), result.get("wall_time_s"),
                 result.get("out_dir"), json.dumps(result, default=str)))
            con.execute("DELETE FROM measurements WHERE run_id = ?", (result.get("run_id"),))
            con.executemany("INSERT INTO measurements VALUES (?,?,?,?,?,?,?)",
                            [(result.get("run_id"), *row) for row in measurements_of(result)])
    finally:
        con.close()


def history(path: str | Path, serial: str) -> list[dict]:
    """Runs of one serial, newest first, with their measurements."""
    con = connect(path)
    con.row_factory = sqlite3.Row
    try:
        runs = [dict(r) for r in con.execute(
            "SELECT run_id, serial, profile, started_utc, status, passed, exit_code, ratio, "
            "bench_time_s, out_dir FROM runs WHERE serial = ? ORDER BY started_utc DESC", (serial,))]
        for r in runs:
            r["measurements"] = [dict(m) for m in con.execute(
                "SELECT name, value, low, high, passed, unit FROM measurements WHERE run_id = ?",
                (r["run_id"],))]
        return runs
    finally:
        con.close()


class StationDatabase(Subscriber):
    def __init__(self, path: str | Path):
        self.path = Path(path)

    def on_run_stop(self, rec: RunStop) -> None:
        store_run(self.path, rec.result)
