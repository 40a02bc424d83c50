"""ASAM MDF4 export of a run's traces (``gearbench export RUN --mdf``, ``run --mdf``): the
file opens with asammdf, every channel of every step is there with its unit, the run's
identity is in the header, and the values are the Parquet traces' (issue 27)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from gearbench.cli import main
from gearbench.station.recorder import load_step_trace

asammdf = pytest.importorskip("asammdf")

UNITS = {"position_rad": "rad", "velocity_rad_s": "rad/s", "current_a": "A",
         "command_rad_s": "rad/s", "command_a": "A"}


def _check(mf4, run_dir):
    result = json.loads((run_dir / "result.json").read_text())
    traces = {p.stem.removeprefix("trace-"): load_step_trace(p) for p in run_dir.glob("trace-*.parquet")}
    mdf = asammdf.MDF(mf4)
    try:
        assert mdf.version.startswith("4.")
        header = mdf.header.comment
        for key in ("serial", "profile", "profile_sha256", "run_id", "status", "gearbench_version"):
            assert f'name="{key}">{result[key]}<' in header, key
        assert "simulated bench" in header
        groups = {g.channel_group.acq_name: (k, g) for k, g in enumerate(mdf.groups)}
        assert set(groups) == set(traces)
        seen_command_units = set()
        for step, tr in traces.items():
            k, g = groups[step]
            chans = {c.name: c.unit for c in g.channels}
            assert chans.pop("time") == "s"
            assert chans.pop("sample") == ""                      # a count
            for col in tr.columns:
                if col == "sample":
                    continue
                motor, _, q = col.partition(".")
                if q == "command":
                    names = [n for n in chans if n.startswith(f"{motor}.command")]
                    assert len(names) == 1, (step, names)
                    name = names[0]
                    if name == f"{motor}.command":            # motor not driven in this step
                        assert np.all(np.asarray(tr[col]) == 0)
                        continue
                    seen_command_units.add(chans[name])
                else:
                    name = col
                assert chans[name] == UNITS[name.split(".", 1)[1]], (step, name, chans[name])
                sig = mdf.get(name, group=k)
                np.testing.assert_allclose(sig.samples, tr[col])
                np.testing.assert_allclose(sig.timestamps, tr.time_s)
        assert seen_command_units == {"rad/s", "A"}              # velocity and braking current apart
    finally:
        mdf.close()
    return groups


def test_run_with_mdf_writes_traces_mf4(cvt_sim_run):
    groups = _check(cvt_sim_run / "traces.mf4", cvt_sim_run)
    assert any(s.startswith("efficiency-") for s in groups)


def test_export_command_writes_a_readable_mdf4(cvt_sim_run, tmp_path, capsys):
    out = tmp_path / "x.mf4"
    assert main(["export", str(cvt_sim_run), "--mdf", "--out", str(out)]) == 0
    assert str(out) in capsys.readouterr().out
    _check(out, cvt_sim_run)


def test_export_of_a_folder_without_traces_is_one_line(tmp_path, capsys):
    assert main(["export", str(tmp_path), "--mdf"]) == 2
    err = capsys.readouterr().err
    assert "no trace-*.parquet" in err and len(err.strip().splitlines()) == 1


def test_profile_outputs_mdf_is_parsed():
    from gearbench.profile import parse_profile_text
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    text = (repo / "profiles" / "motors-only.yaml").read_text()
    prof = parse_profile_text(text + "\noutputs:\n  mdf: true\n", "p.yaml", repo / "profiles")
    assert prof.outputs.mdf is True
    assert parse_profile_text(text, "p.yaml", repo / "profiles").outputs.mdf is False
    with pytest.raises(Exception) as e:
        parse_profile_text(text + "\noutputs:\n  mdf4: true\n", "p.yaml", repo / "profiles")
    assert "did you mean 'mdf'" in str(e.value)
