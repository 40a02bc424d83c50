"""Simulated physics: steady states against hand calculation, efficiency truth,
determinism, batch == stepping, and that every switchable effect shows."""
from __future__ import annotations

import math

import numpy as np
import pytest

from gearbench.errors import ProfileError
from gearbench.sim import (BenchWorld, CvtParams, MotorParams, PlantParams, bench_operating_point,
                           efficiency_truth, simulate_bench, simulate_motor)
from gearbench.sim import waveforms as wf

T = 1e-3


def _mean(x, t0_s, t1_s):
    return float(np.mean(x[int(t0_s / T):int(t1_s / T)]))


# ------------------------------------------------------------------ single motor
def test_velocity_loop_settles_and_steady_current_is_friction():
    m = MotorParams()
    tr = simulate_motor(m, wf.step(wf.time_base(2.0), amplitude=150.0, t_step_s=0.1),
                        include_truth=True)
    assert _mean(tr["true_velocity_rad_s"], 1.0, 2.0) == pytest.approx(150.0, abs=0.05)
    assert _mean(tr["velocity_rad_s"], 1.0, 2.0) == pytest.approx(150.0, abs=0.1)
    # J θ'' = Kt i − D ω − Tc at constant speed: i = (D ω + Tc)/Kt (cogging averages out)
    expected = (m.D * 150.0 + m.Tc) / m.Kt
    assert _mean(tr["current_a"], 1.0, 2.0) == pytest.approx(expected, rel=0.01)
    # the drive's estimate comes from the quantised encoder, so it is not the true speed
    assert not np.allclose(tr["velocity_rad_s"][500:], tr["true_velocity_rad_s"][500:], atol=0.01)


def test_reverse_rotation_is_mirror_image():
    m = MotorParams()
    fwd = simulate_motor(m, np.full(1500, 80.0), include_truth=True)
    rev = simulate_motor(m, np.full(1500, -80.0), include_truth=True)
    assert _mean(rev["true_current_a"], 1.0, 1.5) == pytest.approx(
        -_mean(fwd["true_current_a"], 1.0, 1.5), rel=0.02)


def test_torque_mode_acceleration_gives_inertia_with_disk():
    m = MotorParams(cog_amp=0.0, current_lag_s=0.0)
    disk = 1.0e-5
    i_cmd = 0.3
    tr = simulate_motor(m, np.full(400, i_cmd), mode="torque", disk_kgm2=disk, include_truth=True)
    w = tr["true_velocity_rad_s"]
    # (J + j) ω' = Kt i − Tc − D ω from rest: ω(t) = (Kt i − Tc)/D · (1 − exp(−D t/(J + j)))
    jt = m.J + disk
    expected = (m.Kt * i_cmd - m.Tc) / m.D * (1 - math.exp(-m.D * 0.3 / jt))
    assert w[300] == pytest.approx(expected, rel=0.003)
    # without the disk the same current accelerates (J + j)/J times faster
    alone = simulate_motor(m, np.full(400, i_cmd), mode="torque", include_truth=True)
    assert alone["true_velocity_rad_s"][50] / w[50] == pytest.approx(jt / m.J, rel=0.01)


def test_torque_mode_folds_back_at_speed_limit():
    m = MotorParams(speed_limit_rad_s=200.0)
    tr = simulate_motor(m, np.full(3000, 1.0), mode="torque", include_truth=True)
    assert 195.0 < tr["true_velocity_rad_s"][-1] < 215.0


def test_velocity_setpoint_clipped_and_current_limited():
    m = MotorParams(speed_limit_rad_s=100.0, current_limit_a=0.5)
    tr = simulate_motor(m, np.full(2000, 300.0), include_truth=True)
    assert np.abs(tr["current_cmd_a"]).max() <= 0.5 + 1e-12
    assert _mean(tr["true_velocity_rad_s"], 1.5, 2.0) == pytest.approx(100.0, abs=0.2)
    # anti-windup: a limited accelaration overshoots little
    assert tr["true_velocity_rad_s"].max() < 110.0


def test_sensor_models_are_exact():
    base = dict(current_noise_a=0.0, current_resolution_a=0.0)
    cmd = wf.multisine(wf.time_base(1.0), amplitude=40, offset=80, freqs_hz=[2, 5, 11])
    ideal = simulate_motor(MotorParams(**base), cmd, include_truth=True)
    # transport delay: exactly d samples later
    d = 3
    delayed = simulate_motor(MotorParams(**base, delay_samples=d), cmd)
    np.testing.assert_array_equal(delayed["current_a"][d:], ideal["current_a"][:-d])
    assert (delayed["current_a"][:d] == 0).all()
    # gain and offset
    go = simulate_motor(MotorParams(**base, current_gain=1.1, current_offset_a=0.02), cmd)
    np.testing.assert_allclose(go["current_a"], 1.1 * ideal["current_a"] + 0.02, atol=1e-12)
    # resolution and encoder quantisation
    q = simulate_motor(MotorParams(current_resolution_a=0.005, counts_per_rev=1000), cmd)
    assert np.allclose(q["current_a"] / 0.005, np.round(q["current_a"] / 0.005), atol=1e-9)
    counts = q["position_rad"] / (2 * math.pi / 1000)
    assert np.allclose(counts, np.round(counts), atol=1e-6)
    # noise: the measured-minus-true residual has the configured std
    noisy = simulate_motor(MotorParams(current_resolution_a=0.0, current_avg_s=0.0), cmd,
                           include_truth=True)
    resid = noisy["current_a"] - noisy["true_current_a"]
    assert np.std(resid) == pytest.approx(0.004, rel=0.1)


def test_reported_current_is_the_mean_over_the_last_current_avg_s():
    """Torque step from rest, clean sensor: the first sample is the mean of the exact
    first-order current response over the averaging span (or its value at the instant)."""
    base = dict(current_noise_a=0.0, current_resolution_a=0.0, cog_amp=0.0, Tc=0.0,
                current_lag_s=5e-4)
    nsub, dt = 20, T / 20                      # 50 µs substeps at 1 kHz
    decay = math.exp(-dt / 5e-4) ** np.arange(1, nsub + 1)   # (1 − β)^(m+1)
    for avg_s, last in ((0.0, 1), (2.5e-4, 5), (1e-3, 20), (5e-3, 20)):
        tr = simulate_motor(MotorParams(**base, current_avg_s=avg_s), np.full(3, 0.5),
                            mode="torque")
        expected = 0.5 * (1.0 - decay[nsub - last:].mean())
        assert tr["current_a"][1] == pytest.approx(expected, rel=1e-9), avg_s


def test_velocity_setpoints_are_interpolated_so_the_current_matches_the_torque():
    """Steps of a 1 kHz setpoint into a 4 kHz velocity loop kick the current at every
    sample; a cyclic-synchronous drive ramps between setpoints instead. Only then does
    the instantaneous sampled current identify Kt/J (forward-only multisine, default
    method; the period-mean current of the default drive hides the kicks as well)."""
    from gearbench.analysis.identify import identify_default

    cmd = wf.multisine(wf.time_base(3.0), amplitude=80, offset=150, freqs_hz=[1, 2, 3, 5, 8])
    errors = {}
    for interp in (0, 1):
        m = MotorParams(setpoint_interpolation=interp, cog_amp=0.0, current_avg_s=0.0)
        tr = simulate_motor(m, cmd, seed=4)
        fit = identify_default(tr.time_s, tr["position_rad"], tr["current_a"])
        errors[interp] = fit.b2 / (m.Kt / m.J) - 1
    assert abs(errors[1]) < 0.002
    assert errors[0] > 0.008
    with pytest.raises(ProfileError, match="setpoint_interpolation"):
        MotorParams(setpoint_interpolation=2)


EFFECTS = [
    ("Tc", 0.02), ("Ts", 0.01), ("cog_amp", 0.01), ("ripple_amp", 0.1), ("kt_sat_a", 0.5),
    ("C", 1e-3), ("current_lag_s", 5e-3), ("D", 2e-5), ("shaft_stiffness", 2.0),
    ("backlash_rad", 0.05), ("counts_per_rev", 500), ("delay_samples", 2),
    ("current_offset_a", 0.01), ("current_gain", 1.05), ("current_noise_a", 0.02),
    ("current_resolution_a", 0.01),
]


@pytest.mark.parametrize("name,value", EFFECTS)
def test_each_effect_changes_the_output(name, value):
    """Same seed and command; only the one effect differs → measured current differs."""
    cmd = wf.trapezoid(wf.time_base(1.5), amplitude=60.0, ramp_s=0.2, hold_s=0.3,
                       repeat_s=0.75) - 20.0
    base = MotorParams(cog_amp=0.0)
    changed = MotorParams(**{**base.__dict__, name: value})
    a = simulate_motor(base, cmd, disk_kgm2=1e-5, seed=5)
    b = simulate_motor(changed, cmd, disk_kgm2=1e-5, seed=5)
    diff = np.abs(a["current_a"] - b["current_a"])
    assert diff.mean() > 1e-3, f"{name}={value} did not change the current"


def test_compliant_disk_same_steady_state_different_transient():
    cmd = wf.step(wf.time_base(1.5), amplitude=100.0, t_step_s=0.05)
    rigid = simulate_motor(MotorParams(), cmd, disk_kgm2=1e-5, include_truth=True)
    soft = simulate_motor(MotorParams(shaft_stiffness=3.0, shaft_damping=2e-4), cmd,
                          disk_kgm2=1e-5, include_truth=True)
    assert _mean(soft["true_current_a"], 1.0, 1.5) == pytest.approx(
        _mean(rigid["true_current_a"], 1.0, 1.5), rel=0.02)
    assert np.abs(soft["true_current_a"][50:200] - rigid["true_current_a"][50:200]).max() > 0.02


# -------------------------------------------------------------------- the bench
def _bench_levels(plant, speed, levels, dwell_s=3.0, settle_s=1.0, **kw):
    t = wf.time_base(dwell_s * len(levels))
    cin = wf.ramp(t, slope=1000.0, final=speed)
    cout = wf.staircase(t, levels=levels, dwell_s=dwell_s)
    tr = simulate_bench(plant, cin, cout, include_truth=True, **kw)
    out = []
    for k in range(len(levels)):
        a, b = k * dwell_s + settle_s, (k + 1) * dwell_s
        out.append({key: _mean(tr[key], a, b) for key in
                    ("in_current_a", "out_current_a", "power_in_w", "power_out_w",
                     "in_true_velocity_rad_s", "out_true_velocity_rad_s")})
    return tr, out


def _eta_eq18(plant, pts, k):
    """Paper eq. 18 against the mean of the first and last (zero-load) levels."""
    ref_in = (pts[0]["in_current_a"] + pts[-1]["in_current_a"]) / 2
    ref_out = (pts[0]["out_current_a"] + pts[-1]["out_current_a"]) / 2
    d_out = -(pts[k]["out_current_a"] - ref_out)        # braking current is negative
    d_in = pts[k]["in_current_a"] - ref_in
    return plant.motor_out.Kt * d_out / (plant.ratio * plant.motor_in.Kt * d_in)


@pytest.mark.parametrize("backlash", [0.0, 0.01])
def test_bench_steady_currents_satisfy_eta_relation(backlash):
    plant = PlantParams(ratio=8.0, eta_mesh=0.85, drag_torque_nm=0.01, drag_viscous=1e-5,
                        backlash_rad=backlash, seed=1)
    speed = 150.0
    levels = [0.0, -1.0, -2.0, 0.0]
    tr, pts = _bench_levels(plant, speed, levels)
    assert pts[1]["out_true_velocity_rad_s"] == pytest.approx(speed / 8.0, rel=1e-3)
    for k in (1, 2):
        assert _eta_eq18(plant, pts, k) == pytest.approx(0.85, abs=0.005)
    for k, level in enumerate(levels):
        op = bench_operating_point(plant, speed, level)
        # mean measured input current from the hand balance
        assert pts[k]["in_current_a"] == pytest.approx(op["current_in_a"], abs=0.002)
        # P_out/P_in from the simulated shaft powers
        eta_abs = pts[k]["power_out_w"] / pts[k]["power_in_w"]
        assert eta_abs == pytest.approx(op["eta_absolute"], abs=0.003)


def test_power_flows_backwards_with_division_by_eta():
    """Output motor drives (positive current) against an input motor holding speed:
    T_in_shaft = (T_out_shaft / n)·η, the input motor's current goes negative."""
    plant = PlantParams(ratio=5.0, eta_mesh=0.8, drag_torque_nm=0.0, seed=2,
                        motor_in=MotorParams(Tc=0.0, D=0.0, cog_amp=0.0),
                        motor_out=MotorParams(Tc=0.0, D=0.0, cog_amp=0.0))
    _, pts = _bench_levels(plant, 100.0, [0.0, 2.0, 0.0])
    t_out = plant.motor_out.Kt * 2.0
    expected_in = -(t_out / 5.0) * 0.8 / plant.motor_in.Kt
    assert pts[1]["in_current_a"] == pytest.approx(expected_in, abs=0.002)


def test_cvt_mean_efficiency_and_output_pulsation():
    cvt = CvtParams(eta_max=0.85, eta_slope_per_rad_s=5e-4, pulsation_amp=0.05, pulsation_order=4)
    plant = PlantParams(cvt=cvt, ratio=5.0, drag_torque_nm=0.01, seed=3)
    speed = 300.0
    tr, pts = _bench_levels(plant, speed, [0.0, -1.0, -2.0, 0.0])
    truth = efficiency_truth(plant, speed, 0.1)["eta_incremental"]
    assert truth == pytest.approx(0.7)
    for k in (1, 2):
        assert _eta_eq18(plant, pts, k) == pytest.approx(truth, abs=0.005)
    # output speed pulsates: ω_out = ω_in/n (1 + a sin(kθ)) → relative std a/√2
    w_out = tr["out_true_velocity_rad_s"][2000:3000]
    assert np.std(w_out) / np.mean(w_out) == pytest.approx(0.05 / math.sqrt(2), rel=0.1)


def test_cvt_eq18_in_steady_state_is_the_efficiency_truth():
    """What eq. 18 measures on the pulsating CVT, averaged over the ripple (Hann-weighted
    window means of period-mean currents, clean sensors), is efficiency_truth's η(ω_in)."""
    cvt = CvtParams(eta_max=0.8, eta_slope_per_rad_s=4e-4, pulsation_amp=0.05, pulsation_order=4)
    clean = dict(current_noise_a=0.0, current_resolution_a=0.0)
    plant = PlantParams(motor_in=MotorParams(**clean), motor_out=MotorParams(Kt=0.0512, **clean),
                        cvt=cvt, ratio=8.0, drag_torque_nm=0.015, drag_viscous=2e-5, seed=1)
    speed, dwell = 100.0, 2500
    levels = [0.0, -0.8, -1.6, 0.0]
    cin = np.full(dwell * len(levels), speed)
    cout = np.repeat(levels, dwell)
    tr = simulate_bench(plant, cin, cout)
    w = 1 - np.cos(2 * np.pi * (np.arange(dwell - 500) + 0.5) / (dwell - 500))

    def level_mean(col, k):
        return float(w @ tr[col][k * dwell + 500:(k + 1) * dwell] / w.sum())

    truth = efficiency_truth(plant, speed, 0.05)["eta_incremental"]
    assert truth == pytest.approx(0.76)
    for k in (1, 2):
        di_in = level_mean("in_current_a", k) - (level_mean("in_current_a", 0)
                                                 + level_mean("in_current_a", 3)) / 2
        eta = -plant.motor_out.Kt * levels[k] / (plant.ratio * plant.motor_in.Kt * di_in)
        assert eta == pytest.approx(truth, abs=2e-4)


def test_cvt_ratio_is_settable():
    plant = PlantParams(cvt=CvtParams(pulsation_amp=0.0), ratio=5.0)
    w = BenchWorld(plant)
    w.mount(coupling="reducer")
    w.set_mode("in", "velocity")
    w.set_setpoint("in", 100.0)
    for _ in range(500):
        w.step()
    w.set_ratio(10.0)
    for _ in range(500):
        m = w.step()
    assert m["out"].velocity_rad_s == pytest.approx(10.0, abs=1.0)
    with pytest.raises(ProfileError):
        w.set_ratio(1000.0)
    with pytest.raises(ProfileError):
        BenchWorld(PlantParams()).set_ratio(5.0)


def test_efficiency_truth_definitions():
    plant = PlantParams(ratio=10.0, eta_mesh=0.9, drag_torque_nm=0.02)
    light = efficiency_truth(plant, 200.0, 0.05)
    heavy = efficiency_truth(plant, 200.0, 1.0)
    assert light["eta_incremental"] == heavy["eta_incremental"] == 0.9
    # P_out/P_in by hand: T_in = T_out/(n η) + drag
    t_in = 1.0 / (10 * 0.9) + 0.02
    assert heavy["eta_absolute"] == pytest.approx((1.0 * 20.0) / (t_in * 200.0), rel=1e-6)
    assert light["eta_absolute"] < heavy["eta_absolute"] < 0.9


# ------------------------------------------------------- determinism, batch == step
def test_deterministic_for_a_seed():
    cmd = wf.multisine(wf.time_base(0.5), amplitude=30, offset=60, freqs_hz=[3, 7])
    a = simulate_motor(MotorParams(), cmd, seed=11)
    b = simulate_motor(MotorParams(), cmd, seed=11)
    c = simulate_motor(MotorParams(), cmd, seed=12)
    np.testing.assert_array_equal(a["current_a"], b["current_a"])
    np.testing.assert_array_equal(a["position_rad"], b["position_rad"])
    assert not np.array_equal(a["current_a"], c["current_a"])


def test_batch_equals_stepping():
    plant = PlantParams(seed=7, backlash_rad=0.0)
    n = 5000        # > one noise block, so block boundaries are crossed
    t = wf.time_base(n * T)
    cin = wf.ramp(t, slope=500.0, final=120.0)
    cout = wf.staircase(t, levels=[0.0, -1.5, 0.0], dwell_s=2.0)
    tr = simulate_bench(plant, cin, cout)
    w = BenchWorld(plant)
    w.mount(coupling="reducer")
    w.set_mode("in", "velocity")
    w.set_mode("out", "torque")
    rows = [w.measurement()]
    for k in range(n - 1):
        w.set_setpoint("in", cin[k])
        w.set_setpoint("out", cout[k])
        rows.append(w.step())
    assert w.sample_index == n - 1 and w.time_s == pytest.approx((n - 1) * T)
    stepped = np.array([[r["in"].position_rad, r["in"].current_a,
                         r["out"].position_rad, r["out"].current_a] for r in rows])
    batch = np.column_stack([tr["in_position_rad"], tr["in_current_a"],
                             tr["out_position_rad"], tr["out_current_a"]])
    np.testing.assert_array_equal(stepped, batch)


def test_calibration_then_reducer_in_one_world():
    """The sequencer's order: motors alone with a disk, then the reducer mounted."""
    w = BenchWorld(PlantParams(seed=4))
    w.mount(coupling="none", disk_kgm2={"in": 1e-5, "out": 1e-5})
    for axis in ("in", "out"):
        w.set_mode(axis, "velocity")
        w.set_setpoint(axis, 50.0)
    for _ in range(1000):
        m = w.step()
    assert m["in"].velocity_rad_s == pytest.approx(50.0, abs=2.0)
    assert m["out"].velocity_rad_s == pytest.approx(50.0, abs=2.0)
    for axis in ("in", "out"):
        w.set_mode(axis, "off")
    for _ in range(2000):
        w.step()
    w.mount(coupling="reducer")
    w.set_mode("in", "velocity")
    w.set_mode("out", "torque")
    w.set_setpoint("in", 100.0)
    w.set_setpoint("out", -1.0)
    for _ in range(1500):
        m = w.step()
    assert m["out"].velocity_rad_s == pytest.approx(10.0, abs=0.5)
    assert m["out"].current_a == pytest.approx(-1.0, abs=0.02)


# ------------------------------------------------------------------ profile parsing
def test_from_dict_parses_and_names_bad_keys():
    d = {"motors": {"in": {"Kt": 0.06, "J": 2e-5}, "out": {"counts_per_rev": 4000}},
         "ratio": 7, "eta_mesh": 0.88, "drag_torque_nm": 0.01, "drag_viscous": 0.0,
         "backlash_rad": 0.0, "seed": 3, "cvt": None}
    p = PlantParams.from_dict(d)
    assert p.motor_in.Kt == 0.06 and p.motor_out.counts_per_rev == 4000 and p.ratio == 7.0
    assert p.truth()["motors"]["in"] == {"Kt": 0.06, "J": 2e-5, "D": 2e-6, "Tc": 0.008}
    assert p.truth()["ratio"] == 7.0
    with pytest.raises(ProfileError, match=r"^simulation\.motors\.in\.Kt_typo: unknown key; known keys: Kt, J"):
        PlantParams.from_dict({"motors": {"in": {"Kt_typo": 1}}})
    with pytest.raises(ProfileError, match=r"simulation\.ratioo: unknown key"):
        PlantParams.from_dict({"ratioo": 5})
    with pytest.raises(ProfileError, match=r"prof\.yaml: simulation\.motors\.out\.J: must be > 0"):
        PlantParams.from_dict({"motors": {"out": {"J": -1}}}, "prof.yaml: simulation")
    with pytest.raises(ProfileError, match=r"simulation\.eta_mesh: expected a number"):
        PlantParams.from_dict({"eta_mesh": "high"})
    with pytest.raises(ProfileError, match=r"simulation\.cvt\.eta_typo: unknown key"):
        PlantParams.from_dict({"cvt": {"eta_typo": 0.5}})
    with pytest.raises(ProfileError, match=r"counts_per_rev: expected a whole number"):
        PlantParams.from_dict({"motors": {"in": {"counts_per_rev": 10.5}}})


def test_bad_calls_raise_profile_errors():
    w = BenchWorld(PlantParams())
    with pytest.raises(ProfileError):
        w.mount(coupling="gearbox")
    with pytest.raises(ProfileError):
        w.set_mode("left", "velocity")
    with pytest.raises(ProfileError):
        w.set_mode("in", "position")
    with pytest.raises(ProfileError):
        w.set_setpoint("in", float("nan"))
    with pytest.raises(ProfileError):
        simulate_bench(PlantParams(), np.zeros(10), np.zeros(11))
    with pytest.raises(ProfileError):
        MotorParams(Kt=0.0)


def test_saturating_kt_operating_point():
    """Kt_eff = Kt/(1 + (i/kt_sat)^2): the steady input current follows the inverted curve."""
    motor = MotorParams(kt_sat_a=3.0)
    plant = PlantParams(motor_in=motor, ratio=4.0, seed=6)
    _, pts = _bench_levels(plant, 100.0, [0.0, -2.0, 0.0])
    op = bench_operating_point(plant, 100.0, -2.0)
    assert op["current_in_a"] > (op["torque_in_nm"] + motor.Tc) / motor.Kt * 1.05
    assert pts[1]["in_current_a"] == pytest.approx(op["current_in_a"], abs=0.003)


def test_speed_budget():
    """60 s of bench at 1 kHz well under 2 s; stepping far above 5,000 steps/s."""
    import time

    t = wf.time_base(60.0)
    cin, cout = np.full(t.size, 200.0), wf.staircase(t, levels=[0.0, -1.0, 0.0], dwell_s=20.0)
    simulate_bench(PlantParams(), cin[:10], cout[:10])          # compile / load cache
    t0 = time.perf_counter()
    simulate_bench(PlantParams(), cin, cout)
    assert time.perf_counter() - t0 < 2.0
    w = BenchWorld(PlantParams())
    w.mount(coupling="reducer")
    w.set_mode("in", "velocity")
    t0 = time.perf_counter()
    for _ in range(5000):
        w.step()
    assert time.perf_counter() - t0 < 1.0
