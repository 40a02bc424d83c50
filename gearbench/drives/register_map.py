"""Modbus register maps: one YAML file in ``drivers/`` per drive model.

A map names each register (``address``, ``type``, ``scale`` in SI per count,
``unit``, ``access``), the word order of 32-bit values, the values written to the
control register (CiA 402 controlword semantics), the modes, the status-word bits
and the ``enable_sequence``. A new drive model is a new file, not new code.

Pure: loading validates and returns a frozen ``RegisterMap``; encoding/decoding
turn SI values into register words and back. Both the gearbench Modbus driver and
the emulator's Modbus front-end use this module, so they cannot disagree.
"""
from __future__ import annotations

import ast
import math
import operator
import struct
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Mapping

import yaml

from ..errors import ProfileError
from .shipped import shipped_driver

#: type name -> (struct code, number of 16-bit words)
TYPES: dict[str, tuple[str, int]] = {
    "int16": ("h", 1), "uint16": ("H", 1),
    "int32": ("i", 2), "uint32": ("I", 2),
    "float32": ("f", 2),
}
ACCESS = ("r", "w", "rw")
WORD_ORDERS = ("big", "little")
#: registers every map must declare, with the access each needs
REQUIRED: dict[str, str] = {
    "control": "w", "status": "r", "mode": "w",
    "position": "r", "velocity": "r", "current": "r", "sample_counter": "r",
    "target_velocity": "w", "target_current": "w",
}
#: registers read together in one request per sample (one instant): must be contiguous
SAMPLED = ("status", "sample_counter", "position", "velocity", "current")
CONTROL_VALUES = ("quick_stop", "disable", "fault_reset")
MODES = ("velocity", "torque")
MAX_READ_WORDS = 125     # Modbus limit for one read-holding-registers request


@dataclass(frozen=True)
class Register:
    """One named register (or 32-bit register pair)."""

    name: str
    address: int
    type: str
    scale: float        # SI units per count (1.0 for words such as control/status)
    unit: str
    access: str

    @property
    def words(self) -> int:
        return TYPES[self.type][1]

    @property
    def readable(self) -> bool:
        return "r" in self.access

    @property
    def writable(self) -> bool:
        return "w" in self.access

    @property
    def is_integer(self) -> bool:
        return self.type != "float32"


@dataclass(frozen=True)
class Write:
    """One step of a write sequence: ``value`` is a raw register value or "mode"."""

    register: str
    value: int | str


@dataclass(frozen=True)
class RegisterMap:
    """A validated register map; build it with ``load_register_map``."""

    path: str
    model: str
    word_order: str
    registers: Mapping[str, Register]
    modes: Mapping[str, int]
    control_values: Mapping[str, int]
    enable_sequence: tuple[Write, ...]
    fault_bit: int
    enabled_mask: int
    enabled_value: int
    enable_timeout_s: float
    #: drive-side ring of past samples: (first address, depth in entries), or None (no history)
    history: tuple[int, int] | None = None

    # --- layout -----------------------------------------------------------
    @property
    def entry_words(self) -> int:
        """Words per history entry: laid out like the one-instant sample block."""
        return self.span(SAMPLED)[1]

    def history_address(self, counter: int) -> int:
        """Address of the history entry that holds sample ``counter`` (``counter mod depth``)."""
        address, depth = self.history
        return address + (counter % depth) * self.entry_words

    @property
    def counter_period_s(self) -> float:
        """Seconds per sample-counter count: the drive's time base."""
        return self.registers["sample_counter"].scale

    def span(self, names=SAMPLED) -> tuple[int, int]:
        """(first address, word count) covering ``names``."""
        regs = [self.registers[n] for n in names]
        start = min(r.address for r in regs)
        return start, max(r.address + r.words for r in regs) - start

    def is_fault(self, status: int) -> bool:
        return bool(status >> self.fault_bit & 1)

    def is_enabled(self, status: int) -> bool:
        return status & self.enabled_mask == self.enabled_value

    def sequence_value(self, step: Write, mode: str) -> int:
        """Raw value of one enable-sequence write for ``mode``."""
        return self.modes[mode] if step.value == "mode" else int(step.value)

    # --- values <-> words -------------------------------------------------
    def encode_raw(self, name: str, raw: int | float, *, wrap: bool = False) -> list[int]:
        """Raw count (or float) -> register words in the map's word order.

        ``wrap`` folds integers into the register's range (free-running counters
        and positions wrap on a real drive); otherwise out of range raises ValueError.
        """
        reg = self.registers[name]
        code, nwords = TYPES[reg.type]
        if reg.is_integer:
            raw = int(raw)
            bits = 16 * nwords
            lo, hi = (0, 2**bits - 1) if code.isupper() else (-2**(bits - 1), 2**(bits - 1) - 1)
            if wrap:
                raw = (raw - lo) % 2**bits + lo
            elif not lo <= raw <= hi:
                raise ValueError(f"{raw} does not fit register '{name}' ({reg.type}, {lo}..{hi})")
        words = list(struct.unpack(f">{nwords}H", struct.pack(f">{code}", raw)))
        return words[::-1] if self.word_order == "little" else words

    def decode_raw(self, name: str, words) -> int | float:
        """Register words (map word order) -> raw count (or float)."""
        reg = self.registers[name]
        code, nwords = TYPES[reg.type]
        w = list(words[:nwords])
        if self.word_order == "little":
            w.reverse()
        return struct.unpack(f">{code}", struct.pack(f">{nwords}H", *w))[0]

    def encode(self, name: str, value_si: float, *, wrap: bool = False) -> list[int]:
        """SI value -> register words (value / scale, rounded for integer types)."""
        reg = self.registers[name]
        raw = value_si / reg.scale
        return self.encode_raw(name, round(raw) if reg.is_integer else raw, wrap=wrap)

    def decode(self, name: str, words) -> float:
        """Register words -> SI value (count x scale)."""
        return self.decode_raw(name, words) * self.registers[name].scale

    def decode_block(self, start: int, words, names=SAMPLED) -> dict[str, int | float]:
        """Raw values of ``names`` from a block of words read at ``start``."""
        out = {}
        for n in names:
            off = self.registers[n].address - start
            out[n] = self.decode_raw(n, words[off:off + self.registers[n].words])
        return out


# --- loading --------------------------------------------------------------
class _Map(dict):
    """dict that remembers the YAML line of each key (for error messages)."""

    lines: dict


class _LineLoader(yaml.SafeLoader):
    pass


def _construct_map(loader, node):
    m = _Map(loader.construct_mapping(node, deep=True))
    m.lines = {loader.construct_object(k): k.start_mark.line + 1 for k, _ in node.value}
    m.line = node.start_mark.line + 1
    return m


_LineLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_map)


def _line(m, key=None) -> str:
    if isinstance(m, _Map):
        return f":{m.lines.get(key, m.line)}" if key is not None else f":{m.line}"
    return ""


_OPS = {ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: operator.mul,
        ast.Div: operator.truediv, ast.Pow: operator.pow, ast.USub: operator.neg}


def _number(text) -> float:
    """A number or a small arithmetic expression such as ``2*pi/10000``."""
    if isinstance(text, bool):
        raise ValueError("boolean")
    if isinstance(text, (int, float)):
        return float(text)

    def ev(node):
        if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)):
            return node.value
        if isinstance(node, ast.Name) and node.id == "pi":
            return math.pi
        if isinstance(node, ast.BinOp) and type(node.op) in _OPS:
            return _OPS[type(node.op)](ev(node.left), ev(node.right))
        if isinstance(node, ast.UnaryOp) and type(node.op) in _OPS:
            return _OPS[type(node.op)](ev(node.operand))
        raise ValueError(text)

    return float(ev(ast.parse(str(text), mode="eval").body))


def resolve_description(path: str | Path) -> Path:
    """A path as given, else the same name among the shipped drive descriptions."""
    p = Path(path)
    if p.exists():
        return p
    fallback = shipped_driver(p.name)
    return fallback if fallback.exists() else p


def _read_map(path: str | Path):
    """The map file's parsed YAML (keys remember their lines) and its resolved path."""
    p = resolve_description(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise ProfileError(f"{path}: cannot read register map ({exc.strerror}); "
                           f"give a path to a YAML file in drivers/") from None
    try:
        return yaml.load(text, Loader=_LineLoader), p
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{p}:{mark.line + 1}" if mark else str(p)
        raise ProfileError(f"{where}: not valid YAML ({getattr(exc, 'problem', exc)}); "
                           f"fix the syntax") from None


def load_register_map(path: str | Path) -> RegisterMap:
    """Read and validate a register-map YAML; ProfileError names file, key and fix."""
    data, p = _read_map(path)
    return parse_register_map(data, str(p))


def check_register_map(path: str | Path) -> list[str]:
    """Every problem of a register-map file at once (``gearbench validate``), each
    naming file, line, key and fix; [] for a valid map."""
    try:
        data, p = _read_map(path)
    except ProfileError as exc:
        return [str(exc)]
    return register_map_problems(data, str(p))[1]


def parse_register_map(data, where: str = "register map") -> RegisterMap:
    """Validate an already-parsed map (``where`` names it in errors); the first problem
    is raised (the driver needs a valid map or nothing)."""
    regmap, problems = register_map_problems(data, where)
    if problems:
        raise ProfileError(problems[0])
    return regmap


def register_map_problems(data, where: str = "register map") -> tuple[RegisterMap | None, list[str]]:
    """Check a parsed map whole: register types, addresses, access, overlaps, word order,
    the contiguous sample block, the sample counter, modes, control values, the status
    word and the enable sequence. Returns the map (None if any problem) and every problem."""
    out: list[str] = []

    def bad(m, key, msg, fix):
        out.append(f"{where}{_line(m, key)}: {msg}; {fix}")
        bad.count += 1
    bad.count = 0

    if not isinstance(data, dict):
        return None, [f"{where}: top level is not a mapping; write `registers:`, `word_order:`, ... as keys"]
    word_order = data.get("word_order", "big")
    if word_order not in WORD_ORDERS:
        bad(data, "word_order", f"word_order: '{word_order}' is not a word order",
            "use 'big' (high word at the lower address) or 'little'")
    regs_in, registers = _check_registers(data, bad)
    _check_required(regs_in, registers, bad)
    _check_layout(regs_in, registers, bad)
    modes, cv, sw, fault_bit = _check_control(data, bad)
    seq = _check_enable_sequence(data, registers, bad)
    timeout = data.get("enable_timeout_s", 1.0)
    if isinstance(timeout, bool) or not isinstance(timeout, (int, float)) or timeout <= 0:
        bad(data, "enable_timeout_s", f"enable_timeout_s: '{timeout}' is not a positive number", "use e.g. 1.0")
    history = _check_history(data, registers, bad)
    if out:
        return None, out
    return RegisterMap(
        path=where, model=str(data.get("model", Path(where).stem)), word_order=word_order,
        registers=MappingProxyType(registers), modes=MappingProxyType({m: modes[m] for m in modes}),
        control_values=MappingProxyType({k: cv[k] for k in cv}), enable_sequence=tuple(seq),
        fault_bit=fault_bit, enabled_mask=int(sw.get("enabled_mask", 0x6F)),
        enabled_value=int(sw.get("enabled_value", 0x27)), enable_timeout_s=float(timeout),
        history=history), []


def _check_history(data, registers: dict[str, Register], bad) -> tuple[int, int] | None:
    """``history: {address, depth}``: a ring of ``depth`` entries (each laid out like the sample
    block) after the named registers, at least 2 deep, within the address space."""
    if "history" not in data:
        return None
    h = data["history"]
    if not isinstance(h, dict) or set(h) - {"address", "depth"}:
        bad(data, "history", "history: not a mapping of address and depth",
            "write `history: {address: 100, depth: 64}` or leave it out (a drive without history)")
        return None
    addr, depth = h.get("address"), h.get("depth")
    n = bad.count
    if isinstance(addr, bool) or not isinstance(addr, int) or not 0 <= addr <= 65535:
        bad(h, "address", f"history.address: '{addr}' is not a register address", "use a 0-based PDU address")
    if isinstance(depth, bool) or not isinstance(depth, int) or depth < 2:
        bad(h, "depth", f"history.depth: '{depth}' is not a whole number of entries >= 2",
            "give the ring's length in samples, e.g. 64")
    if bad.count > n or any(r not in registers for r in SAMPLED):
        return None
    regs = [registers[r] for r in SAMPLED]
    words = max(r.address + r.words for r in regs) - min(r.address for r in regs)
    end = addr + depth * words
    clash = next((r for r in registers.values() if r.address < end and r.address + r.words > addr), None)
    if end > 65536:
        bad(h, "depth", f"history: {depth} entries of {words} words from {addr} pass address 65535",
            "lower the depth or the address")
    elif clash is not None:
        bad(h, "address", f"history: the ring {addr}..{end - 1} overlaps registers.{clash.name} at "
            f"{clash.address}", "move the ring past the named registers")
    return (addr, depth)


def _check_registers(data, bad) -> tuple[dict, dict[str, Register]]:
    """Each register's fields (address, type, scale, access): the raw entries and the valid ones."""
    regs_in = data.get("registers")
    if not isinstance(regs_in, dict) or not regs_in:
        bad(data, "registers", "registers: missing or not a mapping",
            "add `registers:` with name: {address, type, scale, unit, access}")
        regs_in = {}
    registers: dict[str, Register] = {}
    for name, spec in regs_in.items():
        key = f"registers.{name}"
        if not isinstance(spec, dict):
            bad(regs_in, name, f"{key}: not a mapping", "write {address: N, type: int16, scale: 1, unit: '', access: r}")
            continue
        n_before = bad.count
        for field in ("address", "type"):
            if field not in spec:
                bad(spec, None, f"{key}.{field}: missing", f"add `{field}:` to register '{name}'")
        addr, rtype = spec.get("address"), spec.get("type")
        if "address" in spec and (isinstance(addr, bool) or not isinstance(addr, int) or not 0 <= addr <= 65535):
            bad(spec, "address", f"{key}.address: '{addr}' is not a register address",
                "use a 0-based PDU address 0..65535")
        if "type" in spec and rtype not in TYPES:
            bad(spec, "type", f"{key}.type: unknown type '{rtype}'", f"use one of {', '.join(TYPES)}")
        try:
            scale = _number(spec.get("scale", 1))
        except (ValueError, SyntaxError, ZeroDivisionError, TypeError):
            scale = float("nan")
        if not math.isfinite(scale) or scale == 0:
            bad(spec, "scale", f"{key}.scale: '{spec.get('scale')}' is not a non-zero number",
                "give SI units per count, e.g. 0.001 or 2*pi/10000")
        access = spec.get("access", "r")
        if access not in ACCESS:
            bad(spec, "access", f"{key}.access: '{access}' is not an access mode", "use r, w or rw")
        if bad.count == n_before:
            registers[name] = Register(str(name), addr, rtype, scale, str(spec.get("unit", "")), access)

    return regs_in, registers


def _check_required(regs_in: dict, registers: dict[str, Register], bad) -> None:
    """The registers gearbench needs, with the access it needs, and the time/watchdog units."""
    for name, need in REQUIRED.items():
        if name not in regs_in:
            bad(regs_in, None, f"registers.{name}: missing (required register)",
                f"add `{name}: {{address: N, type: ..., scale: ..., unit: ..., access: {need}}}`")
        elif name in registers and need not in registers[name].access:
            bad(regs_in[name], "access", f"registers.{name}.access: '{registers[name].access}' "
                f"but gearbench must {'read' if need == 'r' else 'write'} it", f"set access: {need} or rw")
    watchdog = registers.get("comm_timeout")
    if watchdog is not None and (not watchdog.writable or watchdog.unit != "s"):
        bad(regs_in["comm_timeout"], "access", "registers.comm_timeout: the drive's communication watchdog "
            "is written by the master in seconds", "set access: rw (or w), unit: s and scale: <s per count>")
    if "sync" in registers and not registers["sync"].writable:
        bad(regs_in["sync"], "access", "registers.sync.access: sync is written by the master", "set access: w")
    counter = registers.get("sample_counter")
    if counter is not None and (counter.scale <= 0 or counter.unit != "s"):
        bad(regs_in["sample_counter"], "scale", "registers.sample_counter: scale must be the counter "
            "period in seconds (the drive's time base)", "set scale: <period, e.g. 0.001> and unit: s")



def _check_layout(regs_in: dict, registers: dict[str, Register], bad) -> None:
    """No overlaps; the sampled registers one contiguous block (one read, one instant)."""
    # overlapping addresses
    ordered = sorted(registers.values(), key=lambda r: r.address)
    for a, b in zip(ordered, ordered[1:]):
        if b.address < a.address + a.words:
            bad(regs_in[b.name], "address", f"registers.{b.name}.address: {b.address} overlaps "
                f"registers.{a.name} ({a.type} at {a.address}..{a.address + a.words - 1})",
                "move one of them to a free address")
    # the sampled registers form one contiguous block -> one read, one instant
    sampled = sorted((registers[n] for n in SAMPLED if n in registers), key=lambda r: r.address)
    for a, b in zip(sampled, sampled[1:]):
        if b.address != a.address + a.words:
            bad(regs_in[b.name], "address", f"registers.{b.name}.address: {b.address} leaves a gap "
                f"after registers.{a.name}; {', '.join(SAMPLED)} must be contiguous",
                f"place {b.name} at {a.address + a.words} so one request reads them at one instant")
    if sampled and sampled[-1].address + sampled[-1].words - sampled[0].address > MAX_READ_WORDS:
        bad(regs_in, None, "the sample block is longer than one Modbus read",
            f"keep it within {MAX_READ_WORDS} words")



def _check_control(data, bad):
    """Modes, control values and the status word: (modes, control_values, status_word, fault_bit)."""
    modes = data.get("modes")
    if not isinstance(modes, dict) or any(not isinstance(modes.get(m), int) for m in MODES):
        bad(data, "modes", "modes: needs integer values for velocity and torque",
            "add `modes: {velocity: 3, torque: 4}` (the mode register values); a drive without "
            "a torque mode cannot be the output motor")
    cv = data.get("control_values")
    if not isinstance(cv, dict) or any(not isinstance(cv.get(k), int) for k in CONTROL_VALUES):
        bad(data, "control_values", f"control_values: needs integers for {', '.join(CONTROL_VALUES)}",
            "add e.g. `control_values: {quick_stop: 2, disable: 0, fault_reset: 128}`")
    sw = data.get("status_word", {})
    if not isinstance(sw, dict):
        bad(data, "status_word", "status_word: not a mapping",
            "write {fault_bit: 3, enabled_mask: 0x6F, enabled_value: 0x27}")
        sw = {}
    fault_bit = sw.get("fault_bit", 3)
    if isinstance(fault_bit, bool) or not isinstance(fault_bit, int) or not 0 <= fault_bit <= 15:
        bad(sw, "fault_bit", f"status_word.fault_bit: '{fault_bit}' is not a bit number", "use 0..15 (CiA 402: 3)")

    return modes, cv, sw, fault_bit


def _check_enable_sequence(data, registers: dict[str, Register], bad) -> list[Write]:
    """Writable registers, raw values, the mode written, a control write last."""
    seq_in = data.get("enable_sequence")
    if not isinstance(seq_in, list) or not seq_in:
        bad(data, "enable_sequence", "enable_sequence: missing or empty",
            "list the writes, e.g. - {register: control, value: 6}")
        seq_in = []
    seq = []
    for i, step in enumerate(seq_in):
        key = f"enable_sequence[{i}]"
        if not isinstance(step, dict) or "register" not in step or "value" not in step:
            bad(data, "enable_sequence", f"{key}: needs register and value", "write - {register: control, value: 6}")
            continue
        reg = registers.get(step["register"])
        if reg is None or not reg.writable:
            bad(step, "register", f"{key}.register: '{step['register']}' is not a writable register of this map",
                "name a register with access w or rw")
        value = step["value"]
        if value != "mode" and (isinstance(value, bool) or not isinstance(value, int)):
            bad(step, "value", f"{key}.value: '{value}' is not a raw integer", "give the raw register value, or 'mode'")
        seq.append(Write(str(step["register"]), value))
    if seq and not any(w.value == "mode" for w in seq):
        bad(data, "enable_sequence", "enable_sequence never writes the mode", "add - {register: mode, value: mode}")
    if seq and seq[-1].register != "control":
        bad(data, "enable_sequence", "enable_sequence does not end with a control write",
            "end with the enable-operation controlword, e.g. - {register: control, value: 15}")

    return seq
