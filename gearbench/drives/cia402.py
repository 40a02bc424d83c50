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
- Paced (real drives): SYNC every period on the wall clock. Frames are matched to
  their SYNC by the counter echo where the drive has one: an answer completes its SYNC
  however late it is taken (up to ``LATE_ANSWER_S``, 0.2 s), and a SYNC is lost when its answers
  never arrive, or a later SYNC's are complete first (samples stay in SYNC order).
  Without an echo the bus's order decides: a SYNC whose frames are not all in before the
  next one is lost (a frame received before this SYNC was sent answers an earlier one).
  Lost SYNCs are counted in ``lost_samples``; SYNCs sent late (the producer woke late and
  caught up) are timing faults, counted apart (``supervision()``).

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

from ..errors import BenchFault, DriveError
from .base import AxisConfig, DriveNetwork, Sample
from .buses import open_bus, parse_bus
from .cia402_drive import (ABORT_CONNECTION_QUICK_STOP, CW_DISABLE_VOLTAGE, CW_ENABLE, CW_FAULT_RESET,
                           CW_QUICK_STOP, CW_SHUTDOWN, CW_SWITCH_ON, DEFAULT_EDS, STATES, SYNC_OVERFLOW,
                           CiA402Drive, load_eds, load_model, state_of)
from .supervision import HostStallMonitor, Liveness
from .sync_producer import start_sync_producer

NMT_OPERATIONAL_STATE = 0x05          # the heartbeat byte of a node in OPERATIONAL (CiA 301)
STARVED_LIMIT_FACTOR = 10    # an emulated drive starved of CPU may be silent this many limits, not more
HEALTH_PERIOD_S = 0.01       # supervision verdicts at most this often, not per sample: EMCY, NMT and
                             # silence limits are tens of ms or more, and per sample it cost ~20 us
READY_KEEP_S = 2.0           # complete samples kept for a sample loop that fell behind (beyond: lost)
LATE_ANSWER_S = 0.2          # with a SYNC counter echo, an answer this late still completes its SYNC
                             # (at most 200 SYNCs back: the counter repeats after 240)
CATCH_UP_S = 0.05            # SYNC slots a late producer still sends (echo only; sync_producer doc)
DELIVER_S = 0.004            # paced: the sample loop is woken once per this many seconds of samples
                             # (each wake-up of a thread costs the master ~20 us of CPU on a VM)

__all__ = ["ABORT_CONNECTION_QUICK_STOP", "CW_DISABLE_VOLTAGE", "CW_ENABLE", "CW_FAULT_RESET", "CW_QUICK_STOP",
           "CW_SHUTDOWN", "CW_SWITCH_ON", "CiA402Drive", "CiA402Network", "DEFAULT_EDS", "STATES",
           "SYNC_OVERFLOW", "load_eds", "load_model", "state_of"]


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
        self.late_syncs = 0             # SYNC slots never sent (the producer fell too far behind)
        self.syncs_sent_late = 0        # SYNCs sent over half a period late (caught up): timing faults
        self.sync_late_max_s = 0.0
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
        self._pending: dict[int, dict] = {}   # SYNC number -> its answers so far (counter echo, paced)
        self._delivered = 0             # the last SYNC number put in _ready (echo, paced)
        self._window = 1                # SYNCs back an echoed answer may still complete (start())
        self._echo = False              # every drive echoes the SYNC counter (start())
        self._deliver = 1               # samples ready before the sample loop is woken (start())
        self._keep = 256                # samples kept for a sample loop that fell behind (start())
        self._tpdo_nodes: list[int] = []
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
        model = load_model(config.description or DEFAULT_EDS, config.address,
                           profile_dir=(config.extra or {}).get("profile_dir"))
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
        self._window = max(1, min(SYNC_OVERFLOW - 40, round(LATE_ANSWER_S / period_s)))
        self._deliver = max(1, round(DELIVER_S / period_s))
        self._keep = max(256, round(READY_KEEP_S / period_s))
        self._echo = all(d._has_counter for d in self.drives.values())
        self._tpdo_nodes = sorted({cob & 0x7F for cob in self._formats})
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
                "late_syncs": self.late_syncs, "syncs_sent_late": self.syncs_sent_late,
                "sync_late_max_s": round(self.sync_late_max_s, 4),
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
            if self._produced and has_counter:
                self._answer(cob_id, values)
                return
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

    def _answer(self, cob_id: int, values: tuple) -> None:
        """An echoed answer (under ``_cv``, paced by a producer): to the latest SYNC with its
        counter, at most ``_window`` SYNCs back. Complete -> ``_ready``; the SYNCs before it
        that are still incomplete are lost then (samples stay in SYNC order)."""
        back = (self._expect - values[-1]) % SYNC_OVERFLOW if self._expect else 0
        number = self._sync_number - back
        if back >= self._window or number <= self._delivered:
            self.late_frames += 1          # its SYNC is already lost or delivered
            return
        got = self._pending.get(number)
        if got is None:
            got = self._pending[number] = {}
        elif cob_id in got:
            self.late_frames += 1          # a repeat (or an answer 240 SYNCs old): the first one stands
            return
        got[cob_id] = values
        if len(got) == len(self._formats):
            pending = self._pending
            for older in [n for n in pending if n <= number]:
                if older != number:
                    self.dropped_frames += len(self._formats) - len(pending[older])
                del pending[older]
            self._ready.append((number, got))
            self._delivered = number

    def _take_frames(self, frames: list) -> None:
        """Producer thread, once per period: every frame received since, in bus order (one
        lock, TPDOs decoded here; other frames to their canopen subscribers). The sample loop
        is woken once, if a sample became complete."""
        formats, subscribers, pending = self._formats, self.network.subscribers, self._pending
        ready_before = len(self._ready)
        heard = False
        with self._cv:
            for can_id, data, timestamp in frames:
                f = formats.get(can_id)
                if f is None:
                    for callback in subscribers.get(can_id, ()):
                        callback(can_id, data, timestamp)
                    continue
                heard = True
                fmt, has_counter = f
                if len(data) != fmt.size or not has_counter:   # the checks and bus-order rule of _on_tpdo
                    self._on_tpdo(can_id, data, timestamp)
                    continue
                values = fmt.unpack_from(data)
                got = pending.get(self._sync_number - (self._expect - values[-1]) % SYNC_OVERFLOW)
                if got is not None and can_id not in got and len(got) < len(formats) - 1:
                    got[can_id] = values       # the common case: not its SYNC's last answer (_answer)
                else:
                    self._answer(can_id, values)
            if len(self._ready) >= self._deliver > ready_before:
                self._cv.notify()
        if heard:      # any TPDO is proof of life of its node; one clock read per period
            now, last = time.monotonic(), self.liveness.last_heard
            for node in self._tpdo_nodes:
                last[node] = now

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
                self.sync_producer = start_sync_producer(
                    self.network, self.period_s, SYNC_OVERFLOW if self.sync_counter_byte else None,
                    self._begin_sync, kind, receive=self.options.get("receive", "cyclic") == "cyclic",
                    take=self._take_frames, catch_up_s=float(self.options.get("sync_catch_up_s", CATCH_UP_S))
                    if self._echo else 0.0)
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
            if self._pending:       # echoed answers not complete within the window: lost
                for old in [n for n in self._pending if n <= number - self._window]:
                    self.dropped_frames += len(self._formats) - len(self._pending.pop(old))
            while len(self._ready) > self._keep:       # a sample loop that far behind loses the oldest
                self._ready.popleft()

    def _discard_backlog(self) -> None:
        with self._cv:
            self._ready.clear()
            self._pending.clear()
            self._delivered = self._sync_number

    def _wait_produced(self) -> dict | None:
        """The next SYNC whose answers were all in before the SYNC after it (the bus's order
        decides, not how late this loop is); SYNCs without them are gaps: counted lost.
        None when none completed within a supervision period (the caller judges that)."""
        p, ready = self.sync_producer, self._ready
        # without the lock when samples are queued (a deque's popleft is atomic; the producer only
        # pops beyond 256 queued): most samples are taken so, four of every five at 1 kHz
        if ready or self._wait_ready():
            number, got = ready.popleft()
            self.sync_count, self.late_syncs = number, p.late
            self.syncs_sent_late, self.sync_late_max_s = p.sent_late, p.sent_late_max_s
            return got
        if p.idle_s() > self.silence_limit_s:     # outside the lock: stopping the drives needs the receiver
            self._fault(f"no SYNC seen on {self.bus_spec} for {self.silence_limit_s:g} s ({p.kind} producer)")
        return None

    def _wait_ready(self) -> bool:
        with self._cv:
            return bool(self._cv.wait_for(lambda: self._ready, HEALTH_PERIOD_S))

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
        p = self.sync_producer
        if p is not None and p.sent_late_by:    # sent late: the drives sampled then, not on the grid
            time_s += p.sent_late_by.pop(index, 0.0)
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
