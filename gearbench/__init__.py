"""gearbench — gear-reducer efficiency without a torque transducer.

How the package is laid out (dependencies point down only; checked by import-linter,
see ``[tool.importlinter]`` in pyproject.toml and the README):

- the face: ``cli`` (→ ``commands``, one module per subcommand), ``api`` (the open
  test bench), ``openhtf`` (plugs);
- ``reports`` (per-unit report, plots, live view) and ``fleet`` (central database,
  history, SPC, re-analysis, golden units, gauge R&R) read what stations wrote;
- ``station``: the run on one tester — plan, sequencer, records and their outputs;
- ``profile`` (the declarative test), ``drives`` (CANopen CiA 402, Modbus);
- ``emulate`` (drives played by a process behind real endpoints, fault injection)
  over ``sim`` (the physical bench);
- ``analysis``: pure numerics (numpy, scipy), no I/O;
- shared by all: ``trace`` (the one ``Trace`` type) and ``errors``.
"""
import importlib
import importlib.abc
import importlib.util
import os
import sys

from .errors import GearbenchError, TraceError, ProfileError, DriveError, BenchFault, ExcitationError
from .trace import Trace

__version__ = "0.1.0"
__all__ = ["Trace", "GearbenchError", "TraceError", "ProfileError", "DriveError",
           "BenchFault", "ExcitationError", "__version__", "one_blas_thread"]

# Public modules that moved in 0.1 → 0.2's regroup; the old import keeps working
# for one release (documented in README "How the code is laid out").
_MOVED = {"gearbench.recorder": "gearbench.station.recorder"}


class _MovedModules(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Imports an old module name as the module at its new home (the same object)."""

    def find_spec(self, name, path=None, target=None):
        return importlib.util.spec_from_loader(name, self) if name in _MOVED else None

    def create_module(self, spec):
        return importlib.import_module(_MOVED[spec.name])

    def exec_module(self, module):
        pass


if not any(isinstance(f, _MovedModules) for f in sys.meta_path):
    sys.meta_path.append(_MovedModules())


def one_blas_thread() -> None:
    """One BLAS thread in this process and the processes it starts. Our matrices are tall
    and narrow (a few columns), where OpenBLAS's worker threads gain nothing; on a busy
    2-core tester they spin against each other and against the paced acquisition:
    np.linalg.lstsq of 12,000 x 30 took 123 ms instead of 5.7 ms, the bench diagnosis of
    one 12 s trace 58 s instead of 4.9 s (load 3). A user's own setting is kept."""
    from threadpoolctl import threadpool_limits

    if not any(v in os.environ for v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")):
        os.environ["OPENBLAS_NUM_THREADS"] = "1"      # children (the emulator) start with it
        threadpool_limits(1, user_api="blas")
