"""The paced CANopen master's CPU cost per sample, in CPU seconds (Linux schedstat: time
the master's threads ran), not wall time: a busy CI host lengthens the waits, not the
work. Two drives over udp_multicast, SYNC every 1 ms on the wall clock, 1,000 SYNCs:
the drives configured by the emulator (``gearbench emulate``, another process), their
SYNCs answered by the compiled responder (``tools/responder``, another process), so the
figure is the master's alone — the process running this test — as
``python -m gearbench.benchmarks drives_can --paced`` measures it.

What it guards: the acquisition path once cost over 1 ms of CPU per sample (python-can's
notifier thread woke for every frame, supervision ran per sample, a normal-priority
thread holding the interpreter lock stalled the real-time ones), and 163-196 us before
the batch receive (one recvmmsg, one lock per period), the sample loop woken once per
4 ms and the frames kept off the VM's virtual NIC."""
import os
import shutil

import pytest

from gearbench.benchmarks import _responder
from gearbench.benchmarks.drives_can import run_once

SYNCS = 1000
# Measured 109-114 us per SYNC at load 8-9 on the shared 2-core VM (203-215 us at load 10 before
# the last cuts; CPU time inflates with load there: every context switch and wake-up is dearer).
# The bound leaves over 2x for a loaded CI host and still fails a return of any regression above.
MAX_CPU_PER_SYNC_S = 250e-6
# Thread wake-ups (schedstat's third field: times a thread was put on a CPU) per SYNC, all the
# master's threads together: one for the acquisition thread, a quarter for the sample loop (woken
# once per 4 ms), supervision's ticks (1.37-1.41 measured); a receiver that wakes for every frame
# adds five, a sample loop woken per sample one.
MAX_WAKEUPS_PER_SYNC = 2.0

pytestmark = [pytest.mark.skipif(not os.path.exists("/proc/self/task"), reason="needs Linux schedstat"),
              pytest.mark.skipif(_responder.available() is not None or shutil.which("gcc") is None,
                                 reason=f"needs the compiled responder ({_responder.available()})")]


def test_paced_master_cpu_per_sample_is_bounded():
    r = run_once("udp_multicast", SYNCS * 1e-3, 1e-3, paced=True)
    print(f"master: {r['master_cpu_us']:.0f} us CPU and {r['master_wakeups_per_sync']:.2f} wake-ups per SYNC over "
          f"{r['syncs']} SYNCs ({r['lost']} lost, stand-in {r['stand_in']}: {r['stand_in_counters']}; load {r['load']})")
    assert r["stand_in_counters"]["syncs_missed"] == 0      # the stand-in heard every SYNC sent
    assert r["master_cpu_us"] <= MAX_CPU_PER_SYNC_S * 1e6, f"master CPU {r['master_cpu_us']:.0f} us per SYNC"
    assert r["master_wakeups_per_sync"] <= MAX_WAKEUPS_PER_SYNC, \
        f"{r['master_wakeups_per_sync']:.2f} thread wake-ups per SYNC"
