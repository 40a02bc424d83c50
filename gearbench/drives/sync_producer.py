"""Who puts SYNC on the bus in paced (real-time) mode, independently of the sample loop.

Real drives latch their setpoints and sample their measurements on SYNC, so SYNC
must come every period on the wall clock whatever the host is doing. Two producers:

- ``KernelSyncProducer`` (socketcan): the kernel's broadcast manager (python-can
  ``bus.send_periodic`` -> CAN_BCM TX_SETUP) sends SYNC from a kernel timer, so host
  scheduling jitter does not move the drives' sampling instants. The frame list is
  the 240 SYNCs with counter 1..240 (CiA 301 0x1019 = 240), cycled by the kernel;
  the master sees each SYNC on its own socket (CAN loopback), before the answers
  to it, and begins that SYNC's slot there.
- ``ThreadSyncProducer`` (any other bus): a thread sends SYNC number k at the absolute
  deadline ``t0 + k x period`` (no drift); a deadline missed by more than half a
  period is skipped and counted (``late``), so the time base stays number x period.

Both also take over receiving (``receive=True``, the paced master's choice): python-can's
notifier wakes for every frame (SYNC, four TPDOs, heartbeats), and on a tester PC each
wake-up of a thread costs ~30 us of CPU; instead one acquisition thread wakes once per
period, takes every frame received since (in the bus's order, which is what decides a
slot: answers before the next SYNC), hands them to canopen, and for the thread producer
sends the next SYNC. Answers are thus seen one period after their SYNC; nothing is
judged by when they are seen. The notifier is restored when the producer stops.

Both call ``begin(number, counter, wall_s)`` once per SYNC, before any answer to it
can be received: ``number`` counts SYNCs since the producer started (1, 2, ...),
``counter`` is the counter byte (None without one), ``wall_s`` the bus time of the
SYNC (answers received before it belong to an earlier SYNC).
"""
from __future__ import annotations

import socket
import struct
import threading
import time
from functools import partial
from typing import Callable

import can

from .realtime import raise_this_thread

SYNC_COB_ID = 0x80
Begin = Callable[[int, "int | None", float], None]


class _Producer:
    """Shared bookkeeping: the number of the latest SYNC and the time grid."""

    kind = "?"

    def __init__(self, period_s: float, counter_overflow: int | None, begin: Begin):
        self.network = None                      # canopen.Network (subclasses set it)
        self.receive = False                     # this producer's thread receives (see module doc)
        self.exception: BaseException | None = None   # first error of a receive callback (kept going)
        self.frames = 0                          # frames received by the thread
        self.priority = "not started"            # what the thread's scheduling became
        self.skipped = 0                         # slots the thread producer skipped (late beyond half a period)
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.period_s = period_s
        self.overflow = counter_overflow        # None: SYNC without a counter byte
        self.begin = begin
        self.number = 0                          # latest SYNC begun
        self.t0: float | None = None             # perf_counter() of SYNC number 0 on the grid
        self.late = 0                            # slots skipped (thread) / not observed (kernel)
        self._begun_at = time.monotonic()

    def idle_s(self) -> float:
        """Seconds since the latest SYNC began (a producer that stopped producing)."""
        return time.monotonic() - self._begun_at

    def counter_of(self, number: int) -> int | None:
        return None if self.overflow is None else (number - 1) % self.overflow + 1

    def _begun(self, number: int, counter: int | None, wall_s: float) -> None:
        self.begin(number, counter, wall_s)
        self.number = number                 # read without the lock: an int, written by one thread
        self._begun_at = time.monotonic()

    def _on_sync(self, can_id, data, timestamp) -> None:   # notifier thread, in bus order
        """Begin the slot of a SYNC seen on the bus: before its answers, whatever the host's timing."""
        now = time.perf_counter()
        if self.overflow and data:
            step = (data[0] - self.counter_of(self.number)) % self.overflow if self.number else data[0]
            number = self.number + (step or self.overflow)
        else:
            number = self.number + 1
        if self.t0 is None:
            self.t0 = now - number * self.period_s
        self.late += number - self.number - 1
        self._begun(number, data[0] if self.overflow and data else None, timestamp)

    # ------------------------------------------------ receiving in the acquisition thread
    def _take_over_receive(self) -> None:
        notifier = getattr(self.network, "notifier", None)
        if notifier is not None:
            notifier.stop(max(1.0, 2 * getattr(self.network, "NOTIFIER_CYCLE", 1.0)))

    def _give_back_receive(self) -> None:
        net = self.network
        if net is not None and net.bus is not None:
            net.notifier = can.Notifier(net.bus, net.listeners, net.NOTIFIER_CYCLE)

    def _drain(self, recv, notify) -> None:
        """Every frame received since the last call, in order, to canopen's dispatch."""
        for can_id, data, timestamp in recv():
            self.frames += 1
            try:
                notify(can_id, data, timestamp)
            except Exception as exc:   # one bad callback must not end acquisition; kept, reported
                self.exception = self.exception or exc

    def _sleep_until(self, due: float) -> bool:
        """Sleep, never spin (a spinning thread holds the GIL the others need); True when stopped."""
        return self._stop.wait(max(0.0, due - time.perf_counter()))

    def native_ids(self) -> list[int]:
        t = self._thread
        return [t.native_id] if t is not None and t.native_id else []

    def slot_end(self, number: int) -> float:
        """perf_counter() when SYNC ``number + 1`` is due: answers to ``number`` must be in by then."""
        return self.t0 + (number + 1) * self.period_s


def _sync_frames(counter_overflow: int | None) -> list[can.Message]:
    """The SYNC frames in counter order (one empty frame without a counter byte)."""
    counters = range(1, counter_overflow + 1) if counter_overflow else [None]
    return [can.Message(arbitration_id=SYNC_COB_ID, is_extended_id=False,
                        data=b"" if c is None else bytes([c])) for c in counters]


def _senders(bus: can.BusABC, frames: list[can.Message]) -> list[Callable[[], None]]:
    """One call per frame that puts it on ``bus``, built once: a SYNC every millisecond
    through canopen's ``send_message`` (a new Message, a lock, a check) cost ~80 us of
    the master's CPU each; udp_multicast's frames are packed once too."""
    multicast = getattr(bus, "_multicast", None)
    if type(bus).__name__ == "UdpMulticastBus" and hasattr(multicast, "send"):
        from can.interfaces.udp_multicast.utils import pack_message
        return [partial(multicast.send, pack_message(f)) for f in frames]
    return [partial(bus.send, f) for f in frames]


def _reader(bus: can.BusABC) -> Callable[[], list[tuple[int, bytes, float]]]:
    """A call that returns every data frame waiting on ``bus`` as (id, data, receive time), without
    blocking. udp_multicast is read straight from its socket (one non-blocking recvmsg per frame,
    no select, no Message object: half of python-can's per-frame cost); other buses by recv(0)."""
    multicast = getattr(bus, "_multicast", None)
    sock = getattr(multicast, "_socket", None)
    if type(bus).__name__ == "UdpMulticastBus" and sock is not None and \
            getattr(multicast, "timestamp_nanosecond", False):
        import msgpack
        unpackb, size, ancillary = msgpack.unpackb, multicast.max_buffer, multicast.received_ancillary_buffer_size
        timespec = struct.Struct(multicast.received_timestamp_struct).unpack
        fd = bool(getattr(bus, "protocol", None) is can.CanProtocol.CAN_FD)

        def read_udp() -> list[tuple[int, bytes, float]]:
            out = []
            while True:
                try:
                    raw, anc, _, _ = sock.recvmsg(size, ancillary, socket.MSG_DONTWAIT)
                except (BlockingIOError, InterruptedError):
                    return out
                m = unpackb(raw, raw=False)
                if m.get("is_error_frame") or m.get("is_remote_frame") or (m.get("is_fd") and not fd):
                    continue      # as python-can and canopen do: not a data frame of this bus
                sec, ns = timespec(anc[0][2]) if anc else (0, 0)
                out.append((m["arbitration_id"], m["data"], sec + ns * 1e-9))
        return read_udp

    def read_any() -> list[tuple[int, bytes, float]]:
        out = []
        while (msg := bus.recv(0.0)) is not None:
            if not (msg.is_error_frame or msg.is_remote_frame):
                out.append((msg.arbitration_id, msg.data, msg.timestamp))
        return out
    return read_any


class KernelSyncProducer(_Producer):
    """SYNC from the socketcan broadcast manager; slots begun from the SYNCs seen on the bus."""

    kind = "kernel"

    def __init__(self, network, period_s: float, counter_overflow: int | None, begin: Begin,
                 receive: bool = False):
        super().__init__(period_s, counter_overflow, begin)
        self.network = network                   # canopen.Network on a socketcan bus
        self.receive = receive
        self.task = None

    @staticmethod
    def available(bus: can.BusABC) -> bool:
        return type(bus).__name__ == "SocketcanBus"

    def start(self) -> "KernelSyncProducer":
        frames = _sync_frames(self.overflow)
        self.network.subscribe(SYNC_COB_ID, self._on_sync)
        if self.receive:
            self._take_over_receive()
            self._thread = threading.Thread(target=self._run, name="sync-receive", daemon=True)
            self._thread.start()
        self.task = self.network.bus.send_periodic(frames, self.period_s)
        return self

    def _run(self) -> None:
        self.priority = raise_this_thread() or "inherited"
        recv, notify = _reader(self.network.bus), self.network.notify
        due = time.perf_counter()
        while not self._sleep_until(due):
            self._drain(recv, notify)
            due = max(due + self.period_s, time.perf_counter())

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            self._thread = None
            self._give_back_receive()
        if self.task is not None:
            try:
                self.task.stop()
            finally:
                self.task = None
                self.network.unsubscribe(SYNC_COB_ID, self._on_sync)


class ThreadSyncProducer(_Producer):
    """SYNC from a thread at absolute deadlines (buses without a kernel producer)."""

    kind = "thread"

    def __init__(self, network, period_s: float, counter_overflow: int | None, begin: Begin,
                 receive: bool = False):
        super().__init__(period_s, counter_overflow, begin)
        self.network = network
        self.receive = receive
        # udp_multicast hears its own frames: slots then begin on the SYNC as received, in bus order
        self.observe = type(network.bus).__name__ == "UdpMulticastBus" and counter_overflow is not None

    def start(self) -> "ThreadSyncProducer":
        if self.observe:
            self.network.subscribe(SYNC_COB_ID, self._on_sync)
        if self.receive:
            self._take_over_receive()
        self.t0 = time.perf_counter()
        self._thread = threading.Thread(target=self._run, name="sync-producer", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        self.priority = raise_this_thread() or "inherited"
        send = _senders(self.network.bus, _sync_frames(self.overflow))
        recv, notify = _reader(self.network.bus), self.network.notify
        number = 0
        while not self._stop.is_set():
            number += 1
            due = self.t0 + number * self.period_s
            late = time.perf_counter() - due
            if late > self.period_s / 2:          # host stalled: skip the missed slots, keep the grid
                missed = int(late / self.period_s + 0.5)
                number += missed
                self.skipped += missed
                self.late += 0 if self.observe else missed   # observed: the counter jump counts it
                due = self.t0 + number * self.period_s
            if self._sleep_until(due):
                break
            counter = self.counter_of(number)
            if self.observe:
                # the SYNC first, on time; its slot begins where it is seen on the bus, in order,
                # so the answers to the SYNCs before it may be taken after it is sent
                send[counter - 1 if counter else 0]()
                if self.receive:
                    self._drain(recv, notify)
            else:
                if self.receive:    # the answers to the SYNCs before this one
                    self._drain(recv, notify)
                self._begun(number, counter, time.time())    # before sending: no answer can precede it
                send[counter - 1 if counter else 0]()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            self._thread = None
        if self.receive:
            self._give_back_receive()
        if self.observe:
            self.network.unsubscribe(SYNC_COB_ID, self._on_sync)


def start_sync_producer(network, period_s: float, counter_overflow: int | None, begin: Begin,
                        kind: str = "auto", receive: bool = False) -> _Producer:
    """``kind``: "auto" (kernel on socketcan, else thread), "kernel" or "thread"; ``receive``:
    the producer's thread takes over receiving from python-can's notifier (see module doc)."""
    if kind == "auto":
        kind = "kernel" if KernelSyncProducer.available(network.bus) else "thread"
    if kind == "kernel":
        if not KernelSyncProducer.available(network.bus):
            raise ValueError(f"sync: kernel needs a socketcan bus, not {type(network.bus).__name__}")
        return KernelSyncProducer(network, period_s, counter_overflow, begin, receive).start()
    if kind == "thread":
        return ThreadSyncProducer(network, period_s, counter_overflow, begin, receive).start()
    raise ValueError(f"sync: '{kind}' is not one of auto, kernel, thread, loop")
