"""Modbus TCP front-end of the emulated bench: unit ids 1 and 2 on one port.

A pymodbus server with one ``SimDevice`` per unit id, laid out by a register map
from ``drivers/``. Its action callback turns each request into the emulated drive:
reads get status, sample counter, position, velocity and current computed from
``bench.latest`` at that moment (one instant per request); writes go to the
axis's CiA 402 state machine (control, mode, targets in SI via the map's scale).

Communication watchdog (a map's optional ``comm_timeout`` register, seconds): once
armed, a unit that hears no request for that long quick-stops an enabled axis, as a
real drive whose master died (free-running only: in lockstep nothing moves without
the master's sync).

History (a map's ``history: {address, depth}``): after every drive cycle the sample block of
each unit is written into its ring entry ``counter mod depth``; a read inside the ring returns
the entries as written (what a drive with a trace ring does).

Time: free-running by default (a thread advances the world every period on the
monotonic clock, catching up when late). With ``lockstep=True`` the world
advances only when a master writes the ``sync`` register: writing n advances n
sample-counter periods, on whichever unit id (there is one world).
"""
from __future__ import annotations

import asyncio
import functools
import threading
import time

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from ..drives.register_map import RegisterMap, load_register_map
from ..errors import DriveError, ProfileError

DEFAULT_MAP = "drivers/generic-modbus-servo.yaml"
MAX_CATCH_UP = 200      # periods; beyond this the pacer gives up real time and resyncs
WATCHDOG_STALL_S = 0.05  # a pacer this late was stalled itself: it does not blame the master


class ModbusServerHandle:
    """A running Modbus front-end: ``host``, ``port`` (the bound one), ``stop()``."""

    def __init__(self, bench, regmap: RegisterMap, host: str, port: int, lockstep: bool):
        a, b = sorted((regmap.counter_period_s, bench.world.period_s))
        if abs(b / a - round(b / a)) > 1e-6 * b / a:
            raise ProfileError(f"{regmap.path}: registers.sample_counter.scale {regmap.counter_period_s:g} s and "
                               f"the bench period {bench.world.period_s:g} s are not whole multiples of each "
                               f"other; use a map whose counter period fits the simulation period")
        self.bench = bench
        self.map = regmap
        self.host = host
        self.port = port
        self.lockstep = lockstep
        self.overruns = 0          # free-running pacer resyncs (host too slow)
        self.lag_max_s = 0.0       # free-running: the furthest the world fell behind the wall clock
        self.late_periods = 0      # free-running: periods stepped over a period late (in a catch-up burst:
                                   # a master polling on time never saw them; the stand-in's losses)
        self.watchdog_s: dict[int, float] = {}      # unit -> armed comm_timeout
        self.last_request: dict[int, float] = {}    # unit -> monotonic time of its last request
        self.watchdog_trips = 0
        self._loop = asyncio.new_event_loop()
        self._server: ModbusTcpServer | None = None
        self._ready = threading.Event()
        self._stop = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._serve, name="modbus-emulator", daemon=True)
        self._pacer = None if lockstep else threading.Thread(target=self._pace, name="modbus-pacer", daemon=True)
        self._ring: dict[int, list[int]] = {}        # unit -> the history ring's words
        self._ring_counter = -1                       # the newest counter written into the rings
        if regmap.history:
            self._ring = {unit: [0] * (regmap.history[1] * regmap.entry_words) for unit in bench.axes}
            self._record()

    # --- lifecycle -------------------------------------------------------------
    def _start(self) -> "ModbusServerHandle":
        self._thread.start()
        self._ready.wait(10)
        if self._error is not None or self._server is None:
            raise DriveError(f"Modbus emulator cannot listen on {self.host}:{self.port} ({self._error}); "
                             f"choose a free port")
        if self._pacer:
            self._pacer.start()
        return self

    def _serve(self) -> None:
        asyncio.set_event_loop(self._loop)
        try:
            self._loop.run_until_complete(self._listen())
        except BaseException as exc:       # reported to the starting thread
            self._error = exc
            self._loop.close()
            self._ready.set()
            return
        self._ready.set()
        self._loop.run_forever()
        self._loop.run_until_complete(self._server.shutdown())
        self._loop.close()

    async def _listen(self) -> None:
        devices = [SimDevice(id=unit, simdata=self._layout(),
                             action=functools.partial(self._action, unit))
                   for unit in sorted(self.bench.axes)]
        # id 0 catches every other unit id: answer "gateway target failed to respond" (0x0B)
        devices.append(SimDevice(id=0, simdata=self._layout(), action=_no_such_unit))
        server = ModbusTcpServer(devices, address=(self.host, self.port))
        await server.serve_forever(background=True)
        if server.transport is None:
            raise OSError("listen failed")
        self.port = server.transport.sockets[0].getsockname()[1]
        self._server = server

    def _layout(self) -> list[SimData]:
        out = [SimData(address=r.address, count=r.words, datatype=DataType.REGISTERS,
                       readonly=r.access == "r") for r in self.map.registers.values()]
        if self.map.history:
            out.append(SimData(address=self.map.history[0], count=self.map.history[1] * self.map.entry_words,
                               datatype=DataType.REGISTERS, readonly=True))
        return out

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(5)
        if self._pacer and self._pacer.is_alive():
            self._pacer.join(5)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()

    # --- time --------------------------------------------------------------------
    def _pace(self) -> None:
        """Free-running: one world period per period of the monotonic clock."""
        period = self.bench.world.period_s
        next_t = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            if now - next_t > MAX_CATCH_UP * period:   # hopelessly late: resync, count it
                self.overruns += 1
                next_t = now
            elif now - next_t < WATCHDOG_STALL_S:      # judge the master only while we keep up
                self._watchdog(now)
            self.lag_max_s = max(self.lag_max_s, now - next_t)
            while next_t <= now:
                self.late_periods += now - next_t >= period
                self.bench.advance()
                self._record()
                next_t += period
            time.sleep(max(0.0, next_t - time.monotonic()))

    def _watchdog(self, now: float) -> None:
        for unit, limit_s in list(self.watchdog_s.items()):
            if limit_s > 0 and now - self.last_request.get(unit, now) > limit_s:
                self.watchdog_s[unit] = 0.0          # tripped once; the master re-arms it
                self.watchdog_trips += 1
                with self.bench.lock:
                    axis = self.bench.drive(unit)
                    if axis.state == "OPERATION ENABLED":
                        axis.write_controlword(self.map.control_values["quick_stop"])
                self.bench.log("modbus-watchdog", unit=unit, timeout_s=limit_s)

    # --- the emulated drive ----------------------------------------------------------
    async def _action(self, unit, function_code, start_address, address, count, registers, set_values):
        """pymodbus SimDevice action: apply writes, or fill the registers a read returns."""
        self.last_request[unit] = time.monotonic()
        while self.bench.axes[unit] in self.bench.muted and not self._stop.is_set():
            await asyncio.sleep(0.01)      # "mute" fixture: the drive stops answering
        faults = self.bench.modbus_faults  # fault injection: exception, slow answer, dropped connection
        if faults["disconnect"]:
            faults["disconnect"] = False
            self.bench.log("modbus-disconnect")
            for conn in list(self._server.active_connections.values()):
                conn.transport.close()
            return None
        if faults["count"] > 0 and (faults["exception"] or faults["delay_s"]):
            faults["count"] -= 1
            if faults["delay_s"]:
                await asyncio.sleep(faults["delay_s"])
            if faults["exception"]:
                return ExcCodes(faults["exception"])
        try:
            if set_values is not None:
                return self._write(unit, start_address, address, list(set_values), registers)
            self._fill(unit, start_address, registers, address, count)
        except ValueError:
            return ExcCodes.ILLEGAL_VALUE
        return None

    def _record(self) -> None:
        """Write this drive cycle's sample block into every unit's history ring (the counters the
        cycle spans, at most one turn of the ring)."""
        if not self._ring:
            return
        m = self.map
        start, words = m.span()
        ew, depth = m.entry_words, m.history[1]
        for unit, ring in self._ring.items():
            block = [0] * words
            counter = self._fill(unit, start, block)
            for n in range(max(self._ring_counter + 1, counter - depth + 1), counter + 1):
                block_n = list(block)
                self._put(block_n, start, "sample_counter", m.encode_raw("sample_counter", n, wrap=True))
                j = n % depth * ew
                ring[j:j + ew] = block_n
        self._ring_counter = counter

    def _fill(self, unit: int, start: int, registers: list[int], address: int = 0, count: int = 0) -> int:
        """Put the named registers of this instant into ``registers`` (whose first is ``start``), and
        the history ring as of the last drive cycle where the read (``address``, ``count``) reaches
        it. Returns the sample counter."""
        m, bench = self.map, self.bench
        if self._ring and address + count > m.history[0] and 0 <= (off := m.history[0] - start):
            registers[off:off + len(self._ring[unit])] = self._ring[unit]
        with bench.lock:
            axis = self.bench.drive(unit)
            meas = bench.latest.get(bench.axes[unit])     # None before the first step
            counter = round(bench.sample_index * bench.world.period_s / m.counter_period_s)
            values = {"status": (axis.statusword, False), "sample_counter": (counter, True),
                      "error_code": (axis.error_code, False)}
            si = ({"position": meas.position_rad, "velocity": meas.velocity_rad_s, "current": meas.current_a}
                  if meas is not None else {"position": 0.0, "velocity": 0.0, "current": 0.0})
        for name, (raw, wrap) in values.items():
            if name in m.registers:
                self._put(registers, start, name, m.encode_raw(name, raw, wrap=wrap))
        for name, value in si.items():
            self._put(registers, start, name, m.encode(name, value, wrap=True))
        return counter

    def _put(self, registers, start, name, words) -> None:
        off = self.map.registers[name].address - start
        if off < 0 or off + len(words) > len(registers):
            return                                  # not in this block (a map register outside it)
        registers[off:off + len(words)] = words

    def _write(self, unit, start, address, values, registers):
        m, bench = self.map, self.bench
        merged = list(registers)                   # registers as they will be after this write
        merged[address - start:address - start + len(values)] = values
        end = address + len(values)
        sync_n = 0
        with bench.lock:
            axis = self.bench.drive(unit)
            for reg in m.registers.values():
                if not reg.writable or reg.address >= end or reg.address + reg.words <= address:
                    continue
                off = reg.address - start
                raw = m.decode_raw(reg.name, merged[off:off + reg.words])
                if reg.name == "control":
                    axis.write_controlword(int(raw))
                elif reg.name == "mode":
                    axis.set_mode(int(raw))
                elif reg.name == "target_velocity":
                    axis.target_velocity_rad_s = raw * reg.scale
                elif reg.name == "target_current":
                    axis.target_current_a = raw * reg.scale
                elif reg.name == "sync":
                    sync_n = int(raw)
                elif reg.name == "comm_timeout":
                    self.watchdog_s[unit] = float(raw) * reg.scale
        if sync_n and self.lockstep:
            steps = sync_n * m.counter_period_s / bench.world.period_s
            if abs(steps - round(steps)) > 1e-6 or round(steps) < 1:
                return ExcCodes.ILLEGAL_VALUE
            for _ in range(round(steps)):
                bench.advance()
                self._record()
        return None


async def _no_such_unit(*_args):
    return ExcCodes.GATEWAY_NO_RESPONSE


def start_modbus_server(bench, host: str = "127.0.0.1", port: int = 5020, *,
                        register_map: str = DEFAULT_MAP, lockstep: bool = False) -> ModbusServerHandle:
    """Serve ``bench`` over Modbus TCP: unit ids = ``bench.axes`` keys (1 "in", 2 "out").

    ``port=0`` binds a free port; read it back from ``handle.port``. Runs its own
    asyncio loop in a daemon thread; ``handle.stop()`` ends it.
    """
    regmap = load_register_map(register_map)
    return ModbusServerHandle(bench, regmap, host, port, lockstep)._start()
