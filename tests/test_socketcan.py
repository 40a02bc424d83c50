"""The socketcan path on a real virtual CAN bus (``$GEARBENCH_VCAN``, e.g. vcan0).

Run by ``.ci/vcan`` (the host kernel's vcan, or a qemu guest where the kernel has
none). Elsewhere these tests skip with one line; in CI they fail unless ``.ci/run``
hands them to ``.ci/vcan`` (GEARBENCH_VCAN_STEP). Test ids name the bus.

Inside a software-emulated guest (``.ci/vcan`` sets GEARBENCH_VCAN_EMULATED=tcg)
Python runs 20-100x slower than on the host: every timing here is either lockstep
(one period of drive time per SYNC) or loose, and there the supervision timeouts
are generous and the paced SYNC period long enough for the emulated drives to
answer each SYNC within its period. What each test proves is the same on both.
Debian's ``candump`` records the bus as an independent witness of what went over it.
"""
from __future__ import annotations

import os
import signal
import statistics
import subprocess
import time
from pathlib import Path

import pytest

from conftest import emulator_command, in_ci, require_tool, start_emulator
from gearbench.drives.base import AxisConfig, Mode
from gearbench.drives.cia402 import CiA402Network
from gearbench.errors import BenchFault

REPO = Path(__file__).resolve().parents[1]
EDS = str(REPO / "drivers" / "cia402-servo.eds")
VCAN = os.environ.get("GEARBENCH_VCAN", "")
BUS = f"socketcan:{VCAN or 'vcan0'}"
ID = f"socketcan-{VCAN or 'vcan0'}"
EMULATED = bool(os.environ.get("GEARBENCH_VCAN_EMULATED"))   # a TCG guest: CPU-bound Python 20-100x slower
# Bounds, not expectations: in a TCG guest on a loaded 2-core host the emulated drives were seen
# to take > 3 s for one SDO answer (qemu itself waiting for a host CPU). A drive silent this long
# is still a fault.
NET = dict(heartbeat_ms=500, timeout_s=20.0 if EMULATED else 10.0, sdo_timeout_s=10.0 if EMULATED else 1.0,
           state_timeout_s=10.0 if EMULATED else 3.0)


@pytest.fixture(scope="module", autouse=True)
def vcan():
    if not VCAN:
        reason = "socketcan tests need a vcan (GEARBENCH_VCAN unset); run .ci/vcan"
        if in_ci() and not os.environ.get("GEARBENCH_VCAN_STEP"):
            pytest.fail(reason + " (in CI they must run, not skip)")
        pytest.skip(reason + (" (CI: the .ci/vcan step runs them)" if in_ci() else ""))
    return VCAN


@pytest.fixture(autouse=True)
def deadline():
    """A hung test fails (SIGALRM) instead of hanging the guest until its power-off."""
    def expired(*_):
        raise TimeoutError("socketcan test exceeded 900 s")
    previous = signal.signal(signal.SIGALRM, expired)
    signal.alarm(900)       # a loaded host's emulated guest is slow: the run test alone took > 300 s
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, previous)


@pytest.fixture(scope="module", params=[BUS], ids=[ID])
def emulator(vcan, request):
    proc = start_emulator(request.param)
    yield proc
    proc.send_signal(signal.SIGTERM)
    proc.wait(30)


command = emulator_command


class Candump:
    """Debian's candump recording the bus: ``(timestamp) vcan0 181#...`` lines."""

    def __init__(self, tmp_path: Path):
        self.exe = require_tool("candump", "apt-get install can-utils")
        self.path = tmp_path / "candump.log"

    def __enter__(self):
        self.file = open(self.path, "w")
        self.proc = subprocess.Popen([self.exe, "-L", VCAN], stdout=self.file)
        time.sleep(0.5)            # candump binds before the traffic we want to see
        return self

    def __exit__(self, *exc):
        time.sleep(0.3)
        self.proc.send_signal(signal.SIGINT)
        self.proc.wait(10)
        self.file.close()

    def frames(self) -> list[tuple[float, int, bytes]]:
        out = []
        for line in self.path.read_text().splitlines():
            stamp, _, frame = line.split()
            cob, _, data = frame.partition("#")
            out.append((float(stamp.strip("()")), int(cob, 16), bytes.fromhex(data)))
        return out


def open_net(**kw) -> CiA402Network:
    return CiA402Network(bus=BUS, **{**NET, **kw})


def test_master_maps_pdos_and_candump_sees_the_mapping(emulator, tmp_path):
    """PDO mapping configured by SDO, then SYNC/TPDO traffic as candump records it."""
    with Candump(tmp_path) as dump, open_net(lockstep=True) as net:
        din = net.add_drive(AxisConfig("in", 1, EDS))
        net.add_drive(AxisConfig("out", 2, EDS))
        net.start(1e-3)
        din.enable(Mode.VELOCITY)
        din.set_setpoint(30.0)
        rows = [net.sample() for _ in range(100)]
    frames = dump.frames()
    sdo_writes = {(d[2] << 8 | d[1], d[3]): int.from_bytes(d[4:8], "little")
                  for _, cob, d in frames if cob == 0x601 and d and d[0] & 0xE0 == 0x20}
    assert sdo_writes[(0x1A00, 1)] == 0x60410010 and sdo_writes[(0x1A00, 2)] == 0x60640020   # TPDO1 mapping
    assert sdo_writes[(0x1A01, 1)] == 0x606C0020 and sdo_writes[(0x1A01, 2)] == 0x60780010   # TPDO2 mapping
    assert sdo_writes[(0x1800, 2)] == 1 and sdo_writes[(0x1801, 2)] == 1                     # synchronous
    syncs = [d for _, cob, d in frames if cob == 0x080]
    tpdo1 = [d for _, cob, d in frames if cob == 0x181]
    assert len(syncs) >= 100 and len(tpdo1) >= 100
    assert {len(d) for d in tpdo1} == {7}                     # statusword 2 + position 4 + SYNC counter 1
    assert [d[-1] for d in tpdo1[-50:]] == [d[0] for d in syncs[-50:]]   # each answer echoes its SYNC
    idx = [r["in"].index for r in rows]
    assert idx == list(range(idx[0], idx[0] + 100)) and net.lost_samples == 0
    print(f"candump on {VCAN}: {len(frames)} frames, {len(syncs)} SYNC, {len(tpdo1)} TPDO1 of node 1")


def test_state_machine_and_emcy_fault_over_socketcan(emulator, tmp_path):
    with Candump(tmp_path) as dump, open_net(lockstep=True) as net:
        din = net.add_drive(AxisConfig("in", 1, EDS))
        dout = net.add_drive(AxisConfig("out", 2, EDS))
        net.start(1e-3)
        din.enable(Mode.VELOCITY)
        dout.enable(Mode.TORQUE)
        assert din.state() == dout.state() == "OPERATION ENABLED"
        din.set_setpoint(40.0)
        for _ in range(50):
            net.sample()
        din.quick_stop()
        for _ in range(50):
            net.sample()
        assert din.state() == "QUICK STOP ACTIVE"
        din.disable()
        assert din.state() == "SWITCH ON DISABLED"
        din.enable(Mode.VELOCITY)
        assert command(emulator, {"cmd": "fault", "axis": "out", "code": 0x2320})["ok"]
        with pytest.raises(BenchFault, match=rf"node 2 on {BUS}.*EMCY 0x2320"):
            for _ in range(500):
                net.sample()
        assert dout.state() == "FAULT"
        assert din.state() in ("SWITCH ON DISABLED", "QUICK STOP ACTIVE")   # the healthy drive was stopped
        dout.reset_fault()
        assert dout.state() == "SWITCH ON DISABLED"
    emcy = [d for _, cob, d in dump.frames() if cob == 0x082]
    assert any(d[:2] == bytes([0x20, 0x23]) for d in emcy)     # candump saw the EMCY 0x2320 of node 2


def test_sync_from_the_kernel_broadcast_manager(emulator, tmp_path):
    """Paced mode on socketcan: SYNC comes from the kernel (BCM), not from Python; it keeps
    its period while this process sleeps, and no sample the drives answered in time is lost."""
    # the emulated drives must answer every SYNC inside its period: in a TCG guest they need
    # 20-300 ms per SYNC (measured), so the period there is 0.5 s; Python sleeps 5-10 periods
    period_s = 0.5 if EMULATED else 0.1
    sleep_s = (5 if EMULATED else 10) * period_s
    # paced: the drives also watch the master's heartbeat (0x1016); in the guest an emulated drive
    # may hear it late by the guest's stalls, so its consumer timeout is as generous as the rest
    watch = {"master_timeout_ms": 20000} if EMULATED else {}
    with Candump(tmp_path) as dump, open_net(lockstep=False, **watch) as net:
        din = net.add_drive(AxisConfig("in", 1, EDS))
        net.add_drive(AxisConfig("out", 2, EDS))
        net.start(period_s)
        din.enable(Mode.VELOCITY)
        first = net.sample()
        assert net.sync_producer.kind == "kernel" and net.sync_producer.task is not None
        before = [net.sample() for _ in range(5)]
        t_sleep = time.time()
        time.sleep(sleep_s)                              # Python does nothing: the kernel goes on
        t_wake = time.time()
        after = [net.sample() for _ in range(5)]
    rows = [first, *before, *after]
    idx = [r["in"].index for r in rows]
    assert all(b > a for a, b in zip(idx, idx[1:]))
    assert all(r["in"].time_s == pytest.approx(r["in"].index * period_s) for r in rows)
    # SYNCs answered in full while Python slept are kept (the bus order decides, not the host): the loop
    # does not jump to the newest SYNC; any SYNC not answered before the next one is a counted gap
    assert idx[len(before) + 1] - idx[len(before)] < sleep_s / period_s / 2
    assert idx[-1] - idx[0] + 1 - len(idx) <= net.lost_samples
    syncs = [t for t, cob, _ in dump.frames() if cob == 0x080]
    during = [t for t in syncs if t_sleep + 0.05 < t < t_wake - 0.05]
    assert len(during) >= (sleep_s - 0.1) / period_s * 0.8, f"{len(during)} SYNCs while Python slept"
    gaps = [b - a for a, b in zip(syncs, syncs[1:])]
    assert statistics.median(gaps) == pytest.approx(period_s, rel=0.2)
    print(f"kernel SYNC on {VCAN}: {len(syncs)} SYNCs, median interval {statistics.median(gaps) * 1e3:.2f} ms, "
          f"{len(during)} while Python slept {sleep_s:g} s; {len(rows)} samples, {net.lost_samples} lost")


def test_heartbeat_loss_stops_the_bench(emulator):
    """A drive that goes silent (no heartbeat, no PDO) is a BenchFault naming it and the bus."""
    net = open_net(lockstep=True, heartbeat_ms=200, timeout_s=1.0)
    with net:
        net.add_drive(AxisConfig("in", 1, EDS))
        net.add_drive(AxisConfig("out", 2, EDS))
        net.start(1e-3)
        net.sample()
        assert command(emulator, {"cmd": "mute", "axis": "out"})["ok"]
        try:
            t0 = time.monotonic()
            with pytest.raises(BenchFault, match=rf"node 2 on {BUS}"):
                for _ in range(100000):
                    net.sample()
            print(f"silent drive detected after {time.monotonic() - t0:.2f} s on {BUS}")
        finally:
            command(emulator, {"cmd": "mute", "axis": "out", "on": False})
