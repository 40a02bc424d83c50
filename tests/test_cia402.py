"""gearbench's CiA 402 master against the emulated bench, in one process on the
``virtual`` bus (fast; the cross-process buses are in test_emulate_canopen.py)."""
import math
import time
import uuid

import pytest

from gearbench.drives.base import AxisConfig, Mode
from gearbench.drives.buses import BusSpec, parse_bus
from gearbench.drives.cia402 import CiA402Network, load_eds
from gearbench.drives.registry import network_class
from gearbench.drives.scaling import AxisUnits, unwrap_int32, wrap_int32
from gearbench.emulate.bench import EmulatedBench
from gearbench.emulate.canopen_server import start_canopen_server
from gearbench.errors import BenchFault, DriveError
from gearbench.sim import MotorParams, PlantParams

PERIOD_S = 1e-3


@pytest.fixture
def rig(request):
    """(bench, network) on a private virtual bus; drives 'in' (node 1) and 'out' (node 2)."""
    plant = getattr(request, "param", None) or PlantParams()
    channel = f"virtual:{uuid.uuid4().hex}"
    print(f"bus: {channel}")
    bench = EmulatedBench(plant, seed=1)
    server = start_canopen_server(bench, "virtual", parse_bus(channel).channel)
    # heartbeat 0.5 s: a loaded CI host must not turn a starved emulator thread into a false fault
    net = CiA402Network(bus=channel, heartbeat_ms=500, timeout_s=0.4, sdo_timeout_s=0.1, state_timeout_s=0.2,
                         lockstep=True)
    net.open()
    yield bench, net
    net.close()
    server.stop()


def start(net, in_limit_a=3.0):
    din = net.add_drive(AxisConfig("in", 1, "", current_limit_a=in_limit_a))
    dout = net.add_drive(AxisConfig("out", 2, ""))
    net.start(PERIOD_S)
    return din, dout


def test_paced_sync_keeps_the_wall_clock_period():
    """Against real drives SYNC must come every period (they latch on it): SYNC k goes out at
    k periods after the producer started, never before (a late producer catches up, sent late and
    counted, but never runs ahead), the samples come in order, and any slot never sent counts as lost."""
    channel = f"virtual:{uuid.uuid4().hex}"
    bench = EmulatedBench(PlantParams(), seed=1)
    server = start_canopen_server(bench, "virtual", parse_bus(channel).channel)
    try:
        with CiA402Network(bus=channel, heartbeat_ms=100, lockstep=False) as net:
            start(net)
            net.sample()
            samples = [net.sample() for _ in range(300)]
            end = time.perf_counter()
            idx = [s["in"].index for s in samples]
            due = net.sync_producer.t0 + idx[-1] * PERIOD_S      # when the last sample's SYNC was due
            assert end >= due - 1e-4                             # not answered before it was due
            assert all(b > a for a, b in zip(idx, idx[1:]))
            assert end <= due + 0.1                              # paced, not slower either
            assert net.lost_samples >= net.late_syncs   # every skipped slot is a lost sample
    finally:
        server.stop()


def test_registry_finds_the_family():
    assert network_class("cia402") is CiA402Network


def test_two_drives_stream_synchronous_samples_on_drive_time(rig):
    bench, net = rig
    din, dout = start(net)
    din.enable(Mode.VELOCITY)
    dout.enable(Mode.TORQUE)
    din.set_setpoint(50.0)
    dout.set_setpoint(0.2)
    rows = [net.sample() for _ in range(600)]
    idx = [r["in"].index for r in rows]
    assert idx == list(range(1, 601)) and [r["out"].index for r in rows] == idx
    assert rows[-1]["in"].time_s == pytest.approx(600 * PERIOD_S)
    assert net.lost_samples == 0
    last = rows[-200:]
    speed = (last[-1]["in"].position_rad - last[0]["in"].position_rad) / (199 * PERIOD_S)
    assert speed == pytest.approx(50.0, rel=0.02)            # the motor turns at the commanded speed
    assert last[-1]["in"].velocity_rad_s == pytest.approx(50.0, rel=0.05)
    out_current = sum(r["out"].current_a for r in last) / len(last)
    assert out_current == pytest.approx(0.2, abs=0.01)       # current mode: A in, A out
    assert last[-1]["out"].velocity_rad_s > last[0]["out"].velocity_rad_s > 10  # and it accelerates
    assert bench.drives["out"].state == "OPERATION ENABLED"


def test_setpoint_latched_on_the_next_sync(rig):
    bench, net = rig
    din, _ = start(net)
    din.enable(Mode.VELOCITY)
    net.sample()
    din.set_setpoint(20.0)
    assert bench.drives["in"].target_velocity_rad_s == 0.0   # RPDO2 is synchronous: waits for SYNC
    net.sample()
    assert bench.drives["in"].target_velocity_rad_s == pytest.approx(20.0, abs=1e-3)


def test_overcurrent_faults_with_emcy_then_reset(rig):
    bench, net = rig
    din, dout = start(net, in_limit_a=0.2)                   # profile limit -> drive 0x6073
    din.enable(Mode.VELOCITY)
    din.set_setpoint(300.0)                                  # the velocity loop asks far more than 0.2 A
    with pytest.raises(BenchFault, match=r"node 1 .*EMCY 0x2310"):
        for _ in range(200):
            net.sample()
    assert din.state() == "FAULT" and bench.drives["in"].error_code == 0x2310
    assert din.emcy and din.emcy[-1].code == 0x2310
    with pytest.raises(DriveError, match="FAULT"):
        din.enable(Mode.VELOCITY)
    din.reset_fault()
    assert din.state() == "SWITCH ON DISABLED"
    din.enable(Mode.VELOCITY)                                # usable again
    assert din.state() == "OPERATION ENABLED"


def test_quick_stop_brakes_and_disable_removes_power(rig):
    bench, net = rig
    din, _ = start(net)
    din.enable(Mode.VELOCITY)
    din.set_setpoint(100.0)
    for _ in range(300):
        net.sample()
    din.quick_stop()
    speeds = [net.sample()["in"].velocity_rad_s for _ in range(300)]
    assert speeds[0] > 50 and abs(speeds[-1]) < 1.0
    assert din.state() == "QUICK STOP ACTIVE"
    din.disable()
    assert din.state() == "SWITCH ON DISABLED"
    assert bench.drives["in"].command() == ("off", 0.0)


def test_injected_fault_reaches_caller_and_drives_are_stopped(rig):
    bench, net = rig
    din, dout = start(net)
    din.enable(Mode.VELOCITY)
    dout.enable(Mode.VELOCITY)
    assert '"ok": true' in bench.handle_control_line('{"cmd": "fault", "axis": "out", "code": 8992, "at_s": 0.05}')
    with pytest.raises(BenchFault, match=r"node 2 .*EMCY 0x2320"):
        for _ in range(200):
            net.sample()
    assert bench.drives["in"].state == "SWITCH ON DISABLED"  # the healthy drive was disabled too


def test_lost_pdos_are_counted_never_filled_in(rig):
    bench, net = rig
    start(net)
    bench.handle_control_line('{"cmd": "drop", "rate": 0.02}')
    rows = [net.sample() for _ in range(300)]
    idx = [r["in"].index for r in rows]
    assert all(b > a for a, b in zip(idx, idx[1:]))
    assert net.lost_samples > 0 and idx[-1] == len(rows) + net.lost_samples


def test_drive_that_stops_answering_is_named(rig):
    bench, net = rig
    start(net)
    net.sample()
    bench.handle_control_line('{"cmd": "mute", "axis": "out"}')
    with pytest.raises(BenchFault, match=r"node 2 on virtual:"):
        for _ in range(2000):
            net.sample()


def test_absent_node_gives_sdo_timeout_naming_node_and_bus(rig):
    _, net = rig
    net.add_drive(AxisConfig("in", 7, ""))
    with pytest.raises(DriveError, match=r"drive 'in' \(node 7 on virtual:.*no SDO answer"):
        net.start(PERIOD_S)


@pytest.mark.parametrize("rig", [PlantParams(motor_in=MotorParams(counts_per_rev=4096))], indirect=True)
def test_profile_scaling_mismatch_is_refused(rig):
    _, net = rig
    net.add_drive(AxisConfig("in", 1, "", counts_per_rev=10000))
    with pytest.raises(DriveError, match=r"4096 counts/rev.*counts_per_rev: 10000"):
        net.start(PERIOD_S)


def test_malformed_eds_names_file_and_field(tmp_path):
    from gearbench.emulate.canopen_server import DEFAULT_EDS
    text = open(DEFAULT_EDS).read()
    missing = tmp_path / "no-statusword.eds"
    missing.write_text(text.replace("[6041]", "[6F41]"))
    with pytest.raises(DriveError, match=r"no-statusword.eds: 0x6041: statusword missing"):
        load_eds(str(missing), 1)
    broken = tmp_path / "broken.eds"
    broken.write_text(text.replace("DataType=0x0006\nAccessType=rww", "DataType=zz\nAccessType=rww", 1))
    with pytest.raises(DriveError, match=r"broken.eds: malformed EDS"):
        load_eds(str(broken), 1)
    with pytest.raises(DriveError, match="not found"):
        load_eds(str(tmp_path / "nope.eds"), 1)


def test_scaling_round_trips_and_wraps():
    # a CiA 402 axis: 10,000 counts/rev, velocity in inc/s, current in per-mille of 2 A rated
    s = AxisUnits(counts_per_rev=10000, velocity_rad_s_per_unit=2 * math.pi / 10000,
                  current_a_per_unit=2.0 / 1000, torque_a_per_unit=2.0 / 1000)
    assert s.position_rad(s.position_counts(1.0)) == pytest.approx(1.0, abs=s.rad_per_count)
    assert s.current_raw(1.0) == 500 and s.current_a(500) == 1.0
    assert s.velocity_raw(2 * math.pi) == 10000
    assert s.current_raw(1e6) == 2**15 - 1 and s.torque_raw(-1e6) == -2**15   # INTEGER16 clamps
    assert unwrap_int32(2**31 - 10, wrap_int32(2**31 + 5)) == 2**31 + 5


def test_bus_strings():
    assert parse_bus("udp_multicast:239.1.2.3:5000") == BusSpec("udp_multicast", "239.1.2.3", 5000)
    assert parse_bus("udp_multicast:[ff15::1]:5000") == BusSpec("udp_multicast", "ff15::1", 5000)
    assert parse_bus("socketcan:vcan0") == BusSpec("socketcan", "vcan0")
    assert str(BusSpec("udp_multicast", "239.1.2.3", 5000)) == "udp_multicast:239.1.2.3:5000"
    assert parse_bus("pcan:PCAN_USBBUS1") == BusSpec("pcan", "PCAN_USBBUS1")   # any python-can interface
    for bad in ("vcan0", "pcann:1", "udp_multicast:239.1.2.3:99999"):
        with pytest.raises(DriveError, match="bus"):
            parse_bus(bad)
