"""Register maps: the shipped maps load, values round-trip, bad maps name file + key + fix."""
from __future__ import annotations

import math
from pathlib import Path

import pytest
import yaml
from hypothesis import given, settings, strategies as st

from gearbench.drives.register_map import SAMPLED, load_register_map
from gearbench.errors import ProfileError

DRIVERS = Path(__file__).resolve().parents[1] / "drivers"
# drivers/ also holds CiA 402 drive descriptions (family: cia402); those are not register maps
MAPS = sorted(p for p in DRIVERS.glob("*.yaml") if (yaml.safe_load(p.read_text()) or {}).get("family") != "cia402")
GENERIC = DRIVERS / "generic-modbus-servo.yaml"


@pytest.mark.parametrize("path", MAPS, ids=lambda p: p.name)
def test_shipped_maps_load_with_one_contiguous_sample_block(path):
    m = load_register_map(path)
    start, words = m.span(SAMPLED)
    assert words == sum(m.registers[n].words for n in SAMPLED)   # no gaps
    assert words <= 125
    assert m.enable_sequence and m.counter_period_s > 0


def test_generic_map_layout():
    m = load_register_map(GENERIC)
    assert m.word_order == "big"
    assert m.registers["position"].scale == pytest.approx(2 * math.pi / 10000)
    assert m.span() == (10, 9)
    assert "sync" in m.registers
    assert m.is_enabled(0x0237) and not m.is_enabled(0x0233)       # CiA 402 OPERATION ENABLED / SWITCHED ON
    assert m.is_fault(0x0208) and not m.is_fault(0x0237)


def test_two_vendors_put_the_same_value_in_different_words():
    big, little = load_register_map(GENERIC), load_register_map(DRIVERS / "acme-ax2-modbus.yaml")
    assert big.encode_raw("position", 0x12345678) == [0x1234, 0x5678]
    assert little.encode_raw("position", 0x12345678) == [0x5678, 0x1234]
    assert little.decode("velocity", little.encode("velocity", -3.25)) == -3.25    # float32, SI


@settings(deadline=None)   # a loaded host must not fail a pure check on time
@given(st.floats(-2000, 2000, allow_nan=False))
def test_scaled_values_round_trip_within_one_count(value):
    m = load_register_map(GENERIC)
    for name in ("target_velocity", "target_current", "position", "velocity", "current"):
        assert abs(m.decode(name, m.encode(name, value)) - value) <= m.registers[name].scale / 2 + 1e-12


def test_counters_wrap_only_when_asked():
    m = load_register_map(GENERIC)
    assert m.decode_raw("sample_counter", m.encode_raw("sample_counter", 2**32 + 5, wrap=True)) == 5
    with pytest.raises(ValueError, match="does not fit"):
        m.encode_raw("target_velocity", 2**31)


# --- bad maps: each error names the file, the key and the fix -------------------
def _write_variant(tmp_path, edit) -> Path:
    data = yaml.safe_load(GENERIC.read_text())
    edit(data)
    path = tmp_path / "bad-map.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _del(d, *keys):
    for k in keys[:-1]:
        d = d[k]
    del d[keys[-1]]


def _set(value, *keys):
    def edit(d):
        for k in keys[:-1]:
            d = d[k]
        d[keys[-1]] = value
    return edit


BAD = {
    "missing required register": (lambda d: _del(d, "registers", "current"),
                                  "registers.current: missing", "add `current:"),
    "unknown type": (_set("int24", "registers", "velocity", "type"),
                     "registers.velocity.type: unknown type 'int24'", "use one of int16"),
    "overlapping addresses": (_set(3, "registers", "target_current", "address"),
                              "registers.target_current.address: 3 overlaps registers.target_velocity",
                              "move one of them"),
    "bad word order": (_set("middle", "word_order"), "word_order: 'middle'", "use 'big'"),
    "sample block with a gap": (_set(30, "registers", "current", "address"),
                                "registers.current.address: 30 leaves a gap", "one request"),
    "read-only target": (_set("r", "registers", "target_velocity", "access"),
                         "registers.target_velocity.access", "set access: w"),
    "zero scale": (_set(0, "registers", "position", "scale"), "registers.position.scale", "SI units per count"),
    "bad scale expression": (_set("2*pie", "registers", "position", "scale"), "registers.position.scale",
                             "2*pi/10000"),
    "counter without seconds": (_set("", "registers", "sample_counter", "unit"),
                                "registers.sample_counter", "unit: s"),
    "enable sequence writes a read-only register": (
        lambda d: d["enable_sequence"].append({"register": "status", "value": 1}),
        "enable_sequence[6].register: 'status'", "access w or rw"),
    "missing modes": (lambda d: _del(d, "modes"), "modes:", "velocity: 3"),
    "missing control value": (lambda d: _del(d, "control_values", "quick_stop"), "control_values",
                              "quick_stop: 2"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_map_error_names_file_key_and_fix(tmp_path, case):
    edit, key_text, fix_text = BAD[case]
    path = _write_variant(tmp_path, edit)
    with pytest.raises(ProfileError) as err:
        load_register_map(path)
    msg = str(err.value)
    assert str(path) in msg and key_text in msg and fix_text in msg, msg
    assert "\n" not in msg


def test_error_gives_the_yaml_line(tmp_path):
    text = GENERIC.read_text().replace("type: int16,  scale: 1,        unit: \"\",    access: rw}",
                                       "type: short,  scale: 1,        unit: \"\",    access: rw}", 1)
    path = tmp_path / "line.yaml"
    path.write_text(text)
    line = next(i for i, s in enumerate(text.splitlines(), 1) if "type: short" in s)
    with pytest.raises(ProfileError, match=rf"line.yaml:{line}: registers.mode.type: unknown type 'short'"):
        load_register_map(path)


def test_unreadable_and_invalid_yaml(tmp_path):
    with pytest.raises(ProfileError, match="nope.yaml: cannot read register map"):
        load_register_map(tmp_path / "nope.yaml")
    bad = tmp_path / "syntax.yaml"
    bad.write_text("registers: {control: [\n")
    with pytest.raises(ProfileError, match="syntax.yaml:.*not valid YAML"):
        load_register_map(bad)
