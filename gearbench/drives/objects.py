"""CiA 301/402 vocabulary shared by the drive descriptions, the master and the checks:
object references, mode numbers, unit codes, data types, and the problem record."""
from __future__ import annotations

import math
import re
from dataclasses import dataclass

from ..errors import DriveError

# CiA 402 modes of operation (0x6060) and their bit in 0x6502 supported drive modes
MODE_NAMES = {1: "profile position", 2: "velocity (vl)", 3: "profile velocity", 4: "profile torque",
              6: "homing", 7: "interpolated position", 8: "cyclic sync position",
              9: "cyclic sync velocity", 10: "cyclic sync torque"}
MODE_BIT = {1: 0, 2: 1, 3: 2, 4: 3, 6: 5, 7: 6, 8: 7, 9: 8, 10: 9}
VELOCITY_MODES = (9, 3)      # preferred first: cyclic synchronous, then profile (with ramps)
TORQUE_MODES = (10, 4)

# CiA 303-2 SI unit codes used in 0x60A9 (numerator: rad per unit; denominator: s per unit)
SI_NUMERATOR = {0xB4: 2 * math.pi, 0x10: 1.0}         # revolution, radian
SI_DENOMINATOR = {0x03: 1.0, 0x47: 60.0}               # second, minute
CURRENT_UNITS = ("mA", "A", "permille_rated")
TORQUE_RELATIONS = ("permille_rated_current",)

# CANopen data type -> (bits, struct code)
DATA_TYPES = {0x1: (8, "B"), 0x2: (8, "b"), 0x3: (16, "h"), 0x4: (32, "i"), 0x5: (8, "B"),
              0x6: (16, "H"), 0x7: (32, "I")}


def mode_name(mode: int) -> str:
    return MODE_NAMES.get(mode, "manufacturer mode" if mode < 0 else "reserved")


def modes_from_bits(bits: int) -> tuple[int, ...]:
    return tuple(m for m, b in MODE_BIT.items() if bits >> b & 1)


def modes_to_bits(modes) -> int:
    """0x6502 value of the CiA 402 modes among ``modes`` (manufacturer modes have no standard bit)."""
    return sum(1 << MODE_BIT[m] for m in modes if m in MODE_BIT)


def velocity_unit_rad_s(code: int) -> float | None:
    """rad/s per count of a CiA 402 0x60A9 'SI unit velocity' value, None if not a rotary velocity."""
    prefix = (code >> 24) & 0xFF
    exponent = prefix - 256 if prefix > 127 else prefix
    num, den = (code >> 16) & 0xFF, (code >> 8) & 0xFF
    if num not in SI_NUMERATOR or den not in SI_DENOMINATOR:
        return None
    return 10.0 ** exponent * SI_NUMERATOR[num] / SI_DENOMINATOR[den]


def describe_velocity_code(code: int) -> str:
    per = velocity_unit_rad_s(code)
    if per is None:
        return f"0x{code:08X} (not a rotary velocity unit)"
    rpm = per * 60 / (2 * math.pi)
    return f"0x{code:08X} ({rpm:g} rpm)" if abs(rpm - round(rpm, 6)) < 1e-9 or rpm < 1 else f"0x{code:08X}"


def mapping_entry(index: int, subindex: int, bits: int) -> str:
    """A PDO mapping entry as CiA 301 writes it, e.g. 0x60710010 (index, sub-index, bits)."""
    return f"0x{index << 16 | subindex << 8 | bits:08X}"


def interpolation_setting(period_s: float, exponent: int, exponent_writable: bool) -> tuple[int, int] | None:
    """(0x60C2:01 value, 0x60C2:02 exponent) expressing ``period_s`` exactly, or None.

    CiA 402 0x60C2: interpolation time period = value x 10^exponent s, value 1..255.
    The drive's exponent is kept where it fits; a writable exponent may be changed
    (milliseconds first, then finer units).
    """
    tries = [exponent] + ([e for e in (-3, -4, -5, -6, -2, -1, 0) if e != exponent] if exponent_writable else [])
    for e in tries:
        value = round(period_s / 10.0 ** e)
        if 1 <= value <= 255 and abs(value * 10.0 ** e - period_s) <= 1e-9:
            return value, e
    return None


@dataclass(frozen=True, order=True)
class ObjRef:
    index: int
    subindex: int = 0

    def __str__(self) -> str:
        return f"0x{self.index:04X}" + (f":{self.subindex:02X}" if self.subindex else "")

    @classmethod
    def parse(cls, value, where: str) -> "ObjRef":
        if isinstance(value, ObjRef):
            return value
        if isinstance(value, int) and not isinstance(value, bool):
            return cls(value, 0)
        m = re.fullmatch(r"\s*(0x[0-9A-Fa-f]{4})(?::(0x)?([0-9A-Fa-f]{1,2}))?\s*", str(value))
        if not m:
            raise DriveError(f"{where}: '{value}' is not an object like 0x6078 or 0x30D1:02")
        return cls(int(m.group(1), 16), int(m.group(3), 16) if m.group(3) else 0)


@dataclass(frozen=True)
class Problem:
    """One reason gearbench cannot drive (``fatal``) or a warning, naming file, object and fix."""

    file: str
    obj: str
    problem: str
    fix: str
    fatal: bool = True

    def __str__(self) -> str:
        head = ": ".join(x for x in (self.file, self.obj, self.problem) if x)
        return f"{head}; {self.fix}" if self.fix else head
