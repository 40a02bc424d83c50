"""gearbench design-excitation PROFILE: the calibration multisine designed for Kt, with predictions."""
from __future__ import annotations

import json

NAME = "design-excitation"
HELP = ("Design the calibration multisine that minimises Kt's variance per bench second within "
        "the motors' limits, and print it with its predicted Kt scatter; nothing moves.")


def add_arguments(p) -> None:
    p.add_argument("profile", help="test profile YAML, e.g. profiles/cvt.yaml")
    p.add_argument("--motor", help="only this motor's calibrate step (e.g. in)")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def run(args) -> int:
    from ..profile import excitation_design as ed
    from ..errors import GearbenchError
    from ..profile import CalibrateStep, load_profile
    from ..profile.design import DesignProblem, design_waveform, motor_case

    profile = load_profile(args.profile)
    steps = [s for s in profile.steps if isinstance(s, CalibrateStep)]
    if args.motor is not None:
        steps = [s for s in steps if s.motor == args.motor]
    if not steps:
        known = ", ".join(sorted({s.motor for s in profile.steps if isinstance(s, CalibrateStep)})) or "none"
        raise GearbenchError(f"{args.profile}: no calibrate step for motor {args.motor!r} "
                             f"(calibrated motors: {known}); pick one with --motor")
    period = profile.bench.period_s
    kt_target = getattr(getattr(profile, "targets", None), "kt_rel", None)
    out, lines = [], []
    for step in steps:
        wave = profile.waveforms[step.waveform]
        motor, disk = profile.motors[step.motor], profile.disks[step.disk]
        try:
            case = motor_case(motor, disk, wave.params if wave.kind == "multisine" else
                              _default_knobs())
            if wave.design is not None:
                params, design = wave.params, wave.design
            else:
                params, design = design_waveform(
                    {**_default_knobs(), **(wave.params if wave.kind == "multisine" else {})},
                    [(motor, disk, step.duration_s)], period,
                    also_fit_s=[step.min_s] if getattr(step, "min_s", None) else ())
        except DesignProblem as exc:
            raise GearbenchError(f"{args.profile}: {'.'.join(map(str, exc.path))}: {exc.problem}; "
                                 f"{exc.fix}") from None
        pred = ed.predict_calibration("multisine", params, case, duration_s=step.duration_s,
                                      period_s=period)
        current = None
        if wave.design is None and wave.kind in ("multisine", "chirp", "prbs", "trapezoid") \
                and step.mode == "velocity":
            current = ed.predict_calibration(wave.kind, wave.params, case, duration_s=step.duration_s,
                                             period_s=period)
        rec = {"step": step.name, "motor": step.motor, "disk": step.disk, "waveform": step.waveform,
               "designed_in_profile": wave.design is not None,
               "assumptions": {k: v for k, v in case.__dict__.items()},
               "design": {k: v for k, v in params.items() if v is not None},
               "binding": design.binding, "acceleration_crest_factor": design.acceleration_crest_factor,
               "prediction": pred.to_dict(),
               "profile_waveform_prediction": current.to_dict() if current else None}
        if kt_target:
            rec["bench_s_for_target"] = _bench_time(pred.kt_rel_std_per_sqrt_s, kt_target)
        out.append(rec)
        lines += _text(rec, pred, current, design, kt_target, step)
    if args.json:
        print(json.dumps({"profile": str(args.profile), "steps": out}, indent=2, default=float))
    else:
        print("\n".join(lines))
    return 0


def _default_knobs() -> dict:
    from ..profile import waveforms as wf

    return {k: p.default for k, p in wf.PARAMS["multisine"].items() if p.default is not wf.REQUIRED}


def _bench_time(per_sqrt_s: float, kt_rel_95: float) -> float:
    """Bench seconds (both runs) for a 95 % statistical half-width ``kt_rel_95`` (k = 1.96)."""
    return (1.96 * per_sqrt_s / kt_rel_95) ** 2


def _text(rec, pred, current, design, kt_target, step) -> list[str]:
    from ..profile.excitation_design import multisine_summary

    a = rec["assumptions"]
    p = rec["design"]
    src = "designed in the profile (design: optimal)" if rec["designed_in_profile"] else \
        f"design proposed for waveform '{rec['waveform']}'"
    lines = [f"{rec['step']}: motor {rec['motor']} with disk {rec['disk']} - {src}",
             f"  assumes    Kt {a['kt_nm_a']:g} N m/A, J {a['rotor_inertia_kgm2']:.4g} + disk "
             f"{a['disk_inertia_kgm2']:.4g} kg m^2, friction {a['friction_nm']:.3g} N m, current noise "
             f"{a['current_noise_a'] * 1e3:.3g} mA, {a['counts_per_rev']} counts/rev",
             f"  limits     peak {a['peak_current_a']:.3g} A, rms {a['rms_current_a']:.3g} A, speed "
             f"{a['min_speed_rad_s']:.4g}-{a['max_speed_rad_s']:.4g} rad/s (forward only)",
             f"  design     {multisine_summary(p)}",
             f"  binding    {design.binding}; acceleration crest factor {design.acceleration_crest_factor:.3f}",
             "  profile    kind: multisine, offset: {offset:.4g}, amplitude: {amplitude:.4g}, period_s: {period_s:g}, "
             "f_min_hz: {f_min_hz:g}, f_max_hz: {f_max_hz:g}, phases: {phases}, spectrum: {spectrum}, "
             "fade_in_s: {fade_in_s:g}".format(**p),
             f"  predicted  {_pred(pred)}"]
    if current is not None:
        gain = (current.kt_rel_std_per_sqrt_s / pred.kt_rel_std_per_sqrt_s) ** 2
        lines.append(f"  profile's  {_pred(current)}")
        lines.append(f"             -> the design needs {1 / gain:.2f}x the bench time for the same Kt scatter")
    if kt_target:
        lines.append(f"  target     targets.kt_rel {kt_target:g} (95 %, statistical) needs about "
                     f"{rec['bench_s_for_target']:.2f} s of bench time for both runs (step allows "
                     f"{2 * step.duration_s:g} s)")
    lines.append("  note       prediction assumes ideal speed tracking; a PI speed loop near its "
                 "bandwidth draws ~1.2-1.3x more current (more information, and the reason for "
                 "peak_current_fraction's margin)")
    return lines


def _pred(p) -> str:
    return (f"Kt rel std {p.kt_rel_std * 100:.4f} % for 2 x {p.duration_s:g} s = "
            f"{p.kt_rel_std_per_sqrt_s * 100:.4f} % per sqrt(s) (b2 {p.b2_rel_std_unloaded * 100:.4f} / "
            f"{p.b2_rel_std_loaded * 100:.4f} % alone / with disk), peak {p.peak_current_a:.3g} A, "
            f"rms {p.rms_current_a:.3g} A, speed {p.speed_range_rad_s[0]:.0f}-{p.speed_range_rad_s[1]:.0f} rad/s")


