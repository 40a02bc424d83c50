"""A factory of testers: central PostgreSQL fed from station outboxes, history across
stations, re-analysis on a Dask cluster, golden-unit check.

A throwaway PostgreSQL cluster (initdb in a temp folder, pg_ctl on a free port) and
real Dask scheduler/worker processes; one real simulated run feeds them.
"""
import copy
import json
import os
import shutil
import sqlite3
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")
try:
    import psycopg
except ImportError:
    if IN_CI:
        raise
    pytest.skip("psycopg not installed: pip install -e '.[test]'", allow_module_level=True)

from gearbench.fleet.pgtemp import PostgreSQLUnavailable, TempPostgres, free_port  # noqa: E402
from gearbench.fleet.push import CentralPush, push_pending  # noqa: E402
from gearbench.fleet.query import RunQuery, open_results  # noqa: E402
from gearbench.station.records import RunStop  # noqa: E402
from gearbench.station.database import StationDatabase, store_run  # noqa: E402


def gearbench_proc(*args, env=None, timeout=180):
    """A separate process (for concurrency and the real run)."""
    return subprocess.run([sys.executable, "-m", "gearbench", *map(str, args)], cwd=REPO,
                          capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, **(env or {})})


class Done:
    def __init__(self, returncode, stdout, stderr):
        self.returncode, self.stdout, self.stderr = returncode, stdout, stderr


@pytest.fixture
def cli(capsys):
    """The command line in this process (the host is shared: no interpreter start-up per call)."""
    from gearbench.cli import main

    def call(*args):
        capsys.readouterr()
        try:
            code = main([str(a) for a in args])
        except SystemExit as exc:
            code = exc.code
        out, err = capsys.readouterr()
        return Done(code, out, err)
    return call


@pytest.fixture(scope="module")
def pg():
    try:
        server = TempPostgres()
        server.start()
    except PostgreSQLUnavailable as exc:
        if IN_CI:
            pytest.fail(f"PostgreSQL needed in CI: {exc}")
        pytest.skip(f"no PostgreSQL server: {exc}")
    try:
        from gearbench.fleet import migrations
        from gearbench.fleet.push import connect

        with connect(server.url) as conn:
            migrations.upgrade(conn)
        yield server
    finally:
        server.cleanup()


@pytest.fixture(scope="module")
def real_run(pg, tmp_path_factory):
    """One real run on the simulated bench, pushed by the run itself, as a golden unit."""
    station = tmp_path_factory.mktemp("station-A")
    for attempt in (1, 2, 3):  # a host loaded by other jobs can starve the emulated drives
        out = station / f"run-G1-{attempt}"
        p = gearbench_proc("run", REPO / "profiles" / "motors-only.yaml", "--sim", "--out", out, "--serial",
                      "GOLD-1", "--golden", env={"GEARBENCH_STATION": "st-A", "GEARBENCH_CENTRAL": pg.url})
        if p.returncode != 3:
            break
    assert p.returncode == 0, p.stderr[-2000:]
    return out, json.loads((out / "result.json").read_text())


@pytest.fixture(scope="module")
def template():
    """A real run's result.json (motors-only on the simulated bench), the shape that
    synthetic runs of many stations copy."""
    return json.loads((REPO / "tests" / "data" / "result-motors-only.json").read_text())


def central_count(url, sql="SELECT count(*) FROM runs", args=None):
    with psycopg.connect(url) as c:
        return c.execute(sql, args).fetchone()[0]


def synthetic(result: dict, run_id: str, serial: str, started: str, status="passed") -> dict:
    r = copy.deepcopy(result)
    r.update(run_id=run_id, serial=serial, started_utc=started, status=status,
             passed=status == "passed", exit_code={"passed": 0, "failed": 1}.get(status, 3))
    return r


# ------------------------------------------------------------------- schema
def test_db_upgrade_is_versioned_and_idempotent(pg, cli):
    with psycopg.connect(pg.url, autocommit=True) as c:
        c.execute("DROP DATABASE IF EXISTS fresh")
        c.execute("CREATE DATABASE fresh")
    fresh = pg.url.rsplit("/", 1)[0] + "/fresh"
    p = cli("db", "status", fresh)
    assert p.returncode == 1 and "schema version 0" in p.stdout
    p = cli("history", "X", "--central", fresh)
    assert p.returncode == 2 and "gearbench db upgrade" in p.stderr and "Traceback" not in p.stderr
    p = cli("db", "upgrade", fresh)
    assert p.returncode == 0 and "applied migration 1" in p.stdout and "schema version 2" in p.stdout
    p = cli("db", "upgrade", fresh)
    assert p.returncode == 0 and "up to date" in p.stdout and "applied" not in p.stdout.split("(")[0]
    p = cli("db", "upgrade", f"postgresql://postgres@127.0.0.1:{free_port()}/x")
    assert p.returncode == 3 and "unreachable" in p.stderr and "Traceback" not in p.stderr


# ---------------------------------------------------- the run pushes itself
def test_a_run_lands_in_the_central_database_and_history_is_the_same_on_both(pg, real_run, cli):
    out, res = real_run
    assert central_count(pg.url, "SELECT count(*) FROM runs WHERE run_id = %s", (res["run_id"],)) == 1
    assert central_count(pg.url, "SELECT count(*) FROM motor_calibrations WHERE run_id = %s",
                         (res["run_id"],)) == 2
    assert central_count(pg.url, "SELECT count(*) FROM traces WHERE run_id = %s AND uri LIKE %s",
                         (res["run_id"], f"{out}/trace-%.parquet")) == 4
    assert central_count(pg.url, "SELECT count(*) FROM runs WHERE run_id = %s AND golden AND station_id = 'st-A'",
                         (res["run_id"],)) == 1
    local = cli("history", "GOLD-1", "--db", out.parent / "station.sqlite", "--json")
    central = cli("history", "GOLD-1", "--central", pg.url, "--json")
    assert local.returncode == central.returncode == 0, local.stderr + central.stderr
    assert json.loads(local.stdout) == json.loads(central.stdout)
    assert json.loads(central.stdout)["runs"][0]["measurements"]
    # the archived profile makes the run re-analysable whatever happens to profiles/
    assert (out / "profile.yaml").exists()


def test_golden_unit_baseline_then_compared(real_run):
    from gearbench.fleet.golden import check_golden, compare

    out, res = real_run
    assert json.loads((out / "golden.json").read_text())["status"] == "baseline-set"
    db = out.parent / "station.sqlite"
    again = dict(res, run_id="again")
    assert check_golden(db, again)["status"] == "matches"
    drifted = copy.deepcopy(res)
    drifted["motors"]["in"]["Kt"] *= 1.02                       # the tester's input motor lost 2 %
    rep = check_golden(db, drifted)
    assert rep["status"] == "deviates"
    assert [r["quantity"] for r in rep["rows"] if r["ok"] is False] == ["motors.in.Kt"]
    tiny = copy.deepcopy(res)
    tiny["motors"]["in"]["Kt"] += 1e-6                          # well inside the CIs
    assert all(r["ok"] is not False for r in compare(res, tiny))


# ------------------------------------------- two stations, an outage, retries
def test_two_stations_survive_an_outage_without_loss_or_duplication(pg, template, tmp_path, monkeypatch, cli):
    res = template
    dbs = {s: tmp_path / s / "station.sqlite" for s in ("st-L1", "st-L2")}
    runs = {s: [] for s in dbs}
    for s, db in dbs.items():
        monkeypatch.setenv("GEARBENCH_STATION", s)
        for k in range(3):          # online: each run pushed by the subscriber as it finishes
            r = synthetic(res, f"{s}-on-{k}", f"SN-{k}", f"2026-11-0{k + 1}T08:00:00.000+00:00")
            runs[s].append(r["run_id"])
            push = CentralPush(db, pg.url, quiet=True)
            StationDatabase(db)(RunStop("passed", 0, "", r))
            push(RunStop("passed", 0, "", r))
            push.close()
            assert push.report.ok and push.report.pushed == 1
    pg.stop()                       # the network (or the server) goes away
    try:
        for s, db in dbs.items():
            monkeypatch.setenv("GEARBENCH_STATION", s)
            for k in range(20):
                status = "failed" if k % 5 == 0 else "passed"
                r = synthetic(res, f"{s}-off-{k}", f"SN-{k % 7}", f"2026-11-10T{k:02d}:00:00.000+00:00", status)
                runs[s].append(r["run_id"])
                t0 = time.monotonic()
                push = CentralPush(db, pg.url, quiet=True)
                StationDatabase(db)(RunStop(status, 0, "", r))
                push(RunStop(status, 0, "", r))
                push.close()                # the run is never failed by the network
                assert time.monotonic() - t0 < 8
                assert push.report.error and push.report.pending == k + 1
    finally:
        pg.start()
        pg.wait_ready()
    # an interrupted push: committed centrally, the acknowledgement lost before the outbox saw it
    with sqlite3.connect(dbs["st-L1"]) as con:
        con.execute("DELETE FROM central_pushes WHERE run_id = 'st-L1-on-2'")
    # both stations sync at once, station 1 twice concurrently (each its own connections)
    jobs = [dbs["st-L1"], dbs["st-L1"], dbs["st-L2"], dbs["st-L2"]]
    with ThreadPoolExecutor(len(jobs)) as ex:
        reps = list(ex.map(lambda db: push_pending(db, pg.url, batch=4), jobs))
    assert all(r.ok for r in reps), reps
    assert sum(r.pushed for r in reps) == 40                    # 2 x 20 runs of the outage
    assert sum(r.already for r in reps) >= 1                    # st-L1-on-2 (lost acknowledgement)
    for s, ids in runs.items():
        with psycopg.connect(pg.url) as c:
            got = [r for (r,) in c.execute("SELECT run_id FROM runs WHERE station_id = %s ORDER BY run_id", (s,))]
        assert got == sorted(ids)                                  # none lost, none twice
    ours = "SELECT count(*) FROM {} x JOIN runs r USING (run_id) WHERE r.station_id LIKE %s"
    assert central_count(pg.url, "SELECT count(*) FROM runs WHERE station_id LIKE %s", ("st-L%",)) == 46
    assert central_count(pg.url, ours.format("limits"), ("st-L%",)) == 46 * len(res["limits"])
    assert central_count(pg.url, ours.format("motor_calibrations"), ("st-L%",)) == 46 * 2
    again = cli("sync", "--db", dbs["st-L2"], "--to", pg.url)
    assert again.returncode == 0 and "0 run(s) pushed" in again.stdout and "0 pending" in again.stdout
    # another station's run with an id already taken is refused loudly, never dropped silently
    monkeypatch.setenv("GEARBENCH_STATION", "st-L3")
    store_run(tmp_path / "st-L3" / "station.sqlite", synthetic(res, "st-L1-off-3", "SN-X", "2026-11-12T00:00:00Z"))
    p = cli("sync", "--db", tmp_path / "st-L3" / "station.sqlite", "--to", pg.url)
    assert p.returncode == 1 and "already used centrally by station st-L1" in p.stdout and "1 pending" in p.stdout

    # the same query API on both: by serial across stations, by verdict, station, time range
    q = RunQuery(serial="SN-1", verdict="passed", since="2026-11-02", until="2026-11-10T05:00:00Z")
    with open_results(pg.url) as central:
        both = central.runs(q)
        assert {r["station"] for r in both} == {"st-L1", "st-L2"}
        assert [r["started_utc"] for r in both][:2] == ["2026-11-10T01:00:00.000+00:00"] * 2
        for s, db in dbs.items():
            with open_results(db) as local:
                for qq in (q, RunQuery(verdict="failed"), RunQuery(profile="motors-only", newest_first=False)):
                    want = local.runs(qq)
                    assert want and central.runs(RunQuery(**{**qq.__dict__, "station": s})) == want
    p = cli("history", "SN-2", "--central", pg.url, "--verdict", "failed")
    assert p.returncode == 0 and "no runs for SN-2" in p.stdout
    p = cli("history", "SN-0", "--central", pg.url, "--verdict", "failed", "--json")
    assert sorted(r["station"] for r in json.loads(p.stdout)["runs"]) == ["st-L1", "st-L2"]


def test_bad_input_is_one_line_exit_2(tmp_path, cli):
    p = cli("history", "SN1", "--db", tmp_path / "none.sqlite")
    assert p.returncode == 2 and "no station database" in p.stderr
    p = cli("history", "--since", "yesterday", "--db", tmp_path / "none.sqlite")
    assert p.returncode == 2
    store_run(tmp_path / "st.sqlite", {"run_id": "r", "serial": "S", "status": "passed"})
    p = cli("history", "--since", "last week", "--db", tmp_path / "st.sqlite")
    assert p.returncode == 2 and "not a date/time" in p.stderr
    (tmp_path / "station.yaml").write_text("central: postgresql://x@h/db\nlinee: 3\n")
    p = cli("sync", "--db", tmp_path / "st.sqlite")
    assert p.returncode == 2 and "unknown key(s) linee" in p.stderr and "Traceback" not in p.stderr


# ------------------------------------------------------------- re-analysis
def _archive(real_run, tmp_path) -> list[Path]:
    """Four archived runs: two good copies, one judged by a (simulated) faulty older
    analysis, one damaged."""
    src, _ = real_run
    dirs = []
    for name in ("good-1", "good-2", "old-verdict", "damaged"):
        d = tmp_path / name
        shutil.copytree(src, d, ignore=shutil.ignore_patterns("reanalysis-*"))
        dirs.append(d)
    old = json.loads((dirs[2] / "result.json").read_text())
    old["motors"]["in"]["Kt"] *= 1.3                     # what the old analysis said
    old["limits"][0].update(value=1.3, passed=False)
    old.update(status="failed", passed=False, exit_code=1, serial="OLD-7")
    (dirs[2] / "result.json").write_text(json.dumps(old))
    (dirs[3] / "trace-calibrate-out-disk_a.parquet").write_bytes(b"PAR1 truncated")
    return dirs


def test_reanalyze_on_a_local_dask_cluster(real_run, tmp_path, cli):
    dirs = _archive(real_run, tmp_path)
    args = [*dirs[:2], dirs[2].as_uri(), dirs[3], "--workers", "2"]
    p = cli("reanalyze", *args)
    assert p.returncode == 1, p.stderr                   # one run failed ...
    assert "3 of 4 runs re-analysed, 1 verdict(s) would change, 1 failed" in p.stdout
    assert "CHANGED OLD-7" in p.stdout and "failed -> passed" in p.stdout and "kt_in FAIL->PASS" in p.stdout
    assert "FAILED" in p.stdout and "damaged" in p.stdout and "Parquet" in p.stdout
    assert "4/4 runs" in p.stderr                         # progress
    written = sorted(dirs[0].glob("reanalysis-*-default.json"))
    assert len(written) == 1
    new, orig = json.loads(written[0].read_text()), json.loads((dirs[0] / "result.json").read_text())
    assert new["analysis"]["method"] == "default" and new["analysis"]["of_run_id"] == orig["run_id"]
    for m in ("in", "out"):                               # same code, same traces: same numbers
        assert new["motors"][m]["Kt"] == pytest.approx(orig["motors"][m]["Kt"], rel=1e-9)
    mtime = written[0].stat().st_mtime_ns
    p = cli("reanalyze", dirs[0], "--scheduler", "serial", "--quiet")
    assert p.returncode == 0 and written[0].stat().st_mtime_ns == mtime   # never overwritten
    assert json.loads((dirs[2] / "result.json").read_text())["status"] == "failed"   # original kept


def test_reanalyze_on_separate_dask_scheduler_and_worker_processes(pg, real_run, tmp_path, cli):
    _, res = real_run
    port = free_port()
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    procs = [subprocess.Popen([sys.executable, "-m", "dask", "scheduler", "--host", "127.0.0.1",
                               "--port", str(port), "--no-dashboard"], cwd=REPO, env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        procs.append(subprocess.Popen([sys.executable, "-m", "dask", "worker", f"tcp://127.0.0.1:{port}",
                                       "--nworkers", "1", "--nthreads", "1", "--no-dashboard"],
                                      cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        # no RUN_DIR: the runs come from the central database (their archived trace location)
        p = cli("reanalyze", "--central", pg.url, "--serial", "GOLD-1", "--verdict", "passed", "--method", "paper",
                      "--scheduler", f"tcp://127.0.0.1:{port}")
        assert p.returncode == 0, p.stdout + p.stderr
        assert "1 of 1 runs re-analysed" in p.stdout and "1 re-analyses stored" in p.stderr
        with psycopg.connect(pg.url) as c:
            row = c.execute("SELECT method, status, result->'motors'->'in'->>'method' FROM analyses "
                            "WHERE run_id = %s", (res["run_id"],)).fetchone()
        assert row == ("paper", "passed", "paper")
    finally:
        for pr in reversed(procs):
            pr.terminate()
        for pr in procs:
            try:
                pr.wait(10)
            except subprocess.TimeoutExpired:
                pr.kill()


# --------------------------------------------------------------------- SPC
def test_spc_flags_a_drifting_station_motor_on_both_databases(pg, template, tmp_path, monkeypatch, cli):
    import numpy as np

    res = template
    dbs = {}
    for station, drift_from in (("st-ok", None), ("st-drift", 35)):
        monkeypatch.setenv("GEARBENCH_STATION", station)
        db = dbs[station] = tmp_path / station / "station.sqlite"
        rng = np.random.default_rng(11)
        for k in range(60):
            r = synthetic(res, f"{station}-{k}", f"U{k:03d}", f"2026-11-{1 + k // 24:02d}T{k % 24:02d}:00:00.000+00:00")
            for m in ("in", "out"):
                r["motors"][m]["Kt"] *= 1 + 0.0008 * rng.standard_normal()
            if drift_from is not None and k >= drift_from:
                r["motors"]["in"]["Kt"] *= 1 - 0.0004 * (k - drift_from + 1)   # magnets weakening
            store_run(db, r)
        assert push_pending(db, pg.url).ok
    png = tmp_path / "spc.png"
    p = cli("spc", "--central", pg.url, "--station", "st-drift", "--quantity", "motors.*.Kt",
            "--png", png, "--json")
    assert p.returncode == 1, p.stderr                       # something is flagged
    charts = {c["quantity"]: c for c in json.loads(p.stdout)}
    kt_in = charts["motors.in.Kt"]
    assert kt_in["n"] == 60 and kt_in["flags"]
    first = min(f["index"] for f in kt_in["flags"])
    assert 35 <= first <= 45 and all(f["index"] >= 35 for f in kt_in["flags"])
    assert kt_in["flags"][0]["run_id"].startswith("st-drift-")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000
    # the same charts from the station's own database
    p2 = cli("spc", "--db", dbs["st-drift"], "--quantity", "motors.*.Kt", "--png", tmp_path / "l.png", "--json")
    local = {c["quantity"]: c for c in json.loads(p2.stdout)}
    for c in (charts, local):
        for v in c.values():
            v.pop("png")
    assert local == charts
    # every station apart, one image each
    p = cli("spc", "--central", pg.url, "--quantity", "motors.in.Kt", "--png", tmp_path / "all.png")
    assert (tmp_path / "all-st-drift.png").exists() and (tmp_path / "all-st-ok.png").exists()
    assert "st-drift" in p.stdout and "FLAGGED" in p.stdout
