"""Old name of ``gearbench.benchmarks``, kept for one release so that
``python -m gearbench.bench NAME`` still works; "bench" now means the test bench."""
from ..benchmarks import available, run  # noqa: F401
