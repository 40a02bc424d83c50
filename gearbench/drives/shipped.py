"""Where gearbench finds drive descriptions and profiles: a profile's own folder, the
station's folder, then the ones it ships.

The wheel carries the repository's top-level ``drivers/`` and ``profiles/`` as
``gearbench/_data/`` (see setup.py); a source checkout or an editable install uses
the top-level folders themselves, so both see the same files.

A relative ``drive:`` in a profile is looked up, first hit wins, in

1. the profile's folder (``drive: drivers/x.eds`` next to the profile),
2. the station: the folder above the profile's folder when it has a ``drivers/``
   folder (the layout ``gearbench init`` makes: ``STATION/profiles/*.yaml`` beside
   ``STATION/drivers/``), then the current directory — each as given and inside
   its ``drivers/``,
3. the drive descriptions shipped with gearbench.

A profile given by name (``gearbench run cvt``) is ``./profiles/cvt.yaml``, else the
shipped example of that name.
"""
from __future__ import annotations

from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parent.parent   # gearbench/


def shipped_dir(kind: str) -> Path:
    """The shipped ``drivers`` or ``profiles`` folder (installed wheel or checkout)."""
    installed = PACKAGE_DIR / "_data" / kind
    return installed if installed.is_dir() else PACKAGE_DIR.parent / kind


def shipped_driver(name: str) -> Path:
    """A shipped drive description by file name, e.g. ``cia402-servo.eds``."""
    return shipped_dir("drivers") / name


def drive_candidates(value: str | Path, profile_dir: Path) -> list[Path]:
    """The places a profile's ``drive:`` value is looked for, in order (module docstring)."""
    rel = Path(value).expanduser()
    if rel.is_absolute():
        return [rel]
    stations = []
    if (profile_dir.parent / "drivers").is_dir():
        stations.append(profile_dir.parent)
    stations.append(Path.cwd())
    inside = rel.parts[1:] if rel.parts and rel.parts[0] == "drivers" and len(rel.parts) > 1 else rel.parts
    out = [profile_dir / rel]
    for s in stations:
        out += [s / rel, s / "drivers" / Path(*inside)]
    out.append(shipped_dir("drivers") / Path(*inside))
    return list(dict.fromkeys(out))


def find_drive(value: str | Path, profile_dir: Path) -> tuple[Path | None, list[Path]]:
    """(resolved file or None, the places looked in)."""
    looked = drive_candidates(value, profile_dir)
    for cand in looked:
        if cand.is_file():
            return cand.resolve(), looked
    return None, looked
