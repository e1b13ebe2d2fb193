"""The world the plant simulates, as the controller service sends it over ISO-TP (WorldUpload).

In a co-simulation the plant is the world: it judges collisions by the obstacle it holds. The
plant starts with the obstacle of its own scenario file (world number 0). The service makes the
obstacle of the task in force the plant's world: it numbers each task's world (1-255), sends it
whenever the number the plant reports in PlantStatus.World is another, and runs a task only
once the plant reports that task's number. So "set obstacle" moves the obstacle the arm can
hit, not only the one the controller avoids.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

from protocol.geometry import EllipticCylinder
from protocol.scenario import Scenario, obstacle_document, obstacle_of
from protocol.validation import check, read_json

STARTUP_WORLD = 0
"""The number of the world a plant starts with: its own scenario file's obstacle."""
LAST_WORLD = 255


@dataclass(frozen=True, slots=True)
class World:
    """An obstacle (or none) and the number it goes by on the wire."""

    number: int
    obstacle: EllipticCylinder | None
    tool_radius: float

    @classmethod
    def of(cls, scenario: Scenario, number: int) -> World:
        return cls(number, scenario.obstacle, scenario.tool_radius)

    def touched(self) -> EllipticCylinder | None:
        """The obstacle grown by the tool radius only: what the tool really collides with."""
        if self.obstacle is None:
            return None
        return self.obstacle.grown(self.tool_radius - self.obstacle.inflation)

    def encode(self) -> bytes:
        """Compact UTF-8 JSON for WorldUpload."""
        obstacle = (
            None if self.obstacle is None else obstacle_document(self.obstacle, self.tool_radius)
        )
        document = {"world": self.number, "obstacle": obstacle}
        return json.dumps(document, separators=(",", ":")).encode()


def next_world(number: int) -> int:
    """The number after ``number``: 1 to 255, round again (0 is the start-up world's)."""
    return number % LAST_WORLD + 1


def read_world(payload: bytes) -> World:
    """The world of a WorldUpload transfer; :class:`ConfigError` naming the field if it is not
    one (the world's schema, then the obstacle's own rule)."""
    document = read_json(payload, "world")
    check(document, "world.schema.json")
    obstacle, tool_radius = obstacle_of(document["obstacle"])
    return World(document["world"], obstacle, tool_radius)
