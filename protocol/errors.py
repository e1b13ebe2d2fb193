"""One error tree for the whole project, rooted at :class:`ScaraError` (as python-can does)."""

from __future__ import annotations


class ScaraError(Exception):
    """Base of every error this project raises on purpose."""


class ConfigError(ScaraError, ValueError):
    """A configuration or scenario value is wrong; ``field`` names it."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message

    def __reduce__(self) -> tuple[type[ConfigError], tuple[str, str]]:
        """Rebuilt from its own arguments: a study's worker process returns refusals."""
        return type(self), (self.field, self.message)


class UnreachableWaypointError(ConfigError):
    """A scenario's waypoint is out of the arm's reach or joint limits."""


class WaypointInObstacleError(ConfigError):
    """A scenario's waypoint lies inside the inflated obstacle."""


class WaypointNearObstacleError(ConfigError):
    """A scenario's waypoint lies outside the inflated obstacle, but nearer it than a task
    may ask (``controller/task_rules.py``)."""


class WaypointNearLimitError(ConfigError):
    """A scenario's waypoint is reachable, but nearer a joint's stop than a task may ask."""


class PlanTooFastError(ConfigError):
    """A scenario's planned path is faster somewhere than the TCP may move."""


class PathOutsideWorkspaceError(ConfigError):
    """A scenario's planned path between two reachable waypoints leaves the workspace."""


class NoWayRoundError(ConfigError):
    """A segment of a scenario crosses the obstacle and neither way round it stays inside the
    arm's joint limits."""


class KinematicsError(ScaraError, ValueError):
    """A pose cannot be reached by the arm."""


class UnreachableError(KinematicsError):
    """The point lies outside the reachable annulus or the prismatic stroke."""


class JointLimitError(KinematicsError):
    """The point is reachable geometrically, but only outside the joint limits."""


class WireError(ScaraError):
    """A CAN frame cannot be built or read as the DBC defines it."""


class EncodeError(WireError, ValueError):
    """A value does not fit its signal (out of the DBC range, or not finite)."""


class DecodeError(WireError):
    """A received frame is not a valid frame of the DBC: unknown ID, wrong length, bad CRC,
    or a value outside its signal's range. Such a frame is counted and never acted on."""

    def __init__(self, frame_id: int, reason: str) -> None:
        super().__init__(f"frame 0x{frame_id:03X}: {reason}")
        self.frame_id = frame_id
        self.reason = reason

    def __reduce__(self) -> tuple[type[DecodeError], tuple[int, str]]:
        """Rebuilt from its own arguments, as :class:`ConfigError`."""
        return type(self), (self.frame_id, self.reason)
