"""One module per ``gearbench`` subcommand (see ``gearbench.cli``).

Each imports what it runs inside ``run()``: the parser is built by importing every
command module, so a module-level import of the station, numba, Rerun or matplotlib
would be paid by every ``gearbench`` start, ``--help`` included.
"""
