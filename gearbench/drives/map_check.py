"""Every problem of a Modbus register map at once (``gearbench validate``).

``register_map.load_register_map`` stops at the first problem (the driver needs a
valid map or nothing); this lists them all, each naming file, line, key and fix:
register types, addresses, access, overlaps, word order, the contiguous sample
block, the sample counter, modes, control values, the enable sequence.
"""
from __future__ import annotations

import math

import yaml

from ..errors import ProfileError
from .register_map import (ACCESS, CONTROL_VALUES, MAX_READ_WORDS, MODES, REQUIRED, SAMPLED, TYPES, WORD_ORDERS,
                           _LineLoader, _line, _number, parse_register_map, resolve_description)


def check_register_map(path) -> list[str]:
    p = resolve_description(path)
    try:
        data = yaml.load(p.read_text(), Loader=_LineLoader)
    except OSError as exc:
        return [f"{path}: cannot read register map ({exc.strerror}); give a path to a YAML file in drivers/"]
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        return [f"{p}{':' + str(mark.line + 1) if mark else ''}: not valid YAML; fix the syntax"]
    where, out = str(p), []

    def bad(m, key, msg, fix):
        out.append(f"{where}{_line(m, key)}: {msg}; {fix}")

    if not isinstance(data, dict):
        return [f"{where}: top level is not a mapping; write `registers:`, `word_order:`, ... as keys"]
    if data.get("word_order", "big") not in WORD_ORDERS:
        bad(data, "word_order", f"word_order: '{data.get('word_order')}' is not a word order",
            "use 'big' (high word at the lower address) or 'little'")
    regs_in = data.get("registers")
    regs = {}
    if not isinstance(regs_in, dict) or not regs_in:
        bad(data, "registers", "registers: missing or not a mapping",
            "add `registers:` with name: {address, type, scale, unit, access}")
        regs_in = {}
    for name, spec in regs_in.items():
        key = f"registers.{name}"
        if not isinstance(spec, dict):
            bad(regs_in, name, f"{key}: not a mapping", "write {address: N, type: int16, scale: 1, access: r}")
            continue
        ok = True
        addr, rtype = spec.get("address"), spec.get("type")
        if isinstance(addr, bool) or not isinstance(addr, int) or not 0 <= addr <= 65535:
            bad(spec, "address", f"{key}.address: '{addr}' is not a register address", "use a 0-based PDU address")
            ok = False
        if rtype not in TYPES:
            bad(spec, "type", f"{key}.type: '{rtype}' is not a type", f"use one of {', '.join(TYPES)}")
            ok = False
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
            access = ""
        if ok:
            regs[name] = (addr, TYPES[rtype][1], access, spec)
    for name, need in REQUIRED.items():
        if name not in regs_in:
            bad(regs_in, None, f"registers.{name}: missing (required register)",
                f"add `{name}: {{address: N, type: ..., scale: ..., unit: ..., access: {need}}}`")
        elif name in regs and need not in regs[name][2]:
            bad(regs[name][3], "access", f"registers.{name}.access: '{regs[name][2]}' but gearbench must "
                f"{'read' if need == 'r' else 'write'} it", f"set access: {need} or rw")
    counter = regs_in.get("sample_counter") if isinstance(regs_in.get("sample_counter"), dict) else None
    if counter is not None and counter.get("unit") != "s":
        bad(counter, "unit", "registers.sample_counter: the drive's time base needs unit s and scale = its period",
            "set scale: <period, e.g. 0.001> and unit: s")
    ordered = sorted(regs.items(), key=lambda kv: kv[1][0])
    for (na, a), (nb, b) in zip(ordered, ordered[1:]):
        if b[0] < a[0] + a[1]:
            bad(b[3], "address", f"registers.{nb}.address: {b[0]} overlaps registers.{na}", "move one of them")
    sampled = sorted((n for n in SAMPLED if n in regs), key=lambda n: regs[n][0])
    for na, nb in zip(sampled, sampled[1:]):
        end = regs[na][0] + regs[na][1]
        if regs[nb][0] != end:
            bad(regs[nb][3], "address", f"registers.{nb}.address: {regs[nb][0]} leaves a gap after {na}; "
                f"{', '.join(SAMPLED)} must be contiguous", f"place {nb} at {end}: one request, one instant")
    if sampled and regs[sampled[-1]][0] + regs[sampled[-1]][1] - regs[sampled[0]][0] > MAX_READ_WORDS:
        bad(regs_in, None, "the sample block is longer than one Modbus read", f"keep it within {MAX_READ_WORDS} words")
    modes = data.get("modes")
    if not isinstance(modes, dict) or any(not isinstance(modes.get(m), int) for m in MODES):
        bad(data, "modes", "modes: needs integer values for velocity and torque",
            "add `modes: {velocity: 3, torque: 4}`; a drive without a torque mode cannot be the output motor")
    cv = data.get("control_values")
    if not isinstance(cv, dict) or any(not isinstance(cv.get(k), int) for k in CONTROL_VALUES):
        bad(data, "control_values", f"control_values: needs integers for {', '.join(CONTROL_VALUES)}",
            "add e.g. `control_values: {quick_stop: 2, disable: 0, fault_reset: 128}`")
    seq = data.get("enable_sequence")
    if not isinstance(seq, list) or not seq:
        bad(data, "enable_sequence", "enable_sequence: missing or empty", "list the writes, e.g. - {register: control, value: 6}")
        seq = []
    writes_mode = False
    for i, step in enumerate(seq):
        key = f"enable_sequence[{i}]"
        if not isinstance(step, dict) or "register" not in step or "value" not in step:
            bad(data, "enable_sequence", f"{key}: needs register and value", "write - {register: control, value: 6}")
            continue
        reg = regs.get(step["register"])
        if reg is None or "w" not in reg[2]:
            bad(step, "register", f"{key}.register: '{step['register']}' is not a writable register",
                "name a register with access w or rw")
        value = step["value"]
        writes_mode |= value == "mode"
        if value != "mode" and (isinstance(value, bool) or not isinstance(value, int)):
            bad(step, "value", f"{key}.value: '{value}' is not a raw integer", "give the raw value, or 'mode'")
    if seq and not writes_mode:
        bad(data, "enable_sequence", "enable_sequence never writes the mode", "add - {register: mode, value: mode}")
    if seq and isinstance(seq[-1], dict) and seq[-1].get("register") != "control":
        bad(data, "enable_sequence", "enable_sequence does not end with a control write",
            "end with the enable-operation controlword, e.g. - {register: control, value: 15}")
    if not out:   # whatever the loader still refuses
        try:
            parse_register_map(data, where)
        except ProfileError as exc:
            out.append(str(exc))
    return out
