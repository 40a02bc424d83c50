"""Any CAN adapter python-can supports: bus strings, profiles and the open error.

End-of-line testers commonly use PEAK PCAN-USB, Kvaser, IXXAT or Vector adapters
(often on Windows); none is on this machine, so what is checked is everything up to
the driver: the profile validates, the bit rate reaches python-can, and a missing
driver is one line naming the bus and what to install.
"""
import can
import pytest

from gearbench.drives.buses import INTERFACES, BusSpec, open_bus, parse_bus
from gearbench.drives.cia402 import CiA402Network
from gearbench.errors import DriveError, ProfileError
from gearbench.profile import load_profile

from test_profile import CVT_TEXT, replace_once  # noqa: E402  (the frozen reference profile)

UDP_BUS = "    interface: udp_multicast         # real tester: socketcan with channel can0\n    channel: 239.74.163.2\n"
ADAPTERS = {"pcan": "PCAN_USBBUS1", "kvaser": "0", "ixxat": "0", "vector": "0"}


def test_every_python_can_interface_is_accepted():
    assert set(INTERFACES) == set(can.interfaces.VALID_INTERFACES)   # plug-ins included
    for name, channel in ADAPTERS.items():
        assert parse_bus(f"{name}:{channel}") == BusSpec(name, channel)


def test_unknown_interface_names_the_likely_one():
    with pytest.raises(DriveError, match=r"'pcann' is not a python-can interface \(did you mean pcan\?\)"):
        parse_bus("pcann:PCAN_USBBUS1")


@pytest.mark.parametrize("name", sorted(ADAPTERS))
def test_profile_names_the_adapter_and_its_bitrate(tmp_path, name):
    bus = (f"    interface: {name}\n    channel: {ADAPTERS[name]}\n    bitrate: 500000\n")
    text = replace_once(CVT_TEXT, UDP_BUS, bus)
    path = tmp_path / "p.yaml"
    path.write_text(text)
    spec = load_profile(path).bench.bus
    assert (spec.interface, spec.channel) == (name, ADAPTERS[name])
    assert spec.options["bus_kwargs"] == {"bitrate": 500000}


def test_adapter_without_channel_or_with_a_typo_is_a_profile_error(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text(replace_once(CVT_TEXT, UDP_BUS,
                                 "    interface: pcan\n"))
    with pytest.raises(ProfileError, match=r"a pcan bus needs 'channel'.*PCAN_USBBUS1"):
        load_profile(path)
    path.write_text(replace_once(CVT_TEXT, "    interface: udp_multicast", "    interface: kvasr"))
    with pytest.raises(ProfileError, match=r"kvaser"):
        load_profile(path)


def test_missing_driver_is_one_line_naming_bus_and_fix():
    """No PCAN-Basic library here: the error names the bus and the driver to install."""
    with pytest.raises(DriveError, match=r"cannot open CAN bus pcan:PCAN_USBBUS1: .*PCAN-Basic"):
        open_bus("pcan:PCAN_USBBUS1", bitrate=500000)
    net = CiA402Network(bus="kvaser:0", bus_kwargs={"bitrate": 500000})
    with pytest.raises(DriveError, match=r"kvaser:0: .*CANlib"):
        net.open()
