"""``python -m gearbench.benchmarks <name> [args]`` — run one benchmark; no name lists them."""
from __future__ import annotations

import sys

from .. import one_blas_thread
from . import available, run


def main(argv: list[str] | None = None) -> int:
    one_blas_thread()
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print("usage: python -m gearbench.benchmarks NAME [args]\nbenchmarks: " + ", ".join(available()))
        return 0 if argv else 2
    return run(argv[0], argv[1:])


if __name__ == "__main__":
    sys.exit(main())
