"""gearbench — gear-reducer efficiency without a torque transducer.

Layers (dependencies point down only): ``analysis`` (pure numpy), ``sim``
(the physical bench), ``drives`` (CANopen / Modbus / emulation), ``sequencer``,
and the interfaces (``cli``, live view).
"""
from .errors import GearbenchError, TraceError, ProfileError, DriveError, BenchFault, ExcitationError
from .trace import Trace

__version__ = "0.1.0"
__all__ = ["Trace", "GearbenchError", "TraceError", "ProfileError", "DriveError",
           "BenchFault", "ExcitationError", "__version__"]
