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
``lockstep`` (False), ``master_timeout_ms`` (1000; 0 = off). A drive may override
``host``/``port`` in ``AxisConfig.extra`` (real drives usually have one IP each).

A tester PC that dies stops its drives: where the map declares the drive's
communication watchdog (``comm_timeout``, seconds), the master arms it against real
drives (not lockstep), so a drive that hears no request for that long quick-stops.
"""
from __future__ import annotations

import time

from pymodbus.client import ModbusTcpClient
from pymodbus.exceptions import ModbusException
from pymodbus.pdu import ExceptionResponse

from ..errors import BenchFault, DriveError
from .base import AxisConfig, Drive, DriveNetwork, Mode, Sample
from .register_map import SAMPLED, RegisterMap, load_register_map

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
        for d in self.drives.values():
            d.watch_master(0 if self.lockstep else self.master_timeout_ms / 1000.0)

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
        else:
            samples = {first.name: self._next_free_running(first)}
        for d in drives[1:]:
            samples[d.name] = d.read_sample()
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
        return {"skewed_samples": self.skewed_samples, "counter_skew_max": self.counter_skew_max,
                "if_the_master_dies": {n: d.master_watch for n, d in self.drives.items()}}

    def _next_free_running(self, drive: ModbusDrive) -> Sample:
        """Poll until the drive's counter reaches the next sampling instant."""
        deadline = time.monotonic() + max(0.1, 50 * self.period_s)
        while True:
            raw = drive.map.decode_block(drive.block_start, words := drive._read_block(), ("sample_counter",))
            counter = raw["sample_counter"]
            if self._last_counter is None or counter // drive._k > self._last_counter // drive._k or \
                    counter < self._last_counter:
                self._last_counter = counter
                return drive._to_sample(words)
            if time.monotonic() > deadline:
                raise DriveError(f"{drive!r}: sample counter stuck at {counter}; the drive is not running its "
                                 f"cycle (or, emulated, needs lockstep=True)")
            # sleep until the drive's clock enters the next sampling period (each read costs the
            # master ~150-300 us of CPU: polling every period/8 made it ~700 us per sample at 2 ms),
            # then poll finely; never spin: the other core has work too
            k, cp = drive._k, drive.map.counter_period_s
            time.sleep(max(self.period_s / 8, ((counter // k + 1) * k - counter) * cp))

    def _close(self) -> None:
        for d in self.drives.values():
            try:
                d.watch_master(0)      # an orderly end is not a lost master
            except Exception:
                pass
        for c in self._clients.values():
            c.close()
        self._clients.clear()
