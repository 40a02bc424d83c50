"""Profiles: shipped files, every class of bad input (located, with a fix), waveforms,
the validate command, and property tests that no mutation of a profile gives a traceback."""
from __future__ import annotations

import copy
import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gearbench.cli import main
from gearbench.errors import ProfileError
from gearbench.profile import (CalibrateStep, EfficiencyStep, LoadStep, Profile, WaveformSpec, load_profile,
                               parse_profile_text)
from gearbench.profile import waveforms as wf

REPO = Path(__file__).resolve().parents[1]
PROFILES = REPO / "profiles"
REFERENCE = REPO / "tests" / "data" / "cvt-reference.yaml"
CVT_TEXT = REFERENCE.read_text()
LOCATED = re.compile(r"^(?P<file>[^\n]+?):(?P<line>\d+):(?P<col>\d+): [^\n]+$")


def parse(text: str) -> Profile:
    return parse_profile_text(text, "p.yaml", base_dir=REPO)


def error_of(text: str) -> str:
    with pytest.raises(ProfileError) as info:
        parse(text)
    msg = str(info.value)
    assert "\n" not in msg
    return msg


def line_of(text: str, needle: str, nth: int = 0) -> int:
    """1-based line number of the nth line containing ``needle``."""
    hits = [i + 1 for i, line in enumerate(text.splitlines()) if needle in line]
    return hits[nth]


def replace_once(text: str, old: str, new: str) -> str:
    assert text.count(old) >= 1, old
    return text.replace(old, new, 1)


# ----------------------------------------------------------------------------- shipped profiles


@pytest.mark.parametrize("name", ["cvt", "cyclo", "motors-only", "cvt-modbus"])
def test_shipped_profiles_validate(name):
    p = load_profile(PROFILES / f"{name}.yaml")
    assert p.sha256 == __import__("hashlib").sha256((PROFILES / f"{name}.yaml").read_bytes()).hexdigest()
    for m in p.motors.values():
        assert Path(m.drive).is_file() and Path(m.drive).is_absolute()
    assert p.simulation is not None
    for d in p.disks.values():      # Kt's largest uncertainty term, with its source
        assert 0 < d.inertia_tolerance_rel <= 0.02 and d.inertia_source in ("datasheet", "measured")
    from gearbench.sim import PlantParams
    plant = PlantParams.from_dict(p.simulation, "simulation")
    assert plant.period_s == p.bench.period_s
    if name != "motors-only":
        # a map of >= 3 speeds x 4 torques in a bench time a production line accepts
        assert 10.0 <= p.estimated_bench_time_s <= 90.0
        eff = [s for s in p.steps if isinstance(s, EfficiencyStep)]
        assert len(eff[0].speeds_in_rad_s) >= 3 and len(eff[0].torques_out_nm) >= 4
        assert {s.motor for s in p.steps if isinstance(s, CalibrateStep)} == {"in", "out"}
        # the sim's true efficiency sits inside the profile's expected range at every speed
        lo, hi = p.reducer.efficiency_range
        for w in eff[0].speeds_in_rad_s:
            assert lo < plant.mesh_efficiency(w) < hi
    else:
        assert p.reducer is None and p.operating_points == 0


def test_cvt_profile_contents():
    p = load_profile(PROFILES / "cvt.yaml")
    assert p.reducer.ratio is None and p.reducer.cvt_setting == pytest.approx(0.6)
    assert p.simulation["cvt"]["pulsation_amp"] > 0            # output pulsation
    assert p.simulation["cvt"]["eta_slope_per_rad_s"] > 0      # speed-dependent efficiency
    assert p.waveforms["excite"].kind == "multisine"
    assert p.bench.bus.family == "cia402" and p.bench.bus.interface == "udp_multicast"
    limits = {lim.name: lim for lim in p.limits}
    assert (limits["ratio"].low, limits["ratio"].high) == pytest.approx((8.0 * 0.98, 8.0 * 1.02))
    assert (limits["efficiency"].low, limits["efficiency"].high) == p.reducer.efficiency_range
    assert [type(s) for s in p.steps] == [CalibrateStep, CalibrateStep, LoadStep, EfficiencyStep]
    modbus = load_profile(PROFILES / "cvt-modbus.yaml")
    assert modbus.bench.bus.family == "modbus" and modbus.bench.bus.host == "127.0.0.1"
    assert modbus.motors["in"].drive.endswith("generic-modbus-servo.yaml")
    # the Modbus variant runs the classic fixed-length procedure
    assert modbus.estimated_bench_time_s == load_profile(PROFILES / "cvt-classic.yaml").estimated_bench_time_s
    # cvt.yaml is adaptive: both motors alone at once, then one disk in turn (its error cancels
    # in K_out/K_in), and its max_s values bound the motor-running time under the 20 s a
    # reducer line can give
    assert p.bench.parallel_calibration and p.targets.kt_rel > 0 and p.targets.eta_pp > 0
    cal = [s for s in p.steps if isinstance(s, CalibrateStep)]
    assert all(s.adaptive for s in cal) and len({s.disk for s in cal}) == 1
    # (every measurement at max_s: 20.2 s; measured on --sim 15-17 s)
    assert p.steps[3].adaptive and p.estimated_bench_time_s <= 20.5


def test_efficiency_levels_and_bench_time():
    p = parse(CVT_TEXT)
    eff = p.steps[3]
    levels = eff.levels()
    assert levels[:6] == [(100.0, 0.0), (100.0, 0.02), (100.0, 0.04), (100.0, 0.06), (100.0, 0.08), (100.0, 0.0)]
    assert len(levels) == 3 * 6 and eff.operating_points == 12
    assert p.estimated_bench_time_s == pytest.approx(2 * 2 * 3.0 + 18 * (0.3 + 0.8))
    no_zero = parse(replace_once(CVT_TEXT, "    measure_s: 0.8", "    measure_s: 0.8\n    include_zero_load: false"))
    assert len(no_zero.steps[3].levels()) == 12


# ----------------------------------------------------------------------------- located errors

# (old text, new text, needle locating the expected line, expected message fragment)
CASES = [
    ("    rated_current_a: 1.5", "    rated_current_a: -1", "rated_current_a: -1",
     "motors.in.rated_current_a: must be > 0 (got -1); set the drive's rated current in A"),
    ("    kt_datasheet: 0.0527 ", "    kt_datasheett: 0.0527 ", "kt_datasheett",
     "motors.in.kt_datasheett: unknown key; did you mean 'kt_datasheet'?"),
    ("    current_limit_a: 3.0", "    current_limit_a: 1.0", "current_limit_a: 1.0",
     "current_limit_a: must be >= rated_current_a (1.5)"),
    ("    speed_limit_rad_s: 420", "    speed_limit_rad_s: fast", "speed_limit_rad_s: fast",
     "must be a number (got 'fast')"),
    ("    address: 2", "    address: 1", "address: 1", "address 1 is already used by motor 'in'"),
    ("    address: 2", "    address: 300", "address: 300", "must be between 1 and 127"),
    ("    address: 2", "    address: 2.5", "address: 2.5", "must be a whole number"),
    ("drive: drivers/cia402-servo.eds", "drive: drivers/nope.eds", "drivers/nope.eds",
     "drive description 'drivers/nope.eds' not found"),
    ("drive: drivers/cia402-servo.eds", "drive: drivers/generic-modbus-servo.yaml", "generic-modbus-servo",
     "a cia402 drive needs a .eds or .dcf description"),
    ("    interface: udp_multicast", "    interface: udp_multicat", "udp_multicat",
     "did you mean 'udp_multicast'?"),
    ("    family: cia402", "    family: cia420", "cia420", "unknown drive family 'cia420'; did you mean 'cia402'?"),
    ("  ratio: measure ", "  ratio: mesure ", "ratio: mesure", "did you mean 'measure'?"),
    ("  ratio: measure ", "  ratio: 0 ", "ratio: 0", "reducer.ratio: must be > 0 (got 0)"),
    ("efficiency_range: [0.55, 0.85]", "efficiency_range: [0.85, 0.55]", "efficiency_range",
     "low (0.85) must be <= high (0.55)"),
    ("efficiency_range: [0.55, 0.85]", "efficiency_range: [0.55, 1.2]", "efficiency_range",
     "reducer.efficiency_range[1]: must be <= 1 (got 1.2)"),
    ("{inertia_kgm2: 2.0e-5,", "{inertia_kgm2: -2.0e-5,", "{inertia_kgm2: -2",
     "disks.disk_a.inertia_kgm2: must be > 0 (got -2e-05)"),
    (", inertia_tolerance_rel: 0.005,", ",", "disk_a:",
     "disks.disk_a: missing key 'inertia_tolerance_rel'; add 'inertia_tolerance_rel:' with how well"),
    ("inertia_tolerance_rel: 0.005,", "inertia_tolerance_rel: 0,", "disk_a:",
     "disks.disk_a.inertia_tolerance_rel: must be > 0 (got 0)"),
    ("inertia_tolerance_rel: 0.005,", "inertia_tolerance_rel: 5,", "disk_a:",
     "disks.disk_a.inertia_tolerance_rel: must be <= 0.5 (got 5)"),
    ("inertia_source: measured}", "inertia_source: guessed}", "disk_a:",
     "disks.disk_a.inertia_source: must be one of datasheet, measured (got 'guessed')"),
    (", inertia_source: measured}", "}", "disk_a:",
     "disks.disk_a: missing key 'inertia_source'; add 'inertia_source:' with where the tolerance"),
    ("    disk: disk_a", "    disk: disk_b", "disk: disk_b", "unknown disk 'disk_b' (known: disk_a); did you mean 'disk_a'?"),
    ("    motor: out", "    motor: outt", "motor: outt", "steps[1].motor: unknown motor 'outt'"),
    ("    waveform: excite", "    waveform: excit", "waveform: excit", "did you mean 'excite'?"),
    ("  - kind: load ", "  - kind: lod ", "kind: lod", "did you mean 'load'?"),
    ("    duration_s: 3.0 ", "    duration_s: 0.5 ", "duration_s: 0.5", "shorter than one period of waveform 'excite'"),
    ("speeds_in_rad_s: [100, 200, 300]", "speeds_in_rad_s: [100, 200, 500]", "speeds_in_rad_s",
     "steps[3].speeds_in_rad_s[2]: 500 rad/s is above motors.in.speed_limit_rad_s (420)"),
    ("torques_out_nm: [0.02, 0.04, 0.06, 0.08]", "torques_out_nm: [0.02, 0.04, 0.06, 0.2]", "torques_out_nm",
     "needs 3.8 A at Kt 0.0527 N m/A, above motors.out.current_limit_a (3)"),
    ("    amplitude: 70 ", "    amplitude: 170 ", "waveform: excite",
     "needs about 4.24 A to accelerate motor 'in' with disk 'disk_a'"),
    ("    amplitude: 70 ", "    amplitude: 700 ", "waveform: excite", "reaches 730 rad/s, above motors.in.speed_limit"),
    ("    f_max_hz: 8", "    f_max_hz: 800", "f_max_hz: 800", "must be below the Nyquist frequency 500 Hz"),
    ("    f_max_hz: 8", "    f_max_hz: 0.5", "f_min_hz: 1", "f_min_hz: must be <= f_max_hz (0.5)"),
    ("    kind: multisine", "    kind: multisin", "kind: multisin", "did you mean 'multisine'?"),
    ("    fade_in_s: 0.2", "    fade_in: 0.2", "fade_in: 0.2", "unknown key; did you mean 'fade_in_s'?"),
    ("    quantity: ratio", "    quantity: ration", "quantity: ration", "unknown quantity 'ration'; did you mean 'ratio'?"),
    ("    tolerance_rel: 0.02", "    tolerance: 0.02", "tolerance: 0.02", "did you mean 'tolerance_rel'?"),
    ("    nominal: 8.0 ", "    low: 9\n    high: 8\n    nominal: 8.0 ", "nominal: 8.0", "give either nominal"),
    ("  - name: kt_out", "  - name: kt_in", "name: kt_in", "limit name 'kt_in' is already used by limits[0]"),
    ("  period_s: 0.001 ", "  period_s: 0 ", "period_s: 0 ", "bench.period_s: must be > 0 (got 0)"),
    ("  period_s: 0.001 ", "  period_s: .nan ", "period_s: .nan", "must be a finite number"),
    ("out: {Kt: 0.0512,", "out: {Kt: -0.0512,", "out: {Kt: -0.0512",
     "simulation.motors.out.Kt: must be > 0 (got -0.0512)"),
    ("Tc: 0.009,", "Tcc: 0.009,", "Tcc: 0.009", "simulation.motors.out.Tcc: unknown key; did you mean 'Tc'?"),
    ("    eta_min: 0.3", "    eta_min: 0.95", "  cvt:", "simulation.cvt: need 0 < eta_min <= eta_max"),
    ("  ratio: 8.0 ", "  ratio: 40.0 ", "ratio: 40.0", "simulation.ratio: 40.0 is outside the CVT range"),
    ("  seed: 7", "  seed: 7\n  period_s: 0.002", "period_s: 0.002", "differs from bench.period_s"),
    ("reducer:\n", "reducr:\n", "reducr:", "reducr: unknown key; did you mean 'reducer'?"),
    ("  - kind: load ", "  - kind: load\n  - kind: load ", "kind: load", "a second load step"),
]


@pytest.mark.parametrize("old,new,needle,fragment", CASES, ids=[c[3][:40] for c in CASES])
def test_bad_value_is_located_and_says_the_fix(old, new, needle, fragment):
    text = replace_once(CVT_TEXT, old, new)
    msg = error_of(text)
    m = LOCATED.match(msg)
    assert m, msg
    assert m["file"] == "p.yaml"
    assert fragment in msg, msg
    nth = 1 if needle in ("kind: load", "address: 1", "name: kt_in") else 0   # the second one is the offending one
    assert int(m["line"]) == line_of(text, needle, nth), msg
    assert ";" in msg   # every message carries a fix after the problem


def test_column_points_at_the_key():
    text = replace_once(CVT_TEXT, "    rated_current_a: 1.5", "    rated_current_a: -1")
    msg = error_of(text)
    assert f":{line_of(text, 'rated_current_a: -1')}:5: " in msg


def test_step_order_and_references():
    # calibrate after the reducer is mounted
    steps_at = CVT_TEXT.index("steps:")
    text = CVT_TEXT.replace("  - kind: load                       # operator mounts the CVT between the motors\n", "")
    text = text.replace("  - kind: calibrate\n    motor: in", "  - kind: load\n  - kind: calibrate\n    motor: in", 1)
    assert steps_at
    assert "calibrate step after the load step" in error_of(text)
    # efficiency with no load step
    text = CVT_TEXT.replace("  - kind: load                       # operator mounts the CVT between the motors\n", "")
    assert "needs a load step before it" in error_of(text)
    # a load step without a reducer section
    start, end = CVT_TEXT.index("reducer:\n"), CVT_TEXT.index("disks:\n")
    assert "a load step needs a 'reducer:' section" in error_of(CVT_TEXT[:start] + CVT_TEXT[end:])


def test_limit_needs_a_measuring_step():
    text = (PROFILES / "motors-only.yaml").read_text()
    text = replace_once(text, "limits:\n", "limits:\n  - {name: r, quantity: ratio, low: 1, high: 2}\n")
    assert "measured by an efficiency step, and there is none" in error_of(text)
    text = (PROFILES / "motors-only.yaml").read_text().replace(
        "  - kind: calibrate\n    motor: out\n    disk: disk_a\n    waveform: excite\n    duration_s: 3.0\n", "")
    assert "no calibrate step measures motor 'out'" in error_of(text)


def test_missing_required_key_names_parent():
    text = replace_once(CVT_TEXT, "    kt_datasheet: 0.0527             # N m/A, Crouzet 82800502\n", "")
    msg = error_of(text)
    assert "motors.in: missing key 'kt_datasheet'; add 'kt_datasheet:' with the motor's datasheet" in msg
    assert int(LOCATED.match(msg)["line"]) == line_of(text, "  in:")


def test_yaml_syntax_error_has_line_and_column():
    text = replace_once(CVT_TEXT, "    address: 2", "    address: [2")
    msg = error_of(text)
    assert "YAML syntax error" in msg and LOCATED.match(msg)
    text = replace_once(CVT_TEXT, "  out:                               # brakes", "   out:  # brakes")
    msg = error_of(text)
    assert "YAML syntax error" in msg
    assert abs(int(LOCATED.match(msg)["line"]) - line_of(text, "   out:  # brakes")) <= 1


def test_duplicate_key_and_non_text_key():
    text = replace_once(CVT_TEXT, "    address: 2", "    address: 2\n    address: 3")
    msg = error_of(text)
    assert "motors.out.address: duplicate key" in msg
    assert int(LOCATED.match(msg)["line"]) == line_of(text, "address: 3")
    msg = error_of(replace_once(CVT_TEXT, "reducer:\n", "reducer:\n  on: 1\n"))
    assert "key 'on' is not text" in msg and "quote it" in msg


def test_file_level_errors(tmp_path):
    with pytest.raises(ProfileError, match=r"^nowhere\.yaml: no such profile file; check the path"):
        load_profile("nowhere.yaml")
    with pytest.raises(ProfileError, match="is a folder"):
        load_profile(tmp_path)
    bad = tmp_path / "latin1.yaml"
    bad.write_bytes(b"name: caf\xe9\n")
    with pytest.raises(ProfileError, match=r"latin1\.yaml:1:10: not UTF-8"):
        load_profile(bad)
    empty = tmp_path / "empty.yaml"
    empty.write_text("# nothing\n")
    with pytest.raises(ProfileError, match="the profile is empty"):
        load_profile(empty)
    with pytest.raises(ProfileError, match=r"p\.yaml:1:1: <document>: must be a mapping"):
        parse("- a\n- b\n")


def test_drive_paths_resolve_relative_to_the_profile(tmp_path):
    (tmp_path / "drivers").mkdir()
    (tmp_path / "drivers" / "my-drive.eds").write_text("[FileInfo]\n")
    text = CVT_TEXT.replace("drivers/cia402-servo.eds", "drivers/my-drive.eds")
    path = tmp_path / "cell.yaml"
    path.write_text(text)
    p = load_profile(path)
    assert p.motors["in"].drive == str((tmp_path / "drivers" / "my-drive.eds").resolve())
    # the shipped drivers/ is found from any profile folder (repository root)
    path.write_text(CVT_TEXT)
    assert load_profile(path).motors["out"].drive == str((REPO / "drivers" / "cia402-servo.eds").resolve())


def test_scientific_notation_without_dot_is_a_float():
    p = parse(replace_once(CVT_TEXT, "{inertia_kgm2: 2.0e-5,", "{inertia_kgm2: 2e-5,"))
    assert p.disks["disk_a"].inertia_kgm2 == 2e-5
    # measured: ±0.5 % is a 95 % expanded uncertainty (k = 2); datasheet: limits (u = tol/√3)
    assert p.disks["disk_a"].inertia_std_kgm2 == pytest.approx(2e-5 * 0.005 / 2, rel=1e-12)
    ds = parse(replace_once(CVT_TEXT, "inertia_source: measured", "inertia_source: datasheet"))
    assert ds.disks["disk_a"].inertia_std_kgm2 == pytest.approx(2e-5 * 0.005 / 3 ** 0.5, rel=1e-12)


def test_limit_forms():
    text = replace_once(CVT_TEXT, "    quantity: efficiency.eta_incremental   # each operating point; bounds = "
                        "reducer.efficiency_range",
                        "    quantity: efficiency.eta_absolute\n    high: 0.9")
    lim = parse(text).limits[-1]
    assert (lim.low, lim.high, lim.quantity) == (None, 0.9, "efficiency.eta_absolute")
    assert lim.passed(0.5) and not lim.passed(0.95) and not lim.passed(float("nan"))
    msg = error_of(replace_once(CVT_TEXT, "    low: 0.85\n", "", ).replace("    high: 1.15\n", "", 1))
    assert "limits[0]: no bound given" in msg


def test_modbus_bus_checks():
    text = (PROFILES / "cvt-modbus.yaml").read_text()
    assert "port: must be between 1 and 65535" in error_of(replace_once(text, "port: 5020", "port: 70000"))
    assert "is for a CAN bus" in error_of(replace_once(text, "    port: 5020", "    port: 5020\n    channel: can0"))
    assert "address: must be between 1 and 247" in error_of(replace_once(text, "address: 2", "address: 250"))
    p = parse(replace_once(text, "    port: 5020                       # the emulator's port (real drives: usually 502)\n", ""))
    assert p.bench.bus.port == 502


def test_socketcan_needs_a_channel():
    text = replace_once(CVT_TEXT, "    interface: udp_multicast", "    interface: socketcan")
    text = text.replace("    channel: 239.74.163.2\n", "")
    assert "a socketcan bus needs 'channel'" in error_of(text)


# ----------------------------------------------------------------------------- waveforms


def wave(kind, **params) -> WaveformSpec:
    """A validated waveform via the parser (defaults filled in)."""
    body = "\n".join(f"    {k}: {v}" for k, v in params.items())
    text = CVT_TEXT.replace("waveforms:\n", f"waveforms:\n  w:\n    kind: {kind}\n{body}\n", 1)
    return parse(text).waveforms["w"]


def test_multisine_peak_periodicity_and_chunking():
    w = wave("multisine", offset=10, amplitude=50, period_s=2.0, f_min_hz=0.5, f_max_hz=6)
    t = np.arange(0, 4.0, 1e-3)
    y = w.render(t)
    assert np.max(np.abs(y - 10)) == pytest.approx(50, rel=2e-3)       # peak = amplitude
    assert np.allclose(y[:2000], y[2000:4000], atol=1e-9)              # period_s
    chunks = np.concatenate([w.render(t[i:i + 137]) for i in range(0, t.size, 137)])
    assert np.array_equal(chunks, y)                                     # pointwise in time
    spectrum = np.abs(np.fft.rfft(y[:2000] - 10))
    tones = np.flatnonzero(spectrum > 0.01 * spectrum.max())
    assert list(tones) == list(range(1, 13))                            # k/period in [0.5, 6] Hz


def test_prbs_is_maximum_length():
    for order in (3, 7, 9, 12):
        bits = wf.prbs_bits(order, 0)
        n = 2 ** order - 1
        assert bits.size == n and int(bits.sum()) == 2 ** (order - 1)   # balance property of an m-sequence
        # autocorrelation of +/-1 sequence is -1 at every non-zero lag
        s = 2.0 * bits - 1
        assert all(np.dot(s, np.roll(s, lag)) == -1 for lag in (1, 2, n // 2))
    w = wave("prbs", amplitude=20, bit_s=0.01, order=5)
    y = w.render(np.arange(0, 0.31, 1e-3))
    assert set(np.round(y, 9)) == {-20.0, 20.0}


def test_other_waveforms():
    t = np.arange(0, 2.0, 1e-3)
    assert np.all(wave("constant", value=3).render(t) == 3)
    y = wave("step", amplitude=5, t_step_s=0.5, offset=1).render(t)
    assert y[499] == 1 and y[500] == 6
    y = wave("ramp", slope=100, t0_s=0.5, final=50).render(t)
    assert y[500] == 0 and y[1000] == pytest.approx(50) and y[-1] == 50
    y = wave("trapezoid", amplitude=80, ramp_s=0.2, hold_s=0.3, repeat_s=1.0, alternate="true").render(t)
    assert y[350] == pytest.approx(80) and y[1350] == pytest.approx(-80) and y[900] == 0
    y = wave("chirp", amplitude=1, f0_hz=1, f1_hz=5, t1_s=2.0).render(t)
    zero_crossings_first_half = np.sum(np.diff(np.sign(y[:1000])) != 0)
    zero_crossings_second_half = np.sum(np.diff(np.sign(y[1000:])) != 0)
    assert zero_crossings_second_half > 1.5 * zero_crossings_first_half  # frequency rises
    y = wave("constant", value=10, fade_in_s=0.5).render(t)
    assert y[0] == 0 and y[250] == pytest.approx(5) and y[600] == 10


def test_waveform_parameter_errors():
    assert "a prbs waveform needs 'bit_s'" in error_of(
        CVT_TEXT.replace("waveforms:\n", "waveforms:\n  w:\n    kind: prbs\n    amplitude: 1\n", 1))
    assert "give either freqs_hz or both f_min_hz and f_max_hz" in error_of(
        CVT_TEXT.replace("waveforms:\n", "waveforms:\n  w:\n    kind: multisine\n    amplitude: 1\n", 1))
    assert "0.7 Hz is not a multiple of 1/period_s" in error_of(
        CVT_TEXT.replace("waveforms:\n", "waveforms:\n  w:\n    kind: multisine\n    amplitude: 1\n"
                                         "    freqs_hz: [1, 0.7]\n", 1))
    assert wave("multisine", amplitude=1, freqs_hz="[1, 3, 7]").params["freqs_hz"] == [1.0, 3.0, 7.0]


# ----------------------------------------------------------------------------- validate command


def test_validate_command_prints_summary(capsys):
    assert main(["validate", str(REFERENCE)]) == 0
    out = capsys.readouterr().out
    assert ": OK (sha256 " in out
    assert "12 operating points" in out and "estimated bench time 31.8 s" in out
    assert "calibrate motor in with excite" in out and "disk_a" in out


def test_validate_command_bad_profile_exits_2_with_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text(replace_once(CVT_TEXT, "    rated_current_a: 1.5", "    rated_current_a: -1"))
    assert main(["validate", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert f"{bad}:{line_of(bad.read_text(), 'rated_current_a: -1')}:5: motors.in.rated_current_a" in err


# ----------------------------------------------------------------------------- property tests

BASE = yaml.safe_load(CVT_TEXT)


def _paths(node, prefix=()):
    yield prefix
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _paths(v, prefix + (i,))


ALL_PATHS = [p for p in _paths(BASE) if p]
SCALARS = st.one_of(st.none(), st.booleans(), st.integers(-10 ** 6, 10 ** 6),
                    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=12),
                    st.sampled_from(["measure", "in", "out", "disk_a", "excite", "calibrate", "load", "efficiency",
                                     "multisine", "prbs", "chirp", "modbus", "socketcan", "1e-5", "-1", "0"]))
VALUES = st.one_of(SCALARS, st.lists(SCALARS, max_size=4), st.dictionaries(st.text(max_size=8), SCALARS, max_size=3))


def _set(tree, path, op, value, newkey):
    parent = tree
    for part in path[:-1]:
        parent = parent[part]
    last = path[-1]
    if op == "replace":
        parent[last] = value
    elif op == "delete":
        del parent[last]
    elif op == "rename" and isinstance(parent, dict):
        parent[newkey] = parent.pop(last)
    elif op == "insert" and isinstance(parent, dict):
        parent[newkey] = value
    elif op == "scale" and isinstance(parent[last], (int, float)) and not isinstance(parent[last], bool):
        parent[last] = parent[last] * value if isinstance(value, (int, float)) else -parent[last]


def _check_outcome(text: str) -> None:
    try:
        p = parse(text)
    except ProfileError as exc:
        msg = str(exc)
        assert "\n" not in msg and msg.startswith("p.yaml:"), msg
        assert LOCATED.match(msg) or msg.startswith("p.yaml: "), msg
    else:
        assert isinstance(p, Profile) and p.steps and p.motors
        assert p.estimated_bench_time_s >= 0


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(mutations=st.lists(st.tuples(st.sampled_from(ALL_PATHS),
                                    st.sampled_from(["replace", "delete", "rename", "insert", "scale"]),
                                    VALUES, st.text(min_size=1, max_size=10)), min_size=1, max_size=3))
def test_structural_mutations_never_traceback(mutations):
    tree = copy.deepcopy(BASE)
    for path, op, value, newkey in mutations:
        try:
            _set(tree, path, op, value, newkey)
        except (KeyError, IndexError, TypeError):
            pass  # an earlier mutation removed or replaced this path
    _check_outcome(yaml.safe_dump(tree, sort_keys=False, allow_unicode=True))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(pos=st.integers(0, len(CVT_TEXT) - 1), cut=st.integers(0, 6),
       insert=st.text(alphabet=st.sampled_from(list(" \n\t:-[]{}'\"#&*!|>%@`,0123456789e.abc")), max_size=4))
def test_text_mutations_never_traceback(pos, cut, insert):
    _check_outcome(CVT_TEXT[:pos] + insert + CVT_TEXT[pos + cut:])


def test_adaptive_fields_are_validated_with_file_line_and_field(tmp_path):
    text = (PROFILES / "cvt.yaml").read_text()
    cases = [
        ("  kt_rel: 0.001 ", "  kt_rel: -0.001 ", "targets.kt_rel", "must be > 0"),
        ("    max_s: 0.95 ", "    max_s: 0.1 ", "steps[3].max_s", "shorter than min_s"),
        ("    max_s: 0.95 ", "    max_s: 0.95\n    settle_s: 0.3\n", "steps[3].settle_s", "remove settle_s"),
        ("targets:\n  kt_rel: 0.001", "targets:\n  kt_re: 0.001", "targets.kt_re", "unknown key"),
        ("    min_s: 2.0                       # per run", "    duration_s: 3.0\n    min_s: 2.0  # per run",
         "steps[0].duration_s", "adaptive"),
    ]
    for old, new, where, what in cases:
        assert old in text, old
        bad = tmp_path / "bad.yaml"
        bad.write_text(text.replace(old, new, 1))
        with pytest.raises(ProfileError) as err:
            load_profile(bad)
        msg = str(err.value)
        assert "bad.yaml:" in msg and where in msg and what in msg, msg
        assert len(msg.splitlines()) == 1
    # an adaptive step without its target
    bad.write_text(text.replace("  eta_pp: 0.15", "", 1))
    with pytest.raises(ProfileError, match=r"steps\[3\]\.min_s.*targets\.eta_pp"):
        load_profile(bad)


# ----------------------------------------------------------------------------- drive sampling

def test_drive_sampling_is_read_and_checked():
    """``motors.<m>.sampling`` says how the drive samples; the calibration fits a stepping,
    sampling drive's current kick only when told (identify.drive_sampling)."""
    said = "    rotor_inertia_kgm2: 1.5e-5\n    sampling: {setpoint: step, current: instant}\n"
    p = parse(replace_once(CVT_TEXT, "    rotor_inertia_kgm2: 1.5e-5\n", said))
    assert p.motors["in"].sampling == {"setpoint": "step", "current": "instant"}
    assert parse(CVT_TEXT).motors["in"].sampling is None
    for bad, fragment in (("{setpoint: stepped, current: instant}",
                           "motors.in.sampling.setpoint: must be one of step, interpolated (got 'stepped')"),
                          ("{setpoint: step}", "motors.in.sampling: missing key 'current'"),
                          ("step", "motors.in.sampling: ")):
        text = replace_once(CVT_TEXT, "    rotor_inertia_kgm2: 1.5e-5\n",
                            f"    rotor_inertia_kgm2: 1.5e-5\n    sampling: {bad}\n")
        msg = error_of(text)
        assert fragment in msg and int(LOCATED.match(msg)["line"]) == line_of(text, "sampling:"), msg


def test_drive_sampling_may_give_the_drives_loop():
    """The drive's loop as set (all three or none) is read into the description, so its
    kick is computed (identify.declared_kick); a missing or bad one is named."""
    from gearbench.analysis.identify import declared_kick
    from gearbench.trace import Trace

    loop = ("{setpoint: step, current: instant, speed_kp_a_s_per_rad: 0.2, "
            "current_loop_time_constant_s: 6.0e-4, speed_loop_period_s: 2.5e-4}")
    text = replace_once(CVT_TEXT, "    rotor_inertia_kgm2: 1.5e-5\n",
                        f"    rotor_inertia_kgm2: 1.5e-5\n    sampling: {loop}\n")
    said = parse(text).motors["in"].sampling
    assert said["speed_kp_a_s_per_rad"] == 0.2 and said["speed_loop_period_s"] == 2.5e-4
    t = Trace(np.arange(5) * 1e-3, {"position_rad": np.zeros(5)}, {"drive": said}, "x")
    assert declared_kick(t) == pytest.approx(0.2 * 0.1242, rel=1e-3)
    for bad, fragment in (("{setpoint: step, current: instant, speed_kp_a_s_per_rad: 0.2}",
                           "motors.in.sampling: missing key 'current_loop_time_constant_s'"),
                          (loop.replace("0.2,", "-0.2,"), "speed_kp_a_s_per_rad: must be > 0")):
        msg = error_of(replace_once(CVT_TEXT, "    rotor_inertia_kgm2: 1.5e-5\n",
                                    f"    rotor_inertia_kgm2: 1.5e-5\n    sampling: {bad}\n"))
        assert fragment in msg, msg


def test_station_calibration_passes_the_drive_sampling_on():
    """The station's calibration (analyse.calibrate) gives the profile's ``sampling`` to
    the identification: a drive that steps and samples gets its kick fitted, as declared,
    or computed where the description also gives its loop."""
    from gearbench.benchmarks import robustness as R
    from gearbench.station import analyse
    from gearbench.trace import Trace

    case = R.draw_case(11, 8)
    runs = R.simulate_case(case)["runs"]["in"]
    steps = []
    for t in runs:
        said = t.meta.pop("drive")
        steps.append(Trace(t.time_s, {f"in.{n}": t[n] for n in t.names}, dict(t.meta), "calibrate"))
    kt = case.plant.motor_in.Kt
    told = analyse.calibrate(*steps, motor="in", disk_kgm2=case.disks_kgm2["in"], sampling=said)
    untold = analyse.calibrate(*steps, motor="in", disk_kgm2=case.disks_kgm2["in"])
    # with the drive's loop in the description its kick is computed, without it fitted
    assert told.fit["kick_a_per_rad_s"] > 0 and "setpoint_step" not in told.fit
    plain = {k: v for k, v in said.items() if k in ("setpoint", "current", "current_limit_a")}
    fitted = analyse.calibrate(*steps, motor="in", disk_kgm2=case.disks_kgm2["in"], sampling=plain)
    assert fitted.fit["setpoint_step"]["declared"] and not untold.fit["setpoint_step"].get("declared")
    assert abs(told.Kt / kt - 1) < abs(fitted.Kt / kt - 1) < abs(untold.Kt / kt - 1)
