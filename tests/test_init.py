"""gearbench init and where files are found: profile by name, drive description in the
profile's folder, then the station, then the shipped ones (gearbench.drives.shipped)."""
from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from gearbench.cli import main
from gearbench.profile import load_profile
from gearbench.drives.shipped import shipped_dir
from gearbench.profile.shipped import shipped_profiles


@pytest.fixture
def station(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["init", "st"]) == 0
    return tmp_path / "st"


def test_init_makes_a_station_from_the_shipped_files(station, capsys):
    for kind in ("profiles", "drivers"):
        shipped = sorted(p.name for p in shipped_dir(kind).iterdir() if p.is_file())
        assert shipped and sorted(p.name for p in (station / kind).iterdir()) == shipped
    readme = (station / "README.md").read_text()
    assert "What to edit" in readme and "drivers/" in readme
    # again: an edited file is kept, never overwritten
    (station / "profiles" / "cvt.yaml").write_text("# mine\n")
    assert main(["init", str(station)]) == 0
    assert (station / "profiles" / "cvt.yaml").read_text() == "# mine\n"
    assert "existing files kept" in capsys.readouterr().out


def test_init_onto_a_file_is_one_line_exit_2(tmp_path):
    (tmp_path / "f").write_text("x")
    p = subprocess.run([sys.executable, "-m", "gearbench", "init", str(tmp_path / "f")],
                       capture_output=True, text=True)
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1 and "not a folder" in p.stderr


def test_profile_by_name_station_first_then_shipped(station, monkeypatch):
    assert "cvt" in shipped_profiles()
    monkeypatch.chdir(station)
    assert load_profile("cvt").path.resolve() == (station / "profiles" / "cvt.yaml").resolve()
    monkeypatch.chdir(station.parent)            # no profiles/ here: the shipped example
    assert load_profile("cvt").path.resolve() == (shipped_dir("profiles") / "cvt.yaml").resolve()


def test_drive_lookup_order(station, tmp_path, monkeypatch):
    eds = "cia402-servo.eds"
    monkeypatch.chdir(tmp_path)                  # not the station: found through the profile's place
    prof = station / "profiles" / "motors-only.yaml"
    assert Path(load_profile(prof).motors["in"].drive) == (station / "drivers" / eds).resolve()
    # a copy beside the profile wins over the station's
    (station / "profiles" / "drivers").mkdir()
    shutil.copy2(station / "drivers" / eds, station / "profiles" / "drivers" / eds)
    assert Path(load_profile(prof).motors["in"].drive) == (station / "profiles" / "drivers" / eds).resolve()
    # neither: the shipped description
    shutil.rmtree(station / "profiles" / "drivers")
    (station / "drivers" / eds).unlink()
    assert Path(load_profile(prof).motors["in"].drive) == (shipped_dir("drivers") / eds).resolve()


def test_missing_drive_names_every_place_looked(station, monkeypatch):
    monkeypatch.chdir(station)
    prof = station / "profiles" / "motors-only.yaml"
    prof.write_text(prof.read_text().replace("drivers/cia402-servo.eds", "drivers/nope.eds"))
    p = subprocess.run([sys.executable, "-m", "gearbench", "validate", str(prof)], capture_output=True,
                       text=True, cwd=station)
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1
    assert "nope.eds" in p.stderr and str(shipped_dir("drivers")) in p.stderr
