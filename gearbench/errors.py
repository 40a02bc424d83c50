"""One small exception family; the CLI turns each into one line and an exit code."""


class GearbenchError(Exception):
    """Base: a problem the user can fix. ``exit_code`` is what the CLI returns."""

    exit_code = 2


class TraceError(GearbenchError):
    """A trace file or array is unusable (missing column, NaN, irregular time...)."""


class ProfileError(GearbenchError):
    """A profile YAML is invalid; the message names file, line, column and fix."""


class ExcitationError(GearbenchError):
    """The data cannot identify the parameters (poorly conditioned regression)."""


class DriveError(GearbenchError):
    """A drive could not be reached or configured."""

    exit_code = 3


class BenchFault(GearbenchError):
    """A fault or abort during a run: drives were stopped, samples kept."""

    exit_code = 3


class Aborted(BenchFault):
    """The operator (Ctrl-C, 'a' at a prompt) or the system (SIGTERM) stopped the run."""
