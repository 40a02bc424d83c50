"""``--sim``: the emulated bench in a child process, behind real protocol endpoints.

The child is ``gearbench emulate`` (CANopen nodes over udp_multicast by default,
over the profile's own bus when it is a host's virtual CAN ``socketcan`` ``vcan*``,
or Modbus TCP on loopback when the profile's bus is Modbus). The sequencer then
talks to it through the same drive stack it uses on a real tester. The operator's
mounting is done by the child on request (fixture commands on its stdin).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import replace

from ..drives.buses import free_udp_port
from ..errors import BenchFault, DriveError

# first start compiles the physics kernel (numba), later starts are fast; an emulated CI guest needs more
READY_TIMEOUT_S = float(os.environ.get("GEARBENCH_SIM_START_TIMEOUT_S", 60.0))
EMULATOR_NICE = -10      # the emulator stands in for drive hardware, which a busy PC does not slow down
# Supervision of emulated drives: they share this host's CPUs, and on a loaded tester PC a process is
# measured to wait up to ~2 s for a CPU even at nice -10 (load 16 on 2 cores). Real drives keep the
# profile's (default 0.5 s silence, 0.3 s SDO). A frozen emulated drive still stops the bench in 2 s.
SIM_SUPERVISION = {"timeout_s": 2.0, "sdo_timeout_s": 1.0}


def _child_setup() -> None:
    """In the emulator child before exec: a higher priority where the OS grants it."""
    try:
        os.setpriority(os.PRIO_PROCESS, 0, EMULATOR_NICE)
    except OSError:
        pass


class SimBench:
    """Context manager: starts the emulator, gives the bus options to use, mounts on request."""

    def __init__(self, profile, *, seed: int | None = None, simulation: str | None = None):
        self.profile = profile
        self.seed = seed
        self.simulation = simulation   # a YAML file whose simulation: block replaces the profile's
        self.proc: subprocess.Popen | None = None
        self.bus_options: dict = {}
        self._lines: list[str] = []
        self._cv = threading.Condition()

    def __enter__(self):
        bus = self.profile.bench.bus
        # --exit-on-eof: the child ends when our end of its stdin closes, i.e. when this
        # process ends for any reason, SIGKILL included (no orphan emulator on the bus)
        cmd = [sys.executable, "-m", "gearbench", "emulate", str(self.profile.path), "--lockstep",
               "--exit-on-eof"]
        if bus.family == "modbus":
            maps = {str(m.drive) for m in self.profile.motors.values()}
            cmd += ["--modbus", "127.0.0.1:0", "--modbus-map", sorted(maps)[0]]   # the child binds, then says where
            self.bus_options = dict(host="127.0.0.1", lockstep=True)
        elif bus.interface == "socketcan" and (bus.channel or "").startswith("vcan"):
            # a virtual CAN bus of this host's kernel (CI's vcan0): the emulated drives join it
            cmd += ["--can", f"socketcan:{bus.channel}"]
            self.bus_options = dict(interface="socketcan", channel=bus.channel, lockstep=True)
        else:
            # a private multicast port per run: parallel runs on one host never cross-talk
            group = bus.channel if bus.interface == "udp_multicast" and bus.channel else "239.74.163.2"
            port = free_udp_port()
            cmd += ["--can", f"udp_multicast:{group}:{port}"]
            self.bus_options = dict(interface="udp_multicast", channel=group, port=port, lockstep=True)
        if self.seed is not None:
            cmd += ["--seed", str(self.seed)]
        if self.simulation:
            cmd += ["--simulation", str(self.simulation)]
        # test facility (gearbench.emulate.faults): a journal of the emulated drives' states, and
        # faults the emulator applies at given world times
        if os.environ.get("GEARBENCH_SIM_JOURNAL"):
            cmd += ["--journal", os.environ["GEARBENCH_SIM_JOURNAL"]]
        if os.environ.get("GEARBENCH_SIM_FAULT_PLAN"):
            cmd += ["--fault-plan", os.environ["GEARBENCH_SIM_FAULT_PLAN"]]
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        # the child's diagnostics go to a file: an unread pipe would fill and stall it
        keep = os.environ.get("GEARBENCH_EMULATOR_LOG")   # a path to keep the child's diagnostics
        self._log = open(keep, "w+") if keep else tempfile.TemporaryFile(mode="w+")
        try:
            # own session: a Ctrl-C at the terminal reaches gearbench, which stops the drives
            # through the emulator and then ends it, instead of killing the drives first
            self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                         stderr=self._log, text=True, env=env, start_new_session=True,
                                         preexec_fn=_child_setup)
            threading.Thread(target=self._reader, daemon=True).start()
            ready = self._wait_line(lambda ln: ln.split()[:1] == ["ready"], READY_TIMEOUT_S, "start")
        except BaseException:
            self.__exit__()       # never leave the child or its log behind
            raise
        for word in ready.split()[1:]:
            if word.startswith("modbus="):
                self.bus_options["port"] = int(word.rpartition(":")[2])
        return self

    def _reader(self) -> None:
        for line in self.proc.stdout:
            with self._cv:
                self._lines.append(line.strip())
                self._cv.notify_all()
        with self._cv:
            self._cv.notify_all()

    def _wait_line(self, pred, timeout: float, what: str) -> str:
        deadline = time.monotonic() + timeout
        with self._cv:
            while True:
                for i, ln in enumerate(self._lines):
                    if pred(ln):
                        del self._lines[: i + 1]
                        return ln
                if self.proc.poll() is not None:
                    self._log.seek(0)
                    err = self._log.read().strip().splitlines()
                    raise DriveError(f"simulated bench stopped during {what} (exit {self.proc.returncode})"
                                     f"{': ' + err[-1] if err else ''}")
                left = deadline - time.monotonic()
                if left <= 0:
                    raise DriveError(f"simulated bench did not answer {what} within {timeout:.0f} s")
                self._cv.wait(min(left, 0.2))

    def command(self, obj: dict) -> dict:
        self.proc.stdin.write(json.dumps(obj) + "\n")
        self.proc.stdin.flush()
        line = self._wait_line(lambda ln: ln.startswith("{"), 10.0, obj.get("cmd", "command"))
        reply = json.loads(line)
        if not reply.get("ok"):
            raise BenchFault(f"simulated bench refused {obj}: {reply.get('error')}")
        return reply

    def mount(self, *, coupling: str, disk_kgm2: dict[str, float]) -> None:
        self.command({"cmd": "mount", "coupling": coupling, "disk_kgm2": disk_kgm2})

    def substitution(self) -> str:
        """What --sim uses instead of the profile's bus ('' when it is the profile's own bus)."""
        bus = self.profile.bench.bus
        def show(interface, channel, host, port):
            return ":".join(str(x) for x in (interface, channel or host, port) if x not in (None, ""))
        given = show(bus.interface or bus.family, bus.channel, bus.host, bus.port)
        used = show(self.bus_options.get("interface", bus.interface or bus.family),
                    self.bus_options.get("channel", bus.channel), self.bus_options.get("host", bus.host),
                    self.bus_options.get("port", bus.port))
        same_kind = (self.bus_options.get("interface", bus.interface), self.bus_options.get("channel", bus.channel)) \
            == (bus.interface, bus.channel) or bus.family == "modbus" and \
            self.bus_options.get("host", bus.host) in (bus.host, "127.0.0.1")
        if used == given or same_kind:   # the profile's own emulated bus, on a private port
            return ""
        return (f"--sim: the emulated drives are on {used} (a private port on this host), not on the "
                f"profile's bus {given}; the profile's bus is not used")

    def bus_spec(self):
        bus = self.profile.bench.bus
        opts = dict(bus.options or {})
        opts.update({k: v for k, v in self.bus_options.items() if k not in ("interface", "channel", "host", "port")})
        if bus.family == "cia402":   # the profile's own values win; these are for drives that share our CPUs
            for key, value in SIM_SUPERVISION.items():
                opts.setdefault(key, value)
        return replace(bus, interface=self.bus_options.get("interface", bus.interface),
                       channel=self.bus_options.get("channel", bus.channel),
                       host=self.bus_options.get("host", bus.host),
                       port=self.bus_options.get("port", bus.port), options=opts)

    def __exit__(self, *exc):
        if self.proc and self.proc.poll() is None:
            try:
                self.proc.stdin.close()
            except OSError:
                pass
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        if not self._log.closed:
            self._log.close()
        return False
