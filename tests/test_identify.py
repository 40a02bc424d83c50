"""Identification: the paper's eqs. 6-10 exactly, the default method's accuracy and
interval, the excitation check, speed."""
import json
import time

import numpy as np
import pytest

from gearbench.analysis.calibration import calibrate_motor
from gearbench.analysis.identify import (D_J, TC_J, identify, identify_default,
                                         identify_paper, identify_trace)
from gearbench.analysis.uncertainty import coverage_factor
from gearbench.benchmarks._data import DEV_DIR
from gearbench.errors import ExcitationError
from gearbench.trace import Trace

DEV = DEV_DIR                       # ../shared/datasets/dev beside the checkout


def synth_motor(*, kt=0.05, j=2e-5, d=2e-6, tc=0.008, seconds=3.0, rate=1000.0,
                noise_a=0.004, counts=10000, delay_s=0.0, speed=150.0, amp=60.0, seed=0,
                cog_nm=0.0, cog_order=12):
    """Independent little plant with an exact solution: the speed is a multisine
    ω(t) = speed + Σ a sin(2πft + φ), and the current is what the motor equation
    J ω' + D ω + Tc tanh(ω/0.01) = Kt i requires. Sampled like a drive: floor-quantised
    encoder, 4 mA noise and 1 mA resolution on the current, optional current delay."""
    rng = np.random.default_rng(seed)
    f = np.array([0.7, 1.9, 3.1, 5.3, 8.9])
    ph = rng.uniform(0, 2 * np.pi, f.size)
    a = amp / f.size
    t = np.arange(int(seconds * rate)) / rate

    def angle(tt):
        arg = 2 * np.pi * f[None, :] * tt[:, None] + ph
        return speed * tt - (a / (2 * np.pi * f) * (np.cos(arg) - np.cos(ph))).sum(1)

    def current(tt):
        arg = 2 * np.pi * f[None, :] * tt[:, None] + ph
        w = speed + (a * np.sin(arg)).sum(1)
        acc = (a * 2 * np.pi * f * np.cos(arg)).sum(1)
        cog = cog_nm * np.sin(cog_order * angle(tt) + 0.4)
        return (j * acc + d * w + tc * np.tanh(w / 0.01) + cog) / kt

    th = angle(t)
    q = 2 * np.pi / counts
    pos = np.floor(th / q) * q
    i_meas = current(t - delay_s) + rng.normal(0, noise_a, t.size)
    i_meas = np.round(i_meas / 0.001) * 0.001
    return t, pos, i_meas, {"Kt": kt, "J": j, "D": d, "Tc": tc}


# ------------------------------------------------------------------ paper method
def _exact_paper_data(a21, a22, b2, n=400, dt=0.015, seed=1):
    """θ sequence whose *forward differences* obey α = a21 θ + a22 ω + b2 i exactly."""
    rng = np.random.default_rng(seed)
    i = rng.normal(0.5, 0.3, n)
    th, w = np.zeros(n + 2), np.zeros(n + 2)
    w[0] = 10.0
    for k in range(n + 1):
        a = a21 * th[k] + a22 * w[k] + b2 * (i[k] if k < n else 0.0)
        w[k + 1] = w[k] + dt * a
        th[k + 1] = th[k] + dt * w[k]
    return np.arange(n + 2) * dt, th, np.concatenate([i, [0.0, 0.0]])


def test_paper_eq10_recovers_exact_system_matrices():
    t, th, i = _exact_paper_data(-3.0, -2.5, 4000.0)
    fit = identify_paper(t, th, i, check=False)
    np.testing.assert_allclose(fit.A, [[0, 1], [-3.0, -2.5]], atol=1e-6)
    np.testing.assert_allclose(fit.B, [0, 4000.0], rtol=1e-9, atol=1e-9)
    assert fit.b2 == pytest.approx(4000.0, rel=1e-9)
    assert fit.value(D_J) == pytest.approx(2.5, rel=1e-6)


def test_paper_q_matrices_equal_ordinary_least_squares():
    t, th, i, _ = synth_motor(seconds=1.0)
    fit = identify_paper(t, th, i, check=False)
    dt = t[1] - t[0]
    w = np.diff(th) / dt
    a = np.diff(w) / dt
    X = np.column_stack([th[:-2] - th[0], w[:-1], i[:-2]])
    coef = np.linalg.lstsq(X, a, rcond=None)[0]
    np.testing.assert_allclose([fit.A[1, 0], fit.A[1, 1], fit.B[1]], coef, rtol=1e-8)


def test_paper_15ms_is_decimation_then_method():
    t, th, i, _ = synth_motor(seconds=3.0)
    a = identify(t, th, i, method="paper-15ms", check=False)
    b = identify_paper(t[::15], th[::15], i[::15], check=False)
    assert a.b2 == pytest.approx(b.b2, rel=1e-12)
    assert a.dt_s == pytest.approx(0.015)


# ---------------------------------------------------------------- default method
def test_default_recovers_b2_friction_and_its_interval_covers_truth():
    t, th, i, tr = synth_motor(seed=3)
    fit = identify_default(t, th, i)
    b2 = tr["Kt"] / tr["J"]
    assert fit.b2 == pytest.approx(b2, rel=1e-3)
    assert fit.value(D_J) * tr["J"] + 0 == pytest.approx(tr["D"], rel=0.3)
    assert fit.value(TC_J) * tr["J"] == pytest.approx(tr["Tc"], rel=0.03)
    half = coverage_factor(fit.dof) * fit.b2_std
    assert abs(fit.b2 - b2) <= half + 1e-3 * b2 * 0.1
    # the paper's method on the same data is visibly worse (why the default exists)
    paper = identify(t, th, i, method="paper-15ms", check=False)
    assert abs(paper.b2 / b2 - 1) > 5 * abs(fit.b2 / b2 - 1)


def test_default_absorbs_a_current_delay():
    t, th, i, tr = synth_motor(seed=4, delay_s=0.002)
    b2 = tr["Kt"] / tr["J"]
    fit = identify_default(t, th, i)
    assert fit.b2 == pytest.approx(b2, rel=1e-3)
    assert fit.extras["current_delay_s"] == pytest.approx(0.002, abs=0.0001)
    no_lag = identify_default(t, th, i, lag=False)
    assert abs(no_lag.b2 / b2 - 1) > 2 * abs(fit.b2 / b2 - 1)    # the lag term matters


@pytest.mark.usefixtures("dev_data")
def test_default_calibration_on_dev_data_meets_kt_target():
    truth = json.loads((DEV / "truth.json").read_text())["calibration"]
    for name, tr in truth.items():
        cal = calibrate_motor(Trace.read(DEV / f"calib_{name}_unloaded.csv"),
                              Trace.read(DEV / f"calib_{name}_loaded.csv"), tr["disk_inertia"])
        assert abs(cal.Kt / tr["Kt"] - 1) <= 0.002, name
        assert cal.Kt_ci95[0] < cal.Kt < cal.Kt_ci95[1]
        # honest (model error included) but still useful: half-width <= 0.3 % (was 0.13-0.17 %
        # from noise alone, now 0.19-0.25 %)
        assert (cal.Kt_ci95[1] - cal.Kt_ci95[0]) / 2 <= 0.003 * cal.Kt, name
        assert cal.fit["Kt_std_model"] > 0 and cal.fit["Kt_std_statistical"] > 0
        lo, hi = cal.fit["speed_range_rad_s"]            # forward multisine, ~15-275 rad/s
        assert 0 < lo < 50 and 200 < hi < 400, name
        assert cal.J == pytest.approx(tr["J"], rel=0.01)
        # losses at the calibration speeds (~150 rad/s) are what efficiency needs
        assert cal.loss_torque_nm(150.0) == pytest.approx(tr["D"] * 150 + tr["Tc"], rel=0.01)


# -------------------------------------------------------------- excitation check
def test_constant_speed_is_refused_with_the_fix():
    t = np.arange(3000) * 1e-3
    q = 2 * np.pi / 10000
    th = np.floor(150.0 * t / q) * q
    i = 0.2 + np.random.default_rng(0).normal(0, 0.004, t.size)
    with pytest.raises(ExcitationError, match=r"multisine of at least [\d.e+-]+ rad/s amplitude"):
        identify_default(t, th, i)


def test_spring_and_offset_without_reversals_are_refused_not_guessed():
    t, th, i, _ = synth_motor(seconds=2.0)
    with pytest.raises(ExcitationError, match="reversals"):
        identify_default(t, th, i, bias=True)


def test_identification_of_a_million_samples_is_fast():
    n = 1_000_000
    t = np.arange(n) * 1e-3
    w = 150 + 50 * np.sin(2 * np.pi * 1.3 * t)
    q = 2 * np.pi / 10000
    th = np.floor(np.cumsum(w) * 1e-3 / q) * q
    i = 0.3 + 0.2 * np.cos(2 * np.pi * 1.3 * t) + np.random.default_rng(0).normal(0, 0.004, n)
    identify_default(t[:20000], th[:20000], i[:20000], check=False)
    best = np.inf
    for _ in range(3):
        t0 = time.process_time()     # CPU seconds: what the code costs, whatever else the host runs
        identify_default(t, th, i, check=False)
        best = min(best, time.process_time() - t0)
    # ~0.15-0.3 s of CPU on a quiet 2-core machine (0.63 s by 2026-12-03 on the same host); CPU
    # seconds still grow ~2x when the other core is busy (shared caches), so the budget catches
    # a real slowdown, not a neighbour; on a slower host in proportion (``_host_speed``: the
    # AMD EPYC VM 0.95 s quiet, 1.5x the first host)
    from _host_speed import slower_than_reference
    slower = slower_than_reference()
    assert best < 1.0 * slower, f"{best:.2f} CPU s (host {slower:.2f}x slower)"


# ------------------------------------------------------------------------ cogging
def test_cogging_order_is_found_from_the_data_and_removes_the_bias_on_reversing_runs():
    """3 mN m of order-22 cogging on a reversing run: near each reversal it sits inside
    the filter's band. The scan on the rotor angle finds order 22 (and no other), the
    fit recovers its amplitude, and b2 is unbiased again."""
    kw = dict(speed=0.0, amp=150.0, tc=0.005, j=1e-5, cog_nm=0.003, cog_order=22, seconds=3.0)
    t, th, i, tr = synth_motor(**kw)
    b2 = tr["Kt"] / tr["J"]
    fit = identify_default(t, th, i)
    assert list(fit.extras["cogging"]) == [22]
    assert fit.extras["cogging"][22] * tr["J"] == pytest.approx(0.003, rel=0.05)
    blind = identify_default(t, th, i, cogging=False)
    assert abs(fit.b2 / b2 - 1) < 0.002
    assert abs(blind.b2 / b2 - 1) > 3 * abs(fit.b2 / b2 - 1)
    given = identify_default(t, th, i, cogging=(22,))
    assert given.b2 == pytest.approx(fit.b2, rel=1e-9)


def test_cogging_order_survives_its_collinear_neighbours_on_a_slow_heavy_run():
    """A slow reversing run with a heavy disk covers few revolutions: the screen passes
    orders 19-22 together, nearly collinear, each pair short of the Wald price jointly.
    Backward elimination keeps order 21 (the truth); dropping all at once left b2 +1.6 %
    off (robustness seed 7 case 61, the output motor's loaded run)."""
    from gearbench.benchmarks import robustness as rb

    case = rb.draw_case(61, 7)
    motor = case.plant.motor_out
    run = rb.simulate_case(case)["runs"]["out"][1]
    fit = identify_trace(run, check=False, setpoint_step=True, lag=False)
    assert list(fit.extras["cogging"]) == [motor.cog_order] == [21]
    assert abs(fit.b2 / (motor.Kt / (motor.J + case.disks_kgm2["out"])) - 1) < 0.005


def test_no_cogging_terms_are_kept_without_cogging():
    for kw in (dict(), dict(speed=0.0, amp=150.0, tc=0.005, j=1e-5)):
        for seed in range(3):
            t, th, i, _ = synth_motor(seed=seed, **kw)
            assert identify_default(t, th, i).extras["cogging"] == {}, (kw, seed)


def test_cogging_scan_scores_the_true_order_and_hides_orders_the_filter_removes():
    from gearbench.analysis.identify import cogging_order_scores

    rng = np.random.default_rng(1)
    n = 20000
    w = 2.0 + 8.0 * np.sin(np.linspace(0, 40 * np.pi, n))     # slow, reversing, 6 revs
    th = np.cumsum(w) * 1e-3
    e = 0.3 * np.sin(7 * th) + rng.normal(0, 1, n)
    z = cogging_order_scores(th, w, e, cutoff_hz=40.0)
    assert np.nanargmax(z) == 6 and z[6] > 20 * np.nanmedian(z)
    fast = cogging_order_scores(th, w + 100.0, e, cutoff_hz=40.0)
    assert np.isnan(fast[3:]).all()                           # 100 rad/s: only orders <= 2


def test_reversal_instant_is_taken_from_the_angle_not_the_smoothed_speed():
    """Angle of a reversal with a friction kink (deceleration 1000 before, 400 rad/s² after)
    at t_c = 50.3 samples: the refined speed crosses zero there to 0.02 sample; the
    smoothed speed alone misses by more."""
    from gearbench.analysis import derivatives as dv

    dt = 1e-3
    k = np.arange(120, dtype=float)
    s = (k - 50.3) * dt
    th = np.where(s < 0, -0.5 * 1000 * s ** 2, -0.5 * 400 * s ** 2)
    w = dv.smooth_velocity(th, dt)
    r = dv.refine_reversals(th, w)

    def crossing(v):
        j = int(np.flatnonzero((v[:-1] > 0) & (v[1:] <= 0))[0])
        return j + v[j] / (v[j] - v[j + 1])

    assert crossing(r) == pytest.approx(50.3, abs=0.02)
    assert abs(crossing(w) - 50.3) > 0.05


# ------------------------------------------------------------ units (issue 13)
EMPS = DEV_DIR.parent / "real-emps"
K_EMPS = 2 * np.pi / 2.5e-3        # rad of motor shaft per metre of travel (README)


@pytest.mark.parametrize("k", [180 / np.pi, 2.5e-3 / (2 * np.pi), 1.0])
def test_the_same_trace_in_other_units_gives_the_same_physics(k):
    """No threshold is in the user's unit: degrees / metres give the fit scaled."""
    if not (DEV / "calib_motor_a_unloaded.csv").exists():
        pytest.skip("dev data not present (../shared/datasets/dev)")
    tr = Trace.read(DEV / "calib_motor_a_unloaded.csv")
    t, th, i = tr.time_s, np.asarray(tr["position_rad"]), np.asarray(tr["current_a"])
    ref = identify_default(t, th, i)
    fit = identify_default(t, th * k, i)
    assert fit.b2 == pytest.approx(ref.b2 * k, rel=1e-6)
    assert fit.value(D_J) == pytest.approx(ref.value(D_J), rel=1e-6)
    assert fit.value(TC_J) == pytest.approx(ref.value(TC_J) * k, rel=1e-6)
    assert fit.r2 == pytest.approx(ref.r2, abs=1e-9)


def test_real_emps_metres_and_radians_agree():
    """Real data (EMPS): the metre file was fitted with r2 0.088 when thresholds were in
    rad/s; now it gives the motor-radian file's physics, scaled by k = 2 pi / 2.5 mm."""
    if not (EMPS / "emps_train_m.csv").exists():
        pytest.skip("real EMPS data not present (../shared/datasets/real-emps)")
    fits = {}
    for name in ("emps_train_m.csv", "emps_train_motor_rad.csv"):
        tr = Trace.read(EMPS / name)
        fits[name] = identify_default(tr.time_s, tr["position_rad"], tr["current_a"],
                                      cogging=False)
    m, r = fits["emps_train_m.csv"], fits["emps_train_motor_rad.csv"]
    assert m.r2 > 0.99 and m.r2 == pytest.approx(r.r2, abs=1e-6)
    assert m.b2 * K_EMPS == pytest.approx(r.b2, rel=1e-6)
    # published (IDIM-LS): M 95.11 kg, Fv 203.5 N s/m, Fc 20.39 N; Kt = 1 (force in N)
    mass = 1.0 / m.b2
    assert mass == pytest.approx(95.11, rel=0.02)
    assert m.value(D_J) * mass == pytest.approx(203.5, rel=0.05)
    assert m.value(TC_J) * mass == pytest.approx(20.39, rel=0.05)


def test_cogging_orders_are_per_revolution_in_any_stated_unit():
    """Real data (EMPS pulses): cogging orders are per motor revolution, so the metre
    file with its lead (2.5 mm) gives the motor-radian file's orders and physics;
    without a lead no cogging is fitted (a length is not an angle) instead of orders
    of a 'revolution' of 2 pi metres."""
    if not (EMPS / "emps_pulses_m.csv").exists():
        pytest.skip("real EMPS data not present (../shared/datasets/real-emps)")
    m_tr = Trace.read(EMPS / "emps_pulses_m.csv")
    r_tr = Trace.read(EMPS / "emps_pulses_motor_rad.csv")
    r = identify_default(r_tr.time_s, r_tr["position_rad"], r_tr["current_a"])
    m = identify_default(m_tr.time_s, m_tr["position_rad"], m_tr["current_a"],
                         rad_per_unit=K_EMPS)
    assert sorted(m.extras["cogging"]) == sorted(r.extras["cogging"])
    assert m.b2 * K_EMPS == pytest.approx(r.b2, rel=1e-3)
    assert m.value(TC_J) * K_EMPS == pytest.approx(r.value(TC_J), rel=1e-3)
    none = identify_default(m_tr.time_s, m_tr["position_rad"], m_tr["current_a"],
                            rad_per_unit=None)
    assert none.extras["cogging"] == {}


def test_a_fit_far_below_what_the_noise_allows_is_refused():
    from gearbench.analysis.identify import check_fit_quality

    check_fit_quality(r2=0.97, floor_r2=0.999)          # fine
    with pytest.raises(ExcitationError, match="explains little.*allows 0.999"):
        check_fit_quality(r2=0.088, floor_r2=0.999)
    with pytest.raises(ExcitationError, match="explains little"):
        check_fit_quality(r2=float("nan"), floor_r2=0.9)


# ------------------------------------------------- issue 23: beyond our own plant
from gearbench.benchmarks._joint_sim import JOINTS, simulate_joint  # noqa: E402
from gearbench.benchmarks._real import physical  # noqa: E402
from gearbench.analysis.identify import KT_J  # noqa: E402


def _joint(name, seed=1):
    joint = next(j for j in JOINTS if j.name == name)
    return joint, simulate_joint(joint, seed=seed)


def test_friction_dominated_100hz_joint_torque_side_recovers_its_inertia():
    """Robot wrist, 100 Hz, Coulomb ~80 % of the rms current, gravity, ripple and a
    coloured disturbance: the accel form attenuates Kt/J (J 4-5x too large, errors in
    variables: current content the model lacks sits in its regressor); the torque side
    (the default) holds J, Fv, Fc inside their 95 % intervals, and the cross-check
    flags the accel form's disagreement."""
    joint, d = _joint("wrist")
    kw = dict(check=False, load_rad_per_unit=1.0, rad_per_unit=None)
    fit = identify_default(d["time_s"], d["position_rad"], d["current_a"], **kw)
    ph = physical(fit, joint.gain_nm_a)
    for key, truth in (("J", joint.J), ("Fv", joint.Fv), ("Fc", joint.Fc)):
        v, half = ph[key]
        assert abs(v - truth) <= half, (key, v, half, truth)
    acc = identify_default(d["time_s"], d["position_rad"], d["current_a"], form="accel",
                           form_spread=False, **kw)
    # (1.8x since stuck stretches are left out of the fit; 4-5x before)
    assert physical(acc, joint.gain_nm_a)["J"][0] > 1.5 * joint.J
    cc = acc.extras["cross_check"]
    assert not cc["agree"] and KT_J in cc["differ"] and cc["supported"] == "torque-ls"
    # with the spread of the two directions as model error, the accel form's own
    # interval admits how little it knows: it then holds the truth
    acc = identify_default(d["time_s"], d["position_rad"], d["current_a"], form="accel", **kw)
    v, half = physical(acc, joint.gain_nm_a)["J"]
    assert abs(v - joint.J) <= half


def test_load_angle_option_fits_gravity_not_cogging():
    """The shoulder carries gravity G cos(q): fitted as load_sin/load_cos of the load
    angle (order 1), in accel units −(G/gain)/(J/gain) on the cosine."""
    joint, d = _joint("shoulder")
    fit = identify_default(d["time_s"], d["position_rad"], d["current_a"], check=False,
                           load_rad_per_unit=1.0, rad_per_unit=None)
    assert "load_cos" in fit.names and fit.extras["cogging"] == {}
    want = -joint.gravity_nm / joint.J
    assert abs(fit.value("load_cos") - want) <= 2.5 * fit.std("load_cos")
    assert fit.extras["identified"]["load_cos"]


def test_refusal_advice_is_in_the_runs_own_numbers():
    """A run short of Kt/J's 5 % is not refused with a fixed recipe: the message quotes
    its speeds, reversals and band and the factor it falls short by; friction that it
    does identify is still returned (check on: warning, per ampere)."""
    joint, d = _joint("wrist", seed=0)
    fit = identify_default(d["time_s"][:2000], d["position_rad"][:2000], d["current_a"][:2000],
                           load_rad_per_unit=1.0, rad_per_unit=None)
    warn = " ".join(fit.extras.get("warnings", []))
    assert "not identifiable" in warn and "reversals" in warn and "longer run" in warn
    assert fit.extras["identified"][D_J]
    pa = fit.extras["per_ampere"]
    assert set(pa) == {"J/Kt", "D/Kt", "Tc/Kt"}
    # friction per ampere does not pass through J: known to a few %, and right
    tc, tc_std = pa["Tc/Kt"]
    assert tc_std < 0.05 * tc and abs(tc - joint.Fc / joint.gain_nm_a) < 3 * tc_std


@pytest.mark.parametrize("step", [1, 4, 10])
def test_real_emps_at_1khz_250hz_100hz_within_2_percent_of_published(step):
    if not (EMPS / "emps_train_motor_rad.csv").exists():
        pytest.skip("real EMPS data not present (../shared/datasets/real-emps)")
    tr = Trace.read(EMPS / "emps_train_motor_rad.csv")
    fit = identify_default(tr.time_s[::step], tr["position_rad"][::step],
                           tr["current_a"][::step])
    mass = K_EMPS / fit.b2
    assert mass == pytest.approx(95.1089, rel=0.02)
    assert fit.value(D_J) * mass == pytest.approx(203.5034, rel=0.02)
    assert fit.value(TC_J) / fit.b2 == pytest.approx(20.3935, rel=0.02)
    assert fit.extras["cross_check"]["agree"]


# ------------------------------------------ issue 23: stuck stretches left out exactly
def test_weighted_filter_is_the_plain_one_with_unit_weight_and_blind_where_weight_is_zero():
    """The motor equation multiplied by a 0/1 weight before the filter: with w = 1 the
    filtered signals are ``consistent_derivatives``' own; where w = 0 (a stuck stretch and
    its margin) whatever the current does there cannot reach the fit."""
    from gearbench.analysis import derivatives as dv

    rng = np.random.default_rng(3)
    t = np.arange(3000) * 1e-3
    th = np.cumsum(50 * np.sin(2 * np.pi * 1.3 * t) + 5) * 1e-3
    i = rng.normal(size=t.size)
    taps = dv.lowpass_fir(40.0, 1000.0)
    plain = dv.consistent_derivatives(th, {"current": i}, 1e-3, taps)
    ones = dv.weighted_derivatives(th, {"current": i}, 1e-3, taps, np.ones(t.size))
    for key in ("velocity", "acceleration", "current"):
        np.testing.assert_allclose(ones[key], plain[key], rtol=1e-9, atol=1e-9 * np.abs(plain[key]).max())
    w = np.ones(t.size)
    w[1200:1500] = 0.0
    garbage = i.copy()
    garbage[1201:1499] += 100.0          # inside the zero weight, clear of the 3-tap match
    a = dv.weighted_derivatives(th, {"current": i}, 1e-3, taps, w)["current"]
    b = dv.weighted_derivatives(th, {"current": garbage}, 1e-3, taps, w)["current"]
    np.testing.assert_array_equal(a, b)


def test_equation_weight_leaves_out_dwells_with_a_margin_not_fast_crossings():
    from gearbench.analysis.identify import equation_weight

    w = np.r_[np.full(50, 5.0), np.linspace(5, -5, 5), np.full(50, -5.0)]   # fast crossing
    assert equation_weight(w, 0.1, 1e-3).min() == 1.0
    w = np.r_[np.full(50, 5.0), np.zeros(20), np.full(50, 5.0)]              # 20 ms dwell
    out = equation_weight(w, 0.1, 1e-3)
    assert out[40:80].max() == 0.0                           # 10 ms margin each side,
    assert np.all(np.diff(out[29:41]) <= 0) and 0 < out[35] < 1   # then a 10 ms ramp
    assert out[:30].min() == 1.0 and out[90:].min() == 1.0


def test_equation_weight_leaves_out_a_dwell_only_while_the_drive_pushes():
    """A rotor at rest that nothing pushes (before a speed step from rest) satisfies
    J θ'' = Kt i = 0 and stays in; a dwell held by friction against a current is left out."""
    from gearbench.analysis.identify import equation_weight

    rng = np.random.default_rng(3)
    w = np.r_[np.zeros(200), np.linspace(0, 300, 30), np.full(100, 300.0)]
    noise = rng.normal(0, 0.004, len(w))
    at_rest = equation_weight(w, 0.1, 1e-3, current=noise, current_noise=0.004)
    assert at_rest.min() == 1.0
    pushed = equation_weight(w, 0.1, 1e-3, current=noise + 0.2, current_noise=0.004)
    assert pushed[:200].max() == 0.0


def test_equation_weight_leaves_out_a_dwell_whose_current_ramps_through_zero():
    """Static friction holds any current below the breakaway: a dwell whose current sits
    at +12 mA (under 2 sigma of the noise) and then ramps to the -80 mA breakaway has a
    median |i| within 3 sigma, yet the drive pushes; it is left out (the dwell median
    kept it in with zero friction: robustness seed 3 case 62, r² 0.980 -> 0.9994)."""
    from gearbench.analysis.identify import equation_weight

    rng = np.random.default_rng(1)
    w = np.r_[np.full(50, 5.0), np.zeros(100), np.full(50, -5.0)]
    current = rng.normal(0, 0.007, len(w))
    current[50:120] += 0.012
    current[120:150] += np.linspace(0.012, -0.08, 30)
    assert np.median(np.abs(current[50:150])) < 3 * 0.007
    assert equation_weight(w, 0.1, 1e-3, current=current, current_noise=0.007)[60:140].max() == 0.0


def test_equation_weight_finds_a_touch_and_go_stop_from_the_angle():
    """A rotor that stops for 12 ms without reversing while the drive pushes: the
    21-sample cubic speed rings to +0.6 rad/s there (a false double reversal, no dwell
    below the standstill speed); the angle's own 6-sample difference finds the stop."""
    from gearbench.analysis import derivatives as dv
    from gearbench.analysis.identify import equation_weight, standstill_speed

    dt = 1e-3
    w = np.r_[np.full(100, -20.0), np.linspace(-20, 0, 10), np.zeros(12), np.linspace(0, -20, 10),
              np.full(100, -20.0)]
    q = 2 * np.pi / 80000
    th = np.round(np.cumsum(w) * dt / q) * q
    ws = dv.smooth_velocity(th, dt, half_width=10)
    assert ws[105:135].max() > 0.3                       # the smoother's false reversal
    still = standstill_speed(th, ws, dt)
    current = np.where(w == 0, -0.06, -0.1)
    assert equation_weight(ws, still, dt, current=current, current_noise=0.004).min() == 1.0
    out = equation_weight(ws, still, dt, current=current, current_noise=0.004, angle=th)
    assert out[101:130].max() == 0.0 and out[:80].min() == 1.0 and out[160:].min() == 1.0


def test_a_creeping_reversal_is_a_dwell_whatever_the_encoder():
    """A reversal that creeps through zero (the current swinging through the friction's
    transition while a 20-bit encoder still counts) is left out once ``creep_speed`` is
    given, and kept with the encoder's band alone; a start from rest is not a reversal."""
    from gearbench.analysis.identify import equation_weight
    dt = 1e-3
    w = np.r_[np.linspace(50, 0.05, 100), np.linspace(0.05, -0.05, 60), np.linspace(-0.05, -50, 100)]
    current = np.r_[np.full(100, 0.2), np.linspace(0.2, -0.2, 60), np.full(100, -0.2)]
    still = 1e-3                   # 1 count per 6 samples of a 2^20-count encoder
    assert equation_weight(w, still, dt, current=current, current_noise=0.004).min() == 1.0
    out = equation_weight(w, still, dt, current=current, current_noise=0.004, creep_speed=0.05)
    assert out[100:160].max() == 0.0 and out[:60].min() == 1.0 and out[-60:].min() == 1.0
    start = np.r_[np.zeros(50), np.linspace(0.0, 50, 100)]       # from rest: no sign change
    pushed = np.r_[np.zeros(50), np.full(100, 0.3)]
    assert equation_weight(start, still, dt, current=pushed, current_noise=0.004,
                           creep_speed=0.05)[60:].min() == 1.0


def test_speed_step_from_rest_keeps_its_acceleration():
    """The paper's speed step from rest: nothing is left out (the acceleration from rest is
    the run's Kt/J information); with the dwell left out and its 10 ms margin + ramp the
    step cost Kt up to 0.25 % (seed 3, 'in' motor: +0.249 % -> -0.104 %)."""
    from gearbench.benchmarks import accuracy as A
    from gearbench.sim import simulate_motor

    motor, _ = A._motors()
    cmd = A._excitation("step", 3.0)
    u = simulate_motor(motor, cmd, seed=3000)
    lo = simulate_motor(motor, cmd, disk_kgm2=A.DISK_KGM2, seed=3001)
    fu = identify(u.time_s, u["position_rad"], u["current_a"], check=False)
    assert fu.extras.get("left_out_share", 0.0) == 0.0
    cal = A._calibrate(u, lo, "default")
    assert abs(cal.Kt / motor.Kt - 1) < 0.002


def test_drive_sampling_reads_the_description_and_names_a_bad_field():
    from gearbench.analysis.identify import drive_sampling
    from gearbench.errors import TraceError

    def trace(drive):
        return Trace(np.arange(3.0), {"position_rad": np.zeros(3)}, {"drive": drive}, "run.csv")
    assert drive_sampling(trace({"setpoint": "step", "current": "instant"})) == "kick"
    assert drive_sampling(trace({"setpoint": "step", "current": "mean"})) == "plain"
    assert drive_sampling(trace({"setpoint": "interpolated", "current": "instant"})) == "plain"
    assert drive_sampling(trace({"setpoint": "step"})) is None
    assert drive_sampling(Trace(np.arange(3.0), {"position_rad": np.zeros(3)}, {}, "x")) is None
    with pytest.raises(TraceError, match=r"run.csv: meta drive.current is 'sampled'"):
        drive_sampling(trace({"setpoint": "step", "current": "sampled"}))


def test_encoder_step_is_read_through_a_files_printed_decimals():
    """A CSV that prints k·q to fixed decimals rounds each increment by up to two digits;
    the encoder's step (which sets the standstill band) is still q, not the print's digit."""
    from gearbench.analysis.identify import encoder_resolution

    rng = np.random.default_rng(3)
    for counts, decimals in ((2**17, 8), (2**12, 6), (2**20, 9)):
        q = 2 * np.pi / counts
        k = np.cumsum(rng.integers(-40, 41, 3000))
        printed = np.round(k * q, decimals)
        assert encoder_resolution(printed) == pytest.approx(q, rel=1e-4), (counts, decimals)
        assert encoder_resolution(k * q) == pytest.approx(q, rel=1e-6)     # full precision, as before
    # a print coarser than the encoder: the print's digit is the step the data holds
    fine = np.round(np.cumsum(rng.integers(-40, 41, 3000)) * 2 * np.pi / 2**24, 5)
    assert encoder_resolution(fine) == pytest.approx(1e-5, rel=1e-3)
    # not quantised at all: no coarse grid is invented
    assert encoder_resolution(np.cumsum(rng.normal(0, 1e-3, 3000))) < 1e-6


def test_a_joint_that_sticks_between_point_to_point_moves_keeps_its_inertia():
    """A second, independent joint simulator (``_joint_stick_sim``: Karnopp stiction, a PID
    position loop, trapezoidal moves with dwells the joint sits stuck through, 100 Hz,
    gravity): the default's J, Fv and Fc hold the truth within their 95 % intervals. The
    textbook filtered least squares comes as close here (J +1.3 % vs our −1.5 %) but its
    white-noise interval (±0.5 %) misses it: residuals coloured by the filter and the
    unmodelled disturbance are not white (over the benchmark's 12 such traces its J
    interval holds the truth once, ours 12 times)."""
    from gearbench.benchmarks._joint_stick_sim import STICK_JOINTS, simulate_stick_joint
    from gearbench.benchmarks._real import textbook_idim

    joint = next(j for j in STICK_JOINTS if j.name == "shoulder")
    d = simulate_stick_joint(joint, motion="p2p", seed=1)
    fit = identify_default(d["time_s"], d["position_rad"], d["current_a"], check=False,
                           load_rad_per_unit=1.0, rad_per_unit=None)
    ph = physical(fit, joint.gain_nm_a)
    for key, truth in d["truth"].items():
        v, half = ph[key]
        assert abs(v - truth) <= half, (key, v, half, truth)
    tb = textbook_idim(d["time_s"], d["position_rad"], d["current_a"], joint.gain_nm_a, gravity=True)
    assert abs(tb["J"][0] - joint.J) > tb["J"][1]


def test_a_stop_as_long_as_the_standstill_window_is_left_out_at_100_hz():
    """A stick-slip joint at 100 Hz stops for 54-68 ms at each reversal: 7 equal angle
    readings, the drive's current ramping through the static band. The centred 6-sample
    difference is zero on one reading only (a dwell needs 3), so the stop stayed in the
    equation with a Coulomb sign that does not hold there; a held angle counts in full."""
    from gearbench.analysis import derivatives as dv
    from gearbench.analysis.identify import equation_weight, smoothing_half_width, standstill_speed
    dt, count = 0.01, 2 * np.pi / 2 ** 17
    steps = np.r_[-np.tile([2.0, 3.0], 50), np.zeros(6), np.tile([2.0, 3.0], 50)]   # counts/sample
    theta = np.cumsum(np.r_[0.0, steps]) * count
    stop = np.r_[np.zeros(100, bool), np.ones(7, bool), np.zeros(100, bool)]
    current = np.where(stop, np.linspace(-0.3, 0.3, len(theta)), np.sign(np.gradient(theta)) * 0.3)
    w = dv.smooth_velocity(theta, dt, half_width=smoothing_half_width(dt))
    weight = equation_weight(w, standstill_speed(theta, w, dt), dt, current=current,
                             current_noise=1e-3, angle=theta)
    assert np.all(weight[stop] == 0.0), weight[stop]
    assert np.all(weight[:80] == 1.0) and np.all(weight[-80:] == 1.0)


def test_the_default_filter_stops_a_decade_above_the_motions_band():
    """Under a position loop what lies above the motion's band is the loop's answer to
    disturbances (closed-loop bias); the default cutoff is 10x the band, at most 40 Hz and
    rate/10, and the filter never longer than an eighth of the run."""
    from gearbench.analysis.identify import MIN_FILTER_RUNS, default_cutoff, motion_band_hz
    from gearbench.benchmarks._joint_stick_sim import STICK_JOINTS, simulate_stick_joint

    d = simulate_stick_joint(STICK_JOINTS[0], motion="sine", seed=0, rate_hz=100)
    band = motion_band_hz(d["time_s"], d["position_rad"])
    assert 0.3 < band < 1.0            # two sines at 0.15-0.6 Hz
    fit = identify_default(d["time_s"], d["position_rad"], d["current_a"], check=False,
                           load_rad_per_unit=1.0, rad_per_unit=None)
    assert fit.extras["cutoff_hz"] == pytest.approx(10 * band)
    # a 1 kHz multisine up to 10 Hz keeps 40 Hz; a fast motion at 100 Hz keeps rate/10
    t = np.arange(3000) * 1e-3
    th = sum(np.sin(2 * np.pi * f * t) / f for f in (1.0, 3.0, 7.0, 10.0))
    assert default_cutoff(t, th) == 40.0
    t = np.arange(2000) * 1e-2
    assert default_cutoff(t, np.sin(2 * np.pi * 4.0 * t)) == pytest.approx(10.0)
    # a short slow run: the filter (≈ 5.5·rate/cutoff taps) at most 1/8 of it
    t = np.arange(600) * 1e-2
    cut = default_cutoff(t, np.sin(2 * np.pi * 0.3 * t))
    assert cut == pytest.approx(5.5 * 100 * MIN_FILTER_RUNS / 600)


def test_a_calibration_filters_both_runs_alike_at_the_rates_cutoff(monkeypatch):
    """Eq. 17 cancels what the unloaded and loaded fits share: one cutoff for both, the
    rate's (min(40 Hz, rate/10)) - not the motion band's, which cost the adaptive bench
    procedure plants (calibration.py) - even where the runs are slow."""
    import gearbench.analysis.calibration as C
    from gearbench.analysis.identify import default_cutoff
    from gearbench.errors import GearbenchError

    t = np.arange(30000) * 1e-3
    rng = np.random.default_rng(0)

    def run(f_hz):
        th = np.sin(2 * np.pi * f_hz * t) + 0.2 * np.sin(2 * np.pi * 2.3 * f_hz * t)
        acc = np.gradient(np.gradient(th, t), t)
        cur = 0.05 * acc + 0.02 * np.sign(np.gradient(th, t)) + rng.normal(0, 1e-3, len(t))
        return Trace(t, {"position_rad": th, "current_a": cur}, source=f"{f_hz} Hz")
    unloaded, loaded = run(0.8), run(0.5)
    assert default_cutoff(t, loaded["position_rad"]) < 20.0     # identify alone would go lower
    seen = []
    real = C.identify_trace

    def spy(trace, **kw):
        seen.append(kw.get("cutoff_hz"))
        return real(trace, **kw)
    monkeypatch.setattr(C, "identify_trace", spy)
    try:
        C.calibrate_motor(unloaded, loaded, 1e-3)
    except GearbenchError:
        pass                    # refused or not, both runs were filtered alike
    assert len(seen) >= 2 and all(c == pytest.approx(40.0) for c in seen)
