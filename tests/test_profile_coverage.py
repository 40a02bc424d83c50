"""Issue 23, deliverable 6: calibrations cover the efficiency map's speeds."""
from pathlib import Path

import pytest

from gearbench.profile import load_profile
from gearbench.profile.coverage import calibration_speed_range, map_speed_range, uncovered

PROFILES = sorted((Path(__file__).resolve().parents[1] / "profiles").glob("*.yaml"))


@pytest.mark.parametrize("path", PROFILES, ids=lambda p: p.name)
def test_shipped_profiles_extrapolate_no_motor_loss(path):
    assert uncovered(load_profile(path)) == []


def test_a_calibration_short_of_the_map_is_named(tmp_path):
    src = (PROFILES[0].parent / "cvt.yaml").read_text()
    src = src.replace("offset: 200", "offset: 150").replace("amplitude: 120", "amplitude: 80")
    p = tmp_path / "short.yaml"
    p.write_text(src.replace("drivers/", str(PROFILES[0].parents[1] / "drivers") + "/"))
    prof = load_profile(p)
    lo, hi = calibration_speed_range(prof, "in")
    assert hi < 300
    msgs = uncovered(prof)
    assert len(msgs) == 1 and "input 300 rad/s" in msgs[0] and "motor in" in msgs[0]


def test_map_speeds_per_motor():
    prof = load_profile(PROFILES[0].parent / "cvt.yaml")
    assert map_speed_range(prof, "in") == (100.0, 300.0)
    lo, hi = map_speed_range(prof, "out")          # over the ratio limit 8 +/- 2 %
    assert lo == pytest.approx(100.0 / 8.16) and hi == pytest.approx(300.0 / 7.84)


def test_a_designed_calibration_covers_the_map(tmp_path):
    """design: optimal sweeps the map's input speeds (here a map up to 360 rad/s, above
    what the hand-written cvt multisine reaches)."""
    src = (PROFILES[0].parent / "cvt.yaml").read_text()
    hand = src[src.index("    kind: multisine"):src.index("    fade_in_s: 0.2")]
    src = src.replace(hand, "    kind: multisine\n    design: optimal\n")
    src = src.replace("speeds_in_rad_s: [100, 200, 300]", "speeds_in_rad_s: [100, 200, 360]")
    p = tmp_path / "designed.yaml"
    p.write_text(src.replace("drivers/", str(PROFILES[0].parents[1] / "drivers") + "/"))
    prof = load_profile(p)
    assert prof.waveforms["excite"].params["design"] == "optimal"
    lo, hi = calibration_speed_range(prof, "in")
    assert hi >= 360.0
    assert uncovered(prof) == []
