"""The Zenoh key space of a robot and the JSON Schema of every key: the one place for both.

Under ``scara/<robot>/`` the bridge publishes state (``joints``, ``tcp``, ``coordination``,
``status``, ``events``, ``scenario``), answers a query on each with its latest value, holds a
liveliness token per live process under ``alive/``, and takes commands as queries under
``cmd/`` (``waypoints``, ``obstacle``, ``mode``, ``run``, ``reset``, ``stop``, ``estop``).
Payloads are UTF-8 JSON; the schemas are files shipped with the package
(``protocol/schemas/<name>.schema.json``, beside those of the project's documents), so a
subscriber in any language can validate what it gets. The CAN-over-Zenoh transport's raw
frames stay on their own keys (``scara/can/...``).
"""

from __future__ import annotations

import re
from typing import Any, Final

from protocol.validation import bundled, shipped_schemas

STATE_KEYS: Final = ("joints", "tcp", "coordination", "status", "events", "scenario")
EVERY_SAMPLE_KEYS: Final = ("events", "scenario")
"""State keys whose every sample a subscriber that keeps up gets (Zenoh congestion control
BLOCK): what happens once. The others are telemetry at a rate, sent with DROP: a link that
stalls loses samples, which ``seq`` shows, rather than hold the publisher up."""
COMMANDS: Final = ("waypoints", "obstacle", "mode", "run", "reset", "stop", "estop")
PROCESSES: Final = ("bridge", "controller", "plant")
DEFAULT_ROBOT: Final = "arm1"

_ROBOT_NAME: Final = re.compile(r"^[A-Za-z0-9_-]+$")


def check_robot(robot: str) -> str:
    """A robot name is one key chunk: letters, digits, ``-`` and ``_``."""
    if not _ROBOT_NAME.match(robot):
        raise ValueError(f"robot name {robot!r}: use letters, digits, '-' and '_' only")
    return robot


def state_key(robot: str, name: str) -> str:
    """``scara/<robot>/<name>`` for a state key."""
    if name not in STATE_KEYS:
        raise ValueError(f"{name!r} is not a state key ({', '.join(STATE_KEYS)})")
    return f"scara/{robot}/{name}"


def command_key(robot: str, name: str) -> str:
    """``scara/<robot>/cmd/<name>``."""
    if name not in COMMANDS:
        raise ValueError(f"{name!r} is not a command ({', '.join(COMMANDS)})")
    return f"scara/{robot}/cmd/{name}"


def alive_key(robot: str, process: str) -> str:
    """``scara/<robot>/alive/<process>``: a liveliness token while that process is alive."""
    return f"scara/{robot}/alive/{process}"


def schema(name: str) -> dict[str, Any]:
    """The JSON Schema of a state key (``joints`` ...), of a command's payload
    (``cmd-mode`` ...), of a command's reply (``reply``) or error reply (``error``), or of a
    document (``task`` ...): whole, with the shared definitions it refers to embedded."""
    return bundled(name)


def schema_names() -> list[str]:
    """Every schema shipped with the package."""
    return sorted(shipped_schemas())
