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

Both call ``begin(number, counter, wall_s)`` once per SYNC, before any answer to it
can be received: ``number`` counts SYNCs since the producer started (1, 2, ...),
``counter`` is the counter byte (None without one), ``wall_s`` the bus time of the
SYNC (answers received before it belong to an earlier SYNC).
"""
from __future__ import annotations

import threading
import time
from typing import Callable

import can

SYNC_COB_ID = 0x80
Begin = Callable[[int, "int | None", float], None]


class _Producer:
    """Shared bookkeeping: the number of the latest SYNC and the time grid."""

    def __init__(self, period_s: float, counter_overflow: int | None, begin: Begin):
        self.period_s = period_s
        self.overflow = counter_overflow        # None: SYNC without a counter byte
        self.begin = begin
        self.number = 0                          # latest SYNC begun
        self.t0: float | None = None             # perf_counter() of SYNC number 0 on the grid
        self.late = 0                            # slots skipped (thread) / not observed (kernel)
        self._cv = threading.Condition()

    def counter_of(self, number: int) -> int | None:
        return None if self.overflow is None else (number - 1) % self.overflow + 1

    def _begun(self, number: int, counter: int | None, wall_s: float) -> None:
        self.begin(number, counter, wall_s)
        with self._cv:
            self.number = number
            self._cv.notify_all()

    def wait_next(self, after: int, timeout_s: float) -> int:
        """The number of the latest SYNC once it is newer than ``after``; ``after`` on timeout."""
        with self._cv:
            self._cv.wait_for(lambda: self.number > after, timeout_s)
            return self.number

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

    def slot_end(self, number: int) -> float:
        """perf_counter() when SYNC ``number + 1`` is due: answers to ``number`` must be in by then."""
        return self.t0 + (number + 1) * self.period_s


class KernelSyncProducer(_Producer):
    """SYNC from the socketcan broadcast manager; slots begun from the SYNCs seen on the bus."""

    kind = "kernel"

    def __init__(self, network, period_s: float, counter_overflow: int | None, begin: Begin):
        super().__init__(period_s, counter_overflow, begin)
        self.network = network                   # canopen.Network on a socketcan bus
        self.task = None

    @staticmethod
    def available(bus: can.BusABC) -> bool:
        return type(bus).__name__ == "SocketcanBus"

    def start(self) -> "KernelSyncProducer":
        counters = range(1, self.overflow + 1) if self.overflow else [None]
        frames = [can.Message(arbitration_id=SYNC_COB_ID, is_extended_id=False,
                              data=b"" if c is None else bytes([c])) for c in counters]
        self.network.subscribe(SYNC_COB_ID, self._on_sync)
        self.task = self.network.bus.send_periodic(frames, self.period_s)
        return self

    def stop(self) -> None:
        if self.task is not None:
            try:
                self.task.stop()
            finally:
                self.task = None
                self.network.unsubscribe(SYNC_COB_ID, self._on_sync)


class ThreadSyncProducer(_Producer):
    """SYNC from a thread at absolute deadlines (buses without a kernel producer)."""

    kind = "thread"

    def __init__(self, network, period_s: float, counter_overflow: int | None, begin: Begin):
        super().__init__(period_s, counter_overflow, begin)
        self.network = network
        # udp_multicast hears its own frames: slots then begin on the SYNC as received, in bus order
        self.observe = type(network.bus).__name__ == "UdpMulticastBus" and counter_overflow is not None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> "ThreadSyncProducer":
        if self.observe:
            self.network.subscribe(SYNC_COB_ID, self._on_sync)
        self.t0 = time.perf_counter()
        self._thread = threading.Thread(target=self._run, name="sync-producer", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        number = 0
        while not self._stop.is_set():
            number += 1
            due = self.t0 + number * self.period_s
            late = time.perf_counter() - due
            if late > self.period_s / 2:          # host stalled: skip the missed slots, keep the grid
                missed = int(late / self.period_s + 0.5)
                number += missed
                self.late += 0 if self.observe else missed   # observed: the counter jump counts it
                due = self.t0 + number * self.period_s
            # sleep, never spin: a spinning thread holds the GIL the receive thread needs
            if self._stop.wait(max(0.0, due - time.perf_counter())):
                break
            counter = self.counter_of(number)
            if not self.observe:
                self._begun(number, counter, time.time())    # before sending: no answer can precede it
            self.network.send_message(SYNC_COB_ID, b"" if counter is None else bytes([counter]))

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            self._thread = None
        if self.observe:
            self.network.unsubscribe(SYNC_COB_ID, self._on_sync)


def start_sync_producer(network, period_s: float, counter_overflow: int | None, begin: Begin,
                        kind: str = "auto") -> _Producer:
    """``kind``: "auto" (kernel on socketcan, else thread), "kernel" or "thread"."""
    if kind == "auto":
        kind = "kernel" if KernelSyncProducer.available(network.bus) else "thread"
    if kind == "kernel":
        if not KernelSyncProducer.available(network.bus):
            raise ValueError(f"sync: kernel needs a socketcan bus, not {type(network.bus).__name__}")
        return KernelSyncProducer(network, period_s, counter_overflow, begin).start()
    if kind == "thread":
        return ThreadSyncProducer(network, period_s, counter_overflow, begin).start()
    raise ValueError(f"sync: '{kind}' is not one of auto, kernel, thread, loop")
