"""Push finished runs from a station's SQLite outbox to the central PostgreSQL.

A run is pending for a central database until ``central_pushes`` in the station
SQLite says it landed. Pushing is:

- idempotent: ``runs.run_id`` is the key; a run already there is skipped
  (``ON CONFLICT DO NOTHING``) and its child rows are only written together with
  the run row, in the same transaction, so a retry never duplicates anything;
- resumable: runs go over in batches, each its own transaction, and are marked
  in the outbox after the commit; a crash between the two only causes a skip later;
- safe with concurrent pushers: two stations (or two ``sync`` of one station)
  inserting the same key wait for each other's commit and then skip.

The run itself never waits on this: the result is in result.json and the station
SQLite before a push starts, and ``CentralPush`` works in a background thread.
"""
from __future__ import annotations

import json
import sqlite3
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import GearbenchError
from ..station.records import RunStop, Subscriber
from ..station.results import _clean
from . import migrations
from ..station.config import target_name, trace_store
from ..analysis.calibration import motor_value
from ..station.recorder import _safe
from ..station.database import connect as sqlite_connect, station_id

CONNECT_TIMEOUT_S = 3       # a tester on a dead network gives up fast; sync retries later
PUSH_WAIT_S = 6.0           # at most this long at the end of a run for the background push
BATCH_RUNS = 50             # runs per transaction


class CentralUnreachable(GearbenchError):
    """The central database did not answer (network, server down): not bad input."""
    exit_code = 3


class RunIdCollision(Exception):
    """Two different runs with one id: refused, reported, left pending in the outbox."""


@dataclass
class PushReport:
    target: str
    pushed: int = 0           # newly stored centrally
    already: int = 0          # were there already (a retry after a lost acknowledgement)
    pending: int = 0          # still waiting in the outbox
    error: str = ""
    failed_runs: dict = field(default_factory=dict)   # run_id -> why it was refused

    @property
    def ok(self) -> bool:
        return not self.error and not self.failed_runs


def connect(url: str, *, timeout_s: float = CONNECT_TIMEOUT_S):
    import psycopg

    try:
        return psycopg.connect(url, autocommit=True, connect_timeout=max(1, int(timeout_s)))
    except psycopg.OperationalError as exc:
        raise CentralUnreachable(f"central database {target_name(url)} unreachable: "
                             f"{str(exc).strip().splitlines()[-1]}") from None


# ------------------------------------------------------------------ rows of a run
def _ts(v):
    return v or None


def _pair(v):
    return (v[0], v[1]) if isinstance(v, (list, tuple)) and len(v) == 2 else (None, None)


def _num(v):
    return float(v) if isinstance(v, (int, float)) and v == v else None


def trace_uris(result: dict, out_dir: str, store: str | None) -> list[tuple[str, str, int]]:
    """(step, uri, samples) of a run's trace files: in the archive store when the
    station has one (``store/<run folder>/trace-<step>.parquet``), else on the station."""
    base = f"{store.rstrip('/')}/{Path(out_dir).name}" if store else out_dir
    return [(step, f"{base}/trace-{_safe(step)}.parquet", int(n))
            for step, n in (result.get("steps") or {}).items()]


def _insert_run(cur, station: str, result: dict, out_dir: str, store: str | None, golden: bool) -> bool:
    rid = result["run_id"]
    base = f"{store.rstrip('/')}/{Path(out_dir).name}" if store else out_dir
    cur.execute(
        "INSERT INTO runs (run_id, station_id, serial, profile, profile_sha256, started_utc, "
        "finished_utc, status, passed, exit_code, reason, method, ratio, bench_time_s, wall_time_s, "
        "samples, lost_samples, golden, out_dir, trace_uri, result) VALUES "
        "(%s,%s,%s,%s,%s,%s,%s,%s,%s,%s,%s,%s,%s,%s,%s,%s,%s,%s,%s,%s,%s) "
        "ON CONFLICT (run_id) DO NOTHING RETURNING run_id",
        (rid, station, result.get("serial") or "", result.get("profile"), result.get("profile_sha256"),
         _ts(result.get("started_utc")), _ts(result.get("finished_utc")), result.get("status") or "unknown",
         bool(result.get("passed")), result.get("exit_code"), result.get("reason"), result.get("method"),
         _num(result.get("ratio")), _num(result.get("bench_time_s")), _num(result.get("wall_time_s")),
         result.get("samples"), result.get("lost_samples"), golden, out_dir, base,
         json.dumps(result, default=str)))
    if cur.fetchone() is None:
        # there already: the same run pushed before (a retry), or another run with the same
        # id, which must not vanish silently
        cur.execute("SELECT station_id, serial, started_utc = %s::timestamptz FROM runs WHERE run_id = %s",
                    (_ts(result.get("started_utc")), rid))
        there = cur.fetchone()
        if there and (there[0] != station or there[1] != (result.get("serial") or "") or there[2] is False):
            raise RunIdCollision(f"run id {rid} is already used centrally by station {there[0]}, "
                                 f"serial {there[1]}")
        return False
    cur.executemany(
        "INSERT INTO limits VALUES (%s,%s,%s,%s,%s,%s,%s,%s)",
        [(rid, i, lim.get("name"), lim.get("quantity"), _num(lim.get("value")), _num(lim.get("low")),
          _num(lim.get("high")), bool(lim.get("passed"))) for i, lim in enumerate(result.get("limits") or [])])
    cur.executemany(
        "INSERT INTO motor_calibrations VALUES (%s,%s,%s,%s,%s,%s,%s,%s,%s)",
        [(rid, m, _num(p.get("Kt")), *_pair(p.get("Kt_ci95")), _num(motor_value(p, "J")), _num(motor_value(p, "D")),
          _num(motor_value(p, "Tc")), p.get("method")) for m, p in (result.get("motors") or {}).items()])
    cur.executemany(
        "INSERT INTO efficiency_points VALUES (%s,%s,%s,%s,%s,%s,%s,%s,%s,%s,%s,%s,%s,%s)",
        [(rid, i, _num(p.get("speed_setpoint_rad_s")), _num(p.get("speed_in_rad_s")),
          _num(p.get("torque_out_nm")), _num(p.get("torque_in_nm")), _num(p.get("eta_incremental")),
          *_pair(p.get("eta_incremental_ci95")), _num(p.get("eta_absolute")),
          *_pair(p.get("eta_absolute_ci95")), _num(p.get("power_in_w")), _num(p.get("power_out_w")))
         for i, p in enumerate(result.get("efficiency") or [])])
    cur.executemany("INSERT INTO traces VALUES (%s,%s,%s,%s)",
                    [(rid, *t) for t in trace_uris(result, out_dir, store)])
    return True


def _resolve_out_dir(out_dir: str, db_path: Path) -> str:
    """Runs record their folder as given on the command line; centrally it must be absolute."""
    p = Path(out_dir or "")
    if p.is_absolute() or not out_dir:
        return out_dir or ""
    for base in (Path.cwd(), db_path.parent, db_path.parent.parent):
        if (base / p).exists():
            return str((base / p).resolve())
    return out_dir


# -------------------------------------------------------------------------- push
def pending_runs(con: sqlite3.Connection, target: str, limit: int | None = None) -> list[tuple]:
    sql = ("SELECT r.run_id, r.result_json, r.out_dir, r.serial, r.profile FROM runs r WHERE NOT EXISTS "
           "(SELECT 1 FROM central_pushes p WHERE p.run_id = r.run_id AND p.target = ?) ORDER BY r.rowid")
    rows = con.execute(sql, (target,)).fetchall()
    return rows[:limit] if limit else rows


def push_pending(db_path: str | Path, url: str, *, batch: int = BATCH_RUNS,
                 timeout_s: float = CONNECT_TIMEOUT_S, conn=None) -> PushReport:
    """Push every run of the station database not yet in the central one.

    Never raises for a network problem: the report says what is still pending."""
    import psycopg

    db_path = Path(db_path)
    target = target_name(url)
    rep = PushReport(target)
    con = sqlite_connect(db_path)
    own = conn is None
    try:
        station = station_id(con, db_path)
        store = trace_store(db_path)
        golden = {tuple(r) for r in con.execute("SELECT serial, profile FROM golden")}
        todo = pending_runs(con, target)
        rep.pending = len(todo)
        if not todo:
            return rep
        try:
            conn = conn or connect(url, timeout_s=timeout_s)
            migrations.require_current(conn, target)
        except GearbenchError as exc:
            rep.error = str(exc)
            return rep
        for i in range(0, len(todo), batch):
            chunk = todo[i:i + batch]
            try:
                done = _push_batch(conn, station, chunk, db_path, store, golden, rep)
            except psycopg.OperationalError as exc:      # the network went away mid-way
                rep.error = f"central database {target}: connection lost ({str(exc).strip()})"
                break
            except (psycopg.Error, RunIdCollision):
                # one bad run must not hold the queue: retry the batch run by run
                done = []
                for row in chunk:
                    try:
                        done += _push_batch(conn, station, [row], db_path, store, golden, rep)
                    except psycopg.OperationalError as exc:
                        rep.error = f"central database {target}: connection lost ({str(exc).strip()})"
                        break
                    except (psycopg.Error, RunIdCollision) as exc:
                        rep.failed_runs[row[0]] = str(exc).strip().splitlines()[0]
                if rep.error:
                    _mark(con, done, target)
                    break
            _mark(con, done, target)
            rep.pending -= len(done)
        return rep
    finally:
        con.close()
        if own and conn is not None:
            conn.close()


def _push_batch(conn, station, rows, db_path, store, golden, rep) -> list[str]:
    new = old = 0
    with conn.transaction(), conn.cursor() as cur:
        cur.execute("INSERT INTO stations (station_id) VALUES (%s) ON CONFLICT (station_id) "
                    "DO UPDATE SET last_seen_utc = now()", (station,))
        for run_id, result_json, out_dir, serial, profile in rows:
            result = _clean(json.loads(result_json))   # NaN -> null: jsonb is strict JSON
            if _insert_run(cur, station, result, _resolve_out_dir(out_dir, db_path), store,
                           (serial, profile) in golden):
                new += 1
            else:
                old += 1
    rep.pushed += new
    rep.already += old
    return [r[0] for r in rows]


def _mark(con: sqlite3.Connection, run_ids: list[str], target: str) -> None:
    if run_ids:
        now = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
        with con:
            con.executemany("INSERT OR IGNORE INTO central_pushes VALUES (?,?,?)",
                            [(r, target, now) for r in run_ids])


# -------------------------------------------------------------------- subscriber
class CentralPush(Subscriber):
    """After a run is stored in the station database, push the outbox (this run and
    anything left from an outage) in a background thread; never fails the run."""

    def __init__(self, db_path: str | Path, url: str, *, quiet: bool = False, stream=None):
        self.db_path, self.url, self.quiet, self.out = Path(db_path), url, quiet, stream
        self.thread: threading.Thread | None = None
        self.report: PushReport | None = None

    def on_run_stop(self, rec: RunStop) -> None:
        def work():
            try:
                self.report = push_pending(self.db_path, self.url)
            except Exception as exc:   # whatever happens, the run is already safe in the outbox
                self.report = PushReport(self.url, error=f"{type(exc).__name__}: {exc}")

        self.thread = threading.Thread(target=work, name="gearbench-central-push", daemon=True)
        self.thread.start()

    def close(self) -> None:
        if self.thread is None:
            return
        self.thread.join(PUSH_WAIT_S)
        rep = self.report
        if rep is None:
            msg = f"central: push still running after {PUSH_WAIT_S:g} s; the run stays in the outbox " \
                  f"(gearbench sync --db {self.db_path} --to URL)"
        elif rep.error or rep.pending:
            msg = f"central: {rep.error or 'not all runs pushed'}; {rep.pending} run(s) kept in the " \
                  f"outbox {self.db_path} (gearbench sync --db {self.db_path} --to URL)"
        else:
            msg = f"central: {rep.pushed} run(s) pushed to {rep.target}" if rep.pushed else ""
        if msg and not (self.quiet and rep is not None and rep.ok):
            print(msg, file=self.out or sys.stderr)
