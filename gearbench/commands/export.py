"""gearbench export RUN_DIR --mdf: a run's traces for other tools (ASAM MDF4)."""
from __future__ import annotations

from pathlib import Path

from ..errors import GearbenchError

NAME = "export"
HELP = "Export a run folder's traces for other tools: ASAM MDF4 (.mf4) with units and the run's metadata."


def add_arguments(p) -> None:
    p.add_argument("run_dir", metavar="RUN_DIR", help="output folder of 'gearbench run'")
    p.add_argument("--mdf", action="store_true", required=True,
                   help="write ASAM MDF4 (read by CANape, asammdf, MATLAB): one channel group per "
                        "step, master channel time_s, units on every channel")
    p.add_argument("--out", help="output file (default RUN_DIR/traces.mf4)")


def command_units_of(run_dir: Path) -> dict:
    """The drive mode of each step's setpoints, from the profile copied into the run
    folder (profile.yaml); empty when it is missing or no longer loads."""
    from ..profile import load_profile
    from ..station.plan import command_units

    snap = run_dir / "profile.yaml"
    if not snap.is_file():
        return {}
    try:
        return command_units(load_profile(snap))
    except GearbenchError:
        return {}


def run(args) -> int:
    from ..reports.mdf import write_mdf

    run_dir = Path(args.run_dir)
    path = write_mdf(run_dir, args.out, command_units_of(run_dir))
    print(f"gearbench export: wrote {path}")
    return 0
