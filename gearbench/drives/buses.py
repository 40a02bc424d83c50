"""Open python-can buses from ``INTERFACE:CHANNEL`` strings.

Accepted forms:

- ``socketcan:vcan0`` / ``socketcan:can0`` — kernel CAN (vcan where the kernel has it);
- ``udp_multicast:239.74.163.2:43113`` (IPv4 group:port), ``udp_multicast:[ff15::1]:43113``
  (IPv6), or without ``:port`` for python-can's default port — a real bus between
  processes that needs no kernel CAN support; classic CAN frames (``fd=False``);
- ``virtual:name`` — in-process only.

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

INTERFACES = ("socketcan", "udp_multicast", "virtual")
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
        raise DriveError(f"bus '{spec}': expected INTERFACE:CHANNEL with INTERFACE one of "
                         f"{', '.join(INTERFACES)} (e.g. socketcan:vcan0, udp_multicast:{DEFAULT_GROUP}:43113, "
                         f"virtual:bench)")
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


def open_bus(spec: str | BusSpec, **overrides) -> can.BusABC:
    """Open the bus; errors become DriveError naming the bus."""
    bs = parse_bus(spec) if isinstance(spec, str) else spec
    kwargs = {**bs.kwargs, **overrides}
    try:
        bus = can.Bus(interface=bs.interface, channel=bs.channel, **kwargs)
    except (can.CanError, OSError, ValueError) as exc:
        hint = (" (no kernel CAN here? create it with `ip link add dev vcan0 type vcan; ip link set up vcan0` "
                "or use udp_multicast)" if bs.interface == "socketcan" else "")
        raise DriveError(f"cannot open CAN bus {bs}: {exc}{hint}") from exc
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
