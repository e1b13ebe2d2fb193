"""The bridge's Foxglove side (``scara-bridge --foxglove-port``): Foxglove's WebSocket protocol
(the ``foxglove-sdk`` server) beside the Zenoh keys.

- the arm in 3D: ``foxglove.SceneUpdate`` on :data:`~bridge.scene.SCENE_TOPIC` and
  ``foxglove.FrameTransforms`` on :data:`~bridge.scene.TF_TOPIC`, from :class:`ArmScene`;
- the state keys (``scara/joints``, ``scara/coordination``, ``scara/status`` ...) as JSON
  channels with their JSON Schemas (``protocol/keys.py``), the same samples as on Zenoh;
- with ``--foxglove-commands`` only, the seven commands as services ``cmd/<name>``: the
  request is the command's JSON payload, the response its reply (``reply.schema.json``).
  They go through the bridge's own checks (:meth:`Bridge.call`); a malformed request fails
  the call with the field and the reason. Foxglove's protocol has no users: without the flag
  the server is read-only, as the ``monitor`` user is on the secure router.

Clients reach it only through :class:`~bridge.foxglove_gate.FoxgloveGate`, which checks
their ``Host`` and ``Origin``: the SDK's own server listens on 127.0.0.1 over TLS that only
the gate trusts.

Fed by the bridge's publishing thread (:meth:`FoxgloveServer.on_sample`): the CAN side never
waits for it.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import foxglove
from foxglove import Channel, Context, MessageSchema, Schema, Service, ServiceRequest, ServiceSchema
from foxglove.channels import FrameTransformsChannel, SceneUpdateChannel
from foxglove.websocket import Capability, WebSocketServer

from bridge.foxglove_gate import FoxgloveGate
from bridge.scene import SCENE_TOPIC, STATE_TOPIC_PREFIX, TF_TOPIC, ArmScene
from protocol.certs import self_signed
from protocol.config import RobotConfig
from protocol.keys import COMMANDS, STATE_KEYS, schema
from protocol.scenario import Scenario
from protocol.zenoh_can.config import served_hosts

SERVICE_PREFIX = "cmd/"
JSON = "json"

Call = Callable[[str, bytes], dict[str, Any]]
"""A command and its JSON payload in, its reply out (blocking until the controller answers)."""


@dataclass(frozen=True, slots=True)
class FoxgloveSettings:
    """Where the Foxglove server listens, whether it takes commands, and the web origins
    whose pages may connect."""

    host: str
    port: int
    commands: bool
    origins: tuple[str, ...]


INNER_HOST = "127.0.0.1"
"""Where the SDK's own server listens, behind the gate."""


def json_schema(name: str) -> Schema:
    """Schema ``name`` of ``protocol/keys.py`` as Foxglove carries it."""
    return Schema(name=name, encoding="jsonschema", data=json.dumps(schema(name)).encode())


class FoxgloveServer:
    """A Foxglove WebSocket server of its own context (channels, services), reached through
    its gate on ``settings.host:settings.port``. ``RuntimeError`` if it cannot listen."""

    def __init__(
        self,
        settings: FoxgloveSettings,
        robot: RobotConfig,
        task: Callable[[], Scenario | None],
        call: Call | None,
    ) -> None:
        self.context = Context()
        self.scene = ArmScene(robot)
        self._task = task
        self._state = {
            name: Channel(
                STATE_TOPIC_PREFIX + name,
                message_encoding=JSON,
                schema=json_schema(name),
                context=self.context,
            )
            for name in STATE_KEYS
        }
        self._scene = SceneUpdateChannel(SCENE_TOPIC, context=self.context)
        self._transforms = FrameTransformsChannel(TF_TOPIC, context=self.context)
        services = [] if call is None else [_service(name, call) for name in COMMANDS]
        certificate, key = self_signed(INNER_HOST)
        self.server: WebSocketServer = foxglove.start_server(
            name="scara-bridge",
            host=INNER_HOST,
            port=0,
            context=self.context,
            capabilities=[Capability.Services] if services else [],
            supported_encodings=[JSON],
            services=services,
            tls_cert=certificate,
            tls_key=key,
        )
        try:
            self.gate = FoxgloveGate(
                settings.host,
                settings.port,
                self.server.port,
                certificate,
                settings.origins,
                served_hosts(settings.host),
            )
        except OSError as error:
            self.server.stop()
            raise RuntimeError(
                f"cannot listen on {settings.host}:{settings.port}: {error}"
            ) from None

    @property
    def port(self) -> int:
        return self.gate.port

    def on_sample(self, name: str, payload: dict[str, Any]) -> None:
        """A state key's sample, as it went out on Zenoh: to its channel, and to the scene."""
        log_time = round(payload["t"] * 1e9) if "t" in payload else None
        self._state[name].log(payload, log_time=log_time)
        if name == "events":
            self.scene.on_event(payload["event"])
        elif name == "joints":
            self.scene.set_task(self._task())
            position = payload["position"]
            due = self.scene.on_joints((position[0], position[1], position[2]), payload["t"])
            if due.transforms is not None:
                self._transforms.log(due.transforms, log_time=log_time)
            if due.scene is not None:
                self._scene.log(due.scene, log_time=log_time)

    def stop(self) -> None:
        self.gate.stop()
        self.server.stop()


def _service(command: str, call: Call) -> Service:
    """Command ``command`` as a Foxglove service: JSON in, the reply as JSON out."""

    def handle(request: ServiceRequest) -> bytes:
        """The SDK's thread: waits for the controller's answer (2 s at most); an exception
        (a malformed request) fails the call with its message."""
        return json.dumps(call(command, request.payload)).encode()

    return Service(
        SERVICE_PREFIX + command,
        schema=ServiceSchema(
            f"cmd-{command}",
            request=MessageSchema(encoding=JSON, schema=json_schema(f"cmd-{command}")),
            response=MessageSchema(encoding=JSON, schema=json_schema("reply")),
        ),
        handler=handle,
    )
