"""The main job's accuracy on the simulated bench (issue 4 item 6): one full
`gearbench run profiles/cvt.yaml --sim` through the real CANopen stack, checked
against the simulated plant's ``simulation_truth``.

Targets: Kt within 0.2 %, every incremental efficiency within 0.2 pp, ratio within
0.1 %, an efficiency map of at least 3 speeds x 4 torques, ≤ 60 s wall.
"""
import time
from pathlib import Path

import pytest

from gearbench.api import run_profile

PROFILE = Path(__file__).resolve().parents[1] / "profiles" / "cvt.yaml"
WALL_LIMIT_S = 60.0


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("cvt-sim")
    t0 = time.monotonic()
    result = run_profile(str(PROFILE), sim=True, out_dir=out / "run", serial="T1", yes=True,
                         db=out / "station.sqlite")
    return result, time.monotonic() - t0


def test_run_completes_within_the_wall_time_budget(run):
    result, wall_s = run
    assert result["status"] == "passed", result.get("reason")
    assert wall_s <= WALL_LIMIT_S


def test_torque_constants_within_0p2_percent(run):
    result, _ = run
    truth = result["simulation_truth"]["motors"]
    for motor in ("in", "out"):
        err = result["motors"][motor]["Kt"] / truth[motor]["Kt"] - 1
        assert abs(err) <= 0.002, f"motor {motor}: Kt error {100 * err:+.3f} %"


def test_ratio_within_0p1_percent(run):
    result, _ = run
    assert result["ratio"] == pytest.approx(result["simulation_truth"]["ratio"], rel=1e-3)


def test_every_incremental_efficiency_within_0p2_pp(run):
    result, _ = run
    points, truth = result["efficiency"], result["simulation_truth"]["efficiency"]
    speeds = {round(p["speed_in_rad_s"]) for p in points}
    assert len(points) >= 12 and len(speeds) >= 3 and len(points) == len(truth)
    errors = [(p["speed_in_rad_s"], p["torque_out_nm"],
               100 * (p["eta_incremental"] - t["eta_incremental"])) for p, t in zip(points, truth)]
    bad = [e for e in errors if abs(e[2]) > 0.2]
    assert not bad, "incremental efficiency off by more than 0.2 pp at " + ", ".join(
        f"{w:.0f} rad/s {tq:.3f} N m: {e:+.3f} pp" for w, tq, e in bad)
