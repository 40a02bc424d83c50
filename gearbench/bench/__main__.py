"""``python -m gearbench.bench`` — the old spelling of ``python -m gearbench.benchmarks``."""
import sys

from ..benchmarks.__main__ import main

if __name__ == "__main__":
    sys.exit(main())
