import numpy as np
import pytest

from gearbench import Trace, TraceError


def make(n=100):
    t = np.arange(n) * 1e-3
    return Trace(t, {"position_rad": np.sin(t), "current_a": np.cos(t)}, {"motor": "in"})


def test_csv_roundtrip_keeps_columns_and_meta(tmp_path):
    tr = make()
    p = tr.write_csv(tmp_path / "a.csv")
    back = Trace.read(p)
    assert back.names == ["position_rad", "current_a"]
    assert back.meta["motor"] == "in"
    np.testing.assert_allclose(back["position_rad"], tr["position_rad"], rtol=1e-9)
    np.testing.assert_allclose(back.time_s, tr.time_s, atol=1e-12)


def test_parquet_roundtrip(tmp_path):
    tr = make()
    back = Trace.read(tr.write_parquet(tmp_path / "a.parquet"))
    assert back.meta == {"motor": "in"}
    np.testing.assert_array_equal(back["current_a"], tr["current_a"])


def test_missing_column_names_file_and_fix(tmp_path):
    p = tmp_path / "x.csv"
    p.write_text("time_s,position_rad\n0,0\n0.001,0\n")
    with pytest.raises(TraceError, match=r"x.csv: missing column 'current_a'"):
        Trace.read(p).validate(["position_rad", "current_a"], min_samples=1)


def test_bad_cell_names_line_and_column(tmp_path):
    p = tmp_path / "x.csv"
    p.write_text("time_s,position_rad,current_a\n0,0,0\n0.001,abc,0\n")
    with pytest.raises(TraceError, match=r"line 3, column 'position_rad': 'abc'"):
        Trace.read(p)


def test_nan_and_time_problems_found():
    t = np.arange(50) * 1e-3
    with pytest.raises(TraceError, match="non-finite"):
        Trace(t, {"current_a": np.where(t > 0.02, np.nan, 0.0)}).validate(["current_a"])
    t2 = t.copy()
    t2[10] = t2[9]
    with pytest.raises(TraceError, match="not strictly increasing at row 11"):
        Trace(t2, {"current_a": np.zeros(50)}).validate(["current_a"])
    t3 = t.copy()
    t3[20:] += 5e-3
    with pytest.raises(TraceError, match="irregular sampling"):
        Trace(t3, {"current_a": np.zeros(50)}).validate(["current_a"])


def test_too_few_samples():
    with pytest.raises(TraceError, match="only 5 samples"):
        make(5).validate(["current_a"])


def test_unreadable_file(tmp_path):
    with pytest.raises(TraceError, match="file not found"):
        Trace.read(tmp_path / "nope.csv")
    p = tmp_path / "bin.parquet"
    p.write_bytes(b"\x00\x01garbage")
    with pytest.raises(TraceError, match="not a readable Parquet"):
        Trace.read(p)
