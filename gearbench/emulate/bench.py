"""One simulated two-motor bench behind any number of drive front-ends.

``EmulatedBench`` owns the physics world (``gearbench.sim.BenchWorld``) and one
``Cia402Axis`` per drive; the CANopen and Modbus front-ends only translate their
protocol into calls on these, under ``lock``. ``advance()`` is the one place time
moves: drive commands -> one physics period -> drive protections.

Fixture commands (one JSON object per line on ``gearbench emulate``'s stdin; the
reply is one JSON line ``{"ok": true, ...}`` or ``{"ok": false, "error": ...}``):

- ``{"cmd": "mount", "coupling": "none"|"reducer", "disk_kgm2": {"in": 1.5e-5, "out": 0}}``
- ``{"cmd": "fault", "axis": "in", "code": 8976, "at_s": 0.5}`` — drive fault now or
  at world time ``at_s`` (EMCY with ``code``; 8976 = 0x2310 over-current);
- ``{"cmd": "drop", "rate": 0.1}`` — each TPDO frame is dropped with this probability;
- ``{"cmd": "mute", "axis": "in", "on": true}`` — the drive stops answering (no PDO,
  SDO or heartbeat), like a cut cable;
- ``{"cmd": "status"}`` — sample index, time, states and modes.
- ``{"cmd": "pdo", "on": false}`` — no TPDO is sent on SYNC any more (the plant still runs;
  SDO, heartbeat and EMCY go on): another stand-in answers SYNC (the benchmark's compiled
  responder, ``tools/responder``).

Fault injection (test facility of ``gearbench.emulate.faults``; any command but ``status``
may carry ``"at_s"``: it is then applied when world time reaches it, between two steps):

- ``{"cmd": "heartbeat", "axis": "in", "on": false}`` — only the heartbeat stops (PDOs, SDO
  and EMCY go on);
- ``{"cmd": "refuse_disable", "axis": "out", "on": true}`` — the axis ignores every
  controlword while OPERATION ENABLED (a drive that will not disable);
- ``{"cmd": "modbus", "exception": 4, "delay_s": 0.2, "count": 3, "disconnect": true}`` — the
  next ``count`` Modbus requests are answered with that exception code and/or after
  ``delay_s``; ``disconnect`` closes the master's TCP connections once;
- ``{"cmd": "mark", "label": "..."}`` — nothing happens but the journal line (an instant
  for the harness to act on, e.g. send a signal to gearbench).

Journal: with ``journal`` set to a text file, every axis state change and every applied
command is one JSON line ``{"t_s": world time, "wall_s": time.time(), "event": ...}``,
flushed at once (it survives any death of the master).
"""
from __future__ import annotations

import json
import random
import threading
import time

from .cia402_axis import Cia402Axis

AXES = {1: "in", 2: "out"}   # drive address (CANopen node id / Modbus unit id) -> axis


class EmulatedBench:
    """One BenchWorld behind any number of drive front-ends; thread-safe via ``lock``."""

    def __init__(self, plant=None, *, seed: int = 0, world=None):
        if world is None:
            from ..sim import BenchWorld, PlantParams
            plant = plant if plant is not None else PlantParams()
            world = BenchWorld(plant, seed=seed)
        self.plant = plant
        self.world = world
        self.lock = threading.RLock()
        self.axes: dict[int, str] = dict(AXES)
        self.drives: dict[str, Cia402Axis] = {}
        for name in self.axes.values():
            motor = getattr(plant, f"motor_{name}", None) if plant is not None else None
            self.drives[name] = Cia402Axis(
                name,
                rated_current_a=getattr(motor, "rated_current_a", 1.0),
                max_current_a=getattr(motor, "current_limit_a", 3.0),
                speed_limit_rad_s=getattr(motor, "speed_limit_rad_s", 420.0),
                counts_per_rev=getattr(motor, "counts_per_rev", 10000))
            self.drives[name].period_s = world.period_s
        self.latest: dict = {}
        self._world_modes: dict[str, str] = {}
        self.sample_index = 0
        # fault options for tests of the masters' error handling
        self.pdo_drop_rate = 0.0
        self.muted: set[str] = set()
        self.heartbeat_muted: set[str] = set()
        self.pdo_on = True
        self.modbus_faults = {"exception": 0, "delay_s": 0.0, "count": 0, "disconnect": False}
        self._scheduled: list[tuple[float, dict]] = []
        self._rng = random.Random(seed)
        self.journal = None                       # text file: one JSON line per event
        self.counters: dict = {}                  # the front-ends' own counters (e.g. SYNCs heard/missed), in status
        for axis in self.drives.values():
            axis.state_listeners.append(
                lambda a, old, new: self.log("state", axis=a.name, old=old, new=new))

    def log(self, event: str, **fields) -> None:
        """One journal line (fault-injection harness), written and flushed at once."""
        if self.journal is None:
            return
        line = json.dumps({"t_s": round(self.sample_index * self.world.period_s, 6),
                           "wall_s": time.time(), "event": event, **fields})
        try:
            self.journal.write(line + "\n")
            self.journal.flush()
        except (OSError, ValueError):   # a closed journal never stops the drives
            pass

    @property
    def period_s(self) -> float:
        return self.world.period_s

    def drive(self, address: int) -> Cia402Axis:
        return self.drives[self.axes[address]]

    def advance(self, steps: int = 1) -> dict:
        """Advance ``steps`` periods (lockstep); returns the last measurements."""
        with self.lock:
            for _ in range(steps):
                time_s = (self.sample_index + 1) * self.world.period_s
                for due in [f for f in self._scheduled if f[0] <= time_s + 1e-12]:
                    self._scheduled.remove(due)
                    self._handle(due[1])
                for name, axis in self.drives.items():
                    mode, setpoint = axis.command()
                    if mode != self._world_modes.get(name):   # set_mode resets the drive loop
                        self.world.set_mode(name, mode)
                        self._world_modes[name] = mode
                    self.world.set_setpoint(name, setpoint)
                self.latest = self.world.step()
                self.sample_index += 1
                for name, axis in self.drives.items():
                    m = self.latest[name]
                    axis.observe(m.velocity_rad_s, m.current_cmd_a)
            return self.latest

    def drop_frame(self) -> bool:
        """True when the PDO drop option says this frame is lost."""
        return self.pdo_drop_rate > 0 and self._rng.random() < self.pdo_drop_rate

    # ------------------------------------------------------------- fixture commands
    def handle_control_line(self, line: str) -> str:
        try:
            reply = self._handle(json.loads(line))
            return json.dumps({"ok": True, **reply})
        except Exception as exc:   # a fixture mistake must not stop the emulator
            return json.dumps({"ok": False, "error": f"{type(exc).__name__}: {exc}"})

    def _axis_name(self, cmd: dict) -> str:
        name = cmd.get("axis")
        if name not in self.drives:
            raise ValueError(f"'axis' must be one of {sorted(self.drives)}, got {name!r}")
        return name

    def _handle(self, cmd: dict) -> dict:
        with self.lock:
            if "at_s" in cmd and cmd.get("cmd") != "status":
                at_s = float(cmd["at_s"])
                cmd = {k: v for k, v in cmd.items() if k != "at_s"}
                self._apply(cmd, dry=True)          # refuse a bad command now, not at its time
                self._scheduled.append((at_s, cmd))
                return {"scheduled_at_s": at_s}
            reply = self._apply(cmd)
            if cmd.get("cmd") != "status":
                self.log("command", **cmd)
            return reply

    def _apply(self, cmd: dict, dry: bool = False) -> dict:
        kind = cmd.get("cmd")
        if kind in ("fault", "mute", "heartbeat", "refuse_disable"):
            name = self._axis_name(cmd)
        if kind == "mount":
            if not dry:
                self.world.mount(coupling=cmd.get("coupling", "none"), disk_kgm2=cmd.get("disk_kgm2"))
            return {}
        if kind == "fault":
            code = int(cmd.get("code", 0x1000))
            if not dry:
                self.drives[name].inject_fault(code)
            return {}
        if kind == "drop":
            rate = float(cmd["rate"])
            if not 0 <= rate <= 1:
                raise ValueError("'rate' must be within 0..1")
            if not dry:
                self.pdo_drop_rate = rate
            return {}
        if kind == "mute" and not dry:          # "on": muted
            (self.muted.add if cmd.get("on", True) else self.muted.discard)(name)
        if kind == "heartbeat" and not dry:     # "on": heartbeats produced
            (self.heartbeat_muted.discard if cmd.get("on", True) else self.heartbeat_muted.add)(name)
        if kind in ("mute", "heartbeat"):
            return {}
        if kind == "refuse_disable":
            if not dry:
                self.drives[name].refuse_disable = bool(cmd.get("on", True))
            return {}
        if kind == "modbus":
            faults = {"exception": int(cmd.get("exception", 0)), "delay_s": float(cmd.get("delay_s", 0.0)),
                      "count": int(cmd.get("count", 1)), "disconnect": bool(cmd.get("disconnect", False))}
            if not dry:
                self.modbus_faults = faults
            return {}
        if kind == "mark":
            return {}
        if kind == "pdo":
            if not dry:
                self.pdo_on = bool(cmd.get("on", True))
            return {}
        if kind == "status":
            return {"sample_index": self.sample_index,
                    "time_s": self.sample_index * self.world.period_s,
                    "drives": {n: a.snapshot() for n, a in self.drives.items()},
                    "counters": dict(self.counters)}
        raise ValueError(f"unknown cmd {kind!r}; known: mount, fault, drop, mute, heartbeat, "
                         f"refuse_disable, modbus, mark, pdo, status")

    def run_control_loop(self, stdin, stdout) -> threading.Thread:
        """Serve fixture commands from ``stdin`` in a daemon thread until EOF."""
        def loop():
            for line in stdin:
                if line.strip():
                    stdout.write(self.handle_control_line(line) + "\n")
                    stdout.flush()
        t = threading.Thread(target=loop, name="emulate-fixture", daemon=True)
        t.start()
        return t
