"""CPU time by thread, from Linux's per-thread schedstat (load-insensitive figures).

``/proc/PID/task/TID/schedstat`` field 1 is the time the thread ran, in ns; field 2
the time it waited runnable for a CPU. A busy host lengthens the second, not the
first, so CPU per sample is the figure that does not depend on who else runs.
"""
from __future__ import annotations

import os
import threading


def threads(pid: int | str = "self", exclude: frozenset[str] = frozenset()) -> dict[str, tuple[str, float, float, int]]:
    """{tid: (thread name, run s, run-queue wait s, wake-ups)} of every live thread of ``pid`` but
    ``exclude``. Wake-ups are the voluntary context switches (each sleep or blocking call that
    ended): a preemption by another process is not the thread's doing and a loaded host adds many."""
    out = {}
    base = f"/proc/{pid}/task"
    try:
        tids = os.listdir(base)
    except OSError:
        return out
    named = {str(t.native_id): t.name for t in threading.enumerate()} if pid == "self" else {}
    for tid in tids:
        if tid in exclude:
            continue
        try:
            with open(f"{base}/{tid}/comm") as f:
                name = named.get(tid) or f.read().strip()
            with open(f"{base}/{tid}/schedstat") as f:
                run_ns, wait_ns = (int(v) for v in f.read().split()[:2])
            with open(f"{base}/{tid}/status") as f:
                slices = next(int(ln.split()[1]) for ln in f if ln.startswith("voluntary_ctxt_switches"))
        except (OSError, ValueError):
            continue
        out[tid] = (name, run_ns / 1e9, wait_ns / 1e9, slices)
    return out


def foreign_threads() -> frozenset[str]:
    """The threads of this process alive now but the caller's: whatever earlier work left running
    (in a test session, e.g. the Rerun batcher threads of earlier runs), excluded from a
    measurement of the master started after this call."""
    me = str(threading.get_native_id())
    return frozenset(t for t in os.listdir("/proc/self/task") if t != me)


def user_system(pid: int | str = "self") -> tuple[float, float]:
    """(user s, system s) of the whole process from /proc/PID/stat (clock-tick resolution):
    the system share is the kernel's work for it (socket calls, wake-ups)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    tick = os.sysconf("SC_CLK_TCK")
    return int(fields[11]) / tick, int(fields[12]) / tick


def delta(before: dict, after: dict) -> dict[str, float]:
    """CPU seconds used between two ``threads()`` snapshots, summed by thread name
    (threads born in between count from zero; threads that ended are not seen)."""
    out: dict[str, float] = {}
    for tid, (name, run_s, *_) in after.items():
        out[name] = out.get(name, 0.0) + run_s - (before[tid][1] if tid in before else 0.0)
    return out


def wakeups(before: dict, after: dict) -> int:
    """Times the threads woke from a sleep or blocking call between two ``threads()`` snapshots
    (on a VM each costs microseconds of CPU the figures above include)."""
    return sum(s - (before[tid][3] if tid in before else 0) for tid, (_, _, _, s) in after.items())


STAND_IN_FIFO = 20          # above the master's acquisition (drives.realtime.FIFO_PRIORITY = 10)


def realtime_stand_in(pid: int, priority: int = STAND_IN_FIFO) -> str:
    """Every thread of process ``pid`` (the drives' stand-in) to SCHED_FIFO ``priority``, above
    the master's: drive hardware answers whatever the PC does. Returns what was granted."""
    granted = 0
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            os.sched_setscheduler(int(tid), os.SCHED_FIFO, os.sched_param(priority))
            granted += 1
        except (OSError, AttributeError):
            pass
    return f"SCHED_FIFO {priority}" if granted else "normal (SCHED_FIFO refused)"


def normal_priority() -> None:
    """``preexec_fn`` of the CPU hogs: a child forked from a real-time thread inherits SCHED_FIFO,
    and a spinning hog at SCHED_FIFO starves the whole host (it did once, for ten minutes), not
    just what it should compete with. Back to normal scheduling, nice 0."""
    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    os.setpriority(os.PRIO_PROCESS, 0, 0)


def load_average() -> str:
    """The host's 1/5/15-minute load average (the host is shared: every figure says it)."""
    return "/".join(f"{v:.1f}" for v in os.getloadavg())


_PROBE = """
import json, os, sys, time
try:
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param({priority}))
except (OSError, AttributeError):
    pass
period, n, late = {period_s}, {n}, []
due = time.perf_counter()
for _ in range(n):
    due += period
    time.sleep(max(0.0, due - time.perf_counter()))
    late.append(time.perf_counter() - due)
late.sort()
print(json.dumps(dict(n=n, over_half=sum(v > period / 2 for v in late), p99_s=late[int(0.99 * (n - 1))],
                      max_s=late[-1], over_slack=sum(v > {slack_s} for v in late))))
"""


def timer_floor(period_s: float = 1e-3, seconds: float = 2.0, priority: int = 10, slack_s: float | None = None) -> dict:
    """What this host allows at best: a process that does nothing but sleep to absolute
    deadlines every ``period_s`` at SCHED_FIFO ``priority`` (the master's), how often it
    wakes more than half a period late (a SYNC slot any user-space producer would miss),
    more than ``slack_s`` late (``over_slack``: a Modbus read that would miss its cell)
    and its p99/max lateness. On a virtual machine this is the hypervisor's floor."""
    import json
    import subprocess
    import sys
    code = _PROBE.format(priority=priority, period_s=period_s, n=max(1, round(seconds / period_s)),
                         slack_s=period_s / 2 if slack_s is None else slack_s)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=seconds + 30)
    return json.loads(out.stdout)


def floor_text(f: dict, period_s: float) -> str:
    return (f"host timer floor (a SCHED_FIFO process only sleeping to {period_s * 1e3:g} ms deadlines): "
            f"{f['over_half']} of {f['n']} wake-ups later than half a period, p99 {f['p99_s'] * 1e6:.0f} us, "
            f"max {f['max_s'] * 1e6:.0f} us")
