"""Drive description files (``drivers/*.yaml``, ``family: cia402``): loading, checking, finding.

A description holds what a vendor's EDS cannot say (see ``docs/drive-descriptions.md``).
Loading checks the whole file and reports *every* problem once, each with
``file:line``, the key, what is wrong and a did-you-mean for a misspelt key or
source name. Every fact section names its ``source``, which must be one of the
keys of ``sources:`` (a source that is not defined is refused).

Descriptions are looked for in the same order as drive files (``gearbench.drives.shipped``):
the profile's folder, the station's ``drivers/``, beside the EDS, then the shipped
ones; the first folder holding a matching description wins, and inside a folder a
match by vendor id + product code beats one by file name.
"""
from __future__ import annotations

import difflib
import fnmatch
import re
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from ..errors import DriveError
from .shipped import shipped_dir
from .objects import CURRENT_UNITS, MODE_BIT, TORQUE_RELATIONS, ObjRef, velocity_unit_rad_s


class DescriptionError(DriveError):
    """A description file with problems; ``problems`` holds one line each."""

    def __init__(self, problems: list[str]):
        super().__init__("\n  ".join(problems))
        self.problems = problems


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
    why: str | None = None                        # match.why: an identity mismatch explained
    lines: dict = field(default_factory=dict, compare=False)   # "section.key" -> line number

    def fact(self, section: str, key: str, default=None):
        return (self.facts.get(section) or {}).get(key, default)

    def where(self, key: str) -> str:
        """``file:line`` of a key ("torque.mode"), or of its section, for messages."""
        line = self.lines.get(key) or self.lines.get(key.split(".")[0])
        return f"{self.path}:{line}" if line else self.path

    def match_by_identity(self, vendor_id: int | None, product_code: int | None) -> bool:
        return self.vendor_id is not None and vendor_id == self.vendor_id and \
            (not self.product_codes or product_code in self.product_codes)

    def match_by_name(self, eds_path: str) -> str | None:
        name = Path(eds_path).name.lower()
        return next((pat for pat in self.file_names if fnmatch.fnmatch(name, pat.lower())), None)

    def matches(self, eds_path: str, vendor_id: int | None, product_code: int | None) -> bool:
        return self.match_by_identity(vendor_id, product_code) or self.match_by_name(eds_path) is not None


FACT_KEYS = {
    "identity": ("vendor_id", "product_code", "device_type", "source"),
    "supported_modes": ("modes", "why", "source"),
    "position": ("counts_per_rev", "expect", "source"),
    "velocity": ("unit", "object", "set", "allowed", "source"),
    "current": ("object", "unit", "scale", "source"),
    "rated_current": ("object", "unit", "scale", "source"),
    "current_limit": ("object", "unit", "scale", "source"),
    "torque": ("relation", "mode", "setpoint", "unit", "scale", "source"),
    "speed_limit": ("object", "source"),
    "sync_counter_echo": ("object", "source"),
    "ramps": ("acceleration", "deceleration", "torque_slope", "source"),
}
TOP_KEYS = ("family", "model", "match", "sources", "quirks") + tuple(FACT_KEYS)
MATCH_KEYS = ("vendor_id", "product_codes", "file_names", "why")
OBJECT_KEYS = ("object", "counts_per_rev", "acceleration", "deceleration", "torque_slope", "setpoint")


def did_you_mean(word: str, known) -> str:
    close = difflib.get_close_matches(str(word), list(known), n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ""


def _key_lines(node, prefix: str = "", out: dict | None = None) -> dict:
    """{"section.key": line} of a composed YAML mapping (1-based lines)."""
    out = {} if out is None else out
    if isinstance(node, yaml.MappingNode):
        for k, v in node.value:
            key = f"{prefix}{k.value}"
            out.setdefault(key, k.start_mark.line + 1)
            if prefix.count(".") < 1:
                _key_lines(v, key + ".", out)
    return out


def source_names(text: str) -> list[str]:
    """Source keys a ``source:`` text cites: the first word of each ';'/','-separated part,
    parenthesised remarks ignored ("fw 0x3000; eds [3000sub5] (default 0)" -> fw, eds)."""
    bare = re.sub(r"\([^)]*\)|\[[^\]]*\]", "", str(text))
    return [m.group(1) for part in re.split(r"[;,]", bare) if (m := re.match(r"\s*([A-Za-z_][\w-]*)", part))]


class _Checker:
    def __init__(self, path: str, lines: dict):
        self.path, self.lines, self.problems = path, lines, []

    def fail(self, key: str, text: str) -> None:
        line = self.lines.get(key) or self.lines.get(key.split(".")[0])
        self.problems.append(f"{self.path}{':' + str(line) if line else ''}: {key}: {text}")

    def whole(self, key: str, value):
        if isinstance(value, bool) or not isinstance(value, int):
            self.fail(key, f"must be a whole number, e.g. 0x000000FB (got {value!r})")
            return None
        return value

    def obj(self, key: str, value):
        try:
            return ObjRef.parse(value, key)
        except DriveError:
            self.fail(key, f"'{value}' is not an object like 0x6078 or 0x30D1:02")
            return None


def load_description(path: str | Path) -> DriveDescription:
    """Read and check one drive description; DescriptionError lists every problem with file:line."""
    shown = str(path)
    try:
        text = Path(path).read_text()
        doc, root = yaml.safe_load(text), yaml.compose(text)
    except (OSError, yaml.YAMLError) as exc:
        raise DescriptionError([f"{shown}: cannot read the drive description ({exc})"]) from None
    if not isinstance(doc, dict) or doc.get("family") != "cia402":
        raise DescriptionError([f"{shown}: not a CiA 402 drive description (needs 'family: cia402')"])
    c = _Checker(shown, _key_lines(root))
    for key in doc:
        if key not in TOP_KEYS:
            c.fail(str(key), f"unknown key{did_you_mean(key, TOP_KEYS)}; known: {', '.join(TOP_KEYS)}")
    for key, value in _walk(doc):
        if isinstance(value, str) and value.strip().upper().startswith("TODO"):
            c.fail(key, f"still a TODO ({value.strip()[:70]}): fill in the fact and its source")
    sources = doc.get("sources")
    if not isinstance(sources, dict) or not sources:
        c.fail("sources", "list where the facts come from as name: text (manual, EDS, measurement)")
        sources = {}
    match = doc.get("match") or {}
    vendor, codes, names, why = None, (), (), None
    if not isinstance(match, dict):
        c.fail("match", "give vendor_id, product_codes and/or file_names")
        match = {}
    for key in match:
        if key not in MATCH_KEYS:
            c.fail(f"match.{key}", f"unknown key{did_you_mean(key, MATCH_KEYS)}; known: {', '.join(MATCH_KEYS)}")
    if match.get("vendor_id") is not None:
        vendor = c.whole("match.vendor_id", match["vendor_id"])
    codes = tuple(x for x in (c.whole("match.product_codes", p) for p in match.get("product_codes") or ())
                  if x is not None)
    names = tuple(str(n) for n in match.get("file_names") or ())
    why = match.get("why")
    if vendor is None and not names:
        c.fail("match", "needs vendor_id or file_names, or no EDS will ever match it")
    facts = {}
    for section, keys in FACT_KEYS.items():
        value = doc.get(section)
        if value is None:
            continue
        if not isinstance(value, dict):
            c.fail(section, f"must be a mapping with {', '.join(keys)}")
            continue
        value = dict(value)
        for key in value:
            if key not in keys:
                c.fail(f"{section}.{key}", f"unknown key{did_you_mean(key, keys)}; known: {', '.join(keys)}")
        _check_source(c, section, value.get("source"), sources)
        for key in OBJECT_KEYS:
            if key in value and not (section == "position" and key == "counts_per_rev"
                                     and not str(value[key]).startswith("0x")):
                value[key] = c.obj(f"{section}.{key}", value[key])
        _check_section(c, section, value)
        facts[section] = value
    if c.problems:
        raise DescriptionError(c.problems)
    return DriveDescription(path=shown, model=str(doc.get("model") or Path(path).stem), vendor_id=vendor,
                            product_codes=codes, file_names=names, sources=dict(sources), facts=facts,
                            quirks=tuple(str(q) for q in doc.get("quirks") or ()),
                            why=None if why is None else str(why), lines=c.lines)


def _walk(node, prefix=""):
    """(dotted key, value) of every scalar in a mapping, two levels deep (sections and their keys)."""
    if isinstance(node, dict):
        for k, v in node.items():
            key = f"{prefix}{k}"
            if isinstance(v, dict) and prefix.count(".") < 1:
                yield from _walk(v, key + ".")
            else:
                yield key, v


def _check_source(c: _Checker, section: str, text, sources: dict) -> None:
    if not text:
        c.fail(section, "says no 'source'; record where this fact comes from (a key of 'sources:')")
        return
    cited = source_names(text)
    undefined = [s for s in cited if s not in sources]
    if not cited or len(undefined) == len(cited):
        name = undefined[0] if undefined else str(text)
        c.fail(f"{section}.source", f"'{name}' is not a source defined under 'sources:'"
               f"{did_you_mean(name, sources)}; defined: {', '.join(sources) or 'none'}")


def _check_section(c: _Checker, section: str, value: dict) -> None:
    if section in ("current", "rated_current", "current_limit") and value.get("unit") not in CURRENT_UNITS:
        c.fail(f"{section}.unit", f"must be one of {', '.join(CURRENT_UNITS)}{did_you_mean(value.get('unit'), CURRENT_UNITS)}")
    if "scale" in value and (isinstance(value["scale"], bool) or not isinstance(value["scale"], (int, float))
                             or value["scale"] <= 0):
        c.fail(f"{section}.scale", f"a positive factor multiplying the unit (e.g. 0.7071 for a peak "
                                   f"current reported against an rms datasheet), got {value['scale']!r}")
    if section == "torque":
        rel = value.get("relation")
        if rel is not None and rel not in TORQUE_RELATIONS:
            c.fail("torque.relation", f"must be one of {', '.join(TORQUE_RELATIONS)}{did_you_mean(rel, TORQUE_RELATIONS)}")
        if "mode" in value and (isinstance(value["mode"], bool) or not isinstance(value["mode"], int)
                                or not -128 <= value["mode"] <= 127):
            c.fail("torque.mode", f"a 0x6060 mode number (-128..127; manufacturer modes are negative), "
                                  f"got {value['mode']!r}")
        if value.get("setpoint") is not None and value.get("unit") not in CURRENT_UNITS:
            c.fail("torque.unit", f"the setpoint's unit: one of {', '.join(CURRENT_UNITS)}")
        if rel is None and value.get("setpoint") is None:
            c.fail("torque", "give relation (how 0x6071 maps to current) or setpoint + unit (a current setpoint)")
    if section == "position" and "counts_per_rev" in value and not isinstance(value["counts_per_rev"], ObjRef):
        cpr = value["counts_per_rev"]
        if cpr != "profile" and (isinstance(cpr, bool) or not isinstance(cpr, int) or cpr <= 0):
            c.fail("position.counts_per_rev", "an object holding increments per revolution (\"0x608F\", "
                                              "\"0xIIII:SS\"), a positive integer (a fixed resolution no object "
                                              "reports, from the encoder's datasheet) or 'profile' (the profile's "
                                              f"counts_per_rev, unchecked), got {cpr!r}")
    if section == "supported_modes":
        modes = value.get("modes")
        if not isinstance(modes, list) or any(isinstance(m, bool) or not isinstance(m, int) or
                                              (m not in MODE_BIT and m >= 0) for m in modes):
            c.fail("supported_modes.modes", "a list of 0x6060 mode numbers, e.g. [3, 9, 10] "
                                            "(negative numbers: manufacturer modes)")
    if section == "velocity":
        unit = value.get("unit")
        if isinstance(unit, str) and unit.startswith("0x") and len(unit) == 6:
            value["unit"] = c.obj("velocity.unit", unit)
        elif isinstance(unit, int) and not isinstance(unit, bool) and velocity_unit_rad_s(unit) is None:
            c.fail("velocity.unit", f"0x{unit:08X} is not a rotary 0x60A9 unit code")
        elif unit != "inc/s" and not (isinstance(unit, int) and not isinstance(unit, bool)):
            c.fail("velocity.unit", "'inc/s', a 0x60A9 unit code (0x00B44700 = rpm) or the object holding it (0x60A9)")


# --------------------------------------------------------------------------- finding
def description_dirs(eds: str | None = None, profile_dir: str | Path | None = None) -> list[Path]:
    """Where descriptions are looked for, in order: the profile's folder, the station's
    drivers/ (beside the profile's folder, then the current directory's), beside the EDS,
    the shipped ones."""
    dirs: list[Path] = []
    if profile_dir is not None:
        p = Path(profile_dir).resolve()
        dirs += [p, p.parent / "drivers"]
    dirs.append(Path.cwd() / "drivers")
    if eds:
        dirs.append(Path(eds).resolve().parent)
    dirs.append(shipped_dir("drivers").resolve())
    return [d for d in dict.fromkeys(dirs)]


def _cia402_files(folder: Path) -> list[Path]:
    out = []
    for p in sorted(folder.glob("*.yaml")) if folder.is_dir() else []:
        try:
            head = yaml.safe_load(p.read_text())
        except (OSError, yaml.YAMLError):
            continue   # not ours to judge here: register maps and profiles are checked by their own loaders
        if isinstance(head, dict) and head.get("family") == "cia402":
            out.append(p)
    return out


def load_descriptions(*folders: str | Path) -> list[DriveDescription]:
    """Every description in ``folders`` (DescriptionError on the first broken one)."""
    return [load_description(p) for f in (folders or description_dirs()) for p in _cia402_files(Path(f))]


@dataclass
class Lookup:
    """What the search for an EDS's description found: the description, how it matched,
    where it looked, and broken descriptions met on the way."""

    description: DriveDescription | None = None
    matched_by: str = ""
    looked: list[str] = field(default_factory=list)
    broken: list[str] = field(default_factory=list)


def find_description(eds: str, vendor: int | None, product: int | None, dirs=None, descriptions=None) -> Lookup:
    """The first matching description, in ``dirs`` order (see ``description_dirs``)."""
    out = Lookup()
    if descriptions is not None:
        groups = [("given", list(descriptions))]
    else:
        groups = []
        for d in dirs if dirs is not None else description_dirs(eds):
            out.looked.append(str(d))
            loaded = []
            for p in _cia402_files(Path(d)):
                try:
                    loaded.append(load_description(p))
                except DescriptionError as exc:
                    out.broken += exc.problems
            groups.append((str(d), loaded))
    ident = f"vendor id 0x{vendor:08X}" if vendor is not None else "no vendor id"
    ident += f" + product code 0x{product:08X}" if product is not None else ""
    for _, descs in groups:
        for d in descs:
            if d.match_by_identity(vendor, product):
                out.description, out.matched_by = d, ident
                return out
        for d in descs:
            pattern = d.match_by_name(eds)
            if pattern is not None:
                out.description, out.matched_by = d, f"file name '{Path(eds).name}' ~ '{pattern}' ({ident} in the EDS)"
                return out
    return out
