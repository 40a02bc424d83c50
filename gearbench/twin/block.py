"""The twin's ``simulation:`` block on disk: read (for ``run --sim --twin``) and checked."""
from __future__ import annotations

from pathlib import Path

import yaml

from ..errors import GearbenchError, ProfileError
from ..profile.parse import SIM_CHECKED, rating_differs
from ..sim import MotorParams, PlantParams


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


def check_twin_bench(block: dict, profile, path: str) -> None:
    """A twin describes one bench: its motors must be the profile's, with the ratings the
    drives report at start-up (``SIM_CHECKED``: rated current, encoder). Another bench's twin
    is refused here, naming the twin, instead of by the drive's start-up check, which would
    blame the profile. The reducer may differ: a bench's twin predicts a new product's run."""
    motors = block.get("motors") or {}
    missing = [m for m in profile.motors if m not in motors]
    extra = [m for m in motors if m not in profile.motors]
    if missing or extra:
        raise ProfileError(f"{path}: the twin's motors ({', '.join(motors) or 'none'}) are not the profile's "
                           f"({', '.join(profile.motors)}): it was fitted on another bench; fit a twin on a "
                           f"run of this bench (gearbench twin RUN_DIR --write)")
    for name, spec in profile.motors.items():
        for key in SIM_CHECKED:
            # the emulator reads the twin alone: a rating left out is the plant's default
            got, want = motors[name].get(key, getattr(MotorParams, key)), getattr(spec, key)
            if rating_differs(got, want):
                raise ProfileError(f"{path}: motors.{name}.{key} is {got:g} in the twin but {want:g} in "
                                   f"{profile.path}: the twin was fitted on another bench; fit a twin on a "
                                   f"run of this bench (gearbench twin RUN_DIR --write)")
