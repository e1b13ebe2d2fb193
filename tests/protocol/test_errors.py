"""The project's errors cross process boundaries whole: a study's worker process returns the
controller's refusals (NoWayRoundError) to the parent through pickle, which rebuilds an
exception from its arguments; one whose ``__init__`` takes others would stop the pool."""

from __future__ import annotations

import pickle

import pytest

from protocol.errors import (
    ConfigError,
    DecodeError,
    NoWayRoundError,
    ScaraError,
    UnreachableWaypointError,
)


@pytest.mark.parametrize(
    "error",
    [
        ConfigError("obstacle.height", "must be positive"),
        NoWayRoundError("waypoints[1..2]", "no way round the obstacle inside the joint limits"),
        UnreachableWaypointError("waypoints[0]", "out of reach"),
        DecodeError(0x101, "bad CRC"),
    ],
)
def test_an_error_survives_pickling_with_its_type_message_and_fields(error: ScaraError) -> None:
    again = pickle.loads(pickle.dumps(error))
    assert type(again) is type(error)
    assert str(again) == str(error)
    assert vars(again) == vars(error)
