"""gearbench run end to end on the simulated bench (real CANopen stack, emulator in a
child process): results folder, exit codes, limit failure, bad profile, bench fault,
operator abort. The bus used is printed by the emulator tests; here it is the
profile's (udp_multicast on a private port)."""
import json
import signal
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from gearbench.station.recorder import load_step_trace

REPO = Path(__file__).resolve().parents[1]
MOTORS_ONLY = REPO / "profiles" / "motors-only.yaml"


def gearbench(*args, timeout=120, **kw):
    return subprocess.run([sys.executable, "-m", "gearbench", *map(str, args)], cwd=REPO,
                          capture_output=True, text=True, timeout=timeout, **kw)


def planned_samples(profile_path=MOTORS_ONLY) -> dict:
    """Samples per segment as the sequencer plans them (waveform + stop ramp)."""
    from gearbench.profile import load_profile
    from gearbench.station.sequencer import Segment, Sequencer

    seq = Sequencer(load_profile(profile_path), None, emit=lambda r: None, operator=None)
    return {a.name: len(next(iter(a.commands.values()))[1]) for a in seq.plan() if isinstance(a, Segment)}


@pytest.fixture(scope="module")
def passed_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("station") / "run1"
    p = gearbench("run", MOTORS_ONLY, "--sim", "--yes", "--out", out, "--serial", "T-100")
    return p, out


def test_run_writes_a_complete_results_folder(passed_run):
    p, out = passed_run
    assert p.returncode == 0, p.stderr
    assert "Result: SIMULATED PASSED" in p.stdout and str(out) in p.stdout.splitlines()[-1]
    res = json.loads((out / "result.json").read_text())
    for key in ("serial", "profile", "profile_sha256", "started_utc", "finished_utc", "passed",
                "motors", "ratio", "efficiency", "limits", "bench_time_s", "simulation_truth"):
        assert key in res, key
    assert res["serial"] == "T-100" and res["passed"] is True
    for m in ("in", "out"):
        got, true = res["motors"][m], res["simulation_truth"]["motors"][m]
        assert set(got) >= {"Kt", "Kt_ci95", "J_kgm2", "D_nm_s_per_rad", "Tc_nm"}
        assert got["Kt_ci95"][0] < got["Kt"] < got["Kt_ci95"][1]
        assert abs(got["Kt"] / true["Kt"] - 1) < 0.005      # the tight check is test_run_accuracy
    plan = planned_samples()
    assert res["bench_time_s"] == pytest.approx(sum(plan.values()) * 1e-3, abs=1e-6)
    assert res["steps"] == plan
    suite = ET.parse(out / "junit.xml").getroot()
    assert [c.get("name") for c in suite.iter("testcase")] == [lim["name"] for lim in res["limits"]]
    assert suite.get("failures") == "0"


def test_traces_hold_every_sample_with_the_documented_columns(passed_run):
    _, out = passed_run
    files = sorted(out.glob("trace-*.parquet"))
    assert [f.name for f in files] == ["trace-calibrate-in-disk_a.parquet", "trace-calibrate-in-unloaded.parquet",
                                       "trace-calibrate-out-disk_a.parquet", "trace-calibrate-out-unloaded.parquet"]
    res = json.loads((out / "result.json").read_text())
    plan = planned_samples()
    for f in files:
        tr = load_step_trace(f)
        lost = int((np.diff(tr["sample"]) - 1).sum())   # gaps in the drive counter, if any
        assert len(tr) + lost == plan[f.stem[len("trace-"):]]
        for m in ("in", "out"):
            for q in ("position_rad", "velocity_rad_s", "current_a", "command"):
                assert f"{m}.{q}" in tr
        gaps = np.diff(tr["sample"])
        assert (gaps >= 1).all()
        np.testing.assert_allclose(np.diff(tr.time_s) / gaps, 1e-3, rtol=1e-9)  # drive time base


def test_station_database_answers_history(passed_run):
    _, out = passed_run
    db = out.parent / "station.sqlite"
    assert db.exists()
    p = gearbench("history", "T-100", "--db", db, "--json")
    assert p.returncode == 0, p.stderr
    runs = json.loads(p.stdout)["runs"]
    assert len(runs) == 1 and runs[0]["status"] == "passed"
    assert any(m["name"] == "motors.in.Kt" for m in runs[0]["measurements"])


def test_a_failed_limit_exits_1_and_marks_junit(tmp_path):
    text = MOTORS_ONLY.read_text().replace(
        "{name: kt_in, quantity: motors.in.Kt_rel_datasheet, low: 0.85, high: 1.15}",
        "{name: kt_in, quantity: motors.in.Kt_rel_datasheet, low: 1.10, high: 1.15}")
    assert "low: 1.10" in text
    prof = tmp_path / "tight.yaml"
    prof.write_text(text.replace("duration_s: 3.0", "duration_s: 1.5"))
    p = gearbench("run", prof, "--sim", "--yes", "--out", tmp_path / "run", "--serial", "T-101")
    assert p.returncode == 1, p.stderr
    suite = ET.parse(tmp_path / "run" / "junit.xml").getroot()
    failed = [c.get("name") for c in suite.iter("testcase") if c.find("failure") is not None]
    assert failed == ["kt_in"]


def test_bad_profile_is_one_line_exit_2(tmp_path):
    prof = tmp_path / "typo.yaml"
    prof.write_text(MOTORS_ONLY.read_text().replace("rated_current_a: 1.5\n", "rated_curent_a: 1.5\n", 1))
    p = gearbench("run", prof, "--sim", "--yes", "--out", tmp_path / "run")
    assert p.returncode == 2
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in p.stderr
    assert "typo.yaml:" in lines[0] and "rated_curent_a" in lines[0]
    assert not (tmp_path / "run" / "result.json").exists()   # nothing moved


def test_missing_profile_and_no_serial_are_exit_2(tmp_path):
    p = gearbench("run", tmp_path / "nope.yaml", "--sim", "--yes")
    assert p.returncode == 2 and "nope.yaml" in p.stderr and "Traceback" not in p.stderr
    p = gearbench("run", MOTORS_ONLY, "--yes", stdin=subprocess.DEVNULL)
    assert p.returncode == 2 and "--serial" in p.stderr


def test_bench_fault_stops_drives_and_keeps_samples(tmp_path):
    """A drive fault mid-step: quick stop + disable, exit 3, every sample before it kept."""
    from gearbench.api import open_network
    from gearbench.profile import load_profile
    from gearbench.station.recorder import ParquetRecorder
    from gearbench.station.records import RecordStream
    from gearbench.station.results import ResultWriter
    from gearbench.station.sequencer import AutoOperator, Sequencer
    from gearbench.emulate.launch import SimBench

    profile = load_profile(MOTORS_ONLY)
    with SimBench(profile) as sim:
        class FaultingFixture:
            def mount(self, *, coupling, disk_kgm2):
                sim.mount(coupling=coupling, disk_kgm2=disk_kgm2)
                if disk_kgm2:   # 0.5 s into the disk run, the input drive trips
                    now = sim.command({"cmd": "status"})["time_s"]
                    sim.command({"cmd": "fault", "axis": "in", "code": 0x2310, "at_s": now + 0.5})
        net = open_network(sim.bus_spec(), profile)
        stream = RecordStream([ParquetRecorder(tmp_path), ResultWriter(tmp_path)])
        try:
            result = Sequencer(profile, net, emit=stream.emit, operator=AutoOperator(),
                               fixture=FaultingFixture(), serial="T-102", out_dir=str(tmp_path)).run()
        finally:
            stream.close()
        status = sim.command({"cmd": "status"})["drives"]
        net.close()
    assert result["exit_code"] == 3 and result["status"] == "fault"
    assert "drive 'in'" in result["reason"] and "EMCY 0x2310" in result["reason"]
    for name, snap in status.items():   # both drives left without power
        assert "OPERATION ENABLED" not in json.dumps(snap), (name, snap)
    tr = load_step_trace(tmp_path / "trace-calibrate-in-disk_a.parquet")
    assert 400 <= len(tr) <= 600
    assert len(load_step_trace(tmp_path / "trace-calibrate-in-unloaded.parquet")) == \
        planned_samples()["calibrate-in-unloaded"]
    assert json.loads((tmp_path / "result.json").read_text())["status"] == "fault"


def test_ctrl_c_aborts_with_exit_3_and_keeps_samples(tmp_path):
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "gearbench", "run", str(MOTORS_ONLY), "--sim",
                             "--yes", "--out", str(out), "--serial", "T-103"], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 90
    for line in proc.stderr:
        if "step calibrate-in-disk_a:" in line or time.monotonic() > deadline:
            break
    time.sleep(0.3)
    t0 = time.monotonic()
    proc.send_signal(signal.SIGINT)
    rest = proc.stderr.read()
    summary = proc.stdout.read()          # the table and the verdict line go to stdout
    rc = proc.wait(30)
    assert rc == 3, rest
    assert time.monotonic() - t0 < 10
    assert "ABORTED" in summary and str(out) in summary and "Traceback" not in rest
    res = json.loads((out / "result.json").read_text())
    assert res["status"] == "aborted" and res["exit_code"] == 3
    tr = load_step_trace(out / "trace-calibrate-in-disk_a.parquet")
    assert 0 < len(tr) < 3000


def test_watchdog_current_limit_stops_the_run(tmp_path):
    """The plant needs more current than the profile allows (a heavier rotor than the
    datasheet says): the watchdog trips, drives stop, exit 3, samples kept."""
    text = MOTORS_ONLY.read_text().replace(
        "in:  {Kt: 0.0527, J: 1.5e-5, rated_current_a: 1.5, current_limit_a: 3.0}",
        "in:  {Kt: 0.0527, J: 1.5e-4, rated_current_a: 1.5, current_limit_a: 8.0}")
    assert "J: 1.5e-4" in text
    prof = tmp_path / "heavy.yaml"
    prof.write_text(text)
    p = gearbench("run", prof, "--sim", "--yes", "--out", tmp_path / "run", "--serial", "T-104")
    assert p.returncode == 3, p.stderr
    res = json.loads((tmp_path / "run" / "result.json").read_text())
    # whichever trips first: the drive's own current limit (0x6073, written from the
    # profile at start-up) -> EMCY 0x2310, or gearbench's watchdog on the samples
    assert res["status"] == "fault"
    assert "limit: motor 'in' current" in res["reason"] or "EMCY 0x2310" in res["reason"]
    tr = load_step_trace(tmp_path / "run" / "trace-calibrate-in-unloaded.parquet")
    assert 0 < len(tr) < 3000
    assert np.abs(tr["in.current_a"]).max() > 2.9    # it was the current, near the 3 A limit


def test_run_with_rrd_records_every_acquired_sample(tmp_path):
    """`gearbench run --rrd`: the recording holds every sample of every motor that the
    Parquet traces hold, and the result entities (read back with rerun's own reader)."""
    from test_live import read_rrd, series

    out, rrd = tmp_path / "run", tmp_path / "run.rrd"
    p = gearbench("run", MOTORS_ONLY, "--sim", "--yes", "--out", out, "--serial", "T-105", "--rrd", rrd)
    assert p.returncode == 0, p.stderr
    entities, blueprints = read_rrd(str(rrd))
    traces = [load_step_trace(f) for f in sorted(out.glob("trace-*.parquet"), key=lambda f: f.stat().st_mtime)]
    samples = np.sort(np.concatenate([t["sample"] for t in traces]))
    for m in ("in", "out"):
        for q in ("current_a", "position_rad", "velocity_rad_s"):
            got_s, _, got_v = series(entities[f"/bench/{m}/{q}"])
            np.testing.assert_array_equal(got_s, samples)
            want = np.concatenate([t[f"{m}.{q}"] for t in traces])[np.argsort(np.concatenate([t["sample"] for t in traces]), kind="stable")]
            np.testing.assert_array_equal(got_v, want)
    # setpoints: every sample of the steps that drive the motor, on the axis of its unit
    from gearbench.profile import load_profile
    from gearbench.station.plan import command_units

    units = command_units(load_profile(MOTORS_ONLY))
    for m in ("in", "out"):
        for unit in ("rad_s", "a"):
            driven = [t for f, t in zip(sorted(out.glob("trace-*.parquet"), key=lambda f: f.stat().st_mtime), traces)
                      if units.get(f.stem.removeprefix("trace-"), {}).get(m) == unit]
            path = f"/bench/{m}/command_{unit}"
            if not driven:
                assert path not in entities
                continue
            want_s = np.concatenate([t["sample"] for t in driven])
            got_s, _, got_v = series(entities[path])
            np.testing.assert_array_equal(got_s, np.sort(want_s))
            np.testing.assert_array_equal(got_v, np.concatenate([t[f"{m}.command"] for t in driven])[
                np.argsort(want_s, kind="stable")])
    assert "/results/motors/in" in entities and "/results/motors/out" in entities
    assert any(e.startswith("/results/limits/") for e in entities)


def test_run_over_modbus_on_the_simulated_bench(tmp_path):
    """The same chain with the profile's bus set to Modbus TCP (emulator behind pymodbus)."""
    import yaml

    doc = yaml.safe_load(MOTORS_ONLY.read_text())
    doc["bench"]["bus"] = {"family": "modbus", "host": "127.0.0.1", "port": 5020}
    for m in doc["motors"].values():
        m["drive"] = str(REPO / "drivers" / "generic-modbus-servo.yaml")
    prof = tmp_path / "modbus.yaml"
    prof.write_text(yaml.safe_dump(doc))
    out = tmp_path / "run"
    p = gearbench("run", prof, "--sim", "--yes", "--out", out, "--serial", "T-106")
    assert p.returncode == 0, p.stderr
    res = json.loads((out / "result.json").read_text())
    for m in ("in", "out"):
        assert abs(res["motors"][m]["Kt"] / res["simulation_truth"]["motors"][m]["Kt"] - 1) < 0.005
    tr = load_step_trace(out / "trace-calibrate-out-unloaded.parquet")
    assert (np.diff(tr["sample"]) == 1).all()     # lockstep over Modbus: no sample lost
