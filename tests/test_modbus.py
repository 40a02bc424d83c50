"""gearbench's Modbus TCP driver against the emulated bench (in-process server thread).

Every test binds its own free port (port 0), so concurrent runs cannot cross-talk.
"""
from __future__ import annotations

import socket
from pathlib import Path

import numpy as np
import pytest
import yaml

from gearbench.drives.base import AxisConfig, Mode
from gearbench.drives.modbus import ModbusNetwork
from gearbench.drives.registry import network_class
from gearbench.emulate.bench import EmulatedBench
from gearbench.emulate.cia402_axis import OVERCURRENT_SAMPLES
from gearbench.emulate.modbus_server import start_modbus_server
from gearbench.errors import BenchFault, DriveError
from gearbench.sim.params import PlantParams
from gearbench.sim.world import BenchWorld

DRIVERS = Path(__file__).resolve().parents[1] / "drivers"
GENERIC = str(DRIVERS / "generic-modbus-servo.yaml")
ACME = str(DRIVERS / "acme-ax2-modbus.yaml")
PERIOD_S = 1e-3


@pytest.fixture(scope="module", autouse=True)
def _compiled_physics():
    # the first step compiles the numba kernel (seconds on a cold cache); keep it out of request timeouts
    BenchWorld(PlantParams()).step()


def make_bench() -> EmulatedBench:
    return EmulatedBench(PlantParams())


@pytest.fixture
def bench():
    return make_bench()


@pytest.fixture
def server(bench):
    handle = start_modbus_server(bench, port=0, register_map=GENERIC, lockstep=True)
    yield handle
    handle.stop()


def open_network(port, description=GENERIC, *, lockstep=True, timeout_s=5.0, **limits):
    net = ModbusNetwork(port=port, lockstep=lockstep, timeout_s=timeout_s)
    net.open()
    drive_in = net.add_drive(AxisConfig("in", 1, description, **limits))
    drive_out = net.add_drive(AxisConfig("out", 2, description, **limits))
    net.start(PERIOD_S)
    return net, drive_in, drive_out


def run(net, n):
    return [net.sample() for _ in range(n)]


def test_registry_finds_the_modbus_family():
    assert network_class("modbus") is ModbusNetwork


def test_lockstep_streams_both_drives_one_count_per_sample(bench, server):
    net, d_in, d_out = open_network(server.port)
    with net:
        d_in.enable(Mode.VELOCITY)
        d_out.enable(Mode.TORQUE)
        d_in.set_setpoint(30.0)
        d_out.set_setpoint(0.3)
        samples = run(net, 400)
        last_bench = bench.latest
    idx = np.array([s["in"].index for s in samples])
    assert np.all(np.diff(idx) == 1), "sample counter must advance by exactly one per lockstep sample"
    assert [s["out"].index for s in samples] == list(idx)             # both drives, one instant
    assert samples[-1]["in"].time_s == pytest.approx(idx[-1] * PERIOD_S)
    assert net.lost_samples == 0
    # same instant as the physics: the last read equals the world's last measurement (to one count)
    count_rad = 2 * np.pi / 10000
    assert abs(samples[-1]["in"].position_rad - last_bench["in"].position_rad) <= count_rad
    assert samples[-1]["out"].current_a == pytest.approx(last_bench["out"].current_a, abs=1e-4)
    # plausible motion: input follows 30 rad/s, position grows at that speed
    pos = np.array([s["in"].position_rad for s in samples[200:]])
    t = np.array([s["in"].time_s for s in samples[200:]])
    assert np.polyfit(t, pos, 1)[0] == pytest.approx(30.0, rel=0.1)
    assert samples[-1]["in"].velocity_rad_s == pytest.approx(30.0, rel=0.1)
    # output in torque mode: measured current near the 0.3 A command, and it accelerates
    i_out = np.array([s["out"].current_a for s in samples[100:]])
    assert np.mean(i_out) == pytest.approx(0.3, abs=0.05)
    assert samples[-1]["out"].velocity_rad_s > samples[100]["out"].velocity_rad_s > 0
    assert all(not s["in"].fault and not s["out"].fault for s in samples)


def test_quick_stop_brings_the_motor_to_rest_and_close_disables(bench, server):
    net, d_in, _ = open_network(server.port)
    with net:
        d_in.enable(Mode.VELOCITY)
        d_in.set_setpoint(40.0)
        run(net, 300)
        assert bench.drives["in"].state == "OPERATION ENABLED"
        d_in.quick_stop()
        after = run(net, 400)
        assert bench.drives["in"].state == "QUICK STOP ACTIVE"
        assert after[-1]["in"].status & 0x6F == 0x07              # CiA 402 QUICK STOP ACTIVE
        assert abs(after[-1]["in"].velocity_rad_s) < 0.5
        moved = after[-1]["in"].position_rad - after[-100]["in"].position_rad
        assert abs(moved) < 0.05
    assert bench.drives["in"].state == "SWITCH ON DISABLED"        # close() always disables


def test_over_current_sets_the_fault_bit_and_raises_benchfault(bench, server):
    # the drive's over-current protection below the physics' current clamp, so a 2 A command trips it
    bench.drives["out"].max_current_a = 1.0
    net, d_in, d_out = open_network(server.port)
    with net:
        d_in.enable(Mode.VELOCITY)
        d_out.enable(Mode.TORQUE)
        d_in.set_setpoint(10.0)
        kept = run(net, 20)
        d_out.set_setpoint(2.0)
        with pytest.raises(BenchFault) as err:
            for _ in range(50):
                kept.append(net.sample())
        msg = str(err.value)
        assert "drive 'out'" in msg and "0x2310" in msg and "stopped" in msg, msg
        assert err.value.samples["out"].fault                       # the faulted sample is kept
        assert len(kept) - 20 == OVERCURRENT_SAMPLES - 1             # trips on the Nth sample over the limit
        assert bench.drives["out"].state == "FAULT"
        assert bench.drives["in"].state == "SWITCH ON DISABLED"     # the other drive was stopped too
        # acknowledge and run again
        d_out.reset_fault()
        assert bench.drives["out"].state == "SWITCH ON DISABLED"
        d_out.enable(Mode.TORQUE)
        d_out.set_setpoint(0.5)
        assert not run(net, 10)[-1]["out"].fault


def test_setpoint_beyond_the_axis_limit_is_refused(server):
    net, d_in, _ = open_network(server.port, speed_limit_rad_s=100.0)
    with net:
        with pytest.raises(DriveError, match="before enable"):
            d_in.set_setpoint(1.0)
        d_in.enable(Mode.VELOCITY)
        with pytest.raises(DriveError, match=r"drive 'in'.*setpoint 150 beyond the axis limit speed_limit_rad_s=100"):
            d_in.set_setpoint(150.0)


def test_second_vendor_map_is_just_a_file(bench):
    """Little word order, float32 values, a 250 us uint16 counter: no code change."""
    handle = start_modbus_server(bench, port=0, register_map=ACME, lockstep=True)
    try:
        net, d_in, d_out = open_network(handle.port, ACME)
        with net:
            d_in.enable(Mode.VELOCITY)
            d_in.set_setpoint(-20.0)
            samples = run(net, 300)
    finally:
        handle.stop()
    idx = [s["in"].index for s in samples]
    assert np.all(np.diff(idx) == 1)                               # 4 counter counts = 1 ms sample
    assert samples[-1]["in"].time_s == pytest.approx(idx[-1] * PERIOD_S)
    assert samples[-1]["in"].velocity_rad_s == pytest.approx(-20.0, rel=0.1)


def test_free_running_server_counts_gaps_as_lost_samples(bench):
    handle = start_modbus_server(bench, port=0, register_map=GENERIC, lockstep=False)
    try:
        net, d_in, _ = open_network(handle.port, lockstep=False)
        with net:
            d_in.enable(Mode.VELOCITY)
            d_in.set_setpoint(10.0)
            samples = run(net, 100)
            lost = net.lost_samples
    finally:
        handle.stop()
    idx = np.array([s["in"].index for s in samples])
    assert np.all(np.diff(idx) >= 1)                               # never the same instant twice
    assert lost == int(np.sum(np.diff(idx) - 1))                   # gaps counted, not interpolated
    assert idx[-1] - idx[0] >= 99


def test_modbus_exception_names_the_drive_and_the_map(tmp_path, server):
    data = yaml.safe_load(Path(GENERIC).read_text())
    data["registers"]["target_velocity"]["address"] = 40           # not a register of this drive
    bad = tmp_path / "wrong-address.yaml"
    bad.write_text(yaml.safe_dump(data))
    net, d_in, _ = open_network(server.port, str(bad))
    with net:
        with pytest.raises(DriveError, match=r"drive 'in' \(Modbus unit 1 at 127.0.0.1:\d+\): Modbus exception 2 "
                                             r"\(illegal data address\) to write target_velocity=0 at 40.*wrong-address.yaml"):
            d_in.enable(Mode.VELOCITY)


def test_refused_connection_is_a_clear_error():
    with socket.socket() as s:                                      # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(DriveError, match=rf"cannot connect to Modbus TCP 127.0.0.1:{port}"):
        ModbusNetwork(port=port, timeout_s=0.5).open()


def test_dropped_connection_and_silent_drive_are_clear_errors(bench, server):
    net, d_in, _ = open_network(server.port, timeout_s=0.3)
    with net:
        run(net, 5)
        bench.muted.add("out")                                      # the drive stops answering
        with pytest.raises(DriveError, match=r"drive 'out' \(Modbus unit 2 .*no answer to read status"):
            net.sample()
        bench.muted.discard("out")
    net2, _, _ = open_network(server.port, timeout_s=0.3)
    server.stop()                                                   # the other end goes away
    with pytest.raises(DriveError, match=r"drive 'in' .*no answer"):
        net2.sample()
    net2._close()


def test_start_refuses_a_period_the_counter_cannot_express(server):
    net = ModbusNetwork(port=server.port, lockstep=True)
    with net:
        net.add_drive(AxisConfig("in", 1, GENERIC))
        with pytest.raises(DriveError, match="not a whole multiple of the drive's counter period 0.001"):
            net.start(1.5e-3)


def test_unknown_unit_id_is_a_clear_error(server):
    net = ModbusNetwork(port=server.port, timeout_s=2.0)
    with net:
        drive = net.add_drive(AxisConfig("in", 7, GENERIC))
        with pytest.raises(DriveError, match=r"Modbus unit 7 .*exception 11 \(gateway target failed to respond\)"):
            drive.read_sample()


def test_unwrap_follows_a_counter_through_its_wrap():
    from gearbench.drives.modbus import _Unwrap
    unwrap = _Unwrap(16)
    raw = [65530, 65534, 2, 7, 65533, 65530]                         # up through 0, then back down
    assert [unwrap(r) for r in raw] == [65530, 65534, 65538, 65543, 65533, 65530]


def test_emulator_on_a_busy_port_is_a_clear_error(bench):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        with pytest.raises(DriveError, match=rf"cannot listen on 127.0.0.1:{s.getsockname()[1]}"):
            start_modbus_server(bench, port=s.getsockname()[1])
