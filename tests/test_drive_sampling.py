"""What a drive's current sample is, in the calibration: one instant or the period's mean.

**One instant.** A drive whose speed loop differentiates encoder counts puts the count
quantum's error on its speed estimate, and its P gain turns that into current. A drive that
reports one current-loop instant (not the period mean) passes that ripple on, aliased into
the fit band, where it correlates with the motion: Kt came out 0.2–0.5 % off on noise-free
forward runs of random plants. The drive also reports the speed it acted on; the ripple's
regressor (``identify.SPEED_ERR``) with one gain shared by both runs takes it out.

**The period's mean.** The angle's central second difference weights the acceleration by a
triangle about the sample instant; a current sample that is the mean over the period ending
at it is a boxcar. Matched with the instant samples' 3-tap kernel, and its half period left
to the fitted current delay (shifted by linear interpolation), Kt came out 0.03-0.05 % high
on noise-free forward plants whose drive reports the period mean: small beside the 0.2 %
target, but the largest error left on the best-excited motors, whose intervals are narrow
enough to call it biased (``derivatives.match_period_means``, ``derivatives.shift_samples``).
"""
from dataclasses import replace

import numpy as np
import pytest

from gearbench.analysis import derivatives as dv
from gearbench.analysis.calibration import calibrate_motor
from gearbench.analysis.identify import SPEED_ERR
from gearbench.benchmarks import robustness as rb
from gearbench.sim import simulate_motor

# forward plants of the robustness draw whose noise-free Kt the ripple moved by > 0.2 %
CASES = [(7, 16, "in"), (8, 63, "out"), (7, 46, "out")]
# forward plants of the robustness draw whose drives report the period mean
MEAN_CASES = [(7, 28, "in"), (7, 22, "in"), (7, 59, "out")]


def _runs(seed, index, side, **change):
    case = rb.draw_case(index, seed, duration_s=3.0, dwell_s=4.0)
    motor = replace(getattr(case.plant, f"motor_{side}"), current_noise_a=0.0, **change)
    s = case.seed + (0 if side == "in" else 10)
    runs = [simulate_motor(motor, case.commands[side], disk_kgm2=d, seed=s + k,
                           period_s=rb.PERIOD_S)
            for k, d in enumerate((0.0, case.disks_kgm2[side]))]
    for t in runs:
        t.meta["drive"] = rb.drive_description(motor)
    return motor, runs, case.disks_kgm2[side]


@pytest.mark.parametrize("seed,index,side", CASES)
def test_the_ripple_term_takes_the_aliased_ripple_out_of_kt(seed, index, side):
    motor, runs, disk = _runs(seed, index, side)
    assert runs[0].meta["drive"]["current"] == "instant"
    without = calibrate_motor(*runs, disk, speed_error=False, model_variants=False)
    with_term = calibrate_motor(*runs, disk, model_variants=False)
    err_without = abs(without.Kt / motor.Kt - 1)
    err_with = abs(with_term.Kt / motor.Kt - 1)
    assert err_without > 0.002                 # the ripple's bias, noise-free
    assert err_with < 0.001
    assert with_term.fit["speed_error"]["coefficient_a_s_per_rad"] < 0   # −Kp-like: e raises v, lowers i
    # the same plant whose drive reports the period mean has no such bias and no term
    motor_mean, runs_mean, _ = _runs(seed, index, side, current_avg_s=rb.PERIOD_S)
    mean = calibrate_motor(*runs_mean, disk, model_variants=False)
    assert "speed_error" not in mean.fit
    assert abs(mean.Kt / motor_mean.Kt - 1) < 0.001


def test_a_fine_encoder_shows_the_cause():
    """With a 2^24-count encoder the drive's speed estimate has no quantum: no bias to take out."""
    motor, runs, disk = _runs(7, 16, "in", counts_per_rev=2 ** 24)
    without = calibrate_motor(*runs, disk, speed_error=False, model_variants=False)
    assert abs(without.Kt / motor.Kt - 1) < 0.0005


def test_reversing_runs_and_mixed_pairs_leave_the_term_out():
    case = next(c for c in (rb.draw_case(k, 7, duration_s=3.0, dwell_s=4.0) for k in range(40))
                if c.reversing and c.plant.motor_in.current_avg_s == 0.0)
    motor = case.plant.motor_in
    runs = [simulate_motor(motor, case.commands["in"], disk_kgm2=d, seed=case.seed + k,
                           period_s=rb.PERIOD_S)
            for k, d in enumerate((0.0, case.disks_kgm2["in"]))]
    for t in runs:
        t.meta["drive"] = rb.drive_description(motor)
    cal = calibrate_motor(*runs, case.disks_kgm2["in"], model_variants=False)
    assert "speed_error" not in cal.fit
    assert SPEED_ERR not in cal.fit["unloaded"]["params"]


@pytest.mark.parametrize("seed,index,side", MEAN_CASES)
def test_period_means_matched_as_such_give_kt_without_the_bias(seed, index, side):
    motor, runs, disk = _runs(seed, index, side)
    assert runs[0].meta["drive"]["current"] == "mean" and motor.current_avg_s == rb.PERIOD_S
    as_instant = calibrate_motor(*runs, disk, current_period_mean=False, model_variants=False)
    matched = calibrate_motor(*runs, disk, model_variants=False)
    # the bias, noise-free: +0.03-0.05 % with the linear shift, +0.007-0.011 % left with
    # the cubic shift (``derivatives.shift_samples``), −0.0005…−0.0017 % matched
    assert as_instant.Kt / motor.Kt - 1 > 0.00005
    assert abs(matched.Kt / motor.Kt - 1) < 0.00003


def test_the_period_mean_match_is_the_triangle_about_the_sample():
    """Period means of a smooth signal, matched, give its triangle-weighted value about each
    sample (what the second difference weights the acceleration by) to fourth order; the
    3-tap instant match on them is off by the half period and by ~x²."""
    T = 1e-3
    t = np.arange(400) * T
    f = 25.0
    w = 2 * np.pi * f
    # mean of sin(w s) over [t - T, t]; triangle about t: sinc²(wT/2) sin(w t)
    means = (np.cos(w * (t - T)) - np.cos(w * t)) / (w * T)
    tri = np.sinc(f * T) ** 2 * np.sin(w * t)
    err_new = np.max(np.abs(dv.match_period_means(means) - tri)[2:-3])
    err_old = np.max(np.abs(dv.match_samples(means) - tri)[2:-3])
    assert err_new < 1e-5 and err_old > 0.05


def test_a_cubic_shift_keeps_the_amplitude_a_linear_one_loses():
    """Half a sample, 10 Hz at 1 kHz: linear interpolation scales the tone by cos(πfT)
    (−0.05 %), the Lagrange cubic keeps it within 1e-6."""
    k = np.arange(2000)
    x = np.sin(2 * np.pi * 10.0 * k / 1000.0)
    exact = np.sin(2 * np.pi * 10.0 * (k + 0.5) / 1000.0)
    lin = np.interp(k + 0.5, k, x)
    cub = dv.shift_samples(x, 0.5)
    amp = lambda y: np.sqrt(2 * np.mean(y[10:-10] ** 2))          # noqa: E731
    assert abs(amp(lin) / amp(exact) - 1) > 4e-4
    assert abs(amp(cub) / amp(exact) - 1) < 1e-6


def test_a_ripple_below_the_current_noise_is_not_fitted():
    """Behind a 20-bit encoder one count per speed-loop period makes a ripple far below
    the current's noise (``identify.speed_ripple_to_noise``): the term then has only the
    drive estimate's lag to fit and took up friction misfit (seed 8 case 26's output
    motor: D 1.95x, Tc 0.85x its truth). Left out, the losses are right; behind the drawn
    encoder the ripple stands out and the term stays."""
    from gearbench.analysis.identify import speed_ripple_to_noise

    case = rb.draw_case(26, 8, cover_bench_speed=True)
    motor, disk = case.plant.motor_out, case.disks_kgm2["out"]
    drawn = rb.simulate_case(case)["runs"]["out"]
    assert min(speed_ripple_to_noise(t) for t in drawn) > 1.0
    assert "speed_error" in calibrate_motor(*drawn, disk, model_variants=False).fit
    fine = rb.simulate_case(rb.with_encoder(case, 2 ** 20))["runs"]["out"]
    assert max(speed_ripple_to_noise(t) for t in fine) < 0.3
    cal = calibrate_motor(*fine, disk, model_variants=False)
    assert "speed_error" not in cal.fit
    assert cal.D / motor.D == pytest.approx(1.0, abs=0.2)
    assert cal.Tc / motor.Tc == pytest.approx(1.0, abs=0.03)
    forced = calibrate_motor(*fine, disk, model_variants=False, speed_error=True)
    assert forced.D / motor.D > 1.5 or forced.Tc / motor.Tc < 0.9


def _b2_errors_declared_or_not(trace, m, forms) -> dict:
    """b2's error (%) per (loop declared, form) of a simulated run of motor ``m``: the drive
    described as robustness describes it, with and without its speed loop."""
    from gearbench.analysis.identify import DRIVE_LOOP_KEYS, declared_period_kick, identify_trace

    errors = {}
    for declared in (True, False):
        trace.meta["drive"] = {k: v for k, v in rb.drive_description(m).items()
                               if declared or k not in DRIVE_LOOP_KEYS}
        assert (declared_period_kick(trace) is not None) == declared
        for form in forms:
            fit = identify_trace(trace, method=form, check=False)
            errors[declared, form] = 100 * (float(fit.B[1]) / (m.Kt / m.J) - 1)
    return errors


def test_a_stepping_drive_reporting_the_period_mean_gets_its_kicks_at_250_hz():
    """At 250 Hz a drive that steps its setpoint each SYNC kicks its current at the start of
    every 4 ms period; the period means' match cannot see where in the period the current
    went, and b2 came out 0.15 % low (robustness seed 8 case 58's input, noise-free, a
    20-bit encoder, no cogging). The kicks computed from the declared loop
    (``identify.period_mean_kick_weights``) take it to within 0.03 %; without the declared
    loop the bias is back. A steady acceleration's kicks are matched already (Σ w = 0)."""
    from gearbench.analysis.identify import declared_period_kick, period_mean_kick_weights

    w = period_mean_kick_weights(0.09, 0.42e-3, 4e-3, 0.25e-3)
    assert abs(w.sum()) < 1e-12 and np.abs(w).max() > 1e-3
    case = rb.with_period(rb.draw_case(58, 8, cover_bench_speed=True), 4e-3)
    m = replace(case.plant.motor_in, current_noise_a=0.0, current_resolution_a=0.0,
                counts_per_rev=1 << 20, cog_amp=0.0)
    assert (m.setpoint_interpolation, m.current_avg_s) == (0, 4e-3)
    trace = simulate_motor(m, case.commands["in"], seed=11, period_s=4e-3)
    errors = _b2_errors_declared_or_not(trace, m, ("default",))
    assert abs(errors[True, "default"]) < 0.03, errors
    assert errors[False, "default"] < -0.1, errors
    # an interpolating drive of the same kind has no kicks to add
    trace.meta["drive"] = {**rb.drive_description(m), "setpoint": "interpolated"}
    assert declared_period_kick(trace) is None


def test_an_interpolating_drive_sampling_its_current_at_one_instant_gets_its_kinks_at_250_hz():
    """A drive that ramps its setpoint over each 4 ms SYNC period changes the ramp's slope
    at every SYNC; its speed loop passes the kinks into the current, and the sample at the
    period's end sees them at one phase while the rotor integrates them: the 3-tap match
    misses it and b2 came out 0.14-0.16 % low (robustness seed 7 case 1's output drive,
    noise-free, a 20-bit encoder, no cogging). The kinks computed from the declared loop
    (``identify.interpolated_kink_weights``, their steady part out: Σ w = 0) take it to
    within 0.02 %, in the accel and the torque form; without the declared loop the bias
    is back. At 1 kHz the same drive needs nothing (within 0.02 % either way)."""
    from gearbench.analysis.identify import interpolated_kink_weights

    w = interpolated_kink_weights(0.005, 0.3e-3, 4e-3, 0.25e-3)
    assert abs(w.sum()) < 1e-12 and np.abs(w).max() > 1e-5
    case = rb.draw_case(1, 7, cover_bench_speed=True)
    for period_s, bias_without in ((4e-3, -0.1), (1e-3, None)):
        c = rb.with_period(case, period_s) if period_s != 1e-3 else case
        m = replace(c.plant.motor_out, current_noise_a=0.0, current_resolution_a=0.0,
                    counts_per_rev=1 << 20, cog_amp=0.0)
        assert (m.setpoint_interpolation, m.current_avg_s) == (1, 0.0)
        trace = simulate_motor(m, c.commands["out"], seed=3, period_s=period_s)
        errors = _b2_errors_declared_or_not(trace, m, ("default", "torque"))
        assert all(abs(errors[True, f]) < 0.02 for f in ("default", "torque")), (period_s, errors)
        if bias_without is not None:
            assert all(errors[False, f] < bias_without for f in ("default", "torque")), errors
        else:
            assert all(abs(errors[False, f]) < 0.02 for f in ("default", "torque")), errors


def test_the_station_gives_the_analysis_its_drives_limit_with_the_sampling(monkeypatch):
    """A profile's ``sampling`` reaches the calibration with the motor's ``current_limit_a``
    (the kicks and kinks are not added where the drive clips), as a trace's description
    gives them to ``calibrate``; without sampling the runs say nothing of the drive."""
    from gearbench.station import analyse
    from gearbench.trace import Trace

    seen = []

    class Stop(Exception):
        pass

    def capture(u, l_, disk, **kw):
        seen.append((dict(u.meta.get("drive") or {}), dict(l_.meta.get("drive") or {})))
        raise Stop
    monkeypatch.setattr(analyse, "calibrate_motor", capture)
    t = np.arange(200) * 1e-3
    step = Trace(t, {"in.position_rad": t, "in.current_a": 0 * t, "in.command": 0 * t}, source="run")
    sampling = {"setpoint": "interpolated", "current": "instant", "speed_kp_a_s_per_rad": 0.01,
                "current_loop_time_constant_s": 3e-4, "speed_loop_period_s": 2.5e-4}
    for kw, want in (({"sampling": sampling, "current_limit_a": 4.0}, {**sampling, "current_limit_a": 4.0}),
                     ({"sampling": sampling}, sampling), ({"current_limit_a": 4.0}, {})):
        with pytest.raises(Stop):
            analyse.calibrate(step, step, motor="in", disk_kgm2=1e-5, **kw)
        assert seen[-1] == (want, want)
