"""Supervision judges the drive, not the host (issue: robust on a busy PC).

The emulated drives run in their own process (``gearbench emulate``) on a real
cross-process bus, so stopping *this* process stalls the master while the drives
keep talking (a busy host), and stopping the *emulator* freezes the drives (a
silent drive). Only the second may stop the bench. Timing is derived from what the
master itself measured, never from a fixed guess of how fast this host is.
"""
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from gearbench.drives.base import AxisConfig, Mode
from gearbench.drives.buses import bus_for_tests
from gearbench.drives.cia402 import CiA402Network
from gearbench.drives.supervision import HostStallMonitor, Liveness
from gearbench.errors import BenchFault

BUS = bus_for_tests()


@pytest.fixture(scope="module", params=[BUS], ids=[BUS.interface])
def emulator(request):
    bus = request.param
    proc = subprocess.Popen([sys.executable, "-m", "gearbench", "emulate", "--can", str(bus), "--exit-on-eof"],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    assert proc.stdout.readline().split()[:1] == ["ready"]
    yield bus, proc
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGCONT)
        proc.stdin.close()
        proc.wait(10)


def open_net(bus, **options):
    net = CiA402Network(bus=str(bus), heartbeat_ms=100, lockstep=True, **options)
    net.open()
    net.add_drive(AxisConfig("in", 1, ""))
    net.add_drive(AxisConfig("out", 2, ""))
    net.start(1e-3)
    return net


def stop_for(pid: int, seconds: float, after_s: float) -> subprocess.Popen:
    """SIGSTOP ``pid`` for ``seconds`` after ``after_s``, from another process."""
    return subprocess.Popen(["sh", "-c", f"sleep {after_s}; kill -STOP {pid}; sleep {seconds}; kill -CONT {pid}"])


def test_stall_monitor_accounts_stalls_after_a_time():
    m = HostStallMonitor()
    m.record(1.0, 0.5)
    m.record(3.0, 0.2)
    assert m.stalled_since(0.0) == pytest.approx(0.7)
    assert m.stalled_since(2.0) == pytest.approx(0.2)
    assert m.stalled_since(4.0) == 0.0
    live = Liveness(m)
    live.heard(1, 0.5)
    # 3.5 s since the frame, 0.7 s of it the host was not running: 2.8 s of silence
    assert live.silent_s(1, now_s=4.0) == pytest.approx(2.8)


def test_a_stalled_master_is_not_a_silent_drive(emulator):
    """This process is stopped for 1.5 s (3x the silence limit) in the middle of
    sampling: the drives kept talking, so the run goes on, with the stall counted
    and no sample lost (lockstep) and none duplicated."""
    bus, _ = emulator
    net = open_net(bus, timeout_s=0.5)
    try:
        net.drives["in"].enable(Mode.VELOCITY)
        net.drives["in"].set_setpoint(20.0)
        stopper = stop_for(os.getpid(), 1.5, 0.3)
        idx, t0 = [], time.monotonic()
        while stopper.poll() is None or time.monotonic() - t0 < 2.5:
            idx.append(net.sample()["in"].index)
        stopper.wait()
        sup = net.supervision()
        print(sup)
        assert sup["host_stall_max_s"] > 1.0, "the 1.5 s stop must be seen as a host stall"
        assert np.all(np.diff(idx) == 1) and net.lost_samples == 0
    finally:
        net.close()


def test_a_frozen_drive_stops_the_bench_within_its_limit(emulator):
    """The emulator (the drives) is stopped: silence is real, nobody is waiting for a
    CPU. The bench faults naming the node, within about the silence limit."""
    bus, proc = emulator
    net = open_net(bus, timeout_s=0.5)
    try:
        net.sample()
        os.kill(proc.pid, signal.SIGSTOP)
        t_stop = time.monotonic()
        with pytest.raises(BenchFault, match=r"node [12] .*silent"):
            for _ in range(100000):
                net.sample()
        detected_s = time.monotonic() - t_stop - net.stalls.stalled_since(t_stop)
        print(f"frozen drive detected after {detected_s:.2f} s (limit {net.silence_limit_s} s)")
        # limit, plus one SDO probe, plus the final stop attempts on frozen drives
        assert detected_s < net.silence_limit_s + 2 * net.silence_limit_s + 4 * net.state_timeout_s
        assert "did NOT reach a disabled state" in str(net.stop_report), "a frozen drive cannot be seen disabled"
    finally:
        os.kill(proc.pid, signal.SIGCONT)
        net.close()


def test_frames_of_the_wrong_length_are_a_fault_naming_the_cob_id(emulator):
    """A TPDO whose length does not match the mapping gearbench configured is never guessed at."""
    bus, _ = emulator
    net = open_net(bus)
    try:
        net.sample()
        net._on_tpdo(0x181, bytearray(3), time.time())
        with pytest.raises(BenchFault, match=r"TPDO 0x181 of node 1 has 3 bytes"):
            net.sample()
    finally:
        net.close()
