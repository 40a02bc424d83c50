"""The CiA 402 drive state machine of one emulated axis, independent of the protocol.

Both front-ends (CANopen, Modbus) drive it with the same calls, in SI units:
``write_controlword(cw)``, ``set_mode(code)``, ``target_velocity_rad_s``,
``target_current_a``; they read ``statusword``, ``mode_display``, ``error_code``.
``EmulatedBench.advance()`` calls ``command()`` before each physics step and
``observe()`` after it.

State machine: CiA 402 (IEC 61800-7-201) figure "power drive system state machine",
transitions 0-16. Statusword values are the ones canopen's ``BaseNode402`` decodes.
Modes: those of ``supported_modes`` (the drive model's 0x6502); profile velocity (3)
ramps toward the target with ``profile_accel_rad_s2``/``profile_decel_rad_s2`` and
profile torque (4) with ``torque_slope_a_s`` (0x6083/0x6084/0x6087 in SI, None = no
ramp); cyclic synchronous modes (9/10) take each setpoint as it comes.
Limits: over-current (|current command| above ``max_current_a`` for
``OVERCURRENT_SAMPLES`` samples, EMCY 0x2310) and over-speed (|speed| above
``OVERSPEED_FACTOR`` x speed limit, EMCY 0x8400) put the drive in FAULT with the
motor unpowered.
"""
from __future__ import annotations

from typing import Callable

# CiA 402 modes of operation (0x6060) the emulated drive supports
PROFILE_VELOCITY, PROFILE_TORQUE, CYCLIC_VELOCITY, CYCLIC_TORQUE = 3, 4, 9, 10
VELOCITY_MODES = (PROFILE_VELOCITY, CYCLIC_VELOCITY)
TORQUE_MODES = (PROFILE_TORQUE, CYCLIC_TORQUE)
SUPPORTED_MODES = VELOCITY_MODES + TORQUE_MODES

# EMCY / 0x603F error codes (CiA 301 table 21, CiA 402)
ERR_OVERCURRENT = 0x2310      # continuous over-current, device output side
ERR_OVERSPEED = 0x8400        # velocity speed controller
ERR_RESET = 0x0000

STATUSWORD = {                 # state -> statusword bits 0-6 (with bit 4 voltage enabled)
    "NOT READY TO SWITCH ON": 0x0000,
    "SWITCH ON DISABLED": 0x0040,
    "READY TO SWITCH ON": 0x0031,
    "SWITCHED ON": 0x0033,
    "OPERATION ENABLED": 0x0037,
    "QUICK STOP ACTIVE": 0x0017,
    "FAULT REACTION ACTIVE": 0x001F,
    "FAULT": 0x0008,
}
SW_REMOTE = 0x0200
SW_TARGET_REACHED = 0x0400

OVERCURRENT_SAMPLES = 5
OVERSPEED_FACTOR = 1.2
STANDSTILL_RAD_S = 0.5         # quick stop counts as done below this speed


def _toward(now: float, target: float, rate: float | None, period_s: float) -> float:
    """One period of a drive-side ramp from ``now`` toward ``target`` (rate None: a step)."""
    if rate is None:
        return target
    step = rate * period_s
    return target if abs(target - now) <= step else now + step * (1 if target > now else -1)


class Cia402Axis:
    """One emulated servo drive: state machine, mode, targets and protections.

    Not thread-safe by itself: callers hold ``EmulatedBench.lock``.
    """

    def __init__(self, name: str, *, rated_current_a: float = 1.0, max_current_a: float = 3.0,
                 speed_limit_rad_s: float = 420.0, counts_per_rev: int = 10000):
        self.name = name
        self.state_listeners: list[Callable[["Cia402Axis", str, str], None]] = []   # (axis, old, new)
        self.refuse_disable = False         # fault-injection option: ignore commands while enabled
        self.rated_current_a = rated_current_a
        self.max_current_a = max_current_a
        self.speed_limit_rad_s = speed_limit_rad_s
        self.counts_per_rev = counts_per_rev
        self.state = "SWITCH ON DISABLED"   # transitions 0-1 happen at power-up
        self.controlword = 0
        self.mode = 0                       # 0x6060 as written
        self.mode_display = 0               # 0x6061
        self.target_velocity_rad_s = 0.0
        self.target_current_a = 0.0
        self.quick_stop_option = 6          # 0x605A: 1/2 -> then switch on disabled; 5/6 -> stay
        self.supported_modes: tuple[int, ...] = SUPPORTED_MODES
        # 0x6060 code -> what the world does in it; a drive model may add a manufacturer current mode
        self.mode_kinds: dict[int, str] = {**{m: "velocity" for m in VELOCITY_MODES},
                                           **{m: "torque" for m in TORQUE_MODES}}
        self.period_s = 1e-3                # one physics step (set by the bench)
        self.profile_accel_rad_s2: float | None = None
        self.profile_decel_rad_s2: float | None = None
        self.torque_slope_a_s: float | None = None
        self._ramp_velocity = 0.0           # profile-mode setpoints as ramped by the drive
        self._ramp_current = 0.0
        self.error_code = 0                 # 0x603F
        self.target_reached = False
        self.fault_listeners: list[Callable[["Cia402Axis", int], None]] = []
        self._overcurrent_run = 0
        self._pending_fault: int | None = None

    # ------------------------------------------------------------------ inputs
    @property
    def state(self) -> str:
        return self._state

    @state.setter
    def state(self, value: str) -> None:
        old, self._state = getattr(self, "_state", None), value
        if old is not None and value != old:
            for listener in list(self.state_listeners):
                listener(self, old, value)

    @property
    def statusword(self) -> int:
        sw = STATUSWORD[self.state] | SW_REMOTE
        if self.target_reached:
            sw |= SW_TARGET_REACHED
        return sw

    @property
    def error_register(self) -> int:
        """0x1001: bit 0 generic, bit 1 current, bit 7 manufacturer."""
        if not self.error_code:
            return 0
        return 0x01 | (0x02 if self.error_code & 0xF000 == 0x2000 else 0)

    def write_controlword(self, cw: int) -> None:
        """Apply a controlword (0x6040); CiA 402 device control commands."""
        if self.refuse_disable and self.state == "OPERATION ENABLED":
            return               # fault injection: a drive that does not obey disable/quick stop
        previous, self.controlword = self.controlword, cw & 0xFFFF
        s = self.state
        if s in ("FAULT", "FAULT REACTION ACTIVE"):
            if s == "FAULT" and cw & 0x80 and not previous & 0x80:      # 15: fault reset (rising edge)
                self.error_code = 0
                self._overcurrent_run = 0
                self.state = "SWITCH ON DISABLED"
                self._notify(ERR_RESET)
            return
        if cw & 0x80:            # fault reset bit outside FAULT: no command (CiA 402 table 28)
            return
        if cw & 0x02 == 0:       # disable voltage: 7, 9, 10, 12
            if s != "NOT READY TO SWITCH ON":
                self.state = "SWITCH ON DISABLED"
        elif cw & 0x04 == 0:     # quick stop: 11 from OPERATION ENABLED, else 7/10
            if s == "OPERATION ENABLED":
                self.state = "QUICK STOP ACTIVE"
                if self.quick_stop_option == 0:
                    self.state = "SWITCH ON DISABLED"
            elif s in ("READY TO SWITCH ON", "SWITCHED ON"):
                self.state = "SWITCH ON DISABLED"
        elif cw & 0x01 == 0:     # shutdown (xxx0 110): 2, 6, 8
            if s in ("SWITCH ON DISABLED", "SWITCHED ON", "OPERATION ENABLED"):
                self.state = "READY TO SWITCH ON"
        elif cw & 0x08 == 0:     # switch on / disable operation (0111): 3, 5
            if s in ("READY TO SWITCH ON", "OPERATION ENABLED"):
                self.state = "SWITCHED ON"
        else:                    # enable operation (1111): 4, 16, and 3+4 from READY TO SWITCH ON
            if s in ("SWITCHED ON", "QUICK STOP ACTIVE", "READY TO SWITCH ON"):
                self.state = "OPERATION ENABLED"

    def set_mode(self, mode: int) -> None:
        """0x6060; an unsupported mode is ignored (the display keeps the old one)."""
        self.mode = mode
        if mode in self.supported_modes and mode in self.mode_kinds or mode == 0:
            self.mode_display = mode

    def fault_now(self, code: int) -> None:
        """Fault at once, outside a physics step (e.g. the master's heartbeat lost)."""
        if self.state not in ("FAULT", "FAULT REACTION ACTIVE"):
            self._fault(code)

    def inject_fault(self, code: int) -> None:
        """Fault from outside (fixture, emulator fault option); applied at the next step."""
        self._pending_fault = code

    # ------------------------------------------------------------------ per step
    def command(self) -> tuple[str, float]:
        """World mode and setpoint for this axis now (rad/s or A)."""
        if self.state == "OPERATION ENABLED":
            if self.mode_kinds.get(self.mode_display) == "velocity":
                v = max(-self.speed_limit_rad_s, min(self.speed_limit_rad_s, self.target_velocity_rad_s))
                if self.mode_display == PROFILE_VELOCITY:
                    speeding_up = abs(v) > abs(self._ramp_velocity)
                    rate = self.profile_accel_rad_s2 if speeding_up else self.profile_decel_rad_s2
                    v = self._ramp_velocity = _toward(self._ramp_velocity, v, rate, self.period_s)
                return "velocity", v
            if self.mode_kinds.get(self.mode_display) == "torque":
                i = self.target_current_a
                if self.mode_display == PROFILE_TORQUE:
                    i = self._ramp_current = _toward(self._ramp_current, i, self.torque_slope_a_s, self.period_s)
                return "torque", i
        self._ramp_velocity = self._ramp_current = 0.0
        if self.state == "QUICK STOP ACTIVE":
            return "velocity", 0.0          # decelerate on the drive's velocity loop
        return "off", 0.0

    def observe(self, velocity_rad_s: float, current_cmd_a: float) -> None:
        """After a step: protections, quick stop completion, target reached."""
        if self._pending_fault is not None:
            code, self._pending_fault = self._pending_fault, None
            self._fault(code)
            return
        if self.state not in ("OPERATION ENABLED", "QUICK STOP ACTIVE"):
            self._overcurrent_run = 0
            self.target_reached = False
            return
        self._overcurrent_run = self._overcurrent_run + 1 if abs(current_cmd_a) > self.max_current_a else 0
        if self._overcurrent_run >= OVERCURRENT_SAMPLES:
            self._fault(ERR_OVERCURRENT)
            return
        if abs(velocity_rad_s) > OVERSPEED_FACTOR * self.speed_limit_rad_s:
            self._fault(ERR_OVERSPEED)
            return
        if self.state == "QUICK STOP ACTIVE":
            self.target_reached = abs(velocity_rad_s) < STANDSTILL_RAD_S
            if self.target_reached and self.quick_stop_option in (1, 2, 3, 4):
                self.state = "SWITCH ON DISABLED"
        elif self.mode_kinds.get(self.mode_display) == "velocity":
            self.target_reached = abs(velocity_rad_s - self.target_velocity_rad_s) < max(
                STANDSTILL_RAD_S, 0.02 * abs(self.target_velocity_rad_s))
        else:
            self.target_reached = True

    def _fault(self, code: int) -> None:
        self.error_code = code
        self.state = "FAULT"                # fault reaction: motor unpowered at once
        self.target_reached = False
        self._notify(code)

    def _notify(self, code: int) -> None:
        for listener in list(self.fault_listeners):
            listener(self, code)

    def snapshot(self) -> dict:
        return {"state": self.state, "statusword": self.statusword, "mode": self.mode_display,
                "error_code": self.error_code, "target_velocity_rad_s": self.target_velocity_rad_s,
                "target_current_a": self.target_current_a}
