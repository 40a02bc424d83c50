"""The twin's ``simulation:`` block on disk: read (for ``run --sim --twin``) and checked."""
from __future__ import annotations

from pathlib import Path

import yaml

from ..errors import GearbenchError, ProfileError
from ..sim import PlantParams


def load_twin_block(path: str) -> dict:
    """The ``simulation:`` block of a twin file (for ``run --sim --twin``), checked."""
    p = Path(path)
    try:
        doc = yaml.safe_load(p.read_text())
    except OSError as exc:
        raise GearbenchError(f"{p}: cannot read ({exc.strerror})") from None
    except yaml.YAMLError as exc:
        raise ProfileError(f"{p}: not valid YAML ({exc})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("simulation"), dict):
        raise ProfileError(f"{p}: expected a 'simulation:' mapping (written by gearbench twin --write)")
    try:
        PlantParams.from_dict(doc["simulation"], "simulation")
    except ProfileError as exc:
        raise ProfileError(f"{p}: {exc}") from None
    return doc["simulation"]
