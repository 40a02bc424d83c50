"""A drive family added from outside gearbench is found through the ``gearbench.drives``
entry point and used by a profile (issue 7, item 3).

The plugin (tests/plugin_example/gearbench_loopback) is "installed" without pip: a
``.dist-info`` folder with ``entry_points.txt`` on a temporary sys.path entry, which
is exactly what importlib.metadata reads for an installed distribution.
"""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from conftest import assert_claimed_accuracy

from gearbench.api import AutoOperator, RunResult, open_bench, run_profile
from gearbench.drives import registry
from gearbench.errors import ProfileError
from gearbench.profile import load_profile

ROOT = Path(__file__).resolve().parents[1]
PLUGIN_SRC = Path(__file__).resolve().parent / "plugin_example"
PLANT = {"seed": 3, "motors": {"in": {"Kt": 0.0527, "J": 1.5e-5, "rated_current_a": 1.5, "current_limit_a": 3.0},
                               "out": {"Kt": 0.0512, "J": 1.45e-5, "Tc": 0.009, "rated_current_a": 1.5,
                                       "current_limit_a": 3.0}}}


def write_profile(path: Path, *, kt_high: float = 1.15) -> Path:
    doc = yaml.safe_load((ROOT / "profiles" / "motors-only.yaml").read_text())
    doc.pop("simulation")
    doc["bench"]["bus"] = {"family": "loopback", "options": {"plant": PLANT, "seed": 3}}
    for m in doc["motors"].values():
        m["drive"] = str(ROOT / "drivers" / "cia402-servo.eds")
    doc["limits"][0]["high"] = kt_high
    path.write_text(yaml.safe_dump(doc))
    return path


@pytest.fixture
def loopback_installed(tmp_path, monkeypatch):
    site = tmp_path / "site"
    info = site / "gearbench_loopback-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: gearbench-loopback\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(
        '[gearbench.drives]\nloopback = gearbench_loopback:LoopbackNetwork\n')
    monkeypatch.syspath_prepend(str(site))
    monkeypatch.syspath_prepend(str(PLUGIN_SRC))
    # the profile parser caches the family list per process (gearbench.profile.parse)
    yield site


def test_unknown_family_without_the_plugin(tmp_path):
    assert "loopback" not in registry.available()
    with pytest.raises(ProfileError, match="loopback"):
        load_profile(write_profile(tmp_path / "p.yaml"))


def test_plugin_family_is_found(loopback_installed, tmp_path):
    assert registry.available()["loopback"] == "gearbench_loopback:LoopbackNetwork"
    cls = registry.network_class("loopback")
    assert cls.__module__ == "gearbench_loopback" and cls.family == "loopback"
    assert load_profile(write_profile(tmp_path / "p.yaml")).bench.bus.family == "loopback"


def test_profile_runs_through_the_plugin(loopback_installed, tmp_path):
    profile = write_profile(tmp_path / "p.yaml")
    with open_bench(profile, out_dir=tmp_path / "run", serial="PLUG-1", operator=AutoOperator()) as bench:
        assert type(bench.network).__module__ == "gearbench_loopback"
        kt_in = bench.calibrate("in")
        kt_out = bench.calibrate("out")
        result = bench.finish()
    # the plugin's simulated plant answered: Kt identified from its drives' data
    assert result.passed and result.status == "passed"
    on_disk = json.loads((tmp_path / "run" / "result.json").read_text())
    # result.json holds 12 significant digits (float noise rounded)
    assert RunResult.from_dict(on_disk).motors["in"].kt_nm_per_a == pytest.approx(kt_in.kt_nm_per_a, rel=1e-11)
    assert on_disk["motors"]["out"]["Kt"] == pytest.approx(kt_out.kt_nm_per_a, rel=1e-11)
    assert_claimed_accuracy(on_disk, PLANT)       # against the plugin plant's own Kt
    # the profile's disk (±0.5 % measured, u = 0.25 %) is in Kt's stored uncertainty
    for m in ("in", "out"):
        got = on_disk["motors"][m]
        assert got["fit"]["Kt_std_disk"] == pytest.approx(got["Kt"] * 0.0025, rel=1e-9)
        assert got["Kt_std"] >= got["fit"]["Kt_std_disk"] and got["Kt_dof"] >= 1
        assert got["fit"]["disk"] == "disk_a"       # both motors share it: efficiency knows


def test_plugin_run_fails_an_impossible_limit(loopback_installed, tmp_path):
    profile = write_profile(tmp_path / "p.yaml", kt_high=0.9)   # Kt/datasheet is ~1.0
    result = run_profile(profile, out_dir=tmp_path / "run", serial="PLUG-2", yes=True)
    assert result["status"] == "failed" and result["exit_code"] == 1
    assert [lim["name"] for lim in result["limits"] if not lim["passed"]] == ["kt_in"]
