"""On-demand benchmarks: ``python -m gearbench.benchmarks <name> [args]``.

Each benchmark is a module ``gearbench/benchmarks/<name>.py`` with ``main(argv) -> int``;
the dispatcher discovers them, so adding a benchmark is adding a module.
"""
from __future__ import annotations

import importlib
import pkgutil


def available() -> list[str]:
    """Names of the benchmark modules (those defining ``main``)."""
    names = []
    for info in pkgutil.iter_modules(__path__):
        if info.name.startswith("_"):
            continue
        names.append(info.name)
    return sorted(names)


def run(name: str, argv: list[str]) -> int:
    if name not in available():
        raise SystemExit(f"unknown benchmark '{name}'; available: {', '.join(available())}")
    mod = importlib.import_module(f"{__name__}.{name}")
    if not hasattr(mod, "main"):
        raise SystemExit(f"gearbench.benchmarks.{name} has no main(argv)")
    return int(mod.main(argv) or 0)
