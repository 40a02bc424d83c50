"""Robustness benchmark (gearbench/benchmarks/robustness.py) on a small fixed subset, and
the two identification fixes it motivated: the sub-sample Coulomb regressor and the
standstill handling at reversals."""
import functools

import numpy as np
import pytest

from gearbench.analysis import derivatives as dv
from gearbench.analysis.identify import identify_default
from scipy import stats

from gearbench.analysis.uncertainty import coverage_acceptance, design_effect
from gearbench.benchmarks import robustness as R

ALPHA = 0.01       # chance that a correct method fails one of the binomial checks below


def test_draws_are_deterministic_and_forward_runs_stay_forward():
    a, b = R.draw_case(5, 0), R.draw_case(5, 0)
    assert a.plant == b.plant and np.array_equal(a.commands["in"], b.commands["in"])
    assert not np.array_equal(a.commands["in"], R.draw_case(6, 0).commands["in"])
    for k in range(12):
        c = R.draw_case(k, 0)
        if not c.reversing:
            assert min(c.commands["in"].min(), c.commands["out"].min()) > 0


def test_covering_draws_move_only_the_commands_and_reach_the_bench_speeds():
    """The benchmark's calibrations reach each motor's bench speed (as validate demands
    of a profile) where the drive's limits let them; the plant is drawn as before, a
    forward run stays forward, a reversing one still reverses."""
    reached = 0
    for k in range(40):
        a, c = R.draw_case(k, 1), R.draw_case(k, 1, cover_bench_speed=True)
        assert c.plant == a.plant and c.bench_speed_rad_s == a.bench_speed_rad_s
        for side, speed in (("in", c.bench_speed_rad_s), ("out", c.bench_speed_rad_s / c.plant.ratio)):
            cmd = c.commands[side]
            if c.reversing:
                assert cmd.min() < 0 < cmd.max()
            else:
                assert cmd.min() > 0
                # the same swing, only moved
                np.testing.assert_allclose(np.ptp(cmd), np.ptp(a.commands[side]), rtol=1e-12)
                # the top reached beyond the loop's rounding; below, down to half the speed
                assert cmd.min() <= speed <= np.percentile(cmd, 98), (k, side)
            reached += bool(np.percentile(cmd, 2) <= speed <= np.percentile(cmd, 98))
    assert reached >= 50, reached       # of 80 motors (54: forward dips stop at half)


def test_a_case_sampled_at_250_hz_is_the_same_plant_and_commands_every_fourth_sample():
    """``--period-ms 4``: the drawn plant and commands, sampled every 4 ms (a period-mean
    current drive averages the whole new period), simulated and analysed at that period."""
    c = R.draw_case(3, 7, cover_bench_speed=True)
    s = R.with_period(c, 4e-3)
    assert s.plant.period_s == 4e-3 and s.plant.ratio == c.plant.ratio
    for side in ("in", "out"):
        np.testing.assert_array_equal(s.commands[side], c.commands[side][::4])
        m, m4 = getattr(c.plant, f"motor_{side}"), getattr(s.plant, f"motor_{side}")
        assert m4.current_avg_s == (4e-3 if m.current_avg_s > 0 else 0.0)
        assert m4.Kt == m.Kt and m4.counts_per_rev == m.counts_per_rev
    data = R.simulate_case(s)
    unloaded, _ = data["runs"]["in"]
    assert np.median(np.diff(unloaded.time_s)) == pytest.approx(4e-3)
    assert len(unloaded) == len(s.commands["in"])
    assert np.median(np.diff(data["bench"].time_s)) == pytest.approx(4e-3)
    with pytest.raises(ValueError, match="whole multiple"):
        R.with_period(c, 2.5e-3)


def test_coulomb_regressor_is_the_triangle_mean_of_the_sign_with_sub_sample_reversals():
    dt = 1e-3
    t = np.arange(40) * dt
    t0 = 17.3e-3                                   # reversal between samples 17 and 18
    w = 800.0 * (t - t0)
    got = dv.coulomb_regressor(np.zeros_like(t), dt, velocity=w)
    fine = np.linspace(-1, 1, 20001)               # s/dt over [t_k − dt, t_k + dt]
    tri = 1 - np.abs(fine)
    for k in range(1, 39):
        want = np.sum(tri * np.sign(800.0 * (t[k] + fine * dt - t0))) / np.sum(tri)
        assert got[k] == pytest.approx(want, abs=2e-4), k
    assert got[16] == -1 and got[19] == 1 and -1 < got[17] < got[18] < 1


def test_standstill_marks_dwells_not_fast_crossings():
    w = np.array([5, 2, 0.05, -0.05, 0.02, 0.01, -3, -6, 0.08, -4], float)
    np.testing.assert_array_equal(dv.standstill(w, 0.1), [0, 0, 1, 1, 1, 1, 0, 0, 0, 0])


def test_reversing_run_with_sticking_is_no_longer_biased_by_percent():
    """Case 31 of seed 0: Coulomb friction 11 mN m on a 4 Hz speed loop, reversing; the
    rotor sticks at each reversal. The old sampled tanh regressor was off by ~7 % in the
    accel form (the torque form it is now fitted in is less sensitive to it: 0.6 %)."""
    case = R.draw_case(31, 0)
    u, lo = R.simulate_case(case)["runs"]["in"]
    m, j = case.plant.motor_in, case.disks_kgm2["in"]

    def kt_err(**kw):
        fu = identify_default(u.time_s, u["position_rad"], u["current_a"], check=False, **kw)
        fl = identify_default(lo.time_s, lo["position_rad"], lo["current_a"], check=False, **kw)
        return abs(j * fu.b2 * fl.b2 / (fu.b2 - fl.b2) / m.Kt - 1)

    # the accel-form tanh fit is not even positive here: identify falls back to the
    # plain torque-side fit (its cross-check), which is off by 1.3 %
    new, old = kt_err(), kt_err(friction_width_rad_s=1.0, form="accel")
    assert old > 0.01 and new < old / 2


def test_misses_are_split_into_noise_limited_and_biased_and_coverage_is_counted():
    ok = R.Outcome([0.1], [0.1], [0.1], [0.05], [0.05], [0.05], [True], [True], [True])
    noisy = R.Outcome([0.5], [0.1], [0.1], [0.3], [0.05], [0.05], [True], [True], [True])
    biased = R.Outcome([0.1], [0.1], [0.9], [0.05], [0.05], [0.2], [True], [True], [False])
    assert [o.verdict() for o in (ok, noisy, biased)] == ["meet", "noise", "biased"]
    assert R.Outcome(error="TraceError: x").verdict() == "error"
    s = R.summarise([{"default": o} for o in (ok, noisy, biased)], methods=("default",))["default"]
    assert s["ok"] == pytest.approx(1 / 3) and s["noise"] == pytest.approx(1 / 3)
    assert s["biased"] == pytest.approx(1 / 3)
    assert s["cover"]["abs"] == pytest.approx(2 / 3) and s["cover"]["kt"] == 1.0
    # per quantity: only the absolute efficiency of the third plant is a biased miss
    assert s["biased_by"] == {"kt": 0.0, "inc": 0.0, "abs": pytest.approx(1 / 3)}
    # median |error|/sigma per quantity: Kt 0.1/0.05, 0.5/0.3, 0.1/0.05 -> 2, 1.67, 2
    assert s["z_median"]["kt"] == pytest.approx(2.0) and s["z_median"]["abs"] == pytest.approx(2.0)
    assert np.isnan(R.summarise([{"default": R.Outcome(error="x")}], ("default",))["default"]["z_median"]["kt"])


def test_the_coverage_an_honest_method_shows_is_binomial_on_its_independent_units():
    # 100 plants: honest 95 % intervals cover 90-99 % of them in 95 % of benchmarks, and
    # fall inside the 93-97 % band only ~3 times in 4
    h = R.honest_coverage_range(100)
    assert h["range"] == (0.90, 0.99) and h["p_band"] == pytest.approx(0.754, abs=1e-3)
    h = R.honest_coverage_range(200)
    assert h["range"] == (0.92, 0.98) and h["p_band"] == pytest.approx(0.860, abs=1e-3)
    assert np.isnan(R.honest_coverage_range(0)["p_band"])
    # the units: a plant's two motors for Kt, the plant for its efficiency points
    two = R.Outcome([0.1, 0.2], [0.1] * 3, [0.1] * 3, [0.05] * 2, [0.05] * 3, [0.05] * 3,
                    [True, False], [True] * 3, [True] * 3)
    s = R.summarise([{"default": two}, {"default": R.Outcome(error="x")}], ("default",))["default"]
    assert s["honest"]["kt"] == R.honest_coverage_range(2)
    assert s["honest"]["inc"] == R.honest_coverage_range(1)


def test_reversing_case_with_cogging_meets_kt_and_its_interval_covers():
    """Case 2 of seed 0: reversing, 1.4 mN m of order-12 cogging on the input motor; before
    the cogging terms its absolute efficiency was 8-10 pp off (friction absorbed the
    cogging near reversals)."""
    out = R.run_case(R.draw_case(2, 0), methods=("default",))["default"]
    assert not out.error, out.error
    assert abs(out.kt_err_pct[0]) <= R.TARGETS["kt_pct"] and out.kt_cover[0]
    assert max(map(abs, out.abs_err_pp)) < 1.0 and all(out.abs_cover)


# ------------------------------------------------------------------ honest intervals
@pytest.fixture(scope="module")
def seed1_runs():
    """All 40 plants of robustness seed 1 (the model-error constants were chosen on seed 0)."""
    cases = [R.draw_case(k, 1) for k in range(40)]
    return cases, [R.simulate_case(c) for c in cases]


def _summary(runs):
    cases, sims = runs
    outs = [R.run_case(c, ("default",), d) for c, d in zip(cases, sims)]
    return outs, R.summarise(outs, ("default",))["default"]


@pytest.fixture(scope="module")
def seed1_default(seed1_runs):
    """The default method on seed 1's 40 plants, computed once for the checks that read it."""
    return _summary(seed1_runs)


def test_default_meets_its_claims_on_every_plant_of_a_held_out_seed_and_paper_does_not(seed1_runs, seed1_default):
    """All 40 plants of seed 1, none left out: the fraction meeting every target is
    checked against the claim (``R.CLAIMS``) with a one-sided binomial bound, the
    median errors against theirs; the paper's method, on the first 12, meets none."""
    cases, sims = seed1_runs
    outs, s = seed1_default
    assert s["fail"] == 0
    n = len(outs)
    meet = sum(o["default"].meets_targets() for o in outs)
    floor = int(stats.binom.ppf(ALPHA, n, R.CLAIMS["meet_fraction"]))
    assert meet >= floor, f"{meet}/{n} plants meet every target; a {R.CLAIMS['meet_fraction']:.0%} claim needs >= {floor}"
    for key in ("kt", "inc", "abs"):
        median = float(np.median(np.abs(s[key])))
        assert median <= R.CLAIMS[f"{key}_median"], (key, median)
    paper = [R.run_case(c, ("paper",), d)["paper"] for c, d in zip(cases[:12], sims[:12])]
    assert sum(o.meets_targets() for o in paper) == 0


def _cover_counts(outs):
    return {q: (sum(c for o in outs for c in getattr(o["default"], f"{q}_cover")),
                sum(1 for o in outs for _ in getattr(o["default"], f"{q}_cover")))
            for q in ("kt", "inc", "abs")}


def test_intervals_cover_95_percent_on_a_held_out_seed_and_stay_useful(seed1_runs, seed1_default):
    """Coverage against the nominal 95 %: each quantity above its binomial lower bound
    (too narrow), all intervals pooled inside the two-sided bound (too wide fails too).
    The per-quantity checks treat the intervals as independent, which makes them stricter
    than they should be (the points of one plant share a calibration and miss together).
    The pooled check, two-sided, counts plants as clusters: its trials are divided by the
    measured design effect (Kish), so a plant whose eight intervals miss together counts
    as the fewer independent trials it is; all intervals holding still fails (deff 1)."""
    outs, s = seed1_default
    counts = _cover_counts(outs)
    for q, (hits, n) in counts.items():
        low, _ = coverage_acceptance(n, alpha=ALPHA)
        assert hits >= low, f"{q}: {hits}/{n} intervals hold the truth, needs >= {low}"
    hits, n, deff, low, high = _pooled(outs)
    assert low <= hits / deff, (f"pooled: {hits}/{n} intervals hold the truth (design effect {deff:.2f}: "
                                f"{hits / deff:.1f} of {n / deff:.1f} independent), accepted {low}..{high}")
    # most absolute points extrapolate a motor's loss (the output motor turns n times slower
    # than its calibration runs); those must cover too
    assert s["n_abs_extrapolated"] > len(s["abs"]) / 2 and s["cover_abs_extrapolated"] >= 0.9
    median = lambda key, which=outs: float(np.median([v for o in which for v in getattr(o["default"], key)]))
    cases = seed1_runs[0]
    forward = [o for o, c in zip(outs, cases) if not c.reversing]
    # % (0.13 % from noise alone); forward plants: 0.22 % before stuck stretches were left
    # out, 0.24 % after. Reversing plants' Kt intervals are honest since (median 0.37 % ->
    # 1.4 %: a rotor that sticks carries no Kt information), so they are not held to it
    assert median("kt_std_pct", forward) * 1.96 < 0.25
    # pp: 0.23 before the shared setpoint-step term and the overlapping-window covariance,
    # 0.45 with them, 0.43 with stuck stretches left out (seed 1)
    assert median("abs_std_pp") * 1.96 < 0.45


def _pooled(outs):
    """All intervals pooled, plants as clusters: (hits, n, design effect, accepted low, high)."""
    per_plant = np.array([[sum(c for q in ("kt", "inc", "abs") for c in getattr(o["default"], f"{q}_cover")),
                           sum(len(getattr(o["default"], f"{q}_cover")) for q in ("kt", "inc", "abs"))]
                          for o in outs])
    hits, n = per_plant.sum(axis=0)
    deff = design_effect(per_plant[:, 0], per_plant[:, 1])
    low, high = coverage_acceptance(max(1, round(n / deff)), alpha=ALPHA)
    print(f"\npooled: {hits}/{n} hold the truth, design effect {deff:.2f}, accepted {low}..{high} of {round(n / deff)}")
    return hits, n, deff, low, high


@pytest.mark.xfail(strict=True, reason="known: the intervals are too wide on seed 1 (317/320; "
                   "incremental 120/120, absolute 120/120) since a held angle counts as a dwell "
                   "(identify.samples._held) and removed reversing plant 32's biased absolute misses "
                   "(2.3 pp, the 3 clustered misses that had kept this check inside its bound); "
                   "a Kt interval too wide in the bulk (median |z| 0.36-0.40) widens every "
                   "efficiency interval built on it")
def test_pooled_intervals_are_not_too_wide_on_a_held_out_seed(seed1_default):
    """The upper side of the pooled two-sided check: all intervals holding is a failure
    too (intervals wider than the data needs). Seed 1 held 317/320 with the fixed Kt
    model term (above the bound); 314/320 since Kt's model error is measured per
    calibration (``calibration.MODEL_VARIANTS``), 3 of the 6 misses one reversing plant's
    biased absolute efficiency; 317/320 again once that bias was removed (strict xfail:
    it fails the suite as soon as the intervals are narrowed enough to pass)."""
    outs, _ = seed1_default
    hits, n, deff, low, high = _pooled(outs)
    assert hits / deff <= high, (f"pooled: {hits}/{n} intervals hold the truth (design effect {deff:.2f}), "
                                 f"accepted {low}..{high}")


@pytest.mark.xfail(strict=True, reason="known: since the speed loop's ripple term (identify.SPEED_ERR) "
                   "and the period-mean match (derivatives.match_period_means) took out the biases "
                   "the model-error terms covered, seed 1's Kt intervals hold the truth 78/80 "
                   "without the terms as with them: the terms are no longer shown to be needed "
                   "on simulated plants (measured 2026-12-06 with the model variants off, seeds "
                   "0/1/3/7/8/17: Kt coverage 95.5/95.5/96.0/95.5/97.0/95.5 % against 95.0/94.5/"
                   "95.5/95.0/95.0/94.5 % with them, as many plants biased; kept for real benches "
                   "whose physics the model does not hold)")
def test_without_the_model_error_terms_the_same_intervals_under_cover(seed1_runs, seed1_default, monkeypatch):
    """The check above can fail: without the unshared b2 model error (MODEL_B2_REL, for
    the default measured per calibration: calibration.MODEL_VARIANT_SPREAD) the
    Kt intervals hold the truth clearly less often (seed 1: 72/80 against 77/80; the
    overlapping covariance alone covers the efficiency points since it replaced the
    disjoint blocks, so LOSS_RUN_SPREAD no longer decides those)."""
    import gearbench.analysis.calibration as cal
    import gearbench.analysis.torque_constant as tq
    with_terms = _cover_counts(seed1_default[0])["kt"]
    monkeypatch.setattr(tq, "MODEL_B2_REL", 0.0)
    # the variants unmeasured (model_variants=False) with MODEL_B2_REL at 0: the same Kt
    # and Kt_std as MODEL_VARIANT_SPREAD at 0, without the refits that spread would weigh by 0
    monkeypatch.setattr(R, "calibrate_motor", functools.partial(cal.calibrate_motor, model_variants=False))
    monkeypatch.setattr(cal, "LOSS_RUN_SPREAD", 0.0)
    hits, n = _cover_counts(_summary(seed1_runs)[0])["kt"]
    assert hits <= with_terms[0] - 3 and hits / n < 0.93, ("kt", hits, n, with_terms)


def test_drive_stepping_its_setpoint_is_fitted_with_one_setpoint_step_term_for_both_runs():
    """Seed 7 case 89, input motor: the drive applies each speed setpoint as a step
    (no interpolation) and reports an instantaneous current sample. Fitted apart, b2 of
    the unloaded run is ~1 % high at ~40 sigma and Kt −0.2 % at 2 sigma; one shared
    setpoint-step coefficient for the two runs brings Kt within 0.1 % and its interval
    (the drive's loop not declared: declared, the kick is computed, −0.06 ± 0.11 %)."""
    from gearbench.analysis.calibration import calibrate_motor
    from gearbench.analysis.identify import DRIVE_LOOP_KEYS
    case = R.draw_case(89, 7)
    m = case.plant.motor_in
    assert m.setpoint_interpolation == 0 and m.current_avg_s == 0.0
    u, lo = R.simulate_case(case)["runs"]["in"]
    declared = calibrate_motor(u, lo, case.disks_kgm2["in"])
    assert "kick_a_per_rad_s" in declared.fit and abs(declared.Kt / m.Kt - 1) < 0.001
    for t in (u, lo):
        for key in DRIVE_LOOP_KEYS:
            del t.meta["drive"][key]
    shared = calibrate_motor(u, lo, case.disks_kgm2["in"])
    apart = calibrate_motor(u, lo, case.disks_kgm2["in"], setpoint_step=False)
    assert shared.fit["setpoint_step"]["kept"] and "setpoint_step" not in apart.fit
    assert abs(shared.Kt / m.Kt - 1) < 0.001
    assert shared.Kt_ci95[0] <= m.Kt <= shared.Kt_ci95[1]
    assert abs(apart.Kt / m.Kt - 1) > 2 * abs(shared.Kt / m.Kt - 1)


def test_overlapping_covariance_is_honest_for_coloured_residuals():
    """Least squares of an AR(1)-coloured noise (ρ = 0.9) on a slow regressor: the
    overlapping-window covariance matches the true spread of the estimate over 300
    repeats (white OLS covariance is ~4x too small), with ~1.5 (n/L − 1) dof."""
    from scipy.signal import lfilter

    from gearbench.analysis.uncertainty import block_covariance, covariance_block
    rng = np.random.default_rng(3)
    n = 4000
    x = np.sin(2 * np.pi * np.arange(n) / 500.0)
    est, var = [], []
    for _ in range(300):
        e = lfilter([1.0], [1.0, -0.9], rng.normal(size=n))
        b = (x @ e) / (x @ x)
        r = e - b * x
        L = covariance_block(r, 20)
        cov, dof, _ = block_covariance(x[None, :], r, np.array([[x @ x]]), block=L)
        est.append(b)
        var.append(cov[0, 0])
    ratio = np.mean(var) / np.var(est)
    assert 0.75 < ratio < 1.3
    assert dof == int(1.5 * (n / L - 1))


def test_overlapping_covariance_keeps_its_scale_with_long_windows():
    """A fit's scores sum to zero, so window sums of a fifth of the run are short of the
    truth by 1 − L/n unless normalised as Meketon and Schmeiser do (n/(n − L)): white
    noise on an offset and a sine, L = n/5, 2000 repeats; without it the ratio is 0.75
    (a 250 Hz calibration run's b2 spread was 1.11-1.18 its σ)."""
    from gearbench.analysis.uncertainty import block_covariance
    rng = np.random.default_rng(5)
    n, L = 800, 160
    X = np.vstack([np.ones(n), np.sin(2 * np.pi * np.arange(n) / 200.0)])
    A = X @ X.T
    est, var = [], []
    for _ in range(2000):
        e = rng.normal(size=n)
        b = np.linalg.solve(A, X @ e)
        cov, _, _ = block_covariance(X, e - b @ X, A, block=L)
        est.append(b[1])
        var.append(cov[1, 1])
    assert 0.85 < np.mean(var) / np.var(est) < 1.15


def test_rotor_stuck_for_most_of_its_run_is_noise_limited_and_says_so():
    """Seed 7 case 94, output motor: Coulomb friction 1.9x the rms current on a 4 Hz speed
    loop, the rotor stuck 97 % of its reversing run. Stuck stretches carry no Kt
    information and are left out of the fit (``identify.equation_weight``); what remains
    gives Kt with a wide interval that holds the truth and a warning naming the shortfall
    (before: an exception, and the fits with the stuck samples in were off by 8 %)."""
    from gearbench.analysis.calibration import calibrate_motor

    case = R.draw_case(94, 7)
    u, lo = R.simulate_case(case)["runs"]["out"]
    m = case.plant.motor_out
    cal = calibrate_motor(u, lo, case.disks_kgm2["out"])
    assert cal.Kt_ci95[0] <= m.Kt <= cal.Kt_ci95[1]
    assert cal.Kt_std / m.Kt > 0.01                                  # noise-limited
    assert any("acceleration content" in w for w in cal.fit["warnings"])


def test_the_same_stuck_rotor_at_100_hz_is_refused_not_returned_with_a_false_interval():
    """The same drive sampled at 100 Hz moves on 6 of its 300 samples: about 1.2
    independent equations through the 10 Hz filter for 3 parameters. The fit to them left
    almost no residual, and Kt came out −10.6 % at ± 0.09 %; now the run is refused,
    naming what it holds. At 1 kHz (3.5 equations) the wide interval above is kept."""
    from gearbench.analysis.calibration import calibrate_motor
    from gearbench.errors import ExcitationError

    case = R.with_period(R.draw_case(94, 7), 1e-2)
    u, lo = R.simulate_case(case)["runs"]["out"]
    with pytest.raises(ExcitationError, match=r"moves on only \d+ of 300 samples.*independent "
                                              r"equations.*for 3 parameters"):
        calibrate_motor(u, lo, case.disks_kgm2["out"])


def test_causes_name_the_missed_quantities_each_motors_kt_and_the_measured_conditions():
    stuck = {"left_out": (0.1, 0.9), "step_kept": False, "stepping_sampled": False}
    stepping = {"left_out": (0.0, 0.0), "step_kept": True, "stepping_sampled": True}
    plain = {"left_out": (0.0, 0.0), "step_kept": False, "stepping_sampled": False}
    o = R.Outcome([0.5, 0.1], [0.1], [0.1], [0.3, 0.05], [0.05], [0.05], [True, True],
                  [True], [True], motors=[stuck, stepping])
    text = R.causes(o)
    assert text.startswith("missed kt_pct;")
    assert "in: Kt +0.500±0.300 %, stuck 90%" in text and "out: Kt +0.100±0.050 %, stepping+term" in text
    o2 = R.Outcome([0.1, 0.1], [0.5], [0.1], [0.05, 0.05], [0.3], [0.05], [True, True],
                   [True], [True], motors=[plain, plain])
    assert R.causes(o2).endswith("no tagged condition") and "missed inc_pp" in R.causes(o2)
    assert R.causes(R.Outcome(error="TraceError: x")) == "exception"
    # an absolute point beyond its target on an extrapolated motor loss is named; one
    # within its target is not
    o3 = R.Outcome([0.1, 0.1], [0.1], [0.5, 0.1], [0.05, 0.05], [0.05], [0.3, 0.3],
                   [True, True], [True], [True, True], abs_extrapolated=[True, False],
                   motors=[plain, plain])
    assert "missed abs_pp" in R.causes(o3) and R.causes(o3).endswith("; loss extrapolated")
    o3.abs_extrapolated = [False, True]
    assert R.causes(o3).endswith("no tagged condition")


def test_stepping_drive_with_sampled_current_gives_kt_within_target():
    """Seed 8 case 11, input motor: setpoint applied as a step each SYNC, current sampled
    at one instant, as the drive's description says (``meta["drive"]``). The sample
    misses the kick's period mean (unloaded b2 +0.87 %, loaded +0.04 %).

    With the drive's loop declared (speed-loop Kp, current-loop τ, loop period) the kick
    is computed, c = Kp·h(τ/T, M) (``identify.kick_coefficient``, the closed form of the
    numeric periodic solution ``_kick_factor``), and added to the current, a current delay
    fitted (D and Tc need it): Kt +0.07 % ± 0.17 % (std). Without the loop the physical model fits one c for both runs: Kt
    +0.20 % ± 0.30 %, the fitted c/Kp 1.28-1.61 x h: the term, nearly collinear with θ'',
    takes up misfit (noise-free, a drive that interpolates or a current without kick
    still gets c ≈ 0.03-0.1 Kp per run). Without any description (the term judged by its
    Wald, a delay fitted): biased beyond twice its own std."""
    from gearbench.analysis.calibration import calibrate_motor
    from gearbench.analysis.identify import DRIVE_LOOP_KEYS

    case = R.draw_case(11, 8)
    u, lo = R.simulate_case(case)["runs"]["in"]
    m = case.plant.motor_in
    assert not m.setpoint_interpolation and not m.current_avg_s
    assert u.meta["drive"] == {"setpoint": "step", "current": "instant",
                               "current_limit_a": m.current_limit_a,
                               "speed_kp_a_s_per_rad": m.vel_kp,
                               "current_loop_time_constant_s": m.current_lag_s,
                               "speed_loop_period_s": m.loop_period_s}
    h = _kick_factor(m.current_lag_s / R.PERIOD_S, round(R.PERIOD_S / m.loop_period_s))
    known = calibrate_motor(u, lo, case.disks_kgm2["in"])
    assert known.fit["kick_a_per_rad_s"] == pytest.approx(m.vel_kp * h, rel=2e-3)
    assert "setpoint_step" not in known.fit                  # not fitted
    assert abs(known.Kt / m.Kt - 1) <= 0.001
    assert known.Kt_ci95[0] <= m.Kt <= known.Kt_ci95[1]
    assert known.fit["kick_model_difference"] != 0.0        # c's uncertainty carried
    # the loop not declared: one fitted c for both runs, always kept
    for t in (u, lo):
        for k in DRIVE_LOOP_KEYS:
            del t.meta["drive"][k]
    cal = calibrate_motor(u, lo, case.disks_kgm2["in"])
    step = cal.fit["setpoint_step"]
    assert step["kept"] and step["declared"]
    assert abs(cal.Kt / m.Kt - 1) <= 0.0025
    assert cal.Kt_ci95[0] <= m.Kt <= cal.Kt_ci95[1]
    assert abs(known.Kt - m.Kt) < abs(cal.Kt - m.Kt) / 2
    # the fitted c (A per rad/s of setpoint step) exceeds the kick (1.61 x h here with
    # the clipped samples out, 1.28 x h with them diluting it)
    c_per_kp = step["coefficient_a_s2_per_rad"] / R.PERIOD_S / m.vel_kp
    assert -1.8 * h < c_per_kp < -1.0 * h, (c_per_kp, h)
    # without the description: the term judged by its Wald, a delay fitted: biased
    # (beyond twice its own std), with it not
    for t in (u, lo):
        del t.meta["drive"]
    plain = calibrate_motor(u, lo, case.disks_kgm2["in"])
    assert abs(plain.Kt - m.Kt) > 2 * plain.Kt_std
    assert abs(cal.Kt - m.Kt) <= 2 * cal.Kt_std


def test_kick_drives_without_x_bias_once_their_loop_is_declared():
    """Noise-free stepping drives of robustness seed 4 (the first 20 cases, forward runs):
    with the kick fitted (loop not declared) Kt is high by about x/100 of itself,
    x = Kp·Kt·T/J of the unloaded run (+0.16 % at x 0.175); with the kick computed from
    the declared loop (and the current delay fitted) the error no longer follows x (8
    drives: |error| 0.11 % mean, 0.33 % max fitted; 0.02 %, 0.06 % computed)."""
    rows = []
    for idx in range(20):
        case = R.draw_case(idx, 4)
        for side, m in (("in", case.plant.motor_in), ("out", case.plant.motor_out)):
            if m.setpoint_interpolation or m.current_avg_s or case.reversing:
                continue
            errs = _kick_errors_noise_free(case, side, m)
            rows.append((m.vel_kp * m.Kt * R.PERIOD_S / m.J, *errs))
    x, fitted, known = np.array(rows).T
    assert len(x) >= 5 and x.max() > 0.1
    assert np.all(fitted[x > 0.1] > 0.1)                 # +0.16, +0.33 % here
    assert np.polyfit(x, known, 1)[0] < np.polyfit(x, fitted, 1)[0] / 3
    assert np.max(np.abs(known)) < 0.1 and np.mean(np.abs(known)) < np.mean(np.abs(fitted)) / 3


def _kick_errors_noise_free(case, side, m) -> list[float]:
    """Kt error (%) of one drawn motor's noise-free calibration with the kick fitted, then
    computed from the drive's declared loop."""
    from dataclasses import replace

    from gearbench.analysis.calibration import calibrate_motor
    from gearbench.analysis.identify import DRIVE_LOOP_KEYS
    from gearbench.sim import simulate_motor

    m = replace(m, current_noise_a=0.0, current_resolution_a=0.0)
    cmd, disk = case.commands[side], case.disks_kgm2[side]
    runs = [simulate_motor(m, cmd, seed=1, period_s=R.PERIOD_S, disk_kgm2=d)
            for d in (0.0, disk)]
    errs = []
    for declared in (False, True):
        for t in runs:
            t.meta["drive"] = {k: v for k, v in R.drive_description(m).items()
                               if declared or k not in DRIVE_LOOP_KEYS}
        cal = calibrate_motor(*runs, disk, model_errors=False)
        errs.append(100 * (cal.Kt / m.Kt - 1))
    return errs


def test_reversing_kick_drives_take_the_declared_kick_too():
    """Noise-free stepping drives on reversing runs of robustness seed 5 (the first 60
    cases): with the kick fitted (one shared term, nearly collinear with θ'') Kt is high
    (+0.16 % mean, up to +0.53 %: the term takes up the zero crossing's misfit); with
    the kick computed from the declared loop and the current delay fitted, as on forward
    runs, the error halves (+0.07 % mean |error|)."""
    rows = []
    for idx in range(60):
        case = R.draw_case(idx, 5)
        if not case.reversing:
            continue
        for side, m in (("in", case.plant.motor_in), ("out", case.plant.motor_out)):
            if m.setpoint_interpolation or m.current_avg_s:
                continue
            rows.append(_kick_errors_noise_free(case, side, m))
    fitted, known = np.array(rows).T
    assert len(rows) >= 8
    assert np.mean(fitted) > 0.1                          # +0.16 % here
    assert np.mean(np.abs(known)) < np.mean(np.abs(fitted)) / 1.5
    assert np.max(np.abs(known)) < 0.3


def test_stepping_drive_at_its_current_limit_gives_kt_within_target():
    """Seed 11 case 8, output motor: a stepping drive with a sampled current and a fast
    speed loop (22 Hz) whose loaded run sits at the 3 A current limit on 66 % of its
    samples (the unloaded on 20 %). There the P part of the kick is clipped away, so
    one c for both runs over-corrects the loaded run: Kt −0.55 ± 0.11 % (biased) when the
    limit is not known (−0.32 ± 0.16 % since the speed loop's ripple term is fitted too,
    ``identify.SPEED_ERR``); with the drive's declared limit the term is 0 at those samples
    (``identify.samples._below_current_limit``): within 0.2 % (covered before the ripple term: below)."""
    from gearbench.analysis.calibration import calibrate_motor

    case = R.draw_case(8, 11)
    u, lo = R.simulate_case(case)["runs"]["out"]
    m = case.plant.motor_out
    assert not m.setpoint_interpolation and not m.current_avg_s
    at_limit = np.mean(np.abs(lo["current_a"]) > 0.98 * m.current_limit_a)
    assert at_limit > 0.5
    cal = calibrate_motor(u, lo, case.disks_kgm2["out"])
    assert abs(cal.Kt / m.Kt - 1) <= 0.002
    for t in (u, lo):
        del t.meta["drive"]["current_limit_a"]
    unknown = calibrate_motor(u, lo, case.disks_kgm2["out"])
    assert unknown.Kt / m.Kt - 1 < -0.002


@pytest.mark.xfail(strict=True, reason="known: the same motor's Kt −0.12 ± 0.06 % (std; noise-free "
                   "−0.18 %) misses its 95 % interval since the ripple term is fitted: the accel "
                   "form, whose spread had covered it (σ 0.21 %), is no model variant where the "
                   "term is in (it cannot share the gain); the drive at its current limit on "
                   "66 % of the loaded run is the model error left, and zeroing the ripple term "
                   "there made it −0.29 %")
def test_stepping_drive_at_its_current_limit_is_covered_by_its_interval():
    case = R.draw_case(8, 11)
    u, lo = R.simulate_case(case)["runs"]["out"]
    m = case.plant.motor_out
    from gearbench.analysis.calibration import calibrate_motor
    cal = calibrate_motor(u, lo, case.disks_kgm2["out"])
    assert cal.Kt_ci95[0] <= m.Kt <= cal.Kt_ci95[1]


def _kick_factor(tau_per_period: float, ticks: int, n: int = 400) -> float:
    """Period mean minus end value of a first-order lag's periodic response to the
    step-minus-ramp current command pattern (1 − (m+1)/M at speed-loop tick m, mean
    removed), per unit Kp·Δcmd (``identify.drive_loop._setpoint_steps``)."""
    u = np.repeat(1.0 - (np.arange(ticks) + 1.0) / ticks, n // ticks)
    u -= u.mean()
    a = 1.0 - np.exp(-1.0 / (len(u) * tau_per_period))
    i, trace = 0.0, np.empty(len(u))
    for _ in range(40):                     # settle to the periodic steady state
        for k, uk in enumerate(u):
            i += (uk - i) * a
            trace[k] = i
    return float(trace.mean() - trace[-1])


def test_a_drive_that_says_it_interpolates_gets_no_setpoint_step_term():
    """c = 0 by physics for a drive ramping between setpoints (or averaging its current):
    the description turns the term off instead of a Wald test on nearly collinear data."""
    from gearbench.analysis.calibration import calibrate_motor

    case = next(c for c in (R.draw_case(k, 8) for k in range(40))
                if c.plant.motor_in.setpoint_interpolation)
    u, lo = R.simulate_case(case)["runs"]["in"]
    assert u.meta["drive"]["setpoint"] == "interpolated"
    cal = calibrate_motor(u, lo, case.disks_kgm2["in"])
    assert "setpoint_step" not in cal.fit


def test_zero_load_level_off_the_braking_line_no_longer_biases_the_incremental_efficiency():
    """Seed 1 case 45: the output motor has no Coulomb friction and 2 mN m of cogging, so
    at zero load the mesh's power flow reverses within each cogging period and the
    zero-load currents lie off the braking levels' line (both Kt within 0.11 %). The
    secants against them were +1.84/+1.20/+0.90 pp off; the braking levels' slope is
    within the target and flagged (``zero-load off line``)."""
    o = R.run_case(R.draw_case(45, 1), ("default",))["default"]
    assert o.off_line_reference and "zero-load off line" in R.causes(o)
    assert max(abs(e) for e in o.kt_err_pct) < 0.2
    assert max(abs(e) for e in o.inc_err_pp) <= R.TARGETS["inc_pp"]
    assert all(o.inc_cover)


def test_kt_coverage_is_split_by_the_drives_setpoint_and_current_kind():
    """The benchmark's per-drive-kind table groups each motor by how its drive steps its
    setpoint and samples its current (at 250 Hz the stepping, period-mean drives are the
    ones whose Kt intervals miss)."""
    cases = [R.draw_case(k, 8) for k in range(6)]
    outcomes, expect = [], {}
    for j, c in enumerate(cases):
        o = R.Outcome(kt_err_pct=[0.2 * j, -0.1], kt_std_pct=[0.1, 0.1], kt_cover=[j % 2 == 0, True])
        outcomes.append({"default": o})
        for motor, z, cov in zip((c.plant.motor_in, c.plant.motor_out), (2.0 * j, -1.0), o.kt_cover):
            expect.setdefault(R.drive_kind(motor), []).append((z, cov))
    got = R.kt_by_drive_kind(cases, outcomes)
    assert set(got) == set(expect) and set(got) <= {"step/instant", "step/mean", "interpolated/instant",
                                                    "interpolated/mean"}
    for kind, rows in expect.items():
        assert got[kind]["motors"] == len(rows)
        assert got[kind]["cover"] == pytest.approx(np.mean([c for _, c in rows]))
        assert got[kind]["mean_z"] == pytest.approx(np.mean([z for z, _ in rows]))


def test_the_biased_share_honest_intervals_would_give_by_chance():
    """An error beyond its target and 2 sigma is 'biased'; with honest (normal) errors that
    happens by chance where sigma is a good part of the target: 2Φ(−2) = 4.55 % per point
    whose target is within 2 sigma, 2Φ(−target/σ) beyond."""
    tgt = R.TARGETS
    half = R.Outcome([0.0], [0.0], [0.0], [tgt["kt_pct"] / 2], [tgt["inc_pp"] / 4], [tgt["abs_pp"] / 4])
    assert half.chance_biased("kt_pct") == pytest.approx(2 * stats.norm.sf(2.0), rel=1e-9)
    assert half.chance_biased("inc_pp") == pytest.approx(2 * stats.norm.sf(4.0), rel=1e-9)
    both = 1 - (1 - 2 * stats.norm.sf(2.0)) * (1 - 2 * stats.norm.sf(4.0)) ** 2
    assert half.chance_biased() == pytest.approx(both, rel=1e-9)
    s = R.summarise([{"default": half}, {"default": R.Outcome(error="ExcitationError: x")}], ("default",))
    assert s["default"]["chance"] == pytest.approx(both / 2, rel=1e-9)    # a refused plant: no chance


def test_noise_scatter_repeats_a_plant_on_fresh_noise_and_compares_its_sigma(capsys):
    """The same plant on fresh noise draws: Kt moves by the noise's spread, which the
    reported statistical sigma is set beside (a ratio per drive kind, printed)."""
    case = R.draw_case(5, 7)
    rows = R.noise_scatter([case], 3)
    assert {r["side"] for r in rows} == {"in", "out"}
    for r in rows:
        assert r["draws"] + r["refused"] == 3 and r["draws"] >= 2
        assert r["spread_pct"] > 0 and r["stat_pct"] > 0 and r["std_pct"] >= r["stat_pct"]
        assert r["kind"] == R.drive_kind(getattr(case.plant, f"motor_{r['side']}"))
    # fresh noise really is fresh: the draws differ from the case as drawn
    first = R.run_case(case, ("default",))["default"].kt_err_pct
    assert all(abs(r["mean_err_pct"] - first[0 if r["side"] == "in" else 1]) > 0 for r in rows)
    R.print_noise_scatter(rows, 3)
    out = capsys.readouterr().out
    assert "stat σ / spread" in out and out.count("\n  all") == 1


def test_a_stepping_drive_at_100_hz_counts_what_its_declared_kick_leaves_out():
    """Seed 7 case 97's output drive steps its setpoint and samples one instant. At 100 Hz
    x = Kp·(Kt/J)·T is 1.5, and the declared kick leaves out the speed's own response
    within the period (``identify.kick_speed_response``, ε ≈ 0.24 of c): Kt came out
    +3.65 % at σ 0.91 % (z 4.0, biased). With ε in the kick's uncertainty the interval
    holds the truth; at 1 kHz the same term stays below 0.04 (the 10 % of the gain's
    realisation dominates there)."""
    from gearbench.analysis.calibration import KICK_REL_STD, calibrate_motor
    from gearbench.analysis.identify import kick_speed_response

    drawn = R.draw_case(97, 7, duration_s=3.0, dwell_s=4.0, cover_bench_speed=True)
    case = R.with_period(drawn, 1e-2)
    motor = case.plant.motor_out
    u, lo = R.simulate_runs(case)["out"]
    cal = calibrate_motor(u, lo, case.disks_kgm2["out"])
    eps = kick_speed_response(u, cal.fit["b2_unloaded"])
    assert 0.15 < eps < 0.35
    assert cal.fit["kick_rel_std"] == pytest.approx(float(np.hypot(KICK_REL_STD, eps)))
    assert cal.Kt / motor.Kt - 1 > 0.02                 # the bias is still there ...
    assert cal.Kt_ci95[0] <= motor.Kt <= cal.Kt_ci95[1]  # ... and now inside its interval
    u1, _ = R.simulate_runs(drawn)["out"]
    assert kick_speed_response(u1, motor.Kt / motor.J) < 0.04
