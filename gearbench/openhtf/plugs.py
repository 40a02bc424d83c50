"""OpenHTF plugs: the bench (real drives) and its simulated substitute.

A plug is made by OpenHTF with no arguments, so the profile and output folder are
class attributes: ``BenchPlug.for_profile(path)`` makes the configured subclass.
The bench opens at the first phase (the DUT id is known by then) and is finished
and closed in ``tearDown`` whatever happened, so the drives are always disabled
and result.json always written.
"""
from __future__ import annotations

from datetime import datetime, timezone
from pathlib import Path

from ..api import AutoOperator, Bench, RunResult, open_bench
from ..errors import Aborted, GearbenchError
from ._compat import htf


class UserInputOperator:
    """Mounting prompts through OpenHTF's UserInput plug (console and web GUI)."""

    def __init__(self, prompts):
        self.prompts = prompts

    def confirm(self, prompt: str) -> None:
        self.prompts.prompt(f"{prompt} — confirm when done")


class BenchPlug(htf.plugs.BasePlug):
    """The profile's bench: its drives on its bus, prompts to the operator.

    Substitute with ``phase.with_plugs(bench=SubClass)`` (``auto_placeholder``).
    Attributes (set by ``for_profile``): ``profile_path``, ``out_root`` (a run folder
    ``<out_root>/<dut>-<UTC>`` per test), ``seed`` (simulated plant noise).
    """

    auto_placeholder = True
    sim = False
    profile_path: str | None = None
    out_root: str = "results/openhtf"
    seed: int | None = None

    def __init__(self):
        super().__init__()
        self.bench: Bench | None = None
        self.result: RunResult | None = None
        self._cm = None
        self._stopped: BaseException | None = None

    @classmethod
    def for_profile(cls, profile_path, **attrs) -> type:
        """This plug class bound to ``profile_path`` (and ``out_root=``, ``seed=``)."""
        return type(cls.__name__, (cls,), {"profile_path": str(profile_path), "auto_placeholder": True,
                                           "__module__": cls.__module__, **attrs})

    def operator_for(self, prompts):
        """Who confirms mounting: the operator through OpenHTF's UserInput."""
        return UserInputOperator(prompts)

    def open(self, serial: str, prompts=None) -> Bench:
        """The open bench (opened on first call) for the unit ``serial``."""
        if self.bench is None:
            if not self.profile_path:
                raise GearbenchError(f"{type(self).__name__} has no profile; use "
                                     f"{type(self).__name__}.for_profile(path) or gearbench.openhtf.build_test")
            stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ")
            out = Path(self.out_root) / f"{serial or 'unknown'}-{stamp}"
            self._cm = open_bench(self.profile_path, sim=self.sim, out_dir=out, serial=serial or "",
                                  operator=self.operator_for(prompts), seed=self.seed)
            self.bench = self._cm.__enter__()
        return self.bench

    def call(self, fn, *args):
        """Run a bench action; remember an interruption (OpenHTF abort) for tearDown."""
        try:
            return fn(*args)
        except GearbenchError:
            raise
        except BaseException as exc:
            self._stopped = exc
            raise

    def finish(self) -> RunResult:
        if self.bench is None:
            raise GearbenchError("no gearbench step ran; the test has no calibrate/load/efficiency phase")
        self.result = self.bench.finish()
        return self.result

    def tearDown(self) -> None:
        if self._cm is None:
            return
        if self.bench.result is None and self.bench.error is None and self._stopped is not None:
            self.bench.error = Aborted(f"operator abort: OpenHTF stopped the test ({type(self._stopped).__name__})")
        cm, self._cm = self._cm, None
        cm.__exit__(None, None, None)      # finish if needed, disable drives, close outputs
        self.result = self.bench.result


class SimBenchPlug(BenchPlug):
    """The simulated bench: the profile's ``simulation:`` plant behind the same
    drive protocol; prompts are answered at once and the emulator mounts."""

    auto_placeholder = True
    sim = True

    def operator_for(self, prompts):
        return AutoOperator()
