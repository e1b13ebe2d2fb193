"""ISO-TP (ISO 15765-2) transfers on a node's bus: a scenario is a few hundred bytes, more than
one CAN frame carries.

The node keeps reading its bus itself (one reader per bus); it hands the frames of the link's
receive ID to :meth:`IsoTpLink.feed` and calls :meth:`IsoTpLink.poll` from its loop, which runs
``can-isotp``'s state machine (segmentation, flow control, timeouts) without a thread of its
own. The IDs are the DBC's ``ScenarioUpload`` (operator to controller) and
``ScenarioDownload`` (controller to operator); each end sends on one and receives on the other,
so one pair carries transfers both ways. A listener (``listen=True``) receives transfers
between two others without sending flow control: the plant learns the obstacle that way.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

import can
import isotp

MAX_PAYLOAD = 4095
"""Bytes one transfer carries on classic CAN (12-bit length)."""
PARAMS = {
    "stmin": 0,  # the receiver takes frames as fast as they come
    "blocksize": 0,  # one flow control per transfer
    "tx_padding": 0xCC,  # full 8-byte frames, as most ECUs expect
    "rx_flowcontrol_timeout": 1000,
    "rx_consecutive_frame_timeout": 1000,
    "max_frame_size": MAX_PAYLOAD,
}


class IsoTpLink:
    """One end of an ISO-TP pair of IDs, driven by the owning node's loop."""

    def __init__(
        self,
        send_frame: Callable[[can.Message], None],
        txid: int,
        rxid: int,
        *,
        listen: bool = False,
        on_error: Callable[[Exception], None] | None = None,
    ) -> None:
        self._inbox: deque[isotp.CanMessage] = deque(maxlen=1024)
        self._send_frame = send_frame
        self.rxid = rxid
        self.errors = 0
        self._on_error = on_error
        self._stack = isotp.TransportLayerLogic(
            rxfn=self._rx,
            txfn=self._tx,
            address=isotp.Address(isotp.AddressingMode.Normal_11bits, txid=txid, rxid=rxid),
            error_handler=self._error,
            params=PARAMS | {"listen_mode": listen},
        )

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
        """Start sending ``payload`` (frames go out as :meth:`poll` runs)."""
        self._stack.send(payload)

    def poll(self) -> list[bytes]:
        """Run the state machine over what was fed; the transfers completed since."""
        self._stack.process(rx_timeout=0.0)
        received = []
        while self._stack.available():
            payload = self._stack.recv()
            if payload is not None:
                received.append(bytes(payload))
        return received

    @property
    def sending(self) -> bool:
        """A transfer of ours is still under way."""
        return bool(self._stack.transmitting())

    def _rx(self, timeout: float) -> isotp.CanMessage | None:
        return self._inbox.popleft() if self._inbox else None

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
