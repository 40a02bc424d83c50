"""The emulated bench: one simulated world (``EmulatedBench``) behind real drive
protocols — CANopen CiA 402 (``canopen_server``) and Modbus TCP (``modbus_server``) —
with one protocol-independent CiA 402 drive state machine per axis (``Cia402Axis``)."""
from .bench import EmulatedBench
from .cia402_axis import Cia402Axis

__all__ = ["EmulatedBench", "Cia402Axis"]
