"""The emulated drive's CiA 402 state machine, checked against canopen's own decoding."""
from canopen.profiles.p402 import State402

from gearbench.emulate.cia402_axis import (ERR_OVERCURRENT, OVERCURRENT_SAMPLES, PROFILE_TORQUE,
                                           PROFILE_VELOCITY, Cia402Axis)


def decoded(axis):
    """The state a standard master (canopen BaseNode402) reads from the statusword."""
    for state, (mask, bits) in State402.SW_MASK.items():
        if axis.statusword & mask == bits:
            return state
    return "UNKNOWN"


def enabled_axis(mode=PROFILE_VELOCITY, **kw):
    a = Cia402Axis("in", **kw)
    a.set_mode(mode)
    for cw in (0x06, 0x07, 0x0F):
        a.write_controlword(cw)
    return a


def test_enable_sequence_statuswords_decode_as_cia402_states():
    a = Cia402Axis("in")
    seen = [decoded(a)]
    for cw in (0x06, 0x07, 0x0F):
        a.write_controlword(cw)
        seen.append(decoded(a))
    assert seen == ["SWITCH ON DISABLED", "READY TO SWITCH ON", "SWITCHED ON", "OPERATION ENABLED"]


def test_illegal_commands_do_not_change_state():
    a = Cia402Axis("in")
    a.write_controlword(0x0F)          # enable operation straight from SWITCH ON DISABLED: not allowed
    assert a.state == "SWITCH ON DISABLED"
    assert a.command() == ("off", 0.0)


def test_command_follows_mode_and_clips_speed():
    a = enabled_axis(speed_limit_rad_s=100.0)
    a.target_velocity_rad_s = 250.0
    assert a.command() == ("velocity", 100.0)
    a.set_mode(PROFILE_TORQUE)
    a.target_current_a = 0.7
    assert a.command() == ("torque", 0.7)
    a.set_mode(1)                      # profile position: not supported, display keeps torque
    assert a.mode_display == PROFILE_TORQUE


def test_quick_stop_decelerates_then_option_decides():
    a = enabled_axis()
    a.target_velocity_rad_s = 100.0
    a.write_controlword(0x02)
    assert decoded(a) == "QUICK STOP ACTIVE" and a.command() == ("velocity", 0.0)
    a.observe(velocity_rad_s=0.1, current_cmd_a=0.0)
    assert a.state == "QUICK STOP ACTIVE"        # option 6: stay
    a.write_controlword(0x0F)                      # transition 16 back to OPERATION ENABLED
    assert a.state == "OPERATION ENABLED"
    a.quick_stop_option = 2
    a.write_controlword(0x02)
    a.observe(velocity_rad_s=50.0, current_cmd_a=0.0)
    assert a.state == "QUICK STOP ACTIVE"        # still moving
    a.observe(velocity_rad_s=0.1, current_cmd_a=0.0)
    assert a.state == "SWITCH ON DISABLED"


def test_overcurrent_needs_consecutive_samples_then_faults_with_emcy_code():
    codes = []
    a = enabled_axis(max_current_a=1.0)
    a.fault_listeners.append(lambda axis, code: codes.append(code))
    for _ in range(OVERCURRENT_SAMPLES - 1):
        a.observe(0.0, 1.5)
    a.observe(0.0, 0.5)                            # a dip resets the count
    assert a.state == "OPERATION ENABLED"
    for _ in range(OVERCURRENT_SAMPLES):
        a.observe(0.0, -1.5)
    assert decoded(a) == "FAULT" and a.error_code == ERR_OVERCURRENT and codes == [ERR_OVERCURRENT]
    assert a.command() == ("off", 0.0) and a.error_register & 0x02


def test_fault_reset_needs_rising_edge_and_returns_to_switch_on_disabled():
    codes = []
    a = enabled_axis()
    a.fault_listeners.append(lambda axis, code: codes.append(code))
    a.inject_fault(0x2320)
    a.observe(0.0, 0.0)
    assert a.state == "FAULT"
    a.write_controlword(0x0F)                      # enable does nothing in FAULT
    assert a.state == "FAULT"
    a.write_controlword(0x80)
    assert decoded(a) == "SWITCH ON DISABLED" and a.error_code == 0
    assert codes == [0x2320, 0]                    # EMCY then EMCY "error reset"
