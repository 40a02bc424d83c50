"""CANopen front-end of the emulated bench: one CiA 402 servo drive per axis, playing
the drive model the profile names.

Each node serves the object dictionary of *its* EDS (the vendor's file as shipped,
or ``drivers/cia402-servo.eds``) joined with its drive description
(``gearbench.drives.description``): identity, supported modes, the unit objects
(encoder resolution, 0x60A9 velocity unit, rated current), the current object in
its unit, PDO limits. An object missing from the EDS is missing here (SDO abort
0x06020000), a read-only one refuses writes, a mapping the real drive could not
hold is refused (0x06040041 not mappable, 0x06040042 longer than 8 bytes), a unit
object takes only the values the description allows (0x06090030).

Built on canopen's ``LocalNode`` (SDO server, NMT slave) plus what it lacks
(upstream #145, #558, #520):

- SYNC: the world advances one period per SYNC (lockstep), then every node in NMT
  OPERATIONAL sends its synchronous TPDOs from the mapping *currently* in its object
  dictionary. A SYNC counter (0x1019 > 1) that jumps advances the missed periods
  too, so drive time stays SYNC count x period. A SYNC with a counter byte sent to a
  node whose 0x1019 is 0 or absent gets EMCY 0x8240 "unexpected SYNC data length"
  (CiA 301), as CANopenNode-based drives answer it.
- RPDOs: decoded with the current mapping; transmission type 255 applies at once,
  1-240 at the next SYNC (CiA 301). Controlword, modes of operation, target velocity
  and target torque go to the node's ``Cia402Axis`` in SI (also when written by SDO).
- Profile modes 3/4 ramp with 0x6083/0x6084/0x6087 as the dictionary holds them.
- EMCY on faults and on fault reset; heartbeat producer from 0x1017.
- Heartbeat consumer from 0x1016 (CiA 301): once a watched producer (the master) has
  been heard, silence beyond its consumer time sends EMCY 0x8130 and applies 0x6007
  (1 fault, 2 disable voltage, 3 quick stop) to an enabled axis.
- Fault options from ``EmulatedBench``: TPDO drop rate, muted nodes.
"""
from __future__ import annotations

import math
import struct
import threading
import time

import can
import canopen
from canopen.objectdictionary import ODVariable
from canopen.sdo import SdoAbortedError

from ..drives.buses import BusSpec, open_bus
from ..drives.description import DriveModel, ObjRef, axis_units, modes_to_bits, resolve, unit_objects
from ..errors import DriveError
from ..drives.shipped import shipped_driver
from .bench import EmulatedBench
from .cia402_axis import Cia402Axis

DEFAULT_EDS = str(shipped_driver("cia402-servo.eds"))
NMT_OPERATIONAL = 5
PDO_INVALID = 1 << 31
ABORT_NOT_MAPPABLE, ABORT_PDO_LENGTH, ABORT_VALUE_RANGE = 0x06040041, 0x06040042, 0x06090030
EMCY_SYNC_LENGTH = 0x8240
EMCY_HEARTBEAT = 0x8130        # CiA 301: life guard / heartbeat error
ABORT_ACTIONS = {2: 0x0000, 3: 0x0002}   # 0x6007 -> controlword: disable voltage, quick stop
CONSUMER_STALL_S = 0.05        # the consumer judges silence only while this process keeps up


class _ReceiveLag(can.Listener):
    """How far behind the bus this process handles frames (receive time -> handled):
    a heartbeat still queued behind a backlog of SYNCs is not a silent master."""

    def __init__(self):
        self.lag_s = 0.0

    def on_message_received(self, msg) -> None:
        self.lag_s = time.time() - msg.timestamp if msg.timestamp else 0.0
DEVICE_TYPE_SERVO = 0x00020192


class _Pdo:
    """One PDO's communication + mapping, as currently configured in the dictionary."""

    __slots__ = ("cob_id", "trans_type", "entries", "countdown")

    def __init__(self, cob_id: int, trans_type: int, entries: list[ODVariable]):
        self.cob_id, self.trans_type, self.entries, self.countdown = cob_id, trans_type, entries, trans_type


class DriveNode(canopen.LocalNode):
    """A LocalNode wired to one ``Cia402Axis``, playing ``model`` (EDS + description)."""

    def __init__(self, node_id: int, eds: str, bench: EmulatedBench, axis: Cia402Axis,
                 model: DriveModel | None = None, profile_dir=None):
        super().__init__(node_id, eds)
        self.bench, self.axis = bench, axis
        self.model = m = model if model is not None else resolve(eds, node_id, profile_dir=profile_dir)
        self.units = None
        self.tpdos: list[_Pdo] = []
        self.rpdos: dict[int, _Pdo] = {}
        self.pending: list[tuple[int, int, int]] = []  # (index, subindex, value) of sync RPDOs
        self.target_writes = 0                          # setpoints received (tests: none before verification)
        self.sync_length_errors = 0
        self._loading = True
        od = self.object_dictionary
        self.live: dict[ObjRef, int] = {ObjRef(i): 0 for i in (0x6041, 0x6061, 0x6064, 0x606C, 0x6077, 0x603F, 0x1001)
                                        if i in od}
        for ref in (m.current, m.sync_echo):
            if ref is not None and m.var(ref) is not None:
                self.live[ref] = 0
        self._fill_defaults()
        if 0x1000 in od:
            self.set_raw(0x1000, 0, m.device_type if m.device_type is not None else DEVICE_TYPE_SERVO)
        if 0x1018 in od:
            for sub, value in ((1, m.vendor_id), (2, m.product_code)):
                if value is not None and sub in od[0x1018].subindices:
                    self.set_raw(0x1018, sub, value)
        modes = m.supported_modes if m.supported_modes is not None else (3, 4, 9, 10)
        axis.supported_modes = tuple(modes)
        if m.torque_mode is not None:      # a described (manufacturer) current mode plays as torque control
            axis.mode_kinds = {**axis.mode_kinds, m.torque_mode: "torque"}
        if 0x6502 in od:
            self.set_raw(0x6502, 0, modes_to_bits(modes))
        if m.counts_per_rev is not None:
            if m.counts_per_rev.index == 0x608F:
                self.set_raw(0x608F, 1, axis.counts_per_rev)
                self.set_raw(0x608F, 2, 1)
            else:
                self.set_raw(m.counts_per_rev.index, m.counts_per_rev.subindex, axis.counts_per_rev)
        for ref, value in m.expect.items():
            if not isinstance(value, tuple):
                self.set_raw(ref.index, ref.subindex, value)
        if isinstance(m.velocity_unit, ObjRef) and self.raw(m.velocity_unit.index, m.velocity_unit.subindex) == 0:
            self.set_raw(m.velocity_unit.index, m.velocity_unit.subindex, 0x00B44700)   # rpm if the EDS says nothing
        if m.rated_current is not None:
            self.set_raw(m.rated_current.index, m.rated_current.subindex,
                         round(axis.rated_current_a / (self._per_current_unit(m.rated_current_unit)
                                                       * m.rated_current_scale)))
        if m.current_limit is not None:
            self.set_raw(m.current_limit.index, m.current_limit.subindex,
                         min(0xFFFF if m.bits(m.current_limit) == 16 else 0xFFFFFFFF,
                             round(axis.max_current_a / (self._per_current_unit(m.current_limit_unit)
                                                         * m.current_limit_scale))))
        if 0x6072 in od and 0x6073 in od:
            self.set_raw(0x6072, 0, self.raw(0x6073))
        if 0x605A in od:
            self.set_raw(0x605A, 0, axis.quick_stop_option)
        self._loading = False
        self._rescale()
        if 0x6080 in od and od[0x6080].default is None and self.units is not None:
            # no EDS default (ZeroErr: only LowLimit=10): the drive holds what commissioning set; played as
            # the motor's speed limit, the value validate tells the engineer to check (not the LowLimit)
            self._loading = True
            self.set_raw(0x6080, 0, min(0xFFFFFFFF, math.ceil(axis.speed_limit_rad_s
                                                              / self.units.velocity_rad_s_per_unit)))
            self._loading = False
        self.add_read_callback(self._on_read)
        self.add_write_callback(self._on_write)
        self._write_callbacks.remove(self.nmt.on_write)   # our own heartbeat producer
        axis.fault_listeners.append(self._on_fault)

    # -------------------------------------------------------------- dictionary
    def _fill_defaults(self) -> None:
        """A real drive answers every object it has: EDS entries without DefaultValue read 0."""
        for obj in self.object_dictionary.values():
            variables = [obj] if isinstance(obj, ODVariable) else list(getattr(obj, "subindices", {}).values())
            for v in variables:
                if v.default is None and v.data_type in (1, 2, 3, 4, 5, 6, 7):
                    low = v.min if v.min is not None and v.min > 0 else 0
                    self.data_store.setdefault(v.index, {})[v.subindex] = v.encode_raw(low)

    def _per_current_unit(self, unit: str) -> float:
        return {"mA": 1e-3, "A": 1.0, "permille_rated": self.axis.rated_current_a / 1000.0}[unit]

    def set_raw(self, index: int, subindex: int, value: int) -> None:
        obj = self._find_object(index, subindex)
        self.set_data(index, subindex, obj.encode_raw(value))

    def raw(self, index: int, subindex: int = 0) -> int:
        obj = self._find_object(index, subindex)
        return obj.decode_raw(self.get_data(index, subindex))

    def set_data(self, index, subindex, data, check_writable=False):
        if not self._loading:
            self._refuse_what_the_drive_would(index, subindex, data)
        super().set_data(index, subindex, data, check_writable)
        if self._loading:
            return
        ref, m = ObjRef(index, subindex), self.model
        if 0x1400 <= index <= 0x1BFF or index == 0x1019:
            self.read_pdo_config()
        elif ref in unit_objects(m) or index == 0x608F:
            self._rescale()
        elif ref == m.current_limit:
            self.axis.max_current_a = self.raw(index, subindex) * self._per_current_unit(m.current_limit_unit) \
                * m.current_limit_scale
        elif index == 0x605A:
            self.axis.quick_stop_option = self.raw(0x605A)
        if ref in m.ramps.values():
            self._apply_ramps()

    def _refuse_what_the_drive_would(self, index: int, subindex: int, data: bytes) -> None:
        m = self.model
        if 0x1600 <= index <= 0x17FF or 0x1A00 <= index <= 0x1BFF:
            value = int.from_bytes(bytes(data[:4]).ljust(4, b"\0"), "little")
            if subindex > 0 and value:
                v = m.var(ObjRef(value >> 16, (value >> 8) & 0xFF))
                if v is None or not v.pdo_mappable or (value & 0xFF) != m.bits(ObjRef(v.index, v.subindex)):
                    raise SdoAbortedError(ABORT_NOT_MAPPABLE)
            elif subindex == 0 and value:
                total = 0
                for sub in range(1, value + 1):
                    try:
                        total += self.raw(index, sub) & 0xFF
                    except (KeyError, SdoAbortedError):
                        raise SdoAbortedError(ABORT_PDO_LENGTH) from None
                if total > 64:
                    raise SdoAbortedError(ABORT_PDO_LENGTH)
        if isinstance(m.velocity_unit, ObjRef) and (index, subindex) == (m.velocity_unit.index, m.velocity_unit.subindex):
            value = int.from_bytes(bytes(data[:4]).ljust(4, b"\0"), "little")
            if value not in m.velocity_allowed and value != self.raw(index, subindex):
                raise SdoAbortedError(ABORT_VALUE_RANGE)

    def _rescale(self) -> None:
        try:
            values = {ref: self.raw(ref.index, ref.subindex) for ref in unit_objects(self.model)}
            self.units, _ = axis_units(self.model, values, f"emulated node {self.id}", self.axis.counts_per_rev)
        except (DriveError, KeyError, ValueError):
            self.units = None      # a drive without usable units cannot move; the master refuses it
        self._apply_ramps()

    def _apply_ramps(self) -> None:
        a, u, m = self.axis, self.units, self.model
        if u is None:
            return
        for key, attr in (("acceleration", "profile_accel_rad_s2"), ("deceleration", "profile_decel_rad_s2")):
            ref = m.ramps.get(key)
            setattr(a, attr, None if ref is None else self.raw(ref.index, ref.subindex) * u.velocity_rad_s_per_unit)
        ref = m.ramps.get("torque_slope")
        a.torque_slope_a_s = None if ref is None or u.torque_a_per_unit is None else \
            self.raw(ref.index, ref.subindex) * u.torque_a_per_unit

    def _on_read(self, index, subindex, od):
        ref = ObjRef(index, subindex)
        if ref in self.live:
            with self.bench.lock:
                self._refresh_status()
                return self.live[ref]
        return None

    def _on_write(self, index, subindex, od, data):
        ref = ObjRef(index, subindex)
        if (index in (0x6040, 0x6060, 0x60FF) or ref == self.model.torque_setpoint) and not self._loading:
            with self.bench.lock:
                self.apply(index, od.decode_raw(data), subindex)

    # -------------------------------------------------------------- PDOs
    def _read_pdos(self, comm_base: int, map_base: int) -> list[_Pdo]:
        pdos = []
        for n in range(4):
            if comm_base + n not in self.object_dictionary or map_base + n not in self.object_dictionary:
                continue
            cob = self.raw(comm_base + n, 1)
            if cob & PDO_INVALID:
                continue
            entries = []
            for sub in range(1, self.raw(map_base + n, 0) + 1):
                value = self.raw(map_base + n, sub)
                index, subindex = value >> 16, (value >> 8) & 0xFF
                if index:
                    try:
                        entries.append(self._find_object(index, subindex))
                    except SdoAbortedError:   # an EDS default naming an object it lacks: no data for it
                        continue
            pdos.append(_Pdo(cob & 0x7FF, self.raw(comm_base + n, 2), entries))
        return pdos

    def read_pdo_config(self) -> None:
        """(Re)read the PDO configuration from the dictionary: a master's change applies now."""
        self.tpdos = [p for p in self._read_pdos(0x1800, 0x1A00) if 1 <= p.trans_type <= 240]
        rpdos = {p.cob_id: p for p in self._read_pdos(0x1400, 0x1600)}
        if self.has_network():
            for cob in set(self.rpdos) - set(rpdos):
                self.network.unsubscribe(cob, self.on_rpdo)
            for cob in set(rpdos) - set(self.rpdos):
                self.network.subscribe(cob, self.on_rpdo)
        self.rpdos = rpdos

    @property
    def expects_sync_counter(self) -> bool:
        return 0x1019 in self.object_dictionary and self.raw(0x1019) > 1

    def on_rpdo(self, can_id, data, timestamp):
        pdo = self.rpdos.get(can_id)
        if pdo is None or self.nmt._state != NMT_OPERATIONAL or self.axis.name in self.bench.muted:
            return
        values, offset = [], 0
        for obj in pdo.entries:
            size = len(obj) // 8
            chunk = bytes(data[offset:offset + size])
            offset += size
            if len(chunk) == size:
                values.append((obj.index, obj.subindex, obj.decode_raw(chunk)))
        with self.bench.lock:
            if pdo.trans_type <= 240:
                self.pending.extend(values)
            else:
                for index, subindex, value in values:
                    self.apply(index, value, subindex)

    def apply(self, index: int, value: int, subindex: int = 0) -> None:
        """A write to a drive object (by PDO or SDO) -> the axis, in SI."""
        a, u = self.axis, self.units
        if ObjRef(index, subindex) == self.model.torque_setpoint and index != 0x6071:
            # a described current setpoint (a vendor object) in its own unit and scale
            self.target_writes += 1
            a.target_current_a = u.torque_current_a(value) if u is not None and u.torque_a_per_unit else 0.0
            self._refresh_status()
            return
        if index == 0x6040:
            a.write_controlword(value)
        elif index == 0x6060:
            a.set_mode(value)
        elif index == 0x60FF:
            self.target_writes += 1
            a.target_velocity_rad_s = u.velocity_rad_s(value) if u is not None else 0.0
        elif index == 0x6071:
            self.target_writes += 1
            # the drive's own relation of torque to current: per-mille of rated current when described;
            # a drive whose relation gearbench does not know is never commanded in torque by it
            a.target_current_a = value * a.rated_current_a / 1000.0
        self._refresh_status()

    def apply_pending(self) -> None:
        pending, self.pending = self.pending, []
        for index, subindex, value in pending:
            self.apply(index, value, subindex)

    def _refresh_status(self) -> None:
        a, live = self.axis, self.live
        for index, value in ((0x6041, a.statusword), (0x6061, a.mode_display), (0x603F, a.error_code),
                             (0x1001, a.error_register)):
            if ObjRef(index) in live:
                live[ObjRef(index)] = value

    def update_actuals(self, meas, sync_counter: int) -> None:
        u, live, m = self.units, self.live, self.model
        self._refresh_status()
        if m.sync_echo is not None and m.sync_echo in live:
            live[m.sync_echo] = sync_counter
        if u is None:
            return
        live[ObjRef(0x6064)] = u.position_counts(meas.position_rad)
        live[ObjRef(0x606C)] = u.velocity_raw(meas.velocity_rad_s)
        if m.current is not None and m.current in live:
            live[m.current] = u.current_raw(meas.current_a)
        if ObjRef(0x6077) in live:    # torque actual, per-mille of rated torque (= rated current)
            live[ObjRef(0x6077)] = max(-32768, min(32767, round(meas.current_a / self.axis.rated_current_a * 1000)))

    def tpdo_frames(self, steps: int) -> list[tuple[int, bytes]]:
        frames = []
        for pdo in self.tpdos:
            pdo.countdown -= steps
            if pdo.countdown > 0:
                continue
            pdo.countdown = pdo.trans_type
            payload = b"".join(
                obj.encode_raw(self.live[ObjRef(obj.index, obj.subindex)])
                if ObjRef(obj.index, obj.subindex) in self.live
                else self.get_data(obj.index, obj.subindex) for obj in pdo.entries)
            frames.append((pdo.cob_id, payload))
        return frames

    def sync_length_error(self) -> None:
        """CiA 301: a SYNC whose length does not match 0x1019 -> EMCY 0x8240 (the drive keeps running)."""
        self.sync_length_errors += 1
        if self.has_network() and self.axis.name not in self.bench.muted:
            self.emcy.send(EMCY_SYNC_LENGTH, 0x11)   # error register: generic + communication

    def _on_fault(self, axis, code) -> None:
        self._refresh_status()
        if self.has_network() and axis.name not in self.bench.muted:
            if code:
                self.emcy.send(code, axis.error_register, struct.pack("<H", axis.statusword) + b"\0\0\0")
            else:
                self.emcy.reset()


class CanopenServer:
    """Handle returned by ``start_canopen_server``: ``.stop()``, ``.nodes``, ``.sync_count``."""

    def __init__(self, bench: EmulatedBench, bus, eds: str | dict[int, str], profile_dir=None):
        self.bench, self.bus = bench, bus
        self.network = canopen.Network(bus)
        self.nodes: list[DriveNode] = []
        for address in sorted(bench.axes):
            node_eds = eds.get(address, DEFAULT_EDS) if isinstance(eds, dict) else eds
            node = DriveNode(address, node_eds, bench, bench.drive(address), profile_dir=profile_dir)
            self.network.add_node(node)
            self.network.unsubscribe(node.sdo.rx_cobid, node.sdo.on_request)
            self.network.subscribe(node.sdo.rx_cobid, self._sdo_filter(node))
            node.read_pdo_config()
            self.nodes.append(node)
        self.sync_count = 0
        self._last_counter: int | None = None
        # the stand-in's own account, so a benchmark can show that what was lost was the master's:
        # SYNCs heard, SYNCs never heard (counter jumps), TPDO frames sent, answers sent later
        # than one period after the SYNC was received, and the largest such delay
        self.counters = bench.counters
        self.counters.update(syncs_heard=0, syncs_missed=0, frames_sent=0, late_answers=0,
                             answer_delay_max_s=0.0)
        self.network.subscribe(0x80, self.on_sync)
        self.network.NOTIFIER_CYCLE = 0.1    # stop() waits for one notifier cycle
        self.network.connect()
        try:
            self._receive_lag = _ReceiveLag()
            self.network.notifier.add_listener(self._receive_lag)
            self._heard: dict[int, float] = {}                 # producer node id -> last heartbeat (monotonic)
            self._listening: set[int] = set()
            self._lost: dict[tuple[int, int], float] = {}     # (node, producer) -> the heartbeat it timed out after
            self._stop = threading.Event()
            self._heartbeat = threading.Thread(target=self._heartbeat_loop, name="emulate-heartbeat", daemon=True)
            for node in self.nodes:   # power-up: boot-up message, then PRE-OPERATIONAL
                self.network.send_message(0x700 + node.id, [0])
                node.nmt.state = "PRE-OPERATIONAL"
            self._heartbeat.start()
        except Exception:
            # the notifier stops before the bus closes (closed under it, its thread raised "Cannot
            # operate on a closed bus")
            self.network.disconnect()
            raise

    def _sdo_filter(self, node: DriveNode):
        def on_request(can_id, data, timestamp):
            if node.axis.name not in self.bench.muted:
                node.sdo.on_request(can_id, data, timestamp)
        return on_request

    def on_sync(self, can_id, data, timestamp):
        steps, counter = 1, 0
        if data:
            wrong = [n for n in self.nodes if not n.expects_sync_counter]
            for node in wrong:
                node.sync_length_error()
            if not wrong:   # SYNC counter (CiA 301 0x1019): advance the SYNCs we did not hear as well
                overflow = max(2, self.nodes[0].raw(0x1019))
                if self._last_counter is not None:
                    steps = (data[0] - self._last_counter - 1) % overflow + 1
                self._last_counter = counter = data[0]
        frames = []
        with self.bench.lock:
            for node in self.nodes:
                node.apply_pending()
            measured = self.bench.advance(steps)
            self.sync_count += steps
            for node in self.nodes:
                node.update_actuals(measured[node.axis.name], counter)
                if node.nmt._state == NMT_OPERATIONAL and node.axis.name not in self.bench.muted \
                        and self.bench.pdo_on:
                    frames += node.tpdo_frames(steps)
        for cob_id, payload in frames:
            if not self.bench.drop_frame():
                self.network.send_message(cob_id, payload)
        c = self.counters
        c["syncs_heard"] += 1
        c["syncs_missed"] += steps - 1
        c["frames_sent"] += len(frames)
        if timestamp:    # receive time of the SYNC (wall clock on udp_multicast and socketcan)
            delay = time.time() - timestamp
            c["answer_delay_max_s"] = max(c["answer_delay_max_s"], delay)
            c["late_answers"] += delay > self.bench.period_s

    # ------------------------------------------------------------ heartbeat consumer
    def _on_producer_heartbeat(self, can_id, data, timestamp):
        self._heard[can_id - 0x700] = time.monotonic()

    def _consumed(self, node: DriveNode) -> list[tuple[int, float]]:
        """(producer node id, consumer time in s) of every armed 0x1016 slot."""
        if 0x1016 not in node.object_dictionary:
            return []
        out = []
        for sub in node.object_dictionary[0x1016].subindices:
            value = node.raw(0x1016, sub) if sub else 0
            if value & 0xFFFF and (value >> 16) & 0x7F:
                out.append(((value >> 16) & 0x7F, (value & 0xFFFF) / 1000.0))
        return out

    def _check_consumers(self, now: float) -> None:
        for node in self.nodes:
            for producer, limit_s in self._consumed(node):
                if producer not in self._listening:
                    self._listening.add(producer)
                    self.network.subscribe(0x700 + producer, self._on_producer_heartbeat)
                heard = self._heard.get(producer)
                key = (node.id, producer)
                if heard is None or self._lost.get(key) == heard:
                    continue                  # not yet heard (CiA 301: monitoring starts then) or already reported
                if now - heard > limit_s:
                    self._lost[key] = heard
                    self._master_lost(node)

    def _master_lost(self, node: DriveNode) -> None:
        axis = node.axis
        option = node.raw(0x6007) if 0x6007 in node.object_dictionary else 0
        with self.bench.lock:
            enabled = axis.state == "OPERATION ENABLED"
            if enabled and option == 1:
                axis.fault_now(EMCY_HEARTBEAT)            # sends its own EMCY
                return
            if enabled and option in ABORT_ACTIONS:
                axis.write_controlword(ABORT_ACTIONS[option])
            node._refresh_status()
        if node.has_network() and axis.name not in self.bench.muted:
            node.emcy.send(EMCY_HEARTBEAT, 0x11)          # error register: generic + communication

    def _heartbeat_loop(self):
        due = {node.id: 0.0 for node in self.nodes}
        last = hold = time.monotonic()
        while not self._stop.wait(0.005):
            now = time.monotonic()
            if now - last > CONSUMER_STALL_S:   # this process was stalled: let the receiver catch up
                hold = now + 2 * CONSUMER_STALL_S   # before blaming the master for heartbeats still queued
            if now >= hold and self._receive_lag.lag_s < CONSUMER_STALL_S:
                self._check_consumers(now)
            last = now
            for node in self.nodes:
                period_ms = node.raw(0x1017)
                if period_ms and now >= due[node.id]:
                    due[node.id] = now + period_ms / 1000.0
                    if node.axis.name not in self.bench.muted | self.bench.heartbeat_muted:
                        try:
                            self.network.send_message(0x700 + node.id, [node.nmt._state])
                        except Exception:   # bus closing under us at stop()
                            return

    def stop(self) -> None:
        self._stop.set()
        self._heartbeat.join(timeout=1.0)
        self.network.disconnect()


def start_canopen_server(bench: EmulatedBench, interface: str, channel: str, *,
                         eds: str | dict[int, str] = DEFAULT_EDS, port: int | None = None,
                         profile_dir=None, **bus_kwargs) -> CanopenServer:
    """Put ``bench``'s drives on a CAN bus as CANopen nodes (ids = ``bench.axes``).

    ``eds``: one EDS for every node, or {node id: EDS} (a profile's drives).
    """
    bus = open_bus(BusSpec(interface, channel, port), **bus_kwargs)
    try:
        return CanopenServer(bench, bus, eds, profile_dir=profile_dir)
    except Exception:
        bus.shutdown()
        raise
