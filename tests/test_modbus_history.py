"""The Modbus master reading a drive-side history ring (a map's ``history:``), on a simulated clock:
the drives and the host clock are simulated (no socket, no wall time), so what is counted is the
master's logic alone. Last, one run against the compiled stand-in with the master stalled 20 ms.

A drive with a ring keeps its last ``depth`` samples; the master reads back every cell a host stall
covered. A stall shorter than the ring loses nothing and returns the cells in order, on the grid; a
longer one loses the cells whose entries were overwritten (counted); a drive read as without
history loses every cell a stall covers (today's behaviour)."""
from __future__ import annotations

import time

import numpy as np
import pytest

from gearbench.drives import modbus
from gearbench.drives.base import AxisConfig
from gearbench.drives.modbus import ModbusDrive, ModbusNetwork, PollSchedule
from gearbench.drives.register_map import load_register_map

MAP = "drivers/generic-modbus-servo.yaml"
PERIOD_S = 2e-3        # 2 counter periods of 1 ms per cell (the rated rate)


class SimClock:
    """The host clock the master sees; ``sleep`` advances it (plus ``stall_s`` once, when armed)."""

    def __init__(self):
        self.t = 10.0
        self.stall_s = 0.0

    def monotonic(self) -> float:
        return self.t

    def perf_counter(self) -> float:
        return self.t

    def sleep(self, s: float) -> None:
        self.t += max(0.0, s) + 20e-6 + self.stall_s     # a wake-up 20 us late
        self.stall_s = 0.0


class SimNetwork(ModbusNetwork):
    """The master with its two reads answered by simulated drives on ``clock``: counter =
    (t - offset) / 1 ms, position = 3 counts per counter period; the ring written every count."""

    def __init__(self, clock: SimClock, history: bool = True, depth: int | None = None, drift: float = 0.0):
        super().__init__(history=history)
        self.clock, self.offset_s, self.reads, self.drift = clock, 0.0004321, [], drift
        for name, unit in (("in", 1), ("out", 2)):
            d = ModbusDrive(AxisConfig(name, unit, MAP), self, None, "sim")
            if depth is not None:
                d.map = _with_depth(d.map, depth)
            self.drives[name] = d

    def start(self, period_s: float) -> None:       # start() without a connection: the free-running state
        for d in self.drives.values():
            d._k = round(period_s / d.map.counter_period_s)
        first = next(iter(self.drives.values()))
        self.period_s, self._last_index, self._cell = period_s, None, None
        self.schedule = PollSchedule(first.map.counter_period_s, first._k)
        self._ring = self.use_history and all(d.map.history for d in self.drives.values())

    def _now_counter(self) -> int:
        # the request's 30 us transit; the drive's crystal ``drift`` fast
        return int((self.clock.t + 30e-6 - self.offset_s) * (1 + self.drift) // 1e-3)

    def _block(self, d: ModbusDrive, n: int) -> list[int]:
        m = d.map
        words = m.encode_raw("status", 0x27) + m.encode_raw("sample_counter", n, wrap=True) + \
            m.encode_raw("position", 3 * n, wrap=True) + m.encode_raw("velocity", 0) + m.encode_raw("current", 0)
        return words

    def _send_reads(self, spans=None) -> None:
        self._t_sent = self._t_out = self.clock.t
        now = self._now_counter()
        self._words = {}
        for d in self.drives.values():
            if spans is None:
                self._words[d.name] = tuple(self._block(d, now))
                continue
            address, count = spans[d.name]
            (ring, depth), ew = d.map.history, d.map.entry_words
            self.reads.append((address, count))
            words = []
            for j in range((address - ring) // ew, (address - ring) // ew + count // ew):
                n = now - (now - j) % depth          # the newest sample the drive wrote there
                words += self._block(d, n)
            self._words[d.name] = tuple(words)

    def _receive_reads(self) -> dict:
        return self._words


def _with_depth(m, depth: int):
    import dataclasses
    return dataclasses.replace(m, history=(m.history[0], depth))


@pytest.fixture
def clock(monkeypatch):
    c = SimClock()
    monkeypatch.setattr(modbus, "time", c)
    return c


def _run(net: SimNetwork, clock: SimClock, samples: int, stall_at: dict[int, float]):
    net.start(PERIOD_S)
    out = []
    for i in range(samples):
        if i in stall_at:
            clock.stall_s = stall_at[i]
        out.append(net.sample())
    return out


def test_the_shipped_generic_map_declares_its_ring():
    m = load_register_map(MAP)
    assert m.history == (100, 256) and m.entry_words == 9 and m.history_address(257) == 109


@pytest.mark.parametrize("stall_s", [0.0, 0.02, 0.05, 0.2])
def test_a_stall_shorter_than_the_ring_loses_nothing_and_keeps_the_grid(clock, stall_s):
    net = SimNetwork(clock)        # 256 entries of 1 ms: 128 cells of 2 ms
    samples = _run(net, clock, 400, {150: stall_s, 300: stall_s})
    idx = np.array([s["in"].index for s in samples])
    t = np.array([s["in"].time_s for s in samples])
    assert net.lost_samples == 0 and np.all(np.diff(idx) == 1), (net.lost_samples, net.supervision())
    assert np.allclose(np.diff(t[1:]), PERIOD_S) and np.allclose(t[1:] / PERIOD_S, np.round(t[1:] / PERIOD_S))
    assert all(s["in"].position_rad == s["out"].position_rad for s in samples)
    sup = net.supervision()
    assert sup["lost_history_overrun"] == 0 and sup["lost_sent_late"] == 0
    # the cells the stall covered came back from the ring (a drive without one had lost them)
    assert sup["recovered_from_history"] >= (2 * int(stall_s / PERIOD_S) - 4 if stall_s else 0), sup
    # normally one entry per read: a cell costs one read per drive, of one entry (9 registers)
    counts = [c for _, c in net.reads]
    assert np.median(counts) == 9 and max(counts) <= 125


def test_a_stall_longer_than_the_ring_counts_the_overwritten_cells_lost(clock):
    net = SimNetwork(clock, depth=16)       # 16 ms of ring, 8 cells
    samples = _run(net, clock, 200, {100: 0.05})     # a 50 ms stall: 25 cells
    sup = net.supervision()
    assert net.lost_samples == sup["lost_history_overrun"] > 0, sup
    # about the stall's cells less those the ring still held (8, less one of margin)
    assert 25 - 8 <= net.lost_samples <= 25 - 8 + 3, sup
    idx = [s["in"].index for s in samples]
    assert idx == sorted(set(idx))           # in order, none twice


@pytest.mark.parametrize("drift", [-500e-6, 500e-6])
def test_the_schedule_follows_a_drive_crystal_off_by_500_ppm(clock, drift):
    net = SimNetwork(clock, drift=drift)
    samples = _run(net, clock, 6000, {})        # 12 s: 6 ms of drift, 3 cells
    sup = net.supervision()
    assert net.lost_samples == 0 and sup["lost_history_overrun"] == 0, sup
    # the reads stay within a cell of the drive: one entry per read (three every 16th: the next
    # cell's first entry, a look ahead), a stale one now and then
    assert np.mean([c for _, c in net.reads]) < 1.3 * 9 and sup["history_stale"] < 0.08 * len(samples), sup
    assert sup["recovered_from_history"] <= sup["history_stale"] + 1, sup   # only the re-read stale ones


def test_a_read_across_the_ring_wrap_is_split(clock):
    net = SimNetwork(clock, depth=16)
    _run(net, clock, 300, {40: 0.012, 120: 0.012, 200: 0.012})
    ring, ew = 100, 9
    ends = [(a - ring) // ew + c // ew for a, c in net.reads]
    assert max(ends) <= 16                   # never past the last entry: the rest comes in the next read
    assert net.lost_samples == 0 and max(c for _, c in net.reads) > ew


def test_a_drive_read_as_without_history_loses_every_cell_a_stall_covers(clock):
    net = SimNetwork(clock, history=False)
    samples = _run(net, clock, 300, {150: 0.02})
    sup = net.supervision()
    assert net.reads == [] and sup["recovered_from_history"] == 0
    assert net.lost_samples == sup["lost_sent_late"] >= 8, sup
    assert len(samples) == 300


def test_a_map_without_history_is_read_as_before(clock):
    import dataclasses
    net = SimNetwork(clock)
    for d in net.drives.values():
        d.map = dataclasses.replace(d.map, history=None)
    _run(net, clock, 100, {})
    assert net.reads == [] and not net._ring and net.supervision()["history"].startswith("none")


def test_bad_history_entries_name_the_field():
    import yaml
    from gearbench.drives.register_map import register_map_problems
    data = yaml.safe_load(open(MAP))
    for history, field in (({"address": 100, "depth": 1}, "history.depth"),
                           ({"address": 15, "depth": 8}, "overlaps registers"),
                           ({"address": 65530, "depth": 8}, "pass address 65535"),
                           ("yes", "history: not a mapping")):
        _, problems = register_map_problems({**data, "history": history}, "m.yaml")
        assert problems and field in problems[0], (history, problems)


# --- against the compiled stand-in, the master stalled for real -------------------------------------
def test_compiled_stand_in_a_stalled_master_loses_nothing_with_history():
    from gearbench.benchmarks import _responder
    from gearbench.drives.base import Mode
    if _responder.available(_responder.MODBUS_SOURCE) is not None:
        pytest.skip(f"needs the compiled Modbus stand-in ({_responder.available(_responder.MODBUS_SOURCE)})")
    m = load_register_map(MAP)
    srv = _responder.ModbusStandIn(m.counter_period_s, 2, 2e-4, 0, history=m.history)
    try:
        net = ModbusNetwork(port=srv.ports[0], timeout_s=2.0)
        with net:
            net.add_drive(AxisConfig("in", 1, MAP))
            d_out = net.add_drive(AxisConfig("out", 2, MAP, extra={"port": srv.ports[1]}))
            net.start(PERIOD_S)
            net.drives["in"].enable(Mode.VELOCITY)
            d_out.enable(Mode.TORQUE)
            net.drives["in"].set_setpoint(10.0)
            for _ in range(20):
                net.sample()
            lost0, own0 = net.lost_samples, srv.counters()
            times = []
            for i in range(400):
                if i % 100 == 50:
                    time.sleep(0.02)          # the master not run for 20 ms: 10 cells
                times.append(net.sample()["in"].time_s)
            sup, own = net.supervision(), srv.counters()
    finally:
        srv.stop()
    assert net.lost_samples - lost0 == 0, sup
    assert sup["recovered_from_history"] >= 4 * 8, sup
    assert np.allclose(np.diff(times), PERIOD_S), "samples off the grid"
    assert own["cells_unread"] - own0["cells_unread"] == 0 and own["exceptions"] == 0, own


def test_python_emulator_keeps_the_ring_a_stalled_master_reads_back():
    """The emulator (``run --sim`` with Modbus profiles, ``gearbench emulate``) writes each drive
    cycle's sample into the ring: a master stalled 30 ms loses nothing."""
    from gearbench.drives.base import Mode
    from gearbench.emulate.bench import EmulatedBench
    from gearbench.emulate.modbus_server import start_modbus_server
    bench = EmulatedBench()
    bench.advance()
    with start_modbus_server(bench, "127.0.0.1", 0, register_map=MAP) as srv:
        net = ModbusNetwork(port=srv.port, timeout_s=2.0)
        with net:
            d_in = net.add_drive(AxisConfig("in", 1, MAP))
            net.add_drive(AxisConfig("out", 2, MAP))
            net.start(PERIOD_S)
            d_in.enable(Mode.VELOCITY)
            d_in.set_setpoint(20.0)
            samples = []
            for i in range(200):
                if i == 100:
                    time.sleep(0.03)
                samples.append(net.sample())
            sup = net.supervision()
    idx = [s["in"].index for s in samples]
    assert net.lost_samples == 0 and idx == list(range(idx[0], idx[0] + 200)), sup
    assert sup["recovered_from_history"] >= 10 and sup["counter_skew_max"] == 0, sup
    # the ring's samples are the plant's: the velocity follows the setpoint
    assert abs(samples[-1]["in"].velocity_rad_s - 20.0) < 2.0
