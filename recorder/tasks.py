"""The task in force, as a listener on the bus hears it (the recorder sends nothing).

A task reaches the controller over ISO-TP on ScenarioUpload and is in force once the
controller's ControllerAnswer accepts it (the answer names the transfer's ticket); a refused
one never was. A task the controller sends back on ScenarioDownload (a describe's answer) is
the one in force. So a recording of the service shows the obstacle and the waypoints the arm
ran with, not those of the scenario the recorder was started with.
"""

from __future__ import annotations

import logging
from typing import Any

import can

from protocol.errors import ConfigError
from protocol.isotp_link import IsoTpLink
from protocol.messages import SCENARIO_DOWNLOAD, SCENARIO_UPLOAD, Answered
from protocol.scenario import Scenario, parse_task, read_task

log = logging.getLogger("scara.recorder")

TASK_IDS = frozenset({SCENARIO_UPLOAD.frame_id, SCENARIO_DOWNLOAD.frame_id})
"""The ISO-TP IDs whose transfers carry tasks."""


def _send_nothing(message: can.Message) -> None:
    """A listener's links never send (``listen=True``): nothing reaches here."""
    raise AssertionError(f"a listener sent {message}")


class TaskInForce:
    """Follows the task in force from the frames it is given (see the module docstring).

    ``base`` gives what a task does not carry (the robot, the controller's settings)."""

    def __init__(self, base: Scenario) -> None:
        self.base = base
        self.unreadable = 0
        """Transfers that came whole but held no task this base can take: skipped."""
        self._uploads = IsoTpLink(
            _send_nothing, SCENARIO_DOWNLOAD.frame_id, SCENARIO_UPLOAD.frame_id, listen=True
        )
        self._downloads = IsoTpLink(
            _send_nothing, SCENARIO_UPLOAD.frame_id, SCENARIO_DOWNLOAD.frame_id, listen=True
        )
        self._offered: dict[int, Scenario] = {}
        """Tasks sent to the controller, by ticket, until it answers."""

    def on_transfer_frame(self, message: can.Message) -> Scenario | None:
        """A frame of :data:`TASK_IDS`; the task now in force if a described one came whole."""
        uploaded = message.arbitration_id == SCENARIO_UPLOAD.frame_id
        (self._uploads if uploaded else self._downloads).feed(message)
        for payload in self._uploads.poll():
            offered = self._read(payload)
            if offered is not None:
                self._offered[offered[0]] = offered[1]
        in_force = None
        for payload in self._downloads.poll():
            described = self._read(payload)
            if described is not None:
                in_force = described[1]
        return in_force

    def on_answer(self, record: Any) -> Scenario | None:
        """A decoded ControllerAnswer; the task it put in force, if it accepted one."""
        if record.Request != Answered.SCENARIO:
            return None
        task = self._offered.pop(record.Ticket, None)
        return task if record.Accepted else None

    def _read(self, payload: bytes) -> tuple[int, Scenario] | None:
        try:
            ticket, document = read_task(payload)
            return ticket, parse_task(document, self.base)
        except ConfigError as error:  # the controller would have refused it too
            self.unreadable += 1
            log.warning("a task on the bus skipped: %s", error)
            return None
