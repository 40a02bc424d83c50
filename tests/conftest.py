"""Shared test helpers."""
from __future__ import annotations

import os
import shutil

import pytest


def in_ci() -> bool:
    """True where ``.ci/run`` runs the suite (it installs the Debian tools the tests use)."""
    return os.environ.get("CI", "").lower() in ("1", "true", "yes")


def require_tool(name: str, install_hint: str) -> str:
    """Path of an external program, or skip (fail in CI) with a one-line reason.

    On a developer's machine with only python3 a test that needs, say, Debian's
    ``mbpoll`` is skipped with the install hint; in CI, where ``.ci/run`` installs it,
    its absence fails the test so it can never be skipped unnoticed where it matters.
    """
    exe = shutil.which(name)
    if exe is None:
        message = f"{name} is not installed; {install_hint}"
        if in_ci():
            pytest.fail(message + " (.ci/run installs it; in CI this test must not be skipped)")
        pytest.skip(message)
    return exe
