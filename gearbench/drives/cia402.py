"""CANopen CiA 402 servo drives (master side), with ``canopen`` + ``python-can``.

Start-up (``start``), per drive, in NMT PRE-OPERATIONAL by SDO:

- scaling read from the drive and checked against the profile: 0x608F encoder
  increments per revolution, 0x6075 rated current (mA); limits written from the
  profile: 0x6073 max current (per-mille), 0x607F max profile velocity (inc/s);
- PDO mapping (all other PDOs disabled)::

    TPDO1 0x180+id  type 1   statusword 0x6041 | position actual 0x6064 | SYNC counter 0x2001
    TPDO2 0x280+id  type 1   velocity actual 0x606C | current actual 0x6078 | SYNC counter 0x2001
    RPDO1 0x200+id  type 255 controlword 0x6040 | modes of operation 0x6060   (applied at once)
    RPDO2 0x300+id  type 1   target velocity 0x60FF | target torque 0x6071     (latched at SYNC)

  0x2001 (in ``drivers/cia402-servo.eds``) echoes the SYNC counter byte, so every
  frame is matched to its SYNC even when frames are late or lost; drives without it
  get the standard mapping without the counter. Both drives latch setpoints on the
  same SYNC (RPDO2 synchronous); state-machine commands are events (RPDO1 async) and
  their result is confirmed by an SDO read of the statusword.
- heartbeat producer 0x1017 and SYNC counter overflow 0x1019; then NMT OPERATIONAL.

Units: see ``gearbench.drives.scaling`` (counts, inc/s, per-mille of rated current;
torque setpoints are current setpoints, "current mode").

Sampling (``_sample``): one SYNC with counter, wait for both TPDOs of every drive for
that SYNC; ``index`` = SYNC count since ``start``, ``time_s`` = index x period. A
SYNC whose frames do not all arrive is skipped and counted in ``lost_samples``.
EMCY, a fault bit in the statusword or a missed heartbeat -> drives stopped and
``BenchFault``; a drive silent for ``timeout_s`` -> ``BenchFault`` naming node and bus.
"""
from __future__ import annotations

import struct
import threading
import time
from pathlib import Path

import canopen
from canopen.emcy import EmcyError
from canopen.sdo import SdoAbortedError, SdoCommunicationError, SdoVariable

from ..errors import BenchFault, DriveError
from ..shipped import shipped_driver
from .base import AxisConfig, Drive, DriveNetwork, Mode, Sample
from .buses import open_bus, parse_bus
from .scaling import DriveScaling, unwrap_int32

DEFAULT_EDS = str(shipped_driver("cia402-servo.eds"))
REQUIRED_OBJECTS = {0x1000: "device type", 0x1017: "producer heartbeat time", 0x1400: "RPDO1 communication",
                    0x1401: "RPDO2 communication", 0x1600: "RPDO1 mapping", 0x1601: "RPDO2 mapping",
                    0x1800: "TPDO1 communication", 0x1801: "TPDO2 communication", 0x1A00: "TPDO1 mapping",
                    0x1A01: "TPDO2 mapping", 0x6040: "controlword", 0x6041: "statusword",
                    0x6060: "modes of operation", 0x6061: "modes of operation display",
                    0x6064: "position actual value", 0x606C: "velocity actual value",
                    0x6071: "target torque", 0x6075: "motor rated current", 0x6078: "current actual value",
                    0x608F: "position encoder resolution", 0x60FF: "target velocity"}
SYNC_COUNTER_OBJ = 0x2001
SYNC_OVERFLOW = 240
STATES = {  # statusword mask, value (CiA 402)
    "SWITCH ON DISABLED": (0x4F, 0x40), "READY TO SWITCH ON": (0x6F, 0x21), "SWITCHED ON": (0x6F, 0x23),
    "OPERATION ENABLED": (0x6F, 0x27), "QUICK STOP ACTIVE": (0x6F, 0x07), "FAULT": (0x4F, 0x08),
    "FAULT REACTION ACTIVE": (0x4F, 0x0F), "NOT READY TO SWITCH ON": (0x4F, 0x00)}
CW_DISABLE_VOLTAGE, CW_QUICK_STOP, CW_SHUTDOWN, CW_SWITCH_ON, CW_ENABLE, CW_FAULT_RESET = 0, 2, 6, 7, 15, 0x80
MODE_CODES = {(Mode.VELOCITY, False): 3, (Mode.TORQUE, False): 4, (Mode.VELOCITY, True): 9, (Mode.TORQUE, True): 10}


def state_of(statusword: int) -> str:
    for name, (mask, value) in STATES.items():
        if statusword & mask == value:
            return name
    return "UNKNOWN"


def load_eds(path: str, node_id: int) -> canopen.ObjectDictionary:
    """Object dictionary from an EDS; DriveError naming the file and the field."""
    if not Path(path).is_file():
        raise DriveError(f"{path}: EDS file not found; fix the axis 'description' path")
    try:
        od = canopen.import_od(path, node_id)
    except Exception as exc:   # configparser/ValueError/KeyError: all mean a malformed file
        raise DriveError(f"{path}: malformed EDS ({type(exc).__name__}: {exc}); "
                         f"check it with a CANopen EDS editor") from exc
    for index, name in REQUIRED_OBJECTS.items():
        if index not in od:
            raise DriveError(f"{path}: object 0x{index:04X} ({name}) missing; a CiA 402 servo EDS needs it")
    device_type = od[0x1000].default
    if device_type is None or device_type & 0xFFFF != 402:
        raise DriveError(f"{path}: [1000] DefaultValue {device_type!r} is not a CiA 402 device type "
                         f"(low 16 bits must be 402 = 0x0192)")
    return od


class CiA402Drive(Drive):
    """One CiA 402 servo on a ``CiA402Network``; SI in, SI out."""

    def __init__(self, network: "CiA402Network", node: canopen.RemoteNode, config: AxisConfig):
        super().__init__(config)
        self.net, self.node = network, node
        self.scaling = DriveScaling(config.counts_per_rev, config.rated_current_a)
        self.mode: Mode | None = None
        self._mode_code = 0
        self._controlword = 0
        self._has_counter = SYNC_COUNTER_OBJ in node.object_dictionary
        self._position_counts: int | None = None
        self.last_heartbeat: float | None = None
        self.nmt_state: int | None = None
        self.emcy: list[EmcyError] = []

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
        """PRE-OPERATIONAL configuration by SDO (see the module docstring)."""
        device_type = self.sdo_read(0x1000)
        if device_type & 0xFFFF != 402:
            raise DriveError(f"{self.where}: device type 0x{device_type:08X} is not a CiA 402 drive")
        cpr = self.sdo_read(0x608F, 1) / max(1, self.sdo_read(0x608F, 2))
        rated_a = self.sdo_read(0x6075) / 1000.0
        c = self.config
        if abs(cpr - c.counts_per_rev) > 1e-9:
            raise DriveError(f"{self.where}: drive reports {cpr:g} counts/rev (0x608F) but the profile says "
                             f"counts_per_rev: {c.counts_per_rev}; fix the profile or the drive")
        if abs(rated_a - c.rated_current_a) > 1e-3 * c.rated_current_a:
            raise DriveError(f"{self.where}: drive reports rated current {rated_a:g} A (0x6075) but the profile "
                             f"says rated_current_a: {c.rated_current_a}; fix the profile or the drive")
        self.scaling = DriveScaling(round(cpr), rated_a)
        od = self.node.object_dictionary
        if 0x6073 in od:
            self.sdo_write(0x6073, 0, min(0xFFFF, abs(self.scaling.current_permille(c.current_limit_a))))
        if 0x607F in od:
            self.sdo_write(0x607F, 0, abs(self.scaling.velocity_counts_s(c.speed_limit_rad_s)))
        counter = [(SYNC_COUNTER_OBJ, 8)] if self._has_counter else []
        nid = self.node.id
        self._map(0x1800, 0x1A00, 0, 0x180 + nid, 1, [(0x6041, 16), (0x6064, 32)] + counter)
        self._map(0x1800, 0x1A00, 1, 0x280 + nid, 1, [(0x606C, 32), (0x6078, 16)] + counter)
        self._map(0x1400, 0x1600, 0, 0x200 + nid, 255, [(0x6040, 16), (0x6060, 8)])
        self._map(0x1400, 0x1600, 1, 0x300 + nid, 1, [(0x60FF, 32), (0x6071, 16)])
        for n in (2, 3):
            for comm, base in ((0x1800, 0x180), (0x1400, 0x200)):
                if comm + n in od:
                    self.sdo_write(comm + n, 1, (1 << 31) | (base + 0x100 * n + nid))
        if 0x1019 in od:
            self.sdo_write(0x1019, 0, SYNC_OVERFLOW)
        self.sdo_write(0x1017, 0, heartbeat_ms)
        self.tpdo_formats = {0x180 + nid: "<Hi" + ("B" if counter else ""),
                             0x280 + nid: "<ih" + ("B" if counter else "")}

    def _map(self, comm: int, mapping: int, n: int, cob_id: int, trans_type: int, entries) -> None:
        self.sdo_write(comm + n, 1, (1 << 31) | cob_id)        # invalid while remapping (CiA 301)
        self.sdo_write(mapping + n, 0, 0)
        for sub, (index, bits) in enumerate(entries, start=1):
            self.sdo_write(mapping + n, sub, index << 16 | bits)
        self.sdo_write(mapping + n, 0, len(entries))
        self.sdo_write(comm + n, 2, trans_type)
        self.sdo_write(comm + n, 1, cob_id)

    # ----------------------------------------------------------------- RPDOs
    def _send_control(self, controlword: int) -> None:
        self._controlword = controlword
        self.net.send(0x200 + self.node.id, struct.pack("<Hb", controlword, self._mode_code))

    def _send_targets(self, velocity_counts_s: int, torque_permille: int) -> None:
        self.net.send(0x300 + self.node.id, struct.pack("<ih", velocity_counts_s, torque_permille))

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
        self._mode_code = MODE_CODES[(mode, bool(self.net.options.get("cyclic", False)))]
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
            self._send_targets(self.scaling.velocity_counts_s(value), 0)
        elif self.mode is Mode.TORQUE:    # current mode: per-mille of rated current
            self._send_targets(0, self.scaling.current_permille(value))
        else:
            raise DriveError(f"{self.where}: set_setpoint before enable(mode)")

    def quick_stop(self) -> None:
        self._send_control(CW_QUICK_STOP)

    def disable(self) -> None:
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
        s = self.scaling
        return Sample(index=index, time_s=time_s, position_rad=s.position_rad(counts),
                      velocity_rad_s=s.velocity_rad_s(velocity), current_a=s.current_a(current),
                      status=statusword, fault=bool(statusword & 0x08))


class CiA402Network(DriveNetwork):
    """CiA 402 drives on one CAN bus, sampled on SYNC.

    Options (profile ``bus:`` section): ``bus`` ("udp_multicast:239.74.163.2:43113",
    "socketcan:can0", "virtual:bench"), ``heartbeat_ms`` (100), ``timeout_s`` (0.5:
    a drive silent this long is a fault), ``frame_grace_s`` (0.02: once a SYNC's first
    TPDO arrived, its other TPDOs are lost if not in by then), ``sdo_timeout_s`` (0.3), ``cyclic`` (False: profile velocity/torque
    modes 3/4; True: cyclic synchronous 9/10), ``bus_kwargs`` (extra python-can args).
    """

    family = "cia402"

    def __init__(self, bus: str = "udp_multicast:239.74.163.2", *, heartbeat_ms: int = 100,
                 timeout_s: float = 0.5, state_timeout_s: float = 0.5, frame_grace_s: float = 0.02,
                 sdo_timeout_s: float = 0.3, cyclic: bool = False, lockstep: bool = False,
                 bus_kwargs: dict | None = None, **options):
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
        self.network: canopen.Network | None = None
        self.sync_count = 0
        self._cv = threading.Condition()
        self._expect = 0
        self._got: dict[int, tuple] = {}
        self._formats: dict[int, tuple[struct.Struct, bool]] = {}
        self._faults: list[str] = []
        self._last_rx: dict[int, float] = {}
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
        od = load_eds(config.description or DEFAULT_EDS, config.address)
        node = canopen.RemoteNode(config.address, od)
        node.sdo.RESPONSE_TIMEOUT = self.sdo_timeout_s
        self.network.add_node(node)
        drive = CiA402Drive(self, node, config)
        self.drives[config.name] = drive
        self.network.subscribe(0x700 + node.id, self._on_heartbeat_of(drive))
        self.network.subscribe(0x80 + node.id, self._on_emcy_of(drive))
        return drive

    def start(self, period_s: float) -> None:
        if not self.drives:
            raise DriveError("CiA402Network.start with no drive; add_drive() first")
        self.period_s = period_s
        for d in self.drives.values():
            d.node.nmt.state = "PRE-OPERATIONAL"
        for d in self.drives.values():
            d.configure(self.heartbeat_ms)
            for cob_id, fmt in d.tpdo_formats.items():
                self._formats[cob_id] = (struct.Struct(fmt), d._has_counter)
                self.network.subscribe(cob_id, self._on_tpdo)
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
        self._last_rx = {d.node.id: time.monotonic() for d in self.drives.values()}
        self._started = True

    # ----------------------------------------------------------------- receive (notifier thread)
    def _on_tpdo(self, cob_id, data, timestamp):
        fmt, has_counter = self._formats[cob_id]
        try:
            values = fmt.unpack_from(data)
        except struct.error:
            return
        self._last_rx[cob_id & 0x7F] = time.monotonic()
        with self._cv:
            if has_counter and values[-1] != self._expect:
                return                              # late frame of an earlier SYNC
            self._got[cob_id] = values
            self._cv.notify()

    def _on_heartbeat_of(self, drive: CiA402Drive):
        def on_heartbeat(can_id, data, timestamp):
            drive.last_heartbeat = time.monotonic()
            drive.nmt_state = data[0] & 0x7F if data else None
        return on_heartbeat

    def _on_emcy_of(self, drive: CiA402Drive):
        def on_emcy(can_id, data, timestamp):
            if len(data) < 8:
                return
            code, register, extra = struct.unpack("<HB5s", bytes(data[:8]))
            entry = EmcyError(code, register, extra, timestamp)
            drive.emcy.append(entry)
            if code & 0xFF00:
                with self._cv:
                    self._faults.append(f"{drive.where}: EMCY 0x{code:04X} ({entry.get_desc()}), "
                                        f"error register 0x{register:02X}")
        return on_emcy

    # ----------------------------------------------------------------- sampling
    def _check_health(self) -> None:
        now = time.monotonic()
        problems = list(self._faults)
        limit_s = 3 * self.heartbeat_ms / 1000.0
        for d in self.drives.values():
            if d.last_heartbeat is not None and now - d.last_heartbeat > limit_s:
                problems.append(f"{d.where}: no heartbeat for {now - d.last_heartbeat:.2f} s "
                                f"(producer time {self.heartbeat_ms} ms)")
            elif d.nmt_state not in (None, 5):
                problems.append(f"{d.where}: left NMT OPERATIONAL (state {d.nmt_state})")
        if problems:
            self._faults.clear()
            self.stop_all()
            raise BenchFault("; ".join(problems) + "; drives stopped")

    def _sample(self) -> dict[str, Sample]:
        if not self._started:
            raise DriveError("CiA402Network.sample before start(period_s)")
        while True:
            self._check_health()
            if not self.lockstep:
                self._pace()
            self.sync_count += 1
            counter = (self.sync_count - 1) % SYNC_OVERFLOW + 1
            with self._cv:
                self._expect, self._got = counter, {}
            self.network.send_message(0x80, bytes([counter]))
            with self._cv:
                # the drives answer a SYNC together: wait long for the first frame (a busy host is not a
                # lost frame), then briefly for the rest of that SYNC before calling it lost
                self._cv.wait_for(lambda: len(self._got) == len(self._formats) or self._got, self.timeout_s / 2)
                if self._got:
                    self._cv.wait_for(lambda: len(self._got) == len(self._formats), self.frame_grace_s)
                got = dict(self._got)
            if len(got) == len(self._formats):
                return self._build(got)
            # incomplete: this SYNC is lost (base class counts the index gap); a drive silent too long is fatal
            now = time.monotonic()
            missing = [d.where for d in self.drives.values() if now - self._last_rx[d.node.id] > self.timeout_s]
            if missing:
                self.stop_all()
                raise BenchFault(f"{', '.join(missing)}: no TPDO answer to SYNC for {self.timeout_s:g} s; "
                                 f"drives stopped")

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
        if target - now > 2e-3:
            time.sleep(target - now - 1e-3)   # coarse sleep, then spin for the last millisecond
        while time.perf_counter() < target:
            pass

    def _build(self, got: dict[int, tuple]) -> dict[str, Sample]:
        index = self.sync_count
        time_s = index * self.period_s
        out = {}
        for name, d in self.drives.items():
            nid = d.node.id
            out[name] = d.sample(index, time_s, got[0x180 + nid], got[0x280 + nid])
        faulted = [s for s in out.values() if s.fault]
        if faulted:
            self._check_health()   # an EMCY usually arrived first and names the code
            names = [self.drives[n].where for n, s in out.items() if s.fault]
            self.stop_all()
            raise BenchFault(f"{', '.join(names)}: FAULT in statusword at sample {index}; drives stopped")
        return out

    def _close(self) -> None:
        if self.network is not None:
            try:
                for d in self.drives.values():
                    try:
                        d.node.nmt.state = "PRE-OPERATIONAL"
                    except Exception:
                        pass
            finally:
                self.network.disconnect()
                self.network = None
