"""A recorded run played on the page: the decoded state channels of ``scara-record``'s MCAP
(``scara/joints``, ``scara/tcp``, ``scara/coordination``, ``scara/status``,
``scara/events``, ``scara/scenario``, JSON with the bridge's schemas) and the scenario
attached to it (the task until one came into force on the bus).

The whole recording is read once; each page has a :class:`Player` of its own (its time,
play or pause, speed), which feeds a :class:`RobotState` of its own just as Zenoh feeds a
live one: the page cannot tell a recording from a robot but by the slider.
"""

from __future__ import annotations

import bisect
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gui.state import RobotState
from protocol.scenario import Scenario, parse_scenario, task_document
from recorder.mcap_can import read_attachments
from recorder.replay import read_state

SPEEDS = (0.1, 0.25, 0.5, 1.0, 2.0, 4.0)


@dataclass(frozen=True, slots=True)
class Recording:
    """A recording's decoded samples in time order, and its scenario (if it has one)."""

    times: list[float]
    samples: list[tuple[str, dict[str, Any]]]
    scenario: Scenario

    @classmethod
    def read(cls, path: Path) -> Recording:
        """RecordingError if ``path`` is not a readable MCAP recording."""
        decoded = (
            (sample.timestamp, sample.name, json.loads(sample.data)) for sample in read_state(path)
        )
        pairs = sorted(decoded, key=lambda item: item[0])
        attached = read_attachments(path).get("scenario.json")
        scenario = (
            parse_scenario(json.loads(attached), "recording")
            if attached is not None
            else Scenario("recording", (), None)
        )
        return cls([t for t, _, _ in pairs], [(name, p) for _, name, p in pairs], scenario)

    @property
    def start(self) -> float:
        return self.times[0] if self.times else 0.0

    @property
    def duration(self) -> float:
        return self.times[-1] - self.start if self.times else 0.0


class Player:
    """One page's playback of a :class:`Recording`: ``position`` s from its start."""

    def __init__(self, recording: Recording) -> None:
        self.recording = recording
        self.playing = False
        self.speed = 1.0
        self.seek(0.0)

    def seek(self, position: float) -> None:
        """Jump to ``position``: a fresh state fed everything up to it."""
        recording = self.recording
        self.position = min(max(position, 0.0), recording.duration)
        self.state = RobotState(recording.scenario)
        if recording.scenario.waypoints:
            self.state.on_sample("scenario", task_document(recording.scenario))
        self._next = 0
        self._feed()

    def advance(self, elapsed: float) -> None:
        """Move on by ``elapsed`` s of wall time if playing; pause at the end."""
        if not self.playing:
            return
        self.position = min(self.position + elapsed * self.speed, self.recording.duration)
        if self.position >= self.recording.duration:
            self.playing = False
        self._feed()

    def _feed(self) -> None:
        recording = self.recording
        end = bisect.bisect_right(recording.times, recording.start + self.position)
        for name, payload in recording.samples[self._next : end]:
            self.state.on_sample(name, payload)
        self._next = end

    @property
    def time(self) -> float:
        """The recording's own clock (its samples' ``t``) at the position."""
        return self.recording.start + self.position
