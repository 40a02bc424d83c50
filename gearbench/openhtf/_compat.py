"""Import OpenHTF without its global side effects.

openhtf 1.6.3 parses ``sys.argv`` when imported (``CONF``) and in every
``Test.configure()`` (``--config-help`` even calls ``sys.exit``), and replaces the
process's SIGINT handler on import. A station's own command line is not OpenHTF's,
so both parse an empty command line here, and the SIGINT handler in place before
the import is put back; ``GearbenchTest.execute`` installs OpenHTF's handler only
while a test runs (Ctrl-C then aborts the test as OpenHTF intends).
"""
from __future__ import annotations

import contextlib
import signal
import sys
import threading

from ..errors import GearbenchError


@contextlib.contextmanager
def plain_argv():
    """``sys.argv`` without arguments for the duration (program name kept)."""
    saved = sys.argv
    sys.argv = saved[:1] if saved else ["gearbench"]
    try:
        yield
    finally:
        sys.argv = saved


@contextlib.contextmanager
def sigint_kept():
    """Whatever SIGINT handler is in place before is in place after."""
    main = threading.current_thread() is threading.main_thread()
    before = signal.getsignal(signal.SIGINT) if main else None
    try:
        yield
    finally:
        if main and before is not None and signal.getsignal(signal.SIGINT) is not before:
            signal.signal(signal.SIGINT, before)


def import_openhtf():
    """The ``openhtf`` module; GearbenchError with the install command if missing."""
    if "openhtf" in sys.modules:
        return sys.modules["openhtf"]
    try:
        with plain_argv(), sigint_kept():
            import openhtf
    except ImportError as exc:
        raise GearbenchError(f"OpenHTF is not installed ({exc}); install the extra: "
                             f"pip install 'gearbench[openhtf]'") from None
    return openhtf


htf = import_openhtf()
