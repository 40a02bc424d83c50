"""Validate a marked YAML document into a ``Profile``, section by section.

Everything is checked before anything moves: types, ranges, references between
sections, drive description files, step order, feasibility against the motors'
limits, and the ``simulation:`` plant (through ``gearbench.sim.PlantParams.from_dict``).
The first problem raises one ``ProfileError`` line:
``file:line:col: dotted.key: problem; fix``.
"""
from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from ..errors import ProfileError
from . import waveforms as wf
from .coverage import map_speed_range
from .model import (Outputs, BenchSpec, BusSpec, CalibrateStep, DiskSpec, EfficiencyStep, LimitSpec, LoadStep,
                    MotorSpec, Profile, ReducerSpec, Targets, WaveformSpec)
from .yamlmarks import MarkedDoc, did_you_mean, one_line

_MISSING = object()
_NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_.-]{0,63}$")

TOP_KEYS = ("name", "description", "bench", "motors", "reducer", "disks", "waveforms", "steps", "limits",
            "simulation", "targets", "outputs")
OUTPUT_KEYS = ("mdf",)
MOTOR_NAMES = ("in", "out")
CAN_EXAMPLE_CHANNELS = {"socketcan": "can0", "pcan": "PCAN_USBBUS1", "kvaser": 0, "ixxat": 0, "vector": 0}
STEP_KINDS = ("calibrate", "load", "efficiency")
MOTOR_QUANTITIES = ("Kt", "Kt_rel_datasheet", "J", "D", "Tc")
EFFICIENCY_QUANTITIES = ("eta_incremental", "eta_absolute")
# Waveform kinds whose command is continuous, so its slope is a real acceleration demand.
_SMOOTH_KINDS = ("constant", "ramp", "trapezoid", "multisine", "chirp")

# What each field means, used as the "fix" half of an error message.
MEANING = {
    "name": "a short name", "description": "a one-line description",
    "period_s": "the sample (SYNC) period in s, e.g. 0.001",
    "family": "the drive family: cia402 or modbus",
    "interface": "the CAN interface python-can opens: socketcan, pcan, kvaser, ixxat, vector, ... "
                 "(udp_multicast or virtual for a simulated bench)",
    "bitrate": "the CAN bit rate in bit/s, e.g. 1000000",
    "channel": "the CAN channel, e.g. can0",
    "host": "the Modbus TCP host, e.g. 127.0.0.1", "port": "the Modbus TCP port, e.g. 502",
    "drive": "the drive description file, e.g. drivers/cia402-servo.eds",
    "address": "the drive's node id (CANopen) or unit id (Modbus)",
    "kt_datasheet": "the motor's datasheet torque constant in N m/A, e.g. 0.0527",
    "rated_current_a": "the drive's rated current in A",
    "current_limit_a": "the drive's peak current limit in A",
    "speed_limit_rad_s": "the motor's maximum speed in rad/s",
    "counts_per_rev": "the encoder counts per revolution (after quadrature), e.g. 10000",
    "rotor_inertia_kgm2": "the rotor inertia from the datasheet in kg m^2, e.g. 1.5e-5",
    "sampling": "how the drive samples: {setpoint: step | interpolated, current: instant | mean}",
    "ratio": "the nominal reduction ratio n (input/output speed) or 'measure'",
    "cvt_setting": "the CVT adjuster position as a fraction of its travel, 0 < s <= 1",
    "efficiency_range": "the expected efficiency as [low, high], e.g. [0.6, 0.9]",
    "inertia_kgm2": "the disk's moment of inertia in kg m^2, e.g. 2.0e-5",
    "inertia_tolerance_rel": "how well the disk's inertia is known, relative, e.g. 0.005 for +/-0.5 %",
    "inertia_source": "where the tolerance comes from: datasheet (+/- limits) or measured "
                      "(95 % expanded uncertainty)",
    "duration_s": "the length of each calibration run in s",
    "speeds_in_rad_s": "the input speeds in rad/s, e.g. [100, 200, 300]",
    "torques_out_nm": "the output braking torques in N m, e.g. [0.02, 0.04, 0.06, 0.08]",
    "settle_s": "the settling time per level in s", "measure_s": "the measuring time per level in s",
    "include_zero_load": "true or false", "prompt": "the operator prompt text",
    "remove_prompt": "the operator prompt text", "mode": "velocity or torque",
    "low": "the lower limit", "high": "the upper limit", "nominal": "the nominal value",
    "tolerance_rel": "the relative tolerance, e.g. 0.02 for +/-2 %",
    "quantity": "what is limited, e.g. motors.in.Kt_rel_datasheet",
    "min_s": "the shortest an adaptive measurement may stop, in s",
    "max_s": "the longest an adaptive measurement may run, in s",
    "kt_rel": "the target 95 % statistical half-width of Kt, relative, e.g. 0.001 for 0.1 %",
    "eta_pp": "the target 95 % statistical half-width of the incremental efficiency in "
              "percentage points, e.g. 0.1",
    "parallel_calibration": "true (calibrate both motors at once before the reducer is mounted) or false",
}


def _describe(value) -> str:
    if value is None:
        return "nothing"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, (int, float)):
        return f"{value:g}" if isinstance(value, float) else str(value)
    if isinstance(value, str):
        return repr(value if len(value) <= 40 else value[:37] + "...")
    if isinstance(value, list):
        return "a list"
    if isinstance(value, dict):
        return "a mapping"
    return type(value).__name__


class _Checker:
    """Typed getters that raise located ``ProfileError``s; one per document."""

    def __init__(self, doc: MarkedDoc):
        self.doc = doc

    def fail(self, path, problem: str, fix: str = "", *, at_value: bool = False):
        raise self.doc.error(tuple(path), problem, fix, at_value=at_value)

    def mapping(self, value, path, what: str) -> dict:
        if not isinstance(value, dict):
            self.fail(path, f"must be a mapping (got {_describe(value)})", f"write {what}", at_value=True)
        return value

    def keys(self, m: dict, path, allowed, required=()) -> None:
        for key in m:
            if key not in allowed:
                self.fail(tuple(path) + (key,), "unknown key", did_you_mean(key, allowed))
        for key in required:
            if key not in m:
                self.fail(path, f"missing key '{key}'", f"add '{key}:' with {MEANING.get(key, 'a value')}")

    def _get(self, m, path, key, default, meaning=None):
        if key in m and m[key] is not None:
            return m[key], False
        if default is _MISSING:
            self.fail(path, f"missing key '{key}'" if key not in m else f"'{key}' is empty",
                      f"set '{key}:' to {meaning or MEANING.get(key, 'a value')}")
        return default, True

    def number(self, m, path, key, default=_MISSING, *, gt=None, ge=None, le=None, lt=None, meaning=None):
        value, defaulted = self._get(m, path, key, default, meaning)
        if defaulted:
            return value
        return self.check_number(value, tuple(path) + (key,), key, gt=gt, ge=ge, le=le, lt=lt, meaning=meaning)

    def check_number(self, value, path, key, *, gt=None, ge=None, le=None, lt=None, meaning=None) -> float:
        fix = f"set {meaning or MEANING.get(key, 'a number')}"
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            self.fail(path, f"must be a number (got {_describe(value)})", fix)
        value = float(value)
        if not math.isfinite(value):
            self.fail(path, f"must be a finite number (got {value})", fix)
        for bound, ok, sign in ((gt, lambda b: value > b, ">"), (ge, lambda b: value >= b, ">="),
                                (lt, lambda b: value < b, "<"), (le, lambda b: value <= b, "<=")):
            if bound is not None and not ok(bound):
                self.fail(path, f"must be {sign} {bound:g} (got {value:g})", fix)
        return value

    def integer(self, m, path, key, default=_MISSING, *, ge=None, le=None, meaning=None) -> int:
        value, defaulted = self._get(m, path, key, default, meaning)
        if defaulted:
            return value
        kpath = tuple(path) + (key,)
        fix = f"set {meaning or MEANING.get(key, 'a whole number')}"
        if isinstance(value, bool) or not isinstance(value, int):
            self.fail(kpath, f"must be a whole number (got {_describe(value)})", fix)
        if ge is not None and value < ge or le is not None and value > le:
            rng = f"between {ge} and {le}" if ge is not None and le is not None else \
                (f">= {ge}" if ge is not None else f"<= {le}")
            self.fail(kpath, f"must be {rng} (got {value})", fix)
        return value

    def string(self, m, path, key, default=_MISSING, *, choices=None) -> str:
        value, defaulted = self._get(m, path, key, default)
        if defaulted:
            return value
        kpath = tuple(path) + (key,)
        if isinstance(value, (int, float)) and not isinstance(value, bool) and choices is None \
                and key in ("name", "channel", "host"):
            value = str(value)   # e.g. name: 2024 or channel: 0
        if not isinstance(value, str) or not value.strip():
            self.fail(kpath, f"must be text (got {_describe(value)})", f"set {MEANING.get(key, 'some text')}")
        if choices is not None and value not in choices:
            self.fail(kpath, f"must be one of {', '.join(choices)} (got {_describe(value)})",
                      did_you_mean(value, choices))
        return value

    def boolean(self, m, path, key, default=_MISSING) -> bool:
        value, defaulted = self._get(m, path, key, default)
        if not defaulted and not isinstance(value, bool):
            self.fail(tuple(path) + (key,), f"must be true or false (got {_describe(value)})", "write true or false")
        return value

    def number_list(self, m, path, key, *, gt=None, le=None, meaning=None) -> list[float]:
        value, _ = self._get(m, path, key, _MISSING, meaning)
        kpath = tuple(path) + (key,)
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            value = [value]  # a single level is a one-element list
        if not isinstance(value, list) or not value:
            self.fail(kpath, f"must be a non-empty list of numbers (got {_describe(value)})",
                      f"set {meaning or MEANING.get(key, 'a list of numbers')}", at_value=True)
        return [self.check_number(x, kpath + (i,), key, gt=gt, le=le, meaning=meaning) for i, x in enumerate(value)]

    def ident(self, name, path, what: str) -> str:
        if not isinstance(name, str) or not _NAME_RE.match(name):
            self.fail(path, f"{what} name {_describe(name)} is not a plain identifier",
                      "use letters, digits, '_', '-' or '.', starting with a letter")
        return name


# --------------------------------------------------------------------------- sections


def build_profile(doc: MarkedDoc, path: Path, sha256: str, base_dir: Path) -> Profile:
    """Validate ``doc`` (from ``yamlmarks.load_with_marks``) into a ``Profile``."""
    c = _Checker(doc)
    if doc.data is None:
        c.fail((), "the profile is empty", "start from profiles/cvt.yaml or docs/profile-format.md")
    top = c.mapping(doc.data, (), "the profile as a mapping with keys bench, motors, steps, ...")
    c.keys(top, (), TOP_KEYS, required=("bench", "motors", "steps"))
    name = c.string(top, (), "name", path.stem)
    description = c.string(top, (), "description", "")
    bench = _bench(c, top)
    motors = _motors(c, top, bench, base_dir)
    reducer = _reducer(c, top)
    disks = _disks(c, top)
    waveforms = _waveforms(c, top, bench.period_s)
    steps = _steps(c, top, motors, reducer, disks, waveforms, bench.period_s)
    targets = _targets(c, top, steps)
    limits = _limits(c, top, motors, reducer, steps)
    simulation = _simulation(c, top, bench, motors)
    # designed calibrations sweep the map's speeds (coverage.map_speed_range needs the ratio)
    plan = SimpleNamespace(steps=steps, reducer=reducer, limits=limits, simulation=simulation)
    waveforms = _design_waveforms(c, waveforms, steps, motors, disks, bench.period_s,
                                  cover_of=lambda motor: map_speed_range(plan, motor))
    outputs = _outputs(c, top)
    return Profile(path=path, sha256=sha256, name=name, description=description, bench=bench, motors=motors,
                   reducer=reducer, disks=disks, waveforms=waveforms, steps=steps, limits=limits,
                   simulation=simulation, raw=top, targets=targets, outputs=outputs)


def _outputs(c: _Checker, top) -> Outputs:
    """``outputs: {mdf: true}``: files written with every run besides the required ones."""
    m = c.mapping(top.get("outputs") or {}, ("outputs",), "outputs: {mdf: true}")
    c.keys(m, ("outputs",), OUTPUT_KEYS)
    return Outputs(mdf=c.boolean(m, ("outputs",), "mdf", False))


def _targets(c: _Checker, top, steps) -> Targets:
    """``targets: {kt_rel, eta_pp}``; an adaptive step needs the target it stops on."""
    p = ("targets",)
    t = c.mapping(top.get("targets") or {}, p, "targets: {kt_rel: 0.001, eta_pp: 0.1}")
    c.keys(t, p, ("kt_rel", "eta_pp"))
    targets = Targets(kt_rel=c.number(t, p, "kt_rel", None, gt=0.0, lt=1.0),
                      eta_pp=c.number(t, p, "eta_pp", None, gt=0.0, le=100.0))
    for i, s in enumerate(steps):
        if isinstance(s, CalibrateStep) and s.adaptive and targets.kt_rel is None:
            c.fail(("steps", i, "min_s"), "an adaptive calibrate step (min_s/max_s) needs targets.kt_rel",
                   f"add 'targets: {{kt_rel: 0.001}}' ({MEANING['kt_rel']}) or use duration_s")
        if isinstance(s, EfficiencyStep) and s.adaptive and targets.eta_pp is None:
            c.fail(("steps", i, "min_s"), "an adaptive efficiency step (min_s/max_s) needs targets.eta_pp",
                   f"add 'targets: {{eta_pp: 0.1}}' ({MEANING['eta_pp']}) or use settle_s/measure_s")
    return targets


def _known_families() -> list[str]:
    # not cached: a plugin installed while a station runs must be found at the next load
    try:
        from ..drives.registry import available
        return sorted(available())
    except Exception:  # a broken third-party entry point must not hide the profile check
        return ["cia402", "modbus"]


def _bench(c: _Checker, top) -> BenchSpec:
    p = ("bench",)
    m = c.mapping(top["bench"], p, "bench: {name, period_s, bus: {...}}")
    c.keys(m, p, ("name", "period_s", "bus", "parallel_calibration"), required=("bus",))
    name = c.string(m, p, "name", "bench")
    period = c.number(m, p, "period_s", 1e-3, gt=0.0, le=0.1)
    bp = p + ("bus",)
    b = c.mapping(m["bus"], bp, "bus: {family: cia402, interface: socketcan, channel: can0}")
    c.keys(b, bp, ("family", "interface", "channel", "bitrate", "host", "port", "options"), required=("family",))
    family = c.string(b, bp, "family")
    families = _known_families()
    if family not in families:
        c.fail(bp + ("family",), f"unknown drive family {_describe(family)}",
               f"{did_you_mean(family, families)} (or install the plugin that provides it)")
    options = c.mapping(b.get("options") or {}, bp + ("options",), "options as a mapping")
    interface = channel = host = port = None
    if family == "cia402":
        for key in ("host", "port"):
            if key in b:
                c.fail(bp + (key,), "is for a modbus bus", "remove it, or set family: modbus")
        from ..drives.buses import INTERFACES   # every interface python-can knows, plug-ins included
        interface = c.string(b, bp, "interface", choices=INTERFACES)
        channel = c.string(b, bp, "channel", None)
        if interface not in ("udp_multicast", "virtual") and channel is None:
            example = CAN_EXAMPLE_CHANNELS.get(interface, "the adapter's channel")
            c.fail(bp, f"a {interface} bus needs 'channel'",
                   f"add 'channel: {example}'" + (" (or vcan0)" if interface == "socketcan" else ""))
        if "bitrate" in b:   # the adapter's bit rate, passed to python-can with the other bus_kwargs
            kw = dict(options.get("bus_kwargs") or {})
            kw["bitrate"] = c.integer(b, bp, "bitrate", ge=10_000, le=8_000_000)
            options = {**options, "bus_kwargs": kw}
    elif family == "modbus":
        for key in ("interface", "channel", "bitrate"):
            if key in b:
                c.fail(bp + (key,), "is for a CAN bus", "remove it, or set family: cia402")
        host = c.string(b, bp, "host")
        if any(ch.isspace() for ch in host):
            c.fail(bp + ("host",), f"is not a host name or IP address (got {_describe(host)})",
                   "set e.g. host: 127.0.0.1")
        port = c.integer(b, bp, "port", 502, ge=1, le=65535)
    else:  # a plugin family: pass everything through
        interface = c.string(b, bp, "interface", None)
        channel = c.string(b, bp, "channel", None)
        host = c.string(b, bp, "host", None)
        port = c.integer(b, bp, "port", None, ge=1, le=65535)
    bus = BusSpec(family=family, interface=interface, channel=channel, host=host, port=port, options=dict(options))
    return BenchSpec(name=name, bus=bus, period_s=period,
                     parallel_calibration=c.boolean(m, p, "parallel_calibration", False))


def _resolve_drive(c: _Checker, value: str, path, base_dir: Path) -> str:
    # Order (documented in gearbench.drives.shipped): profile's folder, station, shipped.
    from ..drives.shipped import find_drive

    found, looked = find_drive(value, base_dir)
    if found is not None:
        return str(found)
    vendor = ("; gearbench does not ship vendors' EDS/DCF files: put the file your drive's vendor ships "
              "(unchanged) there" if Path(value).suffix.lower() in (".eds", ".dcf")
              and Path(value).name != "cia402-servo.eds" else "")
    c.fail(path, f"drive description '{value}' not found (looked in {', '.join(map(str, looked))})",
           "fix the path, relative to the profile's folder or the station (e.g. drivers/cia402-servo.eds), "
           "or put the file in the station's drivers/ folder" + vendor)


_DRIVE_SUFFIXES = {"cia402": (".eds", ".dcf"), "modbus": (".yaml", ".yml")}


def _motors(c: _Checker, top, bench: BenchSpec, base_dir: Path) -> dict[str, MotorSpec]:
    p = ("motors",)
    m = c.mapping(top["motors"], p, "motors: {in: {...}, out: {...}}")
    c.keys(m, p, MOTOR_NAMES)
    if not m:
        c.fail(p, "no motors", "add motors.in and/or motors.out")
    family = bench.bus.family
    addr_max = {"cia402": 127, "modbus": 247}.get(family, 2 ** 31 - 1)
    addr_min = 1 if family in ("cia402", "modbus") else 0
    motors: dict[str, MotorSpec] = {}
    used: dict[int, str] = {}
    for name, raw in m.items():
        mp = p + (name,)
        d = c.mapping(raw, mp, f"motors.{name}: {{drive, address, kt_datasheet, rated_current_a, ...}}")
        c.keys(d, mp, ("drive", "address", "kt_datasheet", "rated_current_a", "current_limit_a",
                       "speed_limit_rad_s", "counts_per_rev", "rotor_inertia_kgm2", "sampling"),
               required=("drive", "address", "kt_datasheet", "rated_current_a", "current_limit_a",
                         "speed_limit_rad_s"))
        drive_text = c.string(d, mp, "drive")
        suffixes = _DRIVE_SUFFIXES.get(family)
        if suffixes and Path(drive_text).suffix.lower() not in suffixes:
            c.fail(mp + ("drive",), f"a {family} drive needs a {' or '.join(suffixes)} description "
                                    f"(got '{drive_text}')",
                   "use drivers/cia402-servo.eds for cia402 or a register map .yaml for modbus")
        drive = _resolve_drive(c, drive_text, mp + ("drive",), base_dir)
        address = c.integer(d, mp, "address", ge=addr_min, le=addr_max)
        if address in used:
            c.fail(mp + ("address",), f"address {address} is already used by motor '{used[address]}'",
                   "give each drive its own node/unit id")
        used[address] = name
        kt = c.number(d, mp, "kt_datasheet", gt=0.0, le=100.0)
        rated = c.number(d, mp, "rated_current_a", gt=0.0, le=10_000.0)
        limit = c.number(d, mp, "current_limit_a", gt=0.0, le=10_000.0)
        if limit < rated:
            c.fail(mp + ("current_limit_a",), f"must be >= rated_current_a ({rated:g}) (got {limit:g})",
                   "raise current_limit_a or lower rated_current_a")
        speed = c.number(d, mp, "speed_limit_rad_s", gt=0.0, le=20_000.0)
        cpr = c.integer(d, mp, "counts_per_rev", 10000, ge=4, le=2 ** 31 - 1)
        inertia = c.number(d, mp, "rotor_inertia_kgm2", None, gt=0.0, le=10.0)
        motors[name] = MotorSpec(name=name, drive=drive, address=address, kt_datasheet=kt, rated_current_a=rated,
                                 current_limit_a=limit, speed_limit_rad_s=speed, counts_per_rev=cpr,
                                 rotor_inertia_kgm2=inertia, sampling=_sampling(c, d, mp))
    return motors


def _sampling(c: _Checker, d: dict, mp) -> dict | None:
    """``sampling:`` of a motor: how its drive samples, from its set-up (CiA 402: cyclic
    synchronous velocity with interpolation 0x60C2, or setpoints taken as steps; a current
    object that is a period mean, or one current-loop sample). The identification fits a
    stepping, sampling drive's current kick (identify.drive_loop._setpoint_steps) only when told."""
    if d.get("sampling") is None:
        return None
    sp = mp + ("sampling",)
    s = c.mapping(d["sampling"], sp, "sampling: {setpoint: step | interpolated, current: instant | mean}")
    loop = ("speed_kp_a_s_per_rad", "current_loop_time_constant_s", "speed_loop_period_s")
    c.keys(s, sp, ("setpoint", "current", *loop), required=("setpoint", "current"))
    out = {"setpoint": c.string(s, sp, "setpoint", choices=("step", "interpolated")),
           "current": c.string(s, sp, "current", choices=("instant", "mean"))}
    # the drive's loop as set (optional, all three): its kick is then computed
    # (identify.declared_kick; a period-mean or interpolating drive's, identify.declared_period_kick), not fitted
    if any(k in s for k in loop):
        out["speed_kp_a_s_per_rad"] = c.number(s, sp, loop[0], gt=0.0)
        out["current_loop_time_constant_s"] = c.number(s, sp, loop[1], ge=0.0, le=1.0)
        out["speed_loop_period_s"] = c.number(s, sp, loop[2], gt=0.0, le=1.0)
    return out


def _reducer(c: _Checker, top) -> ReducerSpec | None:
    if top.get("reducer") is None:
        return None
    p = ("reducer",)
    m = c.mapping(top["reducer"], p, "reducer: {name, ratio, efficiency_range}")
    c.keys(m, p, ("name", "ratio", "cvt_setting", "efficiency_range"),
           required=("name", "ratio", "efficiency_range"))
    name = c.string(m, p, "name")
    raw_ratio = m["ratio"]
    if isinstance(raw_ratio, str):
        if raw_ratio != "measure":
            c.fail(p + ("ratio",), f"must be a number > 0 or 'measure' (got {_describe(raw_ratio)})",
                   did_you_mean(raw_ratio, ["measure"]))
        ratio = None
    else:
        ratio = c.number(m, p, "ratio", gt=0.0, le=100_000.0)
    setting = c.number(m, p, "cvt_setting", None, gt=0.0, le=1.0)
    rng_path = p + ("efficiency_range",)
    rng = m["efficiency_range"]
    if not isinstance(rng, list) or len(rng) != 2:
        c.fail(rng_path, f"must be a list [low, high] (got {_describe(rng)})", f"set {MEANING['efficiency_range']}",
               at_value=True)
    low = c.check_number(rng[0], rng_path + (0,), "efficiency_range", gt=0.0, le=1.0)
    high = c.check_number(rng[1], rng_path + (1,), "efficiency_range", gt=0.0, le=1.0)
    if low > high:
        c.fail(rng_path, f"low ({low:g}) must be <= high ({high:g})", "swap the two values")
    return ReducerSpec(name=name, ratio=ratio, cvt_setting=setting, efficiency_range=(low, high))


def _disks(c: _Checker, top) -> dict[str, DiskSpec]:
    p = ("disks",)
    example = "{inertia_kgm2: 2.0e-5, inertia_tolerance_rel: 0.005, inertia_source: measured}"
    m = c.mapping(top.get("disks") or {}, p, f"disks: {{disk1: {example}}}")
    disks = {}
    for name, raw in m.items():
        dp = p + (name,)
        c.ident(name, dp, "disk")
        d = c.mapping(raw, dp, f"disks.{name}: {example}")
        # Kt is proportional to the disk's inertia: its tolerance is part of Kt's uncertainty
        keys = ("inertia_kgm2", "inertia_tolerance_rel", "inertia_source")
        c.keys(d, dp, keys, required=keys)
        disks[name] = DiskSpec(name=name, inertia_kgm2=c.number(d, dp, "inertia_kgm2", gt=0.0, le=10.0),
                               inertia_tolerance_rel=c.number(d, dp, "inertia_tolerance_rel", gt=0.0, le=0.5),
                               inertia_source=c.string(d, dp, "inertia_source",
                                                       choices=("datasheet", "measured")))
    return disks


def _waveforms(c: _Checker, top, period_s: float) -> dict[str, WaveformSpec]:
    p = ("waveforms",)
    m = c.mapping(top.get("waveforms") or {}, p, "waveforms: {excite: {kind: multisine, ...}}")
    out = {}
    for name, raw in m.items():
        wp = p + (name,)
        c.ident(name, wp, "waveform")
        d = c.mapping(raw, wp, f"waveforms.{name}: {{kind: multisine, ...}}")
        kind = c.string(d, wp, "kind", choices=wf.KINDS)
        table = wf.PARAMS[kind]
        c.keys(d, wp, ("kind",) + tuple(table))
        designed = kind == "multisine" and d.get("design") == "optimal"
        for key in (wf.DESIGNED_KEYS if designed else wf.DESIGN_ONLY_KEYS if kind == "multisine" else ()):
            if key in d:
                c.fail(wp + (key,), "is chosen by the design (design: optimal)" if designed
                       else "is a design setting, used only with 'design: optimal'",
                       f"remove '{key}'" if designed else f"remove '{key}' or add 'design: optimal'")
        params = {}
        for key, spec in table.items():
            default = _MISSING if spec.default is wf.REQUIRED else spec.default
            if designed and key in wf.DESIGNED_KEYS:
                params[key] = None if default is _MISSING else default   # filled by _design_waveforms
                continue
            if key not in d and default is _MISSING:
                c.fail(wp, f"a {kind} waveform needs '{key}'", f"add '{key}:' ({spec.meaning})")
            meaning = f"'{key}' ({spec.meaning})"
            if spec.type == "number":
                params[key] = c.number(d, wp, key, default, gt=spec.gt, ge=spec.ge, le=spec.le, meaning=meaning)
            elif spec.type == "int":
                params[key] = c.integer(d, wp, key, default, ge=spec.ge, le=spec.le, meaning=meaning)
            elif spec.type == "list":
                params[key] = (c.number_list(d, wp, key, gt=spec.gt, meaning=meaning) if d.get(key) is not None
                               else default)
            elif spec.type == "bool":
                params[key] = c.boolean(d, wp, key, default)
            else:
                params[key] = c.string(d, wp, key, default, choices=spec.choices)
        problem = None if designed else wf.check(kind, params, period_s)
        if problem:
            key, text, fix = problem
            c.fail(wp + (key,), text, fix)
        out[name] = WaveformSpec(name=name, kind=kind, params=params)
    return out


def _ref(c: _Checker, d, path, key, table: dict, what: str) -> str:
    value = c.string(d, path, key)
    if value not in table:
        known = ", ".join(table) or "none defined"
        hint = did_you_mean(value, table) if table else f"define it under '{what}:'"
        c.fail(tuple(path) + (key,), f"unknown {what[:-1]} {_describe(value)} (known: {known})", hint)
    return value


def _steps(c: _Checker, top, motors, reducer, disks, waveforms, period_s):
    p = ("steps",)
    raw = top["steps"]
    if not isinstance(raw, list) or not raw:
        c.fail(p, f"must be a non-empty list of steps (got {_describe(raw)})",
               "list steps as '- kind: calibrate', '- kind: load', '- kind: efficiency'", at_value=True)
    steps, names = [], {}
    loaded = False
    for i, item in enumerate(raw):
        sp = p + (i,)
        d = c.mapping(item, sp, "a step: '- kind: calibrate|load|efficiency' with its keys")
        kind = c.string(d, sp, "kind", choices=STEP_KINDS)
        if kind == "calibrate":
            step = _calibrate(c, d, sp, motors, disks, waveforms, period_s, loaded)
        elif kind == "load":
            if loaded:
                c.fail(sp, "a second load step", "mount the reducer once; remove this step")
            step = _load(c, d, sp, motors, reducer)
            loaded = True
        else:
            if not loaded:
                c.fail(sp, "an efficiency step needs a load step before it",
                       "add '- kind: load' (mount the reducer) before this step")
            step = _efficiency(c, d, sp, motors, reducer, period_s)
        name = step.name
        if "name" in d:
            c.ident(name, sp + ("name",), "step")
            if name in names:
                c.fail(sp + ("name",), f"step name '{name}' is already used by steps[{names[name]}]",
                       "give each step its own name")
        else:  # default names made unique: calibrate-in, calibrate-in-2, ...
            base, k = name, 2
            while name in names:
                name, k = f"{base}-{k}", k + 1
            step = dataclasses.replace(step, name=name)
        names[name] = i
        steps.append(step)
    return steps


def _calibrate(c, d, sp, motors, disks, waveforms, period_s, loaded) -> CalibrateStep:
    c.keys(d, sp, ("kind", "name", "motor", "disk", "waveform", "duration_s", "mode", "prompt", "remove_prompt",
                   "min_s", "max_s"), required=("motor", "disk", "waveform"))
    if loaded:
        c.fail(sp, "a calibrate step after the load step",
               "calibrate the motors before mounting the reducer (move this step up)")
    motor = _ref(c, d, sp, "motor", motors, "motors")
    disk = _ref(c, d, sp, "disk", disks, "disks")
    wname = _ref(c, d, sp, "waveform", waveforms, "waveforms")
    min_s, max_s = _adaptive_bounds(c, d, sp, "duration_s", 100 * period_s)
    duration = max_s if max_s is not None else c.number(d, sp, "duration_s", gt=0.0, le=3600.0)
    if duration < 100 * period_s:
        c.fail(sp + ("duration_s",), f"must cover at least 100 samples ({100 * period_s:g} s) (got {duration:g})",
               "lengthen the run")
    mode = c.string(d, sp, "mode", "velocity", choices=("velocity", "torque"))
    wave, mspec, dspec = waveforms[wname], motors[motor], disks[disk]
    if wave.params.get("design") == "optimal":
        if mode != "velocity":
            c.fail(sp + ("mode",), f"waveform '{wname}' is a designed speed command (design: optimal)",
                   "remove 'mode: torque', or use a hand-written waveform for current mode")
    else:
        _check_run(c, sp, wave, mspec, dspec, duration, period_s, mode)
    prompt = c.string(d, sp, "prompt", f"Mount inertia disk '{disk}' ({dspec.inertia_kgm2:g} kg m^2) "
                                        f"on motor '{motor}'")
    remove = c.string(d, sp, "remove_prompt", f"Remove inertia disk '{disk}' from motor '{motor}'")
    return CalibrateStep(motor=motor, disk=disk, waveform=wname, duration_s=duration, prompt=prompt,
                         name=c.string(d, sp, "name", f"calibrate-{motor}"), mode=mode, remove_prompt=remove,
                         min_s=min_s, max_s=max_s)


def _check_run(c, sp, wave: WaveformSpec, mspec: MotorSpec, dspec: DiskSpec, duration, period_s, mode):
    natural = wave.natural_period_s
    if natural is not None and duration < natural * (1 - 1e-9):
        c.fail(sp + ("duration_s",), f"is shorter than one period of waveform '{wave.name}' ({natural:g} s)",
               f"set duration_s >= {natural:g} or shorten the waveform's period")
    _check_command(c, sp, wave, mspec, dspec, duration, period_s, mode)


def _design_waveforms(c: _Checker, waveforms, steps, motors, disks, period_s, cover_of=lambda m: None):
    """Fill each ``design: optimal`` multisine from the calibrate steps that use it
    (``gearbench.profile.design``), sweeping the speeds ``cover_of(motor)`` its motors
    turn at over the efficiency map, then check those runs like any other."""
    from .design import DesignProblem, design_waveform

    out = dict(waveforms)
    for name, wave in waveforms.items():
        if wave.params.get("design") != "optimal":
            continue
        wp = ("waveforms", name)
        users = [(i, s) for i, s in enumerate(steps) if isinstance(s, CalibrateStep) and s.waveform == name]
        if not users:
            c.fail(wp + ("design",), "a designed waveform needs a calibrate step that uses it",
                   f"use it in a calibrate step ('waveform: {name}') or remove 'design: optimal'")
        try:
            params, design = design_waveform(
                wave.params, [(motors[s.motor], disks[s.disk], s.duration_s) for _, s in users], period_s,
                also_fit_s=[s.min_s for _, s in users if getattr(s, "min_s", None)],
                cover=[cover_of(s.motor) for _, s in users])
        except DesignProblem as exc:
            path = exc.path if exc.path[0] == "motors" else wp + exc.path
            if path not in c.doc.key_marks and path not in c.doc.value_marks:
                path = wp
            c.fail(path, exc.problem, exc.fix)
        problem = wf.check("multisine", params, period_s)
        if problem:   # a design bug, but say it in the profile's words
            c.fail(wp + ("design",), f"the designed {problem[0]} {problem[1]}", problem[2])
        out[name] = WaveformSpec(name=name, kind="multisine", params=params, design=design)
        for i, s in users:
            _check_run(c, ("steps", i), out[name], motors[s.motor], disks[s.disk], s.duration_s,
                       period_s, s.mode)
    return out


def _adaptive_bounds(c, d, sp, fixed_key: str, shortest_s: float):
    """``min_s``/``max_s`` of an adaptive step: both or neither, not with ``fixed_key``,
    0 < min_s <= max_s, min_s at least ``shortest_s``. Returns (None, None) when fixed."""
    if "min_s" not in d and "max_s" not in d:
        return None, None
    for key in ("min_s", "max_s"):
        if key not in d:
            c.fail(sp, f"missing key '{key}' (an adaptive step needs both min_s and max_s)",
                   f"add '{key}:' with {MEANING[key]}")
    if fixed_key in d:
        c.fail(sp + (fixed_key,), "a fixed length and min_s/max_s (adaptive) together",
               f"remove {fixed_key} (adaptive) or min_s/max_s (fixed length)")
    lo = c.number(d, sp, "min_s", gt=0.0, le=3600.0)
    hi = c.number(d, sp, "max_s", gt=0.0, le=3600.0)
    if lo < shortest_s:
        c.fail(sp + ("min_s",), f"must cover at least {shortest_s:g} s (got {lo:g})", "lengthen min_s")
    if hi < lo:
        c.fail(sp + ("max_s",), f"is shorter than min_s ({hi:g} < {lo:g})", "set max_s >= min_s")
    return lo, hi


def _check_command(c, sp, wave: WaveformSpec, motor: MotorSpec, disk: DiskSpec, duration, period_s, mode):
    """The waveform must stay inside the motor's limits over the run (with the disk mounted)."""
    n = int(math.ceil(duration / period_s))
    # Long or finely sampled runs: check on at most 200k points (the slope is then per actual step).
    t = np.arange(n) * period_s if n <= 200_000 else np.linspace(0.0, duration, 200_000)
    dt = t[1] - t[0] if t.size > 1 else period_s
    cmd = wave.render(t)
    peak = float(np.max(np.abs(cmd))) if cmd.size else 0.0
    where = sp + ("waveform",)
    if mode == "velocity":
        if peak > motor.speed_limit_rad_s:
            c.fail(where, f"waveform '{wave.name}' reaches {peak:.4g} rad/s, above motors.{motor.name}."
                          f"speed_limit_rad_s ({motor.speed_limit_rad_s:g})",
                   "lower the waveform's offset/amplitude")
        if motor.rotor_inertia_kgm2 and wave.kind in _SMOOTH_KINDS and cmd.size > 2:
            accel = float(np.max(np.abs(np.diff(cmd)))) / dt
            inertia = motor.rotor_inertia_kgm2 + disk.inertia_kgm2
            need_a = accel * inertia / motor.kt_datasheet
            if need_a > motor.current_limit_a:
                c.fail(where, f"waveform '{wave.name}' needs about {need_a:.3g} A to accelerate motor "
                              f"'{motor.name}' with disk '{disk.name}' ({accel:.4g} rad/s^2 x {inertia:.3g} kg m^2) "
                              f"but current_limit_a is {motor.current_limit_a:g} A",
                       "lower the waveform's amplitude or frequencies")
    elif peak > motor.current_limit_a:
        c.fail(where, f"waveform '{wave.name}' reaches {peak:.4g} A, above motors.{motor.name}.current_limit_a "
                      f"({motor.current_limit_a:g})", "lower the waveform's offset/amplitude")


def _load(c, d, sp, motors, reducer) -> LoadStep:
    c.keys(d, sp, ("kind", "name", "prompt"))
    if reducer is None:
        c.fail(sp, "a load step needs a 'reducer:' section", "add reducer: {name, ratio, efficiency_range}")
    missing = [m for m in MOTOR_NAMES if m not in motors]
    if missing:
        c.fail(sp, f"a load step needs both motors; motors.{missing[0]} is missing", f"add motors.{missing[0]}")
    text = f"Mount reducer '{reducer.name}' between motor 'in' and motor 'out'"
    if reducer.cvt_setting is not None:
        text += f", CVT adjuster at {reducer.cvt_setting:.0%} of travel"
    return LoadStep(prompt=c.string(d, sp, "prompt", text), name=c.string(d, sp, "name", "load"))


def _efficiency(c, d, sp, motors, reducer: ReducerSpec, period_s) -> EfficiencyStep:
    c.keys(d, sp, ("kind", "name", "speeds_in_rad_s", "torques_out_nm", "settle_s", "measure_s",
                   "include_zero_load", "min_s", "max_s"), required=("speeds_in_rad_s", "torques_out_nm"))
    m_in, m_out = motors["in"], motors["out"]
    speeds = c.number_list(d, sp, "speeds_in_rad_s", gt=0.0)
    n, eta_low = reducer.ratio, reducer.efficiency_range[0]
    for i, w in enumerate(speeds):
        if w > m_in.speed_limit_rad_s:
            c.fail(sp + ("speeds_in_rad_s", i), f"{w:g} rad/s is above motors.in.speed_limit_rad_s "
                                                f"({m_in.speed_limit_rad_s:g})", "lower the speed")
        if n is not None and w / n > m_out.speed_limit_rad_s:
            c.fail(sp + ("speeds_in_rad_s", i), f"{w:g} rad/s drives the output at {w / n:.4g} rad/s, above "
                                                f"motors.out.speed_limit_rad_s ({m_out.speed_limit_rad_s:g})",
                   "lower the speed")
    torques = c.number_list(d, sp, "torques_out_nm", gt=0.0)
    for i, t in enumerate(torques):
        need_out = t / m_out.kt_datasheet
        if need_out > m_out.current_limit_a:
            c.fail(sp + ("torques_out_nm", i),
                   f"braking {t:g} N m needs {need_out:.3g} A at Kt {m_out.kt_datasheet:g} N m/A, above "
                   f"motors.out.current_limit_a ({m_out.current_limit_a:g})",
                   f"keep braking torques <= {m_out.current_limit_a * m_out.kt_datasheet:.3g} N m")
        if n is not None:
            need_in = t / (n * eta_low) / m_in.kt_datasheet
            if need_in > m_in.current_limit_a:
                c.fail(sp + ("torques_out_nm", i),
                       f"braking {t:g} N m needs about {need_in:.3g} A on the input motor (ratio {n:g}, "
                       f"efficiency {eta_low:g}), above motors.in.current_limit_a ({m_in.current_limit_a:g})",
                       "lower the torque")
    min_s, max_s = _adaptive_bounds(c, d, sp, "measure_s", 50 * period_s)
    if min_s is not None:
        for key in ("settle_s", "include_zero_load"):
            if key in d:
                c.fail(sp + (key,), "is for a fixed-length efficiency step; an adaptive one (min_s/max_s) "
                                    "finds each level's settling in the data and starts with one zero-load level",
                       f"remove {key}")
        return EfficiencyStep(speeds_in_rad_s=speeds, torques_out_nm=torques, settle_s=0.0, measure_s=0.0,
                              name=c.string(d, sp, "name", "efficiency"), min_s=min_s, max_s=max_s)
    settle = c.number(d, sp, "settle_s", gt=0.0, le=3600.0)
    measure = c.number(d, sp, "measure_s", gt=0.0, le=3600.0)
    if measure < 20 * period_s:
        c.fail(sp + ("measure_s",), f"must cover at least 20 samples ({20 * period_s:g} s) (got {measure:g})",
               "lengthen measure_s")
    return EfficiencyStep(speeds_in_rad_s=speeds, torques_out_nm=torques, settle_s=settle, measure_s=measure,
                          include_zero_load=c.boolean(d, sp, "include_zero_load", True),
                          name=c.string(d, sp, "name", "efficiency"))


def _limits(c: _Checker, top, motors, reducer, steps) -> list[LimitSpec]:
    p = ("limits",)
    raw = top.get("limits") or []
    if not isinstance(raw, list):
        c.fail(p, f"must be a list (got {_describe(raw)})", "write each limit as '- quantity: ...'", at_value=True)
    calibrated = {s.motor for s in steps if isinstance(s, CalibrateStep)}
    has_eff = any(isinstance(s, EfficiencyStep) for s in steps)
    valid = [f"motors.{m}.{q}" for m in motors for q in MOTOR_QUANTITIES] + ["ratio"] + \
        [f"efficiency.{q}" for q in EFFICIENCY_QUANTITIES]
    limits, names = [], {}
    for i, item in enumerate(raw):
        lp = p + (i,)
        d = c.mapping(item, lp, "a limit: '- quantity: ratio' with low/high or nominal/tolerance_rel")
        c.keys(d, lp, ("name", "quantity", "low", "high", "nominal", "tolerance_rel"), required=("quantity",))
        q = c.string(d, lp, "quantity")
        if q not in valid:
            c.fail(lp + ("quantity",), f"unknown quantity {_describe(q)}", did_you_mean(q, valid))
        if q.startswith("motors.") and q.split(".")[1] not in calibrated:
            c.fail(lp + ("quantity",), f"no calibrate step measures motor '{q.split('.')[1]}'",
                   "add a calibrate step for it or remove this limit")
        if (q == "ratio" or q.startswith("efficiency.")) and not has_eff:
            c.fail(lp + ("quantity",), f"'{q}' is measured by an efficiency step, and there is none",
                   "add an efficiency step or remove this limit")
        low = c.number(d, lp, "low", None)
        high = c.number(d, lp, "high", None)
        nominal = c.number(d, lp, "nominal", None)
        tol = c.number(d, lp, "tolerance_rel", None, gt=0.0, lt=1.0)
        if (nominal is None) != (tol is None):
            c.fail(lp, "'nominal' and 'tolerance_rel' go together", "give both, or use low/high")
        if nominal is not None:
            if low is not None or high is not None:
                c.fail(lp + ("nominal",), "give either nominal/tolerance_rel or low/high, not both",
                       "remove one pair")
            low, high = sorted((nominal * (1 - tol), nominal * (1 + tol)))
        elif low is None and high is None:
            if q.startswith("efficiency.") and reducer is not None:
                low, high = reducer.efficiency_range   # the profile's expected range
            else:
                c.fail(lp, "no bound given", "add low and/or high (or nominal and tolerance_rel)")
        if low is not None and high is not None and low > high:
            c.fail(lp + ("low",), f"low ({low:g}) must be <= high ({high:g})", "swap low and high")
        name = c.string(d, lp, "name", q)
        if name in names:
            c.fail(lp + ("name",) if "name" in d else lp, f"limit name '{name}' is already used by limits[{names[name]}]",
                   "give each limit its own 'name:'")
        names[name] = i
        limits.append(LimitSpec(name=name, quantity=q, low=low, high=high))
    return limits


# --------------------------------------------------------------------------- simulation

_SIM_PATH_RE = re.compile(r"simulation(?:\.[A-Za-z_][A-Za-z0-9_]*|\[\d+\])*")


def _sim_error_path(doc: MarkedDoc, message: str) -> tuple:
    """The deepest existing document path named in a sim ProfileError message."""
    match = _SIM_PATH_RE.search(message)
    if not match:
        return ("simulation",)
    parts: list = []
    for token in re.findall(r"[A-Za-z_][A-Za-z0-9_]*|\[\d+\]", match.group(0)):
        parts.append(int(token[1:-1]) if token.startswith("[") else token)
    path = tuple(parts)
    while len(path) > 1 and path not in doc.key_marks and path not in doc.value_marks:
        path = path[:-1]
    return path


# The simulated drive reports the simulated motor's ratings (0x6075 ...), which the station
# checks against the profile's motors: the same numbers, filled in when left out.
SIM_RATINGS = ("rated_current_a", "current_limit_a", "speed_limit_rad_s", "counts_per_rev")
# what a drive reports and the station checks against the profile at start-up (0x6075, the
# encoder); the current and speed limits are written to the drive from the profile instead,
# so a simulated drive may differ there (a test of the watchdog does)
SIM_CHECKED = ("rated_current_a", "counts_per_rev")


def rating_differs(given, want: float) -> bool:
    """A simulated motor's rating (``SIM_CHECKED``) that is a number other than the
    profile motor's (beyond rounding): its drive would report it and the run be refused."""
    return isinstance(given, (int, float)) and abs(float(given) - float(want)) > 1e-9 * max(abs(float(want)), 1.0)


def _sim_ratings(c: _Checker, m: dict, motors: dict) -> dict:
    """``simulation.motors.<m>`` with the profile motor's ratings filled in; a rating that
    differs from the profile's is refused here (validate), not at the start of ``run --sim``."""
    sim_motors = m.get("motors")
    if not isinstance(sim_motors, dict):
        sim_motors = {}
    out = {}
    for name, spec in motors.items():
        given = sim_motors.get(name)
        if given is not None and not isinstance(given, dict):
            continue            # the plant's own check names it
        given = dict(given or {})
        for key in SIM_RATINGS:
            want = getattr(spec, key)
            if key in SIM_CHECKED and key in given and not isinstance(given[key], bool) \
                    and rating_differs(given[key], want):
                c.fail(("simulation", "motors", name, key),
                       f"({given[key]:g}) differs from motors.{name}.{key} ({want:g}): the simulated "
                       f"drive would report {given[key]:g} and the run be refused at its start",
                       f"make them equal, or leave simulation.motors.{name}.{key} out (the motor's "
                       f"rating is then used)", at_value=True)
            given.setdefault(key, want)
        out[name] = given
    for name, v in sim_motors.items():
        out.setdefault(name, v)
    return {**m, "motors": out}


def _simulation(c: _Checker, top, bench: BenchSpec, motors: dict | None = None) -> dict | None:
    if top.get("simulation") is None:
        return None
    p = ("simulation",)
    m = c.mapping(top["simulation"], p, "simulation: {motor_in: {...}, motor_out: {...}, ratio: ...}")
    if motors and isinstance(m.get("motors", {}), dict):
        m = _sim_ratings(c, m, motors)
    if "period_s" in m:
        period = c.number(m, p, "period_s", gt=0.0)
        if abs(period - bench.period_s) > 1e-12:
            c.fail(p + ("period_s",), f"({period:g} s) differs from bench.period_s ({bench.period_s:g} s)",
                   "remove simulation.period_s (the bench period is used) or make them equal")
    try:
        from ..sim import PlantParams
    except ImportError:
        return m   # simulation package not available: structure checked by the sequencer at --sim time
    from_dict = getattr(PlantParams, "from_dict", None)
    if from_dict is None:
        return m
    try:
        from_dict(m, "simulation")
    except ProfileError as exc:
        text = str(exc)
        line, col = c.doc.where(_sim_error_path(c.doc, text))
        unknown = re.match(r"^(\S+): unknown key; known keys: (.*)$", text)
        if unknown:
            word = unknown.group(1).rsplit(".", 1)[-1]
            text = f"{unknown.group(1)}: unknown key; {did_you_mean(word, unknown.group(2).split(', '))}"
        elif ";" not in text:
            text += "; fix this value of the simulated plant (keys: docs/profile-format.md)"
        raise ProfileError(one_line(f"{c.doc.filename}:{line}:{col}: {text}")) from None
    except Exception as exc:  # the plant rejected it some other way: still one located line
        c.fail(p, f"invalid plant ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})",
               "check the simulation keys against docs/profile-format.md")
    return m
