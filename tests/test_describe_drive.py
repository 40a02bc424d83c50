"""Drive descriptions as a bench engineer meets them: `gearbench describe-drive` drafts one
from the vendor's EDS (and the live drive, probed over the bus), `validate` says where it
looked and what matched, and every description problem is named once with file:line."""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from test_validate_start import SHARED, VENDOR_CURRENT_DESC, VENDOR_FILES, profile_with, variants

from gearbench.drives.buses import free_udp_port
from gearbench.drives.description import resolve
from gearbench.drives.drafting import draft
from gearbench.emulate.bench import EmulatedBench
from gearbench.emulate.canopen_server import DEFAULT_EDS, start_canopen_server
from gearbench.sim import PlantParams

REPO = Path(__file__).resolve().parents[1]


def gearbench(*args, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "gearbench", *map(str, args)], capture_output=True, text=True,
                          timeout=180, cwd=cwd, env=dict(os.environ, PYTHONUNBUFFERED="1"))


def test_bad_input_is_one_line_and_exit_2(tmp_path):
    bad = tmp_path / "bad.eds"
    bad.write_text("[FileInfo]\nbroken")
    for args in ((tmp_path / "absent.eds",), (bad,), (DEFAULT_EDS, "--probe")):
        r = gearbench("describe-drive", *args)
        assert r.returncode == 2 and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) <= 2, r.stderr


@pytest.mark.parametrize("path", VENDOR_FILES, ids=lambda p: p.name)
def test_draft_from_every_vendor_file_is_yaml_naming_candidates_and_todos(path):
    m = resolve(str(path), descriptions=[])
    text = draft(m)
    doc = yaml.safe_load(text)
    assert doc["family"] == "cia402" and doc["match"]["file_names"] == [path.name]
    assert "# missing CiA 301/402 objects gearbench needs:" in text
    if m.fatal:      # what the EDS cannot say is a TODO, never a guess
        assert "TODO" in text


def test_draft_left_with_todos_is_refused_naming_each_line(tmp_path):
    eds = str(SHARED / "technosoft-ipos.eds")
    if not Path(eds).is_file():
        pytest.skip("needs ../shared/reference/vendor-eds")
    r = gearbench("describe-drive", eds, "-o", tmp_path / "ipos.yaml")
    assert r.returncode == 0 and "TODOs to fill" in r.stderr
    m = resolve(eds, profile_dir=tmp_path)
    text = "\n".join(str(p) for p in m.fatal)
    assert re.search(r"ipos\.yaml:\d+: velocity\.unit: still a TODO", text), text
    assert re.search(r"ipos\.yaml:\d+: sources\.manual: still a TODO", text), text


def test_probe_reads_the_live_drive_over_udp_multicast(tmp_path):
    """The emulator plays an EPOS4 (rated current 1 A = 1000 mA, modes from its 0x6502);
    the draft carries what the drive answered, cited as the 'probe' source."""
    eds = SHARED / "maxon-epos4.eds"
    if not eds.is_file():
        pytest.skip("needs ../shared/reference/vendor-eds")
    port = free_udp_port()
    server = start_canopen_server(EmulatedBench(PlantParams(), seed=1), "udp_multicast", "239.74.163.2",
                                  port=port, eds={1: str(eds), 2: str(eds)})
    try:
        r = gearbench("describe-drive", eds, "--probe", "--can", f"udp_multicast:239.74.163.2:{port}", "--node", 1)
    finally:
        server.stop()
    assert r.returncode == 0, r.stderr
    assert "probe: \"read from node 1 on udp_multicast:239.74.163.2:" in r.stdout
    assert "0x3001:01 'Nominal current': UNSIGNED32, rww, PDO-mappable, EDS default 5000, drive reads 1000" in r.stdout
    doc = yaml.safe_load(r.stdout)
    assert doc["supported_modes"] == {"modes": [1, 3, 6, 8, 9, 10], "source": "probe 0x6502"}
    silent = gearbench("describe-drive", eds, "--probe", "--can", f"udp_multicast:239.74.163.2:{free_udp_port()}",
                       "--node", 5, "--timeout", 0.05)
    assert silent.returncode == 3 and "no SDO answer" in silent.stderr and "Traceback" not in silent.stderr


def filled(draft_text: str) -> str:
    """What the engineer writes over the TODOs of the manufacturer-current-mode drive, from
    its (synthetic) manual: the current in mA, mode -3 with its setpoint 0x2201 in mA."""
    doc = yaml.safe_load(draft_text)
    doc["sources"]["manual"] = "the (synthetic) firmware manual of the test's variant drive: mode -3, mA"
    doc["velocity"] = {"unit": "inc/s", "source": "manual"}
    doc["current"] = {"object": "0x2200", "unit": "mA", "source": "eds [2200]; manual"}
    doc["torque"] = {"mode": -3, "setpoint": "0x2201", "unit": "mA", "source": "manual"}
    return yaml.safe_dump(doc, sort_keys=False)


def test_manufacturer_current_mode_drive_is_drafted_then_validates(tmp_path):
    eds = variants(tmp_path)["manufacturer current mode -3, vendor objects, 0x6060 by SDO"][0]
    text = draft(resolve(eds, descriptions=[]))
    assert "0x2200 'Current actual value (mA)': INTEGER32, ro, PDO-mappable" in text
    assert "0x2201 'Current mode setting value': INTEGER32, rww, PDO-mappable" in text
    assert "0x6060 modes of operation is not PDO-mappable: gearbench writes it by SDO" in text
    (tmp_path / "drive.yaml").write_text(filled(text))
    r = gearbench("validate", profile_with(tmp_path, eds, eds, ""))
    assert r.returncode == 0, r.stderr
    assert "out: modes torque -3 (manufacturer mode)" in r.stdout
    assert "torque setpoint 0x2201 'Current mode setting value' in mA" in r.stdout
    assert "0x6060 written by SDO per segment" in r.stdout
    assert re.search(r"matched by vendor id 0x00000000 \+ product code 0x00000402", r.stdout)


def test_description_problems_are_named_once_with_line_and_did_you_mean(tmp_path):
    eds = variants(tmp_path)["manufacturer current mode -3, vendor objects, 0x6060 by SDO"][0]
    bad = VENDOR_CURRENT_DESC.replace("setpoint:", "setpiont:").replace("source: eds [2200]; manual",
                                                                        "source: manaul")
    r = gearbench("validate", profile_with(tmp_path, eds, eds, bad))
    assert r.returncode == 2 and "Traceback" not in r.stderr
    lines = [ln for ln in r.stderr.splitlines() if "drive-description.yaml" in ln]
    misspelt = [ln for ln in lines if "torque.setpiont" in ln]
    assert len(misspelt) == 1 and "did you mean 'setpoint'?" in misspelt[0], r.stderr
    assert re.search(r"drive-description\.yaml:\d+: torque\.setpiont", misspelt[0])
    source = [ln for ln in lines if "current.source" in ln]
    assert len(source) == 1 and "'manaul' is not a source defined under 'sources:' (did you mean 'manual'?)" \
        in source[0], r.stderr


def test_station_drivers_folder_is_searched_and_validate_says_where(tmp_path):
    """STATION/profiles/p.yaml with the description in STATION/drivers/ and the EDS elsewhere:
    found there (not ignored), and validate prints the folders and what matched."""
    eds = variants(tmp_path)["manufacturer current mode -3, vendor objects, 0x6060 by SDO"][0]
    station = tmp_path / "station"
    (station / "profiles").mkdir(parents=True)
    (station / "drivers").mkdir()
    (station / "drivers" / "my-servo.yaml").write_text(VENDOR_CURRENT_DESC)
    p = profile_with(tmp_path, eds, eds, "")
    (station / "profiles" / "p.yaml").write_text(p.read_text())
    r = gearbench("validate", station / "profiles" / "p.yaml", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert f"looked for in: {station / 'profiles'}, {station / 'drivers'}" in r.stdout
    assert f"{station / 'drivers' / 'my-servo.yaml'} (matched by vendor id 0x00000000 + product code 0x00000402)" \
        in r.stdout


def test_identity_mismatch_is_refused_unless_the_description_says_why(tmp_path):
    eds = variants(tmp_path)["manufacturer current mode -3, vendor objects, 0x6060 by SDO"][0]
    by_name = VENDOR_CURRENT_DESC.replace("  vendor_id: 0x00000000\n  product_codes: [0x402]\n",
                                          "  vendor_id: 0x00000000\n  product_codes: [0x999]\n"
                                          "  file_names: [\"vendor-current-mode.eds\"]\n")
    r = gearbench("validate", profile_with(tmp_path, eds, eds, by_name))
    assert r.returncode == 2 and "matched by file name only, but the EDS says vendor id 0x00000000 + product " \
                                 "code 0x00000402, the description vendor id 0x00000000 + product code 0x00000999" \
                                 in r.stderr, r.stderr
    explained = by_name.replace("  file_names:", "  why: \"the 0x402 power stage runs the same firmware\"\n"
                                                 "  file_names:")
    r = gearbench("validate", profile_with(tmp_path, eds, eds, explained))
    assert r.returncode == 0, r.stderr


def test_supported_modes_against_the_eds_0x6502_is_named(tmp_path):
    conflict = VENDOR_CURRENT_DESC + "supported_modes:\n  modes: [3, 9, 10]\n  source: manual\n"
    eds = variants(tmp_path)["manufacturer current mode -3, vendor objects, 0x6060 by SDO"][0]
    r = gearbench("validate", profile_with(tmp_path, eds, eds, conflict))
    assert r.returncode == 2
    assert re.search(r"0x6502 'Supported drive modes': .*drive-description\.yaml:\d+ says modes \[3, 9, 10\] but "
                     r"the EDS's 0x6502 default says \[3, 9\]", r.stderr), r.stderr


def test_sim_says_which_bus_it_uses_instead_of_the_profiles(tmp_path):
    from gearbench.profile import load_profile
    from gearbench.emulate.launch import SimBench

    text = (REPO / "profiles" / "cvt.yaml").read_text().replace(
        "interface: udp_multicast", "interface: socketcan").replace("channel: 239.74.163.2", "channel: can9")
    (tmp_path / "p.yaml").write_text(text)
    (tmp_path / "drivers").mkdir()
    (tmp_path / "drivers" / "cia402-servo.eds").write_text(Path(DEFAULT_EDS).read_text())
    sb = SimBench(load_profile(tmp_path / "p.yaml"))
    sb.bus_options = dict(interface="udp_multicast", channel="239.74.163.2", port=43999, lockstep=True)
    assert sb.substitution() == ("--sim: the emulated drives are on udp_multicast:239.74.163.2:43999 (a private "
                                 "port on this host), not on the profile's bus socketcan:can9; the profile's bus "
                                 "is not used")


@pytest.mark.slow
def test_manufacturer_current_mode_drive_runs_on_sim_with_kt_within_0_1_pct(tmp_path):
    """Done-when: a manufacturer-current-mode drive (mode -3, vendor current objects in mA,
    0x6060 by SDO), described from describe-drive's draft, passes `run --sim`."""
    from conftest import assert_claimed_accuracy
    from gearbench.api import run_profile
    from gearbench.profile import load_profile
    from gearbench.sim.truth import simulation_truth

    eds = variants(tmp_path)["manufacturer current mode -3, vendor objects, 0x6060 by SDO"][0]
    (tmp_path / "drive.yaml").write_text(filled(draft(resolve(eds, descriptions=[]))))
    path = profile_with(tmp_path, eds, eds, "")
    path.write_text(path.read_text().replace("period_s: 0.002", "period_s: 0.001").replace(   # the shipped 1 kHz
        "    channel: 239.74.163.2\n", "    channel: 239.74.163.2\n    options: {heartbeat_ms: 500, timeout_s: 3.0}\n", 1))
    profile = load_profile(path)
    result = run_profile(str(path), sim=True, out_dir=tmp_path / "run", serial="M3", yes=True,
                         db=tmp_path / "station.sqlite")
    assert result["status"] == "passed", result.get("reason")
    truth = simulation_truth(profile.simulation, result["efficiency"])
    for m in ("in", "out"):
        err = 100 * (result["motors"][m]["Kt"] / truth["motors"][m]["Kt"] - 1)
        print(f"manufacturer-current-mode drive, motor {m}: Kt {result['motors'][m]['Kt']:.6f} N m/A, "
              f"truth {truth['motors'][m]['Kt']:.6f}, error {err:+.4f} %")
        assert abs(err) <= 0.1
    assert_claimed_accuracy(result, profile.simulation)
