"""Recorder (crash-safe traces), result.json/JUnit and the station database."""
import json
import subprocess
import sys
import xml.etree.ElementTree as ET

import numpy as np

from gearbench.station.recorder import ParquetRecorder, load_step_trace
from gearbench.station.records import RunStop, SampleBatch, StepStart, StepStop
from gearbench.station.results import ResultWriter
from gearbench.station.database import StationDatabase, history


def _batches(rec, step, n_batches, size=100):
    for b in range(n_batches):
        idx = np.arange(b * size, (b + 1) * size)
        rec(SampleBatch(step, idx, idx * 1e-3, {"in.current_a": idx * 0.5}))


def test_recorder_writes_parquet_per_step(tmp_path):
    r = ParquetRecorder(tmp_path)
    r(StepStart("cal-in", "calibrate"))
    _batches(r, "cal-in", 3)
    r(StepStop("cal-in", "ok", 300))
    tr = load_step_trace(tmp_path / "trace-cal-in.parquet")
    assert len(tr) == 300
    np.testing.assert_array_equal(tr["sample"], np.arange(300))
    assert not (tmp_path / "trace-cal-in.arrows").exists()


def test_recorder_survives_kill_9(tmp_path):
    """A writer process killed hard keeps every flushed batch readable."""
    code = f"""
import os, signal, numpy as np
from gearbench.station.recorder import ParquetRecorder
from gearbench.station.records import SampleBatch, StepStart
r = ParquetRecorder({str(tmp_path)!r})
r(StepStart("eff", "efficiency"))
for b in range(7):
    idx = np.arange(b * 100, (b + 1) * 100)
    r(SampleBatch("eff", idx, idx * 1e-3, {{"in.current_a": idx * 1.0}}))
os.kill(os.getpid(), signal.SIGKILL)
"""
    p = subprocess.run([sys.executable, "-c", code])
    assert p.returncode == -9
    tr = load_step_trace(tmp_path / "trace-eff.arrows")
    assert len(tr) == 700
    np.testing.assert_array_equal(tr["in.current_a"], np.arange(700.0))


def _result(passed=True):
    return {"serial": "SN1", "run_id": "r1", "profile": "cvt", "profile_sha256": "ab",
            "started_utc": "2026-11-22T00:00:00Z", "status": "passed" if passed else "failed",
            "passed": passed, "exit_code": 0 if passed else 1, "ratio": 7.0,
            "motors": {"in": {"Kt": 0.05, "J": 1e-5, "D": 1e-6, "Tc": 0.01}},
            "efficiency": [{"speed_in_rad_s": 100.0, "torque_out_nm": 0.2,
                            "eta_incremental": 0.88, "eta_absolute": float("nan")}],
            "limits": [{"name": "Kt_in", "value": 0.05, "low": 0.04, "high": 0.06, "passed": True},
                       {"name": "eta", "value": 0.88, "low": 0.9, "high": 1.0, "passed": passed}]}


def test_result_json_and_junit(tmp_path):
    w = ResultWriter(tmp_path)
    w(RunStop("failed", 1, "eta", _result(passed=False)))
    res = json.loads((tmp_path / "result.json").read_text())
    assert res["efficiency"][0]["eta_absolute"] is None  # NaN -> null, strict JSON
    suite = ET.parse(tmp_path / "junit.xml").getroot()
    assert suite.get("tests") == "2" and suite.get("failures") == "1"
    failed = [c.get("name") for c in suite.iter("testcase") if c.find("failure") is not None]
    assert failed == ["eta"]


def test_station_database_history_by_serial(tmp_path):
    db = StationDatabase(tmp_path / "st.sqlite")
    db(RunStop("passed", 0, "", _result()))
    r2 = dict(_result(False), run_id="r2", started_utc="2026-11-23T00:00:00Z")
    db(RunStop("failed", 1, "", r2))
    runs = history(tmp_path / "st.sqlite", "SN1")
    assert [r["run_id"] for r in runs] == ["r2", "r1"]
    names = {m["name"] for m in runs[0]["measurements"]}
    assert "motors.in.Kt" in names and "limit.eta" in names
    assert history(tmp_path / "st.sqlite", "other") == []
