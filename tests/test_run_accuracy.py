"""The main job's accuracy on the simulated bench (issue 4 item 6): one full
`gearbench run profiles/cvt.yaml --sim` through the real CANopen stack, checked
against the simulated plant's ``simulation_truth``.

Targets (the README's claims, ``gearbench.benchmarks.robustness.TARGETS``): Kt within 0.2 %,
every incremental efficiency within 0.2 pp, every absolute efficiency within 0.3 pp,
ratio within 0.1 %, an efficiency map of at least 3 speeds x 4 torques, ≤ 60 s wall.
The truth is the plant's at the commanded operating points, never at a measured value.
"""
import time
from pathlib import Path

import pytest

from gearbench.api import run_profile
from gearbench.benchmarks.robustness import TARGETS
from gearbench.sim.truth import simulation_truth

from _host_speed import slower_than_reference

PROFILE = Path(__file__).resolve().parents[1] / "profiles" / "cvt.yaml"


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("cvt-sim")
    cpu0 = time.process_time() + _children_cpu_s()
    result = run_profile(str(PROFILE), sim=True, out_dir=out / "run", serial="T1", yes=True,
                         db=out / "station.sqlite")
    return result, time.process_time() + _children_cpu_s() - cpu0


def _children_cpu_s() -> float:
    import resource
    r = resource.getrusage(resource.RUSAGE_CHILDREN)   # the emulator child, once it has exited
    return r.ru_utime + r.ru_stime


def test_run_costs_less_cpu_than_real_time(run):
    """The simulated run (master + emulator) costs less CPU than twice its bench time, i.e.
    it runs faster than real time on each of two cores. CPU seconds, not wall time: a busy
    CI neighbour slows the wall clock, not the cost (~25 CPU s quiet, ~75 s on a loaded host)."""
    result, cpu_s = run
    assert result["status"] == "passed", result.get("reason")
    # on a host slower than the one the bound was set on, in proportion (``_host_speed``:
    # the interpreter loop 0.16 s and 34-36 CPU s for 16 s of bench time on the AMD EPYC VM)
    slower = slower_than_reference()
    assert cpu_s <= 2 * slower * result["bench_time_s"], \
        f"{cpu_s:.0f} CPU s for {result['bench_time_s']:.0f} s of bench time (host {slower:.2f}x slower)"


def test_torque_constants_within_0p2_percent(run):
    result, _ = run
    truth = result["simulation_truth"]["motors"]
    for motor in ("in", "out"):
        err = result["motors"][motor]["Kt"] / truth[motor]["Kt"] - 1
        assert abs(err) <= TARGETS["kt_pct"] / 100, f"motor {motor}: Kt error {100 * err:+.3f} %"


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
    bad = [e for e in errors if abs(e[2]) > TARGETS["inc_pp"]]
    assert not bad, "incremental efficiency off by more than 0.2 pp at " + ", ".join(
        f"{w:.0f} rad/s {tq:.3f} N m: {e:+.3f} pp" for w, tq, e in bad)


def test_every_absolute_efficiency_within_0p3_pp(run):
    result, _ = run
    points, truth = result["efficiency"], result["simulation_truth"]["efficiency"]
    assert len(points) == len(truth) >= 12
    errors = [(p["in_command"], p["out_command"], 100 * (p["eta_absolute"] - t["eta_absolute"]))
              for p, t in zip(points, truth)]
    bad = [e for e in errors if abs(e[2]) > TARGETS["abs_pp"]]
    assert not bad, "absolute efficiency off by more than 0.3 pp at " + ", ".join(
        f"{w:.0f} rad/s {i:.3f} A: {e:+.3f} pp" for w, i, e in bad)


def test_truth_is_at_the_commanded_point_whatever_was_estimated(run):
    """The truth depends on the commands only: changing every measured or estimated field
    of a point leaves it unchanged (it used to follow the measured output torque)."""
    result, _ = run
    plant = PROFILE_PLANT()
    point = dict(result["efficiency"][-1])
    honest = simulation_truth(plant, [point])["efficiency"][0]
    assert honest == result["simulation_truth"]["efficiency"][-1]
    skewed = {**point, **{k: v * 1.1 for k, v in point.items()
                          if isinstance(v, float) and k not in ("in_command", "out_command")}}
    assert simulation_truth(plant, [skewed])["efficiency"][0] == honest
    assert honest["speed_in_rad_s"] == point["speed_setpoint_rad_s"] == point["in_command"]


def PROFILE_PLANT() -> dict:
    import yaml

    return yaml.safe_load(PROFILE.read_text())["simulation"]
