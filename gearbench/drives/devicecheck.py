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
from .objects import ObjRef, interpolation_setting, mode_name, velocity_unit_rad_s

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
    profile_dir = Path(profile.path).parent if getattr(profile, "path", None) else None
    cyclic = (profile.bench.bus.options or {}).get("cyclic")
    for name, motor in profile.motors.items():
        try:
            model = resolve(str(motor.drive), motor.address, profile_dir=profile_dir)
        except DriveError as exc:
            if str(exc) not in seen:
                seen.add(str(exc))
                report.errors.append(str(exc))
            continue
        models[name] = model
        kinds = profile.drive_modes(name)
        problems = [p for p in model.problems if "torque" not in p.problem or "torque" in kinds] + \
            role_problems(model, kinds, name) + start_problems(model, kinds, profile.bench.period_s, cyclic, motor)
        for p in problems:
            text = str(p)
            if text in seen:
                continue
            seen.add(text)
            (report.errors if p.fatal else report.warnings).append(text)
        report.notes += [n for n in _describe(name, model, kinds, cyclic) if n not in report.notes]
    if models and len(models) == len(profile.motors):
        _bus_budget(profile, models, report)


def _velocity_per_count(m, counts_per_rev) -> float | None:
    """rad/s per velocity count as the drive's defaults give it (None when unknown before start-up)."""
    unit = m.velocity_unit
    if isinstance(unit, ObjRef):
        v = m.var(unit)
        unit = v.default if v is not None and v.default is not None else None
        if m.velocity_set is not None:
            unit = m.velocity_set
    if isinstance(unit, int) and not isinstance(unit, bool):
        return velocity_unit_rad_s(unit)
    if unit == "inc/s" and counts_per_rev:
        return 2 * math.pi / counts_per_rev
    return None


def chosen_modes(m, kinds, cyclic) -> dict:
    """{kind: 0x6060 code} the start-up will pick from the EDS's modes (``CiA402Drive._select_modes``)."""
    if m.supported_modes is None:
        return {}
    usable = tuple(x for x in m.supported_modes if not (cyclic is False and x in (9, 10)))
    return {k: m.mode_for(k, usable) for k in kinds}


def start_problems(m, kinds, period_s: float, cyclic, motor=None) -> list[Problem]:
    """What the start-up checks beyond the model itself, decided from the EDS as the drive
    would answer with its defaults: the SYNC period expressed in 0x60C2 (exponent written
    only where 0x60C2:02 is writable), the factor groups 1:1, the max motor speed 0x6080
    against the profile's speed limit (``CiA402Drive.configure``)."""
    out, where = [], Path(m.eds).name
    for ref, want in m.expect.items():
        v = m.var(ref)
        got = v.default if v is not None else None
        if isinstance(want, tuple):
            other = m.var(want[1])
            want = other.default if other is not None else None
        elif got is not None and got != want:   # a described value: the drive is checked at start-up
            out.append(Problem(where, m.label(ref), f"EDS/DCF value {got}, but {m.description.where('position.expect')}"
                               f" expects {want}", "the start-up refuses a drive configured as this file says: "
                               "set the factor group to 1:1", fatal=False))
            continue
        if got is not None and want is not None and got != want:
            out.append(Problem(where, m.label(ref), f"EDS default {got}, but gearbench reads positions in encoder "
                               f"increments and needs {want} (factor group 1:1)",
                               "set the factor group to 1:1 in the drive (and its EDS/DCF)"))
    if motor is not None and m.counts_per_rev_fixed is not None:     # the start-up uses/compares this value
        said = m.description.where("position.counts_per_rev")
        if m.counts_per_rev_fixed == "profile":
            out.append(Problem(where, "encoder resolution", f"no object reports it ({said}: profile); the profile's "
                               f"counts_per_rev {motor.counts_per_rev:g} is used as given",
                               "check it against the encoder's datasheet: Kt and J scale with it", fatal=False))
        elif abs(m.counts_per_rev_fixed - motor.counts_per_rev) > 1e-9:
            out.append(Problem(where, "encoder resolution", f"{said} fixes {m.counts_per_rev_fixed} increments per "
                               f"revolution but the profile says counts_per_rev: {motor.counts_per_rev:g}",
                               "fix the profile or the description"))
    if motor is not None and 0x6080 in m.od and m.od[0x6080].default is None:
        out.append(Problem(where, m.label("0x6080"), "no EDS default: the start-up reads the drive's max motor speed "
                           f"and refuses one below the profile's speed_limit_rad_s {motor.speed_limit_rad_s:g}",
                           "check it in the drive's commissioning tool (or with describe-drive --probe)",
                           fatal=False))
    if motor is not None and 0x6080 in m.od and m.od[0x6080].default is not None:
        per = _velocity_per_count(m, motor.counts_per_rev)
        top = m.od[0x6080].default
        if per is not None and top * per < motor.speed_limit_rad_s * (1 - 1e-3):
            out.append(Problem(where, m.label("0x6080"), f"EDS default {top} ({top * per:.1f} rad/s) is below the "
                               f"profile's speed_limit_rad_s {motor.speed_limit_rad_s:g}",
                               "lower the profile's limit or raise the drive's max motor speed"))
    modes = chosen_modes(m, kinds | {"velocity", "torque"}, cyclic)
    if any(code in (9, 10) for code in modes.values()) and 0x60C2 in m.od:
        exponent = m.exponent_default()
        if interpolation_setting(period_s, exponent, m.exponent_writable) is None:
            out.append(Problem(where, m.label("0x60C2:02"), f"SYNC period {period_s:g} s (bench.period_s) cannot be "
                               f"written to 0x60C2 interpolation time (unit 1e{exponent} s, value 1..255"
                               + ("" if m.exponent_writable else ", exponent read-only") + ")",
                               "choose a period the drive can interpolate"
                               + ("" if m.exponent_writable else f", e.g. {max(1, round(period_s / 10.0 ** exponent))}"
                                  f"e{exponent} s")))
    return out


def _describe(name: str, m, kinds, cyclic=None) -> list[str]:
    """What validate says of one motor's drive: where the description was looked for,
    which one matched and how, and the objects and modes gearbench will use."""
    lines = []
    look = m.lookup
    if look.looked:
        lines.append(f"descriptions of {Path(m.eds).name} looked for in: " + ", ".join(look.looked))
    if m.description is not None:
        lines.append(f"{name}: {m.name} - {m.description.path} (matched by {look.matched_by})")
    else:
        lines.append(f"{name}: {m.name} - no description matched (CiA 402 objects only; EDS "
                     + (f"vendor id 0x{m.vendor_id:08X}" if m.vendor_id is not None else "without vendor id")
                     + (f" + product code 0x{m.product_code:08X}" if m.product_code is not None else "") + ")")
    modes = chosen_modes(m, kinds, cyclic)
    shown = "modes from 0x6502 at start-up" if m.supported_modes is None else "modes " + ", ".join(
        f"{k} {code} ({mode_name(code)})" for k, code in sorted(modes.items()) if code is not None)
    def unit_text(ref, unit, scale):
        return "none" if ref is None else f"{m.label(ref)} in {unit}" + (f" x {scale:g}" if scale != 1 else "")
    vel = m.velocity_unit
    vel = "unknown" if vel is None else m.label(vel) if not isinstance(vel, (int, str)) else \
        (f"0x{vel:08X}" if isinstance(vel, int) else vel)
    torque = "" if "torque" not in kinds else (
        f"; torque setpoint {unit_text(m.torque_setpoint, m.torque_unit, m.torque_scale)}"
        if m.torque_relation == "current" else f"; torque setpoint {m.label(m.torque_setpoint)} "
                                               f"({m.torque_relation or 'relation unknown'})")
    lines.append(f"{name}: {shown}; current actual {unit_text(m.current, m.current_unit, m.current_scale)}; "
                 f"rated current {unit_text(m.rated_current, m.rated_current_unit, m.rated_current_scale)}; "
                 f"velocity unit {vel}{torque}; "
                 + ("0x6060 written by SDO per segment (not PDO-mappable); " if m.mode_by_sdo else "")
                 + (f"SYNC echo {m.label(m.sync_echo)}" if m.sync_echo else "no SYNC echo"))
    return lines


def _bus_budget(profile, models: dict, report: DeviceReport) -> None:
    bus, period = profile.bench.bus, profile.bench.period_s
    bitrate = int(((bus.options or {}).get("bus_kwargs") or {}).get("bitrate") or DEFAULT_BITRATE)
    counter = all(m.has_1019 for m in models.values())
    frames = [1 if counter else 0]                       # SYNC
    for m in models.values():
        t1, t2 = m.tpdo_entries(counter)
        r2 = m.rpdo_entries()[1]   # only the objects the drive has (never a zero-length entry)
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
