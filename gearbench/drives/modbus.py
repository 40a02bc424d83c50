"""Modbus TCP servo drives (pymodbus sync client), described by a register map.

Each drive is one Modbus unit id with a register map YAML from ``drivers/``
(``AxisConfig.description``). Per sample and drive, ONE multi-register read
returns status, sample counter, position, velocity and current of one instant.
The drive's sample counter is the time base: ``time_s = counter x counter
period`` (the map's ``sample_counter.scale``), never the host clock.

Lockstep (``ModbusNetwork(lockstep=True)``, for the emulated bench): before each
sample the master writes the map's ``sync`` register, which advances the bench
by one sampling period; the write and the first drive's read share one
read/write-multiple-registers request (function 0x17).

Options: ``host`` ("127.0.0.1"), ``port`` (502), ``timeout_s`` (1.0),
``lockstep`` (False), ``master_timeout_ms`` (1000; 0 = off), ``history`` (True: read the drives'
history rings where every map declares one; False: read them as drives without one). A drive may override
``host``/``port`` in ``AxisConfig.extra`` (real drives usually have one IP each).

Free-running (real drives): a Modbus drive keeps no history, so a sample the master
does not read within its sampling period (a "cell": ``period_s`` of the first drive's
sample counter) is lost. The master reads every drive's sample block ONCE per cell, at
a time on the wall clock locked to the first drive's counter (``PollSchedule``),
with TCP_NODELAY, raw on the client's own socket (a pymodbus request costs ~150-300 us
of CPU, a raw one tens of us). Drives with their own connection (one IP each) are read at
once; drives sharing one connection in turn (one request outstanding per connection).
The answer to a connection's last read is taken at the next read's wake-up, so the
master wakes once per sample. Lost, defined: a cell of the first drive's counter
between two samples taken that no read fell in (``lost_samples``).

Drive-side history (a map's ``history: {address, depth}``; network option ``history``, True:
used where every drive's map declares it): the drive keeps its last ``depth`` samples in a ring,
the sample of counter n at ``address + (n mod depth) * entry_words``, each entry laid out like
the sample block. The master then reads, at each wake-up, the ring entries of every cell since
the last one taken (normally one; after a host stall up to 125 registers in one read, split at
the ring's wrap), each checked by the counter it holds: a stall shorter than the ring loses
nothing (``recovered_from_history``: samples taken after their cell had ended, which a drive
without history would have lost); cells whose entries were overwritten before the master read
them are lost (``lost_history_overrun``).

A tester PC that dies stops its drives: where the map declares the drive's
communication watchdog (``comm_timeout``, seconds), the master arms it against real
drives (not lockstep), so a drive that hears no request for that long quick-stops.
"""
from __future__ import annotations

import socket
import struct
import time

from pymodbus.client import ModbusTcpClient
from pymodbus.exceptions import ModbusException
from pymodbus.pdu import ExceptionResponse

from ..errors import BenchFault, DriveError
from .base import AxisConfig, Drive, DriveNetwork, Mode, Sample
from .register_map import MAX_READ_WORDS, SAMPLED, RegisterMap, load_register_map

EXCEPTION_NAMES = {1: "illegal function", 2: "illegal data address", 3: "illegal data value",
                   4: "device failure", 5: "acknowledge", 6: "device busy",
                   10: "gateway path unavailable", 11: "gateway target failed to respond"}


class _Unwrap:
    """Undo the wrap-around of a free-running integer register (counter, position)."""

    def __init__(self, bits: int):
        self.modulus = 2**bits
        self.offset = 0
        self.last: int | None = None

    def __call__(self, raw: int) -> int:
        if self.last is not None:
            step = raw - self.last
            if step > self.modulus // 2:
                self.offset -= self.modulus
            elif step < -self.modulus // 2:
                self.offset += self.modulus
        self.last = raw
        return raw + self.offset


class ModbusDrive(Drive):
    """One servo axis: a unit id on a Modbus TCP endpoint, with its register map."""

    def __init__(self, config: AxisConfig, network: "ModbusNetwork", client: ModbusTcpClient,
                 endpoint: str):
        super().__init__(config)
        self.network = network
        self.map: RegisterMap = load_register_map(config.description)
        self.client = client
        self.unit = int(config.address)
        self.endpoint = endpoint
        self.mode: Mode | None = None
        self.block_start, self.block_words = self.map.span(SAMPLED)
        self._unwrap = {n: _Unwrap(16 * self.map.registers[n].words)
                        for n in ("sample_counter", "position") if self.map.registers[n].is_integer}
        self._k = 1   # counter periods per sampling period, set by start()
        self.master_watch = "not armed"

    def __repr__(self):
        return f"drive '{self.name}' (Modbus unit {self.unit} at {self.endpoint})"

    # --- low level: every request goes through _call -------------------------
    def _call(self, what: str, fn, *args, **kwargs):
        self.network._drain()     # an outstanding sample read's answer first: one connection, in order
        try:
            rr = fn(*args, device_id=self.unit, **kwargs)
        except ModbusException as exc:
            raise DriveError(f"{self!r}: no answer to {what} ({exc}); check the drive is powered, "
                             f"the address/unit id and the cable, or that `gearbench emulate` runs") from None
        if isinstance(rr, ExceptionResponse) or rr.isError():
            code = getattr(rr, "exception_code", 0)
            raise DriveError(f"{self!r}: Modbus exception {code} ({EXCEPTION_NAMES.get(code, 'unknown')}) "
                             f"to {what}; check the register map {self.map.path} against the drive manual")
        return rr

    def write(self, name: str, raw: int | float) -> None:
        """Write one raw value to a named register (one request)."""
        reg = self.map.registers[name]
        try:
            words = self.map.encode_raw(name, raw)
        except ValueError as exc:
            raise DriveError(f"{self!r}: {exc}") from None
        what = f"write {name}={raw} at {reg.address}"
        if len(words) == 1:
            self._call(what, self.client.write_register, reg.address, words[0])
        else:
            self._call(what, self.client.write_registers, reg.address, words)

    def read(self, name: str) -> int | float:
        reg = self.map.registers[name]
        rr = self._call(f"read {name} at {reg.address}", self.client.read_holding_registers,
                        reg.address, count=reg.words)
        return self.map.decode_raw(name, rr.registers)

    def _read_block(self, sync_words: list[int] | None = None) -> list[int]:
        what = f"read {', '.join(SAMPLED)} at {self.block_start}..{self.block_start + self.block_words - 1}"
        if sync_words is None:
            rr = self._call(what, self.client.read_holding_registers, self.block_start,
                            count=self.block_words)
        else:   # one request: write sync, then read the block (function 0x17)
            rr = self._call("sync + " + what, self.client.readwrite_registers,
                            read_address=self.block_start, read_count=self.block_words,
                            write_address=self.map.registers["sync"].address, values=sync_words)
        return rr.registers

    def _to_sample(self, words: list[int]) -> Sample:
        raw = self.map.decode_block(self.block_start, words)
        for n, unwrap in self._unwrap.items():
            raw[n] = unwrap(raw[n])
        counter = int(raw["sample_counter"])
        scale = {n: self.map.registers[n].scale for n in ("position", "velocity", "current")}
        status = int(raw["status"])
        # the sampling period's cell the counter is in (integral in lockstep; free-running at a
        # period of k counter periods, rounding made two successive cells one index)
        return Sample(index=counter // self._k, time_s=counter * self.map.counter_period_s,
                      position_rad=raw["position"] * scale["position"],
                      velocity_rad_s=raw["velocity"] * scale["velocity"],
                      current_a=raw["current"] * scale["current"],
                      status=status, fault=self.map.is_fault(status))

    def read_sample(self) -> Sample:
        return self._to_sample(self._read_block())

    # --- Drive protocol -------------------------------------------------------
    def enable(self, mode: Mode) -> None:
        mode = Mode(mode)
        for step in self.map.enable_sequence:
            self.write(step.register, self.map.sequence_value(step, mode.value))
        deadline = time.monotonic() + self.map.enable_timeout_s
        while True:
            status = int(self.read("status"))
            if self.map.is_fault(status):
                raise BenchFault(f"{self!r}: fault while enabling (status 0x{status:04X}{self._error_text()}); "
                                 f"clear the cause, then reset_fault()")
            if self.map.is_enabled(status):
                break
            if time.monotonic() > deadline:
                raise DriveError(f"{self!r}: not OPERATION ENABLED after the enable sequence of "
                                 f"{self.map.path} (status 0x{status:04X}); check the sequence and the drive's "
                                 f"enable inputs")
            if self.network.lockstep:
                self.network._sync()    # drive time passes only when the master syncs
            else:
                time.sleep(0.002)
        self.mode = mode

    def set_setpoint(self, value: float) -> None:
        if self.mode is None:
            raise DriveError(f"{self!r}: set_setpoint before enable(); enable the drive in a mode first")
        if self.mode is Mode.VELOCITY:
            name, limit, what = "target_velocity", self.config.speed_limit_rad_s, "speed_limit_rad_s"
        else:
            name, limit, what = "target_current", self.config.current_limit_a, "current_limit_a"
        if not abs(value) <= limit:
            raise DriveError(f"{self!r}: setpoint {value:g} beyond the axis limit {what}={limit:g}; "
                             f"lower the setpoint or raise the limit in the profile")
        reg = self.map.registers[name]
        raw = value / reg.scale
        self.write(name, round(raw) if reg.is_integer else raw)

    def quick_stop(self) -> None:
        self.write("control", self.map.control_values["quick_stop"])
        self.mode = None

    def disable(self) -> None:
        """Disable and read the status back: DriveError if the drive still shows enabled."""
        self.write("control", self.map.control_values["disable"])
        self.mode = None
        deadline = time.monotonic() + self.map.enable_timeout_s
        while True:
            status = int(self.read("status"))
            if not self.map.is_enabled(status) or self.map.is_fault(status):
                return
            if time.monotonic() > deadline:
                raise DriveError(f"{self!r}: still OPERATION ENABLED (status 0x{status:04X}) after the "
                                 f"disable command; stop it by its enable input / STO")
            if self.network.lockstep:
                self.network._sync()
            else:
                time.sleep(0.002)

    def watch_master(self, timeout_s: float) -> None:
        """Arm (``timeout_s`` > 0) or disarm (0) the drive's communication watchdog."""
        if "comm_timeout" not in self.map.registers:
            self.master_watch = f"not armed: {self.map.model} declares no comm_timeout register " \
                                f"(keeps its last command if the PC dies)"
            return
        reg = self.map.registers["comm_timeout"]
        self.write("comm_timeout", round(timeout_s / reg.scale))
        self.master_watch = (f"quick stop after {timeout_s * 1000:g} ms without a request" if timeout_s
                             else "not armed (lockstep: the emulated plant only moves on sync)")

    def reset_fault(self) -> None:
        # CiA 402 acts on the rising edge of the fault-reset bit
        self.write("control", self.map.control_values["disable"])
        self.write("control", self.map.control_values["fault_reset"])
        self.write("control", self.map.control_values["disable"])

    def _error_text(self) -> str:
        if "error_code" not in self.map.registers:
            return ""
        try:
            return f", error code 0x{int(self.read('error_code')):04X}"
        except DriveError:
            return ""


class PollSchedule:
    """When to read a free-running drive so that each read falls inside its sampling cell.

    Cell ``i`` of the drive's sample counter (``k`` counts of ``counter_period_s`` per sampling
    period) spans drive time ``[i*k, (i+1)*k) * counter_period_s``; the drive's clock is
    ``phase_s`` on the host clock (host time of drive time 0, minus the request's transit).
    Regular reads are sent ``lead`` into their cell, where a late wake-up has the rest of
    the cell before the read misses it and reads the cell's first count (the sample is
    stamped on the grid). Every ``probe_every``-th read (every one while locking) is a probe
    sent on the cell's start edge: whether the drive was still in the previous cell (the
    master reads again at once) or already in this one moves ``phase_s`` by ``step_s``
    toward the edge, so the schedule follows the drive's crystal
    (bang-bang phase tracking; ``step_s / (probe_every * period)`` is the drift it follows:
    625 ppm at the defaults) with no clock exchange the protocol does not have.

    Pure: no I/O; times in seconds on any monotonic host clock.
    """

    def __init__(self, counter_period_s: float, k: int, *, lead: float = 0.15, probe_every: int = 16,
                 step_s: float = 20e-6, lock_probes: int = 64):
        self.cp, self.k = counter_period_s, k
        self.period_s = k * counter_period_s
        self.lead_s = lead * self.period_s
        self.probe_every, self.step_s = probe_every, step_s
        self.phase_s: float | None = None
        self.lock_probes = lock_probes
        self._lock_left = lock_probes

    def lock(self, counter: int, t_sent_s: float) -> None:
        """First estimate: a read sent at ``t_sent_s`` saw ``counter`` change (the edge of that
        count lies between the previous read and this one)."""
        self.phase_s = t_sent_s - counter * self.cp

    def relock(self, counter: int, t_sent_s: float) -> None:
        """A read sent in time fell outside its cell: the drive's clock is not where the schedule
        has it (a drive whose clock jumped: the Python emulator catching up, a drive reset). Take
        the phase from this read (to within a counter period) and lock again with probes."""
        self.phase_s = t_sent_s - (counter + 0.5) * self.cp
        self._lock_left = max(self._lock_left, self.lock_probes)

    def is_probe(self, cell: int) -> bool:
        return self._lock_left > 0 or cell % self.probe_every == 0

    def due_s(self, cell: int) -> float:
        """Host time to send the read of ``cell``."""
        start = self.phase_s + cell * self.period_s
        return start if self.is_probe(cell) else start + self.lead_s

    def cell_end_s(self, cell: int) -> float:
        """Host time the drive's ``cell`` ends (a read sent later cannot fall in it)."""
        return self.phase_s + (cell + 1) * self.period_s

    def observe(self, cell: int, counter: int) -> None:
        """A probe of ``cell`` read ``counter``: move the phase toward the edge (no-op otherwise)."""
        if not self.is_probe(cell):
            return
        self._lock_left = max(0, self._lock_left - 1)
        before_edge = counter < cell * self.k
        self.phase_s += self.step_s if before_edge else -self.step_s

class ModbusNetwork(DriveNetwork):
    """Modbus TCP endpoint(s) with their drives; see the module docstring."""

    family = "modbus"

    def __init__(self, **options):
        super().__init__(**options)
        self.host = str(options.get("host", "127.0.0.1"))
        self.port = int(options.get("port", 502))
        self.timeout_s = float(options.get("timeout_s", 1.0))
        self.lockstep = bool(options.get("lockstep", False))
        self.master_timeout_ms = int(options.get("master_timeout_ms", 1000))
        self._clients: dict[tuple[str, int], ModbusTcpClient] = {}
        self._sync_drive: ModbusDrive | None = None
        self._last_counter: int | None = None
        self._k = 1
        self.counter_skew_max = 0      # largest |index difference| between drives in one sample
        self.skewed_samples = 0
        self.schedule: PollSchedule | None = None
        self._groups: list = []        # free-running: (socket, request bytes, drives) per endpoint
        self._cell: int | None = None  # the next cell to read
        self._tid = 0
        self._buf = bytearray(4096)
        self._pending: tuple | None = None   # (cell, due, sent) of the read whose answer is not yet taken
        self._held: list = []          # samples taken (by _drain or a late read) but not yet returned
        self._sent: list = []
        self._words: dict = {}
        self._t_sent = 0.0             # when the reads started going out
        self._t_out = 0.0              # when the last of them had been handed to the kernel
        self.polls_late = 0            # reads that fell in a later cell than scheduled (a loss each)
        self.poll_late_max_s = 0.0     # the latest a read was sent after its due time
        self.repolls = 0               # reads that came too early (a probe before the cell) and were repeated
        self.lost_sent_late = 0        # cells lost because their read was sent after the cell had ended
        self.lost_misplaced = 0        # cells lost to a read sent in time that fell in a later cell
        self.use_history = bool(options.get("history", True))
        self._ring: bool = False       # free-running from the drives' history rings (start())
        self._req_next = 0             # history: the cell after the last one requested
        self.recovered_from_history = 0   # samples read from the ring after their cell had ended
        self.lost_history_overrun = 0  # cells whose ring entry was overwritten before it was read
        self.history_stale = 0         # ring entries read before the drive wrote them (read again)
        self.history_entries_max = 0   # most ring entries read in one request

    def _client(self, host: str, port: int) -> ModbusTcpClient:
        key = (host, port)
        if key not in self._clients:
            client = ModbusTcpClient(host, port=port, timeout=self.timeout_s, retries=0,
                                     reconnect_delay=0)
            if not client.connect():
                raise DriveError(f"cannot connect to Modbus TCP {host}:{port} (refused or no route); "
                                 f"check the address, that the drive is powered, or start `gearbench emulate`")
            self._clients[key] = client
        return self._clients[key]

    def open(self) -> None:
        self._client(self.host, self.port)

    def add_drive(self, config: AxisConfig) -> ModbusDrive:
        host = str(config.extra.get("host", self.host))
        port = int(config.extra.get("port", self.port))
        drive = ModbusDrive(config, self, self._client(host, port), f"{host}:{port}")
        self.drives[config.name] = drive
        return drive

    def start(self, period_s: float) -> None:
        """Sample every ``period_s``: a whole number of each drive's counter periods."""
        if not self.drives:
            raise DriveError("ModbusNetwork.start() without drives; add_drive() first")
        for d in self.drives.values():
            k = period_s / d.map.counter_period_s
            if round(k) < 1 or abs(k - round(k)) > 1e-6 * k:
                raise DriveError(f"{d!r}: sampling period {period_s:g} s is not a whole multiple of the "
                                 f"drive's counter period {d.map.counter_period_s:g} s ({d.map.path}); "
                                 f"choose a multiple")
            d._k = round(k)
        if self.lockstep:
            self._sync_drive = next((d for d in self.drives.values() if "sync" in d.map.registers), None)
            if self._sync_drive is None:
                raise DriveError("lockstep asked but no drive's register map declares a `sync` register; "
                                 "open the network with lockstep=False or add `sync` to the map")
        self.period_s = period_s
        self._last_index = None
        self._last_counter = None
        self._drain()
        self._cell = None
        self._held.clear()
        for d in self.drives.values():
            d.watch_master(0 if self.lockstep else self.master_timeout_ms / 1000.0)
        if not self.lockstep:
            first = next(iter(self.drives.values()))
            self.schedule = PollSchedule(first.map.counter_period_s, first._k)
            self._ring = self.use_history and all(d.map.history for d in self.drives.values())
            self._groups = []
            for client in {id(d.client): d.client for d in self.drives.values()}.values():
                drives = [d for d in self.drives.values() if d.client is client]
                sock = client.socket
                if sock is None:
                    raise DriveError(f"{drives[0]!r}: not connected; check the drive is powered")
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)   # each request goes out at once
                self._groups.append((sock, drives))

    def _sync(self) -> None:
        d = self._sync_drive or next((d for d in self.drives.values() if "sync" in d.map.registers), None)
        if d is None:
            raise DriveError("lockstep asked but no drive's register map declares a `sync` register; "
                             "open the network with lockstep=False or add `sync` to the map")
        d.write("sync", d._k)

    def _sample(self) -> dict[str, Sample]:
        drives = list(self.drives.values())
        first = drives[0]
        if self.lockstep:
            sync = self._sync_drive
            words = sync.map.encode_raw("sync", sync._k)
            if sync is first:
                samples = {first.name: first._to_sample(first._read_block(words))}
            else:
                sync.write("sync", sync._k)
                samples = {first.name: first.read_sample()}
            for d in drives[1:]:
                samples[d.name] = d.read_sample()
        else:
            samples = self._next_free_running()
        # every drive's own counter is checked: one sample must be one instant on every drive
        skew = max(abs(s.index - samples[first.name].index) for s in samples.values())
        if skew:
            self.skewed_samples += 1
            self.counter_skew_max = max(self.counter_skew_max, skew)
            if self.lockstep:     # lockstep advances every drive together: a skew is a broken bench
                stopped = self.stop_all()
                raise BenchFault(f"sample counters differ by {skew} between drives in lockstep "
                                 f"({', '.join(f'{n}={s.index}' for n, s in samples.items())}); {stopped}")
        faulted = [d for d in drives if samples[d.name].fault]
        if faulted:
            texts = [f"{d!r} status 0x{samples[d.name].status:04X}{d._error_text()}" for d in faulted]
            stopped = self.stop_all()
            exc = BenchFault(f"drive fault at sample {samples[faulted[0].name].index}: {'; '.join(texts)}; "
                             f"{stopped}")
            exc.samples = samples
            raise exc
        return samples

    def supervision(self) -> dict:
        out = {"skewed_samples": self.skewed_samples, "counter_skew_max": self.counter_skew_max,
               "if_the_master_dies": {n: d.master_watch for n, d in self.drives.items()}}
        if not self.lockstep:
            out.update(polls_late=self.polls_late, poll_late_max_s=self.poll_late_max_s, repolls=self.repolls,
                       lost_sent_late=self.lost_sent_late, lost_misplaced=self.lost_misplaced,
                       history=(", ".join(f"{n}: ring of {d.map.history[1]} samples" for n, d in self.drives.items())
                                if self._ring else "none (the read is the sample)"),
                       recovered_from_history=self.recovered_from_history,
                       lost_history_overrun=self.lost_history_overrun, history_stale=self.history_stale,
                       history_entries_max=self.history_entries_max)
        return out

    def _next_free_running(self) -> dict[str, Sample]:
        """Every drive's sample block in the next cell of the first drive's counter, read when
        ``schedule`` says (see the module docstring); a cell passed while the master was not run
        is lost (counted by ``sample()`` from the counter gap).

        One wake-up per sample: the answer to a regular read is taken at the next read's due time
        (it arrived long before), just before that read is sent; so its sample is returned one
        period after the read. A probe's answer is awaited (one read in 16: a probe that came
        before its cell is repeated at once). A request of pymodbus's on the same connection first
        takes the answer outstanding (``_drain``) and keeps its sample for the next call."""
        if self._held:
            return self._held.pop(0)
        if self._ring:
            return self._next_from_history()
        sched = self.schedule
        if self._cell is None:
            return self._lock()
        while True:
            due = sched.due_s(self._cell)
            now = time.monotonic()
            if due > now:
                time.sleep(due - now)
            result = self._take_pending()
            if result is not None and sched.due_s(self._cell) > time.monotonic() + sched.cp / 8:
                self._held.append(result)        # the read fell in a later cell: the next is later too
                continue
            due = max(due, sched.due_s(self._cell))  # a cell read again goes out now, not "late"
            if sched.is_probe(self._cell):
                self._held.extend(r for r in (result, self._probe(due)) if r is not None)
                if self._held:
                    return self._held.pop(0)
                continue
            self._send_reads()
            self._pending = (self._cell, due, self._t_sent, self._t_out)
            self._cell += 1
            if result is not None:
                return result
            if self._held:
                return self._held.pop(0)

    def _next_from_history(self) -> dict[str, Sample]:
        """The next sample from the drives' history rings: one wake-up per cell, ``lead`` into it;
        the answer to a wake-up's read is taken at the next one, which then asks for every cell from
        the first not yet taken to the current one (see the module docstring)."""
        sched = self.schedule
        if self._cell is None:
            self._lock()                    # the block read may be off the grid: the ring starts after it
            self._req_next = self._cell
        while not self._held:
            cell = self._req_next if self._pending is not None else self._cell
            due = sched.phase_s + cell * sched.period_s + sched.lead_s
            now = time.monotonic()
            if due > now:
                time.sleep(due - now)
                self.poll_late_max_s = max(self.poll_late_max_s, time.monotonic() - due)
            self._take_pending()           # fills _held, moves _cell
            if sched.phase_s + self._cell * sched.period_s <= time.monotonic():
                self._send_history()       # (a drive ahead of the schedule gave a cell not yet due)
        return self._held.pop(0)

    def _send_history(self) -> None:
        """Ask every drive for the ring entries from cell ``_cell`` to the current one (by the
        schedule), at most one read's worth and not past the ring's wrap; cells already overwritten
        are counted lost and skipped."""
        first, sched = next(iter(self.drives.values())), self.schedule
        k, (_, depth) = first._k, first.map.history
        now_cell = max(self._cell, int((time.monotonic() - sched.phase_s) // sched.period_s))
        oldest = now_cell - depth // k + 2      # older cells' entries are (being) overwritten
        if self._cell < oldest:
            self.lost_history_overrun += oldest - self._cell
            self._cell = oldest
        a = self._cell * k                      # the first entry's counter
        # every probe_every-th cell one entry more, the next cell's first: there only if the drive's
        # clock runs ahead of the schedule (which then moves); a read before its entry was written
        # says the schedule runs ahead of the drive (see _take_history)
        ahead = now_cell % sched.probe_every == 0
        n = min((now_cell + ahead - self._cell) * k + 1, MAX_READ_WORDS // first.map.entry_words, depth - a % depth)
        self._send_reads({d.name: (d.map.history_address(a), n * d.map.entry_words) for d in self.drives.values()})
        self.history_entries_max = max(self.history_entries_max, n)
        self._pending = ("history", a, n, self._t_sent, now_cell * k)
        self._req_next = min((a + n - 1) // k + 1, now_cell + 1)

    def _take_history(self, a: int, n: int, t_sent: float, due_counter: int, words: dict) -> None:
        """Ring entries ``a .. a+n-1`` (counters) as read at ``t_sent``, ``due_counter`` the newest one
        the schedule had the drive at: each valid entry of a cell's first count is a sample (to
        ``_held``); an entry the drive had not written yet ends the take (read again next time); one
        already overwritten is a lost cell. Entries not where the schedule has them move its phase."""
        first, sched = next(iter(self.drives.values())), self.schedule
        k, ew = first._k, first.map.entry_words
        modulus = 2 ** (16 * first.map.registers["sample_counter"].words)
        for i in range(n):
            counter = a + i
            held = (self._counter(first, words[first.name][i * ew:(i + 1) * ew]) - counter) % modulus
            if held > modulus // 2:            # an older sample: the drive had not reached this one
                if counter <= due_counter:
                    self.history_stale += 1
                    sched.phase_s += sched.step_s    # the schedule runs ahead of the drive's clock
                break
            if counter > due_counter and not held:
                sched.phase_s -= sched.step_s        # the drive's clock runs ahead of the schedule
            self._cell = counter // k + 1
            if held:                           # overwritten by a newer turn of the ring
                self.lost_history_overrun += counter % k == 0
                continue
            if counter % k:
                continue
            if t_sent >= sched.cell_end_s(counter // k):
                self.recovered_from_history += 1
            self._held.append({d.name: d._to_sample(words[d.name][i * (w := d.map.entry_words):(i + 1) * w])
                               for d in self.drives.values()})

    def _lock(self) -> dict[str, Sample]:
        """Lock the schedule on the first drive's next counter edge (reads every 1/8 counter period)."""
        first, sched = next(iter(self.drives.values())), self.schedule
        words = self._read_all()
        c0 = self._counter(first, words[first.name])
        deadline = time.monotonic() + max(0.1, 50 * self.period_s)
        while True:
            time.sleep(sched.cp / 8)
            words = self._read_all()
            c = self._counter(first, words[first.name])
            if c != c0:
                break
            if time.monotonic() > deadline:
                raise DriveError(f"{first!r}: sample counter stuck at {c}; the drive is not running its "
                                 f"cycle (or, emulated, needs lockstep=True)")
        sched.lock(c, self._t_sent)
        self._cell = c // first._k + 1
        return self._samples(words)

    def _probe(self, due: float) -> dict[str, Sample] | None:
        """Read the probe cell on its start edge and wait for the answer; a read that came before
        the edge (the drive still in the previous cell) is repeated after 1/16 counter period."""
        expected, sched = self._cell, self.schedule
        deadline = time.monotonic() + max(0.1, 50 * self.period_s)
        while True:
            self._send_reads()
            out = self._account(expected, due, self._t_sent, self._t_out, self._receive_reads())
            if out is not None or self._cell != expected:
                return out
            if time.monotonic() > deadline:
                first = next(iter(self.drives.values()))
                raise DriveError(f"{first!r}: sample counter does not reach cell {expected}; the drive is not "
                                 f"running its cycle")
            time.sleep(sched.cp / 16)
            due = time.monotonic()

    def _take_pending(self) -> dict[str, Sample] | None:
        """The outstanding regular read's samples, checked against its cell (``_account``)."""
        if self._pending is None:
            return None
        if self._pending[0] == "history":
            _, a, n, t_sent, due_counter = self._pending
            self._pending = None
            self._take_history(a, n, t_sent, due_counter, self._receive_reads())
            return None
        expected, due, t_sent, t_out = self._pending
        self._pending = None
        return self._account(expected, due, t_sent, t_out, self._receive_reads())

    def _account(self, expected: int, due: float, t_sent: float, t_out: float,
                 words: dict) -> dict[str, Sample] | None:
        """The samples of a read meant for cell ``expected``, sent from ``t_sent`` to ``t_out`` (due
        ``due``); None when it fell before that cell (it is read again). Lateness and losses are
        counted."""
        first, sched = next(iter(self.drives.values())), self.schedule
        self.poll_late_max_s = max(self.poll_late_max_s, t_sent - due)
        c = self._counter(first, words[first.name])
        cell = c // first._k
        if cell < expected:
            if sched.is_probe(expected):
                sched.observe(expected, c)       # a probe on the cell's start edge, just early
            else:
                sched.relock(c, t_sent)          # the drive's clock is behind the schedule
            self.repolls += 1
            self._cell = expected
            return None
        if cell == expected:
            sched.observe(cell, c)
        else:
            self.polls_late += 1
            # sent after its cell had ended: the master was not run in time (a host stall, as the
            # host timer floor shows; one between the stamp and the send counts: t_out); else the
            # drive's clock was ahead of the schedule
            if t_out >= sched.cell_end_s(expected):
                self.lost_sent_late += cell - expected
            else:
                self.lost_misplaced += cell - expected
                sched.relock(c, t_sent)
        self._cell = max(self._cell, cell + 1)
        return self._samples(words)

    def _drain(self) -> None:
        """Take the outstanding sample read's answer (before any other request on the connection)."""
        if self._pending is not None:
            result = self._take_pending()
            if result is not None:
                self._held.append(result)

    def _discard_backlog(self) -> None:
        """Samples read before now are not the next acquisition's; it starts at the next cell."""
        self._drain()
        self._held.clear()
        if self._cell is not None:     # the cells between (a pause between segments) were never due
            sched = self.schedule
            self._cell = max(self._cell, int((time.monotonic() - sched.phase_s) // sched.period_s) + 1)

    def _counter(self, drive: ModbusDrive, words) -> int:
        reg = drive.map.registers["sample_counter"]
        off = reg.address - drive.block_start
        return int(drive.map.decode_raw("sample_counter", words[off:off + reg.words]))

    def _samples(self, words: dict) -> dict[str, Sample]:
        return {d.name: d._to_sample(words[d.name]) for d in self.drives.values()}

    def _read_all(self) -> dict[str, tuple]:
        """Every drive's sample block, now (send, then wait for the answers)."""
        self._send_reads()
        return self._receive_reads()

    def _send_reads(self, spans: dict | None = None) -> None:
        """Every drive's sample read; ``_t_sent`` = when it started, ``_t_out`` = when the last
        request had been handed to the kernel (a host stall in between makes a read late, not
        misplaced). One request outstanding per connection (a Modbus TCP server may take one at a
        time: pymodbus's answers only the first of two sent together), so the reads of drives on different connections (real drives: one IP each) go
        out together, those sharing one are read in turn, and only each connection's last read is
        left outstanding (``_receive_reads`` takes its answer)."""
        self._t_sent = time.monotonic()
        sent, self._words = [], {}
        for sock, drives in self._groups:
            if sock.gettimeout() is not None:
                # blocking, with the timeout in the kernel (SO_RCVTIMEO): one recv per answer, where a
                # Python timeout is a poll() and a recv; pymodbus leaves its socket non-blocking
                sock.settimeout(None)
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO,
                                struct.pack("ll", int(self.timeout_s), int(self.timeout_s % 1 * 1e6)))
            for d in drives[:-1]:
                self._words[d.name] = self._receive(sock, d, self._request(sock, d, spans))
            sent.append((sock, drives[-1], self._request(sock, drives[-1], spans)))
        self._sent = sent
        self._t_out = time.monotonic()

    def _request(self, sock: socket.socket, d: ModbusDrive, spans: dict | None = None) -> int:
        """Send a read of ``d``'s sample block (or of ``spans[d.name]`` = (address, words))."""
        self._tid = (self._tid + 1) & 0x7FFF
        tid = 0x8000 | self._tid                    # apart from pymodbus's own transaction ids
        address, count = spans[d.name] if spans else (d.block_start, d.block_words)
        try:
            sock.sendall(struct.pack(">HHHBBHH", tid, 0, 6, d.unit, 3, address, count))
        except OSError as exc:
            raise DriveError(f"{d!r}: cannot send the sample read ({exc}); check the cable and "
                             f"that the drive is powered") from None
        return tid

    def _receive_reads(self) -> dict[str, tuple]:
        words, sent, self._sent = self._words, self._sent, []
        for sock, d, tid in sent:
            words[d.name] = self._receive(sock, d, tid)
        return words

    def _receive(self, sock: socket.socket, d: ModbusDrive, tid: int) -> tuple:
        """The answer to request ``tid``: the words of ``d``'s sample block."""
        buf, view, got = self._buf, memoryview(self._buf), 0
        need = 7
        while True:
            if got >= 7:
                need = 6 + (buf[4] << 8 | buf[5])
                if need <= 8 or need > len(buf):
                    raise DriveError(f"{d!r}: malformed Modbus TCP answer (length {need - 6})")
            if got >= need:
                break
            try:
                n = sock.recv_into(view[got:need], need - got)
            except (BlockingIOError, socket.timeout):
                raise DriveError(f"{d!r}: no answer to the sample read within {self.timeout_s:g} s; check the "
                                 f"drive is powered, the address/unit id and the cable") from None
            if n == 0:
                raise DriveError(f"{d!r}: the drive closed the connection during a sample read; check the "
                                 f"drive (a watchdog, a reboot) and the cable")
            got += n
        r_tid, _, _, unit, fc = struct.unpack_from(">HHHBB", buf)
        if r_tid != tid or unit != d.unit:
            raise DriveError(f"{d!r}: answer to another request (transaction {r_tid}, unit {unit}; expected "
                             f"{tid}, unit {d.unit}); a second master on the same connection?")
        if fc & 0x80:
            code = buf[8]
            raise DriveError(f"{d!r}: Modbus exception {code} ({EXCEPTION_NAMES.get(code, 'unknown')}) to the "
                             f"sample read at {d.block_start}; check the register map {d.map.path} against the "
                             f"drive manual")
        return struct.unpack_from(f">{buf[8] // 2}H", buf, 9)

    def _close(self) -> None:
        for d in self.drives.values():
            try:
                d.watch_master(0)      # an orderly end is not a lost master
            except Exception:
                pass
        for c in self._clients.values():
            c.close()
        self._clients.clear()
