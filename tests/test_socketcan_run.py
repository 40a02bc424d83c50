"""``gearbench run`` of profiles/motors-only.yaml over socketcan on a real vcan (lockstep).

A module of its own, run by ``.ci/vcan`` before ``test_socketcan.py``: ``--sim`` puts
its own emulated nodes 1 and 2 on the bus, so no other emulator may be on it (the
module-scoped emulator of ``test_socketcan.py`` would answer every SDO a second
time). Skips, bounds and the emulated-guest settings are ``test_socketcan``'s.
"""
from __future__ import annotations

import json
import subprocess
import sys

import pytest
import yaml

from test_socketcan import BUS, EMULATED, ID, NET, REPO, VCAN, deadline, vcan   # noqa: F401 (fixtures)


@pytest.mark.parametrize("bus", [BUS], ids=[ID])
def test_gearbench_run_motors_only_over_socketcan(vcan, tmp_path, bus):   # noqa: F811 (the fixture)
    """``gearbench run profiles/motors-only.yaml --sim`` with the profile's bus on vcan (lockstep)."""
    doc = yaml.safe_load((REPO / "profiles" / "motors-only.yaml").read_text())
    doc["bench"]["bus"].update(interface="socketcan", channel=VCAN)
    if EMULATED:   # the profile's own supervision keys: emulated drives in a TCG guest answer slowly
        doc["bench"]["bus"]["options"] = {k: NET[k] for k in ("heartbeat_ms", "timeout_s", "sdo_timeout_s",
                                                               "state_timeout_s")}
    # short: one 0.5 s multisine period per run (tones 2-12 Hz, amplitude within the current
    # limit with the disk): ~2300 lockstep samples, affordable in an emulated guest
    doc["waveforms"]["excite"].update(period_s=0.5, f_min_hz=2, f_max_hz=12, amplitude=60, fade_in_s=0.1)
    for step in doc["steps"]:
        step["duration_s"] = 0.5
    for m in doc["motors"].values():
        m["drive"] = str(REPO / m["drive"])
    profile = tmp_path / "motors-only-vcan.yaml"
    profile.write_text(yaml.safe_dump(doc, sort_keys=False))
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "gearbench", "run", str(profile), "--sim", "--yes", "--out", str(out)],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode in (0, 1), r.stdout[-2000:] + r.stderr[-2000:]   # 1 = a limit failed: still a full run
    result = json.loads((out / "result.json").read_text())
    assert result["lost_samples"] == 0 and result["samples"] > 4 * 450
    assert set(result["motors"]) == {"in", "out"}
    for name, m in result["motors"].items():
        assert m["Kt"] == pytest.approx(doc["simulation"]["motors"][name]["Kt"], rel=0.005)   # the run-accuracy claim: well under 0.5 %
    print(f"gearbench run over {BUS}: exit {r.returncode}, {result['samples']} samples, "
          f"Kt in {result['motors']['in']['Kt']:.5f} out {result['motors']['out']['Kt']:.5f}, "
          f"wall {result.get('wall_time_s', 0):.0f} s")
