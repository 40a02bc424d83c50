"""Open python-can buses from ``INTERFACE:CHANNEL`` strings.

Accepted forms:

- ``socketcan:vcan0`` / ``socketcan:can0`` — kernel CAN (vcan where the kernel has it);
- ``udp_multicast:239.74.163.2:43113`` (IPv4 group:port), ``udp_multicast:[ff15::1]:43113``
  (IPv6), or without ``:port`` for python-can's default port — a real bus between
  processes that needs no kernel CAN support; classic CAN frames (``fd=False``);
- ``virtual:name`` — in-process only;
- any other interface python-can knows (``can.interfaces.VALID_INTERFACES``, which
  includes installed ``can.interface`` entry-point plug-ins): ``pcan:PCAN_USBBUS1``,
  ``kvaser:0``, ``ixxat:0``, ``vector:0``, ``slcan:/dev/ttyACM0``, ... The adapter's
  own options (``bitrate``, Vector's ``app_name``, ...) come from the profile's
  ``bench.bus`` (``bitrate:`` and ``options: {bus_kwargs: {...}}``).

``bus_for_tests()`` tells tests which cross-process bus to use: socketcan on
``$GEARBENCH_VCAN`` when set (``.ci/run`` sets it where it could create vcan0), else
udp_multicast on a free port so concurrent runs cannot hear each other.
"""
from __future__ import annotations

import os
import socket
from dataclasses import dataclass

import can

from ..errors import DriveError

INTERFACES = tuple(sorted(can.interfaces.VALID_INTERFACES))   # built-in + entry-point plug-ins
# What the open error suggests, for the adapters end-of-line testers commonly use.
DRIVER_HINTS = {
    "socketcan": "no kernel CAN here? create it with `ip link add dev vcan0 type vcan; ip link set up vcan0` "
                 "or use udp_multicast; a real adapter: `ip link set can0 up type can bitrate 1000000`",
    "pcan": "install PEAK's PCAN-Basic driver (Windows; on Linux PCAN-USB is socketcan:can0) and check "
            "the channel name, e.g. PCAN_USBBUS1",
    "kvaser": "install Kvaser's CANlib driver and check the channel number (0 = first channel)",
    "ixxat": "install the IXXAT VCI 4 driver and check the channel number (0 = first channel)",
    "vector": "install the Vector XL Driver Library and assign the channel to the application "
              "(Vector Hardware Config; app_name in bus_kwargs, default CANalyzer)",
}
DEFAULT_GROUP = "239.74.163.2"
RECV_BUFFER_BYTES = 4 * 1024 * 1024   # bursts of TPDOs must not overflow the default ~200 kB


@dataclass(frozen=True)
class BusSpec:
    interface: str
    channel: str
    port: int | None = None

    def __str__(self) -> str:
        if self.port is None:
            return f"{self.interface}:{self.channel}"
        host = f"[{self.channel}]" if ":" in self.channel else self.channel
        return f"{self.interface}:{host}:{self.port}"

    @property
    def kwargs(self) -> dict:
        """Keyword arguments for ``can.Bus`` beside interface and channel."""
        if self.interface == "udp_multicast":
            kw = {"fd": False}
            if self.port is not None:
                kw["port"] = self.port
            return kw
        if self.interface == "virtual":
            return {"receive_own_messages": False}
        return {}


def parse_bus(spec: str) -> BusSpec:
    """``"udp_multicast:239.1.2.3:5000"`` -> BusSpec; DriveError naming the fix otherwise."""
    interface, sep, channel = spec.partition(":")
    if not sep or not channel or interface not in INTERFACES:
        known = ("" if not sep or interface in INTERFACES else
                 f"'{interface}' is not a python-can interface{_did_you_mean(interface)}; ")
        raise DriveError(f"bus '{spec}': {known}expected INTERFACE:CHANNEL with INTERFACE one of python-can's "
                         f"{', '.join(INTERFACES)} (e.g. socketcan:can0, pcan:PCAN_USBBUS1, kvaser:0, "
                         f"udp_multicast:{DEFAULT_GROUP}:43113, virtual:bench)")
    port = None
    if interface == "udp_multicast":
        host, port_text = channel, ""
        if channel.startswith("["):
            host, _, rest = channel[1:].partition("]")
            port_text = rest.lstrip(":")
        elif channel.count(":") == 1:
            host, port_text = channel.split(":")
        if port_text:
            if not port_text.isdigit() or not 0 < int(port_text) < 65536:
                raise DriveError(f"bus '{spec}': port '{port_text}' is not a UDP port number 1-65535")
            port = int(port_text)
        channel = host
    return BusSpec(interface, channel, port)


def _did_you_mean(name: str) -> str:
    import difflib
    close = difflib.get_close_matches(name, INTERFACES, n=1)
    return f" (did you mean {close[0]}?)" if close else ""


def open_bus(spec: str | BusSpec, **overrides) -> can.BusABC:
    """Open the bus; ``overrides`` are the adapter's options (bitrate, app_name, ...);
    errors become DriveError naming the bus and what to install or check."""
    bs = parse_bus(spec) if isinstance(spec, str) else spec
    kwargs = {**bs.kwargs, **overrides}
    try:
        bus = can.Bus(interface=bs.interface, channel=bs.channel, **kwargs)
    except Exception as exc:   # vendor back-ends fail in many ways (kvaser: NameError without CANlib)
        hint = DRIVER_HINTS.get(bs.interface, "check the adapter's driver and the python-can documentation "
                                              f"for the '{bs.interface}' interface")
        raise DriveError(f"cannot open CAN bus {bs}: {type(exc).__name__}: {exc} ({hint})") from exc
    if bs.interface == "udp_multicast":
        try:  # loss under bursts comes mostly from the small default receive buffer
            bus._multicast._socket.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECV_BUFFER_BYTES)
        except (AttributeError, OSError):
            pass
    return bus


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def bus_for_tests() -> BusSpec:
    """The cross-process bus tests should use: vcan when available, else udp_multicast."""
    vcan = os.environ.get("GEARBENCH_VCAN")
    if vcan:
        return BusSpec("socketcan", vcan)
    return BusSpec("udp_multicast", DEFAULT_GROUP, free_udp_port())
