"""An independent Modbus client (Debian's ``mbpoll``) against the emulated bench in
another process, using only the register map in ``drivers/`` (read here with plain
PyYAML and struct, not gearbench code): run the enable sequence, command a speed,
read position, current and the sample counter, and check the motor turns.

mbpoll conventions used: ``-0`` 0-based PDU addresses (its default is 1-based),
``-r`` start address, ``-c`` count, ``-t 4`` 16-bit holding registers, ``-t 4:int``
32-bit integers, ``-B`` big-endian word order, ``-1`` poll once, ``-a`` unit id.
"""
from __future__ import annotations

import math
import re
import select
import shutil
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from conftest import require_tool

MAP_PATH = Path(__file__).resolve().parents[1] / "drivers" / "generic-modbus-servo.yaml"
MAP = yaml.safe_load(MAP_PATH.read_text())
REG = MAP["registers"]
TYPES = {"int16": ("h", 1), "uint16": ("H", 1), "int32": ("i", 2), "uint32": ("I", 2), "float32": ("f", 2)}
SPEED_RAD_S = 20.0
UNIT = 1


def _scale(reg) -> float:
    s = reg.get("scale", 1)
    return float(eval(str(s), {"__builtins__": {}, "pi": math.pi}))   # "2*pi/10000" style


@pytest.fixture(autouse=True)
def _mbpoll_installed():
    require_tool("mbpoll", "install Debian's independent Modbus client with `apt-get install mbpoll`")


@pytest.fixture
def emulator(tmp_path):
    """The emulated bench, free-running in real time, in a separate process."""
    cmd = [sys.executable, "-m", "gearbench", "emulate", "--modbus", "127.0.0.1:0"]   # it binds, then says where
    print("emulator:", " ".join(cmd))
    log = (tmp_path / "emulate.stderr").open("w+")
    proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=log, text=True)
    try:
        ready, _, _ = select.select([proc.stdout], [], [], 30)
        line = proc.stdout.readline() if ready else ""
        assert line.split()[:1] == ["ready"], f"emulator did not start: {line!r} {log.seek(0) or log.read()[-500:]}"
        yield int(line.split("modbus=")[1].rpartition(":")[2])
    finally:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()


def mbpoll(port: int, *args: str) -> str:
    exe = require_tool("mbpoll", "install Debian's independent Modbus client with `apt-get install mbpoll`")
    out = subprocess.run([exe, "-m", "tcp", "-p", str(port), "-a", str(UNIT), "-0", "-1", "-o", "2", *args],
                         capture_output=True, text=True, timeout=10)
    assert out.returncode == 0, f"mbpoll {' '.join(args)} failed: {out.stdout[-300:]} {out.stderr[-300:]}"
    return out.stdout


def type_option(reg) -> list[str]:
    kind = {"int16": "4", "uint16": "4", "int32": "4:int", "uint32": "4:int", "float32": "4:float"}[reg["type"]]
    return ["-t", kind] + (["-B"] if TYPES[reg["type"]][1] == 2 and MAP.get("word_order", "big") == "big" else [])


def write(port: int, name: str, value) -> None:
    reg = REG[name]
    mbpoll(port, *type_option(reg), "-r", str(reg["address"]), "127.0.0.1", "--", str(value))


def read_words(port: int, start: int, count: int) -> list[int]:
    out = mbpoll(port, "-t", "4", "-r", str(start), "-c", str(count), "127.0.0.1")
    words = {int(a): int(v) for a, v in re.findall(r"^\[(\d+)\]:\s+(\d+)", out, re.M)}
    return [words[a] for a in range(start, start + count)]


def decode(name: str, words: list[int], start: int):
    reg = REG[name]
    code, n = TYPES[reg["type"]]
    w = words[reg["address"] - start:reg["address"] - start + n]
    if MAP.get("word_order", "big") == "little":
        w = w[::-1]
    return struct.unpack(f">{code}", struct.pack(f">{n}H", *w))[0]


def read_sample(port: int) -> dict:
    names = ("status", "sample_counter", "position", "velocity", "current")
    start = min(REG[n]["address"] for n in names)
    count = max(REG[n]["address"] + TYPES[REG[n]["type"]][1] for n in names) - start
    words = read_words(port, start, count)                       # ONE request: one instant
    return {n: decode(n, words, start) for n in names}


def test_mbpoll_enables_the_drive_and_the_motor_turns(emulator):
    port = emulator
    for step in MAP["enable_sequence"]:
        value = MAP["modes"]["velocity"] if step["value"] == "mode" else step["value"]
        write(port, step["register"], value)
    status = read_sample(port)["status"]
    mask, value = MAP["status_word"]["enabled_mask"], MAP["status_word"]["enabled_value"]
    assert status & mask == value, f"not OPERATION ENABLED after the enable sequence: status 0x{status:04X}"

    write(port, "target_velocity", round(SPEED_RAD_S / _scale(REG["target_velocity"])))
    time.sleep(0.5)                                               # let the speed settle (real time)
    first = read_sample(port)
    mid = int(re.search(r"^\[\d+\]:\s+(-?\d+)", mbpoll(port, *type_option(REG["position"]), "-r",
                                                            str(REG["position"]["address"]), "127.0.0.1"), re.M)[1])
    time.sleep(0.4)
    second = read_sample(port)

    period_s = _scale(REG["sample_counter"])
    dt_s = (second["sample_counter"] - first["sample_counter"]) * period_s
    assert dt_s > 0.3, "the sample counter must advance with drive time"
    pos_scale = _scale(REG["position"])
    speed = (second["position"] - first["position"]) * pos_scale / dt_s
    assert speed == pytest.approx(SPEED_RAD_S, rel=0.1)
    assert first["position"] <= mid <= second["position"]          # mbpoll's own 32-bit decoding agrees
    current_a = second["current"] * _scale(REG["current"])
    assert 0.0 < current_a < 3.0                                  # friction needs a positive current
    assert not second["status"] >> MAP["status_word"]["fault_bit"] & 1

    write(port, "control", MAP["control_values"]["disable"])
    assert read_sample(port)["status"] & mask != value


def test_mbpoll_sees_an_exception_for_a_read_only_register(emulator):
    exe = shutil.which("mbpoll")
    out = subprocess.run([exe, "-m", "tcp", "-p", str(emulator), "-a", "1", "-0", "-1", "-t", "4",
                          "-r", str(REG["status"]["address"]), "127.0.0.1", "5"],
                         capture_output=True, text=True, timeout=10)
    assert out.returncode != 0 and "Illegal data address" in (out.stdout + out.stderr)
