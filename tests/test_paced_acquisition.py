"""Paced acquisition's definitions of lost and late (issue 28), each on a case that can fail:

- an answer that echoes its SYNC's counter completes that SYNC however late the master takes
  it (within ``LATE_ANSWER_S``): a late wake-up that still reads the queued frames loses nothing;
- a SYNC whose answers never all arrive, or arrive after a later SYNC's were complete, is lost
  (samples stay in SYNC order);
- a producer that wakes late sends the SYNCs it owes at once (each counted as sent late) instead
  of skipping them, as far back as ``catch_up_s``; beyond that the slots are skipped (lost).
"""
import struct
import threading
import time
import types
import uuid

import can

from gearbench.drives.cia402 import CiA402Network
from gearbench.drives.sync_producer import ThreadSyncProducer

TPDO = struct.Struct("<HiB")          # statusword | position | SYNC counter echo


def _network(window: int = 100) -> CiA402Network:
    """The receive side of a paced network with two drives (no bus: frames are handed in)."""
    net = CiA402Network(bus="virtual:unused")
    net.network = types.SimpleNamespace(subscribers={})
    net._formats = {cob: (TPDO, True) for cob in (0x181, 0x281, 0x182, 0x282)}
    net._produced, net._window, net._deliver = True, window, 1
    net._tpdo_nodes = [1, 2]
    return net


def _answers(counter: int, cobs=(0x181, 0x281, 0x182, 0x282)) -> list:
    return [(cob, TPDO.pack(0x0637, 1000 + counter, counter), 0.0) for cob in cobs]


def test_an_echoed_answer_completes_its_sync_however_late_it_is_taken():
    net = _network()
    for number in (1, 2, 3):                       # three SYNCs go out before the master reads anything
        net._begin_sync(number, number, 0.0)
    net._take_frames(_answers(1) + _answers(2) + _answers(3))
    assert [n for n, _ in net._ready] == [1, 2, 3]
    assert net._ready[0][1][0x181] == (0x0637, 1001, 1)        # SYNC 1's own values, not a later one's
    assert net.late_frames == 0 and net.dropped_frames == 0


def test_a_sync_with_a_missing_answer_is_lost_when_a_later_one_completes():
    net = _network()
    net._begin_sync(1, 1, 0.0)
    net._begin_sync(2, 2, 0.0)
    net._take_frames(_answers(1, cobs=(0x181, 0x281, 0x182)) + _answers(2))   # SYNC 1 lacks 0x282
    net._take_frames(_answers(1, cobs=(0x282,)))                              # ... which comes after SYNC 2
    assert [n for n, _ in net._ready] == [2]
    assert net.dropped_frames == 1 and net.late_frames == 1


def test_an_answer_older_than_the_window_is_not_taken():
    net = _network(window=5)
    for number in range(1, 8):
        net._begin_sync(number, number, 0.0)
    net._take_frames(_answers(1))                  # 6 SYNCs back, the window is 5
    assert not net._ready and net.late_frames == 4


def _producer_run(catch_up_s: float, stall_s: float = 0.03) -> tuple[list, ThreadSyncProducer]:
    bus = can.Bus(interface="virtual", channel=uuid.uuid4().hex)
    network = types.SimpleNamespace(bus=bus, subscribe=lambda *a: None, unsubscribe=lambda *a: None)
    begun, done, at_80 = [], threading.Event(), {}

    def begin(number, counter, wall_s):
        if done.is_set():
            return
        begun.append(number)
        if number == 20:
            time.sleep(stall_s)                    # the producer's thread is not run for a while
        if number >= 80:                           # its counts as of this slot, in its own thread (a
            at_80.update(skipped=p.skipped, sent_late=p.sent_late)   # later stall adds to both)
            done.set()

    p = ThreadSyncProducer(network, 1e-3, 240, begin, receive=False, catch_up_s=catch_up_s)
    p.at_80 = at_80
    p.start()
    try:
        assert done.wait(5.0)
    finally:
        p._stop.set()
        p._thread.join(1.0)
        bus.shutdown()
    return begun, p


def test_a_late_producer_catches_up_instead_of_skipping():
    begun, p = _producer_run(catch_up_s=0.05)
    assert begun[:80] == list(range(1, 81))        # every SYNC sent, none skipped
    assert p.at_80["skipped"] == 0 and p.at_80["sent_late"] >= 20 and p.sent_late_max_s >= 0.025
    # each SYNC sent late says by how much: its sample is stamped then, off the grid
    assert len(p.sent_late_by) == p.sent_late and max(p.sent_late_by.values()) >= 0.025
    assert all(v > 0.5e-3 for v in p.sent_late_by.values())


def test_slots_further_back_than_catch_up_are_skipped_and_counted():
    begun, p = _producer_run(catch_up_s=0.005)
    gaps = begun[0] - 1 + sum(b - a - 1 for a, b in zip(begun, begun[1:]))   # slots are numbered from 1
    assert p.at_80["skipped"] == gaps >= 20        # ~30 slots owed, at most 5 sent late
    assert p.at_80["sent_late"] >= 1


# --- Modbus TCP, free-running: the read schedule (pure, simulated clocks) ---------------------
def _drive_counter(t_s: float, offset_s: float, drift: float, cp_s: float) -> int:
    """A drive's sample counter at host time ``t_s``: its own crystal, ``drift`` fast."""
    return int((t_s - offset_s) * (1 + drift) // cp_s)


def _simulate_schedule(k: int, cp_s: float, drift: float, cells: int, late_s, seed: int = 3):
    """Lock a PollSchedule on a simulated drive as the master does, then read ``cells`` cells, each
    sent ``late_s(rng)`` after its due time and reaching the drive 50 us later. Returns, per read,
    (lateness, the read's slack to its cell's true end, whether it fell in its cell, whether a probe,
    the count into its cell the drive was at)."""
    import numpy as np

    from gearbench.drives.modbus import PollSchedule
    rng = np.random.default_rng(seed)
    offset, transit = 0.123456, 50e-6
    sched = PollSchedule(cp_s, k)
    t, c0 = 1.0, _drive_counter(1.0 + transit, offset, drift, cp_s)
    while (c := _drive_counter(t + transit, offset, drift, cp_s)) == c0:    # the master's edge search
        t += cp_s / 8
    sched.lock(c, t)
    cell, out = c // k + 1, []
    for _ in range(cells):
        due = sched.due_s(cell)
        late = late_s(rng)
        c = _drive_counter(due + late + transit, offset, drift, cp_s)
        true_end = offset + (cell + 1) * k * cp_s / (1 + drift) - transit
        while c // k < cell:                        # a probe before its cell: read again at once
            sched.observe(cell, c)
            late += cp_s / 16
            c = _drive_counter(due + late + transit, offset, drift, cp_s)
        probe = sched.is_probe(cell)
        sched.observe(cell, c)
        out.append((late, true_end - due, c // k == cell, probe, c - cell * k))
        cell = max(cell, c // k) + 1
    return out


def test_modbus_reads_fall_in_their_cell_while_the_master_is_not_later_than_most_of_the_cell():
    """2 ms cells of a 1 ms counter, a drive crystal 200 ppm fast, the master waking up to 1.5 ms
    late (0-100 us typically): every read falls in its cell; once locked each read leaves at least
    80 % of the cell (1.6 ms) for lateness, and one less than 0.5 ms late reads the cell's first
    count (its sample is stamped on the grid); probes are 1 read in 16."""
    def late(rng):
        return rng.uniform(0, 100e-6) if rng.random() > 0.05 else rng.uniform(0, 1.5e-3)
    reads = _simulate_schedule(2, 1e-3, 200e-6, 30_000, late)
    assert all(inside for _, _, inside, _, _ in reads)
    locked = reads[200:]
    assert min(s for _, s, _, _, _ in locked) >= 0.8 * 2e-3
    assert all(count == 0 for late_s, _, _, _, count in locked if late_s < 0.5e-3)
    assert sum(probe for _, _, _, probe, _ in locked) < len(locked) / 15


def test_modbus_read_sent_after_its_cell_ended_is_the_only_kind_that_misses():
    """The same with lateness up to 3 ms (beyond the cell): a read misses its cell exactly when it
    was sent after the cell's end, never otherwise (the lost cell is the host's, not the schedule's)."""
    def late(rng):
        return rng.uniform(0, 3e-3) if rng.random() < 0.02 else rng.uniform(0, 100e-6)
    reads = _simulate_schedule(2, 1e-3, -150e-6, 20_000, late)
    assert any(not inside for _, _, inside, _, _ in reads)        # the case happens
    for late_s, slack_s, inside, _, _ in reads:
        assert inside == (late_s < slack_s), (late_s, slack_s)


def test_modbus_schedule_follows_a_sampling_period_of_one_counter_period():
    """k = 1 (a cell is one count; probes that come early are read again): still every read in its
    cell for lateness well inside the cell."""
    def late(rng):
        return rng.uniform(0, 100e-6)
    reads = _simulate_schedule(1, 1e-3, 100e-6, 20_000, late)
    assert all(inside for _, _, inside, _, _ in reads)
