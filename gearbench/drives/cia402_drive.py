"""One CiA 402 servo drive on a ``CiA402Network`` (master side): SDO access, the
start-up configuration (identity, units read back, modes, 0x60C2, limits, ramps, PDO
mapping), the CiA 402 state machine and setpoints in the drive's verified units.
See ``gearbench.drives.cia402`` for the network (SYNC, sampling, supervision)."""
from __future__ import annotations

import struct
import time

import canopen
from canopen.emcy import EmcyError
from canopen.sdo import SdoAbortedError, SdoCommunicationError, SdoVariable

from ..errors import DriveError
from .shipped import shipped_driver
from .base import AxisConfig, Drive, Mode, Sample
from .description import (DriveModel, ObjRef, axis_units, describe_velocity_code, modes_from_bits,
                          resolve_or_raise, unit_objects)
from .objects import interpolation_setting, mapping_entry
from .scaling import AxisUnits, unwrap_int32

DEFAULT_EDS = str(shipped_driver("cia402-servo.eds"))
SYNC_OVERFLOW = 240
ABORT_CONNECTION_QUICK_STOP = 3       # 0x6007: quick stop on a communication loss (CiA 402)
STATES = {  # statusword mask, value (CiA 402)
    "SWITCH ON DISABLED": (0x4F, 0x40), "READY TO SWITCH ON": (0x6F, 0x21), "SWITCHED ON": (0x6F, 0x23),
    "OPERATION ENABLED": (0x6F, 0x27), "QUICK STOP ACTIVE": (0x6F, 0x07), "FAULT": (0x4F, 0x08),
    "FAULT REACTION ACTIVE": (0x4F, 0x0F), "NOT READY TO SWITCH ON": (0x4F, 0x00)}
CW_DISABLE_VOLTAGE, CW_QUICK_STOP, CW_SHUTDOWN, CW_SWITCH_ON, CW_ENABLE, CW_FAULT_RESET = 0, 2, 6, 7, 15, 0x80


def state_of(statusword: int) -> str:
    for name, (mask, value) in STATES.items():
        if statusword & mask == value:
            return name
    return "UNKNOWN"


def load_eds(path: str, node_id: int) -> canopen.ObjectDictionary:
    """Object dictionary of a drive gearbench can use; DriveError listing every problem."""
    return load_model(path, node_id).od


def load_model(path: str, node_id: int, profile_dir=None) -> DriveModel:
    """EDS (as the vendor ships it) + its drive description; DriveError listing every problem."""
    return resolve_or_raise(path, node_id, profile_dir=profile_dir)


def _close(a: float, b: float, rel: float = 1e-3) -> bool:
    return abs(a - b) <= rel * max(abs(a), abs(b), 1e-12)


class CiA402Drive(Drive):
    """One CiA 402 servo on a ``CiA402Network``; SI in, SI out."""

    def __init__(self, network, node: canopen.RemoteNode, config: AxisConfig,
                 model: DriveModel):
        super().__init__(config)
        self.net, self.node, self.model = network, node, model
        self.units: AxisUnits | None = None        # from what the drive reports, set by configure()
        self.modes: dict[str, int | None] = {}     # "velocity"/"torque" -> CiA 402 mode code
        self.verified = False                      # units and limits read back as described
        self.mode: Mode | None = None
        self._mode_code = 0
        self._controlword = 0
        self._has_counter = False   # configure(): a described echo object AND a counter byte on the bus
        self._control_format = struct.Struct("<Hb")   # RPDO1 controlword + modes of operation (CiA 402 types)
        self._position_counts: int | None = None
        self.last_heartbeat: float | None = None
        self._heartbeat_overdue = False
        self.nmt_state: int | None = None
        self.emcy: list[EmcyError] = []
        self.master_watch = "not armed (lockstep: the emulated plant only moves on SYNC)"
        self._master_slot: tuple[int, int] | None = None

    @property
    def where(self) -> str:
        return f"drive '{self.name}' (node {self.node.id} on {self.net.bus_spec})"

    # ----------------------------------------------------------------- SDO
    def _sdo_var(self, index: int, subindex: int):
        obj = self.node.sdo[index]
        return obj if isinstance(obj, SdoVariable) else obj[subindex]

    def sdo_read(self, index: int, subindex: int = 0) -> int:
        try:
            return self._sdo_var(index, subindex).raw
        except SdoCommunicationError as exc:
            raise DriveError(f"{self.where}: no SDO answer reading 0x{index:04X}:{subindex} ({exc}); "
                             f"check power, cabling, bus and node id") from exc
        except SdoAbortedError as exc:
            raise DriveError(f"{self.where}: SDO read 0x{index:04X}:{subindex} refused ({exc})") from exc

    def sdo_write(self, index: int, subindex: int, value: int) -> None:
        try:
            self._sdo_var(index, subindex).raw = value
        except SdoCommunicationError as exc:
            raise DriveError(f"{self.where}: no SDO answer writing 0x{index:04X}:{subindex} ({exc}); "
                             f"check power, cabling, bus and node id") from exc
        except SdoAbortedError as exc:
            shown = mapping_entry(value >> 16, (value >> 8) & 0xFF, value & 0xFF) + \
                f" ({self.model.label(ObjRef(value >> 16, (value >> 8) & 0xFF))}, {value & 0xFF} bits)" \
                if (0x1600 <= index <= 0x17FF or 0x1A00 <= index <= 0x1BFF) and subindex else \
                (f"0x{value:X}" if index < 0x2000 else str(value))
            raise DriveError(f"{self.where}: SDO write {self.model.label(ObjRef(index, subindex))} = {shown} "
                             f"refused ({exc})") from exc

    # ----------------------------------------------------------------- start-up
    def configure(self, heartbeat_ms: int) -> None:
        """PRE-OPERATIONAL configuration by SDO: identity, units, modes, limits, ramps, PDOs.

        Every unit is read from the drive (objects named by the EDS or its description)
        and checked against the profile; limits are written and read back. Any
        disagreement raises DriveError before the drive is enabled.
        """
        m, c, od = self.model, self.config, self.node.object_dictionary
        self.verified = False
        device_type = self.sdo_read(0x1000)
        if device_type & 0xFFFF != 402:
            raise DriveError(f"{self.where}: device type 0x{device_type:08X} is not a CiA 402 drive")
        if 0x1018 in od and m.vendor_id is not None:
            vendor = self.sdo_read(0x1018, 1)
            if vendor != m.vendor_id:
                raise DriveError(f"{self.where}: drive reports vendor id 0x{vendor:08X} (0x1018:01) but "
                                 f"{m.eds} is {m.name} (0x{m.vendor_id:08X}); use the EDS of this drive")
        if m.velocity_set is not None and isinstance(m.velocity_unit, ObjRef):
            self.sdo_write(m.velocity_unit.index, m.velocity_unit.subindex, m.velocity_set)
        values = {ref: self.sdo_read(ref.index, ref.subindex) for ref in unit_objects(m)}
        units, rated_a = axis_units(m, values, self.where, c.counts_per_rev)
        if m.velocity_set is not None and values[m.velocity_unit] != m.velocity_set:
            raise DriveError(f"{self.where}: velocity unit {m.velocity_unit} reads "
                             f"{describe_velocity_code(values[m.velocity_unit])} after writing "
                             f"{describe_velocity_code(m.velocity_set)}; the drive did not take it")
        for ref, want in m.expect.items():
            got = self.sdo_read(ref.index, ref.subindex)
            if isinstance(want, tuple):     # ("equal", other): a factor pair that must be 1:1
                want = self.sdo_read(want[1].index, want[1].subindex)
            if got != want:
                raise DriveError(f"{self.where}: {ref} reads {got}, expected {want} ({m.name}); gearbench reads "
                                 f"positions in encoder increments: set the factor group to 1:1")
        cpr_ref = (f"fixed, {m.description.where('position.counts_per_rev')}" if m.counts_per_rev_fixed is not None
                   else "0x608F" if m.counts_per_rev.index == 0x608F else str(m.counts_per_rev))
        if abs(units.counts_per_rev - c.counts_per_rev) > 1e-9:
            raise DriveError(f"{self.where}: drive reports {units.counts_per_rev:g} counts/rev ({cpr_ref}) but the "
                             f"profile says counts_per_rev: {c.counts_per_rev}; fix the profile or the drive")
        if not _close(rated_a, c.rated_current_a):
            raise DriveError(f"{self.where}: drive reports rated current {rated_a:g} A ({m.rated_current}) but the "
                             f"profile says rated_current_a: {c.rated_current_a}; fix the profile or the drive")
        self._select_modes()
        self._write_limits(units, rated_a)
        self._write_ramps(units, rated_a)
        self.units = units
        self._configure_pdos()
        if 0x1019 in od:   # counter byte only when every drive on the bus takes one (CiA 301)
            self.sdo_write(0x1019, 0, SYNC_OVERFLOW if self.net.sync_counter_byte else 0)
        self.sdo_write(0x1017, 0, heartbeat_ms)
        self.verified = True

    def watch_master(self, master_id: int, timeout_ms: int) -> None:
        """Arm a heartbeat-consumer slot of 0x1016 for the master and set 0x6007 to quick
        stop; ``master_watch`` says what the drive will do if the master goes silent."""
        od = self.node.object_dictionary
        if 0x1016 not in od:
            self.master_watch = "not armed: no 0x1016 in the EDS (keeps its last command if the PC dies)"
            return
        slots = {sub: self.sdo_read(0x1016, sub) for sub in od[0x1016].subindices if sub > 0}
        ours = [sub for sub, v in slots.items() if (v >> 16) & 0x7F == master_id and v & 0xFFFF]
        free = [sub for sub, v in slots.items() if not v & 0xFFFF]
        slot = (ours or free or [None])[0]
        if slot is None:
            self.master_watch = "not armed: every 0x1016 consumer slot is in use"
            return
        self._master_slot = (slot, slots[slot])
        if slots[slot] & 0xFFFF:      # CiA 301: an active entry is cleared before it is changed
            self.sdo_write(0x1016, slot, 0)
        self.sdo_write(0x1016, slot, (master_id << 16) | timeout_ms)
        action = "its abort-connection option (no 0x6007)"
        if 0x6007 in od:
            self.sdo_write(0x6007, 0, ABORT_CONNECTION_QUICK_STOP)
            action = "quick stop (0x6007 = 3)"
        self.master_watch = f"{action} after {timeout_ms} ms without the master's heartbeat"

    def unwatch_master(self) -> None:
        """Give the consumer slot back as it was (a factory setting for another master stays)."""
        slot = getattr(self, "_master_slot", None)
        if slot is not None:
            self.sdo_write(0x1016, slot[0], 0)
            if slot[1] & 0xFFFF:
                self.sdo_write(0x1016, slot[0], slot[1])
            self._master_slot = None

    def _select_modes(self) -> None:
        """Modes from 0x6502 as the drive reports it (or the description): cyclic 9/10 preferred."""
        m, od = self.model, self.node.object_dictionary
        supported = m.supported_modes
        if 0x6502 in od:
            reported = modes_from_bits(self.sdo_read(0x6502))
            if supported is not None and m.description is not None and \
                    m.description.fact("supported_modes", "modes") is not None and \
                    set(reported) != {x for x in supported if x >= 0}:
                raise DriveError(f"{self.where}: 0x6502 reports modes {list(reported)} but {m.description.path} "
                                 f"says {list(supported)}; fix the description or check the firmware")
            # manufacturer modes (negative numbers) have no standard 0x6502 bit: they come from the description
            supported = reported + tuple(x for x in supported or () if x < 0)
        force_profile = self.net.options.get("cyclic") is False
        pick = {k: m.mode_for(k, tuple(x for x in supported or () if not (force_profile and x >= 9)))
                for k in ("velocity", "torque")}
        self.modes = pick
        if any(code in (9, 10) for code in pick.values()) and 0x60C2 in od:
            # interpolation period = SYNC period = 0x60C2:01 x 10^(0x60C2:02) s; the exponent is
            # written too where the drive lets it (the same rule validate applies to the EDS)
            exponent = self.sdo_read(0x60C2, 2)
            exponent = exponent - 256 if exponent > 127 else exponent
            setting = interpolation_setting(self.net.period_s, exponent, self.model.exponent_writable)
            if setting is None:
                raise DriveError(f"{self.where}: SYNC period {self.net.period_s:g} s cannot be written to 0x60C2 "
                                 f"(unit 1e{exponent} s, 0x60C2:02 read-only); choose a period the drive can "
                                 f"interpolate")
            if setting[1] != exponent:
                self.sdo_write(0x60C2, 2, setting[1])
            self.sdo_write(0x60C2, 1, setting[0])

    def _write_limits(self, units: AxisUnits, rated_a: float) -> None:
        """Profile limits written to the drive, then read back: a drive that clamps them is refused."""
        m, c = self.model, self.config
        writes = []
        if m.current_limit is not None:
            per = {"mA": 1e-3, "A": 1.0, "permille_rated": rated_a / 1000.0}[m.current_limit_unit]
            raw = round(c.current_limit_a / per)
            if m.bits(m.current_limit) == 16:
                raw = min(raw, 0xFFFF)
            writes.append((m.current_limit, raw, "current limit"))
        if m.speed_limit is not None:
            writes.append((m.speed_limit, abs(units.velocity_raw(c.speed_limit_rad_s)), "speed limit"))
        for ref, raw, what in writes:
            self.sdo_write(ref.index, ref.subindex, raw)
            got = self.sdo_read(ref.index, ref.subindex)
            if got != raw:
                raise DriveError(f"{self.where}: {what} {ref} reads {got} after writing {raw}; the drive clamps "
                                 f"or refuses the profile's value: lower it or fix the drive's limits")
        if 0x6080 in self.node.object_dictionary:   # max motor speed, velocity units
            top = self.sdo_read(0x6080)
            if units.velocity_rad_s(top) < c.speed_limit_rad_s * (1 - 1e-3):
                raise DriveError(f"{self.where}: max motor speed 0x6080 = {top} ({units.velocity_rad_s(top):.1f} "
                                 f"rad/s) is below the profile's speed_limit_rad_s {c.speed_limit_rad_s:g}; "
                                 f"lower the profile's limit or raise the drive's")

    def _write_ramps(self, units: AxisUnits, rated_a: float) -> None:
        """Profile modes (3/4) ramp toward each setpoint with the drive's ramps: gearbench sets them
        so that a full-range step fits in one SYNC period, i.e. they never shape the waveform."""
        m, c, period = self.model, self.config, self.net.period_s
        if self.modes.get("velocity") == 3:
            accel = c.speed_limit_rad_s / period           # rad/s^2
            for key in ("acceleration", "deceleration"):
                ref = m.ramps.get(key)
                if ref is not None:
                    self._write_checked(ref, min(0xFFFFFFFF, round(accel / units.velocity_rad_s_per_unit)), key)
        if self.modes.get("torque") == 4 and "torque_slope" in m.ramps:
            slope = c.current_limit_a / rated_a * 1000.0 / period   # per-mille of rated torque per s
            self._write_checked(m.ramps["torque_slope"], min(0xFFFFFFFF, round(slope)), "torque slope")

    def _write_checked(self, ref: ObjRef, raw: int, what: str) -> None:
        self.sdo_write(ref.index, ref.subindex, raw)
        got = self.sdo_read(ref.index, ref.subindex)
        if got != raw:
            raise DriveError(f"{self.where}: {what} {ref} reads {got} after writing {raw}; the drive clamps it")

    def _configure_pdos(self) -> None:
        m, od, nid = self.model, self.node.object_dictionary, self.node.id
        self._has_counter = m.sync_echo is not None and self.net.sync_counter_byte
        t1, t2 = m.tpdo_entries(self._has_counter)
        r1, r2 = m.rpdo_entries()
        for comm, mapping, n, cob, trans, entries in ((0x1800, 0x1A00, 0, 0x180, 1, t1), (0x1800, 0x1A00, 1, 0x280, 1, t2),
                                                      (0x1400, 0x1600, 0, 0x200, 255, r1),
                                                      (0x1400, 0x1600, 1, 0x300, 1, r2)):
            self._map(comm, mapping, n, cob + nid, trans, [(ref, m.bits(ref)) for ref in entries])
        for n in (2, 3):
            for comm, base in ((0x1800, 0x180), (0x1400, 0x200)):
                if comm + n in od:
                    self.sdo_write(comm + n, 1, (1 << 31) | (base + 0x100 * n + nid))
        self.tpdo_formats = {0x180 + nid: "<" + "".join(m.fmt(r) for r in t1),
                             0x280 + nid: "<" + "".join(m.fmt(r) for r in t2)}
        self._rpdo_format = struct.Struct("<" + "".join(m.fmt(r) for r in r2))
        self._control_format = struct.Struct("<" + "".join(m.fmt(r) for r in r1))
        self._torque_slot = r2.index(m.torque_setpoint) if m.torque_setpoint in r2 else None
        self._velocity_slot = r2.index(ObjRef(0x60FF)) if ObjRef(0x60FF) in r2 else None

    def _map(self, comm: int, mapping: int, n: int, cob_id: int, trans_type: int, entries) -> None:
        self.sdo_write(comm + n, 1, (1 << 31) | cob_id)        # invalid while remapping (CiA 301)
        comm_obj = self.node.object_dictionary[comm + n]
        if mapping < 0x1A00 and 3 in getattr(comm_obj, "subindices", {}):
            self.sdo_write(comm + n, 3, 0)     # no inhibit time: a SYNC TPDO must answer every SYNC
        self.sdo_write(mapping + n, 0, 0)
        for sub, (ref, bits) in enumerate(entries, start=1):
            self.sdo_write(mapping + n, sub, ref.index << 16 | ref.subindex << 8 | bits)
        self.sdo_write(mapping + n, 0, len(entries))
        self.sdo_write(comm + n, 2, trans_type)
        self.sdo_write(comm + n, 1, cob_id)

    # ----------------------------------------------------------------- RPDOs
    def _send_control(self, controlword: int) -> None:
        self._controlword = controlword
        values = (controlword, self._mode_code)[:len(self._control_format.format) - 1]
        self.net.send(0x200 + self.node.id, self._control_format.pack(*values))

    def _send_targets(self, velocity_raw: int, torque_raw: int) -> None:
        """RPDO2 (target velocity, target torque) in the drive's verified units."""
        if not self.verified:
            raise DriveError(f"{self.where}: no setpoint before the drive's units are verified (start())")
        values = [0] * (len(self._rpdo_format.format) - 1)
        if self._velocity_slot is not None:
            values[self._velocity_slot] = velocity_raw
        if self._torque_slot is not None:
            values[self._torque_slot] = torque_raw
        self.net.send(0x300 + self.node.id, self._rpdo_format.pack(*values))

    def statusword(self) -> int:
        return self.sdo_read(0x6041)

    def _wait_state(self, wanted: tuple[str, ...], timeout_s: float) -> str:
        deadline = time.monotonic() + timeout_s
        while True:
            state = state_of(self.statusword())
            if state in wanted or time.monotonic() > deadline:
                return state
            time.sleep(0.001)

    # ----------------------------------------------------------------- Drive protocol
    def enable(self, mode: Mode) -> None:
        mode = Mode(mode)
        self.mode = mode
        if not self.verified:
            raise DriveError(f"{self.where}: enable before start(): units and limits not verified")
        code = self.modes.get(mode.value)
        if code is None:
            raise DriveError(f"{self.where}: {self.model.name} has no {mode.value} mode gearbench can use "
                             f"(0x6502); " + ("a drive that cannot brake cannot be the output motor"
                                              if mode is Mode.TORQUE else "it cannot turn at a commanded speed"))
        if mode is Mode.TORQUE and self.model.var(self.model.torque_setpoint) is None:
            raise DriveError(f"{self.where}: {self.model.name} has no target torque {self.model.torque_setpoint} "
                             f"(nor a described current setpoint): a drive that cannot brake cannot be the "
                             f"output motor")
        if mode is Mode.TORQUE and self.units.torque_a_per_unit is None:
            raise DriveError(f"{self.where}: target torque 0x6071 to motor current relation not stated for "
                             f"{self.model.name}; describe it (torque.relation) in drivers/")
        self._mode_code = code
        if self.model.mode_by_sdo:    # 0x6060 not PDO-mappable: set once per segment, by SDO
            self.sdo_write(0x6060, 0, code)
        self._send_targets(0, 0)
        state = state_of(self.statusword())
        if state in ("FAULT", "FAULT REACTION ACTIVE"):
            raise DriveError(f"{self.where}: in FAULT (error code 0x{self.sdo_read(0x603F):04X}); "
                             f"reset_fault() before enable")
        if state == "OPERATION ENABLED":   # mode change only
            self._send_control(CW_ENABLE)
        else:
            if state == "QUICK STOP ACTIVE":
                self._send_control(CW_DISABLE_VOLTAGE)
                self._wait_state(("SWITCH ON DISABLED",), self.net.state_timeout_s)
            for cw, target in ((CW_SHUTDOWN, "READY TO SWITCH ON"), (CW_SWITCH_ON, "SWITCHED ON"),
                               (CW_ENABLE, "OPERATION ENABLED")):
                self._send_control(cw)
                reached = self._wait_state((target,), self.net.state_timeout_s)
                if reached != target:
                    raise DriveError(f"{self.where}: stuck in {reached} on the way to {target} "
                                     f"(controlword 0x{cw:04X}); check the drive's error code 0x603F")
        shown = self.sdo_read(0x6061)
        if shown != self._mode_code:
            raise DriveError(f"{self.where}: mode of operation {self._mode_code} not accepted "
                             f"(0x6061 shows {shown}); check 0x6502 supported modes")

    def set_setpoint(self, value: float) -> None:
        if self.mode is Mode.VELOCITY:
            self._send_targets(self.units.velocity_raw(value), 0)
        elif self.mode is Mode.TORQUE:    # a current (A), as target torque in the drive's verified unit
            self._send_targets(0, self.units.torque_raw(value))
        else:
            raise DriveError(f"{self.where}: set_setpoint before enable(mode)")

    def quick_stop(self) -> None:
        self._send_control(CW_QUICK_STOP)

    def disable(self) -> None:
        if self.verified:
            self._send_targets(0, 0)
        self._send_control(CW_DISABLE_VOLTAGE)
        self.mode = None
        state = self._wait_state(("SWITCH ON DISABLED", "FAULT"), self.net.state_timeout_s)
        if state not in ("SWITCH ON DISABLED", "FAULT"):
            raise DriveError(f"{self.where}: still {state} after disable voltage")

    def reset_fault(self) -> None:
        self._send_control(CW_DISABLE_VOLTAGE)
        self._send_control(CW_FAULT_RESET)      # rising edge of bit 7
        state = self._wait_state(("SWITCH ON DISABLED",), self.net.state_timeout_s)
        self._send_control(CW_DISABLE_VOLTAGE)
        if state != "SWITCH ON DISABLED":
            raise DriveError(f"{self.where}: fault reset not accepted, still {state} "
                             f"(error code 0x{self.sdo_read(0x603F):04X})")
        self.emcy.clear()

    def state(self) -> str:
        """CiA 402 state now (SDO read of the statusword)."""
        return state_of(self.statusword())

    # ----------------------------------------------------------------- samples
    def sample(self, index: int, time_s: float, tpdo1: tuple, tpdo2: tuple) -> Sample:
        statusword, position = tpdo1[0], tpdo1[1]
        velocity, current = tpdo2[0], tpdo2[1]
        counts = position if self._position_counts is None else unwrap_int32(self._position_counts, position)
        self._position_counts = counts
        s = self.units
        return Sample(index=index, time_s=time_s, position_rad=s.position_rad(counts),
                      velocity_rad_s=s.velocity_rad_s(velocity), current_a=s.current_a(current),
                      status=statusword, fault=bool(statusword & 0x08))
