"""One error tree for the whole project, rooted at :class:`ScaraError` (as python-can does)."""

from __future__ import annotations


class ScaraError(Exception):
    """Base of every error this project raises on purpose."""


class ConfigError(ScaraError, ValueError):
    """A configuration or scenario value is wrong; ``field`` names it."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field}: {message}")
        self.field = field


class KinematicsError(ScaraError, ValueError):
    """A pose cannot be reached by the arm."""


class UnreachableError(KinematicsError):
    """The point lies outside the reachable annulus or the prismatic stroke."""


class JointLimitError(KinematicsError):
    """The point is reachable geometrically, but only outside the joint limits."""
