"""ISO-TP (ISO 15765-2) transfers on a node's bus: a scenario is a few hundred bytes, more than
one CAN frame carries.

The node keeps reading its bus itself (one reader per bus); it hands the frames of the link's
receive ID to :meth:`IsoTpLink.feed` and calls :meth:`IsoTpLink.poll` from its loop, which runs
``can-isotp``'s state machine (segmentation, flow control, timeouts) without a thread of its
own. The IDs are the DBC's ``ScenarioUpload`` (operator to controller) and
``ScenarioDownload`` (controller to operator); each end sends on one and receives on the other,
so one pair carries transfers both ways.

One controller and any number of operators (bridges) share the pair, so an operator's link
sees traffic that is not its own, and ISO-TP is one sender to one receiver:

- a flow control on the receive ID while this end sends nothing is another operator's (the
  controller answering its upload): dropped and counted, not an error;
- a transfer on the receive ID reaches every operator, and only the one that asked for it may
  answer it with flow control: two receivers answering one sender is two flow controls for one
  transfer. An operator's link (``asked`` given) answers a transfer only while ``asked()``
  holds; the others it receives as a listener, silently. The controller's link (``asked``
  None) is the one receiver of its receive ID and answers every transfer.

A listener (``listen=True``) receives the transfers between two others without sending
anything.

ISO-TP checks a transfer's frame order and length, not its bytes, and its frames carry no E2E
header: every transfer ends with a CRC-32 of its payload (:func:`seal`), and a transfer whose
CRC does not match (a bit flipped on the wire) is dropped and counted (:attr:`IsoTpLink.corrupt`),
never handed on: a flipped digit would otherwise be a valid, different obstacle.
"""

from __future__ import annotations

import struct
import zlib
from collections import deque
from collections.abc import Callable

import can
import isotp

from protocol.errors import DecodeError

CRC = struct.Struct(">I")
"""The CRC-32 (zlib's, ISO-HDLC) ending every transfer, big-endian."""
MAX_TRANSFER = 4095
"""Bytes one ISO-TP transfer carries on classic CAN (12-bit length)."""
MAX_PAYLOAD = MAX_TRANSFER - CRC.size
"""Bytes of a payload one transfer carries, its CRC after it."""
PARAMS = {
    "stmin": 0,  # the receiver takes frames as fast as they come
    "blocksize": 0,  # one flow control per transfer
    "tx_padding": 0xCC,  # full 8-byte frames, as most ECUs expect
    "rx_flowcontrol_timeout": 1000,
    "rx_consecutive_frame_timeout": 1000,
    "max_frame_size": MAX_TRANSFER,
}
SINGLE, FIRST, CONSECUTIVE, FLOW_CONTROL = range(4)
"""The frame types, the high nibble of the first byte (normal addressing)."""


class IsoTpLink:
    """One end of an ISO-TP pair of IDs, driven by the owning node's loop (see the module
    docstring for ``asked`` and ``listen``)."""

    def __init__(
        self,
        send_frame: Callable[[can.Message], None],
        txid: int,
        rxid: int,
        *,
        listen: bool = False,
        asked: Callable[[], bool] | None = None,
        on_error: Callable[[Exception], None] | None = None,
    ) -> None:
        self._inbox: deque[isotp.CanMessage] = deque(maxlen=1024)
        self._send_frame = send_frame
        self.rxid = rxid
        self._asked = asked
        self.errors = 0
        """Broken or timed-out transfers of this end's (sent, or answered)."""
        self.stray_flow_controls = 0
        """Flow controls dropped: they came while this end was sending nothing."""
        self.overheard_errors = 0
        """Broken transfers this end only listened to (another operator's)."""
        self.corrupt = 0
        """Transfers of ours that came whole but failed their CRC: dropped."""
        self._on_error = on_error
        address = isotp.Address(isotp.AddressingMode.Normal_11bits, txid=txid, rxid=rxid)
        self._own: deque[isotp.CanMessage] = deque()
        self._stack = isotp.TransportLayerLogic(
            rxfn=lambda timeout: _next(self._own),
            txfn=self._tx,
            address=address,
            error_handler=self._error,
            params=PARAMS | {"listen_mode": listen},
        )
        self._overheard: deque[isotp.CanMessage] = deque()
        self._listener: isotp.TransportLayerLogic | None = None
        if asked is not None:
            self._listener = isotp.TransportLayerLogic(
                rxfn=lambda timeout: _next(self._overheard),
                txfn=self._tx,
                address=address,
                error_handler=self._overheard_error,
                params=PARAMS | {"listen_mode": True},
            )
        self._receiver = self._stack
        """The state machine receiving the transfer under way (the last first frame's)."""

    def feed(self, message: can.Message) -> None:
        """A frame of the receive ID (flow control for our sends, or data for us)."""
        self._inbox.append(
            isotp.CanMessage(
                arbitration_id=message.arbitration_id,
                data=bytes(message.data),
                dlc=message.dlc,
                extended_id=message.is_extended_id,
            )
        )

    def send(self, payload: bytes) -> None:
        """Start sending ``payload`` and its CRC (frames go out as :meth:`poll` runs)."""
        self._stack.send(seal(payload))

    def poll(self) -> list[bytes]:
        """Run the state machines over what was fed, frame by frame (where a frame goes
        depends on the state the previous ones left); the transfers completed since."""
        if self._idle():
            return []
        while self._inbox:
            message = self._inbox.popleft()
            stack = self._route(message)
            if stack is None:
                continue
            (self._own if stack is self._stack else self._overheard).append(message)
            stack.process(rx_timeout=0.0)
        received = []
        for stack in (self._stack, self._listener):
            if stack is None:
                continue
            stack.process(rx_timeout=0.0)  # timers, and our own frames to send
            while stack.available():
                transfer = stack.recv()
                if transfer is None:
                    continue
                payload = unseal(bytes(transfer))
                if payload is not None:
                    received.append(payload)
                elif stack is self._stack:
                    self.corrupt += 1
                    self._error(DecodeError(self.rxid, "the transfer failed its CRC-32"))
                else:
                    self._overheard_error(DecodeError(self.rxid, "the transfer failed its CRC-32"))
        return received

    def _idle(self) -> bool:
        """Nothing to run: no frame fed, and neither state machine sending, receiving or
        holding a completed transfer (so no timer running). The nodes poll every tick, 500 a
        second, and are idle nearly always: running can-isotp's state machines for nothing
        took 15 % of the controller's tick at rest."""
        return not self._inbox and not any(
            stack is not None
            and (stack.transmitting() or stack.is_rx_active() or stack.available())
            for stack in (self._stack, self._listener)
        )

    def _route(self, message: isotp.CanMessage) -> isotp.TransportLayerLogic | None:
        """The state machine ``message`` is for; None to drop it."""
        kind = message.data[0] >> 4 if message.data else None
        if kind == FLOW_CONTROL:
            if self._stack.tx_state == self._stack.TxState.IDLE:
                self.stray_flow_controls += 1
                return None
            return self._stack
        if kind in (SINGLE, FIRST) and self._listener is not None:
            asked = self._asked is not None and self._asked()
            self._receiver = self._stack if asked else self._listener
        return self._receiver  # the transfer the last first frame began

    @property
    def sending(self) -> bool:
        """A transfer of ours is still under way."""
        return bool(self._stack.transmitting())

    def _tx(self, message: isotp.CanMessage) -> None:
        self._send_frame(
            can.Message(
                arbitration_id=message.arbitration_id,
                data=bytes(message.data),
                is_extended_id=message.is_extended_id,
            )
        )

    def _error(self, error: Exception) -> None:
        """A broken or timed-out transfer: counted; what was half received is dropped."""
        self.errors += 1
        if self._on_error is not None:
            self._on_error(error)

    def _overheard_error(self, error: Exception) -> None:
        """Another end's transfer broke: nothing of ours was lost."""
        self.overheard_errors += 1


def seal(payload: bytes) -> bytes:
    """``payload`` as one transfer carries it: its CRC-32 after it."""
    return payload + CRC.pack(zlib.crc32(payload))


def unseal(transfer: bytes) -> bytes | None:
    """The payload of a transfer :func:`seal` made; None if its CRC does not match."""
    payload, crc = transfer[: -CRC.size], transfer[-CRC.size :]
    if len(transfer) < CRC.size or CRC.pack(zlib.crc32(payload)) != crc:
        return None
    return payload


def _next(frames: deque[isotp.CanMessage]) -> isotp.CanMessage | None:
    return frames.popleft() if frames else None
