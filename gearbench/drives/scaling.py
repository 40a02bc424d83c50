"""SI <-> drive units at the drive edge (CiA 402 conventions, shared by all families).

Units on the wire (see ``drivers/cia402-servo.eds``):

- position: encoder increments (counts), ``counts_per_rev`` per motor revolution
  (CiA 402 0x608F position encoder resolution);
- velocity: increments per second (0x606C velocity actual, 0x60FF target velocity);
- current: per-mille of the motor rated current 0x6075 (0x6078 current actual);
- torque: per-mille of rated torque (0x6071 target torque, 0x6077 torque actual),
  where gearbench's drives run "current mode": 1000 per-mille of rated torque is the
  rated current, so a torque setpoint is a current setpoint. No torque constant is
  assumed anywhere (it is what gearbench identifies).
"""
from __future__ import annotations

import math
from dataclasses import dataclass


def wrap_int32(value: int) -> int:
    return (value + 2**31) % 2**32 - 2**31


def unwrap_int32(previous: int, raw: int) -> int:
    """Continue a multi-turn count from ``previous`` with the wrapped reading ``raw``."""
    return previous + wrap_int32(raw - previous)


def _clamp_bits(value: float, bits: int, signed: bool = True) -> int:
    raw = round(value)
    if signed:
        return max(-(1 << (bits - 1)), min((1 << (bits - 1)) - 1, raw))
    return max(0, min((1 << bits) - 1, raw))


@dataclass(frozen=True)
class AxisUnits:
    """SI per drive unit of one axis, each factor read from the drive (or its description).

    ``current_a_per_unit``: current actual (0x6078 per-mille of rated, or a vendor object
    in mA); ``torque_a_per_unit``: target torque 0x6071 expressed as motor current;
    ``velocity_rad_s_per_unit``: 0x606C/0x60FF (inc/s, rpm, 0.001 rpm ...).
    """

    counts_per_rev: float
    velocity_rad_s_per_unit: float
    current_a_per_unit: float
    torque_a_per_unit: float | None = None
    current_bits: int = 16
    torque_bits: int = 16
    velocity_bits: int = 32

    @property
    def rad_per_count(self) -> float:
        return 2.0 * math.pi / self.counts_per_rev

    def position_rad(self, counts: int) -> float:
        return counts * self.rad_per_count

    def position_counts(self, position_rad: float) -> int:
        return wrap_int32(round(position_rad / self.rad_per_count))

    def velocity_rad_s(self, raw: int) -> float:
        return raw * self.velocity_rad_s_per_unit

    def velocity_raw(self, velocity_rad_s: float) -> int:
        return _clamp_bits(velocity_rad_s / self.velocity_rad_s_per_unit, self.velocity_bits)

    def current_a(self, raw: int) -> float:
        return raw * self.current_a_per_unit

    def current_raw(self, current_a: float) -> int:
        return _clamp_bits(current_a / self.current_a_per_unit, self.current_bits)

    def torque_current_a(self, raw: int) -> float:
        if self.torque_a_per_unit is None:
            raise ValueError("target torque unit not verified")
        return raw * self.torque_a_per_unit

    def torque_raw(self, current_a: float) -> int:
        if self.torque_a_per_unit is None:
            raise ValueError("target torque unit not verified")
        return _clamp_bits(current_a / self.torque_a_per_unit, self.torque_bits)
