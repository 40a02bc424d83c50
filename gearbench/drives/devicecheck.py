"""Every device description of a profile checked at once, before anything moves.

``check_profile(profile)`` opens each motor's EDS + drive description (CiA 402) or
register map (Modbus) and returns *all* problems - missing objects, a motor whose
drive lacks the mode its steps need, unmappable objects, PDOs over 8 bytes, units
that cannot be resolved, register-map faults - plus the CAN bus budget of the
profile's SYNC period against ``bench.bus.bitrate`` (default 1 Mbit/s): above
``BUS_WARN`` a warning, above ``BUS_REFUSE`` an error, each naming a period that fits.
``gearbench validate`` prints them; ``gearbench run`` refuses a profile with errors.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import DriveError, ProfileError
from .description import Problem, resolve, role_problems

DEFAULT_BITRATE = 1_000_000
BUS_WARN, BUS_REFUSE = 0.60, 0.90


@dataclass
class DeviceReport:
    errors: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)      # one line per device: what gearbench will use

    @property
    def ok(self) -> bool:
        return not self.errors


def frame_bits(data_bytes: int) -> int:
    """Worst-case bits of a classic CAN frame (11-bit id) with ``data_bytes``, bit stuffing included."""
    payload = 8 * data_bytes
    return payload + 47 + (34 + payload - 1) // 4


def bus_load(frames_bytes: list[int], period_s: float, bitrate: int) -> tuple[float, int]:
    """(fraction of the bus, bits per period) for these frames every period."""
    bits = sum(frame_bits(n) for n in frames_bytes)
    return bits / (period_s * bitrate), bits


def _period_that_fits(bits: int, bitrate: int) -> float:
    """The shortest period (0.1 ms steps) keeping the bus below the warning level."""
    return math.ceil(bits / (BUS_WARN * bitrate) * 1e4) / 1e4


def check_profile(profile) -> DeviceReport:
    report = DeviceReport()
    bus = profile.bench.bus
    if bus.family == "cia402":
        _check_canopen(profile, report)
    elif bus.family == "modbus":
        from .register_map import check_register_map
        for path in sorted({str(m.drive) for m in profile.motors.values()}):
            report.errors += check_register_map(path)
    return report


def _check_canopen(profile, report: DeviceReport) -> None:
    models, seen = {}, set()
    for name, motor in profile.motors.items():
        try:
            model = resolve(str(motor.drive), motor.address)
        except DriveError as exc:
            report.errors.append(str(exc))
            continue
        models[name] = model
        kinds = profile.drive_modes(name)
        problems = [p for p in model.problems if "torque" not in p.problem or "torque" in kinds] + \
            role_problems(model, kinds, name)
        for p in problems:
            text = str(p)
            if text in seen:
                continue
            seen.add(text)
            (report.errors if p.fatal else report.warnings).append(text)
        report.notes.append(_describe(name, model, kinds))
    if models and len(models) == len(profile.motors):
        _bus_budget(profile, models, report)


def _describe(name: str, m, kinds) -> str:
    desc = Path(m.description.path).name if m.description else "no description (CiA 402 objects only)"
    modes = "modes from 0x6502 at start-up" if m.supported_modes is None else \
        "modes " + "/".join(f"{k} {m.mode_for(k, m.supported_modes)}" for k in sorted(kinds)
                            if m.mode_for(k, m.supported_modes) is not None)
    echo = f"SYNC echo {m.sync_echo}" if m.sync_echo else "no SYNC echo"
    unit = m.velocity_unit if not isinstance(m.velocity_unit, int) else f"0x{m.velocity_unit:08X}"
    return (f"{name}: {m.name} ({desc}); current {m.current} [{m.current_unit}], velocity unit {unit}, "
            f"{modes}, {echo}")


def _bus_budget(profile, models: dict, report: DeviceReport) -> None:
    bus, period = profile.bench.bus, profile.bench.period_s
    bitrate = int(((bus.options or {}).get("bus_kwargs") or {}).get("bitrate") or DEFAULT_BITRATE)
    counter = all(m.has_1019 for m in models.values())
    frames = [1 if counter else 0]                       # SYNC
    for m in models.values():
        t1, t2 = m.tpdo_entries(counter)
        r2 = m.rpdo_entries()[1]
        frames += [sum(m.bits(r) for r in entries) // 8 for entries in (t1, t2, r2)]
    load, bits = bus_load(frames, period, bitrate)
    fit = _period_that_fits(bits, bitrate)
    text = (f"bench.bus: {len(frames)} frames ({bits} bits with worst-case stuffing) every "
            f"{period * 1e3:g} ms use {load:.0%} of a {bitrate / 1e6:g} Mbit/s bus")
    if load > BUS_REFUSE:
        report.errors.append(f"{text}, above {BUS_REFUSE:.0%}: frames would queue and samples be lost; "
                             f"set bench.period_s >= {fit:g} s or a faster bus (bench.bus.bitrate)")
    elif load > BUS_WARN:
        report.warnings.append(f"{text}, above {BUS_WARN:.0%}: little room for SDO, EMCY and heartbeats; "
                               f"bench.period_s >= {fit:g} s keeps it below {BUS_WARN:.0%}")
    else:
        report.notes.append(text)


def require_devices(profile) -> DeviceReport:
    """The report, or ProfileError listing every error (``gearbench run`` refuses before anything moves)."""
    report = check_profile(profile)
    if report.errors:
        raise ProfileError(f"{profile.path}: the bench cannot run this profile ({len(report.errors)} "
                           f"problem{'s' if len(report.errors) > 1 else ''}; `gearbench validate` lists them):\n  "
                           + "\n  ".join(report.errors))
    return report


__all__ = ["DeviceReport", "Problem", "check_profile", "require_devices", "bus_load", "frame_bits"]
