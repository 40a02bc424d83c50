"""Drafting a drive description from a vendor's EDS (``gearbench describe-drive``).

``draft(model, probed)`` writes the YAML a bench engineer completes: what the EDS
says (identity, the modes 0x6502 offers, the CiA 402 objects present), candidate
objects for current actual / rated current / current limit / current setpoint /
encoder resolution found by their EDS names with type, access and mappability,
what is missing, and every fact the EDS cannot give as ``TODO`` with where to find
it (manual chapter, object to read on the live drive). Values read from a live drive
(``probed``: ObjRef -> value or error text) are filled in and cited as the source
``probe``. A draft with a TODO left does not validate: every TODO is a refusal
naming the key, so nothing is guessed silently. Pure: the caller reads the files
and the bus.
"""
from __future__ import annotations

import re
from pathlib import Path

from canopen.objectdictionary import ODArray, ODRecord, ODVariable

from .description import DriveModel
from .objects import DATA_TYPES, MODE_BIT, ObjRef, describe_velocity_code, mode_name, modes_from_bits

TYPE_NAMES = {0x1: "BOOLEAN", 0x2: "INTEGER8", 0x3: "INTEGER16", 0x4: "INTEGER32", 0x5: "UNSIGNED8",
              0x6: "UNSIGNED16", 0x7: "UNSIGNED32"}
EXCLUDE = r"kp|ki|kd|gain|offset|threshold|window|time|filter|homing|stepper|stand-by|standby|integr|i2t|calib"
CANDIDATES = {   # what to look for among the EDS's objects, by name
    "current": r"current.*actual|actual.*current|motor current|current value|\biq\b",
    "rated_current": r"nominal current|rated current|continuous current",
    "current_limit": r"current limit|peak current|max.*current|output current",
    "setpoint": r"current.*(setting|setpoint|target|reference|command)|(target|reference|setpoint|demand).*current"
                r"|external.*reference|online reference",
    "encoder": r"encoder.*(resolution|counts|increments)|counts per rev|sensor resolution|increments per",
    "velocity_unit": r"velocity.*(unit|factor|notation|dimension)|si unit velocity",
}
# objects the probe reads when the EDS has them (unit facts, identity, modes)
PROBE_OBJECTS = [ObjRef(0x1000), ObjRef(0x1018, 1), ObjRef(0x1018, 2), ObjRef(0x1018, 3), ObjRef(0x6502),
                 ObjRef(0x60A9), ObjRef(0x608F, 1), ObjRef(0x608F, 2), ObjRef(0x6075), ObjRef(0x6076),
                 ObjRef(0x6073), ObjRef(0x6072), ObjRef(0x6080), ObjRef(0x607F), ObjRef(0x60C2, 1),
                 ObjRef(0x60C2, 2), ObjRef(0x6091, 1), ObjRef(0x6091, 2), ObjRef(0x6092, 1), ObjRef(0x6092, 2)]


def _variables(od):
    for obj in od.values():
        if isinstance(obj, ODVariable):
            yield ObjRef(obj.index, 0), obj
        elif isinstance(obj, (ODRecord, ODArray)):
            for sub, v in obj.subindices.items():
                if sub:
                    yield ObjRef(obj.index, sub), v


def candidates(m: DriveModel, kind: str) -> list[ObjRef]:
    """Objects whose EDS name suggests ``kind`` (numeric, not a tuning or timing parameter)."""
    out = []
    for ref, v in _variables(m.od):
        name = (v.name or "").lower()
        parent = m.od[ref.index].name.lower() if ref.subindex else ""
        text = f"{parent} {name}"
        if v.data_type in DATA_TYPES and re.search(CANDIDATES[kind], text) and not re.search(EXCLUDE, text):
            out.append(ref)
    return out


def rank_current_actual(m: DriveModel, refs: list[ObjRef]) -> list[ObjRef]:
    """Current-actual candidates, the likeliest first: by the object's own name, an 'actual
    current' before the q-axis (torque-forming) current before the rest, and a d-axis /
    flux / phase current last. Nanotec's 0x2039 'Motor Currents' lists Id first: proposing
    0x2039:01 would sample the field-forming current, zero in a running servo."""
    def rank(ref: ObjRef) -> int:
        name = (m.var(ref).name or "").lower()
        if re.search(r"current.*actual|actual.*current", name):
            return 0
        if re.search(r"\biq\b|i_q\b|torque", name):
            return 1
        if re.search(r"\bid\b|i_d\b|flux|field|phase|\bi_?[ab]\b", name):
            return 3
        return 2
    return sorted(refs, key=rank)      # stable: EDS order within a rank


def object_line(m: DriveModel, ref: ObjRef, probed: dict | None = None) -> str:
    v = m.var(ref)
    if v is None:
        return f"{ref}: not in the EDS"
    bits = [TYPE_NAMES.get(v.data_type, f"type 0x{v.data_type:04X}"), v.access_type,
            "PDO-mappable" if v.pdo_mappable else "not mappable"]
    if v.default is not None:
        bits.append(f"EDS default {v.default}")
    if probed and ref in probed:
        bits.append(f"drive reads {probed[ref]}")
    return f"{m.label(ref)}: {', '.join(bits)}"


def _q(ref: ObjRef) -> str:
    return f'"{ref}"'


def draft(m: DriveModel, probed: dict | None = None, probe_source: str = "") -> str:
    """The description YAML for ``m`` (an EDS resolved without a description): one section
    per fact gearbench needs, each either read from the EDS (or the live drive, ``probed``)
    or left as a TODO saying where to find it."""
    probed = probed or {}
    L = _header(m, probed, probe_source)
    for section in (_modes, _position, _velocity, _current_actual, _ratings, _torque):
        L += [""] + section(m, probed)
    if 0x6080 in m.od:     # no EDS default (ZeroErr): only the drive knows it, and the start-up checks it
        L += ["", f"# max motor speed: {object_line(m, ObjRef(0x6080), probed)} - the start-up refuses one below the "
                  "profile's speed_limit_rad_s"]
    return "\n".join(L + [""] + _missing(m)) + "\n"


def _header(m: DriveModel, probed: dict, probe_source: str) -> list[str]:
    """Identity (0x1018, vendor id and product code) and the sources the facts cite."""
    od = m.od
    info = od.device_information
    name = Path(m.eds).name
    vendor = probed.get(ObjRef(0x1018, 1), m.vendor_id)
    product = probed.get(ObjRef(0x1018, 2), m.product_code)
    L = [f"# Drive description drafted by `gearbench describe-drive {name}`"
         + (" --probe" if probed else "") + ".",
         "# Every TODO is a fact the EDS cannot give: replace it with the value and name its source",
         "# (a key of 'sources:'), then check with `gearbench validate PROFILE`. A TODO left is refused.",
         "family: cia402",
         f'model: "{" ".join(str(x) for x in (info.vendor_name, info.product_name) if x) or name}"',
         "match:"]
    L.append(f"  vendor_id: 0x{vendor:08X}" if isinstance(vendor, int) else
             "  # vendor_id: TODO (no vendor id in the EDS; read 0x1018:01 on the drive: describe-drive --probe)")
    if isinstance(product, int):
        L.append(f"  product_codes: [0x{product:08X}]")
    L.append(f'  file_names: ["{name}"]')
    created = " ".join(str(x) for x in (getattr(info, "product_name", None),) if x)
    L += ["sources:", f'  eds: "{name} as the vendor ships it{(" (" + created + ")") if created else ""}"',
          '  manual: "TODO: the drive\'s CANopen/firmware manual: title, document number, version"']
    if probed:
        L.append(f'  probe: "{probe_source}"')
    dtype = probed.get(ObjRef(0x1000), od[0x1000].default if 0x1000 in od else None)
    if isinstance(dtype, int) and (0x1000 not in od or od[0x1000].default is None):
        L += ["identity:", f"  device_type: 0x{dtype:08X}", "  source: probe 0x1000"]
    return L


def _modes(m: DriveModel, probed: dict) -> list[str]:
    """0x6502's modes and the ones gearbench would use (or a TODO)."""
    od = m.od
    L: list[str] = []
    bits = probed.get(ObjRef(0x6502), od[0x6502].default if 0x6502 in od else None)
    if isinstance(bits, int):
        modes = modes_from_bits(bits)
        L.append(f"# modes: 0x6502 = 0x{bits:08X} -> " + ", ".join(f"{x} {mode_name(x)}" for x in modes)
                 + (f"; manufacturer bits 0x{bits >> 16:04X} (see the manual)" if bits >> 16 else ""))
        vel, tq = m.mode_for("velocity", modes), m.mode_for("torque", modes)
        L.append(f"#   gearbench would use velocity mode {vel or 'NONE'}, torque mode {tq or 'NONE'}")
        if 0x6502 in od and od[0x6502].default is None and ObjRef(0x6502) in probed:
            L += ["supported_modes:", f"  modes: {list(modes)}", "  source: probe 0x6502"]
    else:
        L += ["# modes: no 0x6502 default in the EDS: read it on the drive (--probe) or from the manual",
              "supported_modes:", "  modes: TODO   # e.g. [3, 9, 10]; manual chapter 'operating modes'",
              "  source: manual"]
    if 0x6060 in od and m.mode_by_sdo:
        L.append("# 0x6060 modes of operation is not PDO-mappable: gearbench writes it by SDO per segment")
    return L


def _position(m: DriveModel, probed: dict) -> list[str]:
    """Encoder resolution: 0x608F, else candidates by name."""
    od = m.od
    L: list[str] = []
    if 0x608F in od:
        L.append("# encoder resolution: 0x608F (CiA 402) - no entry needed; "
                 + "; ".join(object_line(m, r, probed) for r in (ObjRef(0x608F, 1), ObjRef(0x608F, 2))))
    else:
        cands = candidates(m, "encoder")
        L += ["# encoder resolution: no 0x608F. " + ("Candidates by name:" if cands else
              "No candidate object: give the encoder's fixed increments per revolution (an integer, from its "
              "datasheet) or 'profile' (the profile's counts_per_rev, which no object can confirm)")] + \
             [f"#   {object_line(m, r, probed)}" for r in cands] + \
             ["position:", f"  counts_per_rev: {_q(cands[0]) if cands else 'TODO'}   # TODO confirm: increments "
                           "per MOTOR revolution (manual, object dictionary chapter)",
              "  source: TODO   # e.g. eds [" + (f"{cands[0].index:04X}" if cands else "....") + "]; manual"]
    return L


def _velocity(m: DriveModel, probed: dict) -> list[str]:
    """Velocity unit: 0x60A9, else a TODO."""
    od = m.od
    L: list[str] = []
    if 0x60A9 in od:
        code = probed.get(ObjRef(0x60A9), od[0x60A9].default)
        L.append("# velocity unit: 0x60A9 (read at start-up) - no entry needed"
                 + (f"; {describe_velocity_code(code)}" if isinstance(code, int) else ""))
    else:
        L += ["# velocity unit: no 0x60A9 SI unit velocity"
              + ("; a factor group (0x6094/0x6096) converts to a vendor unit" if 0x6094 in od or 0x6096 in od else ""),
              "velocity:", "  unit: TODO   # inc/s (encoder increments per second), a 0x60A9 code (0x00B44700 = rpm) "
                           "or the object holding it; manual 'units' / 'factor group' chapter",
              "  source: manual"]
    return L


def _current_actual(m: DriveModel, probed: dict) -> list[str]:
    """Current actual: a mappable 0x6078, else candidates by name."""
    od = m.od
    L: list[str] = []
    if 0x6078 in od and m.mappable(ObjRef(0x6078)):
        L += [f"# current actual: {object_line(m, ObjRef(0x6078), probed)} (per-mille of rated current 0x6075, "
              "CiA 402) - no entry needed",
              "#   TODO check in the manual whether it is the q-axis current, peak or rms (scale: 0.7071 for "
              "peak against an rms datasheet)"]
    else:
        cands = rank_current_actual(m, [r for r in candidates(m, "current") if m.mappable(r)]
                                    or candidates(m, "current"))
        L += ["# current actual: no mappable 0x6078. Candidates by name:"] + \
             [f"#   {object_line(m, r, probed)}" for r in cands] + \
             ["current:", f"  object: {_q(cands[0]) if cands else 'TODO'}   # TODO confirm in the manual",
              "  unit: TODO   # mA | A | permille_rated; and peak or rms? (manual: object dictionary)",
              "  # scale: 0.7071   # only if the drive reports peak and the datasheet Kt is per rms",
              "  source: TODO   # e.g. eds [....]; manual"]
    return L


def _ratings(m: DriveModel, probed: dict) -> list[str]:
    """Rated current 0x6075 and current limit 0x6073, else candidates."""
    od = m.od
    L: list[str] = []
    for section, std, kind, unit_hint in (("rated_current", 0x6075, "rated_current", "mA (CiA 402)"),
                                          ("current_limit", 0x6073, "current_limit", "per-mille of rated (CiA 402)")):
        if L:
            L.append("")
        if std in od:
            L.append(f"# {section.replace('_', ' ')}: {object_line(m, ObjRef(std), probed)}, {unit_hint} - "
                     f"no entry needed")
            continue
        cands = candidates(m, kind)
        L += [f"# {section.replace('_', ' ')}: no 0x{std:04X}. Candidates by name:"] + \
             [f"#   {object_line(m, r, probed)}" for r in cands] + \
             [f"{section}:", f"  object: {_q(cands[0]) if cands else 'TODO'}   # TODO confirm",
              "  unit: TODO   # mA | A | permille_rated (manual)", "  source: TODO"]
    return L


def _torque(m: DriveModel, probed: dict) -> list[str]:
    """Target torque 0x6071 in a torque mode, else a manufacturer current mode to describe."""
    od = m.od
    L: list[str] = []
    bits = probed.get(ObjRef(0x6502), od[0x6502].default if 0x6502 in od else None)
    tq_modes = [x for x in modes_from_bits(bits)] if isinstance(bits, int) else []
    if 0x6071 in od and any(x in (4, 10) for x in tq_modes):
        if 0x6076 not in od:      # nothing to probe: the manual says what 0x6071 = 1000 is
            rated = "no rated torque 0x6076 in the EDS (per mille of what? manual: object 0x6071 'target torque')"
        elif ObjRef(0x6076) in probed:
            rated = f"rated torque 0x6076 reads {probed[ObjRef(0x6076)]}"
        else:
            rated = "rated torque 0x6076 (read it: --probe)"
        L += [f"# target torque: {object_line(m, ObjRef(0x6071), probed)}; {rated}",
              "torque:", "  relation: TODO   # permille_rated_current if 0x6071 = 1000 commands the rated CURRENT "
                         "(manual: 'target torque', 'torque constant'); else describe a current mode below",
              "  source: manual"]
    else:
        cands = [r for r in candidates(m, "setpoint") if m.var(r) is not None and "w" in m.var(r).access_type]
        L += ["# torque: " + ("no 0x6071" if 0x6071 not in od else "0x6071 but no torque mode (4/10) in 0x6502")
              + "; a manufacturer current mode may exist (manual: 'operating modes'; manufacturer bits of 0x6502)."
              " Setpoint candidates by name:"] + [f"#   {object_line(m, r, probed)}" for r in cands] + \
             ["torque:", "  mode: TODO   # the 0x6060 number of the current mode (negative: manufacturer)",
              f"  setpoint: {_q(cands[0]) if cands else 'TODO'}   # TODO confirm", "  unit: TODO   # mA | A",
              "  source: manual"]
    return L


def _missing(m: DriveModel) -> list[str]:
    """The CiA 301/402 objects gearbench needs that the EDS lacks; SYNC counter; 0x60C2."""
    od = m.od
    missing = [f"0x{i:04X}" for i in (0x1017, 0x6040, 0x6041, 0x6060, 0x6061, 0x6064, 0x606C, 0x60FF) if i not in od]
    return ["# missing CiA 301/402 objects gearbench needs: " + (", ".join(missing) if missing else "none"),
            f"# 0x1019 SYNC counter: {'present' if 0x1019 in od else 'absent (SYNC without counter byte)'}; "
            f"0x60C2 interpolation period: {_interpolation(m)}"]


def _interpolation(m: DriveModel) -> str:
    """0x60C2:02 as the start-up meets it (ZeroErr's has no default: it is not 0, it is unknown)."""
    if 0x60C2 not in m.od:
        return "absent"
    v = m.var(ObjRef(0x60C2, 2))
    text = f"exponent 0x60C2:02 {'writable' if m.exponent_writable else 'read-only'}"
    if v is not None and v.default is not None:
        return f"{text} (EDS default {m.exponent_default()})"
    return f"{text} (no EDS default" + (": gearbench writes it)" if m.exponent_writable else ")")


__all__ = ["PROBE_OBJECTS", "candidates", "draft", "object_line", "rank_current_actual", "MODE_BIT"]
