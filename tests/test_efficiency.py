"""Efficiency: signs on a hand-made bench, drift cancellation, windows, dev and sim data."""
import json

import numpy as np
import pytest
from scipy import stats

from gearbench.analysis.calibration import MotorCalibration, calibrate_motor
from gearbench.analysis.efficiency import efficiency, steady_windows
from gearbench.analysis.uncertainty import coverage_acceptance
from gearbench.benchmarks._data import DEV_DIR
from gearbench.errors import ExcitationError, TraceError
from gearbench.trace import Trace

DEV = DEV_DIR                       # ../shared/datasets/dev beside the checkout
M_IN = MotorCalibration(0.05, (0.05, 0.05), 2e-5, 2e-6, 0.008, "hand")
M_OUT = MotorCalibration(0.04, (0.04, 0.04), 1e-5, 1e-6, 0.005, "hand")


def hand_bench(*, ratio=5.0, eta=0.9, drag=0.003, speed_in=100.0, levels=(0, 0.5, 1.0, 2.0, 0),
               dwell=2.0, drift_a_per_s=0.0, noise=0.0, seed=0):
    """Steady-state bench built from the power balance, no simulator:
    P_out = η (P_in − drag ω_in); shaft torques from each motor's Kt and losses."""
    rate = 1000.0
    n = int(dwell * rate) * len(levels)
    t = np.arange(n) / rate
    lvl = np.asarray(levels, float)[np.minimum((t // dwell).astype(int), len(levels) - 1)]
    w_out = speed_in / ratio
    brake = -np.sign(w_out) * lvl                     # braking current opposes the output speed
    t_out = -M_OUT.Kt * brake + M_OUT.D * w_out + M_OUT.Tc * np.sign(w_out)
    t_in = t_out * w_out / (eta * speed_in) + drag
    i_in = (t_in + M_IN.D * speed_in + M_IN.Tc) / M_IN.Kt + drift_a_per_s * t
    rng = np.random.default_rng(seed)
    cols = {"in_position_rad": speed_in * t, "in_current_a": i_in + rng.normal(0, noise, n),
            "out_position_rad": w_out * t, "out_current_a": brake + rng.normal(0, noise, n),
            "in_command": np.full(n, speed_in), "out_command": brake}
    expect_abs = (t_out * w_out) / (t_in * speed_in)
    return Trace(t, cols, source="hand.csv"), expect_abs, lvl


@pytest.mark.parametrize("ratio", [5.0, -5.0])
def test_signs_on_a_hand_made_bench(ratio):
    tr, expect_abs, lvl = hand_bench(ratio=ratio)
    res = efficiency(tr, M_IN, M_OUT)
    assert res.ratio == pytest.approx(5.0) and res.ratio_sign == np.sign(ratio)
    assert len(res.points) == 3 and len(res.references) == 2          # zero loads are references
    for p, level in zip(res.points, (0.5, 1.0, 2.0)):
        assert p.eta_incremental == pytest.approx(0.9, abs=1e-9)
        k = int(np.flatnonzero(lvl == level)[-1])
        assert p.eta_absolute == pytest.approx(expect_abs[k], abs=1e-9)
        assert p.torque_out_nm == pytest.approx(M_OUT.Kt * level + M_OUT.D * 20 + M_OUT.Tc, rel=1e-9)
    assert [p.window.out_command for p in res.points] == [-np.sign(ratio) * v for v in (0.5, 1.0, 2.0)]


def test_reference_interpolation_cancels_a_linear_drift():
    tr, _, _ = hand_bench(drift_a_per_s=0.002)
    res = efficiency(tr, M_IN, M_OUT)
    for p in res.points:
        assert p.eta_incremental == pytest.approx(0.9, abs=1e-9)
    one_ref = efficiency(tr.slice(0, 8000), M_IN, M_OUT)                 # drop the last zero level
    assert abs(one_ref.points[-1].eta_incremental - 0.9) > 1e-3


def test_interval_coverage_is_95_percent_within_a_two_sided_binomial_bound():
    """200 noisy benches (fixed seeds): the incremental interval must hold the truth in
    95 % of them — too narrow falls below the bound, ten times too wide above it."""
    n = 200
    hits = 0
    for seed in range(n):
        tr, _, _ = hand_bench(noise=0.004, seed=seed, levels=(0, 1.0, 0), dwell=1.5)
        (p,) = efficiency(tr, M_IN, M_OUT).points
        lo, hi = p.eta_incremental_ci95
        hits += lo <= 0.9 <= hi
    low, high = coverage_acceptance(n)
    assert low <= hits <= high, f"{hits}/{n} intervals hold the truth, accepted {low}..{high}"


def test_interval_is_student_t_on_the_stored_std_and_adds_kt_uncertainty_in_quadrature():
    tr, _, _ = hand_bench(noise=0.004, seed=1, levels=(0, 1.0, 0))
    (p,) = efficiency(tr, M_IN, M_OUT).points
    d = p.to_dict()
    assert d["eta_incremental_std"] == p.eta_incremental_std > 0
    assert 2 <= p.eta_incremental_dof < 100             # block means: a few dof per window
    lo, hi = p.eta_incremental_ci95
    # Student-t on the stored dof (t₀.₉₇₅ from scipy here, not from the code under test)
    assert (hi - lo) / 2 == pytest.approx(stats.t.ppf(0.975, p.eta_incremental_dof) * p.eta_incremental_std,
                                          rel=1e-9)
    u_rel = 0.002                                     # η ∝ 1/Kt_in: u_rel(η) gains u_rel(Kt_in)
    wide_in = MotorCalibration(0.05, (0.0498, 0.0502), 2e-5, 2e-6, 0.008, "hand", Kt_std=0.05 * u_rel,
                               Kt_dof=1e6)
    (q,) = efficiency(tr, wide_in, M_OUT).points
    assert q.eta_incremental_std ** 2 == pytest.approx(
        p.eta_incremental_std ** 2 + (p.eta_incremental * u_rel) ** 2, rel=1e-6)
    assert q.eta_incremental_dof > p.eta_incremental_dof   # a known (type B) part raises ν


def test_one_disk_for_both_motors_cancels_in_the_incremental_efficiency():
    """Kt_in and Kt_out calibrated with the same disk share its error (correlation 1 for
    the disk part): η_inc ∝ Kt_out/Kt_in does not see it; two different disks add
    u_rel(j)² twice. First-order GUM with the covariance."""
    tr, _, _ = hand_bench(noise=0.004, seed=1, levels=(0, 1.0, 0))
    (p0,) = efficiency(tr, M_IN, M_OUT).points
    u = 0.0025                                          # ±0.5 % measured disk: u_rel = 0.25 %

    def with_disk(m, name):
        fit = {"disk": name, "Kt_std_disk": m.Kt * u}
        return MotorCalibration(m.Kt, m.Kt_ci95, m.J, m.D, m.Tc, "hand", fit, Kt_std=m.Kt * u, Kt_dof=1e6)
    (same,) = efficiency(tr, with_disk(M_IN, "disk_a"), with_disk(M_OUT, "disk_a")).points
    (two,) = efficiency(tr, with_disk(M_IN, "disk_a"), with_disk(M_OUT, "disk_b")).points
    assert same.eta_incremental_std == pytest.approx(p0.eta_incremental_std, rel=1e-6)
    assert two.eta_incremental_std ** 2 == pytest.approx(
        p0.eta_incremental_std ** 2 + 2 * (p0.eta_incremental * u) ** 2, rel=1e-6)
    assert p0.eta_absolute_std < same.eta_absolute_std < two.eta_absolute_std


def test_steady_windows_drop_settle_time_and_ramps():
    t = np.arange(5000) / 1000.0
    cin = np.minimum(t * 400, 100.0)                  # ramp for 0.25 s, then constant
    cout = np.where(t < 2.5, 0.0, -1.0)
    w = steady_windows(t, cin, cout, settle_s=0.5)
    assert [(a, b) for a, b in w] == [(750, 2500), (3000, 5000)]


def test_bench_without_zero_load_or_with_wrong_sign_is_refused():
    tr, _, _ = hand_bench(levels=(0.5, 1.0))
    with pytest.raises(TraceError, match="out_command.*zero-load"):
        efficiency(tr, M_IN, M_OUT)
    tr, _, _ = hand_bench()
    flipped = tr.with_columns(out_current_a=-tr["out_current_a"], out_command=-tr["out_command"],
                              in_current_a=2 * tr["in_current_a"][0] - tr["in_current_a"])
    with pytest.raises(ExcitationError, match="does not rise under load"):
        efficiency(flipped, M_IN, M_OUT)


@pytest.mark.usefixtures("dev_data")
def test_dev_bench_meets_targets():
    truth = json.loads((DEV / "truth.json").read_text())
    cal = {}
    for name, t in truth["calibration"].items():
        cal[name] = calibrate_motor(Trace.read(DEV / f"calib_{name}_unloaded.csv"),
                                    Trace.read(DEV / f"calib_{name}_loaded.csv"), t["disk_inertia"])
    b = truth["bench"]
    res = efficiency(Trace.read(DEV / b["file"]), cal[b["motor_in"]], cal[b["motor_out"]])
    assert res.ratio == pytest.approx(b["n"], rel=1e-4)
    loaded = [p for p in b["points"] if p["out_current_cmd"] != 0]
    assert len(res.points) == len(loaded)
    for p, tp in zip(res.points, loaded):
        assert abs(p.eta_incremental - b["eta_mesh"]) <= 0.002
        assert abs(p.eta_absolute - tp["eta_abs"]) <= 0.003
        assert p.eta_absolute_ci95[0] < tp["eta_abs"] < p.eta_absolute_ci95[1]
        # intervals include model error yet stay useful on clean data (now ~0.3-0.4 pp)
        assert (p.eta_absolute_ci95[1] - p.eta_absolute_ci95[0]) / 2 <= 0.005
        assert (p.eta_incremental_ci95[1] - p.eta_incremental_ci95[0]) / 2 <= 0.005
        # both motors run inside their calibration runs' speeds (in 180, out ~26 rad/s)
        assert not p.loss_extrapolated and p.to_dict()["loss_extrapolated"] is False
        assert p.loss_speed_range_in_rad_s[0] < p.speed_in_rad_s < p.loss_speed_range_in_rad_s[1]


def test_simulated_bench_with_true_motor_models():
    sim = pytest.importorskip("gearbench.sim")
    from gearbench.sim import waveforms as wf

    mi, mo = sim.MotorParams(), sim.MotorParams(Kt=0.046, J=1.2e-5, D=1.5e-6, Tc=0.006)
    plant = sim.PlantParams(motor_in=mi, motor_out=mo, ratio=5.0, eta_mesh=0.9, drag_torque_nm=0.005)
    t = wf.time_base(12.0)
    cout = -wf.staircase(t, levels=[0, 0.5, 1.0, 0], dwell_s=3.0)
    tr = sim.simulate_bench(plant, wf.ramp(t, slope=400, final=150.0), cout, seed=3)
    cal = [MotorCalibration(m.Kt, (m.Kt, m.Kt), m.J, m.D, m.Tc, "truth") for m in (mi, mo)]
    res = efficiency(tr, *cal)
    assert len(res.points) == 2
    for p in res.points:
        truth = sim.bench_operating_point(plant, p.speed_in_rad_s, p.window.out_command)
        assert abs(p.eta_incremental - truth["eta_incremental"]) <= 0.002
        assert abs(p.eta_absolute - truth["eta_absolute"]) <= 0.003


def test_window_means_are_robust_to_ripple_of_unknown_period():
    """A ripple with a non-integer number of periods per window (CVT pulsation, cogging)
    leaks up to amplitude/(π·periods) into a flat mean; the Tukey-weighted mean of
    ``measure_windows`` leaves under 1e-3 of the amplitude."""
    from gearbench.analysis.efficiency import measure_windows

    tr, _, lvl = hand_bench(dwell=3.0)
    base = tr["in_current_a"].copy()
    t = tr.time_s
    for f_hz in (9.37, 23.1, 61.7):           # 25 - 160 periods in a 2.5 s window
        rippled = Trace(t, {**{n: tr[n] for n in tr.names},
                            "in_current_a": base + 0.05 * np.sin(2 * np.pi * f_hz * t + 0.3)})
        clean = measure_windows(tr, settle_s=0.5)
        wins = measure_windows(rippled, settle_s=0.5)
        for c, w in zip(clean, wins):
            assert abs(w.current_in_a - c.current_in_a) < 0.05e-3, f_hz
            flat = float(np.mean(rippled["in_current_a"][w.start:w.stop]) -
                         np.mean(base[w.start:w.stop]))
            assert abs(flat) > abs(w.current_in_a - c.current_in_a)


def test_loss_extrapolation_is_flagged_and_widens_the_absolute_interval():
    """The loss D ω + Tc is linear in (D, Tc): a forward run at speeds around c pins it down
    at c, var(ω) = a (ω − c)² + b, so its propagated variance grows with the distance of
    the operating speed from the calibrated speeds."""
    def motor(m, centre, fit_range):
        a, b = 1e-14, 1e-12                        # (D, Tc) covariance of a run centred at c
        cov = ((a, -a * centre), (-a * centre, a * centre ** 2 + b))
        fit = {"speed_range_rad_s": list(fit_range)} if fit_range else {}
        return MotorCalibration(m.Kt, m.Kt_ci95, m.J, m.D, m.Tc, "hand", fit, cov)
    tr, _, _ = hand_bench(speed_in=100.0, levels=(0, 1.0, 0))      # output at 20 rad/s
    m_in = motor(M_IN, 100.0, (50, 250))
    (inside,) = efficiency(tr, m_in, motor(M_OUT, 20.0, (10, 30))).points
    (far,) = efficiency(tr, m_in, motor(M_OUT, 200.0, (150, 250))).points
    (unknown,) = efficiency(tr, M_IN, M_OUT).points
    assert not inside.loss_extrapolated and far.loss_extrapolated
    assert not unknown.loss_extrapolated and unknown.to_dict()["loss_speed_range_in_rad_s"] is None
    d = far.to_dict()
    assert d["loss_extrapolated"] is True and d["loss_speed_range_out_rad_s"] == [150.0, 250.0]
    assert d["speed_out_rad_s"] == pytest.approx(20.0, rel=1e-3)
    assert far.eta_absolute == pytest.approx(inside.eta_absolute, abs=1e-12)
    width = lambda p: p.eta_absolute_ci95[1] - p.eta_absolute_ci95[0]
    assert width(far) > 3 * width(inside)


def test_calibration_runs_that_disagree_on_losses_widen_the_loss_covariance():
    """Both runs measure one motor's friction; a disagreement beyond their covariances is
    model error and enters the (D, Tc) covariance as LOSS_RUN_SPREAD x ΔΔᵀ; one within
    them (Mahalanobis distance² below LOSS_RUN_CHI2) is their noise and adds nothing."""
    from gearbench.analysis.calibration import LOSS_RUN_SPREAD, calibrate_from_fits
    from gearbench.analysis.identify import D_J, KT_J, TC_J, IdentificationResult

    J, DISK = 1.5e-5, 2e-5
    def fit(b2, d, tc, inertia):
        cov = np.diag([1.0, 1e-4, 1.0])
        return IdentificationResult("default", (KT_J, D_J, TC_J), (b2, d / inertia, tc / inertia),
                                    cov, 30, 1e-3, 3000, 300.0, 0.99, 1.0, 5.0, np.eye(2),
                                    np.array([0.0, b2]), {"speed_range_rad_s": [20.0, 200.0]})
    kt = 0.05
    agree = calibrate_from_fits(fit(kt / J, 2e-6, 0.008, J), fit(kt / (J + DISK), 2e-6, 0.008, J + DISK), DISK)
    differ = calibrate_from_fits(fit(kt / J, 2e-6, 0.008, J), fit(kt / (J + DISK), 3e-6, 0.007, J + DISK), DISK)
    extra = np.asarray(differ.loss_covariance) - np.asarray(agree.loss_covariance)
    delta = np.array([-1e-6, 1e-3])
    np.testing.assert_allclose(extra, LOSS_RUN_SPREAD * np.outer(delta, delta), rtol=1e-6, atol=1e-22)
    assert differ.fit["loss_run_difference"] == pytest.approx(list(delta))
    assert differ.fit["speed_range_rad_s"] == [20.0, 200.0]
    # the runs' (D, Tc) standard errors here: 0.38 uN m s and 38 uN m; a quarter of each apart
    noisy = calibrate_from_fits(fit(kt / J, 2e-6, 0.008, J), fit(kt / (J + DISK), 2.1e-6, 0.00801, J + DISK), DISK)
    np.testing.assert_allclose(noisy.loss_covariance, agree.loss_covariance, rtol=1e-9)
    assert noisy.fit["loss_run_difference"] == pytest.approx([-1e-7, -1e-5])


def _with_level_offsets(tr, lvl, offsets_a):
    """``tr`` with the input current shifted by ``offsets_a[level]`` on each level's samples."""
    i_in = tr["in_current_a"].copy()
    for level, off in offsets_a.items():
        i_in[lvl == level] += off
    return tr.with_columns(in_current_a=i_in)


def test_a_zero_load_level_off_the_braking_line_is_not_the_reference():
    """A mesh whose power flow reverses at no load puts the zero-load current off the line
    of the braking levels (``staircase_fit``); eq. 18 then comes from their slope, with
    the drift the two zero-load levels measure taken out, and the biased secant kept."""
    tr, _, lvl = hand_bench(noise=0.002, seed=1, drift_a_per_s=0.0005)
    clean = efficiency(tr, M_IN, M_OUT, incremental="secant")
    assert all(p.incremental_method == "secant" for p in clean.points)   # on the line: unchanged
    res = efficiency(_with_level_offsets(tr, lvl, {0.0: 0.003}), M_IN, M_OUT)
    for p in res.points:
        assert p.incremental_method == "slope"
        lo, hi = p.eta_incremental_secant_ci95                           # 3 mA / Δi_in off
        assert abs(p.eta_incremental_secant - 0.9) > 0.005 and not lo <= 0.9 <= hi
        assert abs(p.eta_incremental - 0.9) < min(0.002, 3 * p.eta_incremental_std)
        assert p.eta_incremental_ci95[0] <= 0.9 <= p.eta_incremental_ci95[1]


def test_levels_scattering_beyond_their_window_errors_widen_the_intervals():
    """A disturbance slower than a window's blocks moves whole levels: their scatter about
    the straight line (χ² beyond its 99 % quantile) widens every window error of the speed
    by the Birge ratio, so the intervals hold the truth the shifted levels miss."""
    levels = (0, 0.5, 1.0, 1.5, 2.0, 0)
    tr, _, lvl = hand_bench(noise=0.002, seed=2, levels=levels)
    plain = efficiency(tr, M_IN, M_OUT)
    wander = {0.0: 0.0, 0.5: 0.002, 1.0: -0.002, 1.5: 0.002, 2.0: -0.002}
    res = efficiency(_with_level_offsets(tr, lvl, wander), M_IN, M_OUT)
    for p, q in zip(plain.points, res.points):
        assert q.eta_incremental_std > 5 * p.eta_incremental_std
        assert q.eta_incremental_ci95[0] <= 0.9 <= q.eta_incremental_ci95[1]
        assert p.eta_incremental_dof > q.eta_incremental_dof >= 2     # ν of the scatter: 6 − 4


def test_levels_on_one_line_give_eq18_from_the_line_through_every_level():
    """``incremental="auto"`` (the default): where a speed's levels lie on one straight
    line within their errors, every secant estimates the same slope; the line through
    every level (zero-load included, the drift free) is that slope with a smaller error
    — at half load the secant's is about twice the line's here — and its interval holds
    the truth as often as it should. A staircase that bends beyond its errors keeps each
    point's secant (eq. 18 as printed)."""
    levels = (0, 0.5, 1.0, 1.5, 2.0, 0)
    hits_line = hits_secant = 0
    n = 100
    ratios = []
    for seed in range(n):
        tr, _, _ = hand_bench(noise=0.004, seed=seed, levels=levels, drift_a_per_s=0.0003)
        auto = efficiency(tr, M_IN, M_OUT)
        sec = efficiency(tr, M_IN, M_OUT, incremental="secant")
        assert {p.incremental_method for p in auto.points} <= {"slope", "secant"}
        if seed == 0:
            assert all(p.incremental_method == "slope" for p in auto.points)
            assert len({p.eta_incremental for p in auto.points}) == 1    # one value per speed
            assert auto.points[0].eta_incremental_secant == sec.points[0].eta_incremental
        ratios.append(sec.points[0].eta_incremental_std / auto.points[0].eta_incremental_std)
        lo, hi = auto.points[0].eta_incremental_ci95
        hits_line += lo <= 0.9 <= hi
        lo, hi = sec.points[0].eta_incremental_ci95
        hits_secant += lo <= 0.9 <= hi
    assert np.median(ratios) > 1.8                       # half load: the line's error is smaller
    assert 88 <= hits_line <= 100 and 88 <= hits_secant <= 100   # both intervals honest
    # a staircase bent beyond its errors (3 mA at the middle level): the secants stay
    tr, _, lvl = hand_bench(noise=0.002, seed=3, levels=levels)
    bent = efficiency(_with_level_offsets(tr, lvl, {1.0: 0.003}), M_IN, M_OUT)
    assert all(p.incremental_method == "secant" for p in bent.points)


def test_the_staircase_slope_pools_its_windows_degrees_of_freedom():
    """Eq. 18's slope rests on every level's mean: its standard error's dof is the
    Welch–Satterthwaite pool of the windows' (9 each here), not the smallest window's."""
    from gearbench.analysis.efficiency import SteadyWindow, incremental_slope

    def window(k, dof):
        return SteadyWindow(0, 1, float(k), 100.0, -0.5 * k, 0.1 + 0.08 * k, 1e-3, -0.5 * k, 1e-3,
                            100.0, 10.0, dof, dof)

    five = [window(k, 9.0) for k in range(5)]
    b, sb, dof = incremental_slope(five)
    assert b == pytest.approx(-0.16) and sb > 0
    # shares ∝ d² = 1, 1/4, 0, 1/4, 1 of 9 dof each: (5/2)² / (17/8 / 9)
    assert dof == pytest.approx(9 * 6.25 / 2.125)
    one_short = five[:4] + [window(4, 2.0)]
    assert incremental_slope(one_short)[2] < dof
