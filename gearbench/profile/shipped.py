"""Where gearbench finds a profile given by name: ``./profiles/NAME.yaml``, else the
example of that name it ships (see ``gearbench.drives.shipped`` for the shipped folders)."""
from __future__ import annotations

from pathlib import Path

from ..drives.shipped import shipped_dir


def find_profile(arg: str | Path) -> Path:
    """A profile path as given; a bare name (``cvt``) is the station's
    ``profiles/cvt.yaml`` or the shipped example. Returned unchanged when nothing
    matches, so the caller reports the path the user typed."""
    p = Path(arg)
    if p.exists() or p.parent != Path("."):
        return p
    names = [p.name] if p.suffix in (".yaml", ".yml") else [f"{p.name}.yaml", f"{p.name}.yml"]
    for folder in (Path("profiles"), shipped_dir("profiles")):
        for name in names:
            if (folder / name).is_file():
                return folder / name
    return p


def shipped_profiles() -> list[str]:
    """Names of the example profiles gearbench ships (``gearbench run NAME``)."""
    return sorted(x.stem for x in shipped_dir("profiles").glob("*.y*ml"))
