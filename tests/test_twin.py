"""The digital twin (gearbench.twin): replay, gap, fit, effect chain, twin file.

Fast tests build a short recorded run in-process (the sequencer's step names, a
multisine calibration with and without a disk, an efficiency staircase) on a hidden
plant; the slow test replays a real ``gearbench run --sim`` recording."""
from __future__ import annotations

import copy
import math
import subprocess
import sys

import numpy as np
import pytest
import yaml
from pathlib import Path

from gearbench.errors import GearbenchError, ProfileError
from gearbench.sim import PlantParams
from gearbench.trace import Trace
from gearbench.twin import fit as F
from gearbench.twin.block import load_twin_block
from gearbench.twin.gap import gap_table, noise_floors, total_gap
from gearbench.twin.replay import Quanta, Segment, replay, simulated_trace

DISK = 2.0e-5
BLOCK = {"seed": 3,
         "motors": {"in": {"Kt": 0.0527, "J": 1.5e-5, "D": 2.0e-6, "Tc": 0.008, "cog_amp": 0.0},
                    "out": {"Kt": 0.0512, "J": 1.45e-5, "D": 2.2e-6, "Tc": 0.009, "cog_amp": 0.0}},
         "ratio": 10.0, "eta_mesh": 0.9, "drag_torque_nm": 0.015, "drag_viscous": 2.0e-5}
Q = Quanta(velocity_rad_s={"in": 2 * math.pi / 1e4, "out": 2 * math.pi / 1e4},
           torque_a={"in": 1.5e-3, "out": 1.5e-3}, current_a={"in": 1.5e-3, "out": 1.5e-3})


def _multisine(n, period_s=1e-3):
    t = np.arange(n) * period_s
    fade = np.clip(t / 0.1, 0, 1)
    return fade * (120 + sum(25 * np.sin(2 * np.pi * f * t + f) for f in (2, 3, 5, 7)))


def _segments(n_cal=1200, n_eff=2000):
    """Commands-only segments in the sequencer's order and names."""
    segs, k = [], 1
    ms = _multisine(n_cal)
    for name, coupling, disks, modes, cin, cout in (
            ("calibrate-in.out-unloaded", "none", {}, {"in": "velocity", "out": "velocity"}, ms, ms),
            ("calibrate-in-disk_a", "none", {"in": DISK}, {"in": "velocity", "out": "off"}, ms, 0 * ms),
            ("calibrate-out-disk_a", "none", {"out": DISK}, {"in": "off", "out": "velocity"}, 0 * ms, ms),
            ("efficiency-0", "reducer", {}, {"in": "velocity", "out": "torque"},
             np.minimum(np.arange(n_eff) * 2.0, 200.0),
             np.repeat([0.0, -0.5, -1.0, -1.5], n_eff // 4))):
        n = len(cin)
        tr = Trace(np.arange(k, k + n) * 1e-3, {"sample": np.arange(k, k + n), "in.command": cin,
                                               "out.command": cout}, {}, name)
        segs.append(Segment(name, coupling, disks, modes, tr, k, k + n - 1))
        k += n
    return segs


def _record(block, segs):
    """The run a bench with ``block`` records for these commands (noise on)."""
    rows = replay(PlantParams.from_dict(block), segs, noise=True, quanta=Q)
    out = []
    for s in segs:
        tr = simulated_trace(rows[s.name], s, quanta=Q)
        out.append(Segment(s.name, s.coupling, s.disks_kgm2, s.modes, tr, s.first_sample, s.last_sample))
    return out


def test_replay_of_the_same_plant_is_at_the_noise_floor():
    rec = _record(BLOCK, _segments())
    floors = noise_floors(rec)
    rows = replay(PlantParams.from_dict(BLOCK), rec, quanta=Q)
    table = gap_table(rows, rec, floors)
    for r in table:
        if r["signal"] in ("position_rad", "velocity_rad_s"):
            assert r["gap"] < 1e-6, r          # deterministic: the same counts
        else:
            assert 0.5 < r["gap"] < 1.3, r     # only the sensor's noise is left
    # the noise floor of the current is the sensor's 4 mA (estimated from the data)
    assert floors[("in", "current_a")] == pytest.approx(0.004, rel=0.3)


def test_gap_names_where_a_wrong_ratio_shows():
    rec = _record(BLOCK, _segments())
    floors = noise_floors(rec)
    wrong = copy.deepcopy(BLOCK)
    wrong["ratio"] = 10.5
    table = gap_table(replay(PlantParams.from_dict(wrong), rec, quanta=Q), rec, floors)
    by = {(r["step"], r["axis"], r["signal"]): r for r in table}
    assert by[("efficiency-0", "out", "velocity_rad_s")]["gap"] > 3
    assert by[("efficiency-0", "out", "position_rad")]["gap"] > 100   # the angle accumulates it
    assert by[("calibrate-in-disk_a", "in", "current_a")]["gap"] < 1.3   # calibration unaffected
    assert by[("efficiency-0", "out", "velocity_rad_s")]["where"]["speed"]


def test_fit_recovers_moved_parameters_within_intervals():
    hidden = copy.deepcopy(BLOCK)
    hidden["motors"]["in"]["Kt"] *= 0.95
    hidden["motors"]["out"]["Tc"] *= 1.3
    hidden["eta_mesh"] = 0.86
    rec = _record(hidden, _segments())
    prob = F.Problem(rec, copy.deepcopy(BLOCK), Q)
    params = [p for p in F.base_params(BLOCK)
              if p.path in ("motors.in.Kt", "motors.in.J", "motors.in.Tc", "motors.out.Kt",
                            "motors.out.J", "motors.out.Tc", "eta_mesh", "drag_torque_nm")]
    res = F.fit(prob, params, iterations=8)
    assert res["S"] < 0.2 * res["S0"]
    got = F.written_values(params)
    for path in ("motors.in.Kt", "motors.out.Tc", "eta_mesh"):
        truth = F.get_value(hidden, path)
        p = next(p for p in params if p.path == path)
        # within the interval itself, and the interval not absurdly wide (under 5 % of the value)
        assert abs(got[path] - truth) <= p.interval < 0.05 * abs(truth), (path, got[path], truth, p.interval)
        # the interval is 1.96·sigma plus the model-error share, both reported
        assert p.interval == pytest.approx(1.96 * p.sigma + abs(p.model_bias))
        assert p.sigma > 0


def test_intervals_take_the_widest_covariance_and_add_the_model_bias():
    """A residual made of a slow wave (coloured, as a model's misfit is) is not
    averaged down as white noise would be: its block sandwich is wider than the
    white-noise interval, and a difference between the exact and smoothed replay's
    residuals along a parameter's column shows as that parameter's model bias."""
    rec = _record(BLOCK, _segments(n_cal=600, n_eff=800))
    prob = F.Problem(rec, copy.deepcopy(BLOCK), Q)
    n = len(prob.blocks())
    t = np.arange(n)
    J = np.stack([np.ones(n), np.sin(t / 400.0)], axis=1)
    params = [F.Param("a", 1.0, 1.0), F.Param("b", 1.0, 1.0)]
    sel = np.ones(n, bool)
    white = np.random.default_rng(1).normal(size=n)
    F.lm._intervals(prob, params, J, white, white, sel)
    iid = [p.interval for p in params]
    assert all(abs(p.model_bias) < 1e-12 for p in params)
    slow = 3 * np.sign(np.sin(t / 150.0)) + white     # coloured over hundreds of samples
    F.lm._intervals(prob, params, J, slow, slow + 0.5, sel)
    assert params[0].interval > 1.5 * iid[0]
    # exact − smooth = 0.5 everywhere = the constant column's direction: a's bias is −0.5
    assert params[0].model_bias == pytest.approx(-0.5, abs=1e-9)
    assert params[1].model_bias == pytest.approx(0.0, abs=1e-9)


def test_second_unit_differs_by_its_spread_not_by_the_seed():
    from gearbench.twin.hidden import HIDDEN, UNIT2, hidden_block, second_unit

    defaults = lambda path: F.get_value({}, path)  # noqa: E731
    first, _ = hidden_block(copy.deepcopy(BLOCK) | {"backlash_rad": 0.0}, HIDDEN["cyclo"], defaults)
    second, truth = second_unit(first, UNIT2["cyclo"], defaults)
    for path, f in UNIT2["cyclo"].items():
        a, b = F.get_value(first, path), F.get_value(second, path)
        assert b == pytest.approx(a * f) and truth[path] == pytest.approx(b)
        assert 0.8 < f < 1.2 and f != 1.0          # a spread of a few %, not another bench
    assert second["seed"] == first["seed"]          # the seed is the benchmark's to set


def test_random_hidden_benches_are_valid_draws_of_their_family():
    import yaml

    from gearbench.benchmarks.twin import ROOT, _defaults
    from gearbench.sim import PlantParams
    from gearbench.twin.hidden import RANDOM_MOVED, RANDOM_PARAMS, RANDOM_REDUCER, hidden_block, random_spec

    for case in ("cvt", "cyclo"):
        block = yaml.safe_load((ROOT / "profiles" / f"{case}.yaml").read_text())["simulation"]
        defaults = _defaults(block)
        assert random_spec(case, block, 3, defaults) == random_spec(case, block, 3, defaults)
        assert random_spec(case, block, 3, defaults) != random_spec(case, block, 4, defaults)
        pool = RANDOM_PARAMS | RANDOM_REDUCER["cvt" if case == "cvt" else "plain"]
        for seed in range(40):
            spec = random_spec(case, block, seed, defaults)
            assert len(spec["params"]) == RANDOM_MOVED and len(spec["effects"]) == 2
            assert case == "cyclo" or "backlash" not in spec["effects"]   # no CVT backlash in the sim
            hidden, truth = hidden_block(block, spec, defaults)
            PlantParams.from_dict(hidden)                                  # a bench the sim accepts
            for path, (op, v) in spec["params"].items():
                lo, hi = pool[path]
                rel = abs(truth[path] / defaults(path) - 1)
                assert op == "=" or lo - 1e-12 <= rel <= hi + 1e-12, (path, rel)
                assert op == "*" or truth[path] <= 0.97                    # an efficiency stays one
            sat = [(k, v) for e in spec["effects"].values() for k, v in e.items() if k.endswith("kt_sat_a")]
            for k, s_a in sat:   # Kt at the current limit lowered by 5-30 %
                lim = defaults(k.replace("kt_sat_a", "current_limit_a"))
                assert 0.05 - 1e-9 <= 1 - 1 / (1 + (lim / s_a) ** 2) <= 0.30 + 1e-9


def test_direction_friction_on_a_one_way_motor_is_scored_as_the_run_shows_it(tmp_path):
    import pandas as pd

    from gearbench.benchmarks.twin import _as_the_run_shows

    v = np.full(1000, 50.0)
    v[:10] = -50.0                                       # 1 % backwards: one way
    pd.DataFrame({"out.velocity_rad_s": v, "in.velocity_rad_s": np.sin(np.arange(1000) / 50.0) * 10}
                 ).to_parquet(tmp_path / "trace-a.parquet")
    truth = {"motors.out.Tc": 0.009, "motors.out.Tc_asym": -0.002, "motors.in.Tc": 0.008, "motors.in.Tc_asym": 0.001}
    spec = {"effects": {"direction_friction": {"motors.out.Tc_asym": -0.002}}}
    tv, unseen = _as_the_run_shows(tmp_path, spec, truth.get)
    assert tv("motors.out.Tc") == pytest.approx(0.007) and tv("motors.out.Tc_asym") is None
    assert "forward only" in unseen["direction_friction"]
    spec = {"effects": {"direction_friction": {"motors.in.Tc_asym": 0.001}}}   # reverses: identifiable
    tv, unseen = _as_the_run_shows(tmp_path, spec, truth.get)
    assert not unseen and tv("motors.in.Tc") == 0.008


def test_the_held_out_fold_holds_steps_starts_too():
    """Each step starts from rest in its first block; the folds put each motor's starts on
    both sides, so an effect of the starts (Stribeck) can gain on the held-out fold."""
    prob = F.Problem(_record(BLOCK, _segments(n_cal=600, n_eff=800)), copy.deepcopy(BLOCK), Q)
    fit_fold, held = F.folds(prob)
    b = prob.blocks()
    assert fit_fold.sum() and held.sum() and not (fit_fold & held).any()
    # steps: both motors, in alone, out alone, both: each motor starts twice, once per fold
    first = [bool(fit_fold[b == k * 100000].all()) for k in range(len(prob.segments))]
    assert first == [True, False, False, True]
    assert all(held[b == k * 100000 + 1].all() == first[k] for k in range(len(prob.segments)))


def test_a_motor_turned_one_way_has_no_direction_friction_to_fit():
    rec = _record(BLOCK, _segments(n_cal=600, n_eff=800))     # every command forward
    prob = F.Problem(rec, copy.deepcopy(BLOCK), Q)
    assert prob.turning() == {"in": "forward", "out": "forward"}
    assert [w.split(":")[0] for w in prob.not_identifiable()] == [
        "direction-dependent friction of motor in", "direction-dependent friction of motor out"]
    names = {(n, ps[0].path if ps else "") for n, ps, _ in F.candidates(BLOCK, {}, turning=prob.turning())}
    assert not any(n == "direction_friction" for n, _ in names)
    segs = _segments(n_cal=600, n_eff=800)
    for sg in segs[:3]:                                        # calibrations swing through zero
        for a in ("in", "out"):
            c = np.asarray(sg.trace[f"{a}.command"], float)
            sg.trace.columns[f"{a}.command"] = np.where(c != 0, c - 120.0, 0.0)
    prob = F.Problem(_record(BLOCK, segs), copy.deepcopy(BLOCK), Q)
    assert prob.turning() == {"in": "both", "out": "both"} and prob.not_identifiable() == []
    paths = [ps[0].path for n, ps, _ in F.candidates(BLOCK, {}, turning=prob.turning()) if n == "direction_friction"]
    assert paths == ["motors.in.Tc_asym", "motors.out.Tc_asym"]


def test_effect_chain_names_a_current_offset():
    hidden = copy.deepcopy(BLOCK)
    hidden["motors"]["in"]["current_offset_a"] = 0.03
    rec = _record(hidden, _segments(n_cal=800, n_eff=1200))
    prob = F.Problem(rec, copy.deepcopy(BLOCK), Q)
    params = [p for p in F.base_params(BLOCK)
              if p.path in ("motors.in.Kt", "motors.in.Tc", "motors.out.Kt", "eta_mesh")]
    F.fit(prob, params, iterations=3)
    chain = F.add_effects(prob, params, max_effects=1)
    assert chain and chain[0]["effect"] == "current_offset" and chain[0]["significant"]
    assert chain[0]["values"]["motors.in.current_offset_a"] == pytest.approx(0.03, abs=0.005)


def test_twin_file_errors_name_the_file(tmp_path):
    bad = tmp_path / "twin.yaml"
    bad.write_text("simulation: {ratio: -2}\n")
    with pytest.raises(ProfileError, match="twin.yaml: simulation.ratio"):
        load_twin_block(str(bad))
    bad.write_text("motors: {}\n")
    with pytest.raises(ProfileError, match="expected a 'simulation:'"):
        load_twin_block(str(bad))
    with pytest.raises(GearbenchError, match="cannot read"):
        load_twin_block(str(tmp_path / "missing.yaml"))
    good = tmp_path / "ok.yaml"
    good.write_text(yaml.safe_dump({"simulation": BLOCK}))
    assert load_twin_block(str(good))["ratio"] == 10.0


def test_another_benchs_twin_is_refused_naming_the_twin(tmp_path):
    """A twin fitted on another bench (here cyclo's output motor, rated 3 A) used with cvt's
    profile (rated 1.5 A): the twin file is named, not the profile blamed by the drive's check."""
    prof = yaml.safe_load(Path("profiles/cyclo.yaml").read_text())
    twin = tmp_path / "twin-cyclo.yaml"
    twin.write_text(yaml.safe_dump({"simulation": prof["simulation"]}))
    cvt_rated = yaml.safe_load(Path("profiles/cvt.yaml").read_text())["motors"]["out"]["rated_current_a"]
    assert prof["simulation"]["motors"]["out"].get("rated_current_a", prof["motors"]["out"]["rated_current_a"]) != cvt_rated
    r = subprocess.run([sys.executable, "-m", "gearbench", "validate", "profiles/cvt.yaml", "--twin", str(twin)],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "twin-cyclo.yaml: motors.out.rated_current_a" in r.stderr and "another bench" in r.stderr


def test_cli_twin_on_a_folder_without_a_run_exits_2(tmp_path):
    r = subprocess.run([sys.executable, "-m", "gearbench", "twin", str(tmp_path)], capture_output=True, text=True)
    assert r.returncode == 2 and "no result.json" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.slow
def test_replay_of_an_emulated_run_is_exact(tmp_path):
    """The replay is the emulator's model: a --sim run replayed on its own plant, seed and
    noise gives the recorded counts and currents to the drive's units."""
    from gearbench.commands.twin import drive_quanta, load_run
    from gearbench.twin.replay import measured, plan_segments, simulated

    out = tmp_path / "run"
    subprocess.run([sys.executable, "-m", "gearbench", "run", "profiles/cvt.yaml", "--sim", "--yes",
                    "--quiet", "--out", str(out)], check=True)
    result, traces, prof, _ = load_run(str(out), None)
    segs = plan_segments(traces, prof)
    q = drive_quanta(prof)
    rows = replay(PlantParams.from_dict(prof.simulation), segs, noise=True, quanta=q)
    for s in segs:
        for a in ("in", "out"):
            assert np.max(np.abs(measured(s, a, "position_rad") - simulated(rows[s.name], s, a, "position_rad"))) < 1e-9
            i = np.round(simulated(rows[s.name], s, a, "current_a") / q.current_a[a]) * q.current_a[a]
            assert np.sqrt(np.mean((measured(s, a, "current_a") - i) ** 2)) < q.current_a[a]
    # noise-free: the angles exact, the velocity to the drive's reporting unit (inc/s)
    assert total_gap(replay(PlantParams.from_dict(prof.simulation), segs, quanta=q), segs,
                     noise_floors(segs), ("position_rad", "velocity_rad_s")) < 0.01


def test_step_names_give_mounting_and_modes():
    from gearbench.twin.replay import _calibration_mount

    disks = {"disk_a": 2e-5, "disk_b": 3e-5}
    assert _calibration_mount("calibrate-in.out-unloaded", disks, {"in", "out"}) == (["in", "out"], {})
    assert _calibration_mount("calibrate-out-disk_a", disks, {"in", "out"}) == (["out"], {"out": 2e-5})
    assert _calibration_mount("calibrate-in.out-disk_a.disk_b", disks, {"in", "out"}) == \
        (["in", "out"], {"in": 2e-5, "out": 3e-5})
    with pytest.raises(Exception, match="cannot tell"):
        _calibration_mount("calibrate-in-unknown_disk", disks, {"in", "out"})


def test_proof_names_what_the_twin_misses():
    from gearbench.commands.twin import _verdict

    real = {"motors": {"in": {"Kt": 0.05, "Kt_ci95": [0.0499, 0.0501]}}, "efficiency": [
        {"speed_in_rad_s": 100, "torque_out_nm": 0.04, "eta_incremental": 0.7, "eta_incremental_ci95": [0.69, 0.71],
         "eta_absolute": 0.3, "eta_absolute_ci95": [0.29, 0.31]}],
        "limits": [{"name": "kt_in", "passed": True}]}
    twin = copy.deepcopy(real)
    assert _verdict({"real": real, "twin": twin}, []) == []
    twin["motors"]["in"]["Kt"] = 0.0503
    twin["efficiency"][0]["eta_incremental"] = 0.72
    twin["limits"][0]["passed"] = False
    assert _verdict({"real": real, "twin": twin}, []) == [
        "Kt in", "eta_incremental at 100 rad/s, 0.040 N m", "limit kt_in verdict"]


def test_a_gap_of_structure_is_said_to_limit_the_intervals():
    assert F.model_limited(1.0) == "" and F.model_limited(F.MODEL_LIMITED_S_N) == ""
    note = F.model_limited(180.0)
    assert "S/n 180" in note and "understate" in note


@pytest.mark.slow
def test_cli_twin_on_a_sim_run_gives_the_proof(tmp_path):
    """The whole command on a recorded --sim run (one iteration, no effects): the proof
    re-analyses both runs (its import had moved once, unnoticed) and the JSON holds the
    parameters with their sigma, model bias and interval."""
    import json

    out = tmp_path / "run"
    subprocess.run([sys.executable, "-m", "gearbench", "run", "profiles/cvt.yaml", "--sim", "--yes",
                    "--quiet", "--out", str(out)], check=True)
    rep = tmp_path / "twin.json"
    r = subprocess.run([sys.executable, "-m", "gearbench", "twin", str(out), "--iterations", "1",
                        "--max-effects", "0", "--json", str(rep), "--write", str(tmp_path / "twin.yaml")],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    doc = json.loads(rep.read_text())
    assert doc["proof"]["real"]["motors"] and doc["proof"]["twin"]["motors"]
    for p in doc["parameters"]:
        # (+ the angles' resolution for the ratio: one output count over the travel)
        assert p["interval95"] == pytest.approx(1.96 * p["sigma"] + abs(p["model_bias"]) + p["resolution"])
        assert (p["resolution"] > 0) == (p["path"] == "ratio")
    assert "interval = 1.96·sigma" in r.stdout
    load_twin_block(str(tmp_path / "twin.yaml"))

    # What the twin is for: validate predicts a profile's run on it, and run --sim --twin
    # runs on it — a twin whose input motor has 5 % more Kt gives that Kt back.
    v = subprocess.run([sys.executable, "-m", "gearbench", "validate", "profiles/cvt.yaml", "--twin",
                        str(tmp_path / "twin.yaml")], capture_output=True, text=True)
    assert v.returncode == 0, v.stderr[-2000:]
    assert "predicted verdict PASSED" in v.stdout and "twin       Kt in " in v.stdout
    block = yaml.safe_load((tmp_path / "twin.yaml").read_text())
    kt_in = block["simulation"]["motors"]["in"]["Kt"] * 1.05
    block["simulation"]["motors"]["in"]["Kt"] = kt_in
    (tmp_path / "moved.yaml").write_text(yaml.safe_dump(block))
    moved = tmp_path / "moved"
    subprocess.run([sys.executable, "-m", "gearbench", "run", "profiles/cvt.yaml", "--sim", "--twin",
                    str(tmp_path / "moved.yaml"), "--yes", "--quiet", "--out", str(moved)], check=True)
    kt = json.loads((moved / "result.json").read_text())["motors"]["in"]["Kt"]
    assert kt == pytest.approx(kt_in, rel=2e-3)


def test_broyden_update_meets_the_secant_and_keeps_other_directions():
    """Broyden's update (Broyden 1965) makes the carried Jacobian reproduce the step just
    taken (J_new·Δu = Δr) and leaves directions orthogonal to the step (in the parameters'
    scales) unchanged: the fit's cheap iterations between fresh Jacobians."""
    rng = np.random.default_rng(0)
    J = rng.normal(size=(50, 3))
    sc = np.array([1e-5, 1.0, 1e3])           # SI scales apart by 10⁸, as Kt/J or D
    step = np.array([2e-7, 0.0, 0.0])
    dr = rng.normal(size=50)
    Jn = F.lm._broyden(J, sc, step, dr)
    assert np.allclose(Jn @ step, dr)
    assert np.allclose(Jn[:, 1:], J[:, 1:])     # the other parameters' columns untouched


def test_fit_stops_once_an_iteration_moves_nothing_the_intervals_can_tell():
    """From the truth the first iteration moves every parameter by a fraction of its
    interval, and the fit stops there instead of running its iteration budget."""
    rec = _record(BLOCK, _segments(n_cal=600, n_eff=800))
    prob = F.Problem(rec, copy.deepcopy(BLOCK), Q)
    params = [p for p in F.base_params(BLOCK) if p.path in ("motors.in.Kt", "motors.in.Tc", "eta_mesh")]
    res = F.fit(prob, params, iterations=8)
    assert res["iterations"] <= 2
    # one replay for the start, a Jacobian (3) and a few steps per iteration, the final Jacobian
    # and the exact replay of the interval: far under 8 iterations' worth (8 x 4 = 32)
    assert prob.evaluations < 22


def test_a_saturation_near_the_peak_current_is_found_from_its_scan():
    """Kt_eff = Kt/(1+(i/s)²) with s at the run's peak current: from "off" a Gauss-Newton
    step sees only its first-order, flat start; the scan of s over multiples of the
    peak current puts the screen in the right basin and the chain names it."""
    segs = _segments(n_cal=800, n_eff=1200)
    probe = _record(BLOCK, segs)
    peak = F.Problem(probe, copy.deepcopy(BLOCK), Q).peak_currents()["in"]
    hidden = copy.deepcopy(BLOCK)
    hidden["motors"]["in"]["kt_sat_a"] = round(0.8 * peak, 3)
    rec = _record(hidden, segs)
    prob = F.Problem(rec, copy.deepcopy(BLOCK), Q)
    params = [p for p in F.base_params(BLOCK)
              if p.path in ("motors.in.Kt", "motors.in.Tc", "motors.out.Kt", "eta_mesh")]
    F.fit(prob, params, iterations=3)
    chain = F.add_effects(prob, params, max_effects=1)
    assert chain[0]["effect"] == "kt_saturation" and chain[0]["significant"], chain
    got = chain[0]["values"]["motors.in.kt_sat_a"]
    assert got == pytest.approx(hidden["motors"]["in"]["kt_sat_a"], rel=0.25)


def test_the_profile_interval_of_a_backlash_holds_its_truth():
    """The backlash's interval comes from the profile of S (others linearised), not its
    Jacobian column; started off the truth, its minimum moves to it."""
    hidden = copy.deepcopy(BLOCK) | {"backlash_rad": 0.02}
    segs = _segments(n_cal=300, n_eff=1600)
    rec = _record(hidden, segs)
    prob = F.Problem(rec, copy.deepcopy(BLOCK) | {"backlash_rad": 0.014}, Q)
    params = [p for p in F.base_params(BLOCK) if p.path in ("motors.in.Kt", "ratio", "eta_mesh")]
    params.append(F.Param("backlash_rad", 0.014, 0.005, 1e-5, fd_factor=40.0, profile=True))
    res = F.fit(prob, params, iterations=2)
    before = {p.path: p.interval for p in params}
    prof = F.apply_profiles(prob, params, res["jac"], res["r"])
    assert prof and prof[0]["path"] == "backlash_rad"
    bl = params[-1]
    # the profile's interval, centred on its minimum: widened by how far the value stayed from it
    assert prof[0]["off_minimum"] == pytest.approx(abs(bl.value - prof[0]["written"]))
    assert bl.interval == pytest.approx(prof[0]["interval"] + prof[0]["off_minimum"])
    assert abs(bl.value - 0.02) <= bl.interval < 0.02, (bl.value, bl.interval)
    # the ratio follows the gap along its profile: its interval carries the gap's uncertainty
    # (it held the gap fixed before); none is narrowed
    after = {p.path: p.interval for p in params}
    assert after["ratio"] > 1.5 * before["ratio"], (before, after)
    assert all(after[k] >= before[k] for k in before if k != "backlash_rad"), (before, after)


def test_ripple_and_cogging_of_one_order_are_said_ambiguous_when_collinear():
    block = copy.deepcopy(BLOCK)
    block["motors"]["in"]["cog_amp"] = 0.002
    params = [F.Param("motors.in.cog_amp", 0.002, 0.002), F.Param("motors.in.ripple_amp", 0.0, 0.01)]
    rng = np.random.default_rng(0)
    a = rng.normal(size=500)
    same = np.stack([a, -2 * a], axis=1)
    note = F.ripple_cogging_ambiguity(params[:1], same, params[1], {"motors.in.ripple_order": 6}, block)
    assert "not separable" in note and "two loads" in note
    apart = np.stack([a, rng.normal(size=500)], axis=1)
    assert F.ripple_cogging_ambiguity(params[:1], apart, params[1], {"motors.in.ripple_order": 6}, block) == ""
    # another order than the cogging's is never ambiguous with it
    assert F.ripple_cogging_ambiguity(params[:1], same, params[1], {"motors.in.ripple_order": 4}, block) == ""


def test_the_ratio_interval_is_no_finer_than_one_output_count_over_the_travel():
    rec = _record(BLOCK, _segments(n_cal=300, n_eff=1200))
    prob = F.Problem(rec, copy.deepcopy(BLOCK), Q)
    travel = float(np.sum(np.abs(np.diff(np.asarray(rec[-1].trace["out.position_rad"], float)))))
    assert prob.ratio_resolution() == pytest.approx(2 * math.pi / 1e4 / travel, rel=0.01)
    params = [F.Param("ratio", 10.0, 10.0)]
    n = len(prob.blocks())
    F.lm._intervals(prob, params, np.ones((n, 1)) * 1e6, np.zeros(n), np.zeros(n), np.ones(n, bool))
    assert params[0].interval == pytest.approx(10.0 * prob.ratio_resolution()) == pytest.approx(params[0].resolution)


def test_an_output_ripple_seen_only_through_the_input_current_is_screened_first():
    """The output motor torque-controlled in the efficiency map: its ripple shows in the
    input drive's current (which holds the speed), not in its own. Every order is screened
    by a linearised held-out step; the hidden order comes first (the own-current ranking
    had no trace of it)."""
    segs = [s for s in _segments(n_cal=300, n_eff=3000) if s.kind == "efficiency"]
    hidden = copy.deepcopy(BLOCK)
    hidden["motors"]["out"] |= {"ripple_amp": 0.04, "ripple_order": 5}
    rec = _record(hidden, segs)
    prob = F.Problem(rec, copy.deepcopy(BLOCK), Q)
    r = prob.residual_vector(prob.block)
    fit_fold, held = F.folds(prob)
    orders = F.residual_orders(prob, r, fit_fold, held)
    assert orders["out"][0] == 5, orders


def test_a_replay_of_the_same_plant_is_not_repeated():
    prob = F.Problem(_record(BLOCK, _segments(n_cal=300, n_eff=400)), copy.deepcopy(BLOCK), Q)
    r1 = prob.residual_vector(prob.block)
    off = copy.deepcopy(BLOCK)
    off["motors"]["out"] |= {"ripple_amp": 0.0, "ripple_order": 4}   # an effect at "off": the same replay
    r2 = prob.residual_vector(off)
    assert prob.evaluations == 1 and r2 is r1 and not r1.flags.writeable
    on = copy.deepcopy(off)
    on["motors"]["out"]["ripple_amp"] = 0.01
    assert not np.array_equal(prob.residual_vector(on), r1) and prob.evaluations == 2
    assert prob.residual_vector(BLOCK, smooth=False) is not r1 and prob.evaluations == 3


def test_a_refit_on_a_retargeted_run_recovers_the_replay_that_made_its_data():
    """``Problem.retargeted``: the data replaced by a noise-free replay; the smoothed fit
    on it from a moved start comes back to that replay's parameters up to the smoothing's
    own bias (what ``smoothing_shift`` measures), far inside the move."""
    rec = _record(BLOCK, _segments(n_cal=600, n_eff=800))
    prob = F.Problem(rec, copy.deepcopy(BLOCK), Q)
    params = [p for p in F.base_params(BLOCK) if p.path in ("motors.in.Kt", "motors.out.Tc", "eta_mesh")]
    target = F.with_params(BLOCK, params)
    r_exact = prob.residual_vector(target, smooth=False)
    sub = prob.retargeted(r_exact)
    assert np.max(np.abs(sub.residual_vector(target, smooth=False))) == 0.0
    assert prob.residual_vector(target, smooth=False) is r_exact     # the cache is untouched
    u0 = np.array([p.value for p in params])
    for p, f in zip(params, (1.03, 0.9, 1.02)):
        p.value *= f
    F.fit(sub, params, iterations=6, intervals=False)
    u = np.array([p.value for p in params])
    assert np.all(np.abs(u / u0 - 1) < np.array([0.03, 0.1, 0.02]) / 4), u / u0 - 1


def test_the_smoothing_shift_is_taken_off_the_value_and_kept_as_the_model_bias(monkeypatch):
    """The mean of the points' shifts is taken off; their spread (× √(1 + 1/points)) joins σ
    in quadrature; b is the larger of the mean shift and the earlier estimate."""
    params = [F.Param("a", 2.0, 1.0), F.Param("b", 5.0, 1.0)]
    for p in params:
        p.sigma, p.model_bias = 0.1, -0.1
    shifts = np.array([[0.2, -0.05], [0.4, -0.05], [0.0, -0.05]])
    monkeypatch.setattr(F.smoothness, "smoothing_shift", lambda prob, ps: shifts)
    F.correct_smoothing_shift(None, params)
    assert [p.value for p in params] == pytest.approx([1.8, 5.05])
    assert [p.model_bias for p in params] == pytest.approx([0.2, -0.1])
    spread = 0.2 * np.sqrt(1 + 1 / 3)
    assert [p.shift_sigma for p in params] == pytest.approx([spread, 0.0])
    sig = np.sqrt(0.1 ** 2 + spread ** 2)
    assert [p.sigma for p in params] == pytest.approx([sig, 0.1])
    assert [p.interval for p in params] == pytest.approx([1.96 * sig + 0.2, 1.96 * 0.1 + 0.1])


def test_the_smoothing_shifts_draws_on_the_carried_jacobian_match_a_converged_refit():
    """``smoothing_shift``: the fitted values' row is the converged refit's shift; at a point
    a σ away (where the draws are) the cheap path (the first refit's Jacobian carried, no
    fresh one) measures the shift a refit on fresh Jacobians measures there, to within σ
    (0.1-0.5 σ on this run: two paths to a minimum of a jagged S). The shift itself differs
    far more from point to point (this run's out.Tc: +8 σ at the fitted values, −4 … −6 σ at
    the draws): what its spread is for."""
    rec = _record(BLOCK, _segments(n_cal=600, n_eff=800))
    prob = F.Problem(rec, copy.deepcopy(BLOCK), Q)
    params = [p for p in F.base_params(BLOCK) if p.path in ("motors.in.Kt", "motors.out.Tc", "eta_mesh")]
    F.fit(prob, params, iterations=6)
    rows = F.smoothing_shift(prob, params, draws=2)
    assert rows.shape == (3, 3) and np.all(np.isfinite(rows))
    u0 = np.array([p.value for p in params])
    fresh, jac = F.smoothness._shift_at(prob, params, u0, None)
    assert np.array_equal(rows[0], fresh)
    sig = np.array([F.smoothness._sigma_value(p, params) for p in params])
    assert np.all(sig > 0)
    uk = F.params._clip(params, u0 + sig * np.array([1.0, -1.0, 0.5]))
    at_uk, _ = F.smoothness._shift_at(prob, params, uk, None)
    carried, _ = F.smoothness._shift_at(prob, params, uk, jac)
    assert np.all(np.abs(carried - at_uk) < sig), (carried - at_uk) / sig
    assert not np.array_equal(rows[1], rows[0]) and not np.array_equal(rows[2], rows[1])


def test_proof_pools_the_twins_noise_draws():
    """The twin's results are the mean of its noise draws, judged within the run's interval
    and the mean's own (√(h² + (1.96·s/√k)²)); a limit's verdict counts when a draw gives it."""
    from gearbench.twin.proof import half_width, pool_draws, understated, verdict_among_draws, within

    def draw(kt, eta, passed):
        return {"status": "passed" if passed else "failed", "ratio": 8.0,
                "motors": {"in": {"Kt": kt, "Kt_ci95": [0.049, 0.051]}},
                "efficiency": [{"speed_in_rad_s": 100, "torque_out_nm": 0.04, "eta_incremental": eta,
                                "eta_incremental_ci95": [eta - 0.05, eta + 0.05], "eta_absolute": None}],
                "limits": [{"name": "eta", "passed": passed}]}
    pooled = pool_draws([draw(0.050, 0.60, True), draw(0.051, 0.70, False), draw(0.049, 0.65, False),
                         draw(0.050, 0.65, False)])
    assert pooled["draws"] == 4 and pooled["status"] == "failed"
    assert pooled["motors"]["in"]["Kt"] == pytest.approx(0.050)
    assert pooled["efficiency"][0]["eta_incremental"] == pytest.approx(0.65)
    sd = pooled["efficiency"][0]["eta_incremental_sd"]
    assert sd == pytest.approx(np.std([0.60, 0.70, 0.65, 0.65], ddof=1))
    assert pooled["efficiency"][0]["eta_absolute"] is None and pooled["efficiency"][0]["eta_absolute_sd"] is None
    assert pooled["limits"][0] == {"name": "eta", "value": None, "passed": False, "passed_draws": 1}
    hw = half_width([0.55, 0.65], sd, 4)
    assert hw == pytest.approx(math.hypot(0.05, 1.96 * sd / 2))
    # one draw 0.70 is outside the run's ±0.05 around 0.60, the draws' mean 0.65 is not
    assert within(0.60, 0.70, [0.55, 0.65]) == "NO"
    assert within(0.60, 0.65, [0.55, 0.65], sd, 4) == "yes"
    assert within(0.60, 0.80, [0.55, 0.65], sd, 4) == "NO" and within(None, 0.6, [0.5, 0.7]) == ""
    assert understated([0.55, 0.65], 0.04) and not understated([0.55, 0.65], 0.02)
    assert verdict_among_draws(True, pooled["limits"][0], 4) and verdict_among_draws(False, pooled["limits"][0], 4)
    assert not verdict_among_draws(True, {"passed": False, "passed_draws": 0}, 4)
    assert not verdict_among_draws(False, {"passed": True}, 1) and not verdict_among_draws(True, {}, 1)


def test_a_profile_vertex_is_taken_only_inside_its_points():
    """``_vertex``: the parabola's minimum where it lies among the profile's points; none
    for a profile that falls all the way (cyclo seed 41's exact backlash profile) or
    has too few points."""
    xs = [0.019, 0.020, 0.021, 0.022, 0.023]
    v, c2, sig = F.profiles._vertex([(x, (x - 0.0205) ** 2 * 1e6 + 3.0) for x in xs], 0.021)
    assert v == pytest.approx(0.0205) and c2 == pytest.approx(1e6) and sig == pytest.approx(0.0, abs=1e-9)
    assert F.profiles._vertex([(x, -x) for x in xs], 0.021) is None                       # no curvature
    assert F.profiles._vertex([(x, (x - 0.03) ** 2) for x in xs], 0.021) is None          # minimum beyond the grid
    assert F.profiles._vertex([(x, x ** 2) for x in xs[:3]], 0.02) is None                # too few points


def test_the_jitter_of_a_profile_moves_its_minimum_by_the_sigma_it_reports():
    """S along a backlash jitters (contact events move by a substep): the vertex's σ from
    the points' scatter about the parabola is the scatter of the vertex over jitter draws
    (the cyclo run: ±40 floors² on a rise of a few hundred over ±2 mrad)."""
    rng = np.random.default_rng(3)
    xs = 0.020 + np.array([-2.0, -1.5, -1.0, -0.5, 0.0, 0.5, 1.0, 1.5, 2.0]) * 1e-3
    draws = [F.profiles._vertex([(x, (x - 0.0203) ** 2 * 2.2e7 + 3.5e5 + rng.normal(0, 40)) for x in xs], 0.020)
             for _ in range(400)]
    draws = [d for d in draws if d is not None]
    assert len(draws) > 350
    spread = np.std([d[0] for d in draws])
    assert 2e-4 < spread < 6e-4          # the jitter moves the minimum by several tenths of a mrad
    assert np.median([d[2] for d in draws]) == pytest.approx(spread, rel=0.3)


class _Rough:
    """A linear problem r = A·u − y plus a jitter of S that neighbouring vectors do not share
    (a replay with contact events): ``settle``'s toy."""

    def __init__(self, jitter: float):
        rng = np.random.default_rng(0)
        self.A, self.y, self.jitter, self.block = rng.normal(size=(200, 2)), rng.normal(size=200), jitter, {}

    def residual_vector(self, block, smooth=None, every_sample=False):
        u = np.array([block["a"], block["b"]])
        bump = np.zeros(200)
        bump[0] = self.jitter * (1.0 + math.sin(1e6 * u.sum()))    # not smooth in u at any scale
        return self.A @ u - self.y + bump

    def blocks(self, span):
        return np.arange(200) // 10


def test_settle_takes_the_linearised_minimum_that_a_rough_S_hid_from_the_fit():
    """LM stalls where S's jitter outweighs what the next step gains; ``settle`` takes the
    undamped Gauss–Newton step when its replay does not rise by more than it promised, else
    widens every interval by the step (the fit is that far from where its interval is drawn)."""
    for jitter, taken in ((0.5, True), (40.0, False)):
        prob = _Rough(jitter)
        params = [F.Param("a", 0.3, 1.0, lo=-10), F.Param("b", -0.2, 1.0, lo=-10)]
        u = np.array([0.3, -0.2])
        r = prob.residual_vector({"a": 0.3, "b": -0.2})
        step = np.linalg.lstsq(prob.A, -r, rcond=None)[0]     # the linearised minimum, from u
        F.settle(prob, params, prob.A, r)
        got = np.array([p.value for p in params])
        if taken:
            assert got == pytest.approx(u + step)
            assert all(p.stall == 0.0 for p in params)
        else:
            assert got == pytest.approx(u)
            assert [p.stall for p in params] == pytest.approx(np.abs(step))
        # the replay's jitter is in σ (in quadrature), the stall added to the interval
        assert all(p.jitter > 0 for p in params)
        bare = copy.deepcopy(params)
        for q in bare:
            q.jitter = 0.0
        F.set_intervals(prob, bare, prob.A, prob.residual_vector({"a": got[0], "b": got[1]}))
        assert [p.sigma for p in params] == pytest.approx(np.hypot([q.sigma for q in bare],
                                                                   [p.jitter for p in params]))
        assert all(p.interval == pytest.approx(1.96 * p.sigma + abs(p.model_bias) + p.stall) for p in params)
    # the jitter's σ grows with the jitter: 40 against 0.5 in one residual of 200
    assert params[0].jitter > 10 * F.replay_jitter(_Rough(0.5), params, prob.A, _Rough(0.5).residual_vector(
        {"a": params[0].value, "b": params[1].value}))[0]


def test_a_profile_whose_exact_curve_falls_all_the_way_keeps_the_smoothed_minimum():
    """Cyclo seed 41's backlash: the smoothed profile has its minimum inside the grid, the
    exact one falls to the grid's edge. Where no grid gives both a minimum (the second pass
    of ``profile_interval``) the smoothed one is kept with the first-order smoothing bias; it
    had been dropped, and the stalled fit's value and Jacobian interval stayed."""
    n = 40
    other = np.where(np.arange(n) % 2, 1.0, -1.0)[:, None]       # orthogonal to the residuals below

    class Prob:
        block = {"backlash_rad": 0.0}

        def residual_vector(self, block, smooth=None, every_sample=False):
            v = block["backlash_rad"]
            s = (v - 0.0200) ** 2 * 1e7 + 100.0 if smooth else 300.0 - 1e4 * v
            return np.full(n, math.sqrt(s / n))
    p = F.Param("backlash_rad", 0.0226, 0.01)
    p.model_bias = 2e-4
    assert F.profiles._profile_on(Prob(), [p], 0, np.array([0.0226]), other * 0.0, 0.0015, 1.0, 1.0, None) is None
    out = F.profiles._profile_on(Prob(), [p], 0, np.array([0.0226]), other * 0.0, 0.0015, 1.0, 1.0, None, False)
    assert out is not None and out["value"] == pytest.approx(0.0200, abs=1e-6)
    assert out["bias"] == pytest.approx(2e-4)
    assert out["interval"] == pytest.approx(math.sqrt(F.CHI2_1_95 / 1e7) + 2e-4, rel=1e-3)


def test_a_profile_takes_in_the_scan_values_whose_S_is_as_low_as_its_minimum():
    """Cyclo random seed 102: S along the backlash has two minima nearly as deep (1.5 and
    8.7 mrad, the truth 8.7), and the local profile drew ±1.4 mrad around 1.6. Every scan
    value whose S lies within the rise (plus S's jitter) is in the confidence set: the
    interval reaches it and the run is said not to resolve the gap. A second basin above
    the rise changes nothing."""
    n = 40
    other = np.where(np.arange(n) % 2, 1.0, -1.0)[:, None]
    scan = (0.00126, 0.002, 0.0032, 0.0051, 0.0081, 0.0129, 0.05)

    class Prob:
        block = {"backlash_rad": 0.0}

        def __init__(self, depth):
            self.depth = depth

        def residual_vector(self, block, smooth=None, every_sample=False):
            v = block["backlash_rad"]
            s = min((v - 0.0016) ** 2 * 1e7, (v - 0.0081) ** 2 * 1e7 + self.depth) + 100.0
            return np.full(n, math.sqrt(s / n))
    for depth, resolved in ((1.0, False), (50.0, True)):
        p = F.Param("backlash_rad", 0.002, 0.005, 1e-5, scan=scan, profile=True)
        prob = Prob(depth)
        local = F.profiles._profile_on(prob, [p], 0, np.array([0.002]), other * 0.0, 7e-4, 1.0, 1.0, None, False)
        assert local["value"] == pytest.approx(0.0016, abs=1e-6)
        half = local["interval"]
        assert half == pytest.approx(math.sqrt(F.CHI2_1_95 / 1e7), rel=1e-3)
        out = F.profiles._other_basins(prob, [p], 0, np.array([0.002]), other * 0.0, local)
        assert out["resolved"] is resolved
        if resolved:
            assert out["interval"] == half and "basins" not in out
        else:
            got = [b["value"] for b in out["basins"]]
            # on the scan's range, 4x as densely: every value found lies in the second basin
            assert got and all(abs(v - 0.0081) < math.sqrt(F.CHI2_1_95 / 1e7) for v in got), got
            assert out["interval"] == pytest.approx(max(got) - 0.0016, rel=1e-6)
            # the interval a parameter reports reaches the other basin whatever its σ says
            p.sigma, p.model_bias, p.basin_reach = 1e-4, 0.0, 0.0065
            assert p.half_width() == pytest.approx(0.0065)


def test_signal_mask_leaves_out_the_named_signals_only():
    """``Problem.signal_mask``: one flag per stacked residual, False exactly on the named
    signals (the angle-free refit after a Kt saturation, ``fit.angle_free_prefit``)."""
    rec = _record(BLOCK, _segments(n_cal=300, n_eff=400))
    prob = F.Problem(rec, copy.deepcopy(BLOCK), Q)
    r = prob.residual_vector(copy.deepcopy(BLOCK))
    m = prob.signal_mask(exclude=("position_rad",))
    assert m.shape == r.shape and 0 < m.sum() < len(m)
    lens = [s.last_sample - s.first_sample + 1 for s in rec]
    want = np.concatenate([np.full(lens[[s.name for s in rec].index(k[0])], k[2] != "position_rad")
                           for k in prob.residual_keys()])
    assert np.array_equal(m, want)
    assert prob.signal_mask().all()


def test_contact_chatter_is_left_out_of_S_and_nothing_else():
    """A gapped mesh taken up at the efficiency step's start bounces chaotically in the
    parameters: those samples (and only those) are left out of S; a rigid model leaves
    out nothing."""
    hidden = copy.deepcopy(BLOCK) | {"backlash_rad": 0.02}
    rec = _record(hidden, _segments(n_cal=300, n_eff=1600))
    params = F.base_params(BLOCK)
    prob = F.Problem(rec, hidden, Q)
    events = F.event_mask(prob, params)
    step, sample = prob.sample_index()
    assert events.any()
    assert {prob.segments[int(g)].name for g in step[events]} == {"efficiency-0"}
    assert sample[events].max() < 400, sample[events].max()    # the take-up, not the staircase
    full = prob.residual_vector(hidden)
    assert F.update_events(prob, params)
    kept = prob.residual_vector(hidden)
    assert np.all(kept[events] == 0) and np.array_equal(kept[~events], full[~events])
    assert np.array_equal(prob.residual_vector(hidden, every_sample=True), full)
    assert not F.event_mask(F.Problem(rec, copy.deepcopy(BLOCK), Q), params).any()
