"""The Python API the CLI itself uses: load a profile, open a bench, run it.

Whole job (what ``gearbench run`` does)::

    from gearbench.api import run_profile
    result = run_profile("profiles/cvt.yaml", sim=True, out_dir="results/demo", serial="SN1")
    result["passed"], result["motors"]["in"]["Kt"], result["efficiency"][0]["eta_incremental"]

Step by step, with typed results (what the OpenHTF phases do)::

    from gearbench.api import open_bench
    with open_bench("profiles/cvt.yaml", sim=True, out_dir="results/sn1", serial="SN1") as bench:
        kt_in = bench.calibrate("in").kt_nm_per_a
        bench.calibrate("out")
        bench.load()
        points = bench.efficiency()
        result = bench.finish()          # RunResult; result.json, junit.xml, traces written

Both paths are one code path: ``open_bench`` -> ``Bench`` -> ``Sequencer.begin /
run_step / finish``. Nothing here imports OpenHTF.
"""
from __future__ import annotations

import contextlib
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable

from .analysis.calibration import MotorCalibration
from .analysis.efficiency import EfficiencyPoint
from .drives.base import AxisConfig, DriveNetwork
from .drives.devicecheck import require_devices
from .drives.registry import network_class
from .emulate.launch import SimBench
from .errors import Aborted, GearbenchError
from .fleet.push import CentralPush
from .fleet.reanalysis import ProfileSnapshot
from .profile import CalibrateStep, EfficiencyStep, LoadStep, load_profile
from .reports.live import open_live_view
from .sim.truth import truth_of
from .station.config import central_url
from .station.console import ProgressDisplay
from .station.database import StationDatabase
from .station.database import check_writable as check_db_writable
from .station.records import LimitResult, RecordStream
from .station.recorder import ParquetRecorder
from .station.results import ResultWriter, as_written
from .station.sequencer import AutoOperator, Sequencer

__all__ = ["load_profile", "open_network", "open_bench", "run_profile", "Bench", "RunResult",
           "MotorCalibration", "EfficiencyPoint", "MotorResult", "EfficiencyPointResult", "LimitCheck", "AutoOperator", "TerminalOperator"]


# ---------------------------------------------------------------------- operators
class TerminalOperator:
    """Prompts at the terminal; Enter confirms, 'a' aborts."""

    def confirm(self, prompt: str) -> None:
        try:
            answer = input(f"\n>>> {prompt} — press Enter when done, 'a' to abort: ")
        except EOFError:
            answer = "a"
        if answer.strip().lower().startswith("a"):
            raise Aborted("operator abort at prompt")


# ------------------------------------------------------------------ typed results
# A motor's identification and an efficiency point are the analysis's own frozen
# dataclasses, the same objects the records carry; the old names stay for one release.
MotorResult = MotorCalibration
EfficiencyPointResult = EfficiencyPoint


LimitCheck = LimitResult          # one limit's verdict: the record the run emitted


@dataclass(frozen=True)
class RunResult:
    """A finished run: the typed view of result.json (``raw`` is the dict itself).

    ``status``: passed | failed (a limit) | fault | aborted; ``exit_code`` 0 / 1 / 3.
    """
    serial: str
    run_id: str
    profile: str
    status: str
    passed: bool
    exit_code: int
    reason: str
    motors: dict[str, MotorCalibration]
    ratio: float | None
    efficiency: tuple[EfficiencyPoint, ...]
    limits: tuple[LimitCheck, ...]
    out_dir: str
    samples: int
    lost_samples: int
    bench_time_s: float
    wall_time_s: float
    raw: dict = field(default_factory=dict, repr=False)

    @classmethod
    def from_dict(cls, d: dict) -> "RunResult":
        """From a result dict (``run_profile``'s return value or a result.json)."""
        return cls(str(d.get("serial", "")), str(d.get("run_id", "")), str(d.get("profile", "")),
                   str(d["status"]), bool(d["passed"]), int(d["exit_code"]), str(d.get("reason", "")),
                   {m: MotorCalibration.from_dict(v, f"motors.{m}", m) for m, v in (d.get("motors") or {}).items()},
                   None if d.get("ratio") is None else float(d["ratio"]),
                   tuple(EfficiencyPoint.from_dict(p) for p in d.get("efficiency") or ()),
                   tuple(LimitResult.from_dict(x) for x in d.get("limits") or ()),
                   str(d.get("out_dir", "")), int(d.get("samples", 0)), int(d.get("lost_samples", 0)),
                   float(d.get("bench_time_s", 0.0)), float(d.get("wall_time_s", 0.0)), dict(d))


# ------------------------------------------------------------------------ network
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
                                     counts_per_rev=m.counts_per_rev,
                                     extra={"profile_dir": str(Path(profile.path).parent)}))
        net.start(profile.bench.period_s)
    except BaseException:
        net.close()
        raise
    return net


# -------------------------------------------------------------------------- bench
class Bench:
    """An open bench running one profile for one unit; made by ``open_bench``.

    Steps run in any order the caller likes (the profile's order is what
    ``run()`` does). A step that faults quick-stops the drives, raises the
    GearbenchError, and the run ends as ``fault`` at ``finish()``.
    """

    def __init__(self, profile, network: DriveNetwork, sequencer, stream: RecordStream):
        self.profile = profile
        self.network = network
        self.sequencer = sequencer
        self.stream = stream
        self.result: RunResult | None = None
        self.error: GearbenchError | None = None

    @property
    def drives(self) -> dict:
        """The drives by axis name ("in", "out"), for callers' own checks."""
        return self.network.drives

    @property
    def operator(self):
        return self.sequencer.operator

    @operator.setter
    def operator(self, op) -> None:
        """Who confirms mounting prompts (anything with ``confirm(prompt)``)."""
        self.sequencer.operator = op

    def run_step(self, step) -> None:
        """Run one profile step (a step object, or its index in ``profile.steps``)."""
        if self.result is not None:
            raise GearbenchError(f"{self.profile.path}: the run is finished; open a new bench")
        if self.error is not None:
            raise GearbenchError(f"run stopped earlier ({self.error}); finish() and open a new bench")
        if isinstance(step, int):
            step = self.profile.steps[step]
        try:
            self.sequencer.run_step(step)
        except GearbenchError as exc:
            self.error = exc
            raise

    def _steps(self, kind: type, **match) -> list:
        return [s for s in self.profile.steps if isinstance(s, kind)
                and all(getattr(s, k) == v for k, v in match.items())]

    def calibrate(self, motor: str) -> MotorCalibration:
        """Run the profile's calibrate step for ``motor``; its Kt, J, D, Tc."""
        steps = self._steps(CalibrateStep, motor=motor)
        if not steps:
            raise GearbenchError(f"{self.profile.path}: no calibrate step for motor '{motor}'; "
                                 f"add one under steps: (kind: calibrate, motor: {motor})")
        self.run_step(steps[0])
        return self.sequencer.calibrations[motor]

    def load(self) -> None:
        """The operator mounts the reducer (the profile's load step, or the default prompt)."""
        steps = self._steps(LoadStep)
        self.run_step(steps[0] if steps else LoadStep(prompt=""))

    def efficiency(self) -> list[EfficiencyPoint]:
        """Run the profile's efficiency step(s); the operating points they measured."""
        steps = self._steps(EfficiencyStep)
        if not steps:
            raise GearbenchError(f"{self.profile.path}: no efficiency step; add one under steps: "
                                 f"(kind: efficiency, speeds_in_rad_s: [...], torques_out_nm: [...])")
        n0 = len(self.sequencer.points)
        for s in steps:
            self.run_step(s)
        return self.sequencer.points[n0:]

    @property
    def motors(self) -> dict[str, MotorCalibration]:
        """Motors calibrated so far."""
        return dict(self.sequencer.calibrations)

    @property
    def points(self) -> list[EfficiencyPoint]:
        """Efficiency points measured so far, in run order."""
        return list(self.sequencer.points)

    def kt_used(self, motor: str) -> float:
        """The Kt the next steps use for ``motor``: calibrated, else the datasheet's."""
        return self.sequencer._kt(motor)

    @property
    def ratio(self) -> float | None:
        """The reducer ratio used by the last efficiency step (measured or the profile's)."""
        return self.sequencer.ratio

    def run(self) -> RunResult:
        """Every profile step in order, then ``finish()``; a fault ends the run (status fault)."""
        try:
            for step in self.sequencer.step_groups():   # parallel calibration: a tuple of steps
                self.run_step(step)
        except GearbenchError:
            pass   # recorded in self.error; finish() reports it
        return self.finish()

    def finish(self) -> RunResult:
        """Check the profile's limits, write the outputs; idempotent."""
        if self.result is None:
            # typed from the result as written, so it equals RunResult.from_dict(result.json)
            self.result = RunResult.from_dict(as_written(self.sequencer.finish(error=self.error)))
        return self.result


@contextlib.contextmanager
def open_bench(profile, *, sim: bool = False, out_dir="results/run", serial: str = "",
               operator=None, subscribers: Iterable[Callable] = (), db=None, seed=None,
               method: str = "default", quiet: bool = True, live: bool = False, rrd=None,
               connect=None, fixture=None, central: str | None = None, twin: str | None = None,
               summary=None):
    """Open the bench for ``profile`` (a path or a loaded Profile); yields a ``Bench``.

    ``sim=True`` starts the emulated bench (the profile's ``simulation:`` plant) in a
    child process behind the same drive protocol. ``operator`` confirms mounting
    prompts (default: the terminal; ``AutoOperator()`` on the simulated bench).
    ``subscribers`` are extra record consumers (callables, see gearbench.station.records).
    ``fixture`` does the physical mounting (default: nothing on a real bench, the
    emulator with ``sim``, or the drive network itself if it has ``mount()``, as an
    in-process simulated drive family does). On leaving, an unfinished run is
    finished (a GearbenchError inside the block makes it a fault), drives are
    disabled and the outputs closed. Every run copies its profile into the run folder
    and, when a central database is configured (``central`` URL, else
    ``$GEARBENCH_CENTRAL`` or the station config), is pushed to it after it ends —
    whoever opens the bench (CLI, script, OpenHTF). ``summary``: a stream for the
    end-of-run table and verdict line (the command line's stdout); progress goes to stderr.
    """
    if not hasattr(profile, "steps"):
        profile = load_profile(profile)
    require_devices(profile)   # every drive description checked, all problems at once, before anything moves
    if sim and not profile.simulation:
        raise GearbenchError(f"{profile.path}: --sim needs a 'simulation:' section describing "
                             f"the plant; add one (see profiles/cvt.yaml)")
    out = Path(out_dir)
    _check_writable(out)
    db_path = Path(db) if db else out.resolve().parent / "station.sqlite"
    check_db_writable(db_path)        # refused before anything moves, not after the test
    if rrd:
        _check_writable_file(Path(rrd), "--rrd")
    # required outputs: a unit cannot pass without them (the result writer last, so it sees
    # a failure of the others); best-effort: the progress display, the live view, callers' extras
    extras: list = [ProfileSnapshot()]   # profile.yaml in the run folder, for re-analysis
    url = central_url(central, db_path)
    if url:
        extras.append(CentralPush(db_path, url, quiet=quiet))
    stream = RecordStream([ProgressDisplay(sys.stderr, quiet=quiet, summary=summary), *extras, *subscribers],
                          required=[ParquetRecorder(out), StationDatabase(db_path), ResultWriter(out)])
    if operator is None:
        operator = AutoOperator() if sim else TerminalOperator()
    sim_plant = dict(profile.simulation) if sim else None
    if sim and twin:   # a fitted digital twin (gearbench twin --write) replaces the profile's plant
        from .twin.block import check_twin_bench, load_twin_block

        sim_plant = dict(load_twin_block(twin))
        check_twin_bench(sim_plant, profile, twin)
    if sim_plant is not None and seed is not None:
        sim_plant["seed"] = seed
    with contextlib.ExitStack() as stack:
        stack.callback(stream.close)
        if rrd or live or connect:

            view = open_live_view(live=live, connect=connect, rrd=rrd)
            if view is not None:
                stream.subscribe(view)
        bus = profile.bench.bus
        if sim:

            simbench = stack.enter_context(SimBench(profile, seed=seed, simulation=twin))
            fixture, bus = fixture or simbench, simbench.bus_spec()
            if simbench.substitution():    # never a silent substitution of the profile's bus
                print(f"gearbench: {simbench.substitution()}", file=sys.stderr)
        try:
            net = open_network(bus, profile)
        except GearbenchError as exc:   # the bench never started: still a record of the attempt
            Sequencer(profile, _NoDrives(), emit=stream.emit, operator=operator, serial=serial,
                      out_dir=str(out), sim_truth=truth_of(sim_plant), method=method).record_failed_start(exc)
            raise
        stack.callback(net.close)
        if sim:
            net.watch_process(simbench.proc.pid)   # the emulated drives share this host's CPUs
        # against real drives a writer that falls behind is a fault; in lockstep nothing can be missed
        stream.realtime = not net.lockstep
        if fixture is None and net.mounts_itself:
            fixture = net
        seq = Sequencer(profile, net, emit=stream.emit, operator=operator, fixture=fixture,
                        serial=serial, out_dir=str(out), sim_truth=truth_of(sim_plant), method=method)
        bench = Bench(profile, net, seq, stream)
        seq.begin()
        try:
            yield bench
        except GearbenchError as exc:
            bench.error = bench.error or exc
            bench.finish()
            raise
        except BaseException:
            net.stop_all()
            seq.restore_signals()
            raise
        bench.finish()
    if stream.errors:
        print("gearbench: warning: output problems: " + "; ".join(stream.errors), file=sys.stderr)


class _NoDrives(DriveNetwork):
    """Stands in for a network that could not be opened, so a failed start is recorded."""
    family = "none"

    def open(self) -> None: ...

    def add_drive(self, config):
        raise GearbenchError("no drive network")

    def start(self, period_s: float) -> None: ...

    def _sample(self):
        raise GearbenchError("no drive network")

    def _close(self) -> None: ...


def _check_writable_file(path: Path, what: str) -> None:
    """Refuse a file the run will write that cannot be created (exit 2, before anything moves)."""
    existed = path.exists()
    try:
        if path.is_dir():
            raise IsADirectoryError(21, "is a folder")
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "ab"):
            pass
        if not existed:
            path.unlink()
    except OSError as exc:
        raise GearbenchError(f"{what} {path}: cannot write it ({exc.strerror or exc}); choose "
                             f"a writable path") from None


def _check_writable(out: Path) -> None:
    """Refuse an output folder that cannot be written before anything moves (exit 2)."""
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".gearbench-write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise GearbenchError(f"{out}: cannot write the run's output folder ({exc.strerror or exc}); "
                             f"choose another --out or fix its permissions/free space") from None


def run_profile(profile_path, *, sim: bool = False, out_dir="results/run", serial: str = "",
                db=None, yes: bool = False, rrd=None, live: bool = False, connect=None,
                method: str = "default", seed=None, quiet: bool = True, subscribers=(),
                operator=None, central: str | None = None, twin: str | None = None,
                summary=None) -> dict:
    """Run a whole profile; returns the result dict (what result.json holds).

    Writes the run folder (Parquet traces, result.json, junit.xml) and a row in the
    station database. ``subscribers`` are extra record consumers (callables).
    """
    if operator is None:
        operator = AutoOperator() if yes else TerminalOperator()
    with open_bench(profile_path, sim=sim, out_dir=out_dir, serial=serial, operator=operator,
                    subscribers=subscribers, db=db, seed=seed, method=method, quiet=quiet,
                    live=live, rrd=rrd, connect=connect, central=central, twin=twin,
                    summary=summary) as bench:
        result = bench.run()
    return result.raw
