"""CiA 402 drive models: a vendor's EDS joined with its drive description.

A vendor ships an EDS/DCF; gearbench reads it as shipped. What the EDS cannot say
- which object carries the current and in what unit, where the rated current and
the encoder resolution live, the velocity unit when there is no 0x60A9, how the
target torque 0x6071 relates to motor current, a manufacturer current mode and its
setpoint object, whether the drive echoes the SYNC counter - is written once per
drive model in a small YAML file (``family: cia402``, ``gearbench.drives.descfile``)
with the source of every fact.

``resolve(eds)`` joins the EDS and its description into a ``DriveModel``: every
object gearbench will read or write, each unit, the supported modes, the PDO
layout, and *every* problem found (never only the first). Pure apart from reading
the files. The start-up (``gearbench.drives.cia402``) and ``gearbench validate``
(``gearbench.drives.devicecheck``) use the same model, so what validate accepts the
start-up does too.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable

from ..errors import DriveError
from .descfile import (DescriptionError, DriveDescription, Lookup, description_dirs, find_description as _find,
                       load_description, load_descriptions)
from .objects import (CURRENT_UNITS, DATA_TYPES, MODE_BIT, MODE_NAMES, TORQUE_MODES, TORQUE_RELATIONS,
                      VELOCITY_MODES, ObjRef, Problem, describe_velocity_code, mode_name, modes_from_bits,
                      modes_to_bits, velocity_unit_rad_s)

__all__ = ["CURRENT_UNITS", "DATA_TYPES", "MODE_BIT", "MODE_NAMES", "TORQUE_MODES", "TORQUE_RELATIONS",
           "VELOCITY_MODES", "DescriptionError", "DriveDescription", "DriveModel", "ObjRef", "Problem",
           "axis_units", "current_a_per_unit", "describe_velocity_code", "description_dirs", "find_description",
           "import_eds", "load_description", "load_descriptions", "modes_from_bits", "modes_to_bits",
           "resolve", "resolve_or_raise", "role_problems", "unit_objects", "velocity_unit_rad_s"]

REQUIRED = {0x1017: "producer heartbeat time", 0x1400: "RPDO1 communication", 0x1401: "RPDO2 communication",
            0x1600: "RPDO1 mapping", 0x1601: "RPDO2 mapping", 0x1800: "TPDO1 communication",
            0x1801: "TPDO2 communication", 0x1A00: "TPDO1 mapping", 0x1A01: "TPDO2 mapping",
            0x6040: "controlword", 0x6041: "statusword", 0x6060: "modes of operation",
            0x6061: "modes of operation display", 0x6064: "position actual value",
            0x606C: "velocity actual value", 0x60FF: "target velocity"}


# --------------------------------------------------------------------------- resolved model
@dataclass
class DriveModel:
    """An EDS joined with its description: what gearbench reads and writes, in which unit."""

    eds: str
    od: canopen.ObjectDictionary
    description: DriveDescription | None
    vendor_id: int | None = None
    product_code: int | None = None
    device_type: int | None = None
    supported_modes: tuple[int, ...] | None = None      # None: read 0x6502 at start-up
    counts_per_rev: ObjRef | None = None                 # 0x608F (ratio) or an object holding inc/rev
    # no object reports the resolution: the datasheet's increments/rev, or "profile" (the profile's
    # counts_per_rev is used as given; nothing on the drive can confirm it)
    counts_per_rev_fixed: int | str | None = None
    velocity_unit: object = None                         # ObjRef (read at start-up), int code, "inc/s"
    velocity_set: int | None = None                      # 0x60A9 value gearbench writes before reading
    velocity_allowed: tuple[int, ...] = ()
    current: ObjRef | None = None
    current_unit: str = ""
    current_scale: float = 1.0
    rated_current: ObjRef | None = None
    rated_current_unit: str = ""
    rated_current_scale: float = 1.0
    current_limit: ObjRef | None = None
    current_limit_unit: str = ""
    current_limit_scale: float = 1.0
    torque_relation: str | None = None
    torque_mode: int | None = None                       # a described (manufacturer) current mode
    torque_setpoint: ObjRef = ObjRef(0x6071)             # 0x6071, or the described current setpoint
    torque_unit: str = "permille_rated"                  # of torque_setpoint
    torque_scale: float = 1.0
    speed_limit: ObjRef | None = None
    sync_echo: ObjRef | None = None
    ramps: dict = field(default_factory=dict)            # "acceleration"/"deceleration"/"torque_slope" -> ObjRef
    expect: dict = field(default_factory=dict)           # ObjRef -> value the drive must read back
    problems: list[Problem] = field(default_factory=list)
    lookup: Lookup = field(default_factory=Lookup)       # where the description was looked for, how it matched

    @property
    def name(self) -> str:
        if self.description is not None:
            return self.description.model
        info = self.od.device_information
        return " ".join(str(x) for x in (info.vendor_name, info.product_name) if x) or Path(self.eds).name

    @property
    def has_1019(self) -> bool:
        return 0x1019 in self.od

    def var(self, ref: ObjRef) -> ODVariable | None:
        if ref.index not in self.od:
            return None
        obj = self.od[ref.index]
        if isinstance(obj, ODVariable):
            return obj if ref.subindex == 0 else None
        return obj.subindices.get(ref.subindex) if isinstance(obj, (ODRecord, ODArray)) else None

    def label(self, ref: ObjRef | str) -> str:
        """An object in hex with its EDS name: 0x30D1:02 'Current actual value'."""
        if isinstance(ref, str):
            try:
                ref = ObjRef.parse(ref, "")
            except DriveError:
                return ref
        obj = self.od[ref.index] if ref.index in self.od else None
        v = obj if isinstance(obj, (ODRecord, ODArray)) and ref.subindex == 0 else self.var(ref)
        return f"{ref} '{v.name}'" if v is not None and v.name else str(ref)

    def bits(self, ref: ObjRef) -> int:
        v = self.var(ref)
        return DATA_TYPES[v.data_type][0] if v is not None and v.data_type in DATA_TYPES else 0

    def fmt(self, ref: ObjRef) -> str:
        return DATA_TYPES[self.var(ref).data_type][1]

    def mappable(self, ref: ObjRef) -> bool:
        v = self.var(ref)
        return v is not None and bool(v.pdo_mappable) and self.bits(ref) > 0

    @property
    def exponent_writable(self) -> bool:
        """0x60C2:02 (interpolation period exponent) can be written."""
        v = self.var(ObjRef(0x60C2, 2))
        return v is not None and "w" in (v.access_type or "")

    def exponent_default(self) -> int:
        """0x60C2:02 as the EDS gives it (an entry without a default reads 0 on the drive gearbench emulates)."""
        v = self.var(ObjRef(0x60C2, 2))
        value = v.default if v is not None and v.default is not None else 0
        return value - 256 if value > 127 else value

    @property
    def mode_by_sdo(self) -> bool:
        """0x6060 is not PDO-mappable: the mode is written by SDO when a segment starts."""
        return not self.mappable(ObjRef(0x6060))

    def mode_for(self, kind: str, modes: tuple[int, ...]) -> int | None:
        if kind == "torque" and self.torque_mode is not None:
            return self.torque_mode if self.torque_mode in modes else None
        for m in (VELOCITY_MODES if kind == "velocity" else TORQUE_MODES):
            if m in modes:
                return m
        return None

    @property
    def fatal(self) -> list[Problem]:
        return [p for p in self.problems if p.fatal]

    # PDO layout gearbench uses (same in master, emulator and checks); objects the EDS lacks are never mapped
    def tpdo_entries(self, counter: bool) -> list[list[ObjRef]]:
        echo = [self.sync_echo] if counter and self.sync_echo is not None else []
        return [[ObjRef(0x6041), ObjRef(0x6064)] + echo,
                [ObjRef(0x606C)] + ([self.current] if self.current else []) + echo]

    def rpdo_entries(self) -> list[list[ObjRef]]:
        r1 = [ObjRef(0x6040)] + ([] if self.mode_by_sdo else [ObjRef(0x6060)])
        r2 = [ref for ref in (ObjRef(0x60FF), self.torque_setpoint) if self.var(ref) is not None]
        return [r1, r2]


def _standard(od, ref: ObjRef) -> bool:
    idx = ref.index
    return idx in od and (ref.subindex == 0 or isinstance(od[idx], (ODRecord, ODArray))
                          and ref.subindex in od[idx].subindices)


def eds_identity(od) -> tuple[int | None, int | None]:
    info = od.device_information
    vendor, product = info.vendor_number, info.product_number
    if 0x1018 in od:
        rec = od[0x1018]
        subs = getattr(rec, "subindices", {})
        vendor = subs[1].default if 1 in subs and subs[1].default is not None else vendor
        product = subs[2].default if 2 in subs and subs[2].default is not None else product
    return vendor, product


def import_eds(path: str, node_id: int = 1) -> canopen.ObjectDictionary:
    if not Path(path).is_file():
        raise DriveError(f"{path}: EDS/DCF file not found; put the EDS your drive's vendor ships "
                         f"(unchanged) there, or fix the motor's 'drive:' path in the profile")
    try:
        return canopen.import_od(path, node_id)
    except Exception as exc:   # configparser/ValueError/KeyError: all mean a malformed file
        raise DriveError(f"{path}: malformed EDS ({type(exc).__name__}: {exc}); "
                         f"check it with a CANopen EDS editor") from exc


def find_description(eds: str, od, descriptions=None, dirs=None) -> DriveDescription | None:
    vendor, product = eds_identity(od)
    return _find(eds, vendor, product, dirs, descriptions).description


# --------------------------------------------------------------------------- resolve
class _Ctx:
    """What the resolve steps share: the model, its description and the problem list."""

    def __init__(self, m: DriveModel):
        self.m, self.od, self.desc = m, m.od, m.description
        self.where = Path(m.eds).name
        self.dpath = Path(self.desc.path).name if self.desc else None

    def fix(self, key: str) -> str:
        if self.desc:
            return f"state {key} in {self.desc.where(key.split(' ')[0])}"
        return (f"describe {key} in a drive description for this model (`gearbench describe-drive "
                f"{self.where}` drafts one; put it in the station's drivers/)")

    def problem(self, obj, text, fix, fatal=True) -> None:
        self.m.problems.append(Problem(self.where, self.m.label(obj) if isinstance(obj, (ObjRef, str)) else str(obj),
                                       text, fix, fatal))

    def fact(self, section, key, default=None):
        return self.desc.fact(section, key, default) if self.desc else default


def resolve(eds: str, node_id: int = 1, descriptions=None, od=None, profile_dir=None) -> DriveModel:
    """Join ``eds`` with its description (if any) and list every problem."""
    od = od if od is not None else import_eds(eds, node_id)
    vendor, product = eds_identity(od)
    dirs = None if descriptions is not None else description_dirs(eds, profile_dir)
    lookup = _find(eds, vendor, product, dirs, descriptions)
    m = DriveModel(eds=eds, od=od, description=lookup.description, lookup=lookup)
    c = _Ctx(m)
    for text in lookup.broken:
        m.problems.append(Problem(text, "", "", "", True))   # already "file:line: key: what; fix"
    for step in (_resolve_identity, _resolve_modes, _resolve_position, _resolve_velocity, _resolve_current,
                 _resolve_torque, _resolve_extras, _check_pdos):
        step(c)
    return m


def _resolve_identity(c: _Ctx) -> None:
    m, od, d = c.m, c.od, c.desc
    m.vendor_id, m.product_code = eds_identity(od)
    if d is not None and d.why is None and "file name" in m.lookup.matched_by and \
            not d.match_by_identity(m.vendor_id, m.product_code) and (m.vendor_id or m.product_code):
        want = ("vendor id " + (f"0x{d.vendor_id:08X}" if d.vendor_id is not None else "any")
                + (" + product code " + "/".join(f"0x{p:08X}" for p in d.product_codes) if d.product_codes else ""))
        c.problem("0x1018", f"{d.path} matched by file name only, but the EDS says vendor id "
                  f"0x{m.vendor_id or 0:08X} + product code 0x{m.product_code or 0:08X}, the description {want}",
                  f"use the description of this drive, add its product code to match.product_codes, or say "
                  f"why it applies in match.why ({d.where('match')})")
    for key in ("vendor_id", "product_code", "device_type"):
        if c.fact("identity", key) is not None:
            setattr(m, key, c.fact("identity", key))
    if m.device_type is None and 0x1000 in od:
        m.device_type = od[0x1000].default
    if 0x1000 not in od:
        c.problem("0x1000", "device type missing", "not a CANopen device description")
    elif m.device_type is not None and m.device_type & 0xFFFF != 402:
        c.problem("0x1000", f"device type 0x{m.device_type:08X} is not CiA 402 (low 16 bits must be 0x0192)",
                  "use the EDS of a CiA 402 servo drive")
    for index, name in REQUIRED.items():
        if index not in od:
            c.problem(f"0x{index:04X}", f"{name} missing", "gearbench needs it to drive a CiA 402 servo")


def _resolve_modes(c: _Ctx) -> None:
    m, od = c.m, c.od
    described = c.fact("supported_modes", "modes")
    eds_modes = modes_from_bits(od[0x6502].default) if 0x6502 in od and od[0x6502].default is not None else None
    if described is not None:
        m.supported_modes = tuple(described)
        standard = {x for x in described if x in MODE_BIT}
        if eds_modes is not None and standard != set(eds_modes) and not c.fact("supported_modes", "why"):
            c.problem("0x6502", f"{c.desc.where('supported_modes.modes')} says modes {sorted(standard)} but the "
                      f"EDS's 0x6502 default says {sorted(eds_modes)}",
                      "remove supported_modes (the EDS decides), or say why the EDS is wrong in supported_modes.why")
    elif eds_modes is not None:
        m.supported_modes = eds_modes
    elif 0x6502 not in od:
        c.problem("0x6502", "supported drive modes missing", c.fix("supported_modes.modes"))
    m.torque_mode = c.fact("torque", "mode")
    if m.torque_mode is not None and m.supported_modes is not None and m.torque_mode not in m.supported_modes:
        m.supported_modes = tuple(m.supported_modes) + (m.torque_mode,)   # a manufacturer mode has no 0x6502 bit
    if m.supported_modes is not None:
        shown = ", ".join(f"{x} {mode_name(x)}" for x in m.supported_modes) or "none"
        if m.mode_for("velocity", m.supported_modes) is None:
            c.problem("0x6502", f"no velocity mode gearbench can use (3 or 9); the drive supports: {shown}",
                      "this drive cannot turn the bench motors at a commanded speed")
        if m.mode_for("torque", m.supported_modes) is None:
            c.problem("0x6502", f"no torque mode (4 or 10, or a described current mode); the drive supports: "
                      f"{shown}", "a drive that cannot brake cannot be the output motor (it may still drive "
                      "the input motor)", fatal=False)


def _resolve_position(c: _Ctx) -> None:
    m, od = c.m, c.od
    cpr = c.fact("position", "counts_per_rev")
    if isinstance(cpr, ObjRef):
        m.counts_per_rev = cpr
    elif cpr is not None:        # a datasheet value or "profile": no object holds the resolution
        m.counts_per_rev_fixed = cpr
    elif 0x608F in od:
        m.counts_per_rev = ObjRef(0x608F)
    else:
        c.problem("0x608F", "no encoder resolution: position units per revolution unknown",
                  c.fix("position.counts_per_rev (the object holding increments per revolution)"))
    for ref, value in (c.fact("position", "expect") or {}).items():
        m.expect[ObjRef.parse(ref, f"{c.dpath}: position.expect")] = value
    if c.desc is None or c.fact("position", "expect") is None:
        for index in (0x6091, 0x6092):    # position factor group: must be 1:1 for positions in increments
            if index in od:
                m.expect[ObjRef(index, 1)] = ("equal", ObjRef(index, 2))
    if m.counts_per_rev is not None and m.counts_per_rev.index != 0x608F and not _standard(od, m.counts_per_rev):
        c.problem(m.counts_per_rev, "encoder resolution object named by the description is not in the EDS",
                  f"fix {c.desc.where('position.counts_per_rev')}")


def _resolve_velocity(c: _Ctx) -> None:
    m, od = c.m, c.od
    unit = c.fact("velocity", "unit")
    if unit is None and 0x60A9 in od:
        unit = ObjRef(0x60A9)
    if unit is None:
        c.problem("0x606C", "velocity unit unknown: no 0x60A9 SI unit velocity in the EDS"
                  + (" (a factor group converts to the vendor's internal unit, which the EDS does not name)"
                     if 0x6094 in od or 0x6096 in od else ""), c.fix("velocity.unit"))
    elif isinstance(unit, ObjRef) and not _standard(od, unit):
        c.problem(unit, "velocity unit object missing from the EDS", f"fix {c.desc.where('velocity.unit')}")
    m.velocity_unit = unit
    m.velocity_set = c.fact("velocity", "set")
    m.velocity_allowed = tuple(c.fact("velocity", "allowed") or ())
    if isinstance(unit, ObjRef) and _standard(od, unit) and m.velocity_set is None:
        code = m.var(unit).default if m.var(unit) is not None else None
        if code is not None and velocity_unit_rad_s(code) is None:
            c.problem(unit, f"velocity unit {describe_velocity_code(code)} is not rotary (rev or rad per s/min)",
                      "gearbench drives rotary motors; set 0x60A9 to an rpm or rad/s unit")


def _described_current(c: _Ctx, section: str, default: ObjRef | None, default_unit: str):
    ref = c.fact(section, "object")
    if ref is not None:
        return ref, c.fact(section, "unit"), float(c.fact(section, "scale", 1.0))
    if default is not None and default.index in c.od:
        return default, default_unit, 1.0
    return None, "", 1.0


def _resolve_current(c: _Ctx) -> None:
    m = c.m
    m.current, m.current_unit, m.current_scale = _described_current(c, "current", ObjRef(0x6078), "permille_rated")
    if m.current is None:
        c.problem("0x6078", "no current actual value", c.fix("current.object and current.unit"))
    m.rated_current, m.rated_current_unit, m.rated_current_scale = \
        _described_current(c, "rated_current", ObjRef(0x6075), "mA")
    if m.rated_current is None:
        c.problem("0x6075", "no motor rated current", c.fix("rated_current.object and rated_current.unit"))
    m.current_limit, m.current_limit_unit, m.current_limit_scale = \
        _described_current(c, "current_limit", ObjRef(0x6073), "permille_rated")
    if m.current_limit is None:
        c.problem("0x6073", "no current limit object: gearbench cannot set the profile's current_limit_a",
                  c.fix("current_limit.object and current_limit.unit") + ", or set the limit in the drive", fatal=False)
    for label, ref, section in (("current", m.current, "current"), ("rated current", m.rated_current, "rated_current"),
                                ("current limit", m.current_limit, "current_limit")):
        if ref is not None and m.var(ref) is None:
            c.problem(ref, f"{label} object named by the description is not in the EDS",
                      f"fix {c.desc.where(section + '.object') if c.desc else 'the description'}")


def _resolve_torque(c: _Ctx) -> None:
    m, od = c.m, c.od
    m.torque_relation = c.fact("torque", "relation")
    setpoint = c.fact("torque", "setpoint")
    if setpoint is not None:     # a current setpoint at a (vendor) object, in its unit
        m.torque_setpoint, m.torque_unit = setpoint, c.fact("torque", "unit")
        m.torque_scale = float(c.fact("torque", "scale", 1.0))
        m.torque_relation = "current"
        v = m.var(setpoint)
        if v is None:
            c.problem(setpoint, "current setpoint named by the description is not in the EDS",
                      f"fix {c.desc.where('torque.setpoint')}")
        elif "w" not in v.access_type:
            c.problem(setpoint, f"current setpoint '{v.name}' is not writable", f"fix {c.desc.where('torque.setpoint')}")
        return
    if m.torque_mode is not None and m.torque_mode < 0:
        c.problem(f"mode {m.torque_mode}", "a manufacturer current mode needs its setpoint object",
                  f"state torque.setpoint and torque.unit in {c.desc.where('torque')}")
    if 0x6071 not in od:
        c.problem("0x6071", "no target torque", "a drive without it (or a described current setpoint) cannot "
                  "brake: it cannot be the output motor", fatal=False)
    elif m.torque_relation is None:
        c.problem("0x6071", "how target torque (per-mille of rated torque 0x6076) relates to motor current is "
                  "not stated", c.fix("torque.relation") + "; until then this drive cannot be the output motor",
                  fatal=False)


def _resolve_extras(c: _Ctx) -> None:
    m, od = c.m, c.od
    sl = c.fact("speed_limit", "object")
    m.speed_limit = sl if sl is not None else (ObjRef(0x607F) if 0x607F in od else None)
    for key, default in (("acceleration", 0x6083), ("deceleration", 0x6084), ("torque_slope", 0x6087)):
        ref = c.fact("ramps", key)
        ref = ref if ref is not None else (ObjRef(default) if default in od else None)
        if ref is not None:
            m.ramps[key] = ref
    echo = c.fact("sync_counter_echo", "object")
    if echo is not None:
        m.sync_echo = echo
        v = m.var(echo)
        if v is None or not v.pdo_mappable:
            c.problem(echo, "SYNC counter echo named by the description is not a mappable object in the EDS",
                      f"fix {c.desc.where('sync_counter_echo.object')}")


def _check_pdos(c: _Ctx) -> None:
    """Mappable objects, 8 bytes per PDO, writable mappings (PDO layout of ``DriveModel``)."""
    m, od = c.m, c.od
    if 0x6060 in od and m.mode_by_sdo and "w" not in (m.var(ObjRef(0x6060)).access_type or ""):
        c.problem("0x6060", "modes of operation is neither PDO-mappable nor writable", "gearbench cannot set a mode")
    for kind, mapping, lists, direction in (("TPDO", 0x1A00, m.tpdo_entries(True), "transmit"),
                                            ("RPDO", 0x1600, m.rpdo_entries(), "receive")):
        for n, entries in enumerate(lists):
            if mapping + n not in od:
                continue
            subs = getattr(od[mapping + n], "subindices", {})
            if 0 not in subs or "w" not in subs[0].access_type:
                c.problem(f"0x{mapping + n:04X}", f"{kind}{n + 1} mapping is not writable", "gearbench maps its "
                          "own PDOs; a drive with fixed mappings needs a description of them (not supported yet)")
            slots = len([s for s in subs if s > 0])
            if slots and slots < len(entries):
                c.problem(f"0x{mapping + n:04X}", f"{kind}{n + 1} holds {slots} objects, gearbench maps "
                          f"{len(entries)}", "this drive's PDOs are too small for gearbench's layout")
            total = 0
            for ref in entries:
                v = m.var(ref)
                if v is None:
                    continue   # missing objects are reported above
                total += m.bits(ref)
                if not v.pdo_mappable:
                    c.problem(ref, f"not PDO-mappable but gearbench samples it every SYNC ({kind}{n + 1})",
                              "a drive that cannot map it cannot be sampled; describe another object")
                elif not m.bits(ref):
                    c.problem(ref, f"data type 0x{v.data_type:04X} cannot be mapped by gearbench",
                              "use an 8/16/32-bit integer object")
                if direction == "receive" and "w" not in v.access_type:
                    c.problem(ref, "not writable", "gearbench writes it by RPDO")
            if total > 64:
                c.problem(f"0x{mapping + n:04X}", f"{kind}{n + 1} would carry {total} bits: more than 8 bytes",
                          "a classic CAN frame holds 64 bits; the drive's objects are too wide")


def role_problems(m: DriveModel, kinds: set[str], motor: str) -> list[Problem]:
    """Fatal problems of using ``m`` for ``kinds`` of control ('velocity', 'torque') on ``motor``."""
    where, out = Path(m.eds).name, []
    if "torque" in kinds:
        why = []
        if m.supported_modes is not None and m.mode_for("torque", m.supported_modes) is None:
            why.append(("0x6502", "the drive has no torque mode (4 profile torque, 10 cyclic sync torque or a "
                                  "described current mode)"))
        if m.var(m.torque_setpoint) is None:
            why.append((str(m.torque_setpoint), "the drive has no target torque object"))
        elif m.torque_relation is None:
            why.append((m.label(m.torque_setpoint), "the relation of target torque to motor current is not stated"))
        for obj, text in why:
            out.append(Problem(where, obj, f"motor '{motor}' must brake in torque (current) control but {text}",
                               "a drive that cannot brake cannot be the output motor; use a torque-capable drive "
                               "or describe its current mode (torque.mode/setpoint/unit) in drivers/"))
    return out


def resolve_or_raise(eds: str, node_id: int = 1, kinds: set[str] = frozenset(), motor: str = "",
                     profile_dir=None) -> DriveModel:
    """The model, or DriveError listing every fatal problem of this EDS (for this role)."""
    m = resolve(eds, node_id, profile_dir=profile_dir)
    m.problems += role_problems(m, set(kinds), motor)
    if m.fatal:
        raise DriveError(f"{eds}: gearbench cannot drive this {m.name}:\n  " +
                         "\n  ".join(str(p) for p in m.fatal))
    return m


# --------------------------------------------------------------------------- units from values
def current_a_per_unit(unit: str, rated_current_a: float | None, scale: float = 1.0) -> float:
    """A per count of a current in ``unit`` (mA, A, per-mille of the rated current), times ``scale``."""
    if unit == "mA":
        return 1e-3 * scale
    if unit == "A":
        return 1.0 * scale
    if rated_current_a is None:
        raise DriveError("a per-mille current needs the rated current")
    return rated_current_a / 1000.0 * scale


def unit_objects(m: DriveModel) -> list[ObjRef]:
    """Objects whose values fix the axis units (read at start-up, served by the emulator)."""
    refs = []
    if m.counts_per_rev is not None:
        refs += [ObjRef(0x608F, 1), ObjRef(0x608F, 2)] if m.counts_per_rev.index == 0x608F else [m.counts_per_rev]
    if isinstance(m.velocity_unit, ObjRef):
        refs.append(m.velocity_unit)
    if m.rated_current is not None:
        refs.append(m.rated_current)
    return refs


def axis_units(m: DriveModel, values: dict[ObjRef, int], where: str, profile_counts_per_rev: float | None = None):
    """``AxisUnits`` from the values of ``unit_objects(m)``; DriveError when one is unusable.
    ``profile_counts_per_rev`` is the resolution used for a drive described with
    ``counts_per_rev: profile`` (no object reports it)."""
    from .scaling import AxisUnits

    if m.counts_per_rev_fixed == "profile":
        if not profile_counts_per_rev:
            raise DriveError(f"{where}: encoder resolution comes from the profile's counts_per_rev, which is not set")
        cpr = profile_counts_per_rev
    elif m.counts_per_rev_fixed is not None:
        cpr = m.counts_per_rev_fixed
    elif m.counts_per_rev is None:
        raise DriveError(f"{where}: encoder resolution unknown")
    elif m.counts_per_rev.index == 0x608F:
        inc, revs = values[ObjRef(0x608F, 1)], values[ObjRef(0x608F, 2)]
        if not inc or not revs:
            raise DriveError(f"{where}: 0x608F encoder resolution reads {inc}/{revs}; configure the encoder")
        cpr = inc / revs
    else:
        cpr = values[m.counts_per_rev]
        if not cpr:
            raise DriveError(f"{where}: {m.counts_per_rev} encoder resolution reads 0; configure the encoder")
    if isinstance(m.velocity_unit, ObjRef):
        code = values[m.velocity_unit]
        per = velocity_unit_rad_s(code)
        if per is None:
            raise DriveError(f"{where}: velocity unit {m.velocity_unit} = {describe_velocity_code(code)} is not "
                             f"a rotary unit gearbench knows; set it to rpm (0x00B44700)")
    elif isinstance(m.velocity_unit, int):
        per = velocity_unit_rad_s(m.velocity_unit)
    elif m.velocity_unit == "inc/s":
        per = 2 * math.pi / cpr
    else:
        raise DriveError(f"{where}: velocity unit unknown")
    rated_a = None
    if m.rated_current is not None:
        rated_raw = values[m.rated_current]
        if not rated_raw:
            raise DriveError(f"{where}: rated current {m.rated_current} reads 0; enter the motor data in the drive")
        rated_a = rated_raw * current_a_per_unit(m.rated_current_unit, None, m.rated_current_scale) \
            if m.rated_current_unit != "permille_rated" else None
    if m.current is None or rated_a is None:
        raise DriveError(f"{where}: current object or rated current unknown")
    if m.torque_relation == "permille_rated_current":
        torque = rated_a / 1000.0
    elif m.torque_relation == "current":     # a described current setpoint, in its own unit
        torque = current_a_per_unit(m.torque_unit, rated_a, m.torque_scale)
    else:
        torque = None
    return AxisUnits(counts_per_rev=cpr, velocity_rad_s_per_unit=per,
                     current_a_per_unit=current_a_per_unit(m.current_unit, rated_a, m.current_scale),
                     torque_a_per_unit=torque, current_bits=m.bits(m.current) or 16,
                     torque_bits=m.bits(m.torque_setpoint) or 16, velocity_bits=m.bits(ObjRef(0x60FF)) or 32), rated_a
