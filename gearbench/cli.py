"""The ``gearbench`` command line.

Each subcommand is one module in ``gearbench/commands/`` exposing ``NAME``,
``HELP``, ``add_arguments(parser)`` and ``run(args) -> int``; adding a command is
adding a module. ``GearbenchError`` becomes one line on stderr and its exit code
(2 bad input, 3 bench fault/abort).
"""
from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import sys

from . import __version__, one_blas_thread
from .errors import GearbenchError


def _command_modules():
    from . import commands

    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        yield importlib.import_module(f"{commands.__name__}.{info.name}")


EXIT_CODES = """exit codes:
  0  done (run: the unit passed)
  1  run: a limit failed (the unit is bad); golden/reanalyze: a deviation
  2  bad input, or refused before anything moved (profile, trace, paths)
  3  bench fault or operator abort (drives stopped)"""


def sentence(text: str) -> str:
    """A command's one-line help as every other: capital first letter, one final period."""
    text = text.strip()
    text = text[:1].upper() + text[1:]
    return text if text.endswith((".", "?", "!")) else text + "."


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="gearbench",
        description="Gear-reducer efficiency without a torque transducer.",
        epilog=EXIT_CODES, formatter_class=argparse.RawDescriptionHelpFormatter)
    from .analysis import METHOD_VERSIONS

    methods = ", ".join(f"{m} {v}" for m, v in METHOD_VERSIONS.items())
    parser.add_argument("--version", action="version",
                        version=f"gearbench {__version__} (analysis methods: {methods})")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in _command_modules():
        text = sentence(mod.HELP)
        p = sub.add_parser(mod.NAME, help=text, description=text, epilog=EXIT_CODES,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser



def main(argv: list[str] | None = None) -> int:
    one_blas_thread()
    # Library chatter (SDO retries, reconnects) is not for the operator's screen;
    # faults reach them as one clear line through GearbenchError.
    for name in ("canopen", "can", "pymodbus"):
        logging.getLogger(name).setLevel(logging.CRITICAL)
    parser = build_parser()
    args = parser.parse_args(argv)  # argparse itself exits 2 on usage errors
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    try:
        return int(args._run(args) or 0)
    except GearbenchError as exc:
        print(f"gearbench {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"gearbench {args.command}: aborted by operator", file=sys.stderr)
        return 3
    except BrokenPipeError:
        return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
