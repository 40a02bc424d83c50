"""gearbench reanalyze RUN_DIR...: re-run the analysis on archived runs, on a Dask cluster."""
from __future__ import annotations

import json
import sys

NAME = "reanalyze"
HELP = ("Re-run the analysis on archived runs' traces (one Dask task per run); write the results "
        "beside the originals and print whose verdict would change.")


def add_arguments(p) -> None:
    p.add_argument("run_dirs", nargs="*", metavar="RUN_DIR",
                   help="run folders (local paths or fsspec URLs, e.g. s3://bucket/run); "
                        "none with --central: the central database's runs matching the filters")
    p.add_argument("--method", choices=["default", "paper"], default="default",
                   help="identification method: default (bias-reduced), paper (as published, at the data rate)")
    p.add_argument("--scheduler", default="local",
                   help="local (a LocalCluster of worker processes, default), tcp://HOST:PORT "
                        "(a running dask scheduler), or serial (this process, no Dask)")
    p.add_argument("--workers", type=int, default=None, help="local cluster: worker processes (default 2)")
    p.add_argument("--profile", help="the profile the runs used, if not at their recorded path")
    p.add_argument("--central", metavar="URL",
                   help="record the re-analyses in this central database (and take the runs from it "
                        "when no RUN_DIR is given)")
    for f in ("serial", "station", "since", "until", "verdict"):
        p.add_argument(f"--{f}", dest=f"q_{f}", help=f"with --central and no RUN_DIR: only runs of this {f}")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--json", action="store_true", help="print the summaries as JSON")


def _from_central(args) -> list[str]:
    from ..fleet.query import RunQuery, open_results

    with open_results(args.central) as db:
        runs = db.runs(RunQuery(serial=args.q_serial, station=args.q_station, since=args.q_since,
                                until=args.q_until, verdict=args.q_verdict,
                                newest_first=False))
    return [r["trace_uri"] for r in runs if r["trace_uri"]]


def run(args) -> int:
    from ..errors import GearbenchError
    from ..fleet.reanalysis import analysis_version, reanalyse_many, store_analyses

    dirs = list(args.run_dirs)
    if not dirs:
        if not args.central:
            raise GearbenchError("give run folders (RUN_DIR...), or --central URL to take them "
                                 "from the central database")
        dirs = _from_central(args)
        if not dirs:
            print("no runs match in the central database")
            return 0
    out = reanalyse_many(dirs, method=args.method, profile=args.profile, scheduler=args.scheduler,
                         workers=args.workers, progress=not args.quiet)
    failed = [s for s in out if s.get("error")]
    changed = [s for s in out if s.get("changed")]
    if args.central:
        stored, missing = store_analyses(args.central, out)
        print(f"central: {stored} re-analyses stored"
              + (f", {missing} run(s) not in the central database (sync them first)" if missing else ""),
              file=sys.stderr)
    if args.json:
        print(json.dumps([{k: v for k, v in s.items() if k != "result"} for s in out], default=str))
    else:
        print(f"analysis {analysis_version()} method {args.method}: {len(out) - len(failed)} of "
              f"{len(out)} runs re-analysed, {len(changed)} verdict(s) would change, {len(failed)} failed")
        for s in changed:
            print(f"  CHANGED {s['serial']:<14}{s['old_status']:>8} -> {s['new_status']:<8} run {s['run_id']}  "
                  f"{'; '.join(s['limits_changed']) or s.get('reason', '')}")
        for s in failed:
            print(f"  FAILED  {s['error']}")
        if out and not args.quiet:
            written = sum(1 for s in out if s.get("output") and not s.get("reused"))
            print(f"  {written} result file(s) written beside the originals, "
                  f"{sum(1 for s in out if s.get('reused'))} already there (same version and method)")
    return 1 if failed else 0
