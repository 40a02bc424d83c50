"""Live view in Rerun: every sample and every result reaches the .rrd.

The recording is read back with rerun's own reader (``rr.chunk.RrdReader``).
"""
from __future__ import annotations

import json
import socket
from collections import defaultdict

import numpy as np
import pytest
import rerun as rr

from gearbench.cli import main
from gearbench.reports.live import RerunView, open_live_view
from gearbench.reports.live.blueprint import EFFICIENCY_TITLE, EFFICIENCY_TITLES
from gearbench.reports.live.replay import replay_records
from gearbench.station.records import (Calibration, EfficiencyPoint, LimitResult, Message, Progress,
                               RecordStream, RunStart, RunStop, SampleBatch, StepStart, StepStop)
from gearbench.trace import Trace

MOTORS = ("in", "out")
QUANTITIES = ("position_rad", "velocity_rad_s", "current_a", "command")
CAL = {"in": {"Kt": 0.1234, "Kt_ci95": [0.1230, 0.1238], "Kt_std": 0.0002, "J": 2.1e-4, "D": 3e-5,
              "Tc": 0.012, "method": "x"},
       "out": {"Kt": 0.2468, "Kt_ci95": [0.2460, 0.2476], "Kt_std": 0.0004, "J_kgm2": 4.2e-4,
               "D_nm_s_per_rad": 6e-5, "Tc_nm": 0.02}}
# Measured speeds and torques scatter around the grid (as on the bench).
POINTS = [{"speed_in_rad_s": s * (1 + 3e-5 * (k % 3 - 1)), "torque_out_nm": t * (1 + 2e-3 * (k % 2)),
           "eta_incremental": 0.9 - 0.01 * k,
           "eta_absolute": 0.85, "eta_incremental_ci95": [0.88, 0.92], "eta_absolute_ci95": [0.84, 0.86],
           "t_mid_s": 2.0 + 0.2 * k, "speed_setpoint_rad_s": s}
          for k, (s, t) in enumerate([(s, t) for s in (20.0, 40.0) for t in (0.5, 1.0, 1.5)])]
LIMITS = [("Kt_in", 0.1234, 0.12, 0.13, True), ("eta_min", 0.86, 0.87, None, False)]


class _AsDict(dict):
    """Stands in for the analysis's typed results: the view reads their ``to_dict()``."""

    def to_dict(self) -> dict:
        return dict(self)


def synthetic_steps(seed: int = 1):
    """Two steps of random data; uneven batch sizes and a lost-sample gap."""
    rng = np.random.default_rng(seed)
    steps = {}
    start = 0
    for name, n in (("calibrate-in-unloaded", 1400), ("efficiency", 1900)):
        sample = np.arange(start, start + n, dtype=np.int64)
        sample[n // 2:] += 3 if name == "efficiency" else 0   # 3 lost samples
        t = sample * 1e-3
        cols = {f"{m}.{q}": rng.normal(size=n) for m in MOTORS for q in QUANTITIES}
        steps[name] = (sample, t, cols)
        start = int(sample[-1]) + 1
    return steps


def feed(view, steps, residuals=None) -> None:
    """Emit a run to ``view``; ``residuals``: the RerunView for the diagnosis hook."""
    view(RunStart("r1", "SN-42", "cvt", "profiles/cvt.yaml", "abc", "2026-11-01T00:00:00Z",
                  True, MOTORS, 1e-3, "/tmp/x"))
    for name, (sample, t, cols) in steps.items():
        view(StepStart(name, name.split("-")[0], "test step", len(sample)))
        view(Message("Mount inertia disk A, then press Enter", level="prompt", step=name))
        sizes = [173, 97, 250, 131]                        # the sequencer's ~100-250
        i, k = 0, 0
        while i < len(sample):
            j = min(i + sizes[k % len(sizes)], len(sample))
            view(SampleBatch(name, sample[i:j], t[i:j], {c: v[i:j] for c, v in cols.items()}))
            view(Progress(name, f"point {k // 3}", j / len(sample), 0.5))
            i, k = j, k + 1
        view(StepStop(name, "ok", len(sample), int(np.sum(np.diff(sample) - 1))))
    for motor, params in CAL.items():
        view(Calibration(motor, _AsDict(params)))
    for p in POINTS:
        view(EfficiencyPoint(_AsDict(p)))
    for name, value, low, high, passed in LIMITS:
        view(LimitResult(name, value, low, high, passed,
                         "efficiency.eta_incremental" if name.startswith("eta") else "motors.in.Kt"))
    (residuals or view).log_residuals("friction_model", np.arange(50) * 1e-2, np.linspace(0, 1, 50))
    view(RunStop("failed", 1, "eta_min"))


def read_rrd(path):
    """entity path -> list of (non-static) record batches, plus the blueprint stores."""
    reader = rr.chunk.RrdReader(path)
    out = defaultdict(list)
    for chunk in reader.stream().to_chunks():
        if not chunk.is_static:
            out[chunk.entity_path].append(chunk.to_record_batch())
    return out, reader.blueprints()


def column(batches, name):
    return [v for b in batches for v in b.column(name).to_pylist()]


def series(batches):
    """(sample, time_ns, value) of a scalar entity, sorted by sample."""
    sample = np.array(column(batches, "sample"), dtype=np.int64)
    time_ns = np.array([d.value for b in batches for d in b.column("bench_time")], dtype=np.int64)
    values = np.array([v[0] for v in column(batches, "Scalars:scalars")])
    order = np.argsort(sample, kind="stable")
    return sample[order], time_ns[order], values[order]


def check_every_sample(entities, steps):
    sample = np.concatenate([s for s, _, _ in steps.values()])
    time_ns = np.rint(np.concatenate([t for _, t, _ in steps.values()]) * 1e9).astype(np.int64)
    for m in MOTORS:
        for q in QUANTITIES:
            if q == "command":
                continue
            got_s, got_t, got_v = series(entities[f"/bench/{m}/{q}"])
            want = np.concatenate([c[f"{m}.{q}"] for _, _, c in steps.values()])
            assert got_s.size == sample.size, f"{m}.{q}: {got_s.size} of {sample.size} samples"
            np.testing.assert_array_equal(got_s, sample)
            np.testing.assert_array_equal(got_t, time_ns)
            np.testing.assert_array_equal(got_v, want)
    # setpoints by unit: the input always in speed; the output in speed while calibrating,
    # in current (its braking staircase) in the efficiency step: never on one axis
    for m, unit, names in (("in", "rad_s", list(steps)), ("out", "rad_s", ["calibrate-in-unloaded"]),
                           ("out", "a", ["efficiency"])):
        got_s, _, got_v = series(entities[f"/bench/{m}/command_{unit}"])
        np.testing.assert_array_equal(got_s, np.concatenate([steps[n][0] for n in names]))
        np.testing.assert_array_equal(got_v, np.concatenate([steps[n][2][f"{m}.command"] for n in names]))
    assert f"/bench/in/command_a" not in entities and "/bench/out/command" not in entities


def test_every_sample_and_result_reach_the_rrd(tmp_path):
    steps = synthetic_steps()
    rrd = tmp_path / "run.rrd"
    view = open_live_view(rrd=rrd)
    assert isinstance(view, RerunView)
    stream = RecordStream([view])
    feed(stream, steps, residuals=view)
    stream.close()
    assert stream.errors == []

    entities, blueprints = read_rrd(rrd)
    assert blueprints, "default blueprint missing"
    check_every_sample(entities, steps)

    motors = {m: entities[f"/results/motors/{m}"] for m in MOTORS}
    assert column(motors["in"], "Kt") == [[0.1234]]
    assert column(motors["in"], "Kt_ci95_high") == [[pytest.approx(0.1238)]]
    assert column(motors["out"], "Kt_ci95_low") == [[0.2460]]
    assert column(motors["out"], "Tc_nm") == [[0.02]]
    assert column(motors["in"], "J_kgm2") == [[2.1e-4]]                # an old result.json's "J"

    pts = entities["/results/efficiency/points"]
    assert sorted(v[0] for v in column(pts, "eta_incremental")) == \
        sorted(p["eta_incremental"] for p in POINTS)
    # efficiency as Rerun's own series: per input speed, incremental and absolute, in %,
    # with their 95 % intervals, and the efficiency limits as lines
    for speed in (20, 40):
        pts = [p for p in POINTS if round(p["speed_in_rad_s"]) == speed]
        base = f"/results/efficiency/series/incremental/{speed:g}rad_s"
        assert [v[0] for v in column(entities[base], "Scalars:scalars")] == \
            pytest.approx([100 * p["eta_incremental"] for p in pts])
        assert [v[0] for v in column(entities[base + "/ci95_low"], "Scalars:scalars")] == pytest.approx([88.0] * 3)
        absolute = f"/results/efficiency/series/absolute/{speed:g}rad_s"
        assert [v[0] for v in column(entities[absolute + "/ci95_high"], "Scalars:scalars")] == pytest.approx([86.0] * 3)
    assert "/results/efficiency/map" not in entities            # no raster image any more
    assert [v[0] for v in column(entities["/results/efficiency/series/incremental/limit_low"],
                                 "Scalars:scalars")] == [pytest.approx(87.0)] * 2
    assert view.panels[-5:] == ["Results", "Diagnosis residuals", EFFICIENCY_TITLES["incremental"],
                                EFFICIENCY_TITLES["absolute"], "Steps and operator"]
    assert [p for p in view.panels if p.startswith("motor out:")] == [
        "motor out: current [A]", "motor out: velocity [rad/s]", "motor out: speed command [rad/s]",
        "motor out: current command [A]", "motor out: position [rad]"]

    assert column(entities["/results/limits/Kt_in"], "passed") == [[True]]
    assert column(entities["/results/limits/eta_min"], "passed") == [[False]]
    summary = column(entities["/results/summary"], "TextDocument:text")[-1][0]
    assert "FAILED" in summary and "eta_min" in summary and "0.1234" in summary
    assert "| 40 | 87.00 | 86.00 | 85.00 |" in summary      # one row per nominal speed

    log = [row[0] for row in column(entities["/log"], "TextLog:text")]
    assert any("OPERATOR: Mount inertia disk A" in line for line in log)
    assert any(line.startswith("step efficiency ok: 1900 samples, 3 lost") for line in log)
    assert any(line.startswith("operating point") for line in log)
    assert len(column(entities["/diagnosis/friction_model"], "Scalars:scalars")) == 50


def test_panels_only_for_data_there_is(tmp_path):
    """A calibration-only run: one panel per motor quantity, no empty map or residuals."""
    view = open_live_view(rrd=tmp_path / "r.rrd")
    view(RunStart("r2", "SN-43", "motors-only", "p.yaml", "abc", "2026-11-01T00:00:00Z",
                  True, MOTORS, 1e-3, str(tmp_path)))
    view(Calibration("in", _AsDict(CAL["in"])))
    view(RunStop("passed", 0, ""))
    view.close()
    assert EFFICIENCY_TITLE not in view.panels and "Diagnosis residuals" not in view.panels
    for m in MOTORS:
        assert [p.split(": ")[1].split(" ")[0] for p in view.panels if p.startswith(f"motor {m}:")] == \
            ["current", "velocity", "speed", "position"]


def write_result_folder(folder, steps):
    for name, (sample, t, cols) in steps.items():
        Trace(t, {"sample": sample, **cols}).write_parquet(folder / f"trace-{name}.parquet")
    result = {"serial": "SN-42", "profile": "cvt", "status": "failed", "passed": False,
              "exit_code": 1, "motors": CAL, "ratio": 10.0, "efficiency": POINTS,
              "limits": [{"name": n, "value": v, "low": lo, "high": hi, "passed": ok}
                         for n, v, lo, hi, ok in LIMITS],
              "steps": {name: len(s) for name, (s, _, _) in steps.items()}, "bench_time_s": 3.3}
    (folder / "result.json").write_text(json.dumps(result))


def test_view_command_replays_a_result_folder(tmp_path, capsys):
    steps = synthetic_steps(seed=2)
    folder = tmp_path / "SN-42"
    folder.mkdir()
    write_result_folder(folder, steps)
    rrd = tmp_path / "replay.rrd"
    assert main(["view", str(folder), "--rrd", str(rrd)]) == 0
    assert "3300 samples replayed" in capsys.readouterr().out
    entities, blueprints = read_rrd(rrd)
    assert blueprints
    check_every_sample(entities, steps)
    assert column(entities["/results/motors/out"], "Kt") == [[0.2468]]
    assert len(column(entities["/results/efficiency/points"], "eta_absolute")) == len(POINTS)
    assert column(entities["/results/limits/eta_min"], "passed") == [[False]]
    summary = column(entities["/results/summary"], "TextDocument:text")[-1][0]
    assert "Reduction ratio n = 10" in summary and "FAILED" in summary


def test_replay_orders_steps_as_acquired(tmp_path):
    steps = synthetic_steps(seed=3)
    write_result_folder(tmp_path, steps)
    names = [r.name for r in replay_records(tmp_path) if r.kind == "step_start"]
    assert names == ["calibrate-in-unloaded", "efficiency"]   # not alphabetical by file


@pytest.mark.parametrize("make", ["missing", "empty", "bad_json"])
def test_view_bad_folder_is_one_line_exit_2(tmp_path, capsys, make):
    folder = tmp_path / "run"
    if make != "missing":
        folder.mkdir()
    if make == "bad_json":
        (folder / "result.json").write_text("{not json")
    assert main(["view", str(folder), "--rrd", str(tmp_path / "x.rrd")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("gearbench view: error:") and str(folder) in err and "\n" not in err


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def no_display(monkeypatch):
    """A headless machine, even if someone runs a viewer on the default port here."""
    from gearbench.reports.live import rerun_view

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    real = rerun_view._listening
    monkeypatch.setattr(rerun_view, "_listening",
                        lambda url, **kw: False if ":9876/" in url else real(url, **kw))


def test_no_viewer_is_a_one_line_notice_and_the_run_goes_on(tmp_path, capsys, monkeypatch):
    no_display(monkeypatch)
    url = f"rerun+http://127.0.0.1:{_free_port()}/proxy"
    assert open_live_view(connect=url) is None
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and url in err

    # with --rrd as well: one notice, and the recording still holds every sample
    rrd = tmp_path / "still.rrd"
    view = open_live_view(live=True, connect=url, rrd=rrd)
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no display" in err and str(rrd) in err
    steps = synthetic_steps(seed=4)
    feed(view, steps)
    view.close()
    check_every_sample(read_rrd(rrd)[0], steps)

    assert open_live_view() is None and capsys.readouterr().err == ""   # nothing asked


def test_view_command_without_viewer_says_so_in_one_line(tmp_path, capsys, monkeypatch):
    no_display(monkeypatch)
    write_result_folder(tmp_path, synthetic_steps(seed=5))
    assert main(["view", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "no display" in err and "--rrd" in err and "\n" not in err


def test_a_finished_recording_opens_on_its_final_results(tmp_path):
    """The results panel's final state is also static: a viewer opening the .rrd shows the
    verdict at once, at any time cursor, never "RUNNING" while the samples load."""
    rrd = tmp_path / "run.rrd"
    view = open_live_view(rrd=rrd)
    stream = RecordStream([view])
    feed(stream, synthetic_steps(), residuals=view)
    stream.close()
    static = [c.to_record_batch() for c in rr.chunk.RrdReader(rrd).stream().to_chunks()
              if c.is_static and c.entity_path == "/results/summary"]
    text = column(static, "TextDocument:text")[-1][0]
    assert "finished: FAILED" in text and "RUNNING" not in text
    assert text.index("Limits: 1 of 2 passed: failed eta_min") < text.index("## Motors")


def test_diagnosis_layout_puts_the_noise_floor_with_the_error_it_bounds(tmp_path):
    """For ``gearbench diagnose --rrd`` (issue 24 wires it): one panel for the error and the
    floor under /diagnosis/, as paths.py declares, another for the equation error."""
    from gearbench.reports.live import paths as P
    from gearbench.reports.live.blueprint import diagnosis_blueprint

    assert P.DIAGNOSIS_ERROR.startswith(P.DIAGNOSIS + "/") and P.DIAGNOSIS_EQUATION.startswith(P.DIAGNOSIS + "/")
    rec = rr.RecordingStream("t")
    rec.save(str(tmp_path / "d.rrd"))
    rec.send_blueprint(diagnosis_blueprint())
    rec.flush()
    rec.disconnect()
    assert rr.chunk.RrdReader(tmp_path / "d.rrd").blueprints()
