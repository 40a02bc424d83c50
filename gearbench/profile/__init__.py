"""Test profiles: YAML in, a validated ``Profile`` out, before anything moves.

>>> from gearbench.profile import load_profile
>>> profile = load_profile("profiles/cvt.yaml")
>>> profile.estimated_bench_time_s

Every problem raises one ``ProfileError`` line ``file:line:col: key.path: problem; fix``.
The format is documented in ``docs/profile-format.md``.
"""
from __future__ import annotations

import hashlib
from pathlib import Path

from ..errors import ProfileError
from .model import (BenchSpec, BusSpec, CalibrateStep, DiskSpec, EfficiencyStep, LimitSpec, LoadStep, MotorSpec,
                    Outputs, Profile, ReducerSpec, Step, Targets, WaveformSpec)
from .parse import build_profile
from .yamlmarks import load_with_marks
from .shipped import find_profile, shipped_profiles

__all__ = ["load_profile", "parse_profile_text", "Profile", "BenchSpec", "BusSpec", "MotorSpec", "ReducerSpec",
           "DiskSpec", "WaveformSpec", "CalibrateStep", "LoadStep", "EfficiencyStep", "Step", "LimitSpec", "Targets",
           "ProfileError"]


def load_profile(path: str | Path) -> Profile:
    """Read and validate a profile file; ``ProfileError`` (one line, file:line:col) on any problem.

    A bare name (``cvt``) is ``./profiles/cvt.yaml`` or the shipped example. Relative
    drive paths resolve against the profile's folder, the station, then the shipped
    drive descriptions (``gearbench.drives.shipped``).
    """
    p = find_profile(path)
    shown = str(path) if p == Path(path) else str(p)
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        from .yamlmarks import did_you_mean

        names = shipped_profiles()
        hint = did_you_mean(Path(str(path)).stem, names) if p.parent == Path(".") else ""
        hint = hint + " " if hint.startswith("did you mean") else ""
        raise ProfileError(f"{shown}: no such profile file; {hint}check the path, or give a shipped "
                           f"profile by name ({', '.join(names)})") from None
    except IsADirectoryError:
        raise ProfileError(f"{shown}: is a folder, not a profile; give a .yaml file inside it") from None
    except OSError as exc:
        raise ProfileError(f"{shown}: cannot read the profile ({exc.strerror}); check permissions") from None
    return _parse(data, shown, p, p.resolve().parent)


def parse_profile_text(text: str | bytes, filename: str = "<profile>", base_dir: str | Path = ".") -> Profile:
    """Validate profile YAML given as text (tests, tools); drive paths resolve from ``base_dir``."""
    data = text.encode("utf-8") if isinstance(text, str) else text
    return _parse(data, filename, Path(filename), Path(base_dir).resolve())


def _parse(data: bytes, shown: str, path: Path, base_dir: Path) -> Profile:
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[:exc.start].count(b"\n") + 1
        col = exc.start - (data.rfind(b"\n", 0, exc.start) + 1) + 1
        raise ProfileError(f"{shown}:{line}:{col}: not UTF-8 text; save the profile as UTF-8") from None
    doc = load_with_marks(text, shown)
    return build_profile(doc, path, hashlib.sha256(data).hexdigest(), base_dir)
