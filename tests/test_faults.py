"""Fault campaign, fast subset: the harness of ``python -m gearbench.benchmarks faults`` on a
handful of runs, so a regression of a bench-fault invariant shows in CI.

Each run is a real ``gearbench run --sim`` subprocess with its emulator child; the
fault is injected at a random (seeded) instant; ``gearbench.emulate.faults`` checks
the invariants (exit code, drives without torque and the time it took, samples kept
and readable, counter gaps == lost, result.json/junit.xml/station database, no
process left). Runs go two at a time to stay within the time budget.
"""
from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor

import pytest

from gearbench.emulate.bench import EmulatedBench
from gearbench.emulate.faults import FAULTS, INVARIANTS, matrix, run_fault

# one of each way a run can end: a drive gone silent (named, others stopped), a drive that
# will not disable (named, no further segment), gearbench killed (emulator ends by itself,
# samples readable through read_partial), the trace folder vanishing (a required output
# failed: fault, never a pass); the full set is the campaign
SUBSET = ["drive-silent", "refuse-disable", "sigkill-gearbench", "vanished-dir"]


@pytest.fixture(scope="module")
def outcomes(tmp_path_factory):
    work = tmp_path_factory.mktemp("faults")
    with ThreadPoolExecutor(2) as ex:
        outs = list(ex.map(lambda n: run_fault(n, 1, work), SUBSET))
    print("\n" + matrix(outs))
    return {o.fault: o for o in outs}


@pytest.mark.parametrize("name", SUBSET)
def test_fault_keeps_every_invariant(outcomes, name):
    o = outcomes[name]
    assert set(o.invariants) == set(INVARIANTS)
    assert o.ok, f"{name} at world time {o.at_s} s: " + "; ".join(o.failures())


def test_silent_drive_is_named_not_claimed_stopped(outcomes):
    o = outcomes["drive-silent"]
    assert o.rc == 3
    assert "did NOT reach" in o.figures["reason"] and "silent" in o.figures["reason"]


def test_killed_gearbench_leaves_readable_samples_and_no_emulator(outcomes):
    o = outcomes["sigkill-gearbench"]
    assert o.rc == -9
    assert o.figures["samples_on_disk"] > 0
    assert o.invariants["no_process_left"][0] is True


def test_harness_sees_a_violation(outcomes):
    """The checks can fail: the silent-drive run judged as if a pass had been expected."""
    from copy import deepcopy
    from dataclasses import replace

    from gearbench.emulate.faults import check_run

    o = deepcopy(outcomes["drive-silent"])
    check_run(o, replace(FAULTS["drive-silent"], expect_exit=0, expect_status="passed", reason=""))
    assert o.invariants["exit_code"][0] is False
    assert o.invariants["records_consistent"][0] is False
    assert o.invariants["samples_kept"][0] is True     # what is on disk is still all there


def test_fault_plan_applies_at_world_time_and_journals():
    """Emulator side: a planned command waits for its world time; state changes are journalled."""
    import io

    bench = EmulatedBench(seed=0)
    bench.journal = io.StringIO()
    assert json.loads(bench.handle_control_line(json.dumps(
        {"cmd": "refuse_disable", "axis": "out", "on": True, "at_s": 0.003})))["ok"]
    axis = bench.drives["out"]
    for cw in (0x06, 0x07, 0x0F):
        axis.write_controlword(cw)
    assert axis.state == "OPERATION ENABLED"
    bench.advance(2)
    axis.write_controlword(0x00)
    assert axis.state == "SWITCH ON DISABLED"        # not yet refusing at 2 ms
    for cw in (0x06, 0x07, 0x0F):
        axis.write_controlword(cw)
    bench.advance(2)
    axis.write_controlword(0x00)
    assert axis.state == "OPERATION ENABLED"         # refusing from 3 ms on
    events = [json.loads(ln) for ln in bench.journal.getvalue().splitlines()]
    # applied before the step that reaches 3 ms, i.e. at the end of the 2nd (journal time 2 ms)
    assert [e["t_s"] for e in events if e["event"] == "command"] == [0.002]
    assert any(e["event"] == "state" and e["new"] == "SWITCH ON DISABLED" for e in events)
    bad = json.loads(bench.handle_control_line(json.dumps({"cmd": "heartbeat", "axis": "x", "at_s": 1})))
    assert not bad["ok"] and "axis" in bad["error"]   # refused when planned, not at its time


def test_every_fault_has_a_plan_and_an_expectation():
    for f in FAULTS.values():
        assert f.bus in ("canopen", "modbus") and f.expect_exit in (0, 3, -9), f
        assert (f.expect_status is None) == (f.expect_exit == -9), f
