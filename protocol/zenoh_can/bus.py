"""CAN over Zenoh: a python-can interface for machines without SocketCAN, and across hosts.

What it is
    :class:`ZenohBus` is a :class:`can.BusABC` whose frames travel as Zenoh samples on one key
    per virtual bus, ``scara/can/<channel>``. Every bus on the same channel sees every frame
    the others send (a broadcast medium, like CAN). Order holds per sender; frames from
    different senders interleave as they arrive. Own frames are not received unless
    ``receive_own_messages=True`` (then they are delivered locally with ``is_rx=False``, as
    python-can's ``virtual`` bus does).

Wire format
    One sample per frame: a 14-byte little-endian header ``<dIBB`` (timestamp float64 in
    seconds since the epoch, arbitration id uint32, flags uint8, dlc uint8) followed by the
    data bytes. Flags: 0x01 extended id, 0x02 remote, 0x04 error frame, 0x08 CAN FD,
    0x10 bit rate switch, 0x20 error state indicator; 0x40 and 0x80 are reserved and must be 0.
    Samples go out on a reliable publisher with congestion control BLOCK (DROP would lose
    frames silently under load). A sample on the key that does not decode is counted in
    :attr:`ZenohBus.rx_malformed` and dropped.

Topology (no multicast, no router)
    Each bus first tries to *listen* on the well-known ``tcp/HOST:PORT`` (default
    ``tcp/127.0.0.1:17447``). If that port is already in use, the bus *connects* to it and also
    listens on ``tcp/HOST:0`` (an ephemeral port); Zenoh's gossip over the existing TCP links
    then tells every peer about every other, so processes may start in any order. The
    well-known holder is not special once the mesh has formed: when it leaves, the others stay
    linked to each other, and Zenoh keeps retrying the well-known port so a newcomer that takes
    it over is joined again.

    "Port in use" is taken from Zenoh's own listener error (EADDRINUSE), not from a separate
    probe: binding is atomic, so two buses starting at the same instant cannot both win. The
    race that remains is the other way round: the holder may close between our failed bind and
    our connect, or the port may be held by a program that is not a Zenoh peer. Both show as
    "connected to nobody", so after joining, the bus waits for a first peer; if none answers it
    closes and tries to listen again, until ``open_timeout`` passes; then it raises
    :class:`can.CanInitializationError` naming the port (a foreign program holding the port
    would otherwise leave every bus silently isolated).

    Zenoh scouting by multicast is always off, and every endpoint is explicit: nothing here
    listens on every interface or sends to a multicast group.

Loopback by default
    ``host`` must be a loopback address (127.x.x.x, ::1 or ``localhost``) unless
    ``allow_remote=True`` is passed explicitly; even then it must be an explicit address
    (never 0.0.0.0, ::, or a multicast group). To put a plant on another machine, run
    the first bus (the listener) with ``host=<its own LAN address>, allow_remote=True`` and
    the others with the same ``host`` plus ``listen_host=<their own LAN address>``.

Using it from python-can (once registered under the ``can.interface`` entry point group)::

    bus = can.Bus(interface="zenoh", channel="scara")            # port 17447 on 127.0.0.1
    bus = can.Bus(interface="zenoh", channel="scara", port=17448)

    CAN_INTERFACE=zenoh CAN_CHANNEL=scara python app.py           # environment
    CAN_CONFIG='{"port": 17448}'                                   # extra kwargs, as JSON

    # ~/.canrc
    [default]
    interface = zenoh
    channel = scara
    port = 17448

python-can's tools (python-can 4.6; all four forms below were run here)::

    python -m can.logger -i zenoh -c scara -f run.asc
    python -m can.logger -i zenoh -c scara -f run.log --bus-kwargs port=17448
    python -m can.player -i zenoh -c scara -g 0 run.blf
    python -m can.player -i zenoh -c scara -g 0 --bus-kwargs port=17448 -- run.blf

    Extra bus keyword arguments go through ``--bus-kwargs key=value ...`` (values are cast
    with ``can.util.cast_from_string``: ``17448`` becomes an int, ``true`` a bool), or through
    ``CAN_CONFIG='{"port": 17448}'`` in the environment. ``--bus-kwargs`` takes one or more
    words, so in the player, whose file name is positional, end the list with ``--`` or
    another option before the file name: ``--bus-kwargs port=17448 run.blf`` reads the file
    name as a bus kwarg (error), and ``run.blf --bus-kwargs port=17448`` hands both words to the
    log reader (error). A trailing ``--port=17448`` is worse: the tools pass ``--key=value``
    words to the log writer or reader, which accept and ignore them, so the bus opens
    *silently on the default port 17447*. The logger writes its file on SIGINT (Ctrl-C).
    The player's default gap ``-g 0.0001`` caps it near 10k frames/s; ``-g 0`` replays as fast
    as the log parses (about 2000 frames from .blf in 0.6 s here, start-up included).

Pitfalls (measured on this machine, see ``notes/environment.md``)
    - A sample put before the receiver's subscription has reached the sender is lost. A late
      joiner that meets a receiver by gossip (not the port holder) lost its first frame in
      about 60 % of trials, even with Zenoh's own wait at open (which also stalled 0.5 s at
      random). A joining bus therefore waits after opening until its peer set has been quiet
      for ``settle`` seconds (at most 0.25 s): 0 losses in 200 trials, also with the CPUs
      saturated. Frames sent before a *later* bus joins are not seen by it, as on a real
      CAN bus; a sender that must not start early can wait for :attr:`ZenohBus.has_receivers`.
    - Closing a session drops frames still in flight to a slow receiver (a receiver 80 us
      per frame behind lost 130k of 200k frames here, with or without a 0.25 s sleep before
      closing). :meth:`shutdown` therefore runs a flush barrier first (:meth:`ZenohBus.flush`:
      a query that every bus answers after it has taken all earlier frames), bounded by
      ``linger`` seconds.
    - With BLOCK, :meth:`send` may block while a receiver is slow; Zenoh closes a link that
      stays blocked for 5 s and loses what was queued on it. ``send``'s ``timeout`` is not
      enforced.
    - Zenoh's connect never fails at open: it retries in the background (1 s, 2 s, 4 s...),
      which is what lets buses rejoin a new port holder, and also why a foreign program on
      the port must be detected explicitly (see Topology).
"""

from __future__ import annotations

import contextlib
import ipaddress
import json
import math
import queue
import re
import struct
import threading
import time
from typing import Any, Final

import can
import zenoh
from can import BusState, CanProtocol, Message
from can.typechecking import AutoDetectedConfig, CanFilters

__all__ = [
    "DEFAULT_CHANNEL",
    "DEFAULT_HOST",
    "DEFAULT_PORT",
    "HEADER",
    "KEY_PREFIX",
    "MalformedFrameError",
    "ZenohBus",
    "build_zenoh_config",
    "decode_frame",
    "encode_frame",
    "endpoint",
    "key_for_channel",
    "session_config",
]

DEFAULT_CHANNEL: Final = "scara"
DEFAULT_HOST: Final = "127.0.0.1"
DEFAULT_PORT: Final = 17447
KEY_PREFIX: Final = "scara/can/"
FLUSH_PREFIX: Final = "scara/canflush/"  # the flush barrier's queryables, beside the frames

#: timestamp float64, arbitration id uint32, flags uint8, dlc uint8; data bytes follow.
HEADER: Final = struct.Struct("<dIBB")

FLAG_EXTENDED: Final = 0x01
FLAG_REMOTE: Final = 0x02
FLAG_ERROR: Final = 0x04
FLAG_FD: Final = 0x08
FLAG_BRS: Final = 0x10
FLAG_ESI: Final = 0x20
_FLAGS_KNOWN: Final = 0x3F

_MAX_STANDARD_ID: Final = 0x7FF
_MAX_EXTENDED_ID: Final = 0x1FFFFFFF
_MAX_CLASSIC_DATA: Final = 8
_MAX_FD_DATA: Final = 64

_FORBIDDEN_IN_CHANNEL: Final = re.compile(r"[*$#?@\s\x00-\x1f\x7f]")
_ADDR_IN_USE: Final = re.compile(r"already in use|os error (98|48|10048)\b", re.IGNORECASE)
_HOSTNAME: Final = re.compile(r"^[A-Za-z0-9]([A-Za-z0-9-]*[A-Za-z0-9])?(\.[A-Za-z0-9-]+)*$")

_HANDSHAKE_MS: Final = 2000  # Zenoh's is 10 s: a session stuck in one cannot close sooner
_FIRST_PEER_WAIT: Final = _HANDSHAKE_MS / 1000  # s: a joining bus waits for the holder
_SETTLE_LIMIT: Final = 0.25  # s: upper bound of the wait for gossip to link the other peers


class MalformedFrameError(ValueError):
    """A payload on the bus key is not a frame in this module's wire format."""


# --------------------------------------------------------------------------- wire format


def encode_frame(msg: Message, timestamp: float | None = None) -> bytes:
    """Pack ``msg`` as header + data; refuse what a receiver would reject as malformed.

    ``timestamp`` overrides ``msg.timestamp`` (the bus passes the send time when the
    message carries none).
    """
    data = bytes(msg.data or b"")
    flags = (
        (FLAG_EXTENDED if msg.is_extended_id else 0)
        | (FLAG_REMOTE if msg.is_remote_frame else 0)
        | (FLAG_ERROR if msg.is_error_frame else 0)
        | (FLAG_FD if msg.is_fd else 0)
        | (FLAG_BRS if msg.bitrate_switch else 0)
        | (FLAG_ESI if msg.error_state_indicator else 0)
    )
    stamp = msg.timestamp if timestamp is None else timestamp
    _check_fields(stamp, msg.arbitration_id, flags, msg.dlc, len(data))
    return HEADER.pack(stamp, msg.arbitration_id, flags, msg.dlc) + data


def decode_frame(payload: bytes, channel: str | None = None) -> Message:
    """Unpack one payload into a received :class:`can.Message`; raise MalformedFrameError."""
    if len(payload) < HEADER.size:
        raise MalformedFrameError(f"payload of {len(payload)} bytes is shorter than the header")
    stamp, arbitration_id, flags, dlc = HEADER.unpack_from(payload)
    data = payload[HEADER.size :]
    _check_fields(stamp, arbitration_id, flags, dlc, len(data))
    return Message(
        timestamp=stamp,
        arbitration_id=arbitration_id,
        is_extended_id=bool(flags & FLAG_EXTENDED),
        is_remote_frame=bool(flags & FLAG_REMOTE),
        is_error_frame=bool(flags & FLAG_ERROR),
        is_fd=bool(flags & FLAG_FD),
        bitrate_switch=bool(flags & FLAG_BRS),
        error_state_indicator=bool(flags & FLAG_ESI),
        dlc=dlc,
        data=data,
        channel=channel,
        is_rx=True,
        check=False,
    )


def _check_fields(stamp: float, arbitration_id: int, flags: int, dlc: int, size: int) -> None:
    """The one set of rules both ends apply, so a frame we send is never dropped as malformed."""
    if not math.isfinite(stamp):
        raise MalformedFrameError(f"timestamp {stamp!r} is not finite")
    if flags & ~_FLAGS_KNOWN:
        raise MalformedFrameError(f"reserved flag bits set in {flags:#04x}")
    limit = _MAX_EXTENDED_ID if flags & FLAG_EXTENDED else _MAX_STANDARD_ID
    if not 0 <= arbitration_id <= limit:
        raise MalformedFrameError(f"arbitration id {arbitration_id:#x} exceeds {limit:#x}")
    most = _MAX_FD_DATA if flags & FLAG_FD else _MAX_CLASSIC_DATA
    if size > most:
        raise MalformedFrameError(f"{size} data bytes exceed {most}")
    if not 0 <= dlc <= most:
        raise MalformedFrameError(f"dlc {dlc} exceeds {most}")


# --------------------------------------------------------------------------- configuration


def key_for_channel(channel: object) -> str:
    """The Zenoh key of a channel; raise CanInitializationError for a name that is not one."""
    if isinstance(channel, int) and not isinstance(channel, bool):
        channel = str(channel)  # python-can casts CAN_CHANNEL=1 to an int
    if not isinstance(channel, str) or not channel:
        raise can.CanInitializationError(
            f"zenoh channel must be a non-empty string, got {channel!r}"
        )
    bad = _FORBIDDEN_IN_CHANNEL.search(channel)
    if bad:
        raise can.CanInitializationError(
            f"zenoh channel {channel!r} contains {bad.group()!r}: "
            "wildcards, '$', '#', '?', '@', spaces and control characters are not allowed"
        )
    key = KEY_PREFIX + channel
    try:
        zenoh.KeyExpr(key)
    except zenoh.ZError as exc:
        raise can.CanInitializationError(
            f"zenoh channel {channel!r} does not make a valid key ({key!r}): {exc}"
        ) from None
    return key


def _check_host(value: object, *, allow_remote: bool, name: str = "host") -> str:
    """Normalise an address; loopback only unless allow_remote, never a wildcard or group."""
    if not isinstance(value, str) or not value.strip():
        raise can.CanInitializationError(f"zenoh {name} must be an explicit address, got {value!r}")
    text = value.strip()
    bare = text[1:-1] if text.startswith("[") and text.endswith("]") else text
    if bare.lower() == "localhost":
        return DEFAULT_HOST
    try:
        address = ipaddress.ip_address(bare)
    except ValueError:
        address = None
    if address is not None:
        if address.is_unspecified or address.is_multicast:
            raise can.CanInitializationError(
                f"zenoh {name} {value!r} is not an explicit unicast address "
                "(wildcard and multicast addresses are refused)"
            )
        if address.is_loopback:
            return str(address)
    elif not _HOSTNAME.match(bare):
        raise can.CanInitializationError(f"zenoh {name} {value!r} is not an address or host name")
    if not allow_remote:
        raise can.CanInitializationError(
            f"zenoh {name} {value!r} is not a loopback address (127.x.x.x, ::1, localhost); "
            "pass allow_remote=True to use another address on purpose"
        )
    return bare


def endpoint(host: str, port: int) -> str:
    """A Zenoh TCP locator; IPv6 literals go in brackets."""
    if ":" in host:
        return f"tcp/[{host}]:{port}"
    return f"tcp/{host}:{port}"


def session_config(
    host: str,
    listen_port: int,
    connect_port: int | None,
    *,
    listen_host: str | None = None,
    lowlatency: bool = False,
) -> dict[str, Any]:
    """The Zenoh settings of one bus, as config path -> JSON value (pure, so tests can read it).

    Peer mode, multicast scouting off, one explicit listen endpoint on ``listen_host``
    (default ``host``) and either no connect endpoint or the well-known one on ``host``.
    Both lists are always set: an unset listen list means "every interface". Gossip (over
    the TCP links only) links the peers to each other. ``scouting/delay`` 0: Zenoh's own
    wait for gossiped peers at open stalled 0.5 s at random here and still lost the first
    frame about 60 % of the time; the bus's explicit settle wait replaces it (0 losses in
    200 trials, open in about 40 ms). The handshake timeout is 2 s instead of 10 s: a session
    whose connect is stuck in a handshake with a program that is not Zenoh cannot close
    before it expires (close() raised "close operation timed out" after 10 s).
    ``lowlatency`` asks for Zenoh's low-latency unicast transport (which has no QoS
    priorities, so QoS is switched off with it): about 15 % less round-trip time here, and at
    1 kHz 99.85 % instead of 96-97 % of commands answered within a tick. Peers that did not
    ask for it still link with it, over the ordinary transport. It is off by default because
    three buses formed their mesh less reliably with it here (6 of 8 trials against 8 of 8).
    """
    host = _check_host(host, allow_remote=True)  # a guard: never a wildcard or a group
    local = host if listen_host is None else _check_host(listen_host, allow_remote=True)
    return {
        "mode": "peer",
        "scouting/multicast/enabled": False,
        "scouting/gossip/enabled": True,
        "scouting/delay": 0,
        "listen/endpoints": [endpoint(local, listen_port)],
        "listen/exit_on_failure": True,
        "connect/endpoints": [] if connect_port is None else [endpoint(host, connect_port)],
        "transport/unicast/open_timeout": _HANDSHAKE_MS,
    } | (
        {"transport/unicast/lowlatency": True, "transport/unicast/qos/enabled": False}
        if lowlatency
        else {}
    )


def build_zenoh_config(settings: dict[str, Any]) -> zenoh.Config:
    """A :class:`zenoh.Config` with every setting of :func:`session_config` inserted."""
    config = zenoh.Config()
    for path, value in settings.items():
        config.insert_json5(path, json.dumps(value))
    return config


def _is_address_in_use(exc: BaseException) -> bool:
    return bool(_ADDR_IN_USE.search(str(exc)))


# --------------------------------------------------------------------------- the bus


class ZenohBus(can.BusABC):
    """A python-can bus whose frames are Zenoh samples on ``scara/can/<channel>``.

    Beyond :class:`can.BusABC`: ``role`` ("listening on" the well-known port, or "joined"),
    ``key``, ``rx_malformed`` (payloads dropped), ``zenoh_settings`` (the config it opened
    with), :attr:`has_receivers`, :attr:`peer_count` and :meth:`flush`.
    """

    def __init__(
        self,
        channel: str | int | None = DEFAULT_CHANNEL,
        *,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        receive_own_messages: bool = False,
        allow_remote: bool = False,
        listen_host: str | None = None,
        can_filters: CanFilters | None = None,
        express: bool = False,
        lowlatency: bool = False,
        linger: float = 2.0,
        settle: float = 0.03,
        open_timeout: float = 3.0,
        fd: bool = False,
        **kwargs: Any,
    ) -> None:
        """Open (or join) the Zenoh mesh of ``channel`` on ``host:port``.

        ``allow_remote`` permits a non-loopback ``host``/``listen_host``; ``listen_host``
        is the local address a joining bus listens on (default ``host``); ``express``
        sends each frame in its own TCP write instead of letting Zenoh batch a backlog
        (measured here: no gain at 1 kHz, and it caps a burst near 22k frames/s instead
        of about 90k, so it is off by default); ``lowlatency`` see :func:`session_config`;
        ``linger`` bounds how long :meth:`shutdown` waits for the receivers to confirm they
        have taken every frame sent before (the flush barrier; 0 skips it);
        ``settle`` how long a joining bus waits for the peer set to stop changing;
        ``open_timeout`` bounds the whole opening. Other keyword arguments from python-can
        configuration (``bitrate``, ``single_handle``, ...) are accepted and ignored.
        """
        self.channel_name = DEFAULT_CHANNEL if channel is None else str(channel)
        self.key = key_for_channel(DEFAULT_CHANNEL if channel is None else channel)
        self.host = _check_host(host, allow_remote=bool(allow_remote))
        self.listen_host = (
            None
            if listen_host is None
            else _check_host(listen_host, allow_remote=bool(allow_remote), name="listen_host")
        )
        if isinstance(port, bool) or not isinstance(port, int) or not 0 < port < 65536:
            raise can.CanInitializationError(f"zenoh port must be in 1..65535, got {port!r}")
        timings = (("linger", linger), ("settle", settle), ("open_timeout", open_timeout))
        for label, value in timings:
            if not isinstance(value, (int, float)) or not 0 <= value < math.inf:
                raise can.CanInitializationError(f"zenoh {label} must be >= 0, got {value!r}")
        self.port = port
        self.lowlatency = bool(lowlatency)
        self.receive_own_messages = bool(receive_own_messages)
        self.rx_malformed = 0
        self._linger = float(linger)
        self._settle_quiet = float(settle)
        self._open_timeout = float(open_timeout)
        self._rx: queue.SimpleQueue[Message | None] = queue.SimpleQueue()
        self._state = BusState.ACTIVE
        self._closed = False
        self._close_lock = threading.Lock()
        self._sent_any = False
        self._can_protocol = CanProtocol.CAN_FD if fd else CanProtocol.CAN_20

        self._flush_key = FLUSH_PREFIX + self.key[len(KEY_PREFIX) :]
        self._session, self.role, self.zenoh_settings = self._open_session()
        try:
            self._subscriber = self._session.declare_subscriber(
                self.key, self._on_sample, allowed_origin=zenoh.Locality.REMOTE
            )
            self._flush_queryable = self._session.declare_queryable(
                self._flush_key, self._on_flush_query, allowed_origin=zenoh.Locality.REMOTE
            )
            self._publisher = self._session.declare_publisher(
                self.key,
                congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE,
                express=bool(express),
                allowed_destination=zenoh.Locality.REMOTE,
            )
        except zenoh.ZError as exc:
            _close(self._session)
            raise can.CanInitializationError(
                f"zenoh declarations on {self.key!r} failed: {exc}"
            ) from None
        if self.role == "joined":
            # After declaring, so our subscription spreads while gossip links the mesh.
            _settle(self._session, self._settle_quiet)
        self.channel_info = (
            f"Zenoh CAN channel {self.channel_name!r} (key {self.key}, "
            f"{self.role} {endpoint(self.host, self.port)})"
        )
        super().__init__(channel=self.channel_name, can_filters=can_filters, **kwargs)

    # ------------------------------------------------------------------ opening

    def _open_session(self) -> tuple[zenoh.Session, str, dict[str, Any]]:
        """Listen on the well-known port, or join whoever holds it (see module docstring).

        Returns the session, the role ("listening on" or "joined") and the settings it was
        opened with (kept as :attr:`zenoh_settings` so they can be inspected).
        """
        deadline = time.monotonic() + self._open_timeout
        well_known = endpoint(self.host, self.port)
        while True:
            settings = session_config(self.host, self.port, None, lowlatency=self.lowlatency)
            try:
                return zenoh.open(build_zenoh_config(settings)), "listening on", settings
            except zenoh.ZError as exc:
                if not _is_address_in_use(exc):
                    raise can.CanInitializationError(
                        f"zenoh cannot listen on {well_known}: {exc}"
                    ) from None
            settings = session_config(
                self.host, 0, self.port, listen_host=self.listen_host, lowlatency=self.lowlatency
            )
            try:
                session = zenoh.open(build_zenoh_config(settings))
            except zenoh.ZError as exc:
                raise can.CanInitializationError(
                    f"zenoh cannot join {well_known} and listen on "
                    f"{settings['listen/endpoints'][0]}: {exc}"
                    + ("" if self.listen_host else " (set listen_host to a local address)")
                ) from None
            wait = min(_FIRST_PEER_WAIT, max(0.0, deadline - time.monotonic()))
            if _wait_for_peer(session, wait):
                return session, "joined", settings
            with contextlib.suppress(zenoh.ZError):
                _close(session)
            if time.monotonic() >= deadline:
                raise can.CanInitializationError(
                    f"zenoh port {self.port} on {self.host} is in use, but no Zenoh peer "
                    f"answered at {well_known} within {self._open_timeout} s: another program "
                    "holds it; choose another port"
                )
            time.sleep(0.02)

    # ------------------------------------------------------------------ receiving

    def _on_sample(self, sample: zenoh.Sample) -> None:
        """Zenoh thread: decode and queue; never let an exception escape into Zenoh."""
        try:
            msg = decode_frame(sample.payload.to_bytes(), self.channel_name)
        except Exception:
            self.rx_malformed += 1
            return
        self._rx.put(msg)

    def _recv_internal(self, timeout: float | None) -> tuple[Message | None, bool]:
        if self._is_shutdown:
            raise can.CanOperationError(f"{self.channel_info} is shut down")
        try:
            msg = self._rx.get(timeout=timeout)
        except queue.Empty:
            return None, False
        if msg is None:  # the wake-up shutdown() leaves for a blocked reader
            self._rx.put(None)
        return msg, False

    # ------------------------------------------------------------------ sending

    def send(self, msg: Message, timeout: float | None = None) -> None:
        """Publish one frame (may block under BLOCK congestion control; timeout not enforced)."""
        if self._is_shutdown:
            raise can.CanOperationError(f"{self.channel_info} is shut down")
        if self._state is BusState.PASSIVE:
            raise can.CanOperationError(f"{self.channel_info} is passive (listen only)")
        try:
            payload = encode_frame(msg, msg.timestamp or time.time())
        except (MalformedFrameError, struct.error) as exc:
            raise ValueError(f"frame cannot be sent on {self.key}: {exc}") from None
        try:
            self._publisher.put(payload)
        except zenoh.ZError as exc:
            raise can.CanOperationError(f"zenoh put on {self.key} failed: {exc}") from exc
        self._sent_any = True
        if self.receive_own_messages:
            own = decode_frame(payload, self.channel_name)
            own.is_rx = False
            self._rx.put(own)

    @property
    def has_receivers(self) -> bool:
        """True once another bus on this channel is subscribed and will get what we send.

        Zenoh's matching status: a sender can wait for this before its first frame instead of
        exchanging handshake frames (it says "at least one", not which one).
        """
        if self._is_shutdown:
            return False
        status: Any = self._publisher.matching_status  # a MatchingStatus (stub says bool)
        return bool(getattr(status, "matching", status))

    @property
    def peer_count(self) -> int:
        """How many other Zenoh sessions (buses, tools, bridges) this bus is linked to now."""
        if self._is_shutdown:
            return 0
        return len(self._session.info.peers_zid())

    def flush_tx_buffer(self) -> None:
        """Nothing to discard: Zenoh owns its queues."""

    # ------------------------------------------------------------------ state and closing

    @property
    def state(self) -> BusState:
        """ACTIVE or PASSIVE (listen only) while open, ERROR once shut down."""
        return BusState.ERROR if self._is_shutdown else self._state

    @state.setter
    def state(self, new_state: BusState) -> None:
        if new_state not in (BusState.ACTIVE, BusState.PASSIVE):
            raise ValueError(f"zenoh bus state can be ACTIVE or PASSIVE, not {new_state}")
        self._state = new_state

    def shutdown(self) -> None:
        """Stop periodic tasks, flush to the receivers, undeclare, close; idempotent."""
        with self._close_lock:
            closing = not self._closed
            self._closed = True
        super().shutdown()
        if not closing:
            return
        if self._sent_any and self._linger > 0:
            self.flush(self._linger)
        for entity in (self._subscriber, self._flush_queryable, self._publisher):
            with contextlib.suppress(zenoh.ZError):
                _undeclare(entity)
        with contextlib.suppress(zenoh.ZError):
            _close(self._session)
        self._rx.put(None)

    def flush(self, timeout: float) -> int:
        """Wait until every bus on the channel has taken all we sent so far; count the buses.

        A flush query travels on the same links, at the same priority, behind the frames,
        and each bus answers it (:meth:`_on_flush_query`) only after its Zenoh thread has
        handed every earlier frame to its queue. Closing a session drops what is still in
        flight; a fixed sleep is too short for a slow receiver and too long for a fast one.
        Returns the number of buses that answered within ``timeout``.
        """
        answered = 0
        with contextlib.suppress(zenoh.ZError):
            replies = self._session.get(
                self._flush_key,
                target=zenoh.QueryTarget.ALL,
                consolidation=zenoh.ConsolidationMode.NONE,
                congestion_control=zenoh.CongestionControl.BLOCK,
                timeout=timeout,
                allowed_destination=zenoh.Locality.REMOTE,
            )
            for reply in replies:  # ends when all have answered or the timeout expires
                answered += reply.ok is not None
        return answered

    def _on_flush_query(self, query: zenoh.Query) -> None:
        """Zenoh thread: every frame received before this query is already queued."""
        with contextlib.suppress(Exception):
            query.reply(query.key_expr, b"")

    @staticmethod
    def _detect_available_configs() -> list[AutoDetectedConfig]:
        return [{"interface": "zenoh", "channel": DEFAULT_CHANNEL}]


def _close(session: Any) -> None:
    """``Session.close`` (zenoh's stub leaves it unannotated, which strict mypy refuses)."""
    session.close()


def _undeclare(entity: Any) -> None:
    """``Subscriber/Publisher.undeclare``, for the same reason as :func:`_close`."""
    entity.undeclare()


def _wait_for_peer(session: zenoh.Session, timeout: float) -> bool:
    """True once the session is linked to at least one peer, polled until ``timeout``."""
    deadline = time.monotonic() + timeout
    while True:
        if session.info.peers_zid():
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.005)


def _settle(session: zenoh.Session, quiet: float) -> None:
    """Wait until no new peer has appeared for ``quiet`` s (gossip links the rest of the mesh)."""
    deadline = time.monotonic() + _SETTLE_LIMIT
    seen = len(session.info.peers_zid())
    calm_since = time.monotonic()
    while time.monotonic() < deadline and time.monotonic() - calm_since < quiet:
        time.sleep(0.002)
        now_seen = len(session.info.peers_zid())
        if now_seen != seen:
            seen, calm_since = now_seen, time.monotonic()
