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
    begun, done = [], threading.Event()

    def begin(number, counter, wall_s):
        begun.append(number)
        if number == 20:
            time.sleep(stall_s)                    # the producer's thread is not run for a while
        if number >= 80:
            done.set()

    p = ThreadSyncProducer(network, 1e-3, 240, begin, receive=False, catch_up_s=catch_up_s).start()
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
    assert p.skipped == 0 and p.sent_late >= 20 and p.sent_late_max_s >= 0.025
    # each SYNC sent late says by how much: its sample is stamped then, off the grid
    assert len(p.sent_late_by) == p.sent_late and max(p.sent_late_by.values()) >= 0.025
    assert all(v > 0.5e-3 for v in p.sent_late_by.values())


def test_slots_further_back_than_catch_up_are_skipped_and_counted():
    begun, p = _producer_run(catch_up_s=0.005)
    gaps = sum(b - a - 1 for a, b in zip(begun, begun[1:]))
    assert p.skipped == gaps >= 20                 # ~30 slots owed, at most 5 sent late
    assert p.sent_late >= 1
