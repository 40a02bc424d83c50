"""gearbench init DIR: a station folder (profiles, drivers, a README) from the shipped examples."""
from __future__ import annotations

import shutil
from pathlib import Path

from ..errors import GearbenchError

NAME = "init"
HELP = "Make a station folder (example profiles, drive descriptions, README) to edit for your bench."

STATION_README = """\
# gearbench station

Made by `gearbench init` (gearbench {version}). Run gearbench from this folder.

    gearbench run cvt --sim --yes            # the shipped CVT job on the simulated bench
    gearbench run profiles/cvt.yaml --serial SN123 --report   # on the real bench, with report.html
    gearbench validate profiles/cvt.yaml     # check a profile without moving anything

## What to edit

- `profiles/*.yaml` — one file per product. Copy `cvt.yaml` and change: `bench.bus`
  (real tester: `interface: socketcan`, `channel: can0`; Modbus: `host`, `port`),
  the motors' `address` (node / unit id), `kt_datasheet`, current and speed limits,
  `counts_per_rev`, the reducer's nominal `ratio`, the inertia `disks` you own,
  the efficiency grid, and the `limits` that decide pass / fail. Drop the
  `simulation:` section if you never run `--sim`. Format: docs/profile-format.md
  in the gearbench sources, or `gearbench validate` which names any wrong field.
- `drivers/` — drive descriptions: the vendor's EDS for a CANopen CiA 402 drive,
  a register map `.yaml` for a Modbus TCP drive. A new drive model is a new file
  here, referenced by a profile as `drive: drivers/<file>`.

## Where files are found

A relative `drive:` is looked up in the profile's own folder, then in this station
folder (`drivers/` beside `profiles/`, then the folder you run gearbench in), then
in the descriptions shipped with gearbench — so a file here overrides the shipped
one of the same name. `gearbench run NAME` runs `profiles/NAME.yaml` from here,
else the shipped example of that name.

Results go to `results/<serial>-<time>/` (result.json, junit.xml, traces, and
report.html with `--report`); the station database is `results/station.sqlite`.
"""


def add_arguments(p) -> None:
    p.add_argument("dir", metavar="DIR", help="station folder to create (may exist; files in it are kept)")


def run(args) -> int:
    from .. import __version__
    from ..drives.shipped import shipped_dir

    root = Path(args.dir)
    if root.exists() and not root.is_dir():
        raise GearbenchError(f"{root}: exists and is not a folder; choose another DIR")
    made, kept = [], []
    try:
        for kind in ("profiles", "drivers"):
            src = shipped_dir(kind)
            for f in sorted(src.rglob("*")):
                if not f.is_file() or "__pycache__" in f.parts or f.suffix == ".pyc":
                    continue
                dest = root / kind / f.relative_to(src)
                (kept if dest.exists() else made).append(dest)
                if not dest.exists():
                    dest.parent.mkdir(parents=True, exist_ok=True)
                    shutil.copyfile(f, dest)
        readme = root / "README.md"
        (kept if readme.exists() else made).append(readme)
        if not readme.exists():
            readme.write_text(STATION_README.format(version=__version__))
    except OSError as exc:
        raise GearbenchError(f"{exc.filename or root}: cannot write ({exc.strerror}); "
                             f"choose a writable DIR") from None
    print(f"gearbench init: station {root}: {len(made)} files written"
          + (f", {len(kept)} existing files kept" if kept else ""))
    print(f"  next: cd {root} && gearbench run cvt --sim --yes   (edit profiles/ and drivers/, see README.md)")
    return 0
