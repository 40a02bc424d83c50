"""What the operator, the quality engineer and the MES see (issue 27): the console's
stdout/stderr split, stable limit names, result.json names, refusing before anything
moves, the output motor's friction in fixed-length steps."""
from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from gearbench.analysis.calibration import MotorCalibration, motor_value
from gearbench.errors import GearbenchError
from gearbench.profile import load_profile
from gearbench.station import limits
from gearbench.station.console import ProgressDisplay, summary_table, verdict_line
from gearbench.station.database import check_writable
from gearbench.station.plan import Known, efficiency_segment, output_friction_nm
from gearbench.station.records import RunStop
from gearbench.station.results import ResultWriter

REPO = Path(__file__).resolve().parents[1]


def _point(speed, torque_meas, out_command, eta=0.75, **kw):
    return {"speed_in_rad_s": speed + 0.013, "speed_setpoint_rad_s": speed, "torque_out_nm": torque_meas,
            "out_command": out_command, "eta_incremental": eta, "eta_absolute": 0.5,
            "eta_incremental_ci95": [eta - 0.002, eta + 0.002], **kw}


def _result(points, sim=True):
    res = {"serial": "SN7", "run_id": "r7", "profile": "cvt-link-mechanism", "status": "passed",
           "passed": True, "exit_code": 0, "reason": "", "out_dir": "/data/results/SN7-x",
           "motors": {"in": {"Kt": 0.0527, "Kt_ci95": [0.0524, 0.053], "J_kgm2": 1.5e-5,
                             "D_nm_s_per_rad": 2e-6, "Tc_nm": 0.008}},
           "ratio": 8.0, "efficiency": points,
           "limits": [{"name": "kt_in", "quantity": "motors.in.Kt_rel_datasheet", "value": 1.0001,
                       "low": 0.85, "high": 1.15, "passed": True}],
           "bench_time_s": 15.0, "wall_time_s": 20.0, "samples": 15000, "lost_samples": 0}
    if sim:
        res["simulation_truth"] = {"motors": {"in": {"Kt": 0.0527}}, "ratio": 8.0,
                                   "efficiency": [{"eta_incremental": 0.75, "eta_absolute": 0.5}] * len(points)}
    return res


# ----------------------------------------------------------------- console


def test_summary_and_verdict_go_to_stdout_progress_to_stderr():
    err, out = io.StringIO(), io.StringIO()
    d = ProgressDisplay(err, summary=out)
    pts = [_point(100, 0.0601, -1.17, incremental_method="slope", loss_extrapolated=True)]
    d(RunStop("passed", 0, "", _result(pts)))
    text = out.getvalue()
    assert "Result: SIMULATED PASSED" in text and "-> /data/results/SN7-x" in text and "exit 0" in text
    # every column that was unexplained is explained
    assert "one value per speed" in text and "percentage points" in text
    assert "x datasheet" in text                     # kt_in 1.0001 has its unit
    assert "loss extrapolated" in text and "profile-authoring" in text
    assert "Result:" not in err.getvalue()


def test_quiet_prints_only_the_verdict_line():
    err, out = io.StringIO(), io.StringIO()
    d = ProgressDisplay(err, quiet=True, summary=out)
    d(RunStop("failed", 1, "efficiency[100rad_s,0.06Nm]", dict(_result([], sim=False), status="failed",
                                                                 exit_code=1, reason="efficiency[100rad_s,0.06Nm]")))
    assert err.getvalue() == ""
    lines = out.getvalue().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Result: FAILED (limit)") and "SN7-x" in lines[0]
    assert "SIMULATED" not in lines[0]


def test_quiet_python_api_prints_nothing():
    err = io.StringIO()
    ProgressDisplay(err, quiet=True)(RunStop("passed", 0, "", _result([])))
    assert err.getvalue() == ""


# ------------------------------------------------------------- stable names


@pytest.fixture(scope="module")
def cvt():
    return load_profile(REPO / "profiles" / "cvt.yaml")


def test_limit_names_are_the_commanded_points_not_the_measured(cvt):
    """Measured torques 0.0601 / 0.0598 N m, friction-compensated currents: the names are
    the profile's 0.06 N m, identical from run to run."""
    kt = 0.0512
    names = []
    for wobble in (0.0003, -0.0002):
        pts = [_point(s, t + wobble, -(t - 0.004) / kt) for s in (100, 200, 300)
               for t in (0.04, 0.06, 0.08, 0.10)]
        res = limits.check(cvt, {"in": {"Kt": 0.0527}, "out": {"Kt": 0.0512}}, 8.0, pts)
        names.append([r.name for r in res])
    assert names[0] == names[1]
    assert "efficiency[100rad_s,0.06Nm]" in names[0] and "efficiency[300rad_s,0.1Nm]" in names[0]
    assert not any("0.0601" in n or "0.0598" in n for n in names[0])


def test_a_speed_that_lost_a_point_still_names_by_nearest_level(cvt):
    pts = [_point(100, 0.0795, -1.5)]
    (sp,) = limits.commanded_points(cvt, pts)
    assert sp == (100.0, 0.08)


def test_junit_names_by_commanded_point(cvt, tmp_path):
    pts = limits.with_setpoints(cvt, [_point(200, 0.0999, -1.9)])
    res = _result(pts)
    res["limits"] = [{"name": limits.point_name("efficiency", pts[0]), "value": 0.75, "low": 0.55,
                      "high": 0.85, "passed": True}]
    ResultWriter(tmp_path)(RunStop("passed", 0, "", res))
    case = [c.get("name") for c in ET.parse(tmp_path / "junit.xml").getroot().iter("testcase")]
    assert case == ["efficiency[200rad_s,0.1Nm]"]


# ------------------------------------------------------------- result.json


def test_result_json_motor_names_carry_units_and_old_files_still_read():
    cal = MotorCalibration(0.05, (0.049, 0.051), 1.5e-5, 2e-6, 0.008, "default", fit={"r2": 0.99998},
                           Kt_std=0.0005)
    d = cal.to_dict()
    assert {"J_kgm2", "D_nm_s_per_rad", "Tc_nm"} <= set(d) and not {"J", "D", "Tc"} & set(d)
    assert "r2" not in d["fit"] and d["fit"]["r2_acceleration"] == 0.99998
    back = MotorCalibration.from_dict(d)
    assert (back.J, back.D, back.Tc, back.fit["r2"]) == (1.5e-5, 2e-6, 0.008, 0.99998)
    old = {"Kt": 0.05, "Kt_std": 0.0005, "Kt_ci95": [0.049, 0.051], "J": 1e-5, "D": 1e-6, "Tc": 0.01,
           "fit": {"r2": 0.9}}
    back = MotorCalibration.from_dict(old)
    assert (back.J, back.D, back.Tc) == (1e-5, 1e-6, 0.01)
    assert motor_value(old, "J") == 1e-5 and motor_value(d, "J") == 1.5e-5


def test_result_json_has_no_float_noise(tmp_path):
    res = _result([_point(100, 0.06, -1.1, t_mid_s=12.300000000000002,
                          loss_speed_range_in_rad_s=[-2.842170943040401e-14, 241.12695054016928])])
    ResultWriter(tmp_path)(RunStop("passed", 0, "", res))
    text = (tmp_path / "result.json").read_text()
    assert "e-14" not in text
    back = json.loads(text)
    assert back["efficiency"][0]["loss_speed_range_in_rad_s"] == [0.0, 241.12695054016928]
    from gearbench.station.results import round_floats

    assert round_floats({"r": [-2.842170943040401e-14, 241.1]}) == {"r": [0.0, 241.1]}
    assert back["motors"]["in"]["J_kgm2"] == 1.5e-5


# ------------------------------------------------- refuse before anything moves


def test_station_database_that_cannot_be_written_is_refused_naming_it(tmp_path):
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("")
    with pytest.raises(GearbenchError) as e:
        check_writable(blocker / "station.sqlite")
    assert str(blocker / "station.sqlite") in str(e.value) and e.value.exit_code == 2
    check_writable(tmp_path / "ok" / "station.sqlite")


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_parent_folder_is_refused(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        with pytest.raises(GearbenchError):
            check_writable(ro / "station.sqlite")
    finally:
        ro.chmod(0o755)


def _cli(*args, timeout=120):
    return subprocess.run([sys.executable, "-m", "gearbench", *args], capture_output=True, text=True,
                          cwd=REPO, timeout=timeout)


def test_run_refuses_unwritable_db_and_rrd_before_the_bench_starts(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    p = _cli("run", "profiles/cvt.yaml", "--sim", "--out", str(tmp_path / "run"), "--db",
             str(blocker / "station.sqlite"))
    assert p.returncode == 2 and str(blocker / "station.sqlite") in p.stderr, p.stderr
    assert "step " not in p.stderr                       # nothing ran
    p = _cli("run", "profiles/cvt.yaml", "--sim", "--out", str(tmp_path / "run2"), "--rrd",
             str(blocker / "live.rrd"))
    assert p.returncode == 2 and "--rrd" in p.stderr and "step " not in p.stderr, p.stderr


def test_validate_refuses_simulated_ratings_that_differ_and_fills_missing_ones(tmp_path):
    text = (REPO / "profiles" / "cvt.yaml").read_text()
    text = text.replace("drivers/", str(REPO / "drivers") + "/")
    bad = tmp_path / "bad.yaml"
    bad.write_text(text.replace("Tc: 0.008, cog_amp: 0.002,\n          rated_current_a: 1.5",
                                "Tc: 0.008, cog_amp: 0.002,\n          rated_current_a: 1.0"))
    p = _cli("validate", str(bad))
    assert p.returncode == 2 and "simulation.motors.in.rated_current_a" in p.stderr and ":12" in p.stderr
    left_out = tmp_path / "left_out.yaml"
    left_out.write_text(text.replace(",\n          rated_current_a: 1.5, current_limit_a: 3.0, speed_limit_rad_s: 420}", "}"))
    prof = load_profile(left_out)
    assert prof.simulation["motors"]["in"]["rated_current_a"] == 1.5
    assert prof.simulation["motors"]["in"]["counts_per_rev"] == 10000


# ------------------------------------------- output motor friction, fixed-length steps


def test_fixed_length_braking_levels_subtract_the_output_motors_friction():
    prof = load_profile(REPO / "profiles" / "cyclo.yaml")
    step = next(s for s in prof.steps if hasattr(s, "torques_out_nm"))
    kt_out = 0.05
    plain = efficiency_segment(prof, step, 0, 100.0, Known({"in": 0.05, "out": kt_out}))
    ratio = prof.reducer.ratio
    if ratio is None:
        pytest.skip("profile measures its ratio")
    friction = lambda w: 1e-3 * w + 0.01          # noqa: E731  D w + Tc of the output motor
    comp = efficiency_segment(prof, step, 0, 100.0, Known({"in": 0.05, "out": kt_out}, loss_out=friction))
    loss = output_friction_nm(prof, 100.0, Known({}, loss_out=friction))
    assert loss == pytest.approx(1e-3 * 100.0 / ratio + 0.01)
    a, b = plain.commands["out"][1], comp.commands["out"][1]
    levels_a = [x for x in np.unique(np.round(a, 9)) if x < 0]
    levels_b = [x for x in np.unique(np.round(b, 9)) if x < 0]
    assert len(levels_a) == len(levels_b) == len(step.torques_out_nm)
    for la, lb in zip(sorted(levels_a), sorted(levels_b)):
        assert (abs(la) - abs(lb)) * kt_out == pytest.approx(loss, rel=1e-6)


# ------------------------------------------------------------------ history


def test_history_finds_the_station_by_its_bench_name_and_columns_stay_apart(tmp_path, capsys, monkeypatch):
    from gearbench.cli import main
    from gearbench.station.database import StationDatabase

    monkeypatch.delenv("GEARBENCH_STATION", raising=False)
    db = tmp_path / "station.sqlite"
    res = dict(_result([], sim=False), profile="cvt-link-mechanism", started_utc="2026-12-01T21:00:00Z",
               station={"name": "eol-station-1", "host": "vm"}, status="passed")
    StationDatabase(db)(RunStop("passed", 0, "", res))
    assert main(["history", "--db", str(db), "--station", "eol-station-1"]) == 0
    out = capsys.readouterr().out
    head, row = out.splitlines()[:2]
    assert "SN7" in row and "cvt-link-mechanism  passed" in row       # never 'cvt-link-mechanismpassed'
    assert head.index("status") == row.index("passed")
    assert main(["history", "--db", str(db), "--station", "eol-station-2"]) == 0
    assert "no runs" in capsys.readouterr().out


# ------------------------------------------------------- a profile for another reducer


def test_harmonic_profile_validates_and_its_calibration_covers_the_map():
    """The guide's worked example (docs/profile-authoring.md): each motor's calibration
    waveform spans the speeds it turns at in the map, so no point will be extrapolated."""
    from gearbench.profile import CalibrateStep, EfficiencyStep

    prof = load_profile("harmonic")
    assert prof.name == "harmonic-100" and prof.reducer.ratio == 100
    eff = next(s for s in prof.steps if isinstance(s, EfficiencyStep))
    speed = {"in": max(eff.speeds_in_rad_s), "out": max(eff.speeds_in_rad_s) / prof.reducer.ratio}
    for s in prof.steps:
        if isinstance(s, CalibrateStep):
            wave = prof.waveforms[s.waveform].render(np.arange(0, s.duration_s, prof.bench.period_s))
            assert wave.max() >= speed[s.motor], (s.motor, wave.max(), speed[s.motor])
    p = _cli("validate", "harmonic")
    assert p.returncode == 0 and "OK" in p.stdout, p.stderr


@pytest.mark.slow     # bench time 40 s; about 3 min of wall time on a loaded 2-core host
def test_harmonic_profile_passes_on_the_simulated_bench_without_flags(tmp_path):
    out = tmp_path / "harm"
    p = _cli("run", "harmonic", "--sim", "--yes", "--quiet", "--out", str(out), timeout=1500)
    assert p.returncode == 0, p.stderr[-2000:]
    assert p.stdout.startswith("Result: SIMULATED PASSED") and str(out) in p.stdout
    res = json.loads((out / "result.json").read_text())
    assert not any(pt["loss_extrapolated"] for pt in res["efficiency"])
    # fixed-length levels brake at the profile's torque: the output motor's own friction
    # (Tc 0.15 N m in the plant) is no longer added on top
    for pt in res["efficiency"]:
        assert abs(pt["torque_out_nm"] - pt["torque_setpoint_nm"]) < 0.03, pt
    names = [lim["name"] for lim in res["limits"]]
    assert "efficiency[100rad_s,5Nm]" in names and "efficiency[300rad_s,20Nm]" in names


def test_validate_warns_when_calibration_does_not_cover_the_map(tmp_path):
    from dataclasses import replace

    from gearbench.profile.coverage import uncovered

    assert uncovered(load_profile("cvt")) == [] and uncovered(load_profile("harmonic")) == []
    cvt = load_profile("cvt")
    fast = [replace(s, speeds_in_rad_s=(100.0, 500.0)) if hasattr(s, "speeds_in_rad_s") else s for s in cvt.steps]
    (w,) = [m for m in uncovered(replace(cvt, steps=fast)) if "motor in" in m]   # 500 rad/s is beyond it
    assert "500 rad/s" in w and "extrapolated motor loss" in w and "profile-authoring" in w


def test_reanalysis_of_an_old_run_does_not_report_renamed_limits_as_changed():
    from gearbench.fleet.reanalysis import _changed_limits

    q = "efficiency.eta_incremental"
    old = {"limits": [{"name": "efficiency[100rad_s,0.0601Nm]", "quantity": q, "passed": True},
                      {"name": "efficiency[100rad_s,0.0799Nm]", "quantity": q, "passed": True}]}
    new = {"limits": [{"name": "efficiency[100rad_s,0.06Nm]", "quantity": q, "passed": True},
                      {"name": "efficiency[100rad_s,0.08Nm]", "quantity": q, "passed": False}]}
    assert _changed_limits(old, new) == ["efficiency[100rad_s,0.08Nm] PASS->FAIL"]
