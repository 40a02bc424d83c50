"""Adaptive measurement (issue 14): measurements stop when their statistical interval
meets the profile's target, or at max_s, and say which. A short simulated case runs the
real sequencer in-process against the simulated bench (gearbench.benchmarks.cycle_time's
InProcessBench: the --sim physics without the bus), so each run takes seconds."""
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from gearbench.analysis.streaming import LevelMean, StreamingB2, slope_fit
from gearbench.benchmarks.cycle_time import run_inprocess
from gearbench.profile import EfficiencyStep, load_profile
from gearbench.profile.model import Targets
from gearbench.sim import MotorParams, PlantParams, simulate_motor
from gearbench.sim import waveforms as wf

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def short_cvt():
    """cvt.yaml cut to one speed x two torques (the adaptive procedure unchanged)."""
    p = load_profile(ROOT / "profiles" / "cvt.yaml")
    steps = [replace(s, speeds_in_rad_s=[200.0], torques_out_nm=[0.06, 0.10]) if isinstance(s, EfficiencyStep)
             else s for s in p.steps]
    return replace(p, steps=steps), PlantParams.from_dict(p.simulation)


def _run(profile, plant, seed=1):
    res = run_inprocess(profile, plant, seed=seed)
    assert res["status"] == "passed", res["reason"]
    return res


def test_measurements_stop_on_target_and_record_why(short_cvt):
    profile, plant = short_cvt
    res = _run(profile, plant)
    ms = res["measurements"]
    cal = [m for m in ms if m["kind"] == "calibrate"]
    eff = [m for m in ms if m["kind"] == "efficiency"]
    # both motors alone at once, then the one disk on each in turn (its error cancels in K_out/K_in)
    assert sorted(res["steps"]) == ["calibrate-in-disk_a", "calibrate-in.out-unloaded", "calibrate-out-disk_a",
                                    "efficiency-0"]
    assert len(cal) == 4 and {m["motor"] for m in cal} == {"in", "out"}
    assert len(eff) == 3                       # zero load + 2 torques, one staircase
    # the output motor's own friction is taken off its braking current: the shaft carries the
    # profile's torque (uncompensated it carried about Tc = 9 mN m more)
    assert [m["friction_compensated_nm"] for m in eff[1:]] == [pytest.approx(plant.motor_out.Tc, rel=0.2)] * 2
    assert [p["torque_out_nm"] for p in res["efficiency"]] == [pytest.approx(0.06, abs=1e-3),
                                                               pytest.approx(0.10, abs=1e-3)]
    for m in ms:
        assert m["stopped_by"] in ("target", "max")
        assert m["duration_s"] > 0 and m["interval_reached"] is not None
        if m["stopped_by"] == "target":
            assert m["interval_reached"] <= m["target"] + 1e-12
    # the calibration runs on this plant reach the Kt target, between min_s and max_s
    for m in cal:
        assert m["stopped_by"] == "target"
        assert 2.0 - 1e-9 <= m["duration_s"] <= 2.4 + 1e-9
        assert m["target"] == pytest.approx(profile.targets.kt_rel / np.sqrt(2))
    # bench time = what was acquired, far below the fixed procedure, and still accurate
    assert res["bench_time_s"] < 10.0
    truth = res["simulation_truth"]
    for motor in ("in", "out"):
        assert abs(res["motors"][motor]["Kt"] / truth["motors"][motor]["Kt"] - 1) < 0.002
    for p, t in zip(res["efficiency"], truth["efficiency"]):
        assert p["incremental_method"] == "slope" and p["eta_incremental_secant"] is not None
        assert abs(p["eta_incremental"] - t["eta_incremental"]) < 0.002
        assert abs(p["eta_absolute"] - t["eta_absolute"]) < 0.003


def test_an_unreachable_target_stops_at_max_s(short_cvt):
    profile, plant = short_cvt
    strict = replace(profile, targets=Targets(kt_rel=1e-7, eta_pp=1e-5))
    res = _run(strict, plant)
    assert {m["stopped_by"] for m in res["measurements"]} == {"max"}
    cal = [m for m in res["measurements"] if m["kind"] == "calibrate"]
    assert all(m["duration_s"] == pytest.approx(2.0) for m in cal)       # cvt.yaml's max_s
    eff = [m for m in res["measurements"] if m["kind"] == "efficiency"]
    assert all(m["duration_s"] == pytest.approx(0.95) for m in eff)


def test_streaming_b2_matches_the_full_fit_within_its_error():
    """Per-block sufficient statistics give b2 and an error close to the analysis' own."""
    from gearbench.analysis.identify import identify_default

    m = MotorParams(Kt=0.0527, J=1.5e-5, D=2e-6, Tc=0.008, cog_amp=0.0)
    t = wf.time_base(3.0)
    cmd = wf.multisine(t, amplitude=80.0, freqs_hz=[1, 2, 3, 4, 5, 6, 7, 8], offset=150.0)
    tr = simulate_motor(m, cmd, seed=4)
    s = StreamingB2(1e-3)
    for k in range(100, len(tr) + 1, 100):       # as the sequencer feeds it
        s.update(tr["position_rad"], tr["current_a"], k)
    b2, sd, dof = s.estimate()
    full = identify_default(tr.time_s, tr["position_rad"], tr["current_a"], check=False)
    assert dof >= 5
    assert abs(b2 - full.b2) < 4 * max(sd, full.b2_std)
    assert 0.3 < sd / full.b2_std < 3.0
    assert abs(b2 / (m.Kt / m.J) - 1) < 0.002


def test_level_settling_is_found_in_the_data():
    """A level with an exponential transient (tau 40 ms) then noise: the settled window
    starts after the transient, and the mean is the final value within its error."""
    rng = np.random.default_rng(0)
    n = 800
    t = np.arange(n) * 1e-3
    x = 0.2 + 0.1 * np.exp(-t / 0.04) + rng.normal(0, 0.004, n)
    acc = LevelMean()
    for a in range(0, n, 20):
        acc.add_chunk(x[a:a + 20], np.full(20, -1.0))
    st = acc.stats()
    assert st is not None
    assert st["settle_chunk"] * 20 * 1e-3 >= 0.1        # after ~2.5 tau at least
    assert abs(st["mean_in"] - 0.2) < 4 * st["sem_in"]


def test_slope_fit_recovers_a_line():
    x = np.array([0.0, -0.5, -1.0, -1.5, -2.0])
    y = 0.3 - 0.16 * x
    _, b, sb = slope_fit(x, y + np.array([1e-4, -1e-4, 0, 1e-4, -1e-4]), np.full(5, 1e-4))
    assert b == pytest.approx(-0.16, abs=3 * sb) and sb < 1e-3


def test_cycle_time_bound_is_every_measurement_at_max_s():
    """Issue 23: the bench-time bound the random plants are judged against, from the plan."""
    from gearbench.benchmarks.cycle_time import bench_time_bound_s

    p = load_profile(ROOT / "profiles" / "cvt.yaml")
    # by hand: 3 calibration segments (both motors alone, then the one disk on each) of 2.0 s
    # + a 0.16 s stop ramp from the multisine's 320 rad/s peak at 2000 rad/s^2; per speed
    # (100, 200, 300 rad/s) run-up and stop ramps of max(speed/2000, 0.05) s + 5 levels x 0.95 s
    hand = 3 * (2.0 + 0.16) + sum(2 * max(v / 2000, 0.05) + 5 * 0.95 for v in (100, 200, 300))
    assert bench_time_bound_s(p) == pytest.approx(hand, abs=0.005)


def test_cycle_time_says_why_a_target_was_missed():
    from gearbench.benchmarks.cycle_time import score

    point = {"eta_incremental": 0.8, "eta_incremental_std": 0.001, "eta_absolute": 0.7,
             "eta_absolute_std": 0.001, "loss_extrapolated": False}
    last = {**point, "eta_incremental": 0.803, "eta_incremental_std": 0.002, "eta_absolute": 0.71,
            "eta_absolute_std": 0.01, "loss_extrapolated": True}
    res = {"status": "passed", "bench_time_s": 18.0,
           "simulation_truth": {"motors": {"in": {"Kt": 1.0}, "out": {"Kt": 1.0}},
                                "efficiency": [{"eta_incremental": 0.8, "eta_absolute": 0.7}] * 12},
           "motors": {"in": {"Kt": 1.005, "Kt_std": 0.001}, "out": {"Kt": 1.003, "Kt_std": 0.002}},
           "efficiency": [point] * 11 + [last],
           "measurements": [{"kind": "calibrate", "stopped_by": "max", "interval_reached": 0.002, "target": 7e-4},
                            {"kind": "efficiency", "stopped_by": "target", "interval_reached": 0.1, "target": 0.15}]}
    s = score(res)
    assert not s["meets"] and not s["meets_all"]
    assert s["why_missed"] == ["Kt in 0.50% biased (5.0 sd)", "Kt out 0.30% noise at the bound (1 runs at max)",
                               "incr 0.30pp noise at the bound (0 levels at max)", "abs 1.00pp extrapolated loss"]
    # issue 23's triage, one cause per missed target: the fakes name no motor per run (no
    # run at max is tied to a Kt); the Kt errors (+0.5 %, +0.3 %) move η by 0.8 x 0.2 % =
    # 0.16 pp of the 0.30 pp incremental miss: the calibration's
    assert s["causes"] == ["Kt: stopped early (biased)", "Kt: stopped early", "incr: from Kt",
                           "abs: extrapolated loss"]
    slope_only = {**res, "motors": {**res["motors"], "out": {"Kt": 1.005, "Kt_std": 0.002}}}
    assert score(slope_only)["causes"][2] == "incr: stopped early"   # same Kt errors: the slope's
    good = {**res, "motors": {m: {"Kt": 1.0, "Kt_std": 0.001} for m in ("in", "out")}, "efficiency": [point] * 12}
    s = score(good)
    assert s["meets"] and s["meets_all"] and s["why_missed"] == []


def test_cycle_time_says_how_far_a_miss_at_max_s_stayed_from_its_target():
    """Issue 23's triage: a miss at max_s is told apart by how far its interval stayed
    above the target (near 1: the budget's share can close it; far above: only more
    information per second), from the measurements that carry the missed target only."""
    from gearbench.benchmarks.cycle_time import score

    point = {"eta_incremental": 0.8, "eta_incremental_std": 0.002, "eta_absolute": 0.7,
             "eta_absolute_std": 0.001, "speed_setpoint_rad_s": 100.0, "torque_setpoint_nm": 0.1}
    res = {"status": "passed", "bench_time_s": 18.0,
           "simulation_truth": {"motors": {"in": {"Kt": 1.0}, "out": {"Kt": 1.0}},
                                "efficiency": [{"eta_incremental": 0.8, "eta_absolute": 0.7}] * 12},
           "motors": {"in": {"Kt": 1.003, "Kt_std": 0.002}, "out": {"Kt": 1.0, "Kt_std": 0.001}},
           "efficiency": [point] * 12,
           "measurements": [
               {"kind": "calibrate", "motor": "in", "stopped_by": "max", "interval_reached": 2.1e-3, "target": 7e-4},
               {"kind": "calibrate", "motor": "out", "stopped_by": "max", "interval_reached": 7e-3, "target": 7e-4},
               {"kind": "efficiency", "speed_in_rad_s": 100.0, "stopped_by": "max", "interval_reached": 0.3,
                "target": 0.15}]}
    s = score(res)
    # Kt in misses (0.3 %) with its run 3x short; Kt out meets, so its 10x run is not counted
    assert s["causes"][0] == "Kt: at max_s" and s["shortfall"] == pytest.approx(3.0)
    ok = {**res, "motors": {m: {"Kt": 1.0, "Kt_std": 0.001} for m in ("in", "out")}}
    assert score(ok)["shortfall"] is None                  # every target met: nothing short
    slow = {**ok, "efficiency": [point] * 11 + [{**point, "eta_incremental": 0.803}]}
    assert score(slow)["causes"] == ["incr: at max_s"] and score(slow)["shortfall"] == pytest.approx(2.0)


def test_designed_calibration_falls_back_where_no_sweep_covers_the_map(monkeypatch):
    """Random plant 4/9: a 0.039 N m/A input motor with a disk of three rotors cannot sweep
    its map speeds (135-226 rad/s) within its rated current in 2 s; as the profile's own
    design does, the benchmark then takes the plain design (was an ERROR row)."""
    import gearbench.profile.excitation_design as ed
    from gearbench.benchmarks.cycle_time import PROFILES, random_plant

    base = load_profile(PROFILES["adaptive"])
    covers = []
    real = ed.design_multisine

    def spy(cases, **kw):
        covers.append(kw.get("cover_rad_s"))
        return real(cases, **kw)
    monkeypatch.setattr(ed, "design_multisine", spy)
    _, prof = random_plant(9, 4, base, excitation="designed")
    assert prof.waveforms["excite_in"].kind == "multisine" and prof.waveforms["excite_in"].design is not None
    # the input motor's design was asked to cover its map speeds, could not, and was made plain
    assert covers[0] is not None and covers[1] is None


def test_output_friction_above_a_braking_torque_is_not_compensated():
    """Issue 23 (random plant 2/10): an output motor whose own friction brakes more than the
    lightest level asks would have every level compensated to zero current (no slope; it
    raised ZeroDivisionError); its levels stay as commanded instead."""
    from gearbench.station.adaptive import Staircase

    def stairs(loss_nm):
        st = Staircase(speed=100.0, currents_out_a=[-0.2, -0.4], torques_out_nm=[0.01, 0.02], period_s=1e-3,
                       min_s=0.25, max_s=0.95, eta_pp=0.15, kt_in=0.05, kt_out=0.05, eta_prior=0.8,
                       ratio_prior=None, ramp_rad_s2=2000.0, segment="e", loss_out=lambda w: loss_nm)
        st._compensate_friction({"start": 0, "settled": 100, "stop": 1100, "dth_out": 10.0})
        return st
    low, high = stairs(0.004), stairs(0.019)
    assert low.compensated_nm == pytest.approx(0.004)
    assert low.levels[1:] == [pytest.approx(-0.12), pytest.approx(-0.32)]
    assert high.compensated_nm is None and high.levels[1:] == [-0.2, -0.4]
    # random plant 3/3: friction just below the lightest torque left it 0.01 A of braking,
    # an input-current rise within the noise; more than half of it is not compensated now
    near = stairs(0.006)
    assert near.compensated_nm is None and near.levels[1:] == [-0.2, -0.4]


# ---------------------------------------------------------------- issue 23: random plants
def test_inertia_corrected_current_removes_a_speed_loops_recovery():
    """A speed loop recovering from a load step moves the current by J θ''/Kt while the shaft
    torque is already steady: the corrected current is flat right after the step."""
    from gearbench.analysis.efficiency import inertia_corrected_current

    dt, J, kt = 1e-3, 5e-5, 0.05
    t = np.arange(1500) * dt
    w = 100.0 - 5.0 * np.exp(-t / 0.15)                 # speed sags 5 rad/s, recovers with tau 150 ms
    theta = np.cumsum(w) * dt
    i = 0.3 + J * np.gradient(w, dt) / kt               # steady shaft torque + the rotor's acceleration
    corr = inertia_corrected_current(i, theta, dt, J, kt)
    assert np.ptp(i[100:600]) > 0.01                    # the raw current still moves by > 10 mA
    # the corrected one is the shaft's 0.3 A (to 0.5 mA: the speed is averaged over 100 ms)
    assert np.max(np.abs(corr[100:1400] - 0.3)) < 5e-4


def test_a_level_settles_only_with_the_speed_at_its_command():
    """A current that is flat while the speed still sags 5 % is not a settled level."""
    rng = np.random.default_rng(1)
    acc = LevelMean(speed_rad_s=100.0, dt_s=1e-3)
    for k in range(40):                                 # 0.8 s at 95 rad/s: never settled
        acc.add_chunk(0.2 + rng.normal(0, 0.003, 20), np.full(20, -1.0), 95.0 * 20e-3)
    assert acc.stats() is None
    for k in range(40):                                 # then 0.8 s at the command
        acc.add_chunk(0.2 + rng.normal(0, 0.003, 20), np.full(20, -1.0), 100.0 * 20e-3)
    st = acc.stats()
    assert st is not None and st["settle_chunk"] >= 40


def test_staircase_levels_share_what_earlier_ones_left_of_their_max_s():
    from gearbench.station.adaptive import Staircase

    st = Staircase(speed=100.0, currents_out_a=[-0.2, -0.4], torques_out_nm=[0.01, 0.02], period_s=1e-3,
                   min_s=0.25, max_s=0.95, eta_pp=0.15, kt_in=0.05, kt_out=0.05, eta_prior=0.8,
                   ratio_prior=None, ramp_rad_s2=2000.0, segment="e")
    assert st._level_max() == 950
    st.done_levels = [{"start": 0, "stop": 400}]        # the zero-load level stopped after 0.4 s
    assert st._level_max() == 950 + 550
    st.done_levels.append({"start": 400, "stop": 1900})
    assert st._level_max() == 950                       # the staircase stays within 3 x 0.95 s


@pytest.mark.parametrize("plant", ["1/13"])
def test_a_slow_speed_loop_is_measured_at_its_commanded_speed(plant):
    """Issue 23, random plant 1/13 (input speed loop 3.3 Hz): its input sagged to 38 rad/s
    of 119 commanded through most of a level and that level was taken as settled (abs
    efficiency 0.9 pp off). Every point now sits at its commanded speed."""
    from gearbench.benchmarks.cycle_time import PROFILES, random_plant, score

    seed, index = map(int, plant.split("/"))
    case, prof = random_plant(index, seed, load_profile(PROFILES["adaptive"]), excitation="designed")
    res = run_inprocess(prof, case.plant, seed=int(case.plant.seed))
    for p in res["efficiency"]:
        assert p["speed_in_rad_s"] == pytest.approx(p["speed_setpoint_rad_s"], rel=0.01)
    assert score(res)["meets_all"]


def test_cycle_time_sets_each_calibration_run_against_its_design():
    """Issue 23 (task 27a): a designed calibration's interval reached, against what its
    excitation design predicted for a run of that length (eq. D1/D2 shares), per run."""
    from gearbench.benchmarks.cycle_time import PROFILES, design_ratio, random_plant
    from gearbench.analysis.streaming import Z95

    _, prof = random_plant(3, 0, load_profile(PROFILES["adaptive"]), excitation="designed")
    pred = prof.waveforms["excite_in"].design.predictions["in"]
    J, j = prof.motors["in"].rotor_inertia_kgm2, prof.disks["disk_in"].inertia_kgm2
    unloaded = Z95 * J / j * pred.b2_rel_std_unloaded
    loaded = Z95 * (J + j) / j * pred.b2_rel_std_loaded
    res = {"measurements": [
        {"kind": "calibrate", "motor": "in", "run": "unloaded", "duration_s": pred.duration_s,
         "interval_reached": 2 * unloaded},
        # a run half the design's length: its prediction widens by sqrt(2)
        {"kind": "calibrate", "motor": "in", "run": "disk_in", "duration_s": pred.duration_s / 2,
         "interval_reached": 3 * loaded},
        {"kind": "efficiency", "interval_reached": 0.3}]}
    r = design_ratio(prof, res)
    assert set(r) == {"in unloaded", "in loaded"}
    assert r["in unloaded"] == pytest.approx(2.0)
    assert r["in loaded"] == pytest.approx(3 / np.sqrt(2))


def test_cycle_time_what_if_scales_the_current_noise_and_quieter_sensors_shorten_the_levels(short_cvt):
    """The what-if behind ``cycle_time --current-noise-scale``: both drives' current noise
    scaled, nothing else; on the cvt plant with its noise at a tenth, the braking levels
    reach their intervals sooner (white current noise sets how long a level takes)."""
    from gearbench.benchmarks.cycle_time import scaled_current_noise

    profile, plant = short_cvt
    quiet = scaled_current_noise(plant, 0.1)
    for m in ("in", "out"):
        a, b = getattr(plant, f"motor_{m}"), getattr(quiet, f"motor_{m}")
        assert b.current_noise_a == pytest.approx(0.1 * a.current_noise_a) and replace(b, current_noise_a=a.current_noise_a) == a
    with pytest.raises(ValueError, match="noise scale"):
        scaled_current_noise(plant, -1.0)
    level_s = lambda res: sum(m["duration_s"] for m in res["measurements"] if m["kind"] == "efficiency")
    assert level_s(_run(profile, quiet)) < level_s(_run(profile, plant))
