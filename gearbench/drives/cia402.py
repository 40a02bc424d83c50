"""CANopen CiA 402 servo drives (master side), with ``canopen`` + ``python-can``.

Start-up (``start``), per drive, in NMT PRE-OPERATIONAL by SDO. Each drive is its
vendor's EDS/DCF as shipped joined with its drive description in ``drivers/``
(``gearbench.drives.description``): which objects carry what, in which unit.

- units read from the drive, never assumed: encoder increments per revolution
  (0x608F or the described object), velocity unit (0x60A9 or described), rated
  current (0x6075 or described), current actual (0x6078 per-mille of rated, or the
  described object and unit); each checked against the profile, factor groups
  checked 1:1; a disagreement refuses the drive before it is enabled;
- modes from 0x6502 as the drive reports it: cyclic synchronous velocity/torque
  (9/10, interpolation period 0x60C2 = SYNC period) where present, else profile
  modes 3/4 with their ramps (0x6083/0x6084/0x6087) written so they never bind;
- limits written from the profile and read back (current limit, 0x607F), 0x6080 checked;
- PDO mapping with each object's own size (all other PDOs disabled, TPDO inhibit time 0)::

    TPDO1 0x180+id  type 1   statusword 0x6041 | position actual 0x6064 [| SYNC echo]
    TPDO2 0x280+id  type 1   velocity actual 0x606C | current actual [| SYNC echo]
    RPDO1 0x200+id  type 255 controlword 0x6040 | modes of operation 0x6060   (applied at once)
    RPDO2 0x300+id  type 1   target velocity 0x60FF | target torque 0x6071     (latched at SYNC)

  A SYNC counter echo is mapped only where the description names one (the
  reference drive's 0x2001; in vendors' files 0x2001 is something else) and only
  when the SYNC carries a counter byte, which it does only if every drive on the
  bus has 0x1019 (CiA 301; 0x1019 is set to 240 then, else 0). Without an echo,
  time is the master's own SYNC count x period. Both drives latch setpoints on the
  same SYNC (RPDO2 synchronous); state-machine commands are events (RPDO1 async) and
  their result is confirmed by an SDO read of the statusword.
- heartbeat producer 0x1017; then NMT OPERATIONAL.

Units at the interface: SI (``gearbench.drives.scaling.AxisUnits``); torque
setpoints are motor currents, sent as 0x6071 per the described torque relation.

Sampling (``_sample``): one SYNC, wait for both TPDOs of every drive for that SYNC;
``index`` = SYNC count since ``start``, ``time_s`` = index x period.

- Lockstep (the emulated bench, whose physics advances one period per SYNC): no
  sample can be missed, so the master waits for every answer, bounded only by the
  drive-silence timeout. If an answer is still missing after a short wait, an SDO
  read of the drive is the barrier: the drive handles it after the SYNC, so when its
  answer is in, every TPDO sent before it is in too and a frame still missing was
  dropped on the bus (counted lost, never filled in).
- Paced (real drives): SYNC every period on the wall clock; a SYNC whose frames are
  not all in by the next slot is counted in ``lost_samples``. Frames are matched to
  their SYNC by the counter echo where the drive has one, otherwise by the bus's
  receive timestamp (a frame received before this SYNC was sent answers an earlier one).

Supervision (``gearbench.drives.supervision``): any frame of a node is proof of life;
silence is measured on a clock that stops while the host is stalled, and a suspected
drive is probed by SDO before the verdict. EMCY, a fault bit in the statusword, a
drive that left NMT OPERATIONAL or one silent for ``timeout_s`` -> drives stopped and
``BenchFault`` naming node and bus. Host stalls are counted (``supervision()``).
"""
from __future__ import annotations

import collections
import struct
import threading
import time

import canopen
from canopen.emcy import EmcyError
from canopen.sdo import SdoAbortedError, SdoCommunicationError, SdoVariable

from ..errors import BenchFault, DriveError
from .shipped import shipped_driver
from .base import AxisConfig, Drive, DriveNetwork, Mode, Sample
from .buses import open_bus, parse_bus
from .supervision import HostStallMonitor, Liveness
from .sync_producer import start_sync_producer
from .description import (DriveModel, ObjRef, axis_units, describe_velocity_code, modes_from_bits,
                          resolve_or_raise, unit_objects)
from .scaling import AxisUnits, unwrap_int32

DEFAULT_EDS = str(shipped_driver("cia402-servo.eds"))
SYNC_OVERFLOW = 240
NMT_OPERATIONAL_STATE = 0x05          # the heartbeat byte of a node in OPERATIONAL (CiA 301)
ABORT_CONNECTION_QUICK_STOP = 3       # 0x6007: quick stop on a communication loss (CiA 402)
STARVED_LIMIT_FACTOR = 10    # an emulated drive starved of CPU may be silent this many limits, not more
HEALTH_PERIOD_S = 0.01       # supervision verdicts at most this often, not per sample: EMCY, NMT and
                             # silence limits are tens of ms or more, and per sample it cost ~20 us
READY_KEEP_S = 2.0           # complete samples kept for a sample loop that fell behind (beyond: lost)
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


def load_model(path: str, node_id: int) -> DriveModel:
    """EDS (as the vendor ships it) + its drive description; DriveError listing every problem."""
    return resolve_or_raise(path, node_id)


def _close(a: float, b: float, rel: float = 1e-3) -> bool:
    return abs(a - b) <= rel * max(abs(a), abs(b), 1e-12)


class CiA402Drive(Drive):
    """One CiA 402 servo on a ``CiA402Network``; SI in, SI out."""

    def __init__(self, network: "CiA402Network", node: canopen.RemoteNode, config: AxisConfig,
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
            raise DriveError(f"{self.where}: SDO write 0x{index:04X}:{subindex} = {value} refused ({exc})") from exc

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
        units, rated_a = axis_units(m, values, self.where)
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
        cpr_ref = "0x608F" if m.counts_per_rev.index == 0x608F else str(m.counts_per_rev)
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
                    m.description.fact("supported_modes", "modes") is not None and set(reported) != set(supported):
                raise DriveError(f"{self.where}: 0x6502 reports modes {list(reported)} but {m.description.path} "
                                 f"says {list(supported)}; fix the description or check the firmware")
            supported = reported
        force_profile = self.net.options.get("cyclic") is False
        pick = {k: m.mode_for(k, tuple(x for x in supported or () if not (force_profile and x >= 9)))
                for k in ("velocity", "torque")}
        self.modes = pick
        if any(code in (9, 10) for code in pick.values()) and 0x60C2 in od:
            # interpolation period = SYNC period, in 10^(0x60C2:02) s
            exponent = self.sdo_read(0x60C2, 2)
            exponent = exponent - 256 if exponent > 127 else exponent
            value = round(self.net.period_s / 10.0 ** exponent)
            if not 1 <= value <= 255 or abs(value * 10.0 ** exponent - self.net.period_s) > 1e-9:
                raise DriveError(f"{self.where}: SYNC period {self.net.period_s:g} s cannot be written to 0x60C2 "
                                 f"(unit 1e{exponent} s); choose a period the drive can interpolate")
            self.sdo_write(0x60C2, 1, value)

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
        self.net.send(0x200 + self.node.id, self._control_format.pack(controlword, self._mode_code))

    def _send_targets(self, velocity_raw: int, torque_raw: int) -> None:
        """RPDO2 (target velocity, target torque) in the drive's verified units."""
        if not self.verified:
            raise DriveError(f"{self.where}: no setpoint before the drive's units are verified (start())")
        self.net.send(0x300 + self.node.id, self._rpdo_format.pack(velocity_raw, torque_raw))

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
        if mode is Mode.TORQUE and self.units.torque_a_per_unit is None:
            raise DriveError(f"{self.where}: target torque 0x6071 to motor current relation not stated for "
                             f"{self.model.name}; describe it (torque.relation) in drivers/")
        self._mode_code = code
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


class CiA402Network(DriveNetwork):
    """CiA 402 drives on one CAN bus, sampled on SYNC.

    Options (profile ``bus:`` section): ``bus`` ("udp_multicast:239.74.163.2:43113",
    "socketcan:can0", "virtual:bench"), ``heartbeat_ms`` (100), ``timeout_s`` (0.5:
    a drive silent this long is a fault), ``frame_grace_s`` (0.02: once a SYNC's first
    TPDO arrived, its other TPDOs are lost if not in by then), ``sdo_timeout_s`` (0.3), ``cyclic`` (None: cyclic
    synchronous 9/10 where the drive has them, else profile modes 3/4 with ramps set by
    gearbench; False: profile modes only), ``bus_kwargs`` (extra python-can args),
    ``master_node_id`` (127) and ``master_timeout_ms`` (1000; 0 = off): against real
    drives (not lockstep) the master produces a heartbeat and arms each drive's
    heartbeat consumer (0x1016) with its abort-connection option (0x6007) set to quick
    stop, so a tester PC that dies or is unplugged stops its drives by itself.
    """

    family = "cia402"

    def __init__(self, bus: str = "udp_multicast:239.74.163.2", *, heartbeat_ms: int = 100,
                 timeout_s: float = 0.5, state_timeout_s: float = 0.5, frame_grace_s: float = 0.02,
                 sdo_timeout_s: float = 0.3, cyclic: bool | None = None, lockstep: bool = False,
                 bus_kwargs: dict | None = None, master_node_id: int = 127, master_timeout_ms: int = 1000,
                 **options):
        super().__init__(bus=bus, cyclic=cyclic, **options)
        # Real drives latch on SYNC, so SYNC must come every period on the wall clock for
        # time_s = count x period to hold. An emulated bench (lockstep) advances its physics
        # one period per SYNC and may be driven as fast as it answers.
        self.lockstep = bool(lockstep)
        self.late_syncs = 0
        self._t0: float | None = None
        self.bus_spec = parse_bus(bus)
        self.bus_kwargs = bus_kwargs or {}
        self.heartbeat_ms = heartbeat_ms
        self.timeout_s = timeout_s
        self.state_timeout_s = state_timeout_s
        self.frame_grace_s = frame_grace_s
        self.sdo_timeout_s = sdo_timeout_s
        self.master_node_id = int(master_node_id)
        self.master_timeout_ms = int(master_timeout_ms)
        self._master_heartbeat = None   # the periodic send task (the kernel's BCM on socketcan)
        self.network: canopen.Network | None = None
        self.sync_count = 0
        self._cv = threading.Condition()
        self._expect = 0
        self._got: dict[int, tuple] = {}
        self._formats: dict[int, tuple[struct.Struct, bool]] = {}
        self._faults: list[str] = []
        self.stalls = HostStallMonitor()
        self.liveness = Liveness(self.stalls)
        self.probes = 0                 # SDO barriers/probes sent (lockstep drops, suspected silence)
        self.dropped_frames = 0         # answers known to be lost on the bus
        self.late_frames = 0            # answers that arrived after their SYNC's slot (discarded)
        self.heartbeat_gaps = 0         # heartbeats overdue while the drive was otherwise heard
        self.starved_deferrals = 0      # silence verdicts deferred: the emulating process was runnable
        self._sync_sent_wall = 0.0
        # (SYNC number, its complete answers) in SYNC order, put by the receive thread the moment the
        # last answer is in, taken by the sample loop: it wakes once per sample, or not at all when behind
        self._ready: collections.deque = collections.deque()
        self._produced = False          # paced by a SYNC producer: answers go to _ready
        self._health_due = 0.0
        self._started = False

    # ----------------------------------------------------------------- lifecycle
    def open(self) -> None:
        bus = open_bus(self.bus_spec, **self.bus_kwargs)
        self.network = canopen.Network(bus)
        self.network.NOTIFIER_CYCLE = 0.1    # close() waits for one notifier cycle
        self.network.connect()

    def send(self, cob_id: int, data: bytes) -> None:
        self.network.send_message(cob_id, data)

    def add_drive(self, config: AxisConfig) -> CiA402Drive:
        if self.network is None:
            raise DriveError("CiA402Network.add_drive before open()")
        if config.name in self.drives:
            raise DriveError(f"axis '{config.name}' added twice; axis names must be unique")
        model = load_model(config.description or DEFAULT_EDS, config.address)
        node = canopen.RemoteNode(config.address, model.od)
        node.sdo.RESPONSE_TIMEOUT = self.sdo_timeout_s
        self.network.add_node(node)
        drive = CiA402Drive(self, node, config, model)
        self.drives[config.name] = drive
        self.network.subscribe(0x700 + node.id, self._on_heartbeat_of(drive))
        self.network.subscribe(0x80 + node.id, self._on_emcy_of(drive))
        self.network.subscribe(0x580 + node.id, self._on_any_of(node.id))   # SDO answers are life too
        return drive

    def start(self, period_s: float) -> None:
        if not self.drives:
            raise DriveError("CiA402Network.start with no drive; add_drive() first")
        self.period_s = period_s
        for d in self.drives.values():
            d.node.nmt.state = "PRE-OPERATIONAL"
        # CiA 301: a SYNC carries a counter byte only if every consumer expects one (0x1019 > 1);
        # a drive without 0x1019 may answer a wrong-length SYNC with EMCY 0x8240
        self.sync_counter_byte = all(0x1019 in d.node.object_dictionary for d in self.drives.values())
        for d in self.drives.values():
            d.configure(self.heartbeat_ms)
            for cob_id, fmt in d.tpdo_formats.items():
                self._formats[cob_id] = (struct.Struct(fmt), d._has_counter)
                self.network.subscribe(cob_id, self._on_tpdo)
        self._watch_master()
        for d in self.drives.values():
            d.node.nmt.state = "OPERATIONAL"
        wait_s = 3 * self.heartbeat_ms / 1000.0 + 0.2
        deadline = time.monotonic() + wait_s
        while any(d.last_heartbeat is None or d.nmt_state != 5 for d in self.drives.values()):
            if time.monotonic() > deadline:
                bad = [d.where for d in self.drives.values() if d.nmt_state != 5]
                raise DriveError(f"{', '.join(bad)}: no heartbeat in NMT OPERATIONAL within {wait_s:.1f} s")
            time.sleep(0.005)
        self.sync_count = 0
        self._last_index = 0
        self.stalls.start()
        self.liveness.reset(d.node.id for d in self.drives.values())
        self._started = True

    def _watch_master(self) -> None:
        """Real drives watch the master's heartbeat (CiA 301 0x1016) and quick-stop when it
        stops (CiA 402 0x6007 = 3): the one stop that works when the tester PC itself dies.
        Not in lockstep: an emulated plant only moves on SYNC, so a dead master freezes it."""
        if self.lockstep or self.master_timeout_ms <= 0:
            return
        if any(d.node.id == self.master_node_id for d in self.drives.values()):
            raise DriveError(f"master_node_id {self.master_node_id} is also a drive's node id on "
                             f"{self.bus_spec}; set bus option master_node_id to a free id (1..127)")
        period_ms = max(10, min(self.heartbeat_ms, self.master_timeout_ms // 4))
        self._master_heartbeat = self.network.send_periodic(
            0x700 + self.master_node_id, [NMT_OPERATIONAL_STATE], period_ms / 1000.0)
        for d in self.drives.values():
            d.watch_master(self.master_node_id, self.master_timeout_ms)

    def watch_process(self, pid: int) -> None:
        """The drives are emulated by process ``pid`` on this host (``--sim``): its
        run-queue waits are host stalls, not drive silence."""
        from .supervision import RunQueueMonitor

        self.liveness.drive_monitors.append(RunQueueMonitor(pid).start())

    def acquisition_threads(self) -> list[int]:
        notifier = getattr(self.network, "notifier", None)
        readers = getattr(notifier, "_readers", []) if notifier is not None else []
        threads = [r for r in readers if hasattr(r, "native_id") and r.is_alive()]   # not once the producer receives
        ids = self.sync_producer.native_ids() if self.sync_producer is not None else []
        if self.stalls._thread is not None:
            threads.append(self.stalls._thread)
        # the master's heartbeat, where a Python thread sends it (not the kernel's BCM): a
        # starved heartbeat would make the drives quick-stop a good unit
        sender = getattr(getattr(self._master_heartbeat, "_task", None), "thread", None)
        if sender is not None and hasattr(sender, "native_id"):
            threads.append(sender)
        return ids + [t.native_id for t in threads]

    def supervision(self) -> dict:
        """What supervision saw: host stalls tolerated, probes, dropped/late frames."""
        drive_stalls = [m.summary() for m in self.liveness.drive_monitors]
        emulated = {"emulator_stalls": sum(d["host_stalls"] for d in drive_stalls),
                    "emulator_stall_max_s": max((d["host_stall_max_s"] for d in drive_stalls), default=0.0)} \
            if drive_stalls else {}
        return {**self.stalls.summary(), **emulated, "sdo_probes": self.probes, "dropped_frames": self.dropped_frames,
                "late_frames": self.late_frames, "heartbeat_gaps": self.heartbeat_gaps,
                "starved_deferrals": self.starved_deferrals,
                # where a drive echoes no SYNC counter, its samples are matched to SYNCs by arrival
                # order and the bus's receive time only: flagged so a reader of the data knows
                "sync_counter_echo": {n: bool(d._has_counter) for n, d in self.drives.items()},
                "late_syncs": self.late_syncs,
                "if_the_master_dies": {n: d.master_watch for n, d in self.drives.items()}}

    # ----------------------------------------------------------------- receive (notifier thread)
    def _on_tpdo(self, cob_id, data, timestamp):
        fmt, has_counter = self._formats[cob_id]
        self.liveness.heard(cob_id & 0x7F)
        if len(data) != fmt.size:
            with self._cv:    # a mapping we did not configure: never guess what the bytes mean
                self._faults.append(f"TPDO 0x{cob_id:03X} of node {cob_id & 0x7F} has {len(data)} bytes, "
                                    f"expected {fmt.size} for the mapping gearbench configured")
                self._cv.notify()
            return
        values = fmt.unpack_from(data)
        with self._cv:
            late = values[-1] != self._expect if has_counter else \
                bool(timestamp) and timestamp < self._sync_sent_wall   # received before this SYNC went out
            if late:
                self.late_frames += 1
                return
            got = self._got
            got[cob_id] = values
            if len(got) == len(self._formats):
                if self._produced:
                    self._ready.append((self._sync_number, got))
                    self._got = {}      # complete: a repeated frame before the next SYNC is not a new sample
                self._cv.notify()       # the sample loop wakes once, when the sample is complete

    def _on_any_of(self, node_id: int):
        def on_frame(can_id, data, timestamp):
            self.liveness.heard(node_id)
        return on_frame

    def _on_heartbeat_of(self, drive: CiA402Drive):
        def on_heartbeat(can_id, data, timestamp):
            drive.last_heartbeat = time.monotonic()
            drive.nmt_state = data[0] & 0x7F if data else None
            self.liveness.heard(drive.node.id, drive.last_heartbeat)
        return on_heartbeat

    def _on_emcy_of(self, drive: CiA402Drive):
        def on_emcy(can_id, data, timestamp):
            if len(data) < 8:
                return
            code, register, extra = struct.unpack("<HB5s", bytes(data[:8]))
            entry = EmcyError(code, register, extra, timestamp)
            self.liveness.heard(drive.node.id)
            drive.emcy.append(entry)
            if code & 0xFF00:
                with self._cv:
                    self._faults.append(f"{drive.where}: EMCY 0x{code:04X} ({entry.get_desc()}), "
                                        f"error register 0x{register:02X}")
        return on_emcy

    # ----------------------------------------------------------------- sampling
    @property
    def silence_limit_s(self) -> float:
        """A drive heard from by no frame for this long (host stalls excluded) is silent."""
        return max(self.timeout_s, 2.5 * self.heartbeat_ms / 1000.0)

    def _check_health(self) -> None:
        """Faults reported by the drives, NMT state, and silence (probed before the verdict)."""
        with self._cv:
            problems, self._faults = self._faults, []     # swapped under the lock: no EMCY lost
        heartbeat_s = 3 * self.heartbeat_ms / 1000.0
        now = time.monotonic()
        for d in self.drives.values():
            if d.nmt_state not in (None, 5):
                problems.append(f"{d.where}: left NMT OPERATIONAL (state {d.nmt_state})")
            if d.last_heartbeat is not None:
                overdue = now - d.last_heartbeat - self.stalls.stalled_since(d.last_heartbeat) > heartbeat_s
                if overdue and not d._heartbeat_overdue:
                    self.heartbeat_gaps += 1     # counted; the verdict is on silence (any frame)
                d._heartbeat_overdue = overdue
            # suspected at half the limit, probed, condemned only if still silent beyond the limit
            if self.liveness.silent_s(d.node.id, now) > self.silence_limit_s / 2 and not self._probe(d):
                self.liveness.poll()      # the stall records must be current before a verdict
                silent = self.liveness.silent_s(d.node.id)
                if silent > self.silence_limit_s and self.liveness.starved() and \
                        silent < STARVED_LIMIT_FACTOR * self.silence_limit_s:
                    self.starved_deferrals += 1    # an emulated drive waiting for this host's CPU
                    continue
                if silent > self.silence_limit_s:
                    problems.append(f"{d.where}: silent for {silent:.2f} s (no heartbeat, PDO or SDO answer; "
                                    f"limit {self.silence_limit_s:g} s, host stalls excluded)")
        if problems:
            self._fault("; ".join(problems))

    def _probe(self, d: CiA402Drive, timeout_s: float | None = None) -> bool:
        """SDO read of the statusword: True if the drive answered (it is alive)."""
        self.probes += 1
        sdo = d.node.sdo
        old = sdo.RESPONSE_TIMEOUT
        sdo.RESPONSE_TIMEOUT = timeout_s or max(self.sdo_timeout_s, self.silence_limit_s / 2)
        try:
            d.sdo_read(0x6041)
            return True
        except DriveError:
            return False
        finally:
            sdo.RESPONSE_TIMEOUT = old

    def _fault(self, text: str) -> None:
        stopped = self.stop_all()
        exc = BenchFault(f"{text}; {stopped}")
        exc.stop_report = stopped     # the drives were stopped (and that was verified) here
        raise exc

    def _complete(self) -> bool:
        return len(self._got) == len(self._formats)

    def _sample(self) -> dict[str, Sample]:
        if not self._started:
            raise DriveError("CiA402Network.sample before start(period_s)")
        since = time.monotonic()
        while True:
            now = time.monotonic()
            if self._faults or now >= self._health_due:     # a reported fault at once, the rest every 10 ms
                self._health_due = now + HEALTH_PERIOD_S
                self._check_health()
            if self._paced_by_producer():   # SYNC from the kernel's broadcast manager or a SYNC thread
                got = self._wait_produced()
            else:
                if not self.lockstep:
                    self._pace()
                self.sync_count += 1
                counter = (self.sync_count - 1) % SYNC_OVERFLOW + 1
                with self._cv:
                    self._expect, self._got = counter, {}
                    self._sync_sent_wall = time.time()
                self.send_sync(counter)
                got = self._wait_lockstep() if self.lockstep else self._wait_paced()
            if got is not None:
                return self._build(got)
            # this SYNC is lost (the base class counts the index gap). Drives that are alive but
            # never answer a SYNC in time would lose every sample: bounded like silence
            stuck = time.monotonic() - since - self.stalls.stalled_since(since)
            if stuck > self.silence_limit_s:
                with self._cv:
                    missing = sorted({cob & 0x7F for cob in self._formats if cob not in self._got})
                names = [d.where for d in self.drives.values() if d.node.id in missing] or ["the drives"]
                self._fault(f"{', '.join(names)}: no complete answer to any SYNC for {stuck:.2f} s "
                            f"(alive, but every answer missing or too late for its SYNC period "
                            f"{self.period_s * 1e3:g} ms; {self.lost_samples + self.sync_count - (self._last_index or 0)} "
                            f"samples lost so far)")

    def _wait_lockstep(self) -> dict | None:
        """Every answer, however late; None only when a frame is known dropped."""
        with self._cv:
            if self._cv.wait_for(self._complete, 0.02):
                return dict(self._got)
        while True:
            self._check_health()
            with self._cv:
                missing = {cob & 0x7F for cob in self._formats if cob not in self._got}
            for d in self.drives.values():
                if d.node.id in missing and not self._probe(d):
                    break       # no answer yet: the silence check above decides
            else:
                with self._cv:   # every drive answered the barrier: what is still missing was dropped
                    if self._complete():
                        return dict(self._got)
                    self.dropped_frames += len(self._formats) - len(self._got)
                    return None
            with self._cv:
                if self._cv.wait_for(self._complete, 0.01):
                    return dict(self._got)

    def _wait_paced(self) -> dict | None:
        """The answers that arrive before the next SYNC slot; None if any is missing."""
        slot_end = self._t0 + (self.sync_count + 1) * self.period_s - 1e-4
        with self._cv:
            self._cv.wait_for(self._complete, max(0.0, slot_end - time.perf_counter()))
            if self._complete():
                return dict(self._got)
            self.dropped_frames += len(self._formats) - len(self._got)
            return None

    def send_sync(self, counter: int) -> None:
        """One SYNC; the counter byte only where every drive has 0x1019 (CiA 301)."""
        self.network.send_message(0x80, bytes([counter]) if self.sync_counter_byte else b"")

    # -- paced mode: SYNC from a producer (gearbench.drives.sync_producer), option sync: auto|kernel|thread|loop
    sync_producer = None
    _sync_number = 0

    def _paced_by_producer(self) -> bool:
        """Paced and not ``sync: loop``: start the producer once (kernel BCM on socketcan, else a thread)."""
        kind = self.options.get("sync", "auto")
        if self.lockstep or kind == "loop":
            return False
        if self.sync_producer is None:
            self._produced = True
            try:
                self.sync_producer = start_sync_producer(self.network, self.period_s, SYNC_OVERFLOW
                                                         if self.sync_counter_byte else None, self._begin_sync, kind,
                                                         receive=self.options.get("receive", "cyclic") == "cyclic")
            except (ValueError, OSError) as exc:
                raise DriveError(f"bus {self.bus_spec}: cannot start the SYNC producer ({exc})") from exc
        return True

    def _begin_sync(self, number: int, counter: int | None, wall_s: float) -> None:
        """Producer callback, before any answer to SYNC ``number`` can arrive. A SYNC whose
        answers were not all in before this one is lost (its complete answers went to
        ``_ready`` as the last one arrived)."""
        with self._cv:
            if self._sync_number and self._got:
                self.dropped_frames += len(self._formats) - len(self._got)
            self._sync_number, self._expect, self._got, self._sync_sent_wall = number, counter, {}, wall_s
            keep = max(256, round(READY_KEEP_S / self.period_s))
            while len(self._ready) > keep:       # a sample loop that far behind loses the oldest
                self._ready.popleft()

    def _discard_backlog(self) -> None:
        with self._cv:
            self._ready.clear()

    def _wait_produced(self) -> dict | None:
        """The next SYNC whose answers were all in before the SYNC after it (the bus's order
        decides, not how late this loop is); SYNCs without them are gaps: counted lost.
        None when none completed within a supervision period (the caller judges that)."""
        p = self.sync_producer
        with self._cv:
            if self._ready or self._cv.wait_for(lambda: self._ready, HEALTH_PERIOD_S):
                number, got = self._ready.popleft()
                self.sync_count, self.late_syncs = number, p.late
                return got
        if p.idle_s() > self.silence_limit_s:     # outside the lock: stopping the drives needs the receiver
            self._fault(f"no SYNC seen on {self.bus_spec} for {self.silence_limit_s:g} s ({p.kind} producer)")
        return None

    def _pace(self) -> None:
        """Wait for this SYNC's slot on the wall clock. A host that fell more than half
        a period behind skips the missed slots: they count as lost samples, so the
        time base stays SYNC count x period instead of silently stretching."""
        now = time.perf_counter()
        if self._t0 is None:
            self._t0 = now - self.sync_count * self.period_s
        target = self._t0 + self.sync_count * self.period_s
        late = now - target
        if late > self.period_s / 2:
            missed = int(late / self.period_s + 0.5)
            self.sync_count += missed
            self.late_syncs += missed
            return
        if target > now:
            time.sleep(target - now)   # sleep, never spin: at SCHED_FIFO a spin would starve the receiver

    def _build(self, got: dict[int, tuple]) -> dict[str, Sample]:
        index = self.sync_count
        time_s = index * self.period_s
        out = {}
        for name, d in self.drives.items():
            nid = d.node.id
            out[name] = d.sample(index, time_s, got[0x180 + nid], got[0x280 + nid])
        faulted = [self.drives[n].where for n, s in out.items() if s.fault]
        if faulted:
            with self._cv:     # an EMCY usually arrived first and names the code
                emcy, self._faults = self._faults, []
            self._fault("; ".join(emcy + [f"{', '.join(faulted)}: FAULT in statusword at sample {index}"]))
        return out

    def _close(self) -> None:
        self.stalls.stop()
        for m in self.liveness.drive_monitors:
            m.stop()
        if self.sync_producer is not None:
            self.sync_producer.stop()
            self.sync_producer = None
        if self.network is not None:
            try:
                for d in self.drives.values():
                    try:
                        d.unwatch_master()     # an orderly end is not a lost master
                    except Exception:
                        pass
                if self._master_heartbeat is not None:
                    self._master_heartbeat.stop()
                    self._master_heartbeat = None
                for d in self.drives.values():
                    try:
                        d.node.nmt.state = "PRE-OPERATIONAL"
                    except Exception:
                        pass
            finally:
                self.network.disconnect()
                self.network = None
