"""CiA 402 drive descriptions: what a vendor's EDS cannot say, as data in ``drivers/*.yaml``.

A vendor ships an EDS/DCF; gearbench reads it as shipped. What the EDS cannot say
- which object carries the current and in what unit, where the rated current and
the encoder resolution live, the velocity unit when there is no 0x60A9, how the
target torque 0x6071 relates to motor current, whether the drive echoes the SYNC
counter - is written once per drive model in a small YAML file (``family: cia402``)
with the source of every fact. It is matched to an EDS by vendor id / product code
(0x1018) or by file name. See ``drivers/maxon-epos4.yaml`` for the format.

``resolve(eds)`` joins the EDS and its description into a ``DriveModel``: every
object gearbench will read or write, each unit, the supported modes, the PDO
limits, and *every* problem found (never only the first). Pure apart from reading
the two files.
"""
from __future__ import annotations

import fnmatch
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import canopen
import yaml
from canopen.objectdictionary import ODArray, ODRecord, ODVariable

from ..errors import DriveError



def _drivers_dirs(eds: str | None = None) -> list[Path]:
    """Where descriptions are looked for: beside the EDS (a station's drivers/), then shipped."""
    from .shipped import shipped_dir
    dirs = [Path(eds).resolve().parent] if eds else []
    return list(dict.fromkeys(dirs + [shipped_dir("drivers").resolve()]))

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


def modes_from_bits(bits: int) -> tuple[int, ...]:
    return tuple(m for m, b in MODE_BIT.items() if bits >> b & 1)


def modes_to_bits(modes) -> int:
    return sum(1 << MODE_BIT[m] for m in modes)


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


@dataclass(frozen=True, order=True)
class ObjRef:
    index: int
    subindex: int = 0

    def __str__(self) -> str:
        return f"0x{self.index:04X}" + (f":{self.subindex:02X}" if self.subindex else "")

    @classmethod
    def parse(cls, value, where: str) -> "ObjRef":
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
        return f"{self.file}: {self.obj}: {self.problem}; {self.fix}"


# --------------------------------------------------------------------------- descriptions
@dataclass(frozen=True)
class DriveDescription:
    """One ``drivers/*.yaml`` with ``family: cia402`` (validated on load)."""

    path: str
    model: str
    vendor_id: int | None
    product_codes: tuple[int, ...]
    file_names: tuple[str, ...]
    sources: dict
    facts: dict            # section -> validated mapping (see FACT_KEYS)
    quirks: tuple[str, ...] = ()

    def fact(self, section: str, key: str, default=None):
        return (self.facts.get(section) or {}).get(key, default)

    def matches(self, eds_path: str, vendor_id: int | None, product_code: int | None) -> bool:
        name = Path(eds_path).name.lower()
        if any(fnmatch.fnmatch(name, pat.lower()) for pat in self.file_names):
            return True
        if self.vendor_id is not None and vendor_id == self.vendor_id:
            return not self.product_codes or product_code in self.product_codes
        return False


FACT_KEYS = {
    "identity": ("vendor_id", "product_code", "device_type", "source"),
    "supported_modes": ("modes", "source"),
    "position": ("counts_per_rev", "expect", "source"),
    "velocity": ("unit", "object", "set", "allowed", "source"),
    "current": ("object", "unit", "source"),
    "rated_current": ("object", "unit", "source"),
    "current_limit": ("object", "unit", "source"),
    "torque": ("relation", "source"),
    "speed_limit": ("object", "source"),
    "sync_counter_echo": ("object", "source"),
    "ramps": ("acceleration", "deceleration", "torque_slope", "source"),
}
TOP_KEYS = ("family", "model", "match", "sources", "quirks") + tuple(FACT_KEYS)


def _int(value, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise DriveError(f"{where}: must be a whole number, e.g. 0x000000FB (got {value!r})")
    return value


def load_description(path: str | Path) -> DriveDescription:
    """Read and validate one drive description; DriveError names file and key."""
    shown = str(path)
    try:
        doc = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise DriveError(f"{shown}: cannot read the drive description ({exc})") from None
    if not isinstance(doc, dict) or doc.get("family") != "cia402":
        raise DriveError(f"{shown}: not a CiA 402 drive description (needs 'family: cia402')")
    for key in doc:
        if key not in TOP_KEYS:
            raise DriveError(f"{shown}: {key}: unknown key; known: {', '.join(TOP_KEYS)}")
    match = doc.get("match") or {}
    if not isinstance(match, dict) or not set(match) <= {"vendor_id", "product_codes", "file_names"}:
        raise DriveError(f"{shown}: match: give vendor_id, product_codes and/or file_names")
    vendor = None if match.get("vendor_id") is None else _int(match["vendor_id"], f"{shown}: match.vendor_id")
    codes = tuple(_int(c, f"{shown}: match.product_codes") for c in match.get("product_codes") or ())
    names = tuple(str(n) for n in match.get("file_names") or ())
    if vendor is None and not names:
        raise DriveError(f"{shown}: match: needs vendor_id or file_names, or no EDS will ever match it")
    facts = {}
    for section, keys in FACT_KEYS.items():
        value = doc.get(section)
        if value is None:
            continue
        if not isinstance(value, dict):
            raise DriveError(f"{shown}: {section}: must be a mapping with {', '.join(keys)}")
        for key in value:
            if key not in keys:
                raise DriveError(f"{shown}: {section}.{key}: unknown key; known: {', '.join(keys)}")
        if "source" not in value:
            raise DriveError(f"{shown}: {section}: says no 'source'; record where this fact comes from")
        for key in ("object", "counts_per_rev", "acceleration", "deceleration", "torque_slope"):
            if key in value and isinstance(value[key], (str, int)) and str(value[key]).startswith("0x"):
                value[key] = ObjRef.parse(value[key], f"{shown}: {section}.{key}")
            elif key in value and isinstance(value[key], int) and key not in ("counts_per_rev",):
                value[key] = ObjRef.parse(value[key], f"{shown}: {section}.{key}")
        if section in ("current", "rated_current", "current_limit") and value.get("unit") not in CURRENT_UNITS:
            raise DriveError(f"{shown}: {section}.unit: must be one of {', '.join(CURRENT_UNITS)}")
        if section == "torque" and value.get("relation") not in TORQUE_RELATIONS:
            raise DriveError(f"{shown}: torque.relation: must be one of {', '.join(TORQUE_RELATIONS)}")
        if section == "supported_modes":
            modes = value.get("modes")
            if not isinstance(modes, list) or any(m not in MODE_BIT for m in modes):
                raise DriveError(f"{shown}: supported_modes.modes: a list of CiA 402 mode numbers, e.g. [3, 9, 10]")
        if section == "velocity":
            unit = value.get("unit")
            if isinstance(unit, str) and unit.startswith("0x") and len(unit) == 6:
                value["unit"] = ObjRef.parse(unit, f"{shown}: velocity.unit")
            elif isinstance(unit, int) and velocity_unit_rad_s(unit) is None:
                raise DriveError(f"{shown}: velocity.unit: 0x{unit:08X} is not a rotary 0x60A9 unit code")
            elif unit not in ("inc/s",) and not isinstance(unit, (int, ObjRef)):
                raise DriveError(f"{shown}: velocity.unit: 'inc/s', a 0x60A9 unit code (0x00B44700 = rpm) "
                                 f"or the object holding it (0x60A9)")
        facts[section] = value
    if not doc.get("sources"):
        raise DriveError(f"{shown}: sources: list where the facts come from (manual, EDS, measurement)")
    return DriveDescription(path=shown, model=str(doc.get("model") or Path(path).stem), vendor_id=vendor,
                            product_codes=codes, file_names=names, sources=dict(doc["sources"]),
                            facts=facts, quirks=tuple(str(q) for q in doc.get("quirks") or ()))


def load_descriptions(*folders: str | Path) -> list[DriveDescription]:
    out = []
    for p in [p for f in (folders or _drivers_dirs()) for p in sorted(Path(f).glob("*.yaml"))]:
        try:
            head = yaml.safe_load(p.read_text())
        except (OSError, yaml.YAMLError):
            continue   # not ours to judge here: register maps are checked by their own loader
        if isinstance(head, dict) and head.get("family") == "cia402":
            out.append(load_description(p))
    return out


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
    velocity_unit: object = None                         # ObjRef (read at start-up), int code, "inc/s"
    velocity_set: int | None = None                      # 0x60A9 value gearbench writes before reading
    velocity_allowed: tuple[int, ...] = ()
    current: ObjRef | None = None
    current_unit: str = ""
    rated_current: ObjRef | None = None
    rated_current_unit: str = ""
    current_limit: ObjRef | None = None
    current_limit_unit: str = ""
    torque_relation: str | None = None
    speed_limit: ObjRef | None = None
    sync_echo: ObjRef | None = None
    ramps: dict = field(default_factory=dict)            # "acceleration"/"deceleration"/"torque_slope" -> ObjRef
    expect: dict = field(default_factory=dict)           # ObjRef -> value the drive must read back
    problems: list[Problem] = field(default_factory=list)

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

    def bits(self, ref: ObjRef) -> int:
        v = self.var(ref)
        return DATA_TYPES[v.data_type][0] if v is not None and v.data_type in DATA_TYPES else 0

    def fmt(self, ref: ObjRef) -> str:
        return DATA_TYPES[self.var(ref).data_type][1]

    def mode_for(self, kind: str, modes: tuple[int, ...]) -> int | None:
        for m in (VELOCITY_MODES if kind == "velocity" else TORQUE_MODES):
            if m in modes:
                return m
        return None

    @property
    def fatal(self) -> list[Problem]:
        return [p for p in self.problems if p.fatal]

    # PDO layout gearbench uses (same in master and checks)
    def tpdo_entries(self, counter: bool) -> list[list[ObjRef]]:
        echo = [self.sync_echo] if counter and self.sync_echo is not None else []
        return [[ObjRef(0x6041), ObjRef(0x6064)] + echo,
                [ObjRef(0x606C)] + ([self.current] if self.current else []) + echo]

    def rpdo_entries(self) -> list[list[ObjRef]]:
        return [[ObjRef(0x6040), ObjRef(0x6060)], [ObjRef(0x60FF), ObjRef(0x6071)]]


def _standard(od, ref: ObjRef) -> bool:
    idx = ref.index
    return idx in od and (ref.subindex == 0 or isinstance(od[idx], (ODRecord, ODArray))
                          and ref.subindex in od[idx].subindices)


def _identity(od) -> tuple[int | None, int | None]:
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


def find_description(eds: str, od, descriptions=None) -> DriveDescription | None:
    vendor, product = _identity(od)
    for d in descriptions if descriptions is not None else load_descriptions(*_drivers_dirs(eds)):
        if d.matches(eds, vendor, product):
            return d
    return None


REQUIRED = {0x1017: "producer heartbeat time", 0x1400: "RPDO1 communication", 0x1401: "RPDO2 communication",
            0x1600: "RPDO1 mapping", 0x1601: "RPDO2 mapping", 0x1800: "TPDO1 communication",
            0x1801: "TPDO2 communication", 0x1A00: "TPDO1 mapping", 0x1A01: "TPDO2 mapping",
            0x6040: "controlword", 0x6041: "statusword", 0x6060: "modes of operation",
            0x6061: "modes of operation display", 0x6064: "position actual value",
            0x606C: "velocity actual value", 0x60FF: "target velocity"}


def resolve(eds: str, node_id: int = 1, descriptions=None, od=None) -> DriveModel:
    """Join ``eds`` with its description (if any) and list every problem."""
    od = od if od is not None else import_eds(eds, node_id)
    desc = find_description(eds, od, descriptions)
    m = DriveModel(eds=eds, od=od, description=desc)
    where = Path(eds).name
    dpath = Path(desc.path).name if desc else None
    fix_desc = (f"state it in {dpath}" if desc else
                "write a drive description for this model in drivers/ (see drivers/maxon-epos4.yaml)")

    def problem(obj, text, fix, fatal=True):
        m.problems.append(Problem(where, str(obj), text, fix, fatal))

    def fact(section, key, default=None):
        return desc.fact(section, key, default) if desc else default

    m.vendor_id, m.product_code = _identity(od)
    if fact("identity", "vendor_id") is not None:
        m.vendor_id = fact("identity", "vendor_id")
    if fact("identity", "product_code") is not None:
        m.product_code = fact("identity", "product_code")
    m.device_type = od[0x1000].default if 0x1000 in od else None
    if fact("identity", "device_type") is not None:
        m.device_type = fact("identity", "device_type")
    if 0x1000 not in od:
        problem("0x1000", "device type missing", "not a CANopen device description")
    elif m.device_type is not None and m.device_type & 0xFFFF != 402:
        problem("0x1000", f"device type 0x{m.device_type:08X} is not CiA 402 (low 16 bits must be 0x0192)",
                "use the EDS of a CiA 402 servo drive")
    for index, name in REQUIRED.items():
        if index not in od:
            problem(f"0x{index:04X}", f"{name} missing", "gearbench needs it to drive a CiA 402 servo")

    # ---- modes
    if fact("supported_modes", "modes") is not None:
        m.supported_modes = tuple(fact("supported_modes", "modes"))
    elif 0x6502 in od and od[0x6502].default is not None:
        m.supported_modes = modes_from_bits(od[0x6502].default)
    elif 0x6502 not in od:
        problem("0x6502", "supported drive modes missing", f"{fix_desc} (supported_modes)")
    if m.supported_modes is not None:
        shown = ", ".join(f"{x} {MODE_NAMES[x]}" for x in m.supported_modes) or "none"
        if m.mode_for("velocity", m.supported_modes) is None:
            problem("0x6502", f"no velocity mode gearbench can use (3 or 9); the drive supports: {shown}",
                    "this drive cannot turn the bench motors at a commanded speed")
        if m.mode_for("torque", m.supported_modes) is None:
            m.problems.append(Problem(where, "0x6502", f"no torque mode (4 or 10); the drive supports: {shown}",
                                      "a drive that cannot brake cannot be the output motor (it may still "
                                      "drive the input motor)", fatal=False))

    # ---- position units
    cpr = fact("position", "counts_per_rev")
    if isinstance(cpr, ObjRef):
        m.counts_per_rev = cpr
    elif 0x608F in od:
        m.counts_per_rev = ObjRef(0x608F)
    else:
        problem("0x608F", "no encoder resolution: position units per revolution unknown",
                f"{fix_desc} (position.counts_per_rev: the object holding increments per revolution)")
    for ref, value in (fact("position", "expect") or {}).items():
        m.expect[ObjRef.parse(ref, f"{dpath}: position.expect")] = value
    if desc is None or fact("position", "expect") is None:
        for index in (0x6091, 0x6092):    # position factor group: must be 1:1 for positions in increments
            if index in od:
                m.expect[ObjRef(index, 1)] = ("equal", ObjRef(index, 2))
    if m.counts_per_rev is not None and m.counts_per_rev.index != 0x608F and not _standard(od, m.counts_per_rev):
        problem(m.counts_per_rev, "encoder resolution object named by the description is not in the EDS",
                "fix position.counts_per_rev in the description")

    # ---- velocity units
    unit = fact("velocity", "unit")
    if unit is None and 0x60A9 in od:
        unit = ObjRef(0x60A9)
    if unit is None:
        problem("0x606C", "velocity unit unknown: no 0x60A9 SI unit velocity in the EDS"
                + (" (a factor group converts to the vendor's internal unit, which the EDS does not name)"
                   if 0x6094 in od or 0x6096 in od else ""),
                f"{fix_desc} (velocity.unit)")
    elif isinstance(unit, ObjRef) and not _standard(od, unit):
        problem(unit, "velocity unit object missing from the EDS", "fix velocity.unit in the description")
    m.velocity_unit = unit
    m.velocity_set = fact("velocity", "set")
    m.velocity_allowed = tuple(fact("velocity", "allowed") or ())
    if isinstance(unit, ObjRef) and m.velocity_set is None and od[unit.index].default is not None:
        code = od[unit.index].default
        if velocity_unit_rad_s(code) is None:
            problem(unit, f"velocity unit {describe_velocity_code(code)} is not rotary (rev or rad per s/min)",
                    "gearbench drives rotary motors; set 0x60A9 to an rpm or rad/s unit")

    # ---- current
    cur = fact("current", "object")
    if cur is not None:
        m.current, m.current_unit = cur, fact("current", "unit")
    elif 0x6078 in od:
        m.current, m.current_unit = ObjRef(0x6078), "permille_rated"
    else:
        problem("0x6078", "no current actual value", f"{fix_desc} (current: object and unit)")
    rated = fact("rated_current", "object")
    if rated is not None:
        m.rated_current, m.rated_current_unit = rated, fact("rated_current", "unit")
    elif 0x6075 in od:
        m.rated_current, m.rated_current_unit = ObjRef(0x6075), "mA"
    else:
        problem("0x6075", "no motor rated current", f"{fix_desc} (rated_current: object and unit)")
    lim = fact("current_limit", "object")
    if lim is not None:
        m.current_limit, m.current_limit_unit = lim, fact("current_limit", "unit")
    elif 0x6073 in od:
        m.current_limit, m.current_limit_unit = ObjRef(0x6073), "permille_rated"
    else:
        problem("0x6073", "no current limit object: gearbench cannot set the profile's current_limit_a",
                f"{fix_desc} (current_limit), or set the limit in the drive", fatal=False)
    for label, ref in (("current", m.current), ("rated current", m.rated_current),
                       ("current limit", m.current_limit)):
        if ref is not None and m.var(ref) is None:
            problem(ref, f"{label} object named by the description is not in the EDS",
                    "fix the description")

    # ---- torque setpoint
    if 0x6071 not in od:
        m.problems.append(Problem(where, "0x6071", "no target torque", "a drive without it cannot brake: it "
                                  "cannot be the output motor", fatal=False))
    m.torque_relation = fact("torque", "relation")
    if m.torque_relation is None and 0x6071 in od:
        m.problems.append(Problem(where, "0x6071", "how target torque (per-mille of rated torque 0x6076) "
                                  "relates to motor current is not stated", f"{fix_desc} (torque.relation); "
                                  "until then this drive cannot be the output motor", fatal=False))

    # ---- limits, ramps, echo
    sl = fact("speed_limit", "object")
    m.speed_limit = sl if sl is not None else (ObjRef(0x607F) if 0x607F in od else None)
    for key, default in (("acceleration", 0x6083), ("deceleration", 0x6084), ("torque_slope", 0x6087)):
        ref = fact("ramps", key)
        ref = ref if ref is not None else (ObjRef(default) if default in od else None)
        if ref is not None:
            m.ramps[key] = ref
    echo = fact("sync_counter_echo", "object")
    if echo is not None:
        m.sync_echo = echo
        v = m.var(echo)
        if v is None or not v.pdo_mappable:
            problem(echo, "SYNC counter echo named by the description is not a mappable object in the EDS",
                    "fix sync_counter_echo in the description")

    # ---- PDO mapping: mappable objects, 8 bytes per PDO, writable mapping
    _check_pdos(m, problem)
    return m


def _check_pdos(m: DriveModel, problem) -> None:
    od = m.od
    for kind, comm, mapping, lists, direction in (("TPDO", 0x1800, 0x1A00, m.tpdo_entries(True), "transmit"),
                                                  ("RPDO", 0x1400, 0x1600, m.rpdo_entries(), "receive")):
        for n, entries in enumerate(lists):
            if mapping + n not in od:
                continue
            rec = od[mapping + n]
            subs = getattr(rec, "subindices", {})
            if 0 not in subs or "w" not in subs[0].access_type:
                problem(f"0x{mapping + n:04X}", f"{kind}{n + 1} mapping is not writable", "gearbench maps its "
                        "own PDOs; a drive with fixed mappings needs a description of them (not supported yet)")
            slots = len([s for s in subs if s > 0])
            if slots and slots < len(entries):
                problem(f"0x{mapping + n:04X}", f"{kind}{n + 1} holds {slots} objects, gearbench maps "
                        f"{len(entries)}", "this drive's PDOs are too small for gearbench's layout")
            total = 0
            for ref in entries:
                v = m.var(ref)
                if v is None:
                    continue   # missing objects are reported above
                total += m.bits(ref)
                if not v.pdo_mappable:
                    problem(ref, f"'{v.name}' is not PDO-mappable but gearbench maps it into {kind}{n + 1}",
                            "gearbench samples it every SYNC; a drive that cannot map it cannot be sampled")
                if direction == "receive" and "w" not in v.access_type:
                    problem(ref, f"'{v.name}' is not writable", "gearbench writes it by RPDO")
            if total > 64:
                problem(f"0x{mapping + n:04X}", f"{kind}{n + 1} would carry {total} bits: more than 8 bytes",
                        "a classic CAN frame holds 64 bits; the drive's objects are too wide")


def role_problems(m: DriveModel, kinds: set[str], motor: str) -> list[Problem]:
    """Fatal problems of using ``m`` for ``kinds`` of control ('velocity', 'torque') on ``motor``."""
    where, out = Path(m.eds).name, []
    if "torque" in kinds:
        why = []
        if m.supported_modes is not None and m.mode_for("torque", m.supported_modes) is None:
            why.append(("0x6502", "the drive has no torque mode (4 profile torque or 10 cyclic sync torque)"))
        if 0x6071 not in m.od:
            why.append(("0x6071", "the drive has no target torque object"))
        elif m.torque_relation is None:
            why.append(("0x6071", "the relation of target torque to motor current is not stated"))
        for obj, text in why:
            out.append(Problem(where, obj, f"motor '{motor}' must brake in torque (current) control but {text}", "a drive that cannot brake cannot be the output motor; "
                               "use a torque-capable drive or describe it in drivers/"))
    return out


def resolve_or_raise(eds: str, node_id: int = 1, kinds: set[str] = frozenset(), motor: str = "") -> DriveModel:
    """The model, or DriveError listing every fatal problem of this EDS (for this role)."""
    m = resolve(eds, node_id)
    m.problems += role_problems(m, set(kinds), motor)
    if m.fatal:
        raise DriveError(f"{eds}: gearbench cannot drive this {m.name}:\n  " +
                         "\n  ".join(str(p) for p in m.fatal))
    return m


# --------------------------------------------------------------------------- units from values
def current_a_per_unit(unit: str, rated_current_a: float | None) -> float:
    if unit == "mA":
        return 1e-3
    if unit == "A":
        return 1.0
    if rated_current_a is None:
        raise DriveError("a per-mille current needs the rated current")
    return rated_current_a / 1000.0


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


def axis_units(m: DriveModel, values: dict[ObjRef, int], where: str):
    """``AxisUnits`` from the values of ``unit_objects(m)``; DriveError when one is unusable."""
    from .scaling import AxisUnits

    if m.counts_per_rev is None:
        raise DriveError(f"{where}: encoder resolution unknown")
    if m.counts_per_rev.index == 0x608F:
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
        rated_a = rated_raw * current_a_per_unit(m.rated_current_unit, None) \
            if m.rated_current_unit != "permille_rated" else None
    if m.current is None or rated_a is None:
        raise DriveError(f"{where}: current object or rated current unknown")
    torque = rated_a / 1000.0 if m.torque_relation == "permille_rated_current" else None
    return AxisUnits(counts_per_rev=cpr, velocity_rad_s_per_unit=per,
                     current_a_per_unit=current_a_per_unit(m.current_unit, rated_a),
                     torque_a_per_unit=torque, current_bits=m.bits(m.current) or 16,
                     torque_bits=m.bits(ObjRef(0x6071)) or 16, velocity_bits=m.bits(ObjRef(0x60FF)) or 32), rated_a
