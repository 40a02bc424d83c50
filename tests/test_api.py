"""The stable Python API (gearbench.api): open_bench step by step, typed results,
run_profile (what ``gearbench run`` calls) on the same code path.

Most tests use the in-process ``loopback`` drive family of tests/plugin_example
(fast, no child process); one runs the real simulated bench (``sim=True``).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import yaml

from gearbench.api import (AutoOperator, EfficiencyPointResult, MotorResult, RunResult, open_bench,
                           run_profile)
from conftest import assert_claimed_accuracy
from gearbench.drives import registry
from gearbench.errors import Aborted, BenchFault, GearbenchError

ROOT = Path(__file__).resolve().parents[1]
PLUGIN_SRC = Path(__file__).resolve().parent / "plugin_example"


@pytest.fixture
def loopback(monkeypatch):
    monkeypatch.syspath_prepend(str(PLUGIN_SRC))
    monkeypatch.setitem(registry.BACKENDS, "loopback", "gearbench_loopback:LoopbackNetwork")
    yield


def cvt_profile(path: Path, *, kt_high: float = 1.15) -> Path:
    """cvt.yaml on the loopback family, its efficiency grid cut to 1 speed x 2 torques (the
    lightest and the heaviest: eq. 18's slope keeps the profile's lever arm)."""
    doc = yaml.safe_load((ROOT / "profiles" / "cvt.yaml").read_text())
    doc["bench"]["bus"] = {"family": "loopback", "options": {"plant": doc["simulation"], "seed": 7}}
    for m in doc["motors"].values():
        m["drive"] = str(ROOT / m["drive"])
    for s in doc["steps"]:
        if s["kind"] == "efficiency":
            s.update(speeds_in_rad_s=s["speeds_in_rad_s"][:1], torques_out_nm=s["torques_out_nm"][::3])
    doc["limits"][0]["high"] = kt_high
    path.write_text(yaml.safe_dump(doc))
    return path


def test_step_by_step_gives_typed_results(loopback, tmp_path):
    profile = cvt_profile(tmp_path / "p.yaml")
    with open_bench(profile, out_dir=tmp_path / "run", serial="API-1", operator=AutoOperator()) as bench:
        kin = bench.calibrate("in")
        kout = bench.calibrate("out")
        bench.load()
        points = bench.efficiency()
        result = bench.finish()
        assert bench.finish() is result                       # idempotent
    assert isinstance(kin, MotorResult) and kin.motor == "in"
    assert kin.kt_ci95_nm_per_a[0] < kin.kt_nm_per_a < kin.kt_ci95_nm_per_a[1]
    assert [type(p) for p in points] == [EfficiencyPointResult] * 2
    assert [p.speed_setpoint_rad_s for p in points] == [100.0, 100.0]   # cvt.yaml's first speed
    assert isinstance(result, RunResult) and result.status == "passed" and result.exit_code == 0
    assert result.ratio == pytest.approx(8.0, rel=0.02)
    assert {lim.name.split("[")[0] for lim in result.limits} == {"kt_in", "kt_out", "ratio", "efficiency"}
    on_disk = json.loads((tmp_path / "run" / "result.json").read_text())
    assert RunResult.from_dict(on_disk) == result              # typed view of result.json
    # Kt and η against the plant's own truth, at the accuracy the README claims
    # result.json rounds float noise to 12 significant digits (station.results.SIGNIFICANT_DIGITS)
    assert [p["eta_incremental"] for p in on_disk["efficiency"]] == pytest.approx([p.eta_incremental for p in points], rel=1e-11)
    assert_claimed_accuracy(on_disk, yaml.safe_load(profile.read_text())["bench"]["bus"]["options"]["plant"])


def test_limit_failure_is_reported(loopback, tmp_path):
    result = run_profile(cvt_profile(tmp_path / "p.yaml", kt_high=0.9), out_dir=tmp_path / "run",
                         serial="API-2", yes=True)
    r = RunResult.from_dict(result)
    assert (r.status, r.exit_code, r.passed) == ("failed", 1, False)
    assert [lim.name for lim in r.limits if not lim.passed] == ["kt_in"]


def test_fault_inside_the_block_ends_the_run_as_fault(loopback, tmp_path):
    with pytest.raises(BenchFault):
        with open_bench(cvt_profile(tmp_path / "p.yaml"), out_dir=tmp_path / "run", serial="API-3",
                        operator=AutoOperator()) as bench:
            bench.calibrate("in")
            raise BenchFault("door opened")
    assert bench.result.status == "fault" and bench.result.exit_code == 3
    assert "door opened" in bench.result.reason
    assert set(bench.result.motors) == {"in"}                 # what was measured is kept
    assert bench.network.world is None                        # network closed
    assert json.loads((tmp_path / "run" / "result.json").read_text())["status"] == "fault"


def test_operator_abort_stops_the_run(loopback, tmp_path):
    class Refuses:
        def confirm(self, prompt):
            raise Aborted("operator abort at prompt")   # an abort is its own type, not a message

    with open_bench(cvt_profile(tmp_path / "p.yaml"), out_dir=tmp_path / "run", serial="API-4",
                    operator=Refuses()) as bench:
        with pytest.raises(BenchFault):
            bench.calibrate("in")
        with pytest.raises(GearbenchError, match="stopped earlier"):
            bench.load()
    assert bench.result.status == "aborted" and bench.result.exit_code == 3


def test_bad_requests_name_the_fix(loopback, tmp_path):
    doc = yaml.safe_load((ROOT / "profiles" / "motors-only.yaml").read_text())
    doc.pop("simulation")
    doc["bench"]["bus"] = {"family": "loopback"}
    for m in doc["motors"].values():
        m["drive"] = str(ROOT / m["drive"])
    p = tmp_path / "nosim.yaml"
    p.write_text(yaml.safe_dump(doc))
    with pytest.raises(GearbenchError, match="simulation:"):
        with open_bench(p, sim=True, out_dir=tmp_path / "a"):
            pass
    with open_bench(p, out_dir=tmp_path / "b", operator=AutoOperator()) as bench:
        with pytest.raises(GearbenchError, match="no efficiency step"):
            bench.efficiency()
        with pytest.raises(GearbenchError, match="no calibrate step for motor 'left'"):
            bench.calibrate("left")
        assert bench.error is None                              # refused before touching the drives


def test_run_profile_on_the_simulated_bench(tmp_path):
    """The CLI's path: emulated drives in a child process behind CANopen (udp_multicast)."""
    doc = yaml.safe_load((ROOT / "profiles" / "motors-only.yaml").read_text())
    for m in doc["motors"].values():
        m["drive"] = str(ROOT / m["drive"])
    p = tmp_path / "motors.yaml"
    p.write_text(yaml.safe_dump(doc))
    seen = []
    result = run_profile(p, sim=True, out_dir=tmp_path / "run", serial="API-SIM", yes=True,
                         subscribers=[lambda rec: seen.append(rec.kind)])
    r = RunResult.from_dict(result)
    assert r.status == "passed", r.reason
    assert_claimed_accuracy(result, doc["simulation"])
    assert result["simulation_truth"]["motors"]["out"]["Kt"] == doc["simulation"]["motors"]["out"]["Kt"]
    # every calibration run: the waveform, then a stop ramp to rest
    n_waveform = sum(round(s["duration_s"] / doc["bench"]["period_s"]) for s in doc["steps"])
    assert math.isfinite(r.motors["in"].inertia_kgm2)
    assert r.samples == sum(r_ for r_ in result["steps"].values()) and r.samples > 2 * n_waveform
    assert result == json.loads((tmp_path / "run" / "result.json").read_text())
    assert seen[0] == "run_start" and seen[-1] == "run_stop" and seen.count("calibration") == 2
