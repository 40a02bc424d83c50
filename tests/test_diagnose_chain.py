"""Issue 13: the diagnosis chain's output, and the reducer-bench diagnosis."""
from __future__ import annotations

import json

import numpy as np
import pytest

from gearbench.bench._data import DEV_DIR
from gearbench.cli import main
from gearbench.trace import Trace

pytest.importorskip("gearbench.sim")
from gearbench.analysis.diagnose.bench import bench_case_trace, diagnose_bench  # noqa: E402


@pytest.mark.parametrize("effect", [None, "torsional_compliance", "ratio_ripple"])
def test_bench_effects_are_named_and_clean_bench_is_quiet(effect):
    d = diagnose_bench(bench_case_trace(effect, seed=1))
    chain = [c["effect"] for c in d.chain]
    if effect is None:
        assert chain == []
    else:
        assert chain[0] == effect
        assert d.chain[0]["shrink_heldout"] > 0.8
        assert d.remaining["kinematics"]["at_noise_floor"]


def test_bench_units_do_not_matter():
    """The bench relations are linear in the angles: degrees give the same chain."""
    tr = bench_case_trace("torsional_compliance", seed=0)
    k = 180 / np.pi
    deg = Trace(tr.time_s, {**{c: tr[c] for c in tr.names},
                            "in_position_rad": tr["in_position_rad"] * k,
                            "out_position_rad": tr["out_position_rad"] * k}, {})
    a, b = diagnose_bench(tr), diagnose_bench(deg)
    assert [c["effect"] for c in a.chain] == [c["effect"] for c in b.chain]
    assert a.chain[0]["shrink_heldout"] == pytest.approx(b.chain[0]["shrink_heldout"], abs=1e-6)


def test_cli_bench_json_and_missing_trace(capsys):
    f = DEV_DIR / "bench_motor_a_in_motor_b_out.csv"
    if not f.exists():
        pytest.skip("dev data not present (../shared/datasets/dev)")
    assert main(["diagnose", "--bench", str(f), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert {"nominal", "chain", "remaining", "verdict", "candidates"} <= set(d)
    assert abs(d["nominal"]["noise"]["ratio_estimate"] - 7.0) < 1e-3   # truth: n = 7
    assert main(["diagnose"]) == 2
    assert "give a TRACE" in capsys.readouterr().err


def test_chain_output_is_consistent_with_the_verdict():
    f = DEV_DIR / "diag_a.csv"
    if not f.exists():
        pytest.skip("dev data not present (../shared/datasets/dev)")
    from gearbench.analysis.diagnose import diagnose

    d = diagnose(Trace.read(f)).as_dict()
    assert d["chain"][0]["effect"] == d["verdict"]["effect"] == "coulomb_friction"
    for c in d["chain"]:
        assert {"effect", "params", "shrink_heldout", "cumulative_shrink", "significant"} <= set(c)
        assert c["significant"]
    # an effect judged untestable never wins, anywhere in the chain
    untestable = {c["effect"] for c in d["candidates"] if c["testable"] is False}
    assert not untestable & {c["effect"] for c in d["chain"]}
    rem = d["remaining"]
    assert 0 <= rem["share_of_gap"] <= 1 and rem["stopped"] in (
        "noise_floor", "no_significant_candidate", "max_steps")
    assert rem["share_of_gap"] == pytest.approx(1 - d["chain"][-1]["cumulative_shrink"], abs=1e-9)
