"""Supervision that judges the drive, not the host.

A drive is alive while frames from it keep arriving: heartbeats, but also every
TPDO, EMCY or SDO answer (CiA 301 heartbeat consumer, generalised: any frame of
the node is proof of life). A drive is *silent* when none has arrived for its
timeout.

The difficulty on a busy tester PC is that "none has arrived" is measured by the
host, and a host that was not scheduled for 300 ms has received nothing from
anybody in that time — the drives kept talking, their frames wait in the socket
buffer. So silence is measured on a clock that stops while the host is stalled:
``HostStallMonitor`` is a small thread that wakes every ``tick_s``; when it wakes
much later than asked, the host (this process) was not running, and that gap is
recorded. ``Liveness.silent_s`` subtracts the stalls since a node's last frame
from the time since that frame. Stalls are counted and reported, never silently
absorbed: they appear in the run's result.

Suspicion is confirmed before a verdict (``CiA402Network`` probes a suspected
drive with an SDO read: a drive that answers is alive whatever the timers say),
so a real drive silent beyond its timeout still stops the bench within about its
timeout, and a starved host does not abort a good unit.
"""
from __future__ import annotations

import bisect
import os
import threading
import time


class HostStallMonitor:
    """Measures host stalls: a thread that asks to wake every ``tick_s`` and records
    any wake-up later than ``threshold_s`` as a stall (start, duration)."""

    def __init__(self, tick_s: float = 0.01, threshold_s: float = 0.01, keep: int = 20000):
        self.tick_s, self.threshold_s, self.keep = tick_s, threshold_s, keep
        self._ends: list[float] = []          # end time of each recorded stall (increasing)
        self._cumulative: list[float] = []    # total stall seconds up to and including it
        self.count = 0                        # stalls longer than REPORT_S (what the run reports)
        self.total_s = 0.0
        self.max_s = 0.0
        self._base = 0.0                      # cumulative stall before the oldest kept record
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> "HostStallMonitor":
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="host-stall-monitor", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            self._thread = None

    def _run(self) -> None:
        due = time.monotonic() + self.tick_s
        while not self._stop.wait(max(0.0, due - time.monotonic())):
            now = time.monotonic()
            late = now - due
            if late > self.threshold_s:
                self.record(due, late)
            due = now + self.tick_s

    REPORT_S = 0.05    # stalls at least this long are counted in the run's report

    def record(self, start_s: float, duration_s: float) -> None:
        with self._lock:
            self.total_s += duration_s
            self._ends.append(start_s + duration_s)
            self._cumulative.append(self.total_s)
            if len(self._ends) > 2 * self.keep:    # keep the recent history only
                self._base = self._cumulative[self.keep - 1]
                del self._ends[:self.keep], self._cumulative[:self.keep]
            if duration_s >= self.REPORT_S:
                self.count += 1
            self.max_s = max(self.max_s, duration_s)

    def stalled_since(self, t_s: float) -> float:
        """Seconds stalled after monotonic time ``t_s`` (a stall straddling ``t_s`` counts whole)."""
        with self._lock:
            i = bisect.bisect_right(self._ends, t_s)
            return self.total_s - (self._cumulative[i - 1] if i > 0 else self._base)

    def poll(self) -> None:
        """Nothing to bring up to date: a stall of this process is seen when it runs again."""

    def summary(self) -> dict:
        return {"host_stalls": self.count, "host_stall_total_s": round(self.total_s, 4),
                "host_stall_max_s": round(self.max_s, 4)}


class RunQueueMonitor(HostStallMonitor):
    """Stalls of *another* process on this host (the emulated drives of ``--sim``):
    the time its threads were runnable but not running, from Linux's per-thread
    ``/proc/PID/task/TID/schedstat`` (second field: run-queue wait, ns). A real drive
    has its own processor; an emulated one shares ours, so its run-queue waits are
    host stalls, not drive silence. A process that died or hangs in a lock has no
    run-queue wait: its silence still counts. Waits are summed between reads, so the
    tick only sets how fresh the record is; a verdict polls first (at 10 ms it cost
    the master ~40 us of CPU per millisecond, /proc reads of every thread)."""

    def __init__(self, pid: int, tick_s: float = 0.1, threshold_s: float = 0.002):
        super().__init__(tick_s=tick_s, threshold_s=threshold_s)
        self.pid = pid
        self._waits: dict[str, int] = {}
        self._poll_lock = threading.Lock()

    def _read(self) -> dict[str, int]:
        out = {}
        try:
            for tid in os.listdir(f"/proc/{self.pid}/task"):
                with open(f"/proc/{self.pid}/task/{tid}/schedstat") as f:
                    out[tid] = int(f.read().split()[1])
        except (OSError, ValueError, IndexError):
            pass
        return out

    def _run(self) -> None:
        self.poll()
        while not self._stop.wait(self.tick_s):
            self.poll()

    def runnable(self) -> bool:
        """True if a thread of the process is running or waiting for a CPU right now.

        Linux accounts a run-queue wait only when the wait ends, so a process starved
        at this very moment shows no stall yet; its state says it is alive."""
        try:
            for tid in os.listdir(f"/proc/{self.pid}/task"):
                with open(f"/proc/{self.pid}/task/{tid}/stat") as f:
                    if f.read().rpartition(")")[2].split()[0] == "R":
                        return True
        except (OSError, IndexError):
            return False
        return False

    def poll(self) -> None:
        """Bring the record up to now (also called by a supervisor about to judge silence:
        this thread may itself have been waiting for the CPU)."""
        with self._poll_lock:
            now, waits = time.monotonic(), self._read()
            # the largest wait of any one thread: threads waiting on each other's lock are
            # asleep, not runnable, so the stalled thread is the one that was runnable
            delta = max((w - self._waits.get(t, w) for t, w in waits.items()), default=0) / 1e9
            self._waits = waits
            if delta > self.threshold_s:
                self.record(now - delta, delta)


class Liveness:
    """Last frame heard from each node, and how long each has been silent on a
    clock that does not run while the host is stalled."""

    def __init__(self, monitor: HostStallMonitor):
        self.monitor = monitor
        self.drive_monitors: list[HostStallMonitor] = []   # stalls of processes that emulate drives
        self.last_heard: dict[int, float] = {}

    def heard(self, node: int, t_s: float | None = None) -> None:
        self.last_heard[node] = time.monotonic() if t_s is None else t_s

    def reset(self, nodes) -> None:
        now = time.monotonic()
        for n in nodes:
            self.last_heard[n] = now

    def poll(self) -> None:
        for m in self.drive_monitors:
            m.poll()

    def starved(self) -> bool:
        """A process emulating drives is runnable right now: it is alive, only waiting for a CPU."""
        return any(m.runnable() for m in self.drive_monitors)

    def silent_s(self, node: int, now_s: float | None = None) -> float:
        """Time since the node's last frame, minus host stalls in between."""
        now = time.monotonic() if now_s is None else now_s
        last = self.last_heard.get(node, now)
        stalled = self.monitor.stalled_since(last) + sum(m.stalled_since(last) for m in self.drive_monitors)
        return max(0.0, now - last - stalled)
