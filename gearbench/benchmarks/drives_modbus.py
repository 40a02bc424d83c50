"""Benchmark: Modbus TCP sampling of two drives, their stand-in in another process.

    python -m gearbench.benchmarks drives_modbus [--seconds 10] [--period-s 0.002] [--hog 0 2]
        [--modes lockstep free] [--stand-in compiled|emulator] [--map drivers/generic-modbus-servo.yaml]
        [--history on off]

The 10-minute acceptance run (free-running at the rated period, quiet and with both cores hogged,
drives with a history ring; add ``off`` for drives without one):

    python -m gearbench.benchmarks drives_modbus --seconds 600 --modes free --hog 0 2 --history on

History (``--history on``, the map's ``history:``): the drives keep their last samples in a ring
and the master reads back every cell since the last one taken, so a host stall shorter than the
ring loses nothing; ``off``: the same drives read as if they had none (the read is the sample).

Modes:
  - lockstep: each sample = sync write + read of drive 1 (one 0x17 request) + read of drive 2,
    against the Python emulator; throughput is what the link and both ends allow;
  - free-running (a real bench): the drives run on their own clock; the master reads each
    drive's sample block once per sampling period (``--period-s``, default 2 ms: the rated
    rate, 500 samples/s per drive; README "Modbus: rated rate") at SCHED_FIFO 10.

Rated rate: 2 ms. Modbus has no SYNC; for a drive without history the master's read *is* the
sample (with one, a stall is read back), and the rate is bounded by the drive's answer time. Vendors document plain register
reads answered within about 1-2 ms (IAI ROBO Cylinder: 1 ms max internal processing;
Oriental Motor BLH/BLV over RTU: silent interval + 2 ms or less), and Kollmorgen says of the
AKD that Modbus TCP "is not deterministic" (the AKD2G throttles high message rates). A 2 ms
period is the fastest at which such a drive answers inside the period; with real drives use
at least twice their documented answer time.

The master is measured, not the stand-in. Free-running, the default stand-in is compiled
(``tools/responder/modbus_stand_in.c``, built with gcc on first use): two drives of the
generic map on two ports (one connection per drive, as drives with an IP each), at
SCHED_FIFO 20 above the master with its memory locked, whose sample counter is the kernel's
receive time of each request (a stand-in the host does not run for a while still answers with
the instant the request reached it, as hardware). Its own counters are printed: requests,
answers later than 0.2 ms, cells of its counter no read fell in (the loss as the drive sees
it), cells read twice. ``--stand-in emulator``: the Python emulator (pymodbus server, world
stepped by a pacer thread) at SCHED_FIFO 20, with its pacing counters.

Lost, defined: a cell (one sampling period of the first drive's sample counter) between two
samples taken that no read fell in: the drive's value for that period is gone. Each lost
cell is attributed: its read was sent after the cell had ended (the master was not run in
time: a host stall, which the host timer floor measured just before, under the same hogs,
shows for a process that does nothing but sleep), or sent in time and still missed (the
master's schedule: 0 expected).

CPU is measured from Linux's schedstat (time on a CPU, not inflated by a busy host) as
microseconds per sample of both drives, with the master's thread wake-ups per sample; ``--hog
N`` runs N ``python3 -c "while 1: pass"`` meanwhile; the host's load average is printed with
each figure.
"""
from __future__ import annotations

import argparse
import json
import select
import subprocess
import sys
import time

import numpy as np

from ..drives.base import AxisConfig, Mode
from ..drives.modbus import ModbusNetwork, PollSchedule
from ..drives.realtime import acquisition_priority
from ..drives.register_map import load_register_map
from . import _cpu, _responder
from ._cpu import STAND_IN_FIFO, load_average, normal_priority, realtime_stand_in, timer_floor

HOG = [sys.executable, "-c", "while 1: pass"]

DEFAULT_MAP = "drivers/generic-modbus-servo.yaml"
COMPILED_MODEL = "generic-modbus-servo"   # the layout tools/responder/modbus_stand_in.c answers
LATE_ANSWER_S = 2e-4     # the compiled stand-in counts answers sent later than this after the request arrived
SERVER = ("import sys, json; from gearbench.emulate.bench import EmulatedBench; "
          "from gearbench.emulate.modbus_server import start_modbus_server; "
          "b = EmulatedBench(); b.advance(); "       # compile the physics before 'ready'
          "h = start_modbus_server(b, '127.0.0.1', 0, register_map={map!r}, lockstep={lockstep}); "
          "print('ready', h.port, flush=True); sys.stdin.read(); "   # port 0: the OS picks, no race
          "print(json.dumps(dict(overruns=h.overruns, lag_max_s=h.lag_max_s, late_periods=h.late_periods, "
          "periods=b.sample_index)), flush=True); "
          "h.stop()")


def _start_server(regmap: str, lockstep: bool) -> tuple[subprocess.Popen, int]:
    proc = subprocess.Popen([sys.executable, "-c", SERVER.format(map=regmap, lockstep=lockstep)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    ready, _, _ = select.select([proc.stdout], [], [], 60)
    words = proc.stdout.readline().split() if ready else []
    if words[:1] != ["ready"]:
        proc.kill()
        raise RuntimeError("emulator process did not start")
    return proc, int(words[1])


class _EmulatorStandIn:
    """The Python emulator (pymodbus server) in another process; its own pacing as counters."""

    def __init__(self, regmap: str, lockstep: bool):
        self.proc, port = _start_server(regmap, lockstep)
        self.ports = (port, port)             # one endpoint, both unit ids: one connection
        self.pid = self.proc.pid
        self.kind = "emulator, " + (realtime_stand_in(self.proc.pid) if not lockstep else "normal")
        self.own: dict = {}

    def counters(self) -> dict:
        return {}

    def stop(self) -> dict:
        self.proc.stdin.close()
        line = self.proc.stdout.readline()
        self.own = json.loads(line) if line.startswith("{") else {}
        self.proc.terminate()
        self.proc.wait(5)
        return self.own


def _stand_in(regmap: str, lockstep: bool, period_s: float, which: str, history: bool = False):
    """The drives' stand-in: the compiled one (free-running, the generic map) or the emulator.
    Returns (stand-in, why the compiled one was not used or None)."""
    if lockstep or which == "emulator":
        return _EmulatorStandIn(regmap, lockstep), None
    m = load_register_map(regmap)
    why = _responder.available(_responder.MODBUS_SOURCE) or \
        (None if m.model == COMPILED_MODEL else f"map {regmap} is not the {COMPILED_MODEL} it lays out")
    if why:
        return _EmulatorStandIn(regmap, lockstep), why
    s = _responder.ModbusStandIn(m.counter_period_s, round(period_s / m.counter_period_s), LATE_ANSWER_S, STAND_IN_FIFO,
                                 history=m.history if history else None)
    s.kind = f"compiled stand-in, {s.priority}"
    return s, None


def measure(regmap: str, seconds: float, lockstep: bool, period_s: float = 1e-3, hog: int = 0,
            stand_in: str = "compiled", latency_reads: int = 2000, history: bool = False) -> dict:
    """Sample both drives for ``seconds``, then time ``latency_reads`` single reads (pymodbus, normal
    priority); returns figures (see module docstring)."""
    foreign = _cpu.foreign_threads()   # the master's threads only: not what earlier work left running
    srv, why_not = _stand_in(regmap, lockstep, period_s, stand_in, history)
    hogs: list[subprocess.Popen] = []
    own0 = own1 = {}
    try:
        hogs = [subprocess.Popen(HOG, preexec_fn=normal_priority) for _ in range(hog)]
        floor = None
        if not lockstep:   # the host's floor under this run's conditions (the hogs running), just before
            floor = timer_floor(period_s, min(10.0, seconds), slack_s=(1 - PollSchedule(1.0, 1).lead_s) * period_s)
        net = ModbusNetwork(port=srv.ports[0], lockstep=lockstep, timeout_s=2.0, history=history)
        with net:
            d_in = net.add_drive(AxisConfig("in", 1, regmap))
            d_out = net.add_drive(AxisConfig("out", 2, regmap, extra={"port": srv.ports[1]}))
            net.start(1e-3 if lockstep else period_s)
            d_in.enable(Mode.VELOCITY)
            d_out.enable(Mode.TORQUE)
            d_in.set_setpoint(50.0)
            d_out.set_setpoint(0.1)
            load0 = load_average()
            with acquisition_priority(realtime=not lockstep) as granted:
                for _ in range(1 if lockstep else 100):    # free-running: the schedule locked (64 probes)
                    samples = net.sample()
                own0 = srv.counters()
                samples = net.sample()         # the window starts after the stand-in's counters were read
                lost0, first_index = net.lost_samples, samples["in"].index
                late0 = (net.polls_late, net.lost_sent_late, net.lost_misplaced, net.recovered_from_history,
                         net.lost_history_overrun, net.history_stale)
                cpu0, srv0, t0 = _cpu.threads(exclude=foreign), _cpu.threads(srv.pid), time.perf_counter()
                per_sample, n = [], 0
                while (now := time.perf_counter()) - t0 < seconds:
                    samples = net.sample()
                    per_sample.append(time.perf_counter() - now)
                    n += 1
                wall = time.perf_counter() - t0
                cpu1, srv1 = _cpu.threads(exclude=foreign), _cpu.threads(srv.pid)
                own1 = srv.counters()
            load1 = load_average()
            cpu, srv_cpu = sum(_cpu.delta(cpu0, cpu1).values()), sum(_cpu.delta(srv0, srv1).values())
            lost, span = net.lost_samples - lost0, samples["in"].index - first_index
            wakeups = _cpu.wakeups(cpu0, cpu1)
            sup = net.supervision()
            if not lockstep:   # this window's
                sup.update(polls_late=net.polls_late - late0[0], lost_sent_late=net.lost_sent_late - late0[1],
                           lost_misplaced=net.lost_misplaced - late0[2],
                           recovered_from_history=net.recovered_from_history - late0[3],
                           lost_history_overrun=net.lost_history_overrun - late0[4],
                           history_stale=net.history_stale - late0[5])
            # latency of single requests: one read of one drive's sample block
            lat = [np.nan]
            for _ in range(latency_reads):
                t = time.perf_counter()
                d_out.read_sample()
                lat.append(time.perf_counter() - t)
    finally:
        for h in hogs:
            h.kill()
            h.wait()
        last = srv.stop()
    own = {k: own1[k] - own0.get(k, 0) for k in own1 if k not in ("answer_delay_max_s", "priority")} if own1 else last
    if own1:
        own["answer_delay_max_s"] = own1["answer_delay_max_s"]
    lat_ms, per_ms = np.array(lat[1:] or lat) * 1e3, np.array(per_sample) * 1e3
    return {"mode": "lockstep" if lockstep else "free-running", "samples": n,
            "samples_per_s_per_drive": n / wall, "lost": lost, "lost_fraction": lost / max(span, 1),
            "request_p50_ms": float(np.percentile(lat_ms, 50)), "request_p99_ms": float(np.percentile(lat_ms, 99)),
            "request_max_ms": float(lat_ms.max()), "syncs_or_cells": span,
            "sample_p50_ms": float(np.percentile(per_ms, 50)), "sample_p99_ms": float(np.percentile(per_ms, 99)),
            "client_cpu": cpu / wall, "server_cpu": srv_cpu / wall, "client_cpu_us": cpu / n * 1e6,
            "server_cpu_us": srv_cpu / n * 1e6, "wakeups_per_sample": wakeups / n, "priority": granted,
            "stand_in": srv.kind + (f" (no compiled stand-in: {why_not})" if why_not else ""),
            "stand_in_own": own, "load": f"{load0} -> {load1}", "period_s": period_s,
            "supervision": sup, "floor": floor}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="gearbench.benchmarks.drives_modbus", description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="measuring time per mode")
    ap.add_argument("--map", default=DEFAULT_MAP, help="register map of both drives")
    ap.add_argument("--period-s", type=float, default=2e-3, help="free-running sample period (rated: 2 ms)")
    ap.add_argument("--hog", type=int, nargs="+", default=[0],
                    help="processes spinning meanwhile (2 = both cores busy); several values: one run each")
    ap.add_argument("--modes", nargs="+", default=["lockstep", "free"], choices=["lockstep", "free"])
    ap.add_argument("--stand-in", default="compiled", choices=["compiled", "emulator"],
                    help="free-running: what answers (the compiled stand-in, or the Python emulator at SCHED_FIFO)")
    ap.add_argument("--history", nargs="+", default=["on", "off"], choices=["on", "off"],
                    help="free-running: drives with a history ring (the map's history:) and/or read as without one")
    args = ap.parse_args(argv)
    print(f"Modbus TCP, 2 drives (unit ids 1, 2), loopback, drives' stand-in in another process, map {args.map}")
    runs = [("lockstep", h, "off") for h in args.hog] * ("lockstep" in args.modes) + \
        [("free", h, hist) for hist in args.history for h in args.hog] * ("free" in args.modes)
    if "on" in args.history and not load_register_map(args.map).history:
        print(f"{args.map} declares no history: ring; --history on reads it as a drive without one")
    for mode, hog, hist in runs:
        r = measure(args.map, args.seconds, mode == "lockstep", args.period_s, hog, args.stand_in,
                    history=hist == "on")
        own = r["stand_in_own"]
        label = (r["mode"] if mode == "lockstep" else
                 f"free-running, {1e3 * r['period_s']:g} ms, history {hist}") + f", {hog} hogs"
        print(f"{label:>28}: "
              f"{r['samples_per_s_per_drive']:7.0f} samples/s per drive "
              f"({r['samples']} samples, lost {r['lost']} = {100 * r['lost_fraction']:.3f} %); "
              f"sample (2 drives) p50 {r['sample_p50_ms']:.2f} ms p99 {r['sample_p99_ms']:.2f} ms; "
              f"single read p50 {r['request_p50_ms']:.2f} ms p99 {r['request_p99_ms']:.2f} ms "
              f"max {r['request_max_ms']:.1f} ms; CPU per sample: master {r['client_cpu_us']:.0f} us "
              f"({100 * r['client_cpu']:.0f} %, {r['wakeups_per_sample']:.2f} wake-ups), "
              f"stand-in {r['server_cpu_us']:.0f} us ({100 * r['server_cpu']:.0f} %)")
        if "requests" in own:
            ownt = (f"{own['requests']} requests, {own['block_reads']} sample reads, {own['late_answers']} answered "
                    f"later than {LATE_ANSWER_S * 1e3:g} ms (max {own['answer_delay_max_s'] * 1e3:.3f} ms), cells no "
                    f"read fell in {own['cells_unread']}, cells read twice {own['repeat_reads']}, "
                    f"{own['exceptions']} exceptions, {own['watchdog_trips']} watchdog trips, "
                    f"{own.get('history_reads', 0)} ring reads delivering {own.get('history_entries', 0)} cells")
        else:
            ownt = (f"{own.get('overruns', '?')} overruns, lag max {1e3 * own.get('lag_max_s', float('nan')):.1f} ms, "
                    f"{own.get('late_periods', '?')} of {own.get('periods', '?')} periods stepped over a period late")
        sup, f = r["supervision"], r["floor"]
        if f:
            slack = (1 - PollSchedule(1.0, 1).lead_s) * r["period_s"]
            print(f"{'':>30}host timer floor just before, same hogs (a SCHED_FIFO 10 process only sleeping to "
                  f"{r['period_s'] * 1e3:g} ms deadlines): {f['over_slack']} of {f['n']} wake-ups later than a read's "
                  f"slack ({slack * 1e3:.2f} ms), p99 {f['p99_s'] * 1e6:.0f} us, max {f['max_s'] * 1e6:.0f} us; "
                  f"the master: {sup['polls_late']} of {r['samples']} reads in a later cell")
        extra = (f"; latest send {sup['poll_late_max_s'] * 1e3:.2f} ms after due; lost: {sup['lost_sent_late']} "
                 f"read sent after its cell had ended (master not run), "
                 f"{sup['lost_misplaced']} sent in time, {sup['lost_history_overrun']} overwritten in the ring "
                 f"before read; recovered from history {sup['recovered_from_history']} (read after their cell "
                 f"had ended; {sup['history_stale']} entries read before written, read again; up to "
                 f"{sup['history_entries_max']} entries per read; history: {sup['history']})"
                 if "polls_late" in sup else "")
        print(f"{'':>30}master {r['priority']}{extra}; stand-in {r['stand_in']}, its own counters: {ownt}; "
              f"load {r['load']}", flush=True)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
