"""The Python API the CLI itself uses: load a profile, open a bench, run it.

    from gearbench.api import load_profile, run_profile
    result = run_profile("profiles/cvt.yaml", sim=True, out_dir="results/demo", serial="SN1")
    result["passed"], result["motors"]["in"]["Kt"], result["efficiency"][0]["eta_incremental"]
"""
from __future__ import annotations

import contextlib
import sys
from pathlib import Path

from .drives.base import AxisConfig, DriveNetwork
from .drives.registry import network_class
from .errors import GearbenchError
from .profile import load_profile
from .records import RecordStream

__all__ = ["load_profile", "open_network", "run_profile"]


class TerminalOperator:
    """Prompts at the terminal; Enter confirms, 'a' aborts."""

    def confirm(self, prompt: str) -> None:
        from .errors import BenchFault

        try:
            answer = input(f"\n>>> {prompt} — press Enter when done, 'a' to abort: ")
        except EOFError:
            answer = "a"
        if answer.strip().lower().startswith("a"):
            raise BenchFault("operator abort at prompt")


def open_network(bus, profile) -> DriveNetwork:
    """Open the profile's bus and add its motors' drives (not yet enabled)."""
    cls = network_class(bus.family)
    opts = {k: v for k, v in dict(interface=bus.interface, channel=bus.channel, host=bus.host,
                                   port=bus.port).items() if v is not None}
    if bus.interface:   # CAN families take one "interface:channel[:port]" string
        opts["bus"] = ":".join(str(x) for x in (bus.interface, bus.channel, bus.port) if x is not None)
    opts.update(bus.options or {})
    net = cls(**opts)
    net.open()
    try:
        for name, m in profile.motors.items():
            net.add_drive(AxisConfig(name=name, address=m.address, description=str(m.drive),
                                     rated_current_a=m.rated_current_a,
                                     current_limit_a=m.current_limit_a,
                                     speed_limit_rad_s=m.speed_limit_rad_s,
                                     counts_per_rev=m.counts_per_rev))
        net.start(profile.bench.period_s)
    except BaseException:
        net.close()
        raise
    return net


def run_profile(profile_path, *, sim: bool = False, out_dir="results/run", serial: str = "",
                db=None, yes: bool = False, rrd=None, live: bool = False, connect=None,
                method: str = "default", seed=None, quiet: bool = True, subscribers=(),
                operator=None) -> dict:
    """Run a whole profile; returns the result dict (what result.json holds).

    Writes the run folder (Parquet traces, result.json, junit.xml) and a row in the
    station database. ``subscribers`` are extra record consumers (callables).
    """
    from .console import ProgressDisplay
    from .recorder import ParquetRecorder
    from .report import ResultWriter
    from .sequencer import AutoOperator, Sequencer
    from .station_db import StationDatabase

    profile = load_profile(profile_path)
    if sim and not profile.simulation:
        raise GearbenchError(f"{profile.path}: --sim needs a 'simulation:' section describing "
                             f"the plant; add one (see profiles/cvt.yaml)")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    db_path = Path(db) if db else out.resolve().parent / "station.sqlite"
    stream = RecordStream([ParquetRecorder(out), ResultWriter(out), StationDatabase(db_path),
                           ProgressDisplay(sys.stderr, quiet=quiet), *subscribers])
    if rrd or live or connect:
        from .live import open_live_view

        view = open_live_view(live=live, connect=connect, rrd=rrd)
        if view is not None:
            stream.subscribe(view)
    if operator is None:
        operator = AutoOperator() if yes else TerminalOperator()
    sim_plant = dict(profile.simulation) if sim else None
    if sim_plant is not None and seed is not None:
        sim_plant["seed"] = seed
    with contextlib.ExitStack() as stack:
        stack.callback(stream.close)
        fixture = None
        bus = profile.bench.bus
        if sim:
            from .simbench import SimBench

            simbench = stack.enter_context(SimBench(profile, seed=seed))
            fixture, bus = simbench, simbench.bus_spec()
        net = open_network(bus, profile)
        stack.callback(net.close)
        seq = Sequencer(profile, net, emit=stream.emit, operator=operator, fixture=fixture,
                        serial=serial, out_dir=str(out), sim_truth=sim_plant, method=method)
        result = seq.run()
    if stream.errors:
        print("gearbench: warning: output problems: " + "; ".join(stream.errors), file=sys.stderr)
    return result
