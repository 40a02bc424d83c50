"""``gearbench emulate`` in a separate process, over a real cross-process bus.

The bus is ``bus_for_tests()``: socketcan on $GEARBENCH_VCAN when set (CI with vcan),
else udp_multicast on a free port. Test ids and output name the bus used.
"""
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from canopen import Network
from canopen.profiles.p402 import BaseNode402

from conftest import emulator_command, start_emulator
from gearbench.drives.base import AxisConfig, Mode
from gearbench.drives.buses import bus_for_tests
from gearbench.drives.cia402 import CiA402Network

EDS = str(Path(__file__).resolve().parents[1] / "drivers" / "cia402-servo.eds")
BUS = bus_for_tests()
# .ci/vcan's software-emulated (TCG) guest runs Python 20-100x slower: fewer SYNCs per second
# for the emulated drives to keep up with, fewer samples, generous supervision timeouts
EMULATED = bool(os.environ.get("GEARBENCH_VCAN_EMULATED"))
SLOW_NET = dict(heartbeat_ms=500, timeout_s=20.0, sdo_timeout_s=10.0, state_timeout_s=10.0) if EMULATED else {}


@pytest.fixture(scope="module", params=[BUS], ids=[BUS.interface])
def emulator(request):
    bus = request.param
    print(f"\nCANopen tests over {bus}")
    proc = start_emulator(bus)
    yield bus, proc
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        proc.wait(10)


fixture_cmd = emulator_command


def test_independent_basenode402_client_turns_the_motor(emulator):
    """A plain canopen master, knowing only the EDS, runs node 1 in profile velocity."""
    bus, _ = emulator
    net = Network()
    net.connect(interface=bus.interface, channel=bus.channel, **bus.kwargs)   # python-can only
    try:
        node = BaseNode402(1, EDS)
        # these only bound waits; a software-emulated CI guest (.ci/vcan) runs Python ~20x slower
        scale = 5 if EMULATED else 1
        for name, seconds in (("TIMEOUT_CHECK_TPDO", 2.0), ("TIMEOUT_SWITCH_STATE_SINGLE", 4.0),
                              ("TIMEOUT_SWITCH_STATE_FINAL", 8.0), ("TIMEOUT_SWITCH_OP_MODE", 5.0)):
            setattr(node, name, seconds * scale)
        node.sdo.RESPONSE_TIMEOUT = 2.0 * scale
        net.add_node(node)
        node.nmt.state = "PRE-OPERATIONAL"
        node.tpdo.read()
        node.rpdo.read()
        for pdo, entries, trans in ((node.tpdo[1], ("Statusword", "Position actual value"), 1),
                                    (node.tpdo[2], ("Velocity actual value", "Current actual value"), 1),
                                    (node.tpdo[3], ("Modes of operation display",), 1),
                                    (node.rpdo[1], ("Controlword", "Modes of operation"), 255),
                                    (node.rpdo[2], ("Target velocity",), 255)):
            pdo.clear()
            for name in entries:
                pdo.add_variable(name)
            pdo.trans_type, pdo.enabled = trans, True
        node.tpdo.save()
        node.rpdo.save()
        node.setup_402_state_machine(read_pdos=False)
        for rpdo in node.rpdo.values():   # udp_multicast echoes our own RPDOs back (see ECOSYSTEM-NOTES)
            if rpdo.enabled and rpdo.on_message in net.subscribers.get(rpdo.cob_id, []):
                net.unsubscribe(rpdo.cob_id, rpdo.on_message)
        node.nmt.state = "OPERATIONAL"
        # SYNC by python-can's send_periodic (the kernel's BCM on socketcan); in a TCG guest the
        # emulator handles ~10-50 SYNCs/s, a faster SYNC would flood its receive queue
        sync_s = 0.05 if EMULATED else 0.005
        net.sync.start(sync_s)
        node.op_mode = "PROFILED VELOCITY"
        assert node.op_mode == "PROFILED VELOCITY"       # the setter only logs failures
        node.state = "OPERATION ENABLED"
        assert node.state == "OPERATION ENABLED"

        counts_per_rev = node.sdo[0x608F][1].raw
        rated_ma = node.sdo[0x6075].raw
        target_rad_s = 60.0
        node.rpdo[2]["Target velocity"].raw = round(target_rad_s * counts_per_rev / (2 * math.pi))
        node.rpdo[2].transmit()
        frames = []
        node.tpdo[1].add_callback(lambda m: frames.append(m["Position actual value"].raw))
        time.sleep(200 * sync_s)                           # 200 SYNCs = 0.2 s of drive time: settled
        n0 = len(frames)
        time.sleep(200 * sync_s)
        window = frames[n0:]
        current_a = node.tpdo[2]["Current actual value"].raw * rated_ma / 1000 / 1000
        speed = (window[-1] - window[0]) * 2 * math.pi / counts_per_rev / ((len(window) - 1) * 1e-3)
        print(f"BaseNode402 over {bus}: {len(window)} TPDO1 frames, speed {speed:.2f} rad/s, "
              f"current {current_a:.3f} A")
        assert len(window) > 20
        # lockstep: one 1 ms period per SYNC; frames lost on the bus would only make this larger
        assert speed == pytest.approx(target_rad_s, rel=0.03)
        assert node.tpdo[2]["Velocity actual value"].raw * 2 * math.pi / counts_per_rev == pytest.approx(
            target_rad_s, rel=0.05)
        assert 0.05 < current_a < 0.5                      # friction + viscous at 60 rad/s, not zero
        node.state = "SWITCH ON DISABLED"
    finally:
        net.sync.stop()
        net.disconnect()


def test_gearbench_master_streams_both_drives(emulator):
    bus, proc = emulator
    net = CiA402Network(bus=str(bus), **{"heartbeat_ms": 100, **SLOW_NET}, lockstep=True)
    with net:
        din = net.add_drive(AxisConfig("in", 1, EDS))
        dout = net.add_drive(AxisConfig("out", 2, EDS))
        net.start(1e-3)
        din.enable(Mode.VELOCITY)
        dout.enable(Mode.TORQUE)
        din.set_setpoint(80.0)
        n = 200 if EMULATED else 1500          # 0.2 s of drive time still settles the 80 rad/s step
        t0 = time.perf_counter()
        rows = [net.sample() for _ in range(n)]
        rate = n / (time.perf_counter() - t0)
        print(f"gearbench master over {bus}: {rate:.0f} samples/s of both drives, lost {net.lost_samples}")
        assert rows[-1]["in"].index == n + net.lost_samples
        assert net.lost_samples <= n // 100                 # honest count; loopback should lose ~none
        assert rows[-1]["in"].velocity_rad_s == pytest.approx(80.0, rel=0.05)
        status = fixture_cmd(proc, {"cmd": "status"})
        assert status["ok"] and status["drives"]["in"]["state"] == "OPERATION ENABLED"


def test_emulator_fault_option_reaches_master_as_benchfault(emulator):
    bus, proc = emulator
    net = CiA402Network(bus=str(bus), **{"heartbeat_ms": 100, **SLOW_NET}, lockstep=True)
    from gearbench.errors import BenchFault
    with net:
        din = net.add_drive(AxisConfig("in", 1, EDS))
        net.add_drive(AxisConfig("out", 2, EDS))
        net.start(1e-3)
        din.enable(Mode.VELOCITY)
        assert fixture_cmd(proc, {"cmd": "fault", "axis": "in", "code": 0x2310})["ok"]
        with pytest.raises(BenchFault, match=r"node 1 on .*EMCY 0x2310"):
            for _ in range(500):
                net.sample()
        din.reset_fault()
        assert din.state() == "SWITCH ON DISABLED"


def test_emulate_stops_cleanly_on_sigterm_and_rejects_bad_profile(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("simulation:\n  ratio: -3\n")
    r = subprocess.run([sys.executable, "-m", "gearbench", "emulate", str(bad), "--can", "virtual:x"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "bad.yaml" in r.stderr and "ratio" in r.stderr and "Traceback" not in r.stderr
    proc = subprocess.Popen([sys.executable, "-m", "gearbench", "emulate", "--can", "virtual:solo"],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready"
    proc.send_signal(signal.SIGINT)
    assert proc.wait(10) == 0


def test_emulated_world_runs_at_the_profiles_period(tmp_path):
    """The emulated world advances one bench period per SYNC: a 2 ms profile without a
    simulation.period_s gets a 2 ms plant (it once ran at the 1 ms default: time stretched,
    accelerations read 4x low, Kt 4x low); a contradicting simulation.period_s is refused."""
    from gearbench.commands.emulate import load_plant
    from gearbench.errors import ProfileError

    text = (Path(__file__).resolve().parents[1] / "profiles" / "cvt.yaml").read_text()
    p = tmp_path / "p.yaml"
    p.write_text(text.replace("period_s: 0.001                    # 1 kHz SYNC", "period_s: 0.002"))
    assert load_plant(str(p)).period_s == 0.002
    p.write_text(text.replace("period_s: 0.001                    # 1 kHz SYNC", "period_s: 0.002")
                 .replace("simulation:\n", "simulation:\n  period_s: 0.001\n", 1))
    with pytest.raises(ProfileError, match="simulation.period_s 0.001 differs from bench.period_s 0.002"):
        load_plant(str(p))
