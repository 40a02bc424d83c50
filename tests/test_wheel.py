"""The installed product: build the wheel, install it (not editable) into a fresh venv,
and from an empty folder ``gearbench init`` a station and run a job on the simulated
bench by profile name — no source checkout involved.

Dependencies are not downloaded again: the fresh venv sees this environment's
site-packages through a ``.pth`` line (after its own), so only gearbench itself
comes from the wheel; the test checks that it really is the wheel's copy that ran.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import time
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SOURCE = ("gearbench", "drivers", "profiles", "pyproject.toml", "setup.py", "MANIFEST.in", "README.md")


def _copy_source(dest: Path) -> None:
    """The files a build reads, without caches or an old build/ folder."""
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info")
    for name in SOURCE:
        src = REPO / name
        if src.is_dir():
            shutil.copytree(src, dest / name, ignore=ignore)
        elif src.exists():
            shutil.copy2(src, dest / name)


def _run(cmd, cwd, env, timeout=600):
    p = subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True,
                       timeout=timeout)
    assert p.returncode == 0, f"{' '.join(map(str, cmd))} -> {p.returncode}\n{p.stdout[-3000:]}\n{p.stderr[-3000:]}"
    return p


@pytest.mark.slow   # ~60-90 s on 2 loaded cores: a full simulated calibration of both motors
def test_wheel_installs_and_runs_from_an_empty_folder(tmp_path):
    t0 = time.monotonic()
    src = tmp_path / "src"
    src.mkdir()
    _copy_source(src)
    # A file dropped into drivers/ (even in a sub-folder) ships without being listed anywhere.
    (src / "drivers" / "vendor-x").mkdir()
    shutil.copy2(src / "drivers" / "cia402-servo.eds", src / "drivers" / "vendor-x" / "new-drive.eds")
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", tmp_path / "dist", src],
         tmp_path, env)
    wheel = next((tmp_path / "dist").glob("gearbench-*.whl"))
    names = set(zipfile.ZipFile(wheel).namelist())
    for kind in ("drivers", "profiles"):
        for f in (REPO / kind).rglob("*"):
            if f.is_file() and "__pycache__" not in f.parts:
                assert f"gearbench/_data/{kind}/{f.relative_to(REPO / kind).as_posix()}" in names, f
    assert "gearbench/_data/drivers/vendor-x/new-drive.eds" in names
    t_build = time.monotonic() - t0

    venv = tmp_path / "fresh"
    _run([sys.executable, "-m", "venv", "--without-pip", venv], tmp_path, env)
    py = venv / "bin" / "python"
    _run([sys.executable, "-m", "pip", "--python", py, "install", "--no-deps", "--no-index", "-q", wheel],
         tmp_path, env)
    site = Path(_run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                     tmp_path, env).stdout.strip())
    # dependencies from this environment, searched after the fresh venv's own packages
    (site / "zz_test_dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    env["VIRTUAL_ENV"] = str(venv)

    empty = tmp_path / "empty"
    empty.mkdir()
    where = _run([py, "-c", "import gearbench; print(gearbench.__file__)"], empty, env).stdout.strip()
    assert Path(where).is_relative_to(venv), f"gearbench imported from {where}, not from the wheel"
    version = _run(["gearbench", "--version"], empty, env).stdout
    from gearbench import __version__
    assert f"gearbench {__version__}" in version

    _run(["gearbench", "init", "station"], empty, env)
    station = empty / "station"
    assert (station / "README.md").is_file()
    assert (station / "profiles" / "cvt.yaml").is_file()
    assert (station / "drivers" / "cia402-servo.eds").is_file()
    t_run = time.monotonic()
    p = _run(["gearbench", "run", "motors-only", "--sim", "--yes", "--quiet", "--out", "results/w1"],
             station, env)
    res = json.loads((station / "results" / "w1" / "result.json").read_text())
    assert res["passed"] is True and res["gearbench_version"] == __version__, p.stderr
    assert res["method_version"]
    assert (station / res["profile_path"]).resolve() == (station / "profiles" / "motors-only.yaml").resolve()
    # drive: drivers/cia402-servo.eds is the station's copy; a name only the wheel has is the shipped one
    drive = _run([py, "-c", "from gearbench.profile import load_profile; "
                  "print(load_profile('motors-only').motors['in'].drive)"], station, env).stdout.strip()
    assert Path(drive) == (station / "drivers" / "cia402-servo.eds").resolve()
    (station / "drivers" / "cia402-servo.eds").unlink()
    drive = _run([py, "-c", "from gearbench.profile import load_profile; "
                  "print(load_profile('motors-only').motors['in'].drive)"], station, env).stdout.strip()
    assert Path(drive) == (site / "gearbench" / "_data" / "drivers" / "cia402-servo.eds").resolve()
    for m in ("in", "out"):
        assert abs(res["motors"][m]["Kt"] / res["simulation_truth"]["motors"][m]["Kt"] - 1) < 0.01
    print(f"\nwheel test: build {t_build:.1f} s, install + init {t_run - t0 - t_build:.1f} s, "
          f"run {time.monotonic() - t_run:.1f} s")
