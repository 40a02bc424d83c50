"""A tester PC that dies stops its drives: the master produces a heartbeat, each real
drive watches it (CiA 301 0x1016) and quick-stops on its loss (CiA 402 0x6007 = 3)."""
import json
import signal
import subprocess
import sys
import textwrap
import time
import uuid

import pytest

from gearbench.drives.base import AxisConfig, Mode
from gearbench.drives.buses import bus_for_tests, parse_bus
from gearbench.drives.cia402 import CiA402Network
from gearbench.emulate.bench import EmulatedBench
from gearbench.emulate.canopen_server import EMCY_HEARTBEAT, start_canopen_server
from gearbench.sim import PlantParams


def _wait_for(predicate, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return predicate()


@pytest.fixture
def paced_rig():
    channel = f"virtual:{uuid.uuid4().hex}"
    bench = EmulatedBench(PlantParams(), seed=1)
    server = start_canopen_server(bench, "virtual", parse_bus(channel).channel)
    yield bench, server, channel
    server.stop()


def test_drives_quick_stop_when_the_masters_heartbeat_stops(paced_rig):
    bench, server, channel = paced_rig
    net = CiA402Network(bus=channel, heartbeat_ms=100, lockstep=False, master_timeout_ms=300,
                        timeout_s=2.0, sdo_timeout_s=1.0, state_timeout_s=1.0)
    with net:
        din = net.add_drive(AxisConfig("in", 1, ""))
        net.add_drive(AxisConfig("out", 2, ""))
        net.start(1e-3)
        watch = net.supervision()["if_the_master_dies"]
        assert watch == {m: "quick stop (0x6007 = 3) after 300 ms without the master's heartbeat"
                         for m in ("in", "out")}
        node = server.nodes[0]
        assert node.raw(0x1016, 1) == (127 << 16) | 300 and node.raw(0x6007) == 3
        din.enable(Mode.VELOCITY)
        din.set_setpoint(30.0)
        for _ in range(600):          # 0.6 s paced, twice the consumer time: a live master trips nothing
            net.sample()
        assert bench.drive(1).state == "OPERATION ENABLED"
        net._master_heartbeat.stop()  # the PC "dies": no heartbeat, no SYNC, no command
        assert _wait_for(lambda: bench.drive(1).state != "OPERATION ENABLED", 3.0), bench.drive(1).state
        assert bench.drive(1).state in ("QUICK STOP ACTIVE", "SWITCH ON DISABLED")
        assert _wait_for(lambda: any(e.code == EMCY_HEARTBEAT for e in din.emcy), 2.0)
        net._master_heartbeat = None
    # an orderly end gives the consumer slot back: a drive left alone is not "master lost"
    assert server.nodes[0].raw(0x1016, 1) == 0 and server.nodes[1].raw(0x1016, 1) == 0


def test_lockstep_does_not_arm_the_drives(paced_rig):
    bench, server, channel = paced_rig
    with CiA402Network(bus=channel, heartbeat_ms=100, lockstep=True, timeout_s=2.0,
                       sdo_timeout_s=1.0) as net:
        net.add_drive(AxisConfig("in", 1, ""))
        net.add_drive(AxisConfig("out", 2, ""))
        net.start(1e-3)
        assert server.nodes[0].raw(0x1016, 1) == 0
        assert net.supervision()["if_the_master_dies"]["in"].startswith("not armed (lockstep")


MASTER = textwrap.dedent("""
    import sys, time
    from gearbench.drives.base import AxisConfig, Mode
    from gearbench.drives.cia402 import CiA402Network
    net = CiA402Network(bus=sys.argv[1], heartbeat_ms=100, lockstep=False, master_timeout_ms=1000,
                        timeout_s=3.0, sdo_timeout_s=2.0, state_timeout_s=3.0)
    net.open()
    din = net.add_drive(AxisConfig("in", 1, ""))
    net.add_drive(AxisConfig("out", 2, ""))
    net.start(1e-3)
    din.enable(Mode.VELOCITY)
    print("enabled", flush=True)
    while True:            # alive: only the heartbeat task talks (no SYNC load on a busy test host)
        time.sleep(1)
""")


def test_sigkill_of_the_tester_stops_the_drives_within_the_consumer_time():
    """The real case: the master process is killed (-9) while a drive runs; the drive,
    in another process, sees the heartbeat stop and quick-stops by itself."""
    bus = bus_for_tests()
    emulator = subprocess.Popen([sys.executable, "-m", "gearbench", "emulate", "--can", str(bus)],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    master = None
    try:
        assert emulator.stdout.readline().strip() == "ready", emulator.stderr.read()
        master = subprocess.Popen([sys.executable, "-c", MASTER, str(bus)], stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True)
        line = master.stdout.readline().strip()
        assert line == "enabled", master.stderr.read()

        def state():
            emulator.stdin.write(json.dumps({"cmd": "status"}) + "\n")
            emulator.stdin.flush()
            return json.loads(emulator.stdout.readline())["drives"]["in"]["state"]

        assert state() == "OPERATION ENABLED"
        time.sleep(3.0)                           # 3 consumer times: a live master trips nothing
        assert state() == "OPERATION ENABLED"
        master.send_signal(signal.SIGKILL)
        master.wait(10)
        killed = time.monotonic()
        assert _wait_for(lambda: state() != "OPERATION ENABLED", 10.0)
        print(f"{bus}: drive left OPERATION ENABLED {time.monotonic() - killed:.2f} s after SIGKILL "
              f"(consumer time 1.0 s): {state()}")
        assert state() in ("QUICK STOP ACTIVE", "SWITCH ON DISABLED")
    finally:
        if master is not None and master.poll() is None:
            master.kill()
        emulator.send_signal(signal.SIGTERM)
        emulator.wait(10)


# ----------------------------------------------------------------- Modbus TCP
def test_modbus_watchdog_quick_stops_a_drive_whose_master_went_quiet():
    """The map's comm_timeout register: armed against a free-running (real-time) drive,
    requests keep it fed; when they stop, the drive quick-stops by itself."""
    from pathlib import Path

    from gearbench.drives.modbus import ModbusNetwork
    from gearbench.emulate.modbus_server import start_modbus_server

    generic = str(Path(__file__).resolve().parents[1] / "drivers" / "generic-modbus-servo.yaml")
    bench = EmulatedBench(PlantParams(), seed=1)
    handle = start_modbus_server(bench, port=0, register_map=generic, lockstep=False)
    try:
        net = ModbusNetwork(port=handle.port, lockstep=False, timeout_s=5.0, master_timeout_ms=300)
        net.open()
        din = net.add_drive(AxisConfig("in", 1, generic))
        net.add_drive(AxisConfig("out", 2, generic))
        net.start(1e-3)
        assert net.supervision()["if_the_master_dies"]["in"] == "quick stop after 300 ms without a request"
        assert handle.watchdog_s == {1: pytest.approx(0.3), 2: pytest.approx(0.3)}
        din.enable(Mode.VELOCITY)
        din.set_setpoint(20.0)
        t_end = time.monotonic() + 0.9                  # 3 watchdog times of a live master
        while time.monotonic() < t_end:
            net.sample()
        assert bench.drive(1).state == "OPERATION ENABLED" and handle.watchdog_trips == 0
        # the master goes quiet (its process hangs or dies): no request any more
        assert _wait_for(lambda: bench.drive(1).state != "OPERATION ENABLED", 3.0)
        assert bench.drive(1).state in ("QUICK STOP ACTIVE", "SWITCH ON DISABLED")
        net.close()                                      # an orderly end disarms
        assert handle.watchdog_s[1] == 0.0
    finally:
        handle.stop()


def test_modbus_map_without_a_watchdog_is_named():
    from pathlib import Path

    from gearbench.drives.modbus import ModbusNetwork
    from gearbench.emulate.modbus_server import start_modbus_server

    acme = str(Path(__file__).resolve().parents[1] / "drivers" / "acme-ax2-modbus.yaml")
    bench = EmulatedBench(PlantParams(), seed=1)
    handle = start_modbus_server(bench, port=0, register_map=acme, lockstep=False)
    try:
        with ModbusNetwork(port=handle.port, lockstep=False, timeout_s=5.0) as net:
            net.add_drive(AxisConfig("in", 1, acme))
            net.start(1e-3)
            assert net.supervision()["if_the_master_dies"]["in"].startswith("not armed: ")
    finally:
        handle.stop()
