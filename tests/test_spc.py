"""SPC: individuals/MR charts and the Western Electric / Nelson rules on known series."""
import numpy as np
import pytest

from gearbench.analysis.spc import individuals_chart, run_rules
from gearbench.errors import GearbenchError

BASE = [0.3, -0.2, 0.1, -0.4, 0.2, -0.1, 0.4, -0.3, 0.0, -0.1]     # in control, alternating


def test_each_rule_fires_on_its_pattern_and_only_there():
    assert run_rules(np.array(BASE)) == {}
    assert run_rules(np.array(BASE + [3.5]))[10] == ["1"]
    assert run_rules(np.array(BASE + [2.5, 0.1, 2.4]))[12] == ["2"]
    assert run_rules(np.array(BASE + [1.5, 1.2, 0.2, 1.4, 1.6]))[14] == ["3"]
    assert run_rules(np.array(BASE + [0.5, 0.4, 0.6, 0.3, 0.5, 0.4, 0.6, 0.5])) == {17: ["4"]}
    assert run_rules(np.array(BASE + [-0.5, -0.3, -0.1, 0.1, 0.3, 0.5])) == {15: ["5"]}
    assert run_rules(np.array(BASE + [0.5]), np.r_[np.nan, np.full(10, 0.5)], 0.4)[10] == ["MR"]


def test_chart_limits_from_the_baseline():
    x = np.array([10.0, 10.2, 9.9, 10.1, 9.8, 10.0, 10.3, 9.9, 10.1, 10.0])
    c = individuals_chart(x, quantity="q", baseline=10)
    mrbar = np.mean(np.abs(np.diff(x)))
    assert c.center == pytest.approx(x.mean()) and c.sigma == pytest.approx(mrbar / 1.128)
    assert c.ucl == pytest.approx(x.mean() + 3 * mrbar / 1.128) and c.mr_ucl == pytest.approx(3.267 * mrbar)
    assert c.in_control
    assert individuals_chart(np.r_[x, 12.0], baseline=10, rules=("MR",)).flags == {10: ["MR"]}


def test_false_alarm_rates_match_theory():
    """In-control normal data, 50-run baseline: per-point rates near the textbook values
    (estimated limits add some), so the rules are what they claim to be."""
    counts, n = {}, 0
    for seed in range(200):
        x = np.random.default_rng(seed).standard_normal(150)
        for i, rules in individuals_chart(x, baseline=50).flags.items():
            if i >= 50:
                for r in rules:
                    counts[r] = counts.get(r, 0) + 1
        n += 100
    rate = {r: c / n for r, c in counts.items()}
    theory = {"1": 0.0027, "2": 0.0021, "3": 0.0045, "4": 0.0078, "5": 0.0028, "MR": 0.0092}
    for r, p in theory.items():
        assert 0.3 * p < rate.get(r, 0) < 3 * p, (r, rate)
    assert sum(rate.values()) < 0.06


def test_a_slowly_drifting_motor_is_flagged_within_a_few_runs():
    """Kt loses 0.04 %/run from run 50 (noise 0.08 %): flagged in every case, soon."""
    delays = []
    for seed in range(100):
        kt = 0.0527 * (1 + 0.0008 * np.random.default_rng(seed).standard_normal(80))
        kt[50:] *= 1 - 0.0004 * np.arange(1, 31)
        c = individuals_chart(kt, quantity="motors.in.Kt", baseline=50)
        late = [i for i in c.flags if i >= 50]
        delays.append(min(late) - 50 if late else 99)
    assert max(delays) <= 15 and np.median(delays) <= 6


def test_too_few_runs_is_a_clear_error():
    with pytest.raises(GearbenchError, match="at least 5 runs"):
        individuals_chart([1.0, 2.0, 3.0], quantity="motors.in.Kt")
    with pytest.raises(GearbenchError, match="unknown"):
        individuals_chart(BASE, rules=("7",))
