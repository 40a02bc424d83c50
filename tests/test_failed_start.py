"""A bench that does not start (no drive answers) leaves a record like any run:
nothing moved, but result.json, junit.xml and the station database say so."""
import json
import sqlite3
import subprocess
import sys
import uuid
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_drives_that_do_not_answer_are_a_recorded_fault(tmp_path):
    text = (REPO / "profiles" / "motors-only.yaml").read_text()
    text = text.replace("interface: udp_multicast", "interface: virtual", 1)
    text = text.replace("channel: 239.74.163.2", f"channel: nobody-{uuid.uuid4().hex}", 1)  # nobody on this bus
    text = text.replace("drive: drivers/", f"drive: {REPO}/drivers/")
    profile = tmp_path / "no-drives.yaml"
    profile.write_text(text)
    out = tmp_path / "run"
    cp = subprocess.run([sys.executable, "-m", "gearbench", "run", str(profile), "--yes", "--serial", "SN-DEAD",
                         "--out", str(out), "--quiet"], capture_output=True, text=True, timeout=120)
    assert cp.returncode == 3, cp.stderr
    assert "Traceback" not in cp.stderr and "no SDO answer" in cp.stderr
    result = json.loads((out / "result.json").read_text())
    assert result["status"] == "fault" and result["exit_code"] == 3 and not result["passed"]
    assert "no SDO answer" in result["reason"] and result["samples"] == 0
    assert 'failures="' in (out / "junit.xml").read_text() or "error" in (out / "junit.xml").read_text()
    with sqlite3.connect(tmp_path / "station.sqlite") as db:
        rows = db.execute("SELECT * FROM runs").fetchall()
    assert len(rows) == 1
