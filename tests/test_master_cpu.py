"""The real-time masters' CPU cost per sample (paced CANopen; free-running Modbus TCP at the end
of the file, against its compiled stand-in), in CPU seconds (Linux schedstat: time
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

from _host_speed import paced_loop_cpu_s

SYNCS = 1000
# Measured 109-114 us per SYNC at load 8-9 on the shared 2-core VM (203-215 us at load 10 before
# the last cuts; CPU time inflates with load there: every context switch and wake-up is dearer).
# The bound leaves over 2x for a loaded CI host and still fails a return of any regression above.
MAX_CPU_PER_SYNC_S = 250e-6
# ... or this many times the host's own minimal paced loop (``_host_speed.paced_loop_cpu_s``),
# whichever is larger: 3.8-4.1 of them on the AMD EPYC VM (258-280 us against 67-70 us)
MAX_PACED_LOOPS_PER_SYNC = 8.0
# Thread wake-ups (voluntary context switches: a sleep or blocking call that ended) per SYNC, all
# the threads the master started together (not what earlier tests left running): one for the
# acquisition thread, a quarter for the sample loop (woken once per 4 ms), supervision's ticks
# (1.37-1.41 measured); a receiver that wakes for every frame adds five, a sample loop woken per
# sample one.
MAX_WAKEUPS_PER_SYNC = 2.0

pytestmark = [pytest.mark.skipif(not os.path.exists("/proc/self/task"), reason="needs Linux schedstat"),
              pytest.mark.skipif(_responder.available() is not None or shutil.which("gcc") is None,
                                 reason=f"needs the compiled responder ({_responder.available()})")]


def test_paced_master_cpu_per_sample_is_bounded():
    r = run_once("udp_multicast", SYNCS * 1e-3, 1e-3, paced=True)
    print(f"master: {r['master_cpu_us']:.0f} us CPU and {r['master_wakeups_per_sync']:.2f} wake-ups per SYNC over "
          f"{r['syncs']} SYNCs ({r['lost']} lost, stand-in {r['stand_in']}: {r['stand_in_counters']}; load {r['load']})")
    assert r["stand_in_counters"]["syncs_missed"] == 0      # the stand-in heard every SYNC sent
    bound_us = max(MAX_CPU_PER_SYNC_S, MAX_PACED_LOOPS_PER_SYNC * paced_loop_cpu_s()) * 1e6
    assert r["master_cpu_us"] <= bound_us, f"master CPU {r['master_cpu_us']:.0f} us per SYNC (bound {bound_us:.0f} us)"
    assert r["master_wakeups_per_sync"] <= MAX_WAKEUPS_PER_SYNC, \
        f"{r['master_wakeups_per_sync']:.2f} thread wake-ups per SYNC"


# --- Modbus TCP, free-running ---------------------------------------------------------------
MODBUS_SAMPLES_S = 2.0          # 1,000 samples of both drives at the rated 2 ms
# a run whose SCHED_FIFO stand-in answered this share of requests late was not run by the host
# on time: its repeat count measures the stall, not the master (the other checks still hold)
HOST_STALLED_LATE_SHARE = 0.10
# Measured 143-239 us per sample at load 5-6 on the shared 2-core VM (the master and the stand-in
# at SCHED_FIFO on the same two cores; the pymodbus polling master it replaced: 326 us, 3.9 wake-ups).
MODBUS_MAX_CPU_PER_SAMPLE_S = 350e-6
# ... or this many paced loops (as MAX_PACED_LOOPS_PER_SYNC): 5.4-6.3 on the AMD EPYC VM (370-427 us)
MODBUS_MAX_PACED_LOOPS_PER_SAMPLE = 12.0
MODBUS_MAX_WAKEUPS_PER_SAMPLE = 1.3     # one per sample (sleep to the due time) + the probes' answers and
                                        # re-reads (1 cell in 16): 1.1-1.2; the polling master: 1.8-3.9


def _modbus_cpu_bound_us() -> float:
    """The Modbus master's CPU bound per sample on this host (the larger of the two), the
    host's paced loop timed again now as well: the suite's other worker can slow every
    process's CPU per period (shared caches, a loaded hypervisor) after the cached timing
    was taken (one loaded run: 932 us measured against an 800 us bound from the cached
    66 us loop)."""
    loop_s = max(paced_loop_cpu_s(), paced_loop_cpu_s.__wrapped__())
    return max(MODBUS_MAX_CPU_PER_SAMPLE_S, MODBUS_MAX_PACED_LOOPS_PER_SAMPLE * loop_s) * 1e6


@pytest.mark.skipif(_responder.available(_responder.MODBUS_SOURCE) is not None,
                    reason=f"needs the compiled Modbus stand-in ({_responder.available(_responder.MODBUS_SOURCE)})")
def test_free_running_modbus_master_reads_each_drive_once_per_sample_at_a_bounded_cost():
    from gearbench.benchmarks.drives_modbus import DEFAULT_MAP, measure
    r = measure(DEFAULT_MAP, MODBUS_SAMPLES_S, lockstep=False, period_s=2e-3, latency_reads=0)
    own, sup = r["stand_in_own"], r["supervision"]
    print(f"Modbus master: {r['client_cpu_us']:.0f} us CPU and {r['wakeups_per_sample']:.2f} wake-ups per sample "
          f"over {r['samples']} samples ({r['lost']} lost; stand-in {r['stand_in']}: {own}; {sup}; load {r['load']})")
    assert own["exceptions"] == 0
    # one read per drive per cell, and a probe (1 cell in 16) that came before its cell's start edge
    # read again: about one repeat per probe (the edge tracking's balance), never more than two
    # (a property of the master's edge tracking, measurable only where the host ran the SCHED_FIFO
    # stand-in on time: quiet, ~2 % of answers later than LATE_ANSWER_S; CI once saw 24 % under a
    # hypervisor stall, 24 samples lost to reads sent late, and 356 repeats)
    probes = r["samples"] / 16 + 2
    # reads that came before their cell beyond the probes' own (``repolls``: the drive's clock
    # read behind the schedule, relocked) are the host's timer: one re-read each, and wake-ups
    # (AMD EPYC VM, whose sleeps overshoot by 60-160 us: 109-300 repolls per 1,000 samples)
    relocks = max(0.0, sup["repolls"] - probes)
    if own["late_answers"] <= HOST_STALLED_LATE_SHARE * own["requests"]:
        assert own["repeat_reads"] <= 2 * 2 * probes + relocks, (own, sup["repolls"])
    else:
        print(f"host stalled ({own['late_answers']} of {own['requests']} answers late): repeat bound not judged")
    # per cell, lost ones included: a cell lost to a read sent late was still read
    assert own["requests"] <= 2 * (r["syncs_or_cells"] + 2) + own["repeat_reads"], own
    # a lost cell is only ever one whose read went out after the cell had ended (the host did not run
    # the master: a stall no schedule avoids); a read sent in time falls in its cell unless the drive
    # answered it late (its SCHED_FIFO stand-in not run in time: CI, the suite's other worker running
    # real-time runs too, saw 1 such cell with 33 answers late, the latest 1.0 ms of a 2 ms cell)
    assert sup["lost_misplaced"] <= own["late_answers"] and sup["lost_sent_late"] >= r["lost"] - sup["lost_misplaced"]
    bound_us = _modbus_cpu_bound_us()
    assert r["client_cpu_us"] <= bound_us, f"master CPU {r['client_cpu_us']:.0f} us per sample (bound {bound_us:.0f} us)"
    # (an early read sleeps cp/16 at a time until its cell: 1.1-1.4 wake-ups beyond the bound per
    # relock measured there, where two runs in three failed the fixed bound)
    assert r["wakeups_per_sample"] <= MODBUS_MAX_WAKEUPS_PER_SAMPLE + 2.5 * relocks / r["samples"], \
        f"{r['wakeups_per_sample']:.2f} wake-ups per sample ({sup['repolls']} repolls)"


@pytest.mark.skipif(_responder.available(_responder.MODBUS_SOURCE) is not None,
                    reason=f"needs the compiled Modbus stand-in ({_responder.available(_responder.MODBUS_SOURCE)})")
def test_modbus_master_reading_the_drives_history_ring_costs_no_more():
    # drives with a history ring: one ring read per drive per cell (normally one entry), one wake-up
    # per sample; 112-128 us and 1.00 wake-ups measured at load 7-10 (60 s runs)
    from gearbench.benchmarks.drives_modbus import DEFAULT_MAP, measure
    r = measure(DEFAULT_MAP, MODBUS_SAMPLES_S, lockstep=False, period_s=2e-3, latency_reads=0, history=True)
    own, sup = r["stand_in_own"], r["supervision"]
    print(f"Modbus master, history ring: {r['client_cpu_us']:.0f} us CPU and {r['wakeups_per_sample']:.2f} wake-ups "
          f"per sample over {r['samples']} samples ({r['lost']} lost; {own}; {sup}; load {r['load']})")
    assert own["exceptions"] == 0 and own["block_reads"] == 0 and own["history_reads"] > 0
    assert own["requests"] <= 2 * (r["samples"] + 2) + 2 * sup["history_stale"], own
    assert r["lost"] == sup["lost_history_overrun"] and own["cells_unread"] == 0
    bound_us = _modbus_cpu_bound_us()
    assert r["client_cpu_us"] <= bound_us, f"master CPU {r['client_cpu_us']:.0f} us per sample (bound {bound_us:.0f} us)"
    assert r["wakeups_per_sample"] <= MODBUS_MAX_WAKEUPS_PER_SAMPLE, f"{r['wakeups_per_sample']:.2f} wake-ups per sample"
