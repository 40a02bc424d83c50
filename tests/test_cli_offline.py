"""Offline commands end to end (calibrate, identify, efficiency) and bad input, case by case:
exit code 2, one line on stderr naming the file/column and the fix, no traceback."""
import json

import numpy as np
import pytest

from gearbench.benchmarks._data import DEV_DIR
from gearbench.cli import main
from gearbench.trace import Trace

DEV = DEV_DIR                       # ../shared/datasets/dev beside the checkout
pytestmark = pytest.mark.usefixtures("dev_data")   # skipped without it, failed in CI
UA, LA = DEV / "calib_motor_a_unloaded.csv", DEV / "calib_motor_a_loaded.csv"
UB, LB = DEV / "calib_motor_b_unloaded.csv", DEV / "calib_motor_b_loaded.csv"
BENCH = DEV / "bench_motor_a_in_motor_b_out.csv"
DISK = "1.5e-5"


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def bad(capsys, *argv, must=()):
    code, out, err = run(capsys, *argv)
    assert code == 2, (out, err)
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    for m in must:
        assert m in err, err
    return err


def test_calibrate_json_and_text(capsys, tmp_path):
    code, out, _ = run(capsys, "calibrate", "--unloaded", UA, "--loaded", LA, "--inertia", DISK, "--json")
    assert code == 0
    d = json.loads(out)
    assert {"Kt", "Kt_ci95", "J_kgm2", "D_nm_s_per_rad", "Tc_nm", "method", "fit"} <= set(d)
    assert d["Kt_ci95"][0] < d["Kt"] < d["Kt_ci95"][1]
    assert abs(d["Kt"] / 0.0612 - 1) < 0.002
    assert {"r2_acceleration", "rmse", "n_samples", "condition", "b2_unloaded", "b2_loaded"} <= set(d["fit"])
    lo, hi = d["fit"]["speed_range_rad_s"]
    assert 0 < lo < hi
    code, out, _ = run(capsys, "calibrate", "--unloaded", UA, "--loaded", LA, "--inertia", DISK,
                       "--method", "paper")
    assert code == 0 and "method       paper" in out and "Kt" in out
    assert "disk inertia taken as exact" in out           # said, not silently left out
    # a ±2 % datasheet disk: u_rel(Kt)² gains (0.02/√3)², stored as std and dof
    code, out, _ = run(capsys, "calibrate", "--unloaded", UA, "--loaded", LA, "--inertia", DISK,
                       "--inertia-tolerance", "0.02", "--inertia-source", "datasheet", "--json")
    t = json.loads(out)
    assert code == 0 and t["Kt"] == d["Kt"]
    assert (t["Kt_std"] / t["Kt"]) ** 2 == pytest.approx((d["Kt_std"] / d["Kt"]) ** 2 + 0.02 ** 2 / 3, rel=1e-9)
    assert t["Kt_dof"] > d["Kt_dof"] and t["fit"]["Kt_std_disk"] == pytest.approx(t["Kt"] * 0.02 / 3 ** 0.5)
    assert t["Kt_ci95"][1] - t["Kt_ci95"][0] > 5 * (d["Kt_ci95"][1] - d["Kt_ci95"][0])
    code, _, err = run(capsys, "calibrate", "--unloaded", UA, "--loaded", LA, "--inertia", DISK,
                       "--inertia-tolerance", "2")
    assert code == 2 and "--inertia-tolerance must be a relative tolerance" in err


def test_identify_json(capsys):
    code, out, _ = run(capsys, "identify", UB, "--json")
    d = json.loads(out)
    assert code == 0 and d["method"] == "default"
    assert d["b2"] == pytest.approx(0.0455 / 1.1e-5, rel=0.002)
    assert {"Kt/J", "D/J", "Tc/J"} <= set(d["params"]) and d["covariance"]["matrix"]
    code, out, _ = run(capsys, "identify", UB, "--method", "paper-15ms")
    assert code == 0 and "C/J" in out


def test_efficiency_from_calibration_files_and_from_kt(capsys, tmp_path):
    for name, (u, l) in {"a": (UA, LA), "b": (UB, LB)}.items():
        code, out, _ = run(capsys, "calibrate", "--unloaded", u, "--loaded", l, "--inertia", DISK, "--json")
        (tmp_path / f"{name}.json").write_text(out)
    code, out, _ = run(capsys, "efficiency", BENCH, "--motor-in", tmp_path / "a.json",
                       "--motor-out", tmp_path / "b.json", "--json")
    assert code == 0
    d = json.loads(out)
    assert d["ratio"] == pytest.approx(7.0, rel=1e-4) and len(d["points"]) == 4
    for p in d["points"]:
        assert {"eta_incremental", "eta_incremental_ci95", "eta_absolute", "eta_absolute_ci95",
                "speed_in_rad_s", "torque_out_nm"} <= set(p)
        assert p["eta_incremental"] == pytest.approx(0.88, abs=0.002)
        assert p["loss_extrapolated"] is False and len(p["loss_speed_range_out_rad_s"]) == 2
    torques = [p["torque_out_nm"] for p in d["points"]]
    assert torques == sorted(torques)                            # trace order: rising load
    code, out, _ = run(capsys, "efficiency", BENCH, "--kt-in", "0.0612", "--kt-out", "0.0455", "--ratio", "7")
    assert code == 0 and "eta incr" in out and "ignores its friction" in out


# ------------------------------------------------------------------ bad input
def _copy_with(tmp_path, src, name, edit):
    tr = Trace.read(src)
    tr = edit(tr)
    p = tmp_path / name
    tr.write_csv(p)
    return p


def test_missing_column(capsys, tmp_path):
    p = _copy_with(tmp_path, UA, "nocur.csv", lambda t: t.select(["position_rad", "command"]))
    bad(capsys, "calibrate", "--unloaded", p, "--loaded", LA, "--inertia", DISK,
        must=("nocur.csv", "current_a"))


def test_misnamed_column(capsys, tmp_path):
    p = _copy_with(tmp_path, UA, "renamed.csv",
                   lambda t: t.select(["position_rad", "current_a"], rename={"current_a": "current"}))
    bad(capsys, "identify", p, must=("renamed.csv", "current_a"))


def test_bench_missing_column(capsys, tmp_path):
    p = _copy_with(tmp_path, BENCH, "bench.csv", lambda t: t.select(
        [n for n in t.names if n != "out_command"]))
    bad(capsys, "efficiency", p, "--kt-in", "0.06", "--kt-out", "0.045", must=("bench.csv", "out_command"))


def test_non_monotonic_time(capsys, tmp_path):
    def edit(t):
        ts = t.time_s.copy()
        ts[100], ts[101] = ts[101], ts[100]
        return Trace(ts, t.columns, {}, t.source)
    p = _copy_with(tmp_path, UA, "order.csv", edit)
    bad(capsys, "identify", p, must=("order.csv", "time_s", "not strictly increasing"))


def test_irregular_time(capsys, tmp_path):
    def edit(t):
        keep = np.ones(len(t), bool)
        keep[500:520] = False                     # 20 lost samples
        return Trace(t.time_s[keep], {k: v[keep] for k, v in t.columns.items()}, {}, t.source)
    p = _copy_with(tmp_path, UA, "gap.csv", edit)
    bad(capsys, "identify", p, must=("gap.csv", "irregular sampling"))


def test_nan_and_inf(capsys, tmp_path):
    for val, name in ((np.nan, "nan.csv"), (np.inf, "inf.csv")):
        def edit(t, val=val):
            c = t["current_a"].copy()
            c[200] = val
            return t.with_columns(current_a=c)
        p = _copy_with(tmp_path, UA, name, edit)
        bad(capsys, "identify", p, must=(name, "current_a", "non-finite"))


def test_too_few_samples(capsys, tmp_path):
    p = _copy_with(tmp_path, UA, "short.csv", lambda t: t.slice(0, 30))
    bad(capsys, "identify", p, must=("short.csv", "samples"))


def test_no_excitation(capsys, tmp_path):
    t = np.arange(3000) * 1e-3
    q = 2 * np.pi / 10000
    tr = Trace(t, {"position_rad": np.floor(150 * t / q) * q,
                   "current_a": 0.2 + np.random.default_rng(0).normal(0, 0.004, t.size)}, {}, "flat")
    p = tmp_path / "flat.csv"
    tr.write_csv(p)
    bad(capsys, "identify", p, must=("flat.csv", "rad/s amplitude"))


def test_loaded_and_unloaded_swapped(capsys):
    bad(capsys, "calibrate", "--unloaded", LA, "--loaded", UA, "--inertia", DISK,
        must=("swap --loaded and --unloaded",))


@pytest.mark.parametrize("inertia", ["0", "-1e-5", "nan"])
def test_inertia_not_positive(capsys, inertia):
    bad(capsys, "calibrate", "--unloaded", UA, "--loaded", LA, f"--inertia={inertia}",
        must=("--inertia", "> 0"))


def test_unreadable_and_missing_files(capsys, tmp_path):
    p = tmp_path / "garbage.csv"
    p.write_bytes(b"\xff\xfe\x00\x01binary\x00")
    bad(capsys, "identify", p, must=("garbage.csv",))
    bad(capsys, "identify", tmp_path / "nope.csv", must=("nope.csv", "not found"))
    q = tmp_path / "text.csv"
    q.write_text("time_s,position_rad,current_a\n0,0,abc\n")
    bad(capsys, "identify", q, must=("text.csv", "not a number"))


def test_motor_json_missing_keys_or_invalid(capsys, tmp_path):
    p = tmp_path / "IN.json"
    p.write_text(json.dumps({"Kt": 0.06, "J": 1.8e-5}))
    bad(capsys, "efficiency", BENCH, "--motor-in", p, "--kt-out", "0.0455",
        must=("IN.json", "D, Tc", "calibrate --json"))
    p.write_text("{not json")
    bad(capsys, "efficiency", BENCH, "--motor-in", p, "--kt-out", "0.0455", must=("IN.json", "JSON"))
    bad(capsys, "efficiency", BENCH, "--kt-in", "0.06", must=("--motor-out", "--kt-out"))


# ------------------------------------------------ gearbench's own run traces (issue 27)


def _run_trace(tmp_path, n=3000, motors=("in", "out")):
    """A run trace as the recorder writes it: columns ``<motor>.<quantity>``."""
    tr = Trace.read(UA)
    t = tr.time_s[:n]
    cols = {"sample": np.arange(len(t))}
    for m in motors:
        cols[f"{m}.position_rad"] = tr["position_rad"][:n]
        cols[f"{m}.current_a"] = tr["current_a"][:n]
    path = tmp_path / "trace-calibrate-in.out-unloaded.parquet"
    Trace(t, cols, source=str(path)).write(path)
    return path


def test_identify_reads_a_run_trace_with_motor(capsys, tmp_path):
    path = _run_trace(tmp_path)
    code, out, _ = run(capsys, "identify", path, "--motor", "out", "--json")
    assert code == 0
    ref_code, ref, _ = run(capsys, "identify", UA, "--json")
    a, b = json.loads(out), json.loads(ref)
    assert a["b2"] == b["b2"]                    # the same samples, the same fit


def test_identify_on_a_two_motor_run_trace_asks_for_motor(capsys, tmp_path):
    bad(capsys, "identify", _run_trace(tmp_path), must=("--motor in or --motor out",))


def test_motor_on_a_plain_trace_is_refused(capsys):
    bad(capsys, "identify", UA, "--motor", "in", must=("leave --motor out",))


def test_efficiency_reads_a_run_trace_as_it_is(capsys, tmp_path):
    tr = Trace.read(BENCH)
    cols = {c.replace("_", ".", 1): tr[c] for c in tr.columns if c.startswith(("in_", "out_"))}
    path = tmp_path / "trace-efficiency-0.parquet"
    Trace(tr.time_s, cols, source=str(path)).write(path)
    code, out, _ = run(capsys, "efficiency", path, "--kt-in", "0.05", "--kt-out", "0.05", "--json")
    ref_code, ref, _ = run(capsys, "efficiency", BENCH, "--kt-in", "0.05", "--kt-out", "0.05", "--json")
    assert code == ref_code == 0
    assert json.loads(out)["points"][0]["eta_incremental"] == json.loads(ref)["points"][0]["eta_incremental"]


def test_calibrate_takes_the_drives_sampling_as_a_profile_does(capsys, tmp_path):
    """``--drive-setpoint step --drive-current instant`` declares what a profile's
    ``motors.<m>.sampling`` declares: a stepping, sampling drive's current kick is modelled
    (seed 8 case 11's input motor, as in test_robustness: Kt within 0.2 % only with it)."""
    from gearbench.benchmarks import robustness as R

    case = R.draw_case(11, 8)
    files = []
    for name, t in zip(("u", "l"), R.simulate_case(case)["runs"]["in"]):
        del t.meta["drive"]                       # as a file from elsewhere: nothing said
        files.append(t.write_csv(tmp_path / f"{name}.csv"))
    base = ("calibrate", "--unloaded", files[0], "--loaded", files[1],
            "--inertia", case.disks_kgm2["in"], "--json")
    code, out, _ = run(capsys, *base, "--drive-setpoint", "step", "--drive-current", "instant")
    said = json.loads(out)
    assert code == 0 and said["fit"]["setpoint_step"]["declared"] is True
    code, out, _ = run(capsys, *base)
    plain = json.loads(out)
    assert code == 0 and plain["fit"]["setpoint_step"]["declared"] is None
    kt = case.plant.motor_in.Kt
    assert abs(said["Kt"] / kt - 1) <= 0.002
    assert abs(plain["Kt"] / kt - 1) > 2 * abs(said["Kt"] / kt - 1)   # undeclared: biased
    bad(capsys, *base, "--drive-setpoint", "step", must=("--drive-current",))
    bad(capsys, *base, "--drive-current-limit", "3", must=("--drive-setpoint",))
    bad(capsys, *base, "--drive-setpoint", "step", "--drive-current", "instant",
        "--drive-current-limit", "-1", must=("--drive-current-limit must be",))
    # the limit declared as the drive has it: the same motor, samples at 3 A carry no kick
    code, out, _ = run(capsys, *base, "--drive-setpoint", "step", "--drive-current", "instant",
                       "--drive-current-limit", case.plant.motor_in.current_limit_a)
    limited = json.loads(out)
    assert code == 0 and abs(limited["Kt"] / kt - 1) <= 0.0025
    # the drive's loop declared as the profile's sampling can: the kick computed, not fitted
    m = case.plant.motor_in
    step = ("--drive-setpoint", "step", "--drive-current", "instant",
            "--drive-current-limit", m.current_limit_a)
    code, out, _ = run(capsys, *base, *step, "--drive-loop", m.vel_kp, m.current_lag_s, m.loop_period_s)
    looped = json.loads(out)
    assert code == 0 and looped["fit"]["kick_a_per_rad_s"] > 0
    assert abs(looped["Kt"] / kt - 1) <= 0.0015
    bad(capsys, *base, "--drive-loop", m.vel_kp, m.current_lag_s, m.loop_period_s,
        must=("--drive-loop goes with",))
    # a drive whose setpoint's shape the analysis does not need its loop for
    bad(capsys, *base, "--drive-setpoint", "interpolated", "--drive-current", "mean",
        "--drive-loop", m.vel_kp, m.current_lag_s, m.loop_period_s, must=("--drive-loop goes with",))
    bad(capsys, *base, *step, "--drive-loop", -1, m.current_lag_s, m.loop_period_s,
        must=("--drive-loop takes",))


def test_calibrate_takes_an_interpolating_drives_loop_for_its_kinks(capsys, tmp_path):
    """``--drive-setpoint interpolated --drive-current instant --drive-loop ...`` gives the
    ramps' kinks to the fit (``identify.interpolated_kink_weights``): seed 7 case 1's output
    drive at 250 Hz, noise-free, Kt 0.11 % low without the loop and within 0.02 % with it."""
    from dataclasses import replace as dc_replace

    from gearbench.benchmarks import robustness as R
    from gearbench.sim import simulate_motor

    case = R.with_period(R.draw_case(1, 7), 4e-3)
    m = dc_replace(case.plant.motor_out, current_noise_a=0.0, current_resolution_a=0.0,
                   counts_per_rev=1 << 20, cog_amp=0.0)
    files = []
    for name, disk, seed in (("u", 0.0, 1), ("l", case.disks_kgm2["out"], 2)):
        t = simulate_motor(m, case.commands["out"], disk_kgm2=disk, seed=seed, period_s=4e-3)
        files.append(t.write_csv(tmp_path / f"{name}.csv"))
    base = ("calibrate", "--unloaded", files[0], "--loaded", files[1], "--inertia",
            case.disks_kgm2["out"], "--json", "--drive-setpoint", "interpolated", "--drive-current",
            "instant", "--drive-current-limit", m.current_limit_a)
    code, out, _ = run(capsys, *base)
    plain = json.loads(out)
    code2, out, _ = run(capsys, *base, "--drive-loop", m.vel_kp, m.current_lag_s, m.loop_period_s)
    looped = json.loads(out)
    assert code == code2 == 0
    assert abs(looped["Kt"] / m.Kt - 1) < 2e-4, looped["Kt"] / m.Kt - 1
    assert plain["Kt"] / m.Kt - 1 < -5e-4, plain["Kt"] / m.Kt - 1


def _joint_csv(path, scale=1.0):
    """A simulated robot shoulder (second joint simulator, 100 Hz, joint angle) as a
    user's CSV, the angle multiplied by ``scale`` (180/π: degrees)."""
    from gearbench.benchmarks._joint_stick_sim import STICK_JOINTS, simulate_stick_joint
    joint = STICK_JOINTS[1]
    d = simulate_stick_joint(joint, motion="sine", seed=3, rate_hz=100)
    Trace(d["time_s"], {"position_rad": d["position_rad"] * scale,
                        "current_a": d["current_a"]}).write(path)
    return joint


def test_identify_with_a_torque_constant_reports_inertia_and_friction_in_si(capsys, tmp_path):
    """--torque-constant k: J, D, Tc = k x the torque side's per-ampere coefficients, the
    same 95 % half-widths (form spread included in both), and near the joint's truth."""
    p = tmp_path / "shoulder.csv"
    joint = _joint_csv(p)
    code, out, _ = run(capsys, "identify", p, "--load-angle", "1", "--torque-constant",
                       joint.gain_nm_a, "--json")
    assert code == 0
    d = json.loads(out)
    ph, pa = d["physical"], d["per_ampere"]
    from gearbench.analysis.uncertainty import coverage_factor
    t = coverage_factor(d["dof"])
    for name, key in (("J", "J/Kt"), ("D", "D/Kt"), ("Tc", "Tc/Kt")):
        assert ph[name]["value"] == pytest.approx(joint.gain_nm_a * pa[key][0], rel=1e-9)
        assert ph[name]["half_width_95"] == pytest.approx(t * joint.gain_nm_a * pa[key][1], rel=1e-6)
    # the form spread is in both (without it J's interval was 2.4x narrower here)
    assert d["form_spread"]["difference"]
    for name, truth in (("J", joint.J), ("D", joint.Fv), ("Tc", joint.Fc)):
        assert ph[name]["value"] == pytest.approx(truth, rel=0.05)
    assert ph["J"]["unit"] == "kg m^2" and ph["Tc"]["unit"] == "N m"
    code, text, _ = run(capsys, "identify", p, "--load-angle", "1", "--torque-constant", "60")
    assert code == 0 and "with 60 N m/A (taken as exact): J " in text


def test_identify_reads_an_angle_in_degrees_as_stated(capsys, tmp_path):
    """--position-unit deg fits the same model as the same run in radians; unstated,
    the degrees would be taken for radians and every rate come out 57x off."""
    rad, deg = tmp_path / "rad.csv", tmp_path / "deg.csv"
    _joint_csv(rad)
    _joint_csv(deg, 180 / np.pi)
    _, a, _ = run(capsys, "identify", rad, "--load-angle", "1", "--json")
    code, b, _ = run(capsys, "identify", deg, "--load-angle", "1", "--position-unit", "deg", "--json")
    assert code == 0
    a, b = json.loads(a), json.loads(b)
    assert b["position_unit"] == "deg"
    assert set(b["params"]) == set(a["params"])
    for name, v in a["params"].items():
        assert b["params"][name] == pytest.approx(v, rel=1e-6, abs=1e-9), name
    _, c, _ = run(capsys, "identify", deg, "--load-angle", "1", "--json", "--no-check")
    assert json.loads(c)["b2"] == pytest.approx(a["b2"] * 180 / np.pi, rel=0.05)


def test_identify_unit_options_bad_input(capsys, tmp_path):
    p = tmp_path / "rad.csv"
    _joint_csv(p)
    bad(capsys, "identify", p, "--torque-constant", "0", must=("--torque-constant", "positive"))
    bad(capsys, "identify", p, "--torque-constant", "60", "--method", "paper",
        must=("--torque-constant", "paper"))
    bad(capsys, "identify", p, "--travel-per-rev", "5", must=("--travel-per-rev", "linear axis"))
    bad(capsys, "identify", p, "--position-unit", "mm", "--travel-per-rev", "-1",
        must=("--travel-per-rev", "positive"))
