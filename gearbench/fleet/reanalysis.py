"""Re-analysis of archived runs: the same analysis code the sequencer ran, on the
run's recorded traces, with today's analysis version or another method.

``reanalyse_run`` does one run folder (local path or any fsspec URL) and writes
``reanalysis-<version>-<method>.json`` beside ``result.json``, never replacing a
file (the same version and method give the same answer, so an existing file is
reused). ``reanalyse_many`` farms runs out to a Dask cluster, one task per run; a
run whose analysis fails is reported and the others go on.
"""
from __future__ import annotations

import hashlib
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable, Iterable

from ..errors import GearbenchError
from ..station.records import Subscriber
from .. import __version__
from ..profile import load_profile
from ..station.plan import CalibrationAnalysis, EfficiencyAnalysis, Segment
from ..station.sequencer import Sequencer
from ..trace import Trace
from ..station.recorder import _safe
from ..station.results import _clean
from .migrations import require_current
from .push import connect
from ..station.config import target_name

_VERSION: str | None = None


class ArchiveError(GearbenchError):
    """The archived run cannot be read (missing or damaged file): no verdict at all."""


def analysis_version() -> str:
    """The package version plus a hash of the analysis source: a new number whenever
    the code that turns traces into results changes."""
    global _VERSION
    if _VERSION is None:

        here = Path(__file__).resolve().parent.parent      # gearbench/
        h = hashlib.sha256()
        for p in sorted([*(here / "analysis").rglob("*.py"), here / "station" / "analyse.py"]):
            h.update(p.relative_to(here).as_posix().encode())
            h.update(p.read_bytes())
        _VERSION = f"{__version__}+{h.hexdigest()[:10]}"
    return _VERSION


def output_name(method: str) -> str:
    return f"reanalysis-{analysis_version()}-{method}.json"


# ----------------------------------------------------------------- one run
def _fs(run_dir: str):
    import fsspec

    fs, root = fsspec.core.url_to_fs(str(run_dir))
    return fs, root.rstrip("/")


def _load_profile(fs, root: str, result: dict, run_dir: str, profile: str | None):
    """The profile the run used: ``--profile``, else the run folder's snapshot
    (``profile.yaml``), else the recorded path; refused if its sha256 differs."""
    want = result.get("profile_sha256")
    if profile:
        cands = [profile]
    else:
        cands = []
        if fs.exists(f"{root}/profile.yaml"):
            snap = Path(tempfile.mkdtemp(prefix="gearbench-profile-")) / "profile.yaml"
            snap.write_bytes(fs.cat_file(f"{root}/profile.yaml"))
            cands.append(str(snap))
        cands.append(str(result.get("profile_path", "")))
    for c in cands:
        if c and Path(c).is_file():
            try:
                prof = load_profile(c)
            finally:
                if c != profile and Path(c).name == "profile.yaml" and "gearbench-profile-" in c:
                    shutil.rmtree(Path(c).parent, ignore_errors=True)
            if want and prof.sha256 != want:
                raise GearbenchError(f"{run_dir}: profile {c} has changed since the run "
                                     f"(sha256 {prof.sha256[:12]}, the run used {want[:12]}); pass "
                                     f"--profile with the version that ran")
            return prof
    raise GearbenchError(f"{run_dir}: profile '{result.get('profile_path')}' not found here; "
                         f"pass --profile PATH (the version that ran, sha256 {str(want)[:12]})")


class ProfileSnapshot(Subscriber):
    """Copies the profile into the run folder at RunStart (``profile.yaml``), so the run
    can be re-analysed after the profile file has moved on."""

    def on_run_start(self, rec) -> None:
        src = Path(rec.profile_path)
        if src.is_file() and rec.out_dir:
            data = src.read_bytes()
            if hashlib.sha256(data).hexdigest() == rec.profile_sha256:
                (Path(rec.out_dir) / "profile.yaml").write_bytes(data)


def reanalyse_result(result: dict, traces: Callable[[str], "object"], profile, method: str) -> dict:
    """The result a run would have had with this analysis and ``method``; ``traces(step)``
    gives a recorded step as a Trace. No file I/O here."""
    # records go nowhere: the archive is read, not re-recorded
    seq = Sequencer(profile, None, emit=lambda rec: None, operator=None, serial=result.get("serial", ""),
                    out_dir=result.get("out_dir", ""), method=method)
    status, exit_code, reason, limits = "passed", 0, "", []
    seq.load_recorded(result.get("measurements"))   # what an adaptive run decided while acquiring
    try:
        for step in seq.step_groups():
            for action in seq.plan_step(step):
                if isinstance(action, Segment):
                    tr = traces(action.name)
                    seq.traces[action.name] = Trace(tr.time_s, dict(tr.columns),
                                                    {"step": action.name, **action.meta}, action.name)
                elif isinstance(action, (CalibrationAnalysis, EfficiencyAnalysis)):
                    seq.analyse(action)
        limits = seq.check_limits()
        if not all(lim["passed"] for lim in limits):
            status, exit_code = "failed", 1
            reason = ", ".join(lim["name"] for lim in limits if not lim["passed"])
    except ArchiveError:
        raise
    except GearbenchError as exc:     # the analysis refuses the data, as it would have on the bench
        status, exit_code, reason = "fault", 3, str(exc)
    new = dict(result)
    new.update(status=status, passed=status == "passed", exit_code=exit_code, reason=reason,
               method=method, motors=seq.motors_result, ratio=seq.ratio,
               efficiency=seq.efficiency, limits=limits)
    return new


def _changed_limits(old: dict, new: dict) -> list[str]:
    olds = old.get("limits") or []
    before = {lim["name"]: lim.get("passed") for lim in olds}
    out = []
    for k, lim in enumerate(new.get("limits") or []):
        was = before.get(lim["name"])
        if was is None and k < len(olds) and olds[k].get("quantity") == lim.get("quantity"):
            # an older run named its points by the measured torque (0.0601Nm): same place, same limit
            was = olds[k].get("passed")
        if was != lim["passed"]:
            out.append(f"{lim['name']} {'PASS' if was else 'FAIL'}->{'PASS' if lim['passed'] else 'FAIL'}")
    return out


def reanalyse_run(run_dir: str, method: str = "default", profile: str | None = None) -> dict:
    """Re-analyse one archived run folder; returns a summary (never raises for a bad run:
    ``error`` says what went wrong)."""
    t0, cpu0 = time.monotonic(), time.process_time()
    summary = dict(run_dir=str(run_dir), run_id=None, serial=None, old_status=None, new_status=None,
                   changed=False, limits_changed=[], output=None, reused=False, error=None,
                   analysis_version=analysis_version(), method=method)
    try:
        fs, root = _fs(run_dir)
        try:
            with fs.open(f"{root}/result.json", "r") as f:
                old = json.load(f)
        except FileNotFoundError:
            raise GearbenchError(f"{run_dir}: no result.json; is this a gearbench run folder?") from None
        except json.JSONDecodeError as exc:
            raise GearbenchError(f"{run_dir}/result.json: not valid JSON (line {exc.lineno}); "
                                 f"the run folder is damaged") from None
        summary.update(run_id=old.get("run_id"), serial=old.get("serial"), old_status=old.get("status"))
        out_path = f"{root}/{output_name(method)}"
        if fs.exists(out_path):
            with fs.open(out_path, "r") as f:
                new = json.load(f)
            summary["reused"] = True
        else:
            new = _reanalyse_files(fs, root, str(run_dir), old, method, profile)
            _write_new(fs, out_path, new)
        summary.update(new_status=new["status"], changed=new["status"] != old.get("status"),
                       limits_changed=_changed_limits(old, new), output=out_path,
                       motors={m: p.get("Kt") for m, p in (new.get("motors") or {}).items()},
                       old_motors={m: p.get("Kt") for m, p in (old.get("motors") or {}).items()},
                       reason=new.get("reason", ""), result=new)
    except GearbenchError as exc:
        summary["error"] = str(exc)
    except Exception as exc:   # a damaged archive must not stop the other runs
        summary["error"] = f"{run_dir}: {type(exc).__name__}: {exc}"
    summary.update(wall_s=time.monotonic() - t0, cpu_s=time.process_time() - cpu0)
    return summary


def _reanalyse_files(fs, root: str, run_dir: str, old: dict, method: str, profile: str | None) -> dict:

    prof = _load_profile(fs, root, old, run_dir, profile)
    local = getattr(fs, "protocol", None) in ("file", ("file", "local"), ("file", "local", "local"))
    tmp = None if local else tempfile.TemporaryDirectory(prefix="gearbench-reanalyse-")
    try:
        def traces(step: str):
            name = f"trace-{_safe(step)}.parquet"
            src = f"{root}/{name}"
            if not fs.exists(src):
                raise ArchiveError(f"{run_dir}: trace {name} missing (the run recorded "
                                   f"{', '.join(old.get('steps') or {}) or 'no steps'})")
            dst = src
            if not local:
                dst = Path(tmp.name) / name
                fs.get(src, str(dst))
            try:
                return Trace.read_parquet(dst)
            except GearbenchError as exc:
                raise ArchiveError(f"{run_dir}: {exc}") from None

        new = reanalyse_result(old, traces, prof, method)
    finally:
        if tmp is not None:
            tmp.cleanup()
    from datetime import datetime, timezone

    new["analysis"] = dict(version=analysis_version(), method=method, of_run_id=old.get("run_id"),
                           original_status=old.get("status"), original_method=old.get("method"),
                           created_utc=datetime.now(timezone.utc).isoformat(timespec="milliseconds"))
    return new


def _write_new(fs, path: str, result: dict) -> None:

    text = json.dumps(_clean(result), indent=2, allow_nan=False) + "\n"
    tmp = f"{path}.tmp"
    with fs.open(tmp, "w") as f:
        f.write(text)
    fs.mv(tmp, path)     # a reader never sees half a file


# ------------------------------------------------------------------ many runs
class _Bar:
    def __init__(self, total: int, stream=None, enabled: bool = True):
        stream = stream or sys.stderr
        self.total, self.done, self.failed, self.stream, self.enabled = total, 0, 0, stream, enabled
        self.t0 = time.monotonic()
        self.tty = getattr(stream, "isatty", lambda: False)()
        self._last = -1

    def step(self, failed: bool) -> None:
        self.done += 1
        self.failed += failed
        if not self.enabled:
            return
        pct = int(100 * self.done / max(self.total, 1))
        if not self.tty and pct // 10 == self._last // 10 and self.done != self.total:
            return
        self._last = pct
        el = time.monotonic() - self.t0
        eta = el * (self.total - self.done) / self.done if self.done else 0
        bar = "#" * (pct // 5) + "." * (20 - pct // 5)
        line = (f"reanalyze [{bar}] {self.done}/{self.total} runs, {self.failed} failed, "
                f"{self.done / max(el, 1e-9):.2f} runs/s, ETA {eta:.0f} s")
        print(("\r" + line) if self.tty else line, end="" if self.tty else "\n", file=self.stream, flush=True)

    def close(self) -> None:
        if self.enabled and self.tty:
            print(file=self.stream)


def open_client(scheduler: str = "local", workers: int | None = None):
    """A dask.distributed Client: a LocalCluster of worker processes, or a running
    scheduler at ``tcp://HOST:PORT``. Returns (client, cluster or None)."""
    import logging

    from dask.distributed import Client, LocalCluster

    if scheduler in (None, "", "local"):
        cluster = LocalCluster(n_workers=workers or 2, threads_per_worker=1, processes=True,
                               dashboard_address=None, silence_logs=logging.ERROR)
        return Client(cluster), cluster
    if not scheduler.startswith(("tcp://", "tls://", "ws://", "wss://")):
        raise GearbenchError(f"--scheduler '{scheduler}': use local, serial, or tcp://HOST:PORT")
    try:
        return Client(scheduler, timeout="15s"), None
    except (OSError, TimeoutError) as exc:
        raise GearbenchError(f"Dask scheduler {scheduler} unreachable ({exc}); start one with "
                             f"'dask scheduler' or use --scheduler local") from None


def reanalyse_many(run_dirs: Iterable[str], *, method: str = "default", profile: str | None = None,
                   scheduler: str = "local", workers: int | None = None, progress: bool = True,
                   stream=None, client=None) -> list[dict]:
    """One task per run on Dask (``scheduler='serial'``: in this process, no Dask).
    Summaries in the order of ``run_dirs``."""
    dirs = [str(d) for d in run_dirs]
    bar = _Bar(len(dirs), stream, progress)
    out: dict[int, dict] = {}
    if scheduler == "serial":
        for i, d in enumerate(dirs):
            out[i] = reanalyse_run(d, method, profile)
            bar.step(bool(out[i]["error"]))
        bar.close()
        return [out[i] for i in range(len(dirs))]
    from dask.distributed import as_completed

    own = client is None
    cluster = None
    if own:
        client, cluster = open_client(scheduler, workers)
    try:
        futures = client.map(reanalyse_run, dirs, method=method, profile=profile, pure=False)
        index = {f.key: i for i, f in enumerate(futures)}
        for fut in as_completed(futures):
            i = index[fut.key]
            try:
                out[i] = fut.result()
            except Exception as exc:    # a worker died under this task: report it, go on
                out[i] = dict(run_dir=dirs[i], error=f"{dirs[i]}: task failed on the cluster "
                              f"({type(exc).__name__}: {exc})", changed=False, run_id=None,
                              serial=None, old_status=None, new_status=None, limits_changed=[])
            bar.step(bool(out[i]["error"]))
    finally:
        bar.close()
        if own:
            client.close()
            if cluster is not None:
                cluster.close()
    return [out[i] for i in range(len(dirs))]


def store_analyses(url: str, summaries: list[dict]) -> tuple[int, int]:
    """Record re-analyses in the central database (analyses table); returns
    (stored, runs not in the central database)."""
    stored = missing = 0
    with connect(url) as conn:
        require_current(conn, target_name(url))
        with conn.transaction(), conn.cursor() as cur:
            for s in summaries:
                if s.get("error") or not s.get("result"):
                    continue
                cur.execute(
                    "INSERT INTO analyses (run_id, analysis_version, method, status, passed, result) "
                    "SELECT %s, %s, %s, %s, %s, %s WHERE EXISTS (SELECT 1 FROM runs WHERE run_id = %s) "
                    "ON CONFLICT DO NOTHING RETURNING run_id",
                    (s["run_id"], s["analysis_version"], s["method"], s["new_status"],
                     s["new_status"] == "passed", json.dumps(_clean(s["result"])), s["run_id"]))
                if cur.fetchone() is not None:
                    stored += 1
                elif not conn.execute("SELECT 1 FROM runs WHERE run_id = %s", (s["run_id"],)).fetchone():
                    missing += 1
    return stored, missing
