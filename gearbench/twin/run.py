"""A recorded run as the twin reads it: its result, traces and profiles, and the drives'
units of setpoints and current (``drive_quanta``)."""
from __future__ import annotations

import json
import math
from pathlib import Path

from ..errors import GearbenchError, ProfileError
from ..trace import Trace


def load_run(run_dir: str, profile_path: str | None):
    """(result dict, {step: Trace}, Profile of the run, starting Profile) with one-line errors."""
    from ..profile import load_profile

    root = Path(run_dir)
    if not (root / "result.json").is_file():
        raise GearbenchError(f"{root}: no result.json; is this a gearbench run folder?")
    try:
        result = json.loads((root / "result.json").read_text())
    except json.JSONDecodeError as exc:
        raise GearbenchError(f"{root}/result.json: not valid JSON (line {exc.lineno})") from None
    traces = {}
    for f in sorted(root.glob("trace-*.parquet")):
        traces[f.name[len("trace-"):-len(".parquet")]] = Trace.read(f)
    if not traces:
        raise GearbenchError(f"{root}: no trace-*.parquet; the twin replays recorded steps")
    run_profile_path = root / "profile.yaml"
    if not run_profile_path.is_file() and not profile_path:
        raise GearbenchError(f"{root}: no profile.yaml in the run folder; pass --profile PROFILE")
    run_prof = load_profile(run_profile_path if run_profile_path.is_file() else profile_path)
    start = load_profile(profile_path) if profile_path else run_prof
    if not start.simulation:
        raise ProfileError(f"{start.path}: no 'simulation:' section; the twin starts from the "
                           f"profile's simulated bench (see profiles/cvt.yaml)")
    return result, traces, run_prof, start


def drive_quanta(profile):
    """The drives' units of setpoints and reported current (``Quanta``), read from each
    motor's drive description as the bus master does (CiA 402: 0x60FF in the drive's
    velocity unit, 0x6071/0x6078 per mille of rated current); none for other buses."""
    from ..twin.replay import AXES, Quanta

    if profile.bench.bus.family != "cia402":
        return Quanta()
    vel, tq, cur = {}, {}, {}
    for a, m in profile.motors.items():
        if a not in AXES:
            continue
        per = 2 * math.pi / m.counts_per_rev
        try:
            from ..drives.description import resolve, velocity_unit_rad_s

            d = resolve(str(m.drive), m.address)
            if isinstance(d.velocity_unit, int):
                per = velocity_unit_rad_s(d.velocity_unit) or per
        except Exception:   # an unreadable description: assume inc/s, the CiA 402 default
            pass
        vel[a], tq[a], cur[a] = per, m.rated_current_a / 1000.0, m.rated_current_a / 1000.0
    return Quanta(velocity_rad_s=vel, torque_a=tq, current_a=cur)
