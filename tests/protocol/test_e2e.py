"""The receiving side of the E2E header (``protocol.e2e``): alive counters per frame ID."""

from __future__ import annotations

import can

from protocol.codec import WIRE
from protocol.e2e import RESYNC_AFTER, Check, E2EMonitor


def test_alive_counter_classification() -> None:
    monitor = E2EMonitor()
    sequence = [(5, Check.FIRST), (6, Check.OK), (6, Check.REPEATED), (9, Check.LOST)]
    sequence += [(7, Check.STALE), (10, Check.OK), (15, Check.LOST), (0, Check.OK)]
    for counter, expected in sequence:
        assert monitor.check(0x100, counter) is expected, counter
    assert monitor.check(0x200, 3) is Check.FIRST  # each frame ID has its own counter
    counts = monitor.counts
    assert (counts.repeated, counts.stale, counts.lost) == (1, 1, 2 + 4)
    assert [c.usable for c in (Check.FIRST, Check.OK, Check.LOST)] == [True] * 3
    assert not Check.REPEATED.usable and not Check.STALE.usable
    monitor.forget()
    assert monitor.check(0x100, 3) is Check.FIRST


def test_alive_counter_resynchronises_after_a_long_gap() -> None:
    monitor = E2EMonitor()
    monitor.check(0x110, 0)
    # Ten frames lost: 11 looks like an old frame (stale), but 12 continues it, so the
    # sender has moved on and the receiver follows instead of rejecting everything after.
    assert [monitor.check(0x110, c) for c in (11, 12, 13)] == [Check.STALE, Check.OK, Check.OK]
    # A single late frame does not move the receiver back.
    assert monitor.check(0x110, 10) is Check.STALE
    assert monitor.check(0x110, 14) is Check.OK


def test_a_late_frame_is_stale_whatever_came_late_before_it() -> None:
    """A stale frame is followed only by the next one received: 3 late once, then long after
    5 before 4 (a frame reordered on the wire), 4 is stale too. It was once taken as 3's
    successor, and acted on (found by scara-soak's reordering)."""
    monitor = E2EMonitor()
    assert [monitor.check(0x100, c) for c in (2, 4, 3)] == [Check.FIRST, Check.LOST, Check.STALE]
    for counter in range(5, 16):
        monitor.check(0x100, counter)
    assert [monitor.check(0x100, c) for c in (0, 1, 2, 3, 5, 4)] == [Check.OK] * 4 + [
        Check.LOST,
        Check.STALE,
    ]


def test_a_sender_silent_for_longer_than_any_frame_is_late_starts_over() -> None:
    """A restarted sender (a new bridge) begins at counter 0: after a silence its first
    command is acted on, while the same jump back within the silence is a stale frame."""
    monitor = E2EMonitor()
    for time, counter in ((10.0, 4), (10.1, 5)):
        assert monitor.check(0x40, counter, time).usable
    assert monitor.check(0x40, 0, 10.1 + RESYNC_AFTER / 2) is Check.STALE
    restarted = 10.1 + RESYNC_AFTER / 2 + RESYNC_AFTER * 1.01
    assert monitor.check(0x40, 0, restarted) is Check.FIRST
    assert monitor.check(0x40, 0, restarted + 0.01) is Check.REPEATED
    assert monitor.check(0x40, 1, restarted + 0.02) is Check.OK


def test_frames_of_ids_the_dbc_does_not_define_are_counted_as_unknown_and_passed_over() -> None:
    """Another system's traffic (cangen, a foreign ECU) is never acted on; it is counted,
    apart from the frames of this node's own IDs that were bad."""
    monitor = E2EMonitor()
    command = WIRE["JointVelocityCommand"]
    data = command.encode(
        command.Record(Enable=1, Theta1Rate=0.1, Theta2Rate=0.0, D3Rate=0.0), counter=1
    )
    wanted = {command.frame_id}
    foreign = [
        can.Message(arbitration_id=0x7FF, data=data, is_extended_id=False),
        can.Message(arbitration_id=command.frame_id, data=data, is_extended_id=True),
    ]
    another_nodes = can.Message(
        arbitration_id=WIRE["PlantStatus"].frame_id, data=bytes(8), is_extended_id=False
    )
    for message in (*foreign, another_nodes):
        assert monitor.accept(message, wanted) is None
    assert monitor.counts.unknown == len(foreign)
    assert monitor.counts.bad == 0
    ours = can.Message(arbitration_id=command.frame_id, data=data, is_extended_id=False)
    accepted = monitor.accept(ours, wanted)
    assert accepted is not None and accepted[1] == 1
    assert 0x7FF not in WIRE.defined_ids and command.frame_id in WIRE.defined_ids
