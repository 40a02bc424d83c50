"""gearbench msa: gauge R&R numerics against AIAG's published example, the study from
station databases written by the real writer, bad input, and one simulated study (slow).

The published example is the crossed study of AIAG, *Measurement Systems Analysis*,
Reference Manual, 4th ed. (2010): 10 parts × 3 appraisers (A, B, C) × 3 trials, the data
of its gauge R&R data sheet (Fig. III-B 16 / Appendix A). Published answers:
- ANOVA (Tables III-B 7/8, A 4/A 5): SS appraiser 3.1673, parts 88.3619, interaction
  0.3590, equipment 2.7589, total 94.6471; interaction F = 0.434 (not significant, pooled);
  EV 0.199933, AV 0.226838, INT 0, GRR 0.302373, PV 1.042327, TV 1.085; %EV 18.4, %AV 20.9,
  %GRR 27.9, %PV 96.0; ndc 4.
- Average and range (Fig. III-B 17): EV 0.20188, AV 0.22963, GRR 0.30575, PV 1.10456,
  TV 1.14610, %GRR 26.68, ndc 5.
The data and these figures are reproduced in many public places, e.g. the
gagerandr.com data-sheet pages (K1 = 0.5908, K2 = 0.5231, K3 = 0.3146 for this design).
"""
from __future__ import annotations

import json
import math
import os
import shutil
import sqlite3

import numpy as np
import pytest
from scipy import stats

from gearbench.analysis.msa import (anova_gauge_rr, crossed_array, grr_verdict, range_gauge_rr,
                                    type1_study)
from gearbench.cli import main
from gearbench.errors import GearbenchError
from gearbench.station.database import connect, store_run

AIAG = {   # appraiser: part -> 3 trials (AIAG MSA 4th ed. gauge R&R data sheet)
    "A": [[0.29, 0.41, 0.64], [-0.56, -0.68, -0.58], [1.34, 1.17, 1.27], [0.47, 0.50, 0.64],
          [-0.80, -0.92, -0.84], [0.02, -0.11, -0.21], [0.59, 0.75, 0.66], [-0.31, -0.20, -0.17],
          [2.26, 1.99, 2.01], [-1.36, -1.25, -1.31]],
    "B": [[0.08, 0.25, 0.07], [-0.47, -1.22, -0.68], [1.19, 0.94, 1.34], [0.01, 1.03, 0.20],
          [-0.56, -1.20, -1.28], [-0.20, 0.22, 0.06], [0.47, 0.55, 0.83], [-0.63, 0.08, -0.34],
          [1.80, 2.12, 2.19], [-1.68, -1.62, -1.50]],
    "C": [[0.04, -0.11, -0.15], [-1.38, -1.13, -0.96], [0.88, 1.09, 0.67], [0.14, 0.20, 0.11],
          [-1.46, -1.07, -1.45], [-0.29, -0.67, -0.49], [0.02, 0.01, 0.21], [-0.46, -0.56, -0.49],
          [1.77, 1.45, 1.87], [-1.49, -1.77, -2.16]],
}


def aiag_array() -> np.ndarray:
    return np.array([[AIAG[a][p] for a in "ABC"] for p in range(10)])


def test_anova_reproduces_aiag_published_example():
    g = anova_gauge_rr(aiag_array())
    ss = {row.source.split(" ")[0]: row.ss for row in g.anova}
    for source, published in (("station", 3.1673), ("part", 88.3619), ("part×station", 0.3590),
                              ("total", 94.6471)):
        assert ss[source] == pytest.approx(published, abs=5e-5), source
    inter = next(r for r in g.anova if r.source == "part×station")
    assert inter.f == pytest.approx(0.434, abs=5e-4)
    assert g.interaction_pooled and g.interaction == 0.0
    # equipment SS = pooled SS − interaction SS
    assert ss["repeatability"] - ss["part×station"] == pytest.approx(2.7589, abs=5e-5)
    for got, published in ((g.ev, 0.199933), (g.av, 0.226838), (g.grr, 0.302373), (g.pv, 1.042327)):
        assert got == pytest.approx(published, abs=5e-6)
    assert g.tv == pytest.approx(1.085, abs=5e-4)
    for got, published in ((g.pct_ev, 18.4), (g.pct_av, 20.9), (g.pct_grr, 27.9), (g.pct_pv, 96.0)):
        assert got == pytest.approx(published, abs=0.05)
    assert g.ndc == 4
    assert g.verdict == "marginal"                      # 27.9 %: AIAG's "may be acceptable"


def test_range_method_reproduces_aiag_published_example():
    g = range_gauge_rr(aiag_array())
    # AIAG rounds R̿ and X̄diff before multiplying: agreement to its printed digits
    for got, published in ((g.ev, 0.20188), (g.av, 0.22963), (g.grr, 0.30575), (g.pv, 1.10456),
                           (g.tv, 1.14610)):
        assert got == pytest.approx(published, abs=1e-4)
    assert g.pct_grr == pytest.approx(26.68, abs=0.02)
    assert g.ndc == 5


def test_interaction_kept_when_significant_and_ev_is_the_within_cell_variance():
    rng = np.random.default_rng(5)
    n, k, r = 10, 3, 3
    x = (rng.normal(0, 1.0, n)[:, None, None] + rng.normal(0, 0.2, k)[None, :, None]
         + rng.normal(0, 1.5, (n, k))[:, :, None] + rng.normal(0, 0.1, (n, k, r)))
    g = anova_gauge_rr(x)
    assert g.interaction_p < 0.05 and not g.interaction_pooled
    assert g.interaction > 0.5
    # unpooled EV² is MS_E = mean of the cells' sample variances (numpy, independently)
    assert g.ev ** 2 == pytest.approx(x.var(axis=2, ddof=1).mean(), rel=1e-12)
    assert g.grr ** 2 == pytest.approx(g.ev ** 2 + g.av ** 2 + g.interaction ** 2, rel=1e-12)
    assert g.tv ** 2 == pytest.approx(g.grr ** 2 + g.pv ** 2, rel=1e-12)
    # forcing the interaction in (alpha = 1) on AIAG's data gives the unpooled MS_E
    x = aiag_array()
    assert anova_gauge_rr(x, alpha=1.0).ev ** 2 == pytest.approx(x.var(axis=2, ddof=1).mean())


def test_one_station_is_a_repeatability_study():
    x = aiag_array()[:, :1, :]
    g = anova_gauge_rr(x)
    assert g.av == 0 and g.interaction == 0
    assert g.ev ** 2 == pytest.approx(x.var(axis=2, ddof=1).mean())
    assert any("one station" in n for n in g.notes)


def test_tolerance_gives_percent_of_tolerance_and_verdicts():
    g = anova_gauge_rr(aiag_array(), tolerance=5.0)
    assert g.pct_tolerance == pytest.approx(100 * 6 * 0.302373 / 5.0, abs=1e-3)
    assert grr_verdict(5.0, None, 12) == "acceptable"
    assert grr_verdict(5.0, 12.0, 12) == "marginal"        # the larger of %GRR and %P/T decides
    assert grr_verdict(5.0, 31.0, 12) == "unacceptable"
    assert grr_verdict(5.0, None, 3) == "marginal"          # ndc < 5
    assert anova_gauge_rr(aiag_array()).pct_tolerance is None


def test_type1_bias_t_test_and_cg():
    v = [1.002, 0.998, 1.004, 1.001, 0.999, 1.003, 1.000, 1.002]
    t = type1_study(v, reference=1.0, tolerance=0.1)
    s = np.std(v, ddof=1)
    ref = stats.ttest_1samp(v, 1.0)
    assert t.bias_t == pytest.approx(ref.statistic) and t.bias_p == pytest.approx(ref.pvalue)
    assert t.cg == pytest.approx(0.2 * 0.1 / (6 * s))
    assert t.cgk == pytest.approx((0.1 * 0.1 - abs(np.mean(v) - 1.0)) / (3 * s))
    assert t.bias_significant == (ref.pvalue < 0.05)
    no_ref = type1_study(v)
    assert no_ref.bias is None and no_ref.cg is None and "no tolerance" in no_ref.verdict


@pytest.mark.parametrize("records, match", [
    ([("P1", "A", 1.0), ("P1", "A", 1.1), ("P2", "A", 2.0)], r"part P2 at A has 1 trial"),
    ([("P1", "A", 1.0), ("P2", "A", 2.0)], r"1 trial per part"),
    ([("P1", "A", 1.0), ("P1", "A", 1.1)], r"at least 2 parts"),
    ([("P1", "A", 1.0), ("P1", "A", float("nan")), ("P2", "A", 2.0), ("P2", "A", 2.0)], r"non-finite"),
    ([("P1", "A", 1.0), ("P1", "A", 1.0), ("P1", "B", 1.0), ("P1", "B", 1.0), ("P2", "A", 1.0),
      ("P2", "A", 1.0)], r"part P2 at B has 0 trial"),
])
def test_degenerate_designs_are_named(records, match):
    with pytest.raises(GearbenchError, match=match):
        crossed_array(records)


def test_zero_variance_is_refused():
    with pytest.raises(GearbenchError, match="identical"):
        anova_gauge_rr(np.ones((3, 2, 2)))
    with pytest.raises(GearbenchError, match="identical"):
        type1_study([0.05, 0.05, 0.05])


# ------------------------------------------------------ from station databases
TRUE_ETA = 0.72


def _result(serial, station, trial, eta, kt_in, n, when, status="passed"):
    """A result as the sequencer writes it (the keys gearbench msa reads)."""
    pts = [dict(speed_setpoint_rad_s=100.0 * (i + 1), speed_in_rad_s=100.0 * (i + 1),
                torque_out_nm=0.08, eta_incremental=e, eta_absolute=e - 0.1) for i, e in enumerate(eta)]
    limits = [dict(name="kt_in", quantity="motors.in.Kt_rel_datasheet", value=kt_in / 0.0527,
                   low=0.85, high=1.15, passed=True)]
    limits += [dict(name=f"efficiency[{i}]", quantity="efficiency.eta_incremental", value=e,
                    low=0.55, high=0.85, passed=True) for i, e in enumerate(eta)]
    return dict(serial=serial, run_id=f"{station}-{serial}-{trial}-{n}", profile="synthetic",
                started_utc=f"2026-11-29T{8 + n // 60:02d}:{n % 60:02d}:00.000+00:00",
                finished_utc=when, status=status, passed=status == "passed",
                exit_code=0 if status == "passed" else 3, motors={"in": {"Kt": kt_in}},
                efficiency=pts, limits=limits, out_dir="",
                simulation_truth={"motors": {"in": {"Kt": 0.0527}},
                                  "efficiency": [dict(eta_incremental=TRUE_ETA, eta_absolute=TRUE_ETA - 0.1)
                                                 for _ in eta]})


def _station_db(path, station):
    con = connect(path)
    with con:
        con.execute("INSERT OR REPLACE INTO meta VALUES ('station', ?)", (station,))
    con.close()


@pytest.fixture(scope="module")
def study_dbs(tmp_path_factory):
    """10 units × 2 stations × 3 trials; known part spread 1 pp, station offset 0.2 pp,
    repeatability 0.05 pp, written with the real station-database writer."""
    tmp_path = tmp_path_factory.mktemp("msa-dbs")
    rng = np.random.default_rng(3)
    parts = TRUE_ETA + rng.normal(0, 0.01, 10)
    dbs, n = [], 0
    for s, offset in ((1, 0.0), (2, 0.002)):
        db = tmp_path / f"station-{s}" / "station.sqlite"
        _station_db(db, f"line-{s}")
        dbs.append(db)
    for trial in range(3):
        for s, offset in ((1, 0.0), (2, 0.002)):
            for u, eta in enumerate(parts):
                n += 1
                e = [eta + offset + rng.normal(0, 0.0005), eta - 0.02 + offset + rng.normal(0, 0.0005)]
                store_run(dbs[s - 1], _result(f"SN{u:02d}", s, trial, e, 0.0527 * (1 + rng.normal(0, 2e-4)),
                                              n, "x"))
    return dbs


@pytest.fixture
def two_station_dbs(study_dbs, tmp_path):
    out = []
    for db in study_dbs:   # a copy per test: some tests add runs
        dst = tmp_path / db.parent.name / db.name
        dst.parent.mkdir()
        shutil.copy(db, dst)
        out.append(str(dst))
    return out


def test_study_from_station_databases(two_station_dbs, capsys):
    args = ["msa"] + sum((["--db", d] for d in two_station_dbs), []) + ["--json"]
    code = main(args)
    rep = json.loads(capsys.readouterr().out)
    assert rep["parts"][:2] == ["SN00", "SN01"] and rep["stations"] == ["line-1", "line-2"]
    assert rep["trials"] == 3 and rep["runs_used"] == 60
    eta = [c for c in rep["efficiency"] if c["quantity"] == "eta_incremental"]
    assert len(eta) == 2 and len(rep["efficiency"]) == 4
    a = eta[0]["anova"]
    # the spreads that made the data come back (loose: 10 parts, 2 stations)
    assert 0.0003 < a["ev"] < 0.0008
    assert 0.0004 < a["av"] < 0.004
    assert 0.005 < a["pv"] < 0.02
    assert a["tolerance"] == pytest.approx(0.30)
    assert a["pct_tolerance"] == pytest.approx(100 * 6 * a["grr"] / 0.30)
    assert eta[0]["bias_vs_truth"]["n"] == 60
    abs_ = [c for c in rep["efficiency"] if c["quantity"] == "eta_absolute"][0]
    assert abs_["anova"]["pct_tolerance"] is None and "no limit" in abs_["tolerance_note"]
    kt = rep["kt"]
    assert [(k["station"], k["motor"]) for k in kt] == [("line-1", "in"), ("line-2", "in")]
    t = kt[0]["type1"]
    assert t["n"] == 30 and t["reference"] == pytest.approx(0.0527)
    assert t["tolerance"] == pytest.approx(0.30 * 0.0527, rel=1e-9)
    assert t["cg"] == pytest.approx(0.2 * t["tolerance"] / (6 * t["s"])) and t["cg"] > 20
    assert rep["verdict_on"] == ["eta_incremental"]     # eta_absolute has no limit: not in the verdict
    assert code == (0 if rep["verdict"] == "acceptable" else 1)

    assert main(["msa"] + sum((["--db", d] for d in two_station_dbs), [])) == code
    text = capsys.readouterr().out
    assert "eta_incremental  100 rad/s, 0.08 N m" in text
    assert "Kt belongs to the station's motor" in text and "line-2" in text


def test_faulted_and_extra_runs(two_station_dbs, capsys):
    db = two_station_dbs[0]
    # a faulted run is left out; a fourth trial of one cell unbalances the design
    store_run(db, _result("SN00", 1, 9, [0.7, 0.7], 0.0527, 900, "x", status="fault"))
    store_run(db, _result("SN00", 1, 3, [0.73, 0.71], 0.0527, 901, "x"))
    dbs = sum((["--db", d] for d in two_station_dbs), [])
    assert main(["msa", *dbs]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unbalanced design" in err and "--repeats" in err
    assert main(["msa", *dbs, "--repeats", "3", "--json"]) in (0, 1)
    rep = json.loads(capsys.readouterr().out)
    assert rep["runs_used"] == 60
    assert {x["why"].split(" ")[0] for x in rep["left_out"]} == {"status", "beyond"}


@pytest.mark.parametrize("argv, match", [
    (["msa"], "no runs to study"),
    (["msa", "--db", "{tmp}/none.sqlite"], "no station database"),
    (["msa", "profiles/cvt.yaml"], "only used with --sim"),
    (["msa", "--sim"], "needs a profile"),
    (["msa", "--db", "{db}", "--profile", "other"], "no runs of profile other"),
    (["msa", "tests/data/msa-tiny.yaml", "--sim", "--units", "1"], "--units 1: need at least 2"),
    (["msa", "--db", "{db}", "--alpha", "2"], "--alpha"),
])
def test_bad_input_is_one_line_exit_2(argv, match, two_station_dbs, tmp_path, capsys):
    argv = [a.format(tmp=tmp_path, db=two_station_dbs[0]) for a in argv]
    if "profiles/cvt.yaml" in argv:
        argv += ["--db", two_station_dbs[0]]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and match in err and "Traceback" not in err


def test_sim_units_and_stations_differ_where_they_should():
    from gearbench.fleet.gauge_study import STATION_SPREAD, UNIT_SPREAD, _perturbed
    import yaml

    from gearbench.sim import PlantParams

    sim = yaml.safe_load(open(os.path.join(os.path.dirname(__file__), "data", "msa-tiny.yaml")))["simulation"]
    kw = dict(seed=1, unit_spread=UNIT_SPREAD, station_spread=STATION_SPREAD)
    a = PlantParams.from_dict(_perturbed(sim, unit=1, station=1, **kw))
    b = PlantParams.from_dict(_perturbed(sim, unit=2, station=1, **kw))
    c = PlantParams.from_dict(_perturbed(sim, unit=1, station=2, **kw))
    assert a == PlantParams.from_dict(_perturbed(sim, unit=1, station=1, **kw))   # seeded
    assert a.cvt.eta_max != b.cvt.eta_max and a.motor_in == b.motor_in          # unit: the reducer
    assert a.cvt == c.cvt and a.motor_in.Kt != c.motor_in.Kt                    # station: the motors


@pytest.mark.slow
def test_sim_study_end_to_end(tmp_path, capsys):
    """2 units × 1 station × 2 trials of a short CVT profile, each run through the normal
    run chain (emulated drives behind CANopen), then the table. Minutes on a busy host."""
    out = tmp_path / "study"
    code = main(["msa", "tests/data/msa-tiny.yaml", "--sim", "--units", "2", "--repeats", "2",
                 "--stations", "1", "--out", str(out), "--json"])
    rep = json.loads(capsys.readouterr().out)
    assert code in (0, 1)
    assert rep["runs_used"] == 4 and rep["parts"] == ["MSA-U01", "MSA-U02"]
    assert rep["stations"] == ["sim-station-1"]
    eta = [c for c in rep["efficiency"] if c["quantity"] == "eta_incremental"]
    # the two torque points of the one speed lie on one line: one eq. 18 slope reported at
    # both (``efficiency(incremental="auto")``), so one study
    assert len(eta) == 1 and eta[0]["points"] == [0, 1]
    for c in eta:
        # the two units differ by their drawn efficiency; the tester sees it through its noise
        assert c["anova"]["ev"] < 0.003 and c["anova"]["pv"] > c["anova"]["ev"]
        assert abs(c["bias_vs_truth"]["mean"]) < 0.005
    for k in rep["kt"]:
        assert abs(k["type1"]["bias"]) / k["type1"]["reference"] < 0.005
    con = sqlite3.connect(out / "station-1" / "station.sqlite")
    assert con.execute("SELECT COUNT(*) FROM runs").fetchone()[0] == 4
    assert not math.isnan(eta[0]["anova"]["grr"]) and os.path.exists(out / "plants")


def test_one_estimate_reported_at_several_points_is_one_study():
    """A staircase reports one eq. 18 slope per speed at each of its torque points: one study."""
    from gearbench.fleet.gauge_study import efficiency_series

    runs = []
    for n, (serial, st) in enumerate([(s, t) for s in ("A", "B") for t in ("s1", "s2")] * 2):
        res = _result(serial, 1, n, [0.7 + 0.01 * n] * 2, 0.0527, n, "x")
        res["efficiency"][1]["speed_setpoint_rad_s"] = 100.0      # same speed, next torque
        res["efficiency"][1]["torque_out_nm"] = 0.1
        runs.append(dict(serial=serial, station=st, result=res))
    inc = [s for s in efficiency_series(runs) if s["quantity"] == "eta_incremental"]
    assert len(inc) == 1 and inc[0]["points"] == [0, 1]
    assert inc[0]["label"] == "100 rad/s, 0.08-0.1 N m"
