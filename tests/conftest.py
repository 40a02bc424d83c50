"""Shared test helpers."""
from __future__ import annotations

import os
import shutil

import pytest


def in_ci() -> bool:
    """True where ``.ci/run`` runs the suite (it installs the Debian tools the tests use)."""
    return os.environ.get("CI", "").lower() in ("1", "true", "yes")


def require_dev_data() -> None:
    """Skip (fail in CI, where ``../shared`` is always beside the clone) when the dev
    data sets are absent."""
    from gearbench.bench._data import DEV_DIR

    if not (DEV_DIR / "truth.json").is_file():
        message = f"dev data not found at {DEV_DIR} (../shared/datasets/dev beside the checkout)"
        if in_ci():
            pytest.fail(message + " (CI provides ../shared; in CI this test must not be skipped)")
        pytest.skip(message)


@pytest.fixture(scope="session")      # before any module fixture that reads the data
def dev_data():
    """Use as ``pytest.mark.usefixtures("dev_data")`` on tests that read the dev data."""
    require_dev_data()


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
