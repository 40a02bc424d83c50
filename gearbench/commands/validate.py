"""gearbench validate PROFILE: check a test profile without moving anything."""
from __future__ import annotations

import os
import sys
from pathlib import Path

NAME = "validate"
HELP = "Check a test profile (YAML) and print a summary; nothing moves."


def add_arguments(p) -> None:
    p.add_argument("profile", help="test profile YAML, e.g. profiles/cvt.yaml")
    p.add_argument("--twin", metavar="YAML",
                   help="also run the profile on this digital twin of the bench (gearbench twin --write) "
                        "and say what it predicts: bench time, intervals, verdicts")


def run(args) -> int:
    from ..profile import load_profile

    from ..drives.devicecheck import check_profile
    from ..profile.coverage import uncovered

    profile = load_profile(args.profile)
    devices = check_profile(profile)   # every device description: all problems at once
    lines = summary_lines(profile, args.profile)
    if devices.errors:
        lines[0] = f"{args.profile}: REFUSED - {len(devices.errors)} problem{'s' * (len(devices.errors) > 1)} " \
                   f"with the drives (nothing moved)"
    lines += [f"drives     {n}" for n in devices.notes]
    lines += [f"warning    {w}" for w in devices.warnings]
    lines += [f"warning    {w}" for w in uncovered(profile)]
    print("\n".join(lines))
    if devices.errors:
        print("\n".join(f"error      {e}" for e in devices.errors), file=sys.stderr)
        return 2
    if getattr(args, "twin", None):
        print("\n".join(twin_prediction(args.profile, args.twin)))
    return 0


def twin_prediction(profile: str, twin: str) -> list[str]:
    """Run the profile on the twin (``run --sim --twin``) in a scratch folder and say what
    the bench would give: bench time, each Kt and η with its 95 % interval, verdicts."""
    import tempfile

    from ..api import run_profile

    with tempfile.TemporaryDirectory() as tmp:
        r = run_profile(profile, sim=True, twin=twin, out_dir=f"{tmp}/run", serial="TWIN-PREDICTION",
                        db=f"{tmp}/station.sqlite", yes=True, quiet=True)
    lines = [f"twin       on {twin}: bench time {r.get('bench_time_s', float('nan')):.1f} s, "
             f"predicted verdict {r['status'].upper()}{' (' + r['reason'] + ')' if r.get('reason') else ''}"]
    for m, v in (r.get("motors") or {}).items():
        ci = v.get("Kt_ci95") or [float("nan")] * 2
        lines.append(f"twin       Kt {m} {v['Kt']:.5g} N m/A, 95 % interval ±{(ci[1] - ci[0]) / 2:.2g}")
    for e in r.get("efficiency") or []:
        ci = e.get("eta_incremental_ci95") or [float("nan")] * 2
        lines.append(f"twin       eta {e['speed_in_rad_s']:.0f} rad/s {e['torque_out_nm']:.3f} N m: "
                     f"{e['eta_incremental']:.4f} ±{(ci[1] - ci[0]) / 2:.4f}")
    return lines


def _rel(path: str) -> str:
    try:
        return os.path.relpath(path)
    except ValueError:  # another drive on Windows
        return path


def _fmt(x: float) -> str:
    return f"{x:g}"


def summary_lines(profile, shown: str | Path) -> list[str]:
    """The human summary ``gearbench validate`` prints (one fact per line)."""
    from ..profile import CalibrateStep, EfficiencyStep, LoadStep

    b = profile.bench
    bus = b.bus
    if bus.family == "modbus":
        where = f"modbus TCP {bus.host}:{bus.port}"
    else:
        where = f"{bus.family} over {bus.interface or '?'}" + (f" {bus.channel}" if bus.channel else "")
    lines = [f"{shown}: OK (sha256 {profile.sha256[:12]})",
             f"profile    {profile.name}" + (f" - {profile.description}" if profile.description else ""),
             f"bench      {b.name}: {where}, sample period {b.period_s * 1e3:g} ms"]
    for i, m in enumerate(profile.motors.values()):
        head = "motors    " if i == 0 else "          "
        lines.append(f"{head} {m.name:<4} address {m.address}, {_rel(m.drive)}, Kt {_fmt(m.kt_datasheet)} N m/A, "
                     f"rated {_fmt(m.rated_current_a)} A, limit {_fmt(m.current_limit_a)} A, "
                     f"{_fmt(m.speed_limit_rad_s)} rad/s")
    r = profile.reducer
    if r is None:
        lines.append("reducer    none (motors only)")
    else:
        ratio = "measured" if r.ratio is None else _fmt(r.ratio)
        cvt = f", CVT setting {r.cvt_setting:.0%}" if r.cvt_setting is not None else ""
        lines.append(f"reducer    {r.name}: ratio {ratio}{cvt}, expected efficiency "
                     f"{_fmt(r.efficiency_range[0])}-{_fmt(r.efficiency_range[1])}")
    for i, s in enumerate(profile.steps):
        head = "steps     " if i == 0 else "          "
        if isinstance(s, CalibrateStep):
            what = (f"calibrate motor {s.motor} with {s.waveform} ({profile.waveforms[s.waveform].kind}, "
                    f"{s.mode}), alone then with disk {s.disk}: 2 x "
                    + (f"{_fmt(s.min_s)}..{_fmt(s.max_s)} s until Kt is known to {_fmt(100 * profile.targets.kt_rel)} %"
                       if s.adaptive else f"{_fmt(s.duration_s)} s")
                    + (" (alone at once with the other motor; the disk runs together when each motor "
                       "has its own disk, else in turn)" if profile.bench.parallel_calibration else ""))
        elif isinstance(s, LoadStep):
            what = f"prompt: {s.prompt}"
        else:
            assert isinstance(s, EfficiencyStep)
            ratio = profile.reducer.ratio if profile.reducer else None
            outs = f", output {', '.join(_fmt(w / ratio) for w in s.speeds_in_rad_s)} rad/s" if ratio else ""
            what = (f"input {', '.join(_fmt(w) for w in s.speeds_in_rad_s)} rad/s{outs}; braking "
                    f"{', '.join(_fmt(t) for t in s.torques_out_nm)} N m at the output: "
                    f"{len(s.speeds_in_rad_s)} speeds x {len(s.torques_out_nm)} torques = {s.operating_points} "
                    + (f"operating points, staircase of {len(s.levels())} levels x {_fmt(s.min_s)}..{_fmt(s.max_s)} s "
                       f"until the efficiency slope is known to {_fmt(profile.targets.eta_pp)} pp" if s.adaptive else
                       f"operating points, {len(s.levels())} levels x ({_fmt(s.settle_s)} + {_fmt(s.measure_s)}) s"))
        lines.append(f"{head} {i + 1}. {s.name:<14} {what}  [{s.bench_time_s:.1f} s]")
    limits = ", ".join(f"{lim.name} [{'-inf' if lim.low is None else f'{lim.low:.4g}'}, "
                       f"{'inf' if lim.high is None else f'{lim.high:.4g}'}]" for lim in profile.limits)
    lines.append(f"limits     {limits or 'none'}")
    sim = profile.simulation
    lines.append("simulation " + ("plant defined (used by --sim)" if sim is not None else "none (--sim uses defaults)"))
    lines.append(f"operating points {profile.operating_points}; estimated bench time "
                 f"{profile.estimated_bench_time_s:.1f} s (motors running; operator prompts not included"
                 + ("; adaptive steps at their max_s: an upper bound)" if any(
                     getattr(s, "adaptive", False) for s in profile.steps) else ")"))
    return lines
