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


# Every switchable effect, each with the size the model says it must have (not merely
# "the output changed"): (parameter, value, relative tolerance). Base: the default motor
# without cogging; seed 5; steady windows, torque-mode steps or fits as noted.
EFFECT_SIZES = [
    ("Tc", 0.02, 0.005), ("Ts", 0.01, 0.005), ("D", 2e-5, 0.005), ("C", 1e-3, 0.005),
    ("cog_amp", 0.01, 0.05), ("ripple_amp", 0.1, 0.05), ("kt_sat_a", 0.5, 0.02),
    ("current_lag_s", 5e-3, 0.01), ("shaft_stiffness", 2.0, 0.03), ("backlash_rad", 0.05, 0.03),
    ("counts_per_rev", 500, 0.0), ("delay_samples", 2, 0.0), ("current_offset_a", 0.01, 0.005),
    ("current_gain", 1.05, 0.005), ("current_noise_a", 0.02, 0.05), ("current_resolution_a", 0.01, 0.05),
]
BASE = MotorParams(cog_amp=0.0)
DISK = 1e-5


def _with(**kw) -> MotorParams:
    return MotorParams(**{**BASE.__dict__, **kw})


def _hold(m, speed, seconds=2.0, **kw):
    return simulate_motor(m, np.full(int(seconds / T), float(speed)), seed=5, include_truth=True, **kw)


def _push(m, amps, n, **kw):
    return simulate_motor(m, np.full(n, float(amps)), mode="torque", seed=5, include_truth=True, **kw)


def _effect_size(name, value):
    """(measured, expected) size of one effect."""
    kt, m = BASE.Kt, _with(**{name: value})
    steady = lambda tr: _mean(tr["current_a"], 1.0, 2.0)                       # noqa: E731
    if name in ("Tc", "D", "current_offset_a", "current_gain", "C"):
        a, b = _hold(BASE, 40.0), _hold(m, 40.0)
        want = {"Tc": (value - BASE.Tc) / kt, "D": (value - BASE.D) * 40.0 / kt, "current_offset_a": value,
                "current_gain": (value - 1.0) * steady(a),
                "C": value * _mean(b["position_rad"], 1.0, 2.0) / kt}[name]     # spring C θ at the mean angle
        return steady(b) - steady(a), want
    if name == "Ts":                          # Stribeck: Ts·exp(−(ω/ws)²) at ω = ws
        return steady(_hold(m, BASE.ws)) - steady(_hold(BASE, BASE.ws)), value * math.exp(-1.0) / kt
    if name in ("cog_amp", "ripple_amp"):     # slow (2 rad/s, inside the speed loop): current
        tr = _hold(m, 2.0, 4.0)               # cancels the torque: i ≈ (T + cog·sin 6θ)/(Kt(1 + r sin 6θ))
        th, i = tr["position_rad"][1000:], tr["current_a"][1000:]
        coef = np.linalg.lstsq(np.column_stack([np.ones_like(th), np.sin(6 * th), np.cos(6 * th)]), i,
                               rcond=None)[0]
        load = (BASE.D * 2.0 + BASE.Tc) / kt
        return float(coef[1]), (value / kt if name == "cog_amp" else -value * load)
    if name == "kt_sat_a":                    # from rest at 0.5 A: torque Kt·i/(1 + (i/i_sat)²)
        a, b = _push(BASE, 0.5, 100), _push(m, 0.5, 100)
        ratio = b["true_velocity_rad_s"][50] / a["true_velocity_rad_s"][50]
        return ratio, (kt * 0.5 / (1 + (0.5 / value) ** 2) - BASE.Tc) / (kt * 0.5 - BASE.Tc)
    if name == "current_lag_s":               # first order: 63 % of a step after one time constant
        return float(_push(m, 0.3, 20)["true_current_a"][int(round(value / T))]), 0.3 * (1 - math.exp(-1))
    if name == "shaft_stiffness":             # two-mass resonance sqrt(k (J + j)/(J j))
        w = _push(m, 0.3, 600, disk_kgm2=DISK)["true_velocity_rad_s"][100:]
        k = np.arange(len(w))
        w = (w - np.polyval(np.polyfit(k, w, 2), k)) * np.hanning(len(w))
        f = np.fft.rfftfreq(len(w), T)[np.argmax(np.abs(np.fft.rfft(w)))]
        return float(f), math.sqrt(value * (BASE.J + DISK) / (BASE.J * DISK)) / (2 * math.pi)
    if name == "backlash_rad":                # inside the gap the rotor turns without the disk
        a, b = _push(BASE, 0.3, 10, disk_kgm2=DISK), _push(m, 0.3, 10, disk_kgm2=DISK)
        return b["true_velocity_rad_s"][5] / a["true_velocity_rad_s"][5], (BASE.J + DISK) / BASE.J
    if name == "counts_per_rev":              # position on the encoder's grid, never between
        pos = _hold(m, 40.0, 0.5)["position_rad"] / (2 * math.pi / value)
        return float(np.max(np.abs(pos - np.round(pos)))), 0.0
    if name == "delay_samples":               # the same samples, exactly value samples later
        quiet = _with(current_noise_a=0.0)    # (the noise is drawn per reported sample)
        a = _hold(quiet, 40.0, 0.5)["current_a"]
        b = _hold(_with(current_noise_a=0.0, delay_samples=value), 40.0, 0.5)["current_a"]
        return float(np.max(np.abs(b[value:] - a[:-value]))), 0.0
    if name == "current_noise_a":             # same draws, scaled: std of the difference
        a, b = _hold(BASE, 40.0), _hold(m, 40.0)
        return float(np.std(b["current_a"][500:] - a["current_a"][500:])), value - BASE.current_noise_a
    if name == "current_resolution_a":        # rounding error of a quantum q: q/√12
        a, b = _hold(BASE, 40.0), _hold(m, 40.0)
        return float(np.std(b["current_a"][500:] - a["current_a"][500:])), value / math.sqrt(12)
    raise AssertionError(name)


@pytest.mark.parametrize("name,value,rel", EFFECT_SIZES)
def test_each_effect_has_the_size_the_model_gives(name, value, rel):
    got, want = _effect_size(name, value)
    if want == 0.0:
        assert got <= 1e-9, f"{name}={value}: {got}"
    else:
        assert got == pytest.approx(want, rel=rel), f"{name}={value}: {got:.6g}, model {want:.6g}"


def test_every_switchable_effect_is_sized():
    switchable = {"Tc", "Ts", "D", "C", "cog_amp", "ripple_amp", "kt_sat_a", "current_lag_s",
                  "shaft_stiffness", "backlash_rad", "counts_per_rev", "delay_samples",
                  "current_offset_a", "current_gain", "current_noise_a", "current_resolution_a"}
    assert {e[0] for e in EFFECT_SIZES} == switchable


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


def test_simulation_truth_is_the_plant_at_the_commanded_point_whatever_was_measured():
    """result.json's simulation_truth: each point at its speed setpoint and output current
    command (bench_operating_point), never at a measured speed or estimated torque, so a
    wrong estimate cannot drag its own reference along."""
    from gearbench.sim.truth import simulation_truth

    plant = PlantParams(ratio=8.0, eta_mesh=0.8, drag_torque_nm=0.01)
    point = {"in_command": 150.0, "out_command": -1.2, "speed_in_rad_s": 149.7, "torque_out_nm": 0.061,
             "eta_incremental": 0.79, "eta_absolute": 0.7}
    (got,) = simulation_truth(plant, [point])["efficiency"]
    op = bench_operating_point(plant, 150.0, -1.2)
    assert got["eta_absolute"] == op["eta_absolute"] and got["torque_out_nm"] == op["torque_out_nm"]
    assert got["eta_incremental"] == 0.8 and got["speed_in_rad_s"] == 150.0
    skewed = {**point, "speed_in_rad_s": 120.0, "torque_out_nm": 0.09, "eta_absolute": 0.5}
    assert simulation_truth(plant, [skewed])["efficiency"] == [got]
    # the truth moves with the command: 10 % more braking current, a different absolute η
    (more,) = simulation_truth(plant, [{**point, "out_command": -1.32}])["efficiency"]
    assert more["torque_out_nm"] == pytest.approx(
        op["torque_out_nm"] + 0.12 * plant.motor_out.Kt, rel=1e-9)


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
    t0 = time.process_time()     # CPU seconds: the code's cost, not the host's load
    simulate_bench(PlantParams(), cin, cout)
    assert time.process_time() - t0 < 2.0
    w = BenchWorld(PlantParams())
    w.mount(coupling="reducer")
    w.set_mode("in", "velocity")
    t0 = time.process_time()
    for _ in range(5000):
        w.step()
    assert time.process_time() - t0 < 1.0
