"""gearbench as OpenHTF phases and plugs, headless on the simulated bench (issue 7).

A profile derived from profiles/cvt.yaml (efficiency grid cut to 1 x 2) keeps a full
OpenHTF run to seconds; the shipped profiles' tuning (waveforms, durations) is kept. Every run goes through
``build_test(..., sim=True)``: SimBenchPlug swapped in for BenchPlug by with_plugs.
"""
from __future__ import annotations

import io
import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from conftest import assert_claimed_accuracy

openhtf = pytest.importorskip("openhtf")   # the optional extra

from openhtf.core import base_plugs  # noqa: E402
from openhtf.output.callbacks import json_factory  # noqa: E402

from gearbench.openhtf import BenchPlug, SimBenchPlug, build_test, phases  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def small_profile(path: Path) -> tuple[Path, list]:
    """cvt.yaml with its efficiency grid cut to 1 speed x 2 torques; (path, grid)."""
    doc = yaml.safe_load((ROOT / "profiles" / "cvt.yaml").read_text())
    for m in doc["motors"].values():
        m["drive"] = str(ROOT / m["drive"])
    grid = []
    for s in doc["steps"]:
        if s["kind"] == "efficiency":
            s.update(speeds_in_rad_s=s["speeds_in_rad_s"][:1], torques_out_nm=s["torques_out_nm"][:2])
            grid = [(w, t) for w in s["speeds_in_rad_s"] for t in s["torques_out_nm"]]
    path.write_text(yaml.safe_dump(doc))
    return path, grid


def run(profile: Path, tmp_path: Path, dut: str):
    """Execute the OpenHTF test; (passed, JSON record as dict)."""
    test = build_test(profile, sim=True, out_root=tmp_path / "runs")
    buf = io.BytesIO()
    test.add_output_callbacks(json_factory.OutputToJSON(buf, inline_attachments=False, indent=1))
    passed = test.execute(test_start=lambda: dut)
    return passed, json.loads(buf.getvalue())


def measurements(record: dict) -> dict:
    return {name: m for ph in record["phases"] for name, m in ph["measurements"].items()}


@pytest.fixture(scope="module")
def passing(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("htf_pass")
    profile, grid = small_profile(tmp / "cvt-small.yaml")
    return (*run(profile, tmp, "SN-PASS"), grid)


def test_openhtf_run_passes_on_the_simulated_bench(passing):
    passed, record, _ = passing
    assert passed and record["outcome"] == "PASS", [
        (n, m.get("measured_value"), m["outcome"]) for n, m in measurements(record).items() if m["outcome"] != "PASS"]
    assert record["dut_id"] == "SN-PASS"
    assert [ph["name"] for ph in record["phases"]][1:] == [
        "calibrate-in", "calibrate-out", "load", "efficiency", "gearbench_result"]


def test_json_holds_every_measurement_with_unit_validator_and_outcome(passing):
    _, record, grid = passing
    meas = measurements(record)
    points = [f"{q}_{w:g}rad_s_{t:g}Nm" for w, t in grid for q in ("eta_incremental", "eta_absolute")]
    expected = [f"{m}_{s}" for m in ("in", "out") for s in ("kt", "kt_rel_datasheet", "inertia", "viscous",
                                                          "coulomb")] + ["ratio", *points, "gearbench_status"]
    assert sorted(meas) == sorted(expected)
    assert all(m["outcome"] == "PASS" for m in meas.values())
    # units and the profile's limits as validators
    assert meas["in_kt"]["units"]["suffix"] == "N·m/A"
    assert meas["in_kt_rel_datasheet"]["validators"] == ["0.85 <= x <= 1.15"]
    assert meas["in_kt"]["validators"] == [f"{0.85 * 0.0527!r} <= x <= {1.15 * 0.0527!r}"]
    assert meas["ratio"]["validators"] == ["7.84 <= x <= 8.16"]
    assert meas[points[0]]["validators"] == ["0.55 <= x <= 0.85"]
    # the OpenHTF verdicts agree with gearbench's own result.json
    result_dir = next((Path(record["metadata"]["gearbench_profile"]).parent / "runs").glob("SN-PASS-*"))
    result = json.loads((result_dir / "result.json").read_text())
    assert result["status"] == "passed" and result["serial"] == "SN-PASS"
    assert meas["in_kt"]["measured_value"] == pytest.approx(result["motors"]["in"]["Kt"])
    # Kt, ratio and every η against the simulated plant's truth, at the claimed accuracy
    plant = yaml.safe_load(Path(record["metadata"]["gearbench_profile"]).read_text())["simulation"]
    assert_claimed_accuracy(result, plant)
    assert meas["ratio"]["measured_value"] == pytest.approx(result["simulation_truth"]["ratio"], rel=1e-3)
    assert "gearbench_result.json" in record["phases"][-1]["attachments"]


def test_impossible_limit_fails_with_that_measurement_marked(tmp_path):
    # motors-only: calibration only, the quickest whole run; Kt/datasheet is about 1
    doc = yaml.safe_load((ROOT / "profiles" / "motors-only.yaml").read_text())
    for m in doc["motors"].values():
        m["drive"] = str(ROOT / m["drive"])
    doc["limits"][1].update(low=1.5, high=2.0)      # kt_out: impossible
    profile = tmp_path / "motors-impossible.yaml"
    profile.write_text(yaml.safe_dump(doc))
    passed, record = run(profile, tmp_path, "SN-FAIL")
    assert not passed and record["outcome"] == "FAIL"
    failed = {n for n, m in measurements(record).items() if m["outcome"] == "FAIL"}
    assert failed == {"out_kt", "out_kt_rel_datasheet", "gearbench_status"}
    phase = {ph["name"]: ph for ph in record["phases"]}
    assert phase["calibrate-out"]["outcome"] == "FAIL" and phase["calibrate-in"]["outcome"] == "PASS"
    assert phase["calibrate-out"]["measurements"]["out_kt_rel_datasheet"]["validators"] == ["1.5 <= x <= 2.0"]
    assert phase["gearbench_result"]["measurements"]["gearbench_status"]["measured_value"] == "failed"


def test_sim_plug_is_a_substitute_for_the_bench_plug(tmp_path):
    profile = ROOT / "profiles" / "motors-only.yaml"
    generic = phases(profile)
    assert all(p.plugs[0].cls is BenchPlug for p in generic)      # placeholder until swapped
    swapped = [p.with_plugs(bench=SimBenchPlug.for_profile(profile)) for p in generic]
    assert all(issubclass(p.plugs[0].cls, SimBenchPlug) for p in swapped)

    class NotABench(openhtf.plugs.BasePlug):
        pass

    with pytest.raises(base_plugs.InvalidPlugError):
        generic[0].with_plugs(bench=NotABench)


def test_import_has_no_openhtf_side_effects():
    """``import gearbench`` never imports OpenHTF; gearbench.openhtf keeps the SIGINT
    handler and ignores the station's argv (``--config-help`` would make OpenHTF exit)."""
    code = (
        "import signal, sys\n"
        "sys.argv = ['station', '--config-help', '-v']\n"
        "import gearbench, gearbench.api, gearbench.openhtf\n"
        "assert 'openhtf' not in sys.modules, 'openhtf imported by import gearbench'\n"
        "before = signal.getsignal(signal.SIGINT)\n"
        "t = gearbench.openhtf.build_test('profiles/motors-only.yaml', sim=True)\n"
        "assert 'openhtf' in sys.modules\n"
        "assert signal.getsignal(signal.SIGINT) is before, signal.getsignal(signal.SIGINT)\n"
        "print('ok', type(t).__mro__[1].__module__)\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["ok", "openhtf.core.test_descriptor"]


def test_operator_abort_ends_the_test_and_the_run(tmp_path, monkeypatch):
    """An abort at a mounting prompt: OpenHTF outcome ERROR, later phases not run, the
    gearbench run still finished (drives disabled, result.json status aborted)."""
    from gearbench.drives import registry
    from gearbench.errors import Aborted

    # in-process drive family from tests/plugin_example: no child process needed
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parent / "plugin_example"))
    monkeypatch.setitem(registry.BACKENDS, "loopback", "gearbench_loopback:LoopbackNetwork")
    doc = yaml.safe_load((ROOT / "profiles" / "motors-only.yaml").read_text())
    doc["bench"]["bus"] = {"family": "loopback", "options": {"plant": doc.pop("simulation")}}
    for m in doc["motors"].values():
        m["drive"] = str(ROOT / m["drive"])
    profile = tmp_path / "loop.yaml"
    profile.write_text(yaml.safe_dump(doc))

    class Refuses:
        def confirm(self, prompt):
            raise Aborted("operator abort at prompt")

    class RefusingBench(BenchPlug):
        auto_placeholder = True

        def operator_for(self, prompts):
            return Refuses()

    test = build_test(profile, out_root=tmp_path / "runs", plug=RefusingBench)
    buf = io.BytesIO()
    test.add_output_callbacks(json_factory.OutputToJSON(buf, inline_attachments=False))
    assert test.execute(test_start=lambda: "SN-ABORT") is False
    record = json.loads(buf.getvalue())
    assert record["outcome"] == "ERROR"
    assert [ph["name"] for ph in record["phases"]][1:] == ["calibrate-in"]
    result = json.loads(next((tmp_path / "runs").glob("SN-ABORT-*/result.json")).read_text())
    assert result["status"] == "aborted" and result["exit_code"] == 3
