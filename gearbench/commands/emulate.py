"""``gearbench emulate``: the simulated two-motor bench behind real drive protocols.

One physics world (the profile's ``simulation:`` section, default plant if absent)
behind CANopen nodes 1 and 2 (``--can``) and/or Modbus TCP unit ids 1 and 2
(``--modbus``). Prints ``ready`` once every endpoint listens, reads fixture commands
(JSON lines, see ``gearbench.emulate.bench``) on stdin, answers on stdout, and stops
cleanly on SIGINT/SIGTERM. Without endpoints it serves CANopen on
``udp_multicast:239.74.163.2:43113`` (multicast TTL 1: this host's network only).
"""
from __future__ import annotations

import gc
import json
import os
import signal
import sys
import threading
import time
from pathlib import Path

import yaml

from ..errors import DriveError, ProfileError

NAME = "emulate"
HELP = "run the simulated bench behind CANopen CiA 402 and/or Modbus TCP drive endpoints"
DEFAULT_CAN = "udp_multicast:239.74.163.2:43113"


def add_arguments(parser) -> None:
    parser.add_argument("profile", nargs="?", help="profile YAML whose 'simulation:' section is the plant")
    parser.add_argument("--can", metavar="INTERFACE:CHANNEL",
                        help="CAN bus for nodes 1 and 2, e.g. udp_multicast:239.74.163.2:43113, socketcan:vcan0")
    parser.add_argument("--modbus", metavar="HOST:PORT", help="Modbus TCP endpoint, e.g. 127.0.0.1:5020")
    parser.add_argument("--modbus-map", metavar="YAML", default=None,
                        help="register map the Modbus drives serve (default drivers/generic-modbus-servo.yaml)")
    parser.add_argument("--lockstep", action="store_true",
                        help="Modbus: advance the world on each write of the 'sync' register (CANopen always "
                             "advances one period per SYNC)")
    parser.add_argument("--seed", type=int, default=None, help="noise seed (default: the plant's)")
    parser.add_argument("--simulation", metavar="YAML", default=None,
                        help="take the plant from this file's simulation: block instead of the profile's "
                             "(a digital twin written by gearbench twin --write)")
    parser.add_argument("--exit-on-eof", action="store_true",
                        help="stop when stdin closes (a parent that started the emulator has gone, even by SIGKILL)")
    parser.add_argument("--journal", metavar="FILE",
                        help="test facility: append every axis state change and applied fixture command "
                             "to FILE as JSON lines (world and wall time)")
    parser.add_argument("--fault-plan", metavar="JSON",
                        help="test facility: a JSON list of fixture commands applied at start, usually "
                             "with \"at_s\" (world time), e.g. '[{\"cmd\": \"mute\", \"axis\": \"in\", \"at_s\": 1.2}]'")


def load_plant(profile: str | None):
    """PlantParams from a profile's ``simulation:`` section; ProfileError names the file."""
    from ..sim import PlantParams

    if not profile:
        return PlantParams()
    path = Path(profile)
    try:
        doc = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ProfileError(f"{profile}: cannot read ({exc.strerror})") from exc
    except yaml.YAMLError as exc:
        raise ProfileError(f"{profile}: not valid YAML ({exc})") from exc
    if doc is None:
        doc = {}
    if not isinstance(doc, dict):
        raise ProfileError(f"{profile}: expected a mapping at the top level")
    sim = dict(doc.get("simulation") or {})
    bench_period = (doc.get("bench") or {}).get("period_s") if isinstance(doc.get("bench"), dict) else None
    # the emulated world advances one bench period per SYNC: a plant at another period would
    # stretch time (a 2 ms profile on the 1 ms default read accelerations 4x low, Kt 4x low)
    if isinstance(bench_period, (int, float)) and not isinstance(bench_period, bool):
        if "period_s" not in sim:
            sim["period_s"] = bench_period
        elif abs(float(sim["period_s"]) - bench_period) > 1e-12:
            raise ProfileError(f"{profile}: simulation.period_s {sim['period_s']} differs from bench.period_s "
                               f"{bench_period}; the emulated drives sample at the bench's period: remove "
                               f"simulation.period_s or make them equal")
    motors, sim_motors = doc.get("motors"), sim.get("motors")
    if isinstance(motors, dict) and isinstance(sim_motors or {}, dict):
        # the simulated motors have the profile motors' ratings where they leave them out
        # (as 'gearbench validate' reads it: gearbench.profile.parse.SIM_RATINGS)
        from ..profile.parse import SIM_RATINGS

        filled = dict(sim_motors or {})
        for name, spec in motors.items():
            if isinstance(spec, dict) and isinstance(filled.get(name, {}), dict) and name in ("in", "out"):
                filled[name] = {**{k: spec[k] for k in SIM_RATINGS if k in spec}, **(filled.get(name) or {})}
        sim["motors"] = filled
    try:
        return PlantParams.from_dict(sim, where="simulation")
    except ProfileError as exc:
        raise ProfileError(f"{profile}: {exc}") from exc


def profile_drives(profile: str | None, bench) -> dict[int, str]:
    """{node id: EDS} of a CANopen profile's motors (the emulator plays those drive models);
    the bench's axes follow the profile's addresses. Empty without a profile."""
    if not profile:
        return {}
    from ..profile import load_profile

    p = load_profile(profile)
    if p.bench.bus.family != "cia402":
        return {}
    bench.axes = {m.address: name for name, m in p.motors.items() if name in bench.drives}
    return {m.address: str(m.drive) for m in p.motors.values()}


def _host_port(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit():
        raise DriveError(f"--modbus '{text}': expected HOST:PORT, e.g. 127.0.0.1:5020")
    return host or "127.0.0.1", int(port)


def _warm_up(plant) -> None:
    """Compile the physics kernel before saying ``ready``: on a fresh install numba
    needs seconds for it, and the master's first SYNC must not wait that long."""
    from ..sim import BenchWorld

    world = BenchWorld(plant, seed=0)
    world.step()
    world.mount(coupling="reducer")
    world.step()


def _log_stalls(stop: threading.Event) -> None:
    """Diagnostics: this process's own stalls on stderr (when GEARBENCH_EMULATOR_LOG is set)."""
    from ..drives.supervision import HostStallMonitor

    class Logging(HostStallMonitor):
        def record(self, start_s, duration_s):
            super().record(start_s, duration_s)
            if duration_s > 0.1:
                print(f"emulator stalled {duration_s:.3f} s", file=sys.stderr, flush=True)
    Logging().start()
    starts = {}

    def on_gc(phase, info):
        if phase == "start":
            starts["t"] = time.perf_counter()
        elif time.perf_counter() - starts.get("t", time.perf_counter()) > 0.05:
            print(f"emulator gc gen{info['generation']} took {time.perf_counter() - starts['t']:.3f} s",
                  file=sys.stderr, flush=True)
    gc.callbacks.append(on_gc)


def run(args) -> int:
    from ..drives.buses import parse_bus
    from ..emulate.bench import EmulatedBench
    from ..emulate.canopen_server import start_canopen_server

    plant = load_plant(getattr(args, "simulation", None) or args.profile)
    _warm_up(plant)
    # the imports and the compiled kernel are hundreds of thousands of long-lived objects: a full
    # collection over them stalls the emulated drives for ~0.5 s; freeze them out of the collector
    gc.collect()
    gc.freeze()
    bench = EmulatedBench(plant, seed=plant.seed if args.seed is None else args.seed)
    can_spec = args.can or (None if args.modbus else DEFAULT_CAN)
    handles = []
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        if can_spec:
            bs = parse_bus(can_spec)
            handles.append(start_canopen_server(bench, bs.interface, bs.channel, port=bs.port,
                                                eds=profile_drives(args.profile, bench),
                                                profile_dir=Path(args.profile).parent if args.profile else None))
        if args.modbus:
            from ..emulate.modbus_server import start_modbus_server
            host, port = _host_port(args.modbus)
            # with CANopen on the same world, SYNC already advances time: Modbus must not too
            lockstep = args.lockstep or bool(can_spec)
            kw = {"register_map": args.modbus_map} if args.modbus_map else {}
            handles.append(start_modbus_server(bench, host, port, lockstep=lockstep, **kw))
        if args.journal:
            bench.journal = open(args.journal, "a")
            bench.log("ready", pid=os.getpid())
        for cmd in json.loads(args.fault_plan) if args.fault_plan else []:
            reply = json.loads(bench.handle_control_line(json.dumps(cmd)))
            if not reply.get("ok"):
                raise DriveError(f"--fault-plan: {cmd}: {reply.get('error')}")
        # 'ready' names the endpoints actually bound (a Modbus port 0 is chosen by the OS: no race)
        bound = [f"modbus={h.host}:{h.port}" for h in handles if hasattr(h, "port") and hasattr(h, "host")]
        print(" ".join(["ready", *bound]), flush=True)
        if os.environ.get("GEARBENCH_EMULATOR_LOG"):
            _log_stalls(stop)
        control = bench.run_control_loop(sys.stdin, sys.stdout)
        ended = "signal"
        while not stop.wait(0.2):
            if args.exit_on_eof and not control.is_alive():
                ended = "stdin closed"
                break
        bench.log("exit", why=ended, states={n: a.state for n, a in bench.drives.items()})
    finally:
        for h in reversed(handles):
            try:
                h.stop()
            except Exception as exc:   # keep stopping the others
                print(f"gearbench emulate: stopping {type(h).__name__}: {exc}", file=sys.stderr)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0
