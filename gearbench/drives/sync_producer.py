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
  deadline ``t0 + k x period`` (no drift), so the time base stays number x period;
  how it catches up after a late wake-up is below.

Both also take over receiving (``receive=True``, the paced master's choice): python-can's
notifier wakes for every frame (SYNC, four TPDOs, heartbeats), and on a tester PC each
wake-up of a thread costs ~30 us of CPU; instead one acquisition thread wakes once per
period, takes every frame received since (in the bus's order, which is what decides a
slot: answers before the next SYNC), hands them to canopen, and for the thread producer
sends the next SYNC. Answers are thus seen one period after their SYNC; nothing is
judged by when they are seen. The notifier is restored when the producer stops.

Late wake-ups (a VM's vCPU not run for a few ms, both cores hogged): the thread producer
sends every SYNC whose deadline has passed at once, oldest first, when the drives echo the
SYNC counter (``catch_up_s`` > 0: each answer names its SYNC, so a burst is matched
exactly); the SYNC went out late, which is a timing fault, counted (``sent_late``,
``sent_late_max_s``), not a lost sample — but the drives sampled when it arrived, so its
sample is stamped with that time (``sent_late_by``), never the grid's, and the analysis
treats a sample off the grid as lost (``station.analyse.fill_lost_samples``). Slots further back than ``catch_up_s`` (and every
missed slot without an echo, where answers are matched by bus order) are skipped
(``skipped``): those samples are lost.

The frames taken each period go to ``take(frames)`` in one call (the network's batch
handler: one lock, no per-frame dispatch through canopen) where given, else one by one
to canopen's ``notify``.

Both call ``begin(number, counter, wall_s)`` once per SYNC, before any answer to it
can be received: ``number`` counts SYNCs since the producer started (1, 2, ...),
``counter`` is the counter byte (None without one), ``wall_s`` the bus time of the
SYNC (answers received before it belong to an earlier SYNC).
"""
from __future__ import annotations

import ctypes
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
Frame = "tuple[int, bytes, float]"
Take = Callable[[list], None]


class _Producer:
    """Shared bookkeeping: the number of the latest SYNC and the time grid."""

    kind = "?"

    def __init__(self, period_s: float, counter_overflow: int | None, begin: Begin,
                 take: Take | None = None, catch_up_s: float = 0.0):
        self.network = None                      # canopen.Network (subclasses set it)
        self.take = take                         # batch handler of the frames taken per period
        self.catch_up_s = catch_up_s             # missed slots this far back are sent late, not skipped
        self.sent_late = 0                       # SYNCs sent more than half a period after their deadline
        self.sent_late_max_s = 0.0               # the latest of them, behind its deadline
        # SYNC number -> seconds behind its deadline, for the SYNCs sent late: the drives
        # sampled then, not on the grid (the master stamps the sample so; the sample loop pops)
        self.sent_late_by: dict[int, float] = {}
        self.receive = False                     # this producer's thread receives (see module doc)
        self.exception: BaseException | None = None   # first error of a receive callback (kept going)
        self.frames = 0                          # frames received by the thread
        self.priority = "not started"            # what the thread's scheduling became
        self.skipped = 0                         # slots the thread producer never sent (beyond catch_up_s)
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

    def _taker(self) -> Callable[[], None]:
        """One call that takes every frame received since the last one, in order, to ``take``
        (or frame by frame to canopen's dispatch)."""
        recv, take, notify = _reader(self.network.bus), self.take, self.network.notify

        def drain() -> None:
            frames = recv()
            if not frames:
                return
            self.frames += len(frames)
            try:
                if take is not None:
                    take(frames)
                else:
                    for can_id, data, timestamp in frames:
                        notify(can_id, data, timestamp)
            except Exception as exc:   # one bad callback must not end acquisition; kept, reported
                self.exception = self.exception or exc
        return drain

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
    the master's CPU each; udp_multicast's frames are packed once and go straight to its
    socket (python-can's send adds a timeout check and a length check per call)."""
    multicast = getattr(bus, "_multicast", None)
    sock = getattr(multicast, "_socket", None)
    if type(bus).__name__ == "UdpMulticastBus" and sock is not None and hasattr(multicast, "_send_destination"):
        from can.interfaces.udp_multicast.utils import pack_message
        sock.settimeout(None)     # blocking sends, as python-can's send(timeout=None)
        return [partial(sock.sendto, pack_message(f), multicast._send_destination) for f in frames]
    return [partial(bus.send, f) for f in frames]


class _Iovec(ctypes.Structure):
    _fields_ = [("base", ctypes.c_void_p), ("len", ctypes.c_size_t)]


class _Msghdr(ctypes.Structure):
    _fields_ = [("name", ctypes.c_void_p), ("namelen", ctypes.c_uint32), ("iov", ctypes.POINTER(_Iovec)),
                ("iovlen", ctypes.c_size_t), ("control", ctypes.c_void_p), ("controllen", ctypes.c_size_t),
                ("flags", ctypes.c_int)]


class _Mmsghdr(ctypes.Structure):
    _fields_ = [("hdr", _Msghdr), ("len", ctypes.c_uint)]


class _BatchReceiver:
    """Every datagram waiting on a UDP socket with its SO_TIMESTAMPNS receive time, in one
    ``recvmmsg`` call (Linux): one system call per period instead of one per frame plus the
    one that finds the socket empty (on a VM each costs the master several microseconds)."""

    SLOTS, SIZE, CONTROL = 64, 512, 64      # datagrams per call, bytes per datagram (a CAN FD frame
                                            # in msgpack is ~230), control bytes (one timespec cmsg)
    MSG_DONTWAIT = 0x40

    def __init__(self, sock: socket.socket):
        libc = ctypes.CDLL(None, use_errno=True)
        self._recvmmsg = libc.recvmmsg
        self._recvmmsg.argtypes = [ctypes.c_int, ctypes.POINTER(_Mmsghdr), ctypes.c_uint, ctypes.c_int, ctypes.c_void_p]
        self._fd = sock.fileno()
        n = self.SLOTS
        self.data = ctypes.create_string_buffer(n * self.SIZE)
        self.control = ctypes.create_string_buffer(n * self.CONTROL)
        self._iov = (_Iovec * n)()
        self.msgs = (_Mmsghdr * n)()
        base, cbase = ctypes.addressof(self.data), ctypes.addressof(self.control)
        for i in range(n):
            self._iov[i].base, self._iov[i].len = base + i * self.SIZE, self.SIZE
            h = self.msgs[i].hdr
            h.iov, h.iovlen = ctypes.pointer(self._iov[i]), 1
            h.control, h.controllen = cbase + i * self.CONTROL, self.CONTROL
        self.view = memoryview(self.data).cast("B")
        self.cview = memoryview(self.control).cast("B")
        # the headers read and reset through one buffer at fixed offsets (a ctypes field access
        # builds an object per access): received length, control length
        self.hview = memoryview(self.msgs).cast("B")
        self.header = ctypes.sizeof(_Mmsghdr)
        self.length_at = _Mmsghdr.len.offset
        self.control_at = _Mmsghdr.hdr.offset + _Msghdr.controllen.offset
        self._args = (self._fd, self.msgs, self.SLOTS, self.MSG_DONTWAIT, None)

    def receive(self) -> int:
        """Datagrams now in slots 0..n-1 (length at ``length_at`` of each header; the control
        length, which the kernel lowers to what it wrote, is restored by the caller)."""
        return max(self._recvmmsg(*self._args), 0)   # -1: EAGAIN (nothing waiting) or EINTR


def _reader(bus: can.BusABC) -> Callable[[], list[tuple[int, bytes, float]]]:
    """A call that returns every data frame waiting on ``bus`` as (id, data, receive time), without
    blocking. udp_multicast is read straight from its socket (no select, no Message object), all
    waiting datagrams in one recvmmsg where Linux has it, else one recvmsg per frame; other buses
    by recv(0)."""
    multicast = getattr(bus, "_multicast", None)
    sock = getattr(multicast, "_socket", None)
    if type(bus).__name__ == "UdpMulticastBus" and sock is not None and \
            getattr(multicast, "timestamp_nanosecond", False):
        import msgpack
        unpackb, size, ancillary = msgpack.unpackb, multicast.max_buffer, multicast.received_ancillary_buffer_size
        timespec = struct.Struct(multicast.received_timestamp_struct).unpack
        fd = bool(getattr(bus, "protocol", None) is can.CanProtocol.CAN_FD)
        try:
            batch = _BatchReceiver(sock)
        except (OSError, AttributeError):      # not Linux / no recvmmsg
            batch = None
        if batch is not None:
            # a cmsghdr (len: size_t, level: int, type: int) then the timespec (two longs)
            head = struct.calcsize("@Nii")
            stamp = struct.Struct("@ll").unpack_from
            length = struct.Struct("@I").unpack_from
            control = struct.Struct("@N")
            view, cview, hview, slot, cslot = batch.view, batch.cview, batch.hview, batch.SIZE, batch.CONTROL
            header, length_at, control_at, slots = batch.header, batch.length_at, batch.control_at, batch.SLOTS

            def read_batch() -> list[tuple[int, bytes, float]]:
                out = []
                while n := batch.receive():
                    for i in range(n):
                        h, d = i * header, i * slot
                        m = unpackb(view[d:d + length(hview, h + length_at)[0]], raw=False)
                        if m.get("is_error_frame") or m.get("is_remote_frame") or (m.get("is_fd") and not fd):
                            continue      # as python-can and canopen do: not a data frame of this bus
                        if control.unpack_from(hview, h + control_at)[0] >= head:
                            sec, ns = stamp(cview, i * cslot + head)
                            out.append((m["arbitration_id"], m["data"], sec + ns * 1e-9))
                        else:
                            out.append((m["arbitration_id"], m["data"], 0.0))
                        control.pack_into(hview, h + control_at, cslot)
                    if n < slots:
                        return out
                return out
            return read_batch

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
                 receive: bool = False, take: Take | None = None, catch_up_s: float = 0.0):
        super().__init__(period_s, counter_overflow, begin, take)   # the kernel never falls behind: no catch-up
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
        drain, clock, sleep, stop = self._taker(), time.perf_counter, time.sleep, self._stop
        due = clock()
        while not stop.is_set():
            now = clock()
            if due > now:
                sleep(due - now)    # sleep, never spin: a spinning thread holds the GIL the others need
            drain()
            due = max(due + self.period_s, clock())

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
                 receive: bool = False, take: Take | None = None, catch_up_s: float = 0.0):
        super().__init__(period_s, counter_overflow, begin, take, catch_up_s)
        self.network = network
        self.receive = receive
        # udp_multicast hears its own frames: slots then begin on the SYNC as received, in bus order;
        # not where answers echo the counter (catch_up_s > 0): they name their SYNC, order does not matter
        self.direct = catch_up_s > 0 and counter_overflow is not None
        self.observe = type(network.bus).__name__ == "UdpMulticastBus" and counter_overflow is not None \
            and not self.direct

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
        drain = self._taker() if self.receive else (lambda: None)
        # the grid starts when this thread runs, not when start() was called: a thread that
        # a busy host starts 100 ms late would otherwise skip its first slots (CI: 46 of them)
        self.t0 = time.perf_counter()
        clock, sleep, stop, period, t0 = time.perf_counter, time.sleep, self._stop, self.period_s, self.t0
        # a burst only where each answer names its SYNC (counter echo): see the module doc
        catch_up = max(1, round(self.catch_up_s / period)) if self.overflow else 1
        number = 0           # the last slot sent (or skipped)
        overflow, direct, begin, wall = self.overflow, self.direct, self.begin, time.time
        while not stop.is_set():
            due = t0 + (number + 1) * period
            now = clock()
            if due > now:
                sleep(due - now)   # sleep, never spin (a spinning thread holds the GIL the others need)
                now = clock()
            # every slot whose deadline has passed: normally just number + 1
            last = number + 1 + max(0, int((now - due) / period))
            first = max(number + 1, last - catch_up + 1)
            if first > number + 1:        # too far behind: the oldest slots are skipped (lost)
                missed = first - number - 1
                self.skipped += missed
                self.late += 0 if self.observe else missed   # observed: the counter jump counts it
            for n in range(first, last + 1):
                behind = now - (t0 + n * period)
                if behind > period / 2:
                    self.sent_late += 1
                    self.sent_late_max_s = max(self.sent_late_max_s, behind)
                    if len(self.sent_late_by) > 4096:   # never taken (their samples were lost)
                        self.sent_late_by.clear()
                    self.sent_late_by[n] = behind
                counter = None if overflow is None else (n - 1) % overflow + 1
                if direct:
                    begin(n, counter, wall())
                    self.number = n
                    send[counter - 1]()
                elif self.observe:
                    # the SYNC first, on time; its slot begins where it is seen on the bus, in order,
                    # so the answers to the SYNCs before it may be taken after it is sent
                    send[counter - 1 if counter else 0]()
                else:
                    drain()        # the answers to the SYNCs before this one
                    self._begun(n, counter, time.time())    # before sending: no answer can precede it
                    send[counter - 1 if counter else 0]()
            number = last
            if direct:
                self._begun_at = time.monotonic()
            drain()

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
                        kind: str = "auto", receive: bool = False, take: Take | None = None,
                        catch_up_s: float = 0.0) -> _Producer:
    """``kind``: "auto" (kernel on socketcan, else thread), "kernel" or "thread"; ``receive``:
    the producer's thread takes over receiving from python-can's notifier, handing each
    period's frames to ``take`` (see module doc); ``catch_up_s``: how far back missed SYNC
    slots are still sent (0: skipped)."""
    if kind == "auto":
        kind = "kernel" if KernelSyncProducer.available(network.bus) else "thread"
    if kind == "kernel":
        if not KernelSyncProducer.available(network.bus):
            raise ValueError(f"sync: kernel needs a socketcan bus, not {type(network.bus).__name__}")
        return KernelSyncProducer(network, period_s, counter_overflow, begin, receive, take).start()
    if kind == "thread":
        return ThreadSyncProducer(network, period_s, counter_overflow, begin, receive, take, catch_up_s).start()
    raise ValueError(f"sync: '{kind}' is not one of auto, kernel, thread, loop")
