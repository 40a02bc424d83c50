"""Excitation design benchmark: predicted vs empirical Kt scatter, designed vs hand-chosen.

    python -m gearbench.benchmarks excitation [PROFILE] [--seeds N] [--duration S]

For each motor of the profile (default ``profiles/cvt.yaml``): the profile's own
calibration multisine (``waveforms.excite`` or the first calibrate step's waveform)
and the one ``gearbench.profile.excitation_design`` designs from the profile's motor
limits. Each is run on the profile's simulated plant (``simulation:``, the fast
in-process path of the accuracy/robustness benchmarks), alone and with the disk, for
``--seeds`` noise seeds, and calibrated with ``calibrate_motor`` (default method,
excitation check on). Printed per motor and waveform: the predicted statistical Kt
relative std (from the profile's assumptions, and from the simulated plant's true
parameters), the empirical std over seeds and its 90 % chi-square interval, the mean
error (bias: not noise, the same for every seed), the mean std the analysis itself
reported, all also per sqrt(bench second), and the true peak current of the disk run.
"""
from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
from scipy import stats

from ..profile import excitation_design as ed
from ..analysis.calibration import calibrate_motor

REPO = Path(__file__).resolve().parents[2]
# profiles/cvt.yaml's hand-chosen calibration multisine before the design existed
CLASSIC = {"offset": 150.0, "amplitude": 80.0, "period_s": 1.0, "f_min_hz": 1.0, "f_max_hz": 8.0,
           "fade_in_s": 0.2}


def empirical(motor, command: np.ndarray, disk_kgm2: float, seeds, period_s: float) -> dict:
    """Calibrate ``motor`` (sim MotorParams) on ``command`` for each seed → Kt relative
    errors, reported statistical stds, run b2 relative errors and the disk run's true peak
    current (incl. the drive's own ripple)."""
    from ..sim import simulate_motor

    kt, rep, bu, bl, peak = [], [], [], [], []
    for s in seeds:
        u = simulate_motor(motor, command, seed=10_000 + 2 * s, period_s=period_s)
        lo = simulate_motor(motor, command, disk_kgm2=disk_kgm2, seed=10_001 + 2 * s,
                            period_s=period_s, include_truth=True)
        cal = calibrate_motor(u, lo, disk_kgm2)
        kt.append(cal.Kt / motor.Kt - 1)
        rep.append(cal.fit["Kt_std_statistical"] / motor.Kt)
        bu.append(cal.fit["b2_unloaded"] * motor.J / motor.Kt - 1)
        bl.append(cal.fit["b2_loaded"] * (motor.J + disk_kgm2) / motor.Kt - 1)
        peak.append(float(np.max(np.abs(lo["true_current_a"]))))
    return {"kt": np.array(kt), "reported": np.array(rep), "b2u": np.array(bu), "b2l": np.array(bl),
            "peak_a": max(peak)}


def std_interval(x: np.ndarray, level: float = 0.9) -> tuple[float, float, float]:
    """Sample std with its chi-square interval (normal data)."""
    n = len(x)
    s = float(np.std(x, ddof=1))
    lo = s * math.sqrt((n - 1) / stats.chi2.ppf(0.5 + level / 2, n - 1))
    hi = s * math.sqrt((n - 1) / stats.chi2.ppf(0.5 - level / 2, n - 1))
    return s, lo, hi


def truth_case(case: ed.MotorCase, motor) -> ed.MotorCase:
    """The design's assumptions replaced by the simulated plant's true values."""
    from dataclasses import replace

    return replace(case, kt_nm_a=motor.Kt, rotor_inertia_kgm2=motor.J, viscous_nms_rad=motor.D,
                   friction_nm=motor.Tc, current_noise_a=motor.current_noise_a,
                   current_resolution_a=motor.current_resolution_a, counts_per_rev=motor.counts_per_rev)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m gearbench.benchmarks excitation", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("profile", nargs="?", default=str(REPO / "profiles" / "cvt.yaml"))
    ap.add_argument("--seeds", type=int, default=12, help="noise seeds per waveform (default 12)")
    ap.add_argument("--duration", type=float, default=None,
                    help="run length in s (default: the profile's calibrate step)")
    ap.add_argument("--random", type=int, default=0, metavar="N",
                    help="also N random plants of the robustness benchmark (their own command vs "
                         "the design), --seeds noise seeds each")
    args = ap.parse_args(argv)
    if args.random:
        t0 = time.perf_counter()
        random_plants(args.random, max(args.seeds, 2))
        print(f"random plants: {time.perf_counter() - t0:.1f} s")
        return 0
    from ..profile import CalibrateStep, load_profile
    from ..profile import waveforms as wf
    from ..profile.design import motor_case
    from ..sim import PlantParams

    t0 = time.perf_counter()
    prof = load_profile(args.profile)
    period = prof.bench.period_s
    plant = PlantParams.from_dict(prof.simulation or {})
    steps = [s for s in prof.steps if isinstance(s, CalibrateStep)]
    hand_name = "excite" if "excite" in prof.waveforms else steps[0].waveform
    hand = prof.waveforms[hand_name]
    if hand.params.get("design") == "optimal":        # compare with cvt's classic hand choice
        hand = type(hand)(name="classic", kind="multisine", params={
            **{k: p.default for k, p in wf.PARAMS["multisine"].items() if p.default is not wf.REQUIRED},
            **CLASSIC})
    print(f"excitation: {args.profile}, {args.seeds} seeds per waveform, sample period "
          f"{period * 1e3:g} ms; Kt relative std (statistical part), x sqrt(bench s) = per sqrt(s)")
    hdr = (f"{'motor':<5} {'waveform':<9} {'run s':>5} {'pred(profile)':>13} {'pred(true)':>10} "
           f"{'empirical [90% CI]':>27} {'reported':>9} {'bias':>9} {'per sqrt(s): pred':>18} "
           f"{'emp':>8} {'peak A':>7}")
    print(hdr)
    for step in steps:
        motor = plant.motor_in if step.motor == "in" else plant.motor_out
        disk = prof.disks[step.disk].inertia_kgm2
        duration = args.duration or step.duration_s
        case = motor_case(prof.motors[step.motor], prof.disks[step.disk], hand.params)
        design = ed.design_multisine([case], duration_s=duration, period_s=period,
                                     max_tone_hz=10.0, min_fade_s=hand.params.get("fade_in_s", 0.2))
        got = {}
        for label, kind, params in (("hand", hand.kind, hand.params),
                                    ("designed", "multisine", design.params)):
            n = int(round(duration / period))
            cmd = wf.render(kind, params, np.arange(n) * period)
            pred = ed.predict_calibration(kind, params, case, duration_s=duration, period_s=period)
            pred_t = ed.predict_calibration(kind, params, truth_case(case, motor), duration_s=duration,
                                            period_s=period)
            emp = empirical(motor, cmd, disk, range(args.seeds), period)
            s, lo, hi = std_interval(emp["kt"])
            root = math.sqrt(2 * duration)
            print(f"{step.motor:<5} {label:<9} {duration:5.2f} {pred.kt_rel_std * 100:12.4f}% "
                  f"{pred_t.kt_rel_std * 100:9.4f}% {s * 100:9.4f}% [{lo * 100:.4f}, {hi * 100:.4f}] "
                  f"{np.mean(emp['reported']) * 100:8.4f}% {np.mean(emp['kt']) * 100:+8.4f}% "
                  f"{pred.kt_rel_std * root * 100:17.4f}% {s * root * 100:7.4f}% {emp['peak_a']:7.3f}")
            print(f"      {'':<9} b2 rel std unloaded/loaded: predicted(true) "
                  f"{pred_t.b2_rel_std_unloaded * 100:.4f}/{pred_t.b2_rel_std_loaded * 100:.4f} %, "
                  f"empirical {np.std(emp['b2u'], ddof=1) * 100:.4f}/{np.std(emp['b2l'], ddof=1) * 100:.4f} %"
                  f"; {ed.multisine_summary(params)}")
            got[label] = (pred.kt_rel_std, float(np.mean(emp["reported"])), emp["kt"])
        (ph, rh, eh), (pd, rd, e_d) = got["hand"], got["designed"]
        ratio = float(np.std(e_d, ddof=1) / np.std(eh, ddof=1))
        f_lo, f_hi = (stats.f.ppf(q, len(e_d) - 1, len(eh) - 1) for q in (0.05, 0.95))
        print(f"      designed/hand Kt std: predicted {pd / ph:.2f}, reported by the analysis "
              f"{rd / rh:.2f}, empirical {ratio:.2f} [90 % CI {ratio / math.sqrt(f_hi):.2f}, "
              f"{ratio / math.sqrt(f_lo):.2f}]")
        print(f"      design binding: {design.binding}; acceleration crest factor "
              f"{design.acceleration_crest_factor:.3f}; {design.candidates} candidates"
              + (f"; {'; '.join(design.notes)}" if design.notes else ""))
    print(f"benchmark time {time.perf_counter() - t0:.1f} s")
    return 0


def random_plants(n_cases: int, seeds: int, duration_s: float = 3.0) -> None:
    """The robustness benchmark's random motors (loop bandwidth 3-30 Hz, 2,000-20,000
    counts/rev, 2-8 mA noise...): each input motor calibrated with its drawn command (a
    test engineer's multisine, scaled to the current limit) and with the design made from
    its datasheet-like values (Kt, J, disk, limits; friction and noise at the defaults)."""
    from .robustness import draw_case
    from ..profile import waveforms as wf

    print(f"random plants: {n_cases} cases x {seeds} seeds; Kt rel std % (empirical), design/drawn "
          f"ratio, true peak current / limit")
    print(f"{'case':>4} {'loop Hz':>7} {'drawn':>8} {'designed':>8} {'ratio':>6} {'pred ratio':>10} "
          f"{'peak/limit drawn':>16} {'designed':>8}  band")
    ratios, peaks, fails, emp_pred = [], [], 0, []
    for idx in range(n_cases):
        case = draw_case(idx, seed=1, duration_s=duration_s)
        m, disk = case.plant.motor_in, case.disks_kgm2["in"]
        mc = ed.MotorCase(kt_nm_a=m.Kt, rotor_inertia_kgm2=m.J, disk_inertia_kgm2=disk,
                          peak_current_a=0.65 * m.current_limit_a, rms_current_a=m.rated_current_a,
                          min_speed_rad_s=0.1 * m.speed_limit_rad_s, max_speed_rad_s=0.9 * m.speed_limit_rad_s,
                          friction_nm=0.1 * m.Kt * m.rated_current_a, counts_per_rev=m.counts_per_rev,
                          name=f"case{idx}")
        d = ed.design_multisine([mc], duration_s=duration_s, period_s=1e-3)
        n = int(round(duration_s / 1e-3))
        cmds = {"drawn": case.commands["in"][:n],
                "designed": wf.render("multisine", d.params, np.arange(n) * 1e-3)}
        std, peak = {}, {}
        for label, cmd in cmds.items():
            try:
                emp = empirical(m, cmd, disk, range(seeds), 1e-3)
                std[label] = float(np.std(emp["kt"], ddof=1))
                peak[label] = emp["peak_a"] / m.current_limit_a
            except Exception as exc:   # a refused calibration is a result here
                std[label], peak[label] = math.nan, math.nan
                fails += 1
                print(f"     case {idx} {label}: {type(exc).__name__}: {str(exc)[:100]}")
        pred_ratio = d.predictions[mc.name].kt_rel_std / ed.predict_command(
            cmds["drawn"], mc, period_s=1e-3).kt_rel_std
        true_pred = ed.predict_calibration("multisine", d.params, truth_case(mc, m), duration_s=duration_s,
                                           period_s=1e-3).kt_rel_std
        emp_pred.append(std["designed"] / true_pred)
        bw = m.vel_kp * m.Kt / (m.J + disk) / (2 * np.pi)
        r = std["designed"] / std["drawn"]
        ratios.append(r)
        peaks.append(peak["designed"])
        print(f"{idx:4d} {bw:7.1f} {std['drawn'] * 100:8.4f} {std['designed'] * 100:8.4f} {r:6.2f} "
              f"{pred_ratio:10.2f} {peak['drawn']:16.2f} {peak['designed']:8.2f}  "
              f"{d.params['f_min_hz']:g}-{d.params['f_max_hz']:g} Hz, {d.binding}; designed "
              f"empirical/predicted(true) {emp_pred[-1]:.2f}")
    r = np.array(ratios)
    print(f"design/drawn std ratio: median {np.nanmedian(r):.2f}, better on {np.sum(r < 1)}/{len(r)}; "
          f"designed peak/limit max {np.nanmax(peaks):.2f}; failures {fails}; designed empirical/"
          f"predicted(true): median {np.nanmedian(emp_pred):.2f}, range {np.nanmin(emp_pred):.2f}-"
          f"{np.nanmax(emp_pred):.2f}")
