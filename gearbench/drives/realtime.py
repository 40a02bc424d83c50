"""The acquisition thread's share of a busy PC: priority and no garbage collection.

``acquisition_priority()`` wraps one acquisition (a segment): it asks the OS for
the highest scheduling the process is allowed — SCHED_FIFO (real-time, above every
normal program), else a lower nice value — for the *calling thread* only (on Linux
policy and nice are per thread), and keeps Python's cyclic garbage collector out of
the loop (a full collection can take tens of milliseconds). Both are restored when
the segment ends, where a collection runs instead. What was granted is returned so
the run can report it; nothing is required (a tester PC without the right still
works, with more jitter).

SCHED_FIFO is safe here because the acquisition thread sleeps between samples (it
waits on the bus, never spins); Linux also throttles real-time threads to 95 % of
a core (``/proc/sys/kernel/sched_rt_runtime_us``).

Real-time: *every* thread of the process is raised, not only the acquisition path's.
Python threads share one interpreter lock: a thread at normal priority (the record
writer, a supervision monitor) that a busy PC preempts while it holds the lock blocks
the real-time ones until the OS runs it again — tens of milliseconds with both cores
hogged, measured as SYNCs sent 5-15 ms late. Raised, a thread holding the lock runs
on and hands it over within the switch interval, which is shortened meanwhile to
``SWITCH_INTERVAL_S`` (Python's 5 ms default is five SYNC periods). Threads started
inside keep the priority they inherit (the SYNC producer's thread is one of them).
"""
from __future__ import annotations

import contextlib
import gc
import os
import sys

FIFO_PRIORITY = 10        # low among real-time priorities: above every normal program, below kernel threads
NICE = -10
SWITCH_INTERVAL_S = 2e-4  # the longest one Python thread keeps the interpreter while another waits


def _try_fifo(tid: int) -> str | None:
    if not hasattr(os, "sched_setscheduler"):
        return None
    try:
        os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(FIFO_PRIORITY))
        return f"SCHED_FIFO {FIFO_PRIORITY}"
    except (OSError, AttributeError):
        return None


def _try_nice(tid: int) -> str | None:
    if not hasattr(os, "setpriority"):
        return None
    try:
        if os.getpriority(os.PRIO_PROCESS, tid) > NICE:
            os.setpriority(os.PRIO_PROCESS, tid, NICE)
        return f"nice {os.getpriority(os.PRIO_PROCESS, tid)}"
    except OSError:
        return None


def _saved(tid: int):
    try:
        return os.sched_getscheduler(tid), os.sched_getparam(tid), os.getpriority(os.PRIO_PROCESS, tid)
    except (OSError, AttributeError):
        return None


def _restore(tid: int, saved) -> None:
    if saved is None:
        return
    policy, param, nice = saved
    with contextlib.suppress(OSError):
        os.sched_setscheduler(tid, policy, param)
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PROCESS, tid, nice)


@contextlib.contextmanager
def acquisition_priority(threads=(), *, realtime: bool = True, enabled: bool = True):
    """Raise the calling thread's priority (and that of ``threads``, native thread ids of
    the same acquisition path: the bus receiver, the stall monitor) and pause gc;
    yields what was granted, e.g. ``"SCHED_FIFO 10"`` or ``"nice -10"``.

    ``realtime=False`` (lockstep with an emulated bench): nice only, never SCHED_FIFO.
    A lockstep master is busy, not sleeping, between samples, and a real-time thread
    that is busy starves every normal process — the emulated drives first of all."""
    if not enabled or os.environ.get("GEARBENCH_NO_RT") or not hasattr(os, "sched_getscheduler"):
        yield "normal (not requested)"
        return
    tids = [0, *[t for t in threads if t]]
    if realtime:
        tids += [t for t in _own_threads() if t not in tids and t != _self_tid()]
    saved = {tid: _saved(tid) for tid in tids}
    raise_ = (lambda tid: _try_fifo(tid) or _try_nice(tid)) if realtime else _try_nice
    granted = raise_(0) or "normal (the OS granted no higher priority)"
    for tid in tids[1:]:
        raise_(tid)
    gc_was_enabled = gc.isenabled()
    gc.disable()
    interval = sys.getswitchinterval()
    if realtime:
        sys.setswitchinterval(min(interval, SWITCH_INTERVAL_S))
    try:
        yield granted
    finally:
        sys.setswitchinterval(interval)
        for tid, s in saved.items():
            _restore(tid, s)
        if gc_was_enabled:
            gc.enable()


def _own_threads() -> list[int]:
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return []


def _self_tid() -> int:
    return getattr(os, "gettid", lambda: 0)()


def raise_this_thread(above: int = 1) -> str | None:
    """The calling thread to SCHED_FIFO ``FIFO_PRIORITY + above`` where the OS allows it (the
    SYNC producer: above the sample loop, so that the loop, which holds the interpreter lock
    for ~60 us per sample, never makes a SYNC late). None when not granted or not wanted."""
    if os.environ.get("GEARBENCH_NO_RT") or not hasattr(os, "sched_setscheduler"):
        return None
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(FIFO_PRIORITY + above))
        return f"SCHED_FIFO {FIFO_PRIORITY + above}"
    except OSError:
        return None
