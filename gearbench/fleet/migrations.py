"""The central database's schema as numbered migrations (``gearbench db upgrade URL``).

Pending migrations run in one transaction, each recorded in
``schema_migrations``; an advisory lock makes two stations upgrading at once safe.
A new schema change is a new entry at the end; never edit an applied one.
"""
from __future__ import annotations

from ..errors import GearbenchError

LOCK_KEY = 0x6765_6172   # "gear": advisory lock serialising concurrent upgrades

MIGRATIONS: list[tuple[int, str, str]] = [
    (1, "stations, runs, limits, motor calibrations, efficiency points, traces", """
CREATE TABLE stations (
    station_id      text PRIMARY KEY,
    first_seen_utc  timestamptz NOT NULL DEFAULT now(),
    last_seen_utc   timestamptz NOT NULL DEFAULT now());
CREATE TABLE runs (
    run_id          text PRIMARY KEY,           -- the station's run id; a run lands once
    station_id      text NOT NULL REFERENCES stations,
    serial          text NOT NULL,
    profile         text,
    profile_sha256  text,
    started_utc     timestamptz,
    finished_utc    timestamptz,
    status          text NOT NULL,              -- passed | failed | fault | aborted
    passed          boolean NOT NULL,
    exit_code       integer,
    reason          text,
    method          text,
    ratio           double precision,
    bench_time_s    double precision,
    wall_time_s     double precision,
    samples         bigint,
    lost_samples    bigint,
    golden          boolean NOT NULL DEFAULT false,   -- a reference unit's run
    out_dir         text,                       -- the folder on the station
    trace_uri       text,                       -- where the run folder is archived
    result          jsonb NOT NULL,             -- result.json as written
    received_utc    timestamptz NOT NULL DEFAULT now());
CREATE INDEX runs_serial ON runs (serial, started_utc DESC);
CREATE INDEX runs_station ON runs (station_id, started_utc);
CREATE INDEX runs_profile ON runs (profile, started_utc);
CREATE TABLE limits (
    run_id text NOT NULL REFERENCES runs ON DELETE CASCADE, idx integer NOT NULL,
    name text NOT NULL, quantity text, value double precision, low double precision,
    high double precision, passed boolean NOT NULL, PRIMARY KEY (run_id, idx));
CREATE TABLE motor_calibrations (
    run_id text NOT NULL REFERENCES runs ON DELETE CASCADE, motor text NOT NULL,
    kt_nm_per_a double precision, kt_ci95_low double precision, kt_ci95_high double precision,
    inertia_kgm2 double precision, viscous_nm_s_per_rad double precision,
    coulomb_nm double precision, method text, PRIMARY KEY (run_id, motor));
CREATE TABLE efficiency_points (
    run_id text NOT NULL REFERENCES runs ON DELETE CASCADE, idx integer NOT NULL,
    speed_setpoint_rad_s double precision, speed_in_rad_s double precision,
    torque_out_nm double precision, torque_in_nm double precision,
    eta_incremental double precision, eta_incremental_ci95_low double precision,
    eta_incremental_ci95_high double precision, eta_absolute double precision,
    eta_absolute_ci95_low double precision, eta_absolute_ci95_high double precision,
    power_in_w double precision, power_out_w double precision, PRIMARY KEY (run_id, idx));
CREATE TABLE traces (
    run_id text NOT NULL REFERENCES runs ON DELETE CASCADE, step text NOT NULL,
    uri text NOT NULL, samples bigint, PRIMARY KEY (run_id, step));
"""),
    (2, "re-analyses of archived runs", """
CREATE TABLE analyses (
    run_id            text NOT NULL REFERENCES runs ON DELETE CASCADE,
    analysis_version  text NOT NULL,
    method            text NOT NULL,
    status            text NOT NULL,
    passed            boolean,
    result            jsonb NOT NULL,
    created_utc       timestamptz NOT NULL DEFAULT now(),
    PRIMARY KEY (run_id, analysis_version, method));
"""),
]

LATEST = MIGRATIONS[-1][0]


def current_version(conn) -> int:
    """The schema version of a central database (0: empty)."""
    exists = conn.execute("SELECT to_regclass('schema_migrations')").fetchone()[0]
    if exists is None:
        return 0
    return conn.execute("SELECT coalesce(max(version), 0) FROM schema_migrations").fetchone()[0]


def upgrade(conn) -> list[tuple[int, str]]:
    """Apply the migrations not yet applied; returns those applied now."""
    applied = []
    with conn.transaction():
        conn.execute("SELECT pg_advisory_xact_lock(%s)", (LOCK_KEY,))
        conn.execute("CREATE TABLE IF NOT EXISTS schema_migrations (version integer PRIMARY KEY, "
                     "name text NOT NULL, applied_utc timestamptz NOT NULL DEFAULT now())")
        done = {v for (v,) in conn.execute("SELECT version FROM schema_migrations")}
        for version, name, sql in MIGRATIONS:
            if version in done:
                continue
            conn.execute(sql)
            conn.execute("INSERT INTO schema_migrations (version, name) VALUES (%s, %s)", (version, name))
            applied.append((version, name))
    return applied


def require_current(conn, url_name: str) -> None:
    v = current_version(conn)
    if v < LATEST:
        raise GearbenchError(f"central database {url_name} has schema version {v}, this gearbench "
                             f"needs {LATEST}; run: gearbench db upgrade URL")
    if v > LATEST:
        raise GearbenchError(f"central database {url_name} has schema version {v}, newer than this "
                             f"gearbench knows ({LATEST}); upgrade gearbench on this station")
