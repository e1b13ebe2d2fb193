"""A Foxglove client written from the protocol alone (``websockets``, subprotocol
``foxglove.sdk.v1``): what the Foxglove app does, without it. Shared by the bridge's tests
and the attack suite."""

from __future__ import annotations

import contextlib
import json
import struct
import threading
from collections import defaultdict
from typing import Any

from support import wait_until
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection, connect
from websockets.typing import Origin, Subprotocol

SUBPROTOCOL = Subprotocol("foxglove.sdk.v1")
FOXGLOVE_APP = Origin("https://app.foxglove.dev")
"""The origin the Foxglove app's pages send, which the bridge lets in by default."""
MESSAGE_DATA = 1
SERVICE_CALL_REQUEST = 2
SERVICE_CALL_RESPONSE = 3
HEAD = struct.Struct("<BIQ")
"""A message frame's head: opcode, subscription ID, log time (ns)."""
CALL = struct.Struct("<BIII")
"""A service call's or response's head: opcode, service ID, call ID, encoding's length."""


class FoxgloveClient:
    """One connection to a Foxglove WebSocket server: what it advertises, every message of
    the channels subscribed to, and service calls answered or failed."""

    def __init__(self, port: int, origin: str = FOXGLOVE_APP) -> None:
        self._closing = contextlib.ExitStack()
        self.socket: ClientConnection = self._closing.enter_context(
            connect(
                f"ws://127.0.0.1:{port}",
                subprotocols=[SUBPROTOCOL],
                origin=Origin(origin),
                open_timeout=10,
            )
        )
        assert self.socket.subprotocol == SUBPROTOCOL
        self.server_info: dict[str, Any] = {}
        self.channels: dict[int, dict[str, Any]] = {}
        self.services: dict[str, dict[str, Any]] = {}
        self.messages: dict[str, list[tuple[int, bytes]]] = defaultdict(list)
        self._subscribed: dict[int, str] = {}
        self._answers: dict[int, tuple[bool, Any]] = {}
        self._lock = threading.Lock()
        self._calls = 0
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        try:
            for frame in self.socket:
                if isinstance(frame, str):
                    self._on_text(json.loads(frame))
                else:
                    self._on_binary(frame)
        except ConnectionClosed:
            pass

    def _on_text(self, message: dict[str, Any]) -> None:
        with self._lock:
            if message["op"] == "serverInfo":
                self.server_info = message
            elif message["op"] == "advertise":
                self.channels.update((channel["id"], channel) for channel in message["channels"])
            elif message["op"] == "advertiseServices":
                self.services.update((s["name"], s) for s in message["services"])
            elif message["op"] == "serviceCallFailure":
                self._answers[message["callId"]] = (False, message["message"])

    def _on_binary(self, frame: bytes) -> None:
        with self._lock:
            if frame[0] == MESSAGE_DATA:
                _, subscription, log_time = HEAD.unpack_from(frame)
                self.messages[self._subscribed[subscription]].append((log_time, frame[HEAD.size :]))
            elif frame[0] == SERVICE_CALL_RESPONSE:
                _, _, call, length = CALL.unpack_from(frame)
                encoding = frame[CALL.size : CALL.size + length]
                assert encoding == b"json"
                self._answers[call] = (True, json.loads(frame[CALL.size + length :]))

    def subscribe_all(self) -> None:
        """Every channel advertised so far, subscription ``i`` to the ``i``-th."""
        with self._lock:
            self._subscribed = {i: c["topic"] for i, c in enumerate(self.channels.values())}
            subscriptions = [
                {"id": i, "channelId": channel_id} for i, channel_id in enumerate(self.channels)
            ]
        self.socket.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))

    def of(self, topic: str) -> list[tuple[int, bytes]]:
        with self._lock:
            return list(self.messages[topic])

    def json_of(self, topic: str) -> list[dict[str, Any]]:
        return [json.loads(data) for _, data in self.of(topic)]

    def call(self, name: str, body: Any = None, timeout: float = 10.0) -> tuple[bool, Any]:
        """Call service ``name`` with ``body`` as JSON; ``(True, response)`` or ``(False,
        the failure's message)``."""
        with self._lock:
            service = self.services[name]["id"]
        payload = b"" if body is None else json.dumps(body).encode()
        return self.call_raw(service, payload, timeout, name)

    def call_raw(
        self, service: int, payload: bytes, timeout: float = 10.0, what: str = "a call"
    ) -> tuple[bool, Any]:
        """Call service ID ``service`` (advertised or not) with ``payload`` as it is."""
        with self._lock:
            self._calls += 1
            call = self._calls
        head = CALL.pack(SERVICE_CALL_REQUEST, service, call, len(b"json"))
        self.socket.send(head + b"json" + payload)
        wait_until(lambda: call in self._answers, timeout, f"the answer to {what}")
        with self._lock:
            return self._answers.pop(call)

    def close(self) -> None:
        self._closing.close()
        self._reader.join(5)
