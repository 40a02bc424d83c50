"""The package layout is the architecture: import-linter's contracts (pyproject.toml
``[tool.importlinter]``) and the short list of top-level modules."""
from pathlib import Path

import pytest

import gearbench

PACKAGE = Path(gearbench.__file__).parent
# the package's face and its shared types; everything else lives in a layer's folder
TOP_LEVEL = {"__init__.py", "__main__.py", "cli.py", "api.py", "errors.py", "trace.py"}


def test_import_contracts_kept(capsys):
    lint = pytest.importorskip("importlinter.cli")
    code = lint.lint_imports(config_filename=str(PACKAGE.parent / "pyproject.toml"), no_cache=True)
    out = capsys.readouterr().out
    assert code == 0, out[-3000:]


def test_no_loose_modules():
    loose = {p.name for p in PACKAGE.glob("*.py")} - TOP_LEVEL
    assert not loose, f"modules outside a layer's folder: {sorted(loose)}"


def test_old_public_imports_still_work():
    from gearbench.recorder import read_partial
    from gearbench.station.recorder import read_partial as new
    assert read_partial is new
    from gearbench.bench import available
    assert "accuracy" in available()
