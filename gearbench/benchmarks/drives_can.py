"""Benchmark: two CiA 402 drives sampled on SYNC from the emulated bench.

``python -m gearbench.benchmarks drives_can [--duration-s 60] [--period-s 0.001] [--bus udp_multicast virtual]
[--paced] [--hog N [N ...]] [--stand-in responder|emulator] [--threads]``

A run is ``duration_s / period_s`` SYNCs of drive time (60,000 at 1 kHz for 60 s).
Lockstep (default): SYNCs go out as fast as the drives answer, so the figure is the
sustained sample rate; ``--paced`` sends them on the wall clock at ``period_s``, as a
real tester does. udp_multicast runs the emulator in another process (``gearbench
emulate``); virtual runs it in this one. udp_multicast frames are sent with hop limit 0
(they stay on this host, see ``run_once``).

The master is measured, not the drives' stand-in. Paced on udp_multicast, the emulator
configures the drives (SDO, NMT, heartbeats) and then the compiled responder
(``tools/responder``, built with gcc on first use) answers every SYNC with the four
TPDOs, at SCHED_FIFO 20 above the master's 10 with its memory locked, as drive
hardware answers whatever the PC does; ``--stand-in emulator`` keeps the emulator
answering (its threads at SCHED_FIFO 20). The stand-in's own counters are printed: SYNCs
heard, SYNCs sent that it never heard (counter gaps), answers later than a period, answers
later than the master takes them (0.2 s), its largest delay.

Lost, defined: a SYNC whose answers never reach the record (``lost_samples``: gaps in the
sample index). A late wake-up of the master that still takes the queued answers is not a
loss (answers name their SYNC by the counter echo). A SYNC the producer sent late because
it woke late is a timing fault, counted apart ("sent late", with the latest); one it never
sent (further behind than it catches up, 50 ms) is lost and the master's. Lost samples are
split into the master's and the stand-in's (SYNCs it never heard or answered too late).

CPU is measured per thread from Linux's schedstat (time on a CPU, which a busy host does
not inflate much) and given per SYNC period: the master's whole process (receive, decode,
supervision, SYNC production, the sample loop) and the stand-in's. Paced, the SYNC
interval jitter (|dT - T| p50 / p99 / max between consecutive SYNCs) is taken from the
kernel receive timestamps of an independent process: the responder's, or a listener's
with the emulator. ``--hog N`` starts N ``python3 -c "while 1: pass"`` at normal priority
during each run (a busy tester PC: N = 2 loads both cores). The host's load average is
printed with every run: the host is shared. Paced, the host's own floor is measured first
(``_cpu.timer_floor``): how often a real-time process that only sleeps to 1 ms deadlines
wakes more than half a period late, i.e. the SYNC slots no user-space producer could
keep on time on this host.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

from ..drives.base import AxisConfig, Mode
from ..drives.buses import BusSpec, free_udp_port, open_bus
from ..drives.cia402 import LATE_ANSWER_S, CiA402Network
from ..drives.realtime import acquisition_priority, raise_this_thread
from ..emulate.launch import _child_setup
from ..errors import BenchFault
from . import _cpu, _responder
from ._cpu import STAND_IN_FIFO, floor_text, load_average, normal_priority, realtime_stand_in, timer_floor

HOG = [sys.executable, "-c", "while 1: pass"]


def listen(bus: str, path: str) -> None:
    """Independent SYNC listener (run in its own process, own bus connection): bus receive
    timestamps of every SYNC and its counter byte (-1 without), saved to ``path`` when stdin
    closes. Its thread runs at SCHED_FIFO where allowed (a starved listener whose receive
    buffer overflows would see gaps that are not the producer's)."""
    b = open_bus(bus, can_filters=[{"can_id": 0x80, "can_mask": 0x7FF}])
    stamps, stop = [], threading.Event()

    def run():
        raise_this_thread(above=-1)
        while not stop.is_set():
            msg = b.recv(0.1)
            if msg is not None and msg.arbitration_id == 0x80:
                stamps.append((msg.timestamp, msg.data[0] if msg.data else -1))
    t = threading.Thread(target=run, daemon=True)
    t.start()
    print("ready", flush=True)
    sys.stdin.read()
    stop.set()
    t.join(2)
    b.shutdown()
    np.save(path, np.array(stamps, dtype=float).reshape(-1, 2))


def sync_intervals(stamps: np.ndarray) -> np.ndarray:
    """Intervals (s) between consecutive SYNCs from (receive time, counter) rows: where the SYNC
    carries a counter, only pairs one counter step apart (a SYNC the receiver missed is not an
    interval of the producer's)."""
    if len(stamps) < 2:
        return np.array([])
    dt = np.diff(stamps[:, 0])
    counters = stamps[:, 1]
    if (counters < 0).any():
        return dt
    return dt[np.diff(counters) % 240 == 1]


def _start_listener(bus: str, path: str) -> subprocess.Popen:
    code = f"from gearbench.benchmarks.drives_can import listen; listen({bus!r}, {path!r})"
    proc = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    if proc.stdout.readline().strip() != "ready":
        raise RuntimeError("SYNC listener did not start")
    return proc


def _status(proc: subprocess.Popen) -> dict:
    return json.loads(_command(proc, {"cmd": "status"}))


def run_once(interface: str, duration_s: float, period_s: float, paced: bool, hog: int = 0,
             stand_in: str = "responder") -> dict:
    """One run; ``stand_in`` (udp_multicast, paced): "responder" (the compiled one, see
    ``_responder``) or "emulator" (``gearbench emulate`` answering SYNC itself, at SCHED_FIFO)."""
    foreign = _cpu.foreign_threads()   # the master's threads only: not what earlier work left running
    proc = server = responder = None
    if interface == "udp_multicast":
        bus = BusSpec("udp_multicast", "239.74.163.2", free_udp_port())
        proc = subprocess.Popen([sys.executable, "-m", "gearbench", "emulate", "--can", str(bus)],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                preexec_fn=_child_setup)   # as --sim starts it: the drives' stand-in
        if proc.stdout.readline().strip() != "ready":
            raise RuntimeError("gearbench emulate did not start")
        if not paced:
            stand_in = "emulator, nice -10"
        elif stand_in == "emulator" or _responder.available():
            stand_in = f"emulator, {realtime_stand_in(proc.pid)}" + \
                ("" if stand_in == "emulator" else f" (no responder: {_responder.available()})")
    else:
        from ..emulate.bench import EmulatedBench
        from ..emulate.canopen_server import start_canopen_server
        bus = BusSpec("virtual", f"bench-{time.monotonic_ns()}")
        server = start_canopen_server(EmulatedBench(), "virtual", bus.channel)
        stand_in = "emulator, in-process"
    n = round(duration_s / period_s)
    hogs: list[subprocess.Popen] = []
    listener = None
    stamps_path = os.path.join(tempfile.mkdtemp(prefix="gearbench-sync-"), "stamps.npy")
    counters0 = counters1 = {}
    try:
        if paced and interface != "virtual" and stand_in != "responder":   # the responder stamps SYNCs itself
            listener = _start_listener(str(bus), stamps_path)
        # hop limit 0: the frames stay on this host (Linux loops multicast back to local sockets, then
        # drops it); with python-can's default 1 every SYNC also went out on the VM's virtual NIC,
        # a VM exit per frame that was 17 % of the master's CPU (perf) and that no CAN adapter costs
        local = {"hop_limit": 0} if interface == "udp_multicast" else {}
        with CiA402Network(bus=str(bus), lockstep=not paced, bus_kwargs=local) as net:
            din = net.add_drive(AxisConfig("in", 1, ""))
            dout = net.add_drive(AxisConfig("out", 2, ""))
            if proc is not None and not paced:   # paced, the stand-in runs above the master: never starved
                net.watch_process(proc.pid)
            net.start(period_s)
            din.enable(Mode.VELOCITY)
            dout.enable(Mode.TORQUE)
            din.set_setpoint(100.0)
            dout.set_setpoint(0.1)
            with acquisition_priority(net.acquisition_threads(), realtime=paced) as granted:
                net.sample()                       # the producer's thread started (paced), first answer in
                if stand_in == "responder":
                    responder = _hand_over(net, bus, proc, period_s)
                    stand_in = f"compiled responder, {responder.priority}"
                    for _ in range(50):            # its first answers in; the hand-over's gap counted before
                        net.sample()
                hogs = [subprocess.Popen(HOG, preexec_fn=normal_priority) for _ in range(hog)]
                load0 = load_average()
                time.sleep(0.05 * hog)             # the hogs running before the figures start
                counters0 = _stand_in_counters(proc, responder)
                if paced:      # the window starts at the first SYNC after the stand-in's counters were read
                    net.discard_backlog()
                    net.sample()
                got, lost0, skipped0, late0 = 1, net.lost_samples, net.late_syncs, net.syncs_sent_late
                us0 = _cpu.user_system()
                pid = responder.pid if responder is not None else proc.pid if proc is not None else None
                cpu0, emu0, t0 = _cpu.threads(exclude=foreign), _cpu.threads(pid) if pid else {}, time.perf_counter()
                while got + net.lost_samples - lost0 < n + 1:
                    net.sample()
                    got += 1
                wall = time.perf_counter() - t0
                cpu1, emu1 = _cpu.threads(exclude=foreign), _cpu.threads(pid) if pid else {}
                us1 = _cpu.user_system()
                counters1 = _stand_in_counters(proc, responder)
                if responder is not None:     # the drives' stop at close is SDO: the emulator answers it
                    realtime_stand_in(proc.pid)
            load1 = load_average()
            lost = net.lost_samples - lost0
            skipped = net.late_syncs - skipped0
            sent_late = net.syncs_sent_late - late0
            sup = net.supervision()
            producer = getattr(net.sync_producer, "kind", "loop" if paced else "lockstep")
    finally:
        for h in hogs:
            h.kill()
            h.wait()
        if responder is not None:
            responder.stop()
            np.save(stamps_path, responder.sync_stamps()[counters0.get("syncs_heard", 0):counters1.get("syncs_heard", 0)])
        if listener is not None:
            listener.stdin.close()
            listener.wait(30)
        if server is not None:
            server.stop()
        if proc is not None:
            proc.send_signal(signal.SIGTERM)
            proc.wait(10)
    intervals = sync_intervals(np.load(stamps_path)) if os.path.exists(stamps_path) else np.array([])
    dev_us = np.abs(intervals - period_s) * 1e6 if len(intervals) > 1 else np.array([np.nan])
    master = _cpu.delta(cpu0, cpu1)
    stand_in_cpu = sum(_cpu.delta(emu0, emu1).values()) if pid is not None else None
    syncs = got - 1 + lost
    keys = ("syncs_heard", "syncs_missed", "late_answers", "too_late")
    heard = {k: counters1.get(k, 0) - counters0.get(k, 0) for k in keys}
    # who lost what: SYNC slots the producer never sent (the master's: its thread was not run for
    # longer than it catches up), SYNCs sent that the stand-in never heard, or answered too late for
    # the master to take them (the stand-in's), and the rest (the master's: answers it did not take)
    stand_in_lost = max(0, heard["syncs_missed"] - skipped) + heard["too_late"] if pid is not None else 0
    return {"bus": interface, "syncs": syncs, "samples": got - 1, "lost": lost, "wall_s": wall,
            "skipped": skipped, "sent_late": sent_late, "sync_late_max_s": sup.get("sync_late_max_s", 0.0),
            "stand_in_lost": stand_in_lost, "master_lost": lost - min(lost, stand_in_lost),
            "samples_per_s": (got - 1) / wall, "producer": producer,
            "master_cpu_us": sum(master.values()) / syncs * 1e6,
            "master_wakeups_per_sync": _cpu.wakeups(cpu0, cpu1) / syncs,
            "master_user_us": (us1[0] - us0[0]) / syncs * 1e6, "master_system_us": (us1[1] - us0[1]) / syncs * 1e6,
            "master_threads_us":
                {k: v / syncs * 1e6 for k, v in sorted(master.items(), key=lambda kv: -kv[1])},
            "stand_in_cpu_us": None if stand_in_cpu is None else stand_in_cpu / syncs * 1e6,
            "stand_in": stand_in, "stand_in_counters": heard if pid is not None else None,
            "answer_delay_max_ms": counters1.get("answer_delay_max_s", float("nan")) * 1e3,
            "jitter_us": [np.percentile(dev_us, 50), np.percentile(dev_us, 99), np.max(dev_us)],
            "priority": granted, "host_stall_max_s": sup.get("host_stall_max_s", 0.0),
            "faults": "", "load": f"{load0} -> {load1}"}


def _stand_in_counters(proc, responder) -> dict:
    if responder is not None:
        return responder.counters()
    return _status(proc)["counters"] if proc is not None else {}


def _hand_over(net: CiA402Network, bus: BusSpec, proc: subprocess.Popen, period_s: float) -> "_responder.Responder":
    """The compiled responder takes over answering SYNC from the emulator (which keeps SDO,
    NMT and heartbeats, at normal priority): it starts with the TPDO payloads the emulated
    drives sent last, the SYNC counter echo (the last byte of an echoing TPDO) rewritten."""
    cobs = {cob: has_counter for cob, (_, has_counter) in net._formats.items()}
    tap = open_bus(bus)
    try:
        payloads = _responder.last_tpdos(tap, cobs)
    finally:
        tap.shutdown()
    responder = _responder.Responder(bus.channel, bus.port, period_s, LATE_ANSWER_S,
                                     {cob: (data, len(data) - 1 if cobs[cob] else -1) for cob, data in payloads.items()},
                                     STAND_IN_FIFO)
    reply = json.loads(_command(proc, {"cmd": "pdo", "on": False}))
    if not reply.get("ok"):
        responder.stop()
        raise RuntimeError(f"emulator refused the hand-over: {reply}")
    return responder


def _command(proc: subprocess.Popen, cmd: dict) -> str:
    proc.stdin.write(json.dumps(cmd) + "\n")
    proc.stdin.flush()
    return proc.stdout.readline()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m gearbench.benchmarks drives_can", description=__doc__.splitlines()[0])
    p.add_argument("--duration-s", type=float, default=60.0, help="drive time per bus (s)")
    p.add_argument("--period-s", type=float, default=1e-3, help="SYNC period (s)")
    p.add_argument("--bus", nargs="+", default=["udp_multicast", "virtual"], choices=["udp_multicast", "virtual"])
    p.add_argument("--paced", action="store_true", help="send SYNC on the wall clock instead of lockstep")
    p.add_argument("--hog", type=int, nargs="+", default=[0],
                   help="processes spinning during a run (2 = both cores busy); several values: one run each")
    p.add_argument("--stand-in", default="responder", choices=["responder", "emulator"],
                   help="paced on udp_multicast: what answers SYNC (the compiled responder, or the emulator itself)")
    p.add_argument("--threads", action="store_true", help="also print the master's CPU per thread")
    args = p.parse_args(argv)
    print(f"two CiA 402 drives, SYNC period {args.period_s * 1e3:g} ms, {args.duration_s:g} s of drive time, "
          f"{'paced' if args.paced else 'lockstep'}; CPU in us per SYNC period")
    if args.paced:
        print(f"load {load_average()}; " + floor_text(timer_floor(args.period_s), args.period_s))
    print(f"{'bus, hogs':<16}{'SYNCs':>8}{'lost':>6}{'master/stand-in':>16}{'sent late, max':>16}{'samples/s':>10}"
          f"{'master CPU':>11}{'stand-in CPU':>13}{'SYNC |dT-T| p50/p99/max us':>28}"
          f"  stand-in: heard/missed/late/too late, max delay   producer, priority, load 1/5/15 min before -> after")
    for interface, hog in ((i, h) for i in args.bus for h in args.hog):
        name = f"{interface}, {hog}"
        try:
            r = run_once(interface, args.duration_s, args.period_s, args.paced, hog, args.stand_in)
        except BenchFault as exc:
            print(f"{name:<16}bench fault: {exc} (load {load_average()})", flush=True)
            continue
        emu = "in-process" if r["stand_in_cpu_us"] is None else f"{r['stand_in_cpu_us']:.0f}"
        jit = "/".join(f"{v:.0f}" for v in r["jitter_us"]) if args.paced and interface != "virtual" else "-"
        c = r["stand_in_counters"]
        own = "-" if c is None else (f"{c['syncs_heard']}/{c['syncs_missed']}/{c['late_answers']}/{c['too_late']}, "
                                     f"{r['answer_delay_max_ms']:.2f} ms")
        who = f"{r['master_lost']}/{r['stand_in_lost']}" if c is not None else "-"
        late = f"{r['sent_late']}, {r['sync_late_max_s'] * 1e3:.1f} ms" if args.paced else "-"
        print(f"{name:<16}{r['syncs']:>8}{r['lost']:>6}{who:>16}{late:>16}{r['samples_per_s']:>10.0f}"
              f"{r['master_cpu_us']:>11.0f}{emu:>13}{jit:>28}  {r['stand_in']}: {own}   "
              f"{r['producer']}, {r['priority']}, {r['load']}", flush=True)
        if args.threads:
            print("    master by thread (us/SYNC): " + ", ".join(f"{k} {v:.0f}" for k, v in r["master_threads_us"].items())
                  + f"; user {r['master_user_us']:.0f} / kernel {r['master_system_us']:.0f}"
                  + f"; {r['master_wakeups_per_sync']:.2f} thread wake-ups per SYNC"
                  + f"; SYNC slots never sent (producer too far behind): {r['skipped']}",
                  flush=True)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
