"""CANopen front-end of the emulated bench: nodes 1 and 2 as CiA 402 servo drives.

Built on canopen's ``LocalNode`` (SDO server, NMT slave, object dictionary from
``drivers/cia402-servo.eds``) plus what it lacks (upstream #145, #558, #520):

- SYNC: the world advances one period per SYNC (lockstep), then every node in NMT
  OPERATIONAL sends its synchronous TPDOs from the mapping *currently* in its object
  dictionary. A SYNC counter (0x1019 > 1) that jumps advances the missed periods
  too, so drive time stays SYNC count x period.
- RPDOs: decoded with the current mapping; transmission type 255 applies at once,
  1-240 at the next SYNC (CiA 301). Controlword, modes of operation, target velocity
  and target torque go to the node's ``Cia402Axis`` (also when written by SDO).
- PDO configuration written by the master takes effect at once.
- EMCY on faults and on fault reset; heartbeat producer from 0x1017.
- Fault options from ``EmulatedBench``: TPDO drop rate, muted nodes.
"""
from __future__ import annotations

import struct
import threading
import time

import canopen
from canopen.objectdictionary import ODVariable

from ..drives.buses import BusSpec, open_bus
from ..drives.scaling import DriveScaling
from ..shipped import shipped_driver
from .bench import EmulatedBench
from .cia402_axis import Cia402Axis

DEFAULT_EDS = str(shipped_driver("cia402-servo.eds"))
NMT_OPERATIONAL = 5
PDO_INVALID = 1 << 31
LIVE = (0x6041, 0x6061, 0x6064, 0x606C, 0x6077, 0x6078, 0x603F, 0x1001, 0x2001)


class _Pdo:
    """One PDO's communication + mapping, as currently configured in the dictionary."""

    __slots__ = ("cob_id", "trans_type", "entries", "countdown")

    def __init__(self, cob_id: int, trans_type: int, entries: list[ODVariable]):
        self.cob_id, self.trans_type, self.entries, self.countdown = cob_id, trans_type, entries, trans_type


class DriveNode(canopen.LocalNode):
    """A LocalNode wired to one ``Cia402Axis``."""

    def __init__(self, node_id: int, eds: str, bench: EmulatedBench, axis: Cia402Axis):
        super().__init__(node_id, eds)
        self.bench, self.axis = bench, axis
        self.live: dict[int, int] = {i: 0 for i in LIVE}
        self.tpdos: list[_Pdo] = []
        self.rpdos: dict[int, _Pdo] = {}
        self.pending: list[tuple[int, int]] = []       # (index, value) of sync RPDOs
        self._loading = True
        od = self.object_dictionary
        self.set_raw(0x608F, 1, axis.counts_per_rev)
        self.set_raw(0x608F, 2, 1)
        self.set_raw(0x6075, 0, round(axis.rated_current_a * 1000))
        self.set_raw(0x6073, 0, min(0xFFFF, round(axis.max_current_a / axis.rated_current_a * 1000)))
        self.set_raw(0x6072, 0, od[0x6073].decode_raw(self.get_data(0x6073, 0)))
        self.set_raw(0x605A, 0, axis.quick_stop_option)
        self._loading = False
        self._rescale()
        self.add_read_callback(self._on_read)
        self.add_write_callback(self._on_write)
        self._write_callbacks.remove(self.nmt.on_write)   # our own heartbeat producer
        axis.fault_listeners.append(self._on_fault)

    # -------------------------------------------------------------- dictionary
    def set_raw(self, index: int, subindex: int, value: int) -> None:
        obj = self._find_object(index, subindex)
        self.set_data(index, subindex, obj.encode_raw(value))

    def raw(self, index: int, subindex: int = 0) -> int:
        obj = self._find_object(index, subindex)
        return obj.decode_raw(self.get_data(index, subindex))

    def set_data(self, index, subindex, data, check_writable=False):
        super().set_data(index, subindex, data, check_writable)
        if self._loading:
            return
        if 0x1400 <= index <= 0x1BFF or index == 0x1019:
            self.read_pdo_config()
        elif index in (0x608F, 0x6075):
            self._rescale()
        elif index == 0x6073:
            self.axis.max_current_a = self.scaling.current_a(self.raw(0x6073))
        elif index == 0x605A:
            self.axis.quick_stop_option = self.raw(0x605A)

    def _rescale(self):
        self.scaling = DriveScaling(
            counts_per_rev=max(1, round(self.raw(0x608F, 1) / max(1, self.raw(0x608F, 2)))),
            rated_current_a=max(1, self.raw(0x6075)) / 1000.0)

    def _on_read(self, index, subindex, od):
        if index in self.live:
            with self.bench.lock:
                self._refresh_status()
                return self.live[index]
        return None

    def _on_write(self, index, subindex, od, data):
        if index in (0x6040, 0x6060, 0x60FF, 0x6071) and not self._loading:
            with self.bench.lock:
                self.apply(index, od.decode_raw(data))

    # -------------------------------------------------------------- PDOs
    def _read_pdos(self, comm_base: int, map_base: int) -> list[_Pdo]:
        pdos = []
        for n in range(4):
            if comm_base + n not in self.object_dictionary:
                continue
            cob = self.raw(comm_base + n, 1)
            if cob & PDO_INVALID:
                continue
            entries = []
            for sub in range(1, self.raw(map_base + n, 0) + 1):
                value = self.raw(map_base + n, sub)
                index, subindex = value >> 16, (value >> 8) & 0xFF
                if index:
                    entries.append(self._find_object(index, subindex))
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
                values.append((obj.index, obj.decode_raw(chunk)))
        with self.bench.lock:
            if pdo.trans_type <= 240:
                self.pending.extend(values)
            else:
                for index, value in values:
                    self.apply(index, value)

    def apply(self, index: int, value: int) -> None:
        """A write to a drive object (by PDO or SDO) -> the axis, in SI."""
        a = self.axis
        if index == 0x6040:
            a.write_controlword(value)
        elif index == 0x6060:
            a.set_mode(value)
        elif index == 0x60FF:
            a.target_velocity_rad_s = self.scaling.velocity_rad_s(value)
        elif index == 0x6071:   # current mode: per-mille of rated current
            a.target_current_a = self.scaling.current_a(value)
        self._refresh_status()

    def apply_pending(self) -> None:
        pending, self.pending = self.pending, []
        for index, value in pending:
            self.apply(index, value)

    def _refresh_status(self) -> None:
        a, live = self.axis, self.live
        live[0x6041] = a.statusword
        live[0x6061] = a.mode_display
        live[0x603F] = a.error_code
        live[0x1001] = a.error_register

    def update_actuals(self, m, sync_counter: int) -> None:
        s, live = self.scaling, self.live
        self._refresh_status()
        live[0x2001] = sync_counter
        live[0x6064] = s.position_counts(m.position_rad)
        live[0x606C] = s.velocity_counts_s(m.velocity_rad_s)
        live[0x6078] = live[0x6077] = s.current_permille(m.current_a)

    def tpdo_frames(self, steps: int) -> list[tuple[int, bytes]]:
        frames = []
        for pdo in self.tpdos:
            pdo.countdown -= steps
            if pdo.countdown > 0:
                continue
            pdo.countdown = pdo.trans_type
            payload = b"".join(
                obj.encode_raw(self.live[obj.index]) if obj.index in self.live
                else self.get_data(obj.index, obj.subindex) for obj in pdo.entries)
            frames.append((pdo.cob_id, payload))
        return frames

    def _on_fault(self, axis, code) -> None:
        self._refresh_status()
        if self.has_network() and axis.name not in self.bench.muted:
            if code:
                self.emcy.send(code, axis.error_register, struct.pack("<H", axis.statusword) + b"\0\0\0")
            else:
                self.emcy.reset()


class CanopenServer:
    """Handle returned by ``start_canopen_server``: ``.stop()``, ``.nodes``, ``.sync_count``."""

    def __init__(self, bench: EmulatedBench, bus, eds: str):
        self.bench, self.bus = bench, bus
        self.network = canopen.Network(bus)
        self.nodes: list[DriveNode] = []
        for address in sorted(bench.axes):
            node = DriveNode(address, eds, bench, bench.drive(address))
            self.network.add_node(node)
            self.network.unsubscribe(node.sdo.rx_cobid, node.sdo.on_request)
            self.network.subscribe(node.sdo.rx_cobid, self._sdo_filter(node))
            node.read_pdo_config()
            self.nodes.append(node)
        self.sync_count = 0
        self._last_counter: int | None = None
        self.network.subscribe(0x80, self.on_sync)
        self.network.NOTIFIER_CYCLE = 0.1    # stop() waits for one notifier cycle
        self.network.connect()
        self._stop = threading.Event()
        self._heartbeat = threading.Thread(target=self._heartbeat_loop, name="emulate-heartbeat", daemon=True)
        for node in self.nodes:   # power-up: boot-up message, then PRE-OPERATIONAL
            self.network.send_message(0x700 + node.id, [0])
            node.nmt.state = "PRE-OPERATIONAL"
        self._heartbeat.start()

    def _sdo_filter(self, node: DriveNode):
        def on_request(can_id, data, timestamp):
            if node.axis.name not in self.bench.muted:
                node.sdo.on_request(can_id, data, timestamp)
        return on_request

    def on_sync(self, can_id, data, timestamp):
        steps, counter = 1, 0
        if data:   # SYNC counter (CiA 301 0x1019): advance the SYNCs we did not hear as well
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
                if node.nmt._state == NMT_OPERATIONAL and node.axis.name not in self.bench.muted:
                    frames += node.tpdo_frames(steps)
        for cob_id, payload in frames:
            if not self.bench.drop_frame():
                self.network.send_message(cob_id, payload)

    def _heartbeat_loop(self):
        due = {node.id: 0.0 for node in self.nodes}
        while not self._stop.wait(0.005):
            now = time.monotonic()
            for node in self.nodes:
                period_ms = node.raw(0x1017)
                if period_ms and now >= due[node.id]:
                    due[node.id] = now + period_ms / 1000.0
                    if node.axis.name not in self.bench.muted:
                        try:
                            self.network.send_message(0x700 + node.id, [node.nmt._state])
                        except Exception:   # bus closing under us at stop()
                            return

    def stop(self) -> None:
        self._stop.set()
        self._heartbeat.join(timeout=1.0)
        self.network.disconnect()


def start_canopen_server(bench: EmulatedBench, interface: str, channel: str, *,
                         eds: str = DEFAULT_EDS, port: int | None = None, **bus_kwargs) -> CanopenServer:
    """Put ``bench``'s drives on a CAN bus as CANopen nodes (ids = ``bench.axes``)."""
    bus = open_bus(BusSpec(interface, channel, port), **bus_kwargs)
    try:
        return CanopenServer(bench, bus, eds)
    except Exception:
        bus.shutdown()
        raise
