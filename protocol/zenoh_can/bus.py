"""CAN over Zenoh: a python-can bus for machines without SocketCAN, and across hosts.

:class:`ZenohBus` is a :class:`can.BusABC` whose frames travel as Zenoh samples on one key
per virtual bus, ``scara/can/<channel>`` (format: :mod:`protocol.zenoh_can.frame`). Every bus
on the same channel sees every frame the others send (a broadcast medium, like CAN); each
sender's frames arrive in order. Own frames are not received unless
``receive_own_messages=True`` (then they are delivered locally with ``is_rx=False``, as
python-can's ``virtual`` bus does). A received message carries this bus's receive time.

Every bus is a client of one Zenoh router (``scara-router``, which ``scara-run`` starts when
none runs): see :mod:`protocol.zenoh_can.config` for the topology and ``docs/transport.md``
for what was measured. Frames sent while another bus is not yet subscribed do not reach it,
as on a real CAN bus; a sender that must not start early can wait for :attr:`has_receivers`.

Registered under python-can's ``can.interface`` entry point group::

    bus = can.Bus(interface="zenoh", channel="scara")            # router on 127.0.0.1:17447
    bus = can.Bus(interface="zenoh", channel="scara", port=17448)
    bus = can.Bus(interface="zenoh", channel="scara", tls_ca="certs/ca.pem")  # a TLS router
    python -m can.logger -i zenoh -c scara -f run.asc --bus-kwargs port=17448
"""

from __future__ import annotations

import contextlib
import logging
import math
import queue
import struct
import threading
import time
from collections.abc import Sequence
from typing import Any

import can
import zenoh
from can import BusState, CanProtocol, Message
from can.typechecking import AutoDetectedConfig, CanFilters

from protocol.zenoh_can.config import (
    DEFAULT_CHANNEL,
    DEFAULT_HOST,
    DEFAULT_PORT,
    FLUSH_PREFIX,
    KEY_PREFIX,
    Tls,
    build_zenoh_config,
    check_host,
    check_port,
    client_config,
    close,
    endpoint,
    is_loopback,
    key_for_channel,
)
from protocol.zenoh_can.frame import MalformedFrameError, decode_frames, encode_frame

_RETRY = 0.05  # s between attempts to reach the router while opening
log = logging.getLogger("scara.zenoh_can")


class ZenohBus(can.BusABC):
    """A python-can bus whose frames are Zenoh samples on ``scara/can/<channel>``.

    Beyond :class:`can.BusABC`: ``key``, ``rx_malformed`` (payloads dropped),
    ``zenoh_settings`` (the config it opened with), :meth:`send_many`, :attr:`has_receivers`,
    :attr:`router_connected` and :meth:`flush`.
    """

    def __init__(
        self,
        channel: str | int | None = DEFAULT_CHANNEL,
        *,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        receive_own_messages: bool = False,
        allow_remote: bool = False,
        can_filters: CanFilters | None = None,
        express: bool = True,
        linger: float = 2.0,
        open_timeout: float = 5.0,
        fd: bool = False,
        tls_ca: str | None = None,
        tls_cert: str | None = None,
        tls_key: str | None = None,
        **kwargs: Any,
    ) -> None:
        """Join the channel through the router at ``host:port``.

        ``allow_remote`` permits a non-loopback ``host``; ``express`` (the default) sends each
        frame at once instead of letting Zenoh hold it up to 1 ms to batch it with others:
        through the router that halves the p99 round trip of a command and its answer
        (``docs/transport.md``); ``express=False`` batches, for bulk transfers (a replay as
        fast as possible) where throughput matters more than latency;
        ``linger`` bounds how long :meth:`shutdown` waits for the receivers to confirm they
        have taken every frame sent before (the flush barrier; 0 skips it); ``open_timeout``
        how long to wait for the router; ``tls_ca`` (the CA that signed the router's
        certificate) joins a router that listens on a ``tls/`` link, ``tls_cert`` and
        ``tls_key`` are this bus's own certificate for one that asks (mutual TLS). Other
        keyword arguments from python-can
        configuration (``bitrate``, ``single_handle``, ...) are accepted and ignored.
        """
        self.channel_name = DEFAULT_CHANNEL if channel is None else str(channel)
        self.key = key_for_channel(DEFAULT_CHANNEL if channel is None else channel)
        self.host = check_host(host, allow_remote=bool(allow_remote))
        self.port = check_port(port)
        for label, value in (("linger", linger), ("open_timeout", open_timeout)):
            if not isinstance(value, (int, float)) or not 0 <= value < math.inf:
                raise can.CanInitializationError(f"zenoh {label} must be >= 0, got {value!r}")
        self.receive_own_messages = bool(receive_own_messages)
        self.rx_malformed = 0
        self._linger = float(linger)
        self._rx: queue.Queue[Message | None] = queue.Queue()
        """Not a queue.SimpleQueue: its get(timeout) waits for ever once a signal handler (a
        node's SIGINT) has outlasted the timeout (CPython 3.11, _queuemodule.c)."""
        self._state = BusState.ACTIVE
        self._closed = False
        self._close_lock = threading.Lock()
        self._sent_any = False
        self._can_protocol = CanProtocol.CAN_FD if fd else CanProtocol.CAN_20
        # The barrier's queryable key ends in a verbatim chunk, which no other channel's can
        # match, so that the query may end in /**: a query for the exact key waits its whole
        # timeout for a queryable that has already left (eclipse-zenoh/zenoh#2454).
        self._flush_key = FLUSH_PREFIX + self.key[len(KEY_PREFIX) :] + "/@end"
        self.tls = Tls.of(tls_ca, tls_cert, tls_key, "client")
        if self.tls is None and not is_loopback(self.host):
            log.warning("the frames to and from %s cross the network in clear (no TLS)", self.host)
        self.zenoh_settings = client_config(self.host, self.port, tls=self.tls)
        self._session = self._open_session(float(open_timeout))
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
            close(self._session)
            raise can.CanInitializationError(
                f"zenoh declarations on {self.key!r} failed: {exc}"
            ) from None
        self.channel_info = (
            f"Zenoh CAN channel {self.channel_name!r} (key {self.key}, "
            f"router {endpoint(self.host, self.port, tls=self.tls is not None)})"
        )
        super().__init__(channel=self.channel_name, can_filters=can_filters, **kwargs)

    def _open_session(self, timeout: float) -> zenoh.Session:
        """A client session of the router, retried until ``timeout`` (it may be starting)."""
        deadline = time.monotonic() + timeout
        where = endpoint(self.host, self.port, tls=self.tls is not None)
        while True:
            try:
                session = zenoh.open(build_zenoh_config(self.zenoh_settings))
            except zenoh.ZError as exc:
                if time.monotonic() >= deadline:
                    raise can.CanInitializationError(
                        f"no Zenoh router answers at {where} ({exc}); start one with "
                        f"`scara-router --port {self.port}` (scara-run starts one itself)"
                    ) from None
                time.sleep(_RETRY)
                continue
            if session.info.routers_zid():
                return session
            close(session)  # something that is not a Zenoh router holds the port
            if time.monotonic() >= deadline:
                raise can.CanInitializationError(
                    f"the program at {where} is not a Zenoh router; choose another port"
                )
            time.sleep(_RETRY)

    # ------------------------------------------------------------------ receiving

    def _on_sample(self, sample: zenoh.Sample) -> None:
        """Zenoh thread: decode, stamp the receive time, queue; never raise into Zenoh."""
        try:
            frames = decode_frames(sample.payload.to_bytes(), self.channel_name)
        except Exception:
            self.rx_malformed += 1
            return
        received = time.time()
        for msg in frames:
            msg.timestamp = received
            self._rx.put(msg)

    def _recv_internal(self, timeout: float | None) -> tuple[Message | None, bool]:
        if self._closed:
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
        self.send_many([msg])

    def send_many(self, messages: Sequence[Message]) -> None:
        """Publish frames that belong together as one sample: they reach every receiver
        together and in this order, at the cost of one message instead of several."""
        if self._closed:
            raise can.CanOperationError(f"{self.channel_info} is shut down")
        if self._state is BusState.PASSIVE:
            raise can.CanOperationError(f"{self.channel_info} is passive (listen only)")
        now = time.time()
        try:
            payload = b"".join(encode_frame(msg, msg.timestamp or now) for msg in messages)
        except (MalformedFrameError, struct.error) as exc:
            raise ValueError(f"frame cannot be sent on {self.key}: {exc}") from None
        try:
            self._publisher.put(payload)
        except zenoh.ZError as exc:
            raise can.CanOperationError(f"zenoh put on {self.key} failed: {exc}") from exc
        self._sent_any = True
        if self.receive_own_messages:
            for own in decode_frames(payload, self.channel_name):
                own.is_rx = False
                self._rx.put(own)

    @property
    def has_receivers(self) -> bool:
        """True once another bus on this channel is subscribed and will get what we send."""
        if self._closed:
            return False
        status: Any = self._publisher.matching_status  # a MatchingStatus (stub says bool)
        return bool(getattr(status, "matching", status))

    @property
    def router_connected(self) -> bool:
        """True while the session is linked to its router (it reconnects on its own)."""
        return not self._closed and bool(self._session.info.routers_zid())

    def flush_tx_buffer(self) -> None:
        """Nothing to discard: Zenoh owns its queues."""

    # ------------------------------------------------------------------ state and closing

    @property
    def state(self) -> BusState:
        """ACTIVE or PASSIVE (listen only) while open, ERROR once shut down."""
        return BusState.ERROR if self._closed else self._state

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
            close(self._session)
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
        deadline = time.monotonic() + timeout
        try:
            replies = self._session.get(
                self._flush_key + "/**",
                target=zenoh.QueryTarget.ALL,
                consolidation=zenoh.ConsolidationMode.NONE,
                congestion_control=zenoh.CongestionControl.BLOCK,
                timeout=timeout,
                allowed_destination=zenoh.Locality.REMOTE,
            )
        except zenoh.ZError:
            return 0
        while True:  # bounded by our own clock too: a query has been seen to outlive its timeout
            try:
                reply = replies.try_recv()
            except zenoh.ZError:  # complete: every bus answered, or Zenoh's timeout
                return answered
            if reply is not None:
                answered += reply.ok is not None
            elif time.monotonic() >= deadline:
                return answered
            else:
                time.sleep(0.001)

    def _on_flush_query(self, query: zenoh.Query) -> None:
        """Zenoh thread: every frame received before this query is already queued."""
        with contextlib.suppress(Exception):
            query.reply(self._flush_key, b"")

    @staticmethod
    def _detect_available_configs() -> list[AutoDetectedConfig]:
        return [{"interface": "zenoh", "channel": DEFAULT_CHANNEL}]


def _undeclare(entity: Any) -> None:
    """``Subscriber/Publisher.undeclare`` (zenoh's stub leaves it unannotated)."""
    entity.undeclare()
