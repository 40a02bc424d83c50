"""validate <=> start-up: any profile `gearbench validate` accepts starts on the emulator
serving that EDS, and any it refuses does not start - over every vendor EDS in
../shared/reference/vendor-eds (plus the held-out ones in tests/data/vendor-eds) and
synthetic variants of them (0x6060 not mappable, 0x6071 missing on one drive of two,
a 1 s interpolation unit with a writable or read-only exponent, vendor current
objects and a manufacturer current mode, wrong device type, no 0x1017, broken
descriptions, an encoder resolution no object reports, fixed by the description, and
Nanotec's dictionary before the firmware that added 0x2039:05)."""
from __future__ import annotations

import re
import uuid
from pathlib import Path

import pytest

from gearbench.drives.base import AxisConfig, Mode
from gearbench.drives.buses import parse_bus
from gearbench.drives.cia402 import CiA402Network
from gearbench.drives.devicecheck import check_profile
from gearbench.emulate.bench import EmulatedBench
from gearbench.emulate.canopen_server import DEFAULT_EDS, start_canopen_server
from gearbench.errors import GearbenchError
from gearbench.profile import load_profile
from gearbench.sim import PlantParams

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(__file__).resolve().parents[2] / "shared" / "reference" / "vendor-eds"
HELD_OUT = REPO / "tests" / "data" / "vendor-eds"
VENDOR_FILES = sorted(p for d in (SHARED, HELD_OUT) if d.is_dir() for p in d.iterdir()
                      if p.suffix.lower() in (".eds", ".dcf"))


# ------------------------------------------------------------------ EDS editing
def _blocks(text: str) -> list[str]:
    return re.split(r"(?m)^(?=\[)", text)


def set_key(text: str, section: str, key: str, value: str) -> str:
    out = []
    for b in _blocks(text):
        if b.lower().startswith(f"[{section.lower()}]"):
            if re.search(rf"(?mi)^{key}=", b):
                b = re.sub(rf"(?mi)^{key}=.*$", f"{key}={value}", b)
            else:
                b = b.rstrip("\n") + f"\n{key}={value}\n\n"
        out.append(b)
    return "".join(out)


def drop(text: str, index: str) -> str:
    return "".join(b for b in _blocks(text) if not re.match(rf"(?i)\[{index}(sub[0-9a-f]+)?\]", b))


def var(index: str, name: str, dtype: str, access: str, mapping: int, default: str = "0") -> str:
    return (f"\n[{index}]\nParameterName={name}\nObjectType=0x7\nDataType={dtype}\nAccessType={access}\n"
            f"DefaultValue={default}\nPDOMapping={mapping}\n\n")


def interpolation(sub2_access: str, exponent: int = 0) -> str:
    return ("\n[60C2]\nParameterName=Interpolation time period\nObjectType=0x9\nSubNumber=3\n\n"
            "[60C2sub0]\nParameterName=Highest sub-index supported\nObjectType=0x7\nDataType=0x0005\n"
            "AccessType=ro\nDefaultValue=2\nPDOMapping=0\n\n"
            "[60C2sub1]\nParameterName=Interpolation time period value\nObjectType=0x7\nDataType=0x0005\n"
            "AccessType=rw\nDefaultValue=1\nPDOMapping=0\n\n"
            f"[60C2sub2]\nParameterName=Interpolation time index\nObjectType=0x7\nDataType=0x0002\n"
            f"AccessType={sub2_access}\nDefaultValue={exponent}\nPDOMapping=0\n\n")


VENDOR_CURRENT_DESC = """family: cia402
model: manufacturer-current-mode servo (synthetic)
match:
  vendor_id: 0x00000000
  product_codes: [0x402]
sources:
  eds: "the variant EDS written by this test: 0x2200 current actual (INTEGER32), 0x2201 current setpoint"
  manual: "the (synthetic) firmware manual: current mode -3, currents in mA"
velocity:
  unit: inc/s
  source: manual
current:
  object: "0x2200"
  unit: mA
  source: eds [2200]; manual
torque:
  mode: -3
  setpoint: "0x2201"
  unit: mA
  source: manual
"""


def variants(tmp: Path) -> dict[str, tuple[str, str, str]]:
    """name -> (EDS of motor in, EDS of motor out, description YAML beside them or '')."""
    ref = Path(DEFAULT_EDS).read_text()
    epos = (SHARED / "maxon-epos4.eds").read_text() if (SHARED / "maxon-epos4.eds").is_file() else None
    out: dict[str, tuple[str, str, str]] = {}

    def write(name: str, text: str) -> str:
        p = tmp / name
        p.write_text(text)
        return str(p)

    ref_no_map = write("ref-6060-sdo.eds", set_key(ref, "6060", "PDOMapping", "0"))
    out["0x6060 not mappable (reference)"] = (ref_no_map, ref_no_map, "")
    vendor = set_key(drop(drop(drop(ref, "6078"), "6071"), "6087"), "6502", "DefaultValue", "0x00000104")
    vendor += var("2200", "Current actual value (mA)", "0x0004", "ro", 1)
    vendor += var("2201", "Current mode setting value", "0x0004", "rww", 1)
    manuf = write("vendor-current-mode.eds", set_key(vendor, "6060", "PDOMapping", "0"))
    out["manufacturer current mode -3, vendor objects, 0x6060 by SDO"] = (manuf, manuf, VENDOR_CURRENT_DESC)
    unmappable = write("vendor-current-unmappable.eds", set_key(vendor, "2200", "PDOMapping", "0"))
    out["vendor current actual not mappable"] = (unmappable, unmappable, VENDOR_CURRENT_DESC)
    out["description cites an undefined source"] = (manuf, manuf, VENDOR_CURRENT_DESC.replace(
        "source: eds [2200]; manual", "source: datasheet p. 4"))
    out["description names an object the EDS lacks"] = (manuf, manuf, VENDOR_CURRENT_DESC.replace(
        'object: "0x2200"', 'object: "0x2300"'))
    out["description misspells a key"] = (manuf, manuf, VENDOR_CURRENT_DESC.replace("setpoint:", "set_point:"))
    writable = write("ref-60c2-1s-writable.eds", ref + interpolation("rw", 0))
    out["0x60C2 unit 1 s, exponent writable"] = (writable, writable, "")
    fixed = write("ref-60c2-1s-readonly.eds", ref + interpolation("ro", 0))
    out["0x60C2 unit 1 s, exponent read-only"] = (fixed, fixed, "")
    ms = write("ref-60c2-ms-readonly.eds", ref + interpolation("ro", -3))
    out["0x60C2 unit 1 ms, exponent read-only"] = (ms, ms, "")
    slow = write("ref-slow-6080.eds", ref + var("6080", "Max motor speed", "0x0007", "rw", 0, "30000"))
    out["0x6080 max motor speed below the profile's limit"] = (slow, slow, "")
    fast = write("ref-fast-6080.eds", ref + var("6080", "Max motor speed", "0x0007", "rw", 0, "3000000"))
    out["0x6080 max motor speed above the profile's limit"] = (fast, fast, "")
    if (SHARED / "elmo-gold.dcf").is_file():
        elmo = (SHARED / "elmo-gold.dcf").read_text()
        geared = write("elmo-feed-4.dcf", set_key(elmo, "6092sub1", "DefaultValue", "4"))
        out["position factor group not 1:1 (Elmo 0x6092:01 = 4)"] = (geared, geared, "")
    wrong = write("ref-wrong-type.eds", set_key(ref, "1000", "DefaultValue", "0x00020191"))
    out["wrong device type (0x0191)"] = (wrong, wrong, "")
    no1017 = write("ref-no-1017.eds", drop(ref, "1017"))
    out["no 0x1017 heartbeat"] = (no1017, no1017, "")
    zeroerr_desc = (REPO / "drivers" / "zeroerr-edriver.yaml").read_text()
    zeroerr = str(HELD_OUT / "zeroerr-edriver-v1.5.eds")
    for cpr, agrees in (("524288", "differs"), ("10000", "agrees")):     # the profile says 10000
        out[f"encoder resolution fixed by the description, profile {agrees} (ZeroErr)"] = (
            zeroerr, zeroerr, zeroerr_desc.replace("counts_per_rev: profile ", f"counts_per_rev: {cpr} "))
    nanotec = (HELD_OUT / "nanotec-cl4-e-1-12.eds").read_text()
    old_fw = write("nanotec-before-fir-v2213.eds",     # 0x2039 with subindices 1-4 only
                   set_key(drop(nanotec, "2039sub5"), "2039sub0", "DefaultValue", "0x04"))
    out["Nanotec firmware before FIR-v2213: no 0x2039:05 'Actual current'"] = (old_fw, old_fw, "")
    if epos is not None:
        no6071 = write("epos4-no-6071.eds", drop(epos, "6071"))
        out["0x6071 missing on the input drive only (EPOS4)"] = (no6071, str(SHARED / "maxon-epos4.eds"), "")
        out["0x6071 missing on the output drive (EPOS4)"] = (str(SHARED / "maxon-epos4.eds"), no6071, "")
        epos_sdo = write("epos4-6060-sdo.eds", set_key(epos, "6060", "PDOMapping", "0"))
        out["0x6060 not mappable (EPOS4)"] = (epos_sdo, epos_sdo, "")
    return out


def profile_with(tmp: Path, eds_in: str, eds_out: str, desc: str) -> Path:
    text = (REPO / "profiles" / "cvt.yaml").read_text()
    text = text.replace("drive: drivers/cia402-servo.eds", "drive: DRIVE", 2)
    text = text.replace("drive: DRIVE", f"drive: {eds_in}", 1).replace("drive: DRIVE", f"drive: {eds_out}", 1)
    text = text.replace("period_s: 0.001                    # 1 kHz SYNC", "period_s: 0.002")
    if desc:
        (tmp / "drive-description.yaml").write_text(desc)
    p = tmp / "profile.yaml"
    p.write_text(text)
    return p


def starts(profile) -> tuple[bool, str]:
    """Start the profile's drives on the emulator serving their EDS; enable each in the
    mode its steps need and take samples. (True, "") or (False, why)."""
    channel = parse_bus(f"virtual:{uuid.uuid4().hex}").channel
    bench = EmulatedBench(PlantParams.from_dict(profile.simulation or {}, where="simulation"), seed=1)
    server = net = None
    profile_dir = str(Path(profile.path).parent)
    try:
        server = start_canopen_server(bench, "virtual", channel, profile_dir=profile_dir,
                                      eds={m.address: str(m.drive) for m in profile.motors.values()})
        net = CiA402Network(bus=f"virtual:{channel}", heartbeat_ms=500, timeout_s=1.0, sdo_timeout_s=0.2,
                            state_timeout_s=0.3, lockstep=True)
        net.open()
        drives = {}
        for name, m in profile.motors.items():
            drives[name] = net.add_drive(AxisConfig(name, m.address, str(m.drive), m.rated_current_a,
                                                    m.current_limit_a, m.speed_limit_rad_s, m.counts_per_rev,
                                                    extra={"profile_dir": profile_dir}))
        net.start(profile.bench.period_s)
        drives["in"].enable(Mode.VELOCITY)
        drives["out"].enable(Mode.TORQUE)
        drives["in"].set_setpoint(20.0)
        drives["out"].set_setpoint(0.1)
        for _ in range(30):
            net.sample()
        return True, ""
    except (GearbenchError, Exception) as exc:     # any failure to start is a verdict, recorded with its text
        return False, f"{type(exc).__name__}: {exc}"
    finally:
        if net is not None:
            net.close()
        if server is not None:
            server.stop()


def verdicts(tmp: Path, eds_in: str, eds_out: str, desc: str):
    profile = load_profile(profile_with(tmp, eds_in, eds_out, desc))
    report = check_profile(profile)
    ok, why = starts(profile)
    return not report.errors, ok, report, why


@pytest.mark.parametrize("path", VENDOR_FILES, ids=lambda p: p.name)
def test_validate_verdict_equals_start_on_vendor_files(tmp_path, path):
    valid, started, report, why = verdicts(tmp_path, str(path), str(path), "")
    assert valid == started, f"validate {'accepted' if valid else 'refused'} but start-up " \
                             f"{'ran' if started else 'failed: ' + why}\n" + "\n".join(report.errors)


VARIANT_EXPECTED = {      # the verdict itself (validate == start-up is checked for every one)
    "0x6060 not mappable (reference)": True,
    "manufacturer current mode -3, vendor objects, 0x6060 by SDO": True,
    "vendor current actual not mappable": False,
    "description cites an undefined source": False,
    "description names an object the EDS lacks": False,
    "description misspells a key": False,
    "0x60C2 unit 1 s, exponent writable": True,
    "0x60C2 unit 1 s, exponent read-only": False,
    "0x60C2 unit 1 ms, exponent read-only": True,
    "0x6080 max motor speed below the profile's limit": False,
    "0x6080 max motor speed above the profile's limit": True,
    # the description says the drive must read 1: the emulator plays it so, validate warns
    "position factor group not 1:1 (Elmo 0x6092:01 = 4)": True,
    "wrong device type (0x0191)": False,
    "no 0x1017 heartbeat": False,
    "0x6071 missing on the input drive only (EPOS4)": True,
    "0x6071 missing on the output drive (EPOS4)": False,
    "0x6060 not mappable (EPOS4)": True,
    "encoder resolution fixed by the description, profile differs (ZeroErr)": False,
    "encoder resolution fixed by the description, profile agrees (ZeroErr)": True,
    "Nanotec firmware before FIR-v2213: no 0x2039:05 'Actual current'": False,
}


@pytest.mark.parametrize("name", list(VARIANT_EXPECTED))
def test_validate_verdict_equals_start_on_synthetic_variants(tmp_path, name):
    cases = variants(tmp_path)
    if name not in cases:
        pytest.skip("needs ../shared/reference/vendor-eds/maxon-epos4.eds")
    valid, started, report, why = verdicts(tmp_path, *cases[name])
    assert valid == started, f"{name}: validate {'accepted' if valid else 'refused'} but start-up " \
                             f"{'ran' if started else 'failed: ' + why}\n" + "\n".join(report.errors)
    assert valid is VARIANT_EXPECTED[name], "\n".join(report.errors) or why
    if "factor group" in name:
        assert any("0x6092:01" in w and "expects 1" in w for w in report.warnings), report.warnings
