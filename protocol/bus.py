"""Opening the CAN bus a node talks on, with python-can's own configuration.

The transport is python-can's ``interface`` + ``channel``: given on the command line, else
taken from python-can's environment variables or config file (``CAN_INTERFACE``,
``CAN_CHANNEL``, ``~/.canrc``), else the embedded default: ``socketcan`` on ``vcan0`` where
that device exists, otherwise the CAN-over-Zenoh interface through its router on 127.0.0.1.
"""

from __future__ import annotations

import argparse
import os
import socket
import struct
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import can

DEFAULT_ZENOH_CHANNEL = "scara"


def default_transport() -> tuple[str, str]:
    """socketcan/vcan0 where the device exists, else zenoh on loopback."""
    if Path("/sys/class/net/vcan0").exists():
        return "socketcan", "vcan0"
    return "zenoh", DEFAULT_ZENOH_CHANNEL


def resolve_transport(interface: str | None, channel: str | None) -> tuple[str, str]:
    """Command line first, then python-can's configuration, then the default."""
    if interface is None:
        configured: dict[str, Any]
        try:
            configured = dict(can.util.load_config())
        except can.CanInterfaceNotImplementedError:  # python-can has no interface configured
            configured = {}
        interface = configured.get("interface")
        channel = channel or configured.get("channel")
    if interface is None:
        interface, default_channel = default_transport()
        channel = channel or default_channel
    if channel is None:
        channel = "vcan0" if interface == "socketcan" else DEFAULT_ZENOH_CHANNEL
    return interface, str(channel)


def parse_options(pairs: Sequence[str]) -> dict[str, Any]:
    """``key=value`` pairs into bus keyword arguments (ints and floats converted)."""
    options: dict[str, Any] = {}
    for pair in pairs:
        key, separator, text = pair.partition("=")
        if not separator or not key:
            raise argparse.ArgumentTypeError(f"bus option {pair!r} is not key=value")
        value: Any = {"true": True, "false": False}.get(text.lower(), text)
        for kind in (int, float):
            try:
                value = kind(text)
                break
            except ValueError:
                continue
        options[key] = value
    return options


def add_bus_arguments(parser: argparse.ArgumentParser) -> None:
    """The transport flags every node and tool shares."""
    group = parser.add_argument_group("CAN transport (python-can interface + channel)")
    group.add_argument(
        "--interface",
        "-i",
        default=os.environ.get("SCARA_CAN_INTERFACE"),
        help="python-can interface: zenoh, socketcan, udp_multicast, virtual ... "
        "(default: python-can's config, else socketcan on vcan0 if present, else zenoh)",
    )
    group.add_argument(
        "--channel", "-c", default=os.environ.get("SCARA_CAN_CHANNEL"), help="channel name"
    )
    group.add_argument(
        "--bus-option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="extra keyword for the bus, e.g. port=17447 (repeatable)",
    )


def open_bus(interface: str | None, channel: str | None, options: dict[str, Any]) -> can.BusABC:
    resolved_interface, resolved_channel = resolve_transport(interface, channel)
    return can.Bus(interface=resolved_interface, channel=resolved_channel, **options)


RECEIVE_BUFFER = 8 * 1024 * 1024
"""bytes a listener that must miss nothing asks the kernel to queue for its SocketCAN socket
(the default, about 200 kB, holds a few hundred frames: a listener not scheduled for a
while loses the rest silently)."""


SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)
"""Linux's SO_RCVBUFFORCE (Python names it from 3.12 on)."""


SO_MEMINFO = getattr(socket, "SO_MEMINFO", 55)
"""Linux's SO_MEMINFO: a socket's memory counters, its drops among them."""
_MEMINFO_DROPS = 8
"""SK_MEMINFO_DROPS: the index of the drop count among SO_MEMINFO's 32-bit counters."""


def can_socket(bus: Any) -> socket.socket | None:
    """The SocketCAN socket of ``bus`` (also under a wrapper that keeps its bus in ``inner``,
    like the fault injector), or None where the bus is of another kind."""
    while bus is not None:
        raw = getattr(bus, "socket", None)
        if isinstance(raw, socket.socket) and raw.family == socket.AF_CAN:
            return raw
        bus = getattr(bus, "inner", None)
    return None


def enlarge_receive_buffer(bus: can.BusABC, size: int = RECEIVE_BUFFER) -> None:
    """Ask for a ``size`` receive queue where the bus is a SocketCAN socket (SO_RCVBUFFORCE
    where allowed, else SO_RCVBUF up to the system's limit); other buses queue in process."""
    raw = can_socket(bus)
    if raw is None:
        return
    try:
        raw.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, size)
    except OSError:  # no CAP_NET_ADMIN
        raw.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size)


def receive_drops(bus: can.BusABC) -> int | None:
    """Frames the kernel dropped so far because the receive queue of ``bus``'s SocketCAN
    socket was full (the socket's drop count, which SO_RXQ_OVFL would attach to each frame;
    python-can's reader takes no such extra data, so it is read with SO_MEMINFO); None where
    the bus is not a SocketCAN socket, or the kernel does not say."""
    raw = can_socket(bus)
    if raw is None:
        return None
    try:
        info = raw.getsockopt(socket.SOL_SOCKET, SO_MEMINFO, 4 * (_MEMINFO_DROPS + 1))
    except OSError:
        return None
    if len(info) < 4 * (_MEMINFO_DROPS + 1):
        return None
    return int(struct.unpack_from("=I", info, 4 * _MEMINFO_DROPS)[0])


def open_bus_from_args(args: argparse.Namespace) -> can.BusABC:
    return open_bus(args.interface, args.channel, parse_options(args.bus_option))


def send_frames(bus: can.BusABC, messages: Sequence[can.Message]) -> None:
    """Send frames that belong together: as one unit where the transport can (CAN over
    Zenoh's ``send_many``), else one after the other."""
    send_many = getattr(bus, "send_many", None)
    if send_many is not None:
        send_many(messages)
        return
    for message in messages:
        bus.send(message)
