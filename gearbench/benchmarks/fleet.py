"""A factory of testers, measured: ingest into PostgreSQL and re-analysis on Dask.

    python -m gearbench.benchmarks fleet [--stations 8] [--runs 150] [--outage-s 3]
                                    [--real-runs 2] [--archive 24] [--profile profiles/motors-only.yaml]

(a) ingest: a throwaway PostgreSQL; ``--stations`` processes, each a station with its
    own SQLite outbox, store and push runs as fast as they can (a new connection per
    push, as each ``gearbench run`` does); the server is stopped for ``--outage-s``
    in the middle; then every station syncs. Prints runs/s, push latency (p50/p99,
    from the run's end to its central commit), and lost / duplicated runs counted
    against what the stations made.
(b) re-analysis: ``--real-runs`` real runs on the simulated bench, copied to an
    archive of ``--archive`` run folders; runs/s serial (one process, no Dask) and
    on a Dask LocalCluster with 1 and 2 worker processes; CPU seconds per run, and
    what that means for 100 testers x 1,000 units/day x 1 year.
"""
from __future__ import annotations

import argparse
import copy
import json
import multiprocessing as mp
import os
import shutil
import tempfile
import time
import uuid
from pathlib import Path

import numpy as np

PLANT_RUNS_PER_YEAR = 100 * 1000 * 365


def _station(args) -> dict:
    """One station process: store + push ``n`` runs; latencies of online pushes."""
    name, db, url, template, n, ready, made_total = args
    os.environ["GEARBENCH_STATION"] = name
    from gearbench.fleet.push import push_pending
    from gearbench.station.database import store_run

    made, lat, offline = [], [], 0
    ready.wait()
    for k in range(n):
        r = copy.deepcopy(template)
        r.update(run_id=uuid.uuid4().hex, serial=f"{name}-U{k:05d}",
                 started_utc=time.strftime("%Y-%m-%dT%H:%M:%S.000+00:00", time.gmtime()))
        t0 = time.perf_counter()
        store_run(db, r)
        made.append(r["run_id"])
        made_total.put(1)
        rep = push_pending(db, url, timeout_s=1)
        if rep.error or rep.pending:
            offline += 1
            time.sleep(0.05)            # a tester does not make runs faster when offline
        else:
            lat.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    while True:                         # after the outage: gearbench sync until empty
        rep = push_pending(db, url)
        if not rep.pending and not rep.error:
            break
        time.sleep(0.2)
    return dict(name=name, made=made, latencies=lat, offline=offline, sync_s=time.perf_counter() - t0)


def ingest(template: dict, *, stations: int, runs: int, outage_s: float, tmp: Path) -> dict:
    from gearbench.fleet import migrations
    from gearbench.fleet.pgtemp import TempPostgres
    from gearbench.fleet.push import connect

    with TempPostgres(max_connections=max(100, 4 * stations)) as pg:
        with connect(pg.url) as c:
            migrations.upgrade(c)
        ctx = mp.get_context("spawn")
        with ctx.Manager() as mgr:
            ready, made_total = mgr.Event(), mgr.Queue()
            jobs = [(f"st-{i:02d}", tmp / f"st-{i:02d}" / "station.sqlite", pg.url, template, runs, ready,
                     made_total) for i in range(stations)]
            with ctx.Pool(stations) as pool:
                res = pool.map_async(_station, jobs)
                time.sleep(3.0)             # interpreters up
                t0 = time.perf_counter()
                ready.set()
                if outage_s > 0:
                    for _ in range(stations * runs // 3):   # the outage starts a third of the way in
                        made_total.get()
                    pg.stop()
                    t_out = time.perf_counter()
                    time.sleep(outage_s)
                    pg.start()
                    outage = time.perf_counter() - t_out
                else:
                    outage = 0.0
                out = res.get()
                wall = time.perf_counter() - t0
        with connect(pg.url) as c:
            central = {r for (r,) in c.execute("SELECT run_id FROM runs")}
            n_rows = c.execute("SELECT count(*) FROM runs").fetchone()[0]
            n_lim = c.execute("SELECT count(*) FROM limits").fetchone()[0]
            n_cal = c.execute("SELECT count(*) FROM motor_calibrations").fetchone()[0]
    made = [r for o in out for r in o["made"]]
    lat = np.array([x for o in out for x in o["latencies"]])
    dup = (n_rows - len(central)) + (n_lim - len(made) * len(template.get("limits") or [])) \
        + (n_cal - len(made) * len(template.get("motors") or {}))
    return dict(stations=stations, runs=len(made), wall_s=wall, runs_per_s=len(made) / wall,
                p50_ms=1e3 * float(np.percentile(lat, 50)), p99_ms=1e3 * float(np.percentile(lat, 99)),
                online=len(lat), offline=sum(o["offline"] for o in out), outage_s=outage,
                lost=len(set(made) - central), duplicated=dup, unknown=len(central - set(made)))


def _real_runs(profile: str, n: int, tmp: Path) -> list[Path]:
    from gearbench.api import run_profile

    dirs = []
    for k in range(n):
        for attempt in range(3):         # the emulated bench on a loaded host can stall
            out = tmp / f"real-{k}-{attempt}"
            res = run_profile(profile, sim=True, out_dir=out, serial=f"REAL-{k}", yes=True, seed=k,
                              quiet=True)   # the run folder gets profile.yaml itself
            if res["status"] == "passed":
                dirs.append(out)
                break
    if not dirs:
        raise SystemExit("fleet: the simulated bench did not complete a run; is the host overloaded?")
    return dirs


def _archive(real: list[Path], n: int, tmp: Path) -> list[Path]:
    dirs = []
    for i in range(n):
        d = tmp / "archive" / f"run-{i:04d}"
        shutil.copytree(real[i % len(real)], d)
        res = json.loads((d / "result.json").read_text())
        res["run_id"] = uuid.uuid4().hex
        (d / "result.json").write_text(json.dumps(res))
        dirs.append(d)
    return dirs


def _clear(dirs) -> None:
    for d in dirs:
        for f in Path(d).glob("reanalysis-*.json"):
            f.unlink()


def reanalysis(dirs: list[Path]) -> list[dict]:
    from gearbench.fleet.reanalysis import open_client, reanalyse_many, reanalyse_run

    rows = []
    reanalyse_run(str(dirs[0]))          # imports and caches warm in this process
    _clear(dirs)
    t0, c0 = time.perf_counter(), time.process_time()
    out = reanalyse_many(dirs, scheduler="serial", progress=False)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    assert not any(s["error"] for s in out), [s["error"] for s in out if s["error"]]
    rows.append(dict(how="serial (1 process)", workers=1, wall_s=wall, runs_per_s=len(dirs) / wall,
                     cpu_per_run_s=cpu / len(dirs), startup_s=0.0))
    for workers in (1, 2):
        _clear(dirs)
        t0 = time.perf_counter()
        client, cluster = open_client("local", workers)
        try:
            client.run(lambda: __import__("gearbench.fleet.reanalysis").reanalysis.analysis_version())
            # warm every worker (imports, caches) on one run each, then time the archive
            warm = reanalyse_many(dirs[:workers], client=client, progress=False)
            assert not any(s["error"] for s in warm)
            startup = time.perf_counter() - t0
            _clear(dirs)
            t1 = time.perf_counter()
            out = reanalyse_many(dirs, client=client, progress=False)
            wall = time.perf_counter() - t1
        finally:
            client.close()
            cluster.close()
        assert not any(s["error"] for s in out), [s["error"] for s in out if s["error"]]
        cpu = sum(s["cpu_s"] for s in out) / len(out)
        rows.append(dict(how="Dask LocalCluster", workers=workers, wall_s=wall, runs_per_s=len(dirs) / wall,
                         cpu_per_run_s=cpu, startup_s=startup))
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m gearbench.benchmarks fleet", description=__doc__.splitlines()[0])
    ap.add_argument("--stations", type=int, default=8)
    ap.add_argument("--runs", type=int, default=150, help="runs per station (ingest)")
    ap.add_argument("--outage-s", type=float, default=3.0, help="PostgreSQL stopped this long mid-ingest")
    ap.add_argument("--profile", default="profiles/motors-only.yaml")
    ap.add_argument("--real-runs", type=int, default=2)
    ap.add_argument("--archive", type=int, default=24, help="archived runs to re-analyse")
    ap.add_argument("--skip", choices=["ingest", "reanalysis"], action="append", default=[])
    ap.add_argument("--template", help="with --skip reanalysis: ingest copies of this result.json "
                                       "instead of making real runs first")
    args = ap.parse_args(argv)
    print(f"host: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f} (shared: figures are lower bounds)")
    with tempfile.TemporaryDirectory(prefix="gearbench-fleet-") as t:
        tmp = Path(t)
        t0 = time.perf_counter()
        if args.template and "reanalysis" in args.skip:
            template = json.loads(Path(args.template).read_text())
            print(f"ingest template: {args.template} (a recorded real run)")
        else:
            real = _real_runs(args.profile, args.real_runs, tmp)
            template = json.loads((real[0] / "result.json").read_text())
            print(f"real runs on the simulated bench: {len(real)} of {args.profile} "
                  f"({time.perf_counter() - t0:.0f} s)")
        if "ingest" not in args.skip:
            r = ingest(template, stations=args.stations, runs=args.runs, outage_s=args.outage_s, tmp=tmp)
            print(f"\n(a) ingest: {r['stations']} station processes, {r['runs']} runs, PostgreSQL stopped "
                  f"{r['outage_s']:.1f} s mid-way")
            print(f"    {r['runs_per_s']:.1f} runs/s over {r['wall_s']:.1f} s (store in the station SQLite + "
                  f"push, a new connection per push)")
            print(f"    latency run end -> central commit (online pushes, n={r['online']}): "
                  f"p50 {r['p50_ms']:.1f} ms, p99 {r['p99_ms']:.1f} ms; {r['offline']} runs made during the "
                  f"outage, pushed by the next push or sync")
            print(f"    lost {r['lost']}, duplicated {r['duplicated']}, unknown {r['unknown']}")
            need = PLANT_RUNS_PER_YEAR / 365 / 86400
            print(f"    plant load 100 testers x 1,000 units/day = {need:.2f} runs/s on average: "
                  f"{r['runs_per_s'] / need:.0f}x headroom on this 2-CPU host")
        if "reanalysis" not in args.skip:
            dirs = _archive(real, args.archive, tmp)
            rows = reanalysis(dirs)
            print(f"\n(b) re-analysis of {len(dirs)} archived {Path(args.profile).stem} runs "
                  f"(Parquet traces, calibration fits, limits)")
            print(f"    {'how':<22}{'workers':>8}{'runs/s':>9}{'wall s':>9}{'CPU s/run':>11}{'start-up s':>12}")
            for r in rows:
                print(f"    {r['how']:<22}{r['workers']:>8}{r['runs_per_s']:>9.2f}{r['wall_s']:>9.1f}"
                      f"{r['cpu_per_run_s']:>11.3f}{r['startup_s']:>12.1f}")
            cost = min(r["cpu_per_run_s"] for r in rows)
            year_cpu_h = PLANT_RUNS_PER_YEAR * cost / 3600
            print(f"    per-run cost {cost:.3f} CPU s -> a plant year (100 x 1,000 x 365 = "
                  f"{PLANT_RUNS_PER_YEAR / 1e6:.1f} M runs) is {year_cpu_h:,.0f} CPU h:")
            for hours in (24, 8):
                print(f"      re-score a year within {hours} h: {year_cpu_h / hours:,.0f} worker processes "
                      f"(one CPU each)")
            print(f"      keep up live (100,000 runs/day): {100_000 * cost / 86400:.2f} worker CPUs")
    return 0
