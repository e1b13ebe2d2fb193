"""The soak's invariants, checked from the recordings alone (``scara-soak check``).

The checker sees what the recorder saw: every frame on the bus in the order the recorder
received it, stamped with the recorder's receive time. Through one router each sender's frames
arrive in order, and a frame a node received before it sent another reached the recorder
before that other too, so the order is one the nodes could have seen; the times are the
recorder's (a paused recorder stamps a backlog at once: durations look shorter, never
longer). What each invariant reads, and what it cannot see, is in ``docs/soak.md``.

Each invariant is a pure function over the frames of one recording, decoded once
(:func:`decode`), so that it can be tested on hand-made sequences.
"""

from __future__ import annotations

import bisect
import json
import tempfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can

from controller.node import STALE_TICKS
from protocol.codec import COUNTER_MODULO, WIRE, alive_counter
from protocol.config import RobotConfig
from protocol.e2e import E2EMonitor
from protocol.errors import ConfigError, DecodeError
from protocol.geometry import EllipticCylinder
from protocol.isotp_link import CONSECUTIVE, FIRST, SINGLE, unseal
from protocol.kinematics import forward
from protocol.messages import (
    COMMAND,
    CONTROLLER_STATUS,
    NODE_COMMAND,
    PLANT_STATUS,
    STATE_IDS,
    STOP,
    WORLD_UPLOAD,
    JointStateParts,
    NodeId,
    NodeState,
    PlantFault,
    PlantFlag,
    Request,
)
from protocol.scenario import parse_scenario
from protocol.world import STARTUP_WORLD, read_world
from recorder.mcap_can import RecordingError, frames, read_attachments
from recorder.recover import recover

INVARIANTS = (
    "stale_command",
    "collision",
    "inside_obstacle",
    "fault_latch",
    "estop_latch",
    "bad_frame_acted",
    "recording",
    "recovery",
)
"""Every invariant, by the name the report counts its violations under."""
NEW_START = 0.25
"""s of silence after which a node whose counter is back near 0 (:func:`_early`: its
status's, the plant's joint state's) is taken for a new process: a restart (it has no latch
to keep, its echo starts over). A pause that happens to end on such a counter is taken for
one too, which only leaves something unjudged."""
EARLY = 4
"""A counter below this is a new process's (its first frames may be lost on the wire)."""
HEARD = 0.5
"""s without a node's status after which it is taken for not heard."""
ESTOP_WITHIN = 1.0
"""s after an EmergencyStop by which every node heard must say e-stop."""
RECOVERY_BOUND = 15.0
"""s the system may be other than up (both nodes heard, each ready or running) at a time."""
ORDER_SKEW = 0.1
"""s by which the recorder's order of two senders' frames may differ from the order the nodes
saw them in. The router forwards each frame to each receiver on a queue of its own: on this
loaded 2-core machine a plant's answer was recorded 24 ms before the command it answers
(after a pause of the recorder), and during a flood a controller's commands came in a burst
18 ms after the states they were computed from. A joint state recorded up to this after a
command counts as before it, and a command recorded up to this after a state as sent before
it: a violation can be missed, not invented."""
BACKLOG = 1.0
"""s by which a plant's echo may come after the command it echoes: a plant paused for up to
0.5 s takes the commands that queued meanwhile one by one, its echoes racing through them."""
AHEAD = 0.030
"""s by which a command may be recorded after a plant's state that echoes it (24 ms seen,
after a pause of the recorder): less than the 32 ms after which its counter comes again, so
that the echoes are not followed along the commands of a later round."""
MAX_SKIP = 12
"""Usable commands a plant's new echo may lie beyond the one it echoed before: answers the
wire lost (at 10 % loss per frame, a set of three is lost 27 % of the time, twelve in a row
once in ten million commands). A taken command 16 on has the same counter, so a corrupt or
stale one taken is 15 on."""
CONFIRMED = 8
"""Echoes in a row along one way before an echo off it is judged: the way is the plant's."""
LOST_WAY = 3
"""Echoes in a row off a way through the commands after which the plant is taken not to be
on it."""
UNRECORDED = -1
"""The way of a plant echoing a command sent before the recording began: before the first
usable command recorded (its next echo may be one of the first :data:`MAX_SKIP` of them, as
from any way, or another command sent before the recording)."""
LATCHED = ("fault", "estop")
UP = ("ready", "running")
"""The node states of a system that is up: ready for a task, or running one."""
E2E_IDS = frozenset(WIRE.by_id)
"""The frames with an E2E header (the ISO-TP carriers have none)."""
NODES = {CONTROLLER_STATUS.frame_id: "controller", PLANT_STATUS.frame_id: "plant"}
RESET_TARGETS = {
    "controller": (NodeId.CONTROLLER, NodeId.ALL),
    "plant": (NodeId.PLANT, NodeId.ALL),
}


@dataclass(frozen=True, slots=True)
class Seen:
    """One recorded frame as a receiver judges it."""

    t: float
    frame_id: int
    check: str
    """``ok`` (may be acted on), ``corrupt``, ``repeated``, ``stale``, or ``other`` (no E2E
    header: ISO-TP, foreign IDs, extended, remote and error frames)."""
    counter: int | None = None
    record: Any = None
    data: bytes = b""

    @property
    def usable(self) -> bool:
        return self.check == "ok"


@dataclass(frozen=True, slots=True)
class Violation:
    invariant: str
    t: float
    """The recorder's time of the frame that shows it (s since the epoch)."""
    detail: str
    recording: str = ""


def decode(messages: Iterable[can.Message]) -> list[Seen]:
    """Judge each frame as a node would: CRC and range (the codec), then the alive counter
    (:class:`E2EMonitor`, started over at each reset, as the nodes do)."""
    monitor = E2EMonitor()
    seen = []
    for message in messages:
        data = bytes(message.data)
        frame_id = message.arbitration_id
        if (
            message.is_extended_id
            or message.is_remote_frame
            or message.is_error_frame
            or frame_id not in E2E_IDS
        ):
            seen.append(Seen(message.timestamp, frame_id, "other", data=data))
            continue
        try:
            codec, counter, record = WIRE.decode(frame_id, data)
        except DecodeError:
            nibble = alive_counter(data) if len(data) > 1 else None
            seen.append(Seen(message.timestamp, frame_id, "corrupt", nibble, data=data))
            continue
        check = monitor.check(frame_id, counter, message.timestamp)
        verdict = "ok" if check.usable else check.value
        seen.append(Seen(message.timestamp, frame_id, verdict, counter, record, data))
        if verdict == "ok" and codec is NODE_COMMAND and record.Command == Request.RESET:
            monitor.forget()
    return seen


def _early(frame: Seen) -> bool:
    """The frame's counter is one of a new process's first (:data:`EARLY`)."""
    return frame.counter is not None and frame.counter < EARLY


def _is_reset(frame: Seen, node: str) -> bool:
    return (
        frame.usable
        and frame.frame_id == NODE_COMMAND.frame_id
        and frame.record.Command == Request.RESET
        and frame.record.Target in RESET_TARGETS[node]
    )


def _states(seen: Sequence[Seen]) -> Iterable[tuple[Seen, tuple[Any, Any, int]]]:
    """The complete joint states (the three frames of one counter), at their last frame."""
    parts = JointStateParts()
    for frame in seen:
        if frame.usable and frame.frame_id in STATE_IDS:
            assert frame.counter is not None
            joint = STATE_IDS.index(frame.frame_id)
            complete = parts.add(joint, frame.counter, frame.record)
            if complete is not None:
                yield frame, complete


def stale_commands(seen: Sequence[Seen]) -> list[Violation]:
    """No command with Enable was sent more than STALE_TICKS control ticks after the newest
    complete joint state before it. Ticks are the commands recorded after the state (a
    corrupt one too; a duplicate or one held back is no tick of its own), not counting those
    recorded up to :data:`ORDER_SKEW` after it (the controller may have sent them before the state
    reached it) nor the commands the wire dropped (when they were sent, no frame says); a
    state recorded up to ORDER_SKEW after a command counts as before it. So a violation can be
    missed, never invented. Commands before the recording's first state are not judged."""
    found = []
    complete = {id(frame) for frame, _ in _states(seen)}
    times = [frame.t for frame in seen if id(frame) in complete]
    ticks: int | None = None
    state_time = -float("inf")
    for frame in seen:
        if id(frame) in complete:
            ticks, state_time = 0, frame.t
            continue
        if frame.frame_id != COMMAND.frame_id or frame.check in ("repeated", "stale"):
            continue
        if ticks is None or frame.t - state_time <= ORDER_SKEW:
            continue
        ticks += 1
        if not frame.usable or not frame.record.Enable or ticks <= STALE_TICKS:
            continue
        if bisect.bisect_right(times, frame.t + ORDER_SKEW) > bisect.bisect_right(times, frame.t):
            continue  # a state recorded just after it
        found.append(
            Violation(
                "stale_command",
                frame.t,
                f"drive enabled {ticks} ticks after the newest joint state (at most {STALE_TICKS})",
            )
        )
    return found


def collisions(seen: Sequence[Seen]) -> list[Violation]:
    """The plant never reported a collision (its own truth, on the obstacle it holds)."""
    found = []
    colliding = False
    for frame in seen:
        if frame.frame_id != PLANT_STATUS.frame_id or not frame.usable:
            continue
        now = bool(
            frame.record.Flags & int(PlantFlag.COLLISION)
            or frame.record.FaultCode & int(PlantFault.COLLISION)
        )
        if now and not colliding:
            found.append(Violation("collision", frame.t, "the plant reports a collision"))
        colliding = now
    return found


@dataclass
class Worlds:
    """The worlds the plant was sent (WorldUpload transfers put back together), by number,
    and the robot the joint states are read with; kept across the recordings of one soak."""

    robot: RobotConfig = field(default_factory=RobotConfig)
    obstacles: dict[int, EllipticCylinder | None] = field(default_factory=dict)
    _transfer: bytearray = field(default_factory=bytearray)
    _length: int = 0

    def feed(self, data: bytes) -> None:
        """One WorldUpload frame (ISO-TP, normal addressing, as ``protocol/isotp_link.py``)."""
        if not data:
            return
        kind = data[0] >> 4
        if kind == SINGLE:
            self._complete(data[1 : 1 + (data[0] & 0x0F)])
        elif kind == FIRST and len(data) >= 2:
            self._length = ((data[0] & 0x0F) << 8) | data[1]
            self._transfer = bytearray(data[2:])
        elif kind == CONSECUTIVE and self._length:
            self._transfer += data[1:]
            if len(self._transfer) >= self._length:
                self._complete(bytes(self._transfer[: self._length]))
                self._length = 0

    def _complete(self, transfer: bytes) -> None:
        payload = unseal(transfer)
        if payload is None:
            return  # failed its CRC: the plant drops it too
        try:
            world = read_world(payload)
        except ConfigError:
            return  # the plant refuses it too
        self.obstacles[world.number] = world.obstacle


def inside_obstacle(seen: Sequence[Seen], worlds: Worlds) -> tuple[list[Violation], int]:
    """The tool's centre never entered the inflated obstacle of the world the plant holds
    (PlantStatus.World; that world's upload read from the recordings). Also the number of
    joint states not judged: their world's upload was not recorded."""
    found = []
    unjudged = 0
    world: int | None = None
    states = {id(frame): joints for frame, joints in _states(seen)}
    inside = False
    for frame in seen:
        if frame.frame_id == WORLD_UPLOAD.frame_id:
            worlds.feed(frame.data)
        elif frame.frame_id == PLANT_STATUS.frame_id and frame.usable:
            world = frame.record.World
        elif id(frame) in states:
            if world is None or world not in worlds.obstacles:
                unjudged += 1
                continue
            obstacle = worlds.obstacles[world]
            position = states[id(frame)][0]
            now = obstacle is not None and obstacle.holds(*forward(worlds.robot, *position))
            if now and not inside:
                found.append(
                    Violation(
                        "inside_obstacle",
                        frame.t,
                        f"the tool inside world {world}'s inflated obstacle at joints "
                        f"{tuple(round(p, 4) for p in position)}",
                    )
                )
            inside = now
    return found, unjudged


def _starts(seen: Sequence[Seen], node: str) -> Iterable[tuple[Seen, bool]]:
    """The node's usable statuses, each with whether it is a new process's first."""
    status_id = CONTROLLER_STATUS.frame_id if node == "controller" else PLANT_STATUS.frame_id
    last: float | None = None
    for frame in seen:
        if frame.frame_id == status_id and frame.usable:
            new = last is not None and frame.t - last > NEW_START and _early(frame)
            last = frame.t
            yield frame, new


def fault_latches(seen: Sequence[Seen]) -> list[Violation]:
    """A node in fault or e-stop stays there until a reset to it (or to all) is recorded;
    a new process starts afresh."""
    found = []
    for node in RESET_TARGETS:
        latched: str | None = None
        reset_seen = False
        statuses = {id(frame): new for frame, new in _starts(seen, node)}
        for frame in seen:
            if _is_reset(frame, node):
                reset_seen = True
            if id(frame) not in statuses:
                continue
            state = NodeState(frame.record.State).name.lower()
            if statuses[id(frame)]:
                latched = None
            if state in LATCHED:
                if latched is None:  # a reset before it was for an earlier latch
                    latched, reset_seen = state, False
                continue  # (a status sent before the node took the reset may follow it)
            if latched is not None and not reset_seen:
                found.append(
                    Violation("fault_latch", frame.t, f"the {node} left {latched} without a reset")
                )
            latched = None
    return found


def estop_latches(seen: Sequence[Seen]) -> list[Violation]:
    """After an EmergencyStop, every node heard within :data:`ESTOP_WITHIN` (before a reset
    to it) says e-stop at least once; staying there is :func:`fault_latches`'s."""
    found = []
    stops = [frame for frame in seen if frame.frame_id == STOP.frame_id and frame.usable]
    for node in RESET_TARGETS:
        statuses = [frame for frame, _ in _starts(seen, node)]
        resets = [frame.t for frame in seen if _is_reset(frame, node)]
        for stop in stops:
            end = min([stop.t + ESTOP_WITHIN, *(t for t in resets if t > stop.t)])
            window = [s for s in statuses if stop.t < s.t <= end]
            if window and not any(s.record.State == NodeState.ESTOP for s in window):
                found.append(
                    Violation(
                        "estop_latch",
                        stop.t,
                        f"the {node} did not say e-stop in {len(window)} statuses after it",
                    )
                )
    return found


def bad_frames_acted(seen: Sequence[Seen]) -> list[Violation]:
    """The plant acted only on commands that passed their CRC and counter. The CommandEcho of
    its joint states (the counter of the last command it took) changes along the usable
    commands' counters in their order, each sender's frames being in the order sent whatever
    the recorder's interleaving: each new echo is one of the next :data:`MAX_SKIP` usable
    commands after the last one echoed (the plant answers every command it takes, and an
    answer the wire lost skips one). An echo that is not, where a command that failed its CRC
    or counter carried that counter among those next commands, is a bad frame acted on; one
    that no recorded frame carried is a command the recorder missed (its start, a pause), not
    judged, and so are an echo of 0 (a plant reset or restarted says 0 before its first
    command) and a duplicate (its counter is its first's).

    After a reset or a restart of the plant, and at a recording's start, the echoes are
    followed from every command the first one may echo (:func:`_anchors`), and along every
    way through the commands that keeps within AHEAD of the echoes. An echo is judged when
    one way is left that the last :data:`CONFIRMED` echoes followed, and the next echo
    follows it too."""
    found = []
    start = seen[0].t if seen else 0.0
    states = {id(frame): joints[2] for frame, joints in _states(seen)}
    commands = [
        (frame.t, frame.counter)
        for frame in seen
        if frame.frame_id == COMMAND.frame_id and frame.usable
    ]
    bad: dict[int, list[int]] = {}
    """For each usable command (by index), the counters of the bad commands recorded just
    before it."""
    usable = 0
    for frame in seen:
        if frame.frame_id != COMMAND.frame_id:
            continue
        if frame.usable:
            usable += 1
        elif frame.counter is not None:
            bad.setdefault(usable, []).append(frame.counter)
    ways: dict[int, int] = {}
    """Where in the commands the plant may be (one index once its echoes are followed), each
    with the echoes in a row it has missed."""
    streak = 0
    """Echoes in a row that continued the one way left."""
    suspect: Violation | None = None
    """An echo off the way, only a bad command carrying its counter: a violation once the
    next echo continues the way (else the way was not the plant's)."""
    last_echo: int | None = None
    last_state = -float("inf")
    for frame in seen:
        if _is_reset(frame, "plant"):
            ways, streak, suspect, last_echo = {}, 0, None, None
            continue
        echo = states.get(id(frame))
        if echo is None:
            continue
        if frame.t - last_state > NEW_START and _early(frame):
            ways, streak, suspect, last_echo = {}, 0, None, None  # a new plant
        last_state = frame.t
        if echo in (last_echo, 0):
            continue
        last_echo = echo
        if not ways:
            ways = _anchors(commands, echo, frame.t, start)
            continue
        onward: dict[int, int] = {}
        for way, missed in ways.items():
            step = _next(commands, way, echo)
            if step is not None and commands[step][0] <= frame.t + AHEAD:
                onward[step] = 0
            elif way != UNRECORDED and missed + 1 < LOST_WAY:
                onward[way] = missed + 1  # a command the recording lacks, or a bad one taken
        if UNRECORDED in ways and frame.t - BACKLOG < start:
            onward[UNRECORDED] = 0  # another command sent before the recording began
        advanced = len(onward) == 1 and UNRECORDED not in onward and 0 in onward.values()
        if advanced and suspect is not None and len(ways) == 1:
            found.append(suspect)
        suspect = None
        if len(ways) == 1 and not advanced and streak >= CONFIRMED:
            (way,) = ways
            if any(echo in bad.get(k, ()) for k in range(way + 1, way + 1 + MAX_SKIP)):
                suspect = Violation(
                    "bad_frame_acted",
                    frame.t,
                    f"the plant echoes command counter {echo}, which only a command that "
                    "failed its CRC or counter carried",
                )
        streak = streak + 1 if advanced else 0
        ways = onward or _anchors(commands, echo, frame.t, start)
    return found


def _anchors(
    commands: Sequence[tuple[float, int | None]], echo: int, t: float, start: float
) -> dict[int, int]:
    """The ways a plant's first echo (at ``t``, of counter ``echo``) may start, none missed:
    each command :func:`_near` it, and, when the recording began (its first frame, at
    ``start``) less than :data:`BACKLOG` before it, :data:`UNRECORDED` too. The counter is 4
    bits: a plant working through a backlog a cycle or more behind the commands recorded echoes
    those of an earlier cycle, sent before the recording began, and its echoes fit the
    recorded cycle after it as well, commands alike, until the plant catches up (beyond
    :data:`AHEAD`) or a command one cycle lacks tells them apart. Anchored on the recorded
    cycle alone, the checker followed a plant one cycle ahead of where it was, and judged an
    echo of the earlier cycle against the later one's corrupt command (seed 73: the first
    echo, 3, with the later cycle's 3 the only one recorded near it)."""
    ways = dict.fromkeys(_near(commands, echo, t), 0)
    if t - BACKLOG < start:
        ways[UNRECORDED] = 0
    return ways


def _near(commands: Sequence[tuple[float, int | None]], echo: int, t: float) -> list[int]:
    """The usable commands with counter ``echo`` recorded from :data:`BACKLOG` before ``t``
    to :data:`AHEAD` after it."""
    start = bisect.bisect_left(commands, (t - BACKLOG,))
    end = bisect.bisect_right(commands, (t + AHEAD, COUNTER_MODULO))
    return [i for i in range(start, end) if commands[i][1] == echo]


def _next(commands: Sequence[tuple[float, int | None]], way: int, echo: int) -> int | None:
    """The first of the :data:`MAX_SKIP` usable commands after ``way`` with counter
    ``echo``."""
    for index in range(way + 1, min(way + 1 + MAX_SKIP, len(commands))):
        if commands[index][1] == echo:
            return index
    return None


def outages(seen: Sequence[Seen]) -> list[Violation]:
    """The system (both nodes heard within :data:`HEARD`, each ready or running) was never
    other than up for longer than :data:`RECOVERY_BOUND`. An outage still open when the
    recording ends is not judged (a soak's end stops the nodes first)."""
    found = []
    state: dict[str, str] = {}
    heard: dict[str, float] = {}
    down_since: float | None = None
    for frame in seen:
        node = NODES.get(frame.frame_id)
        if node is None or not frame.usable:
            continue
        state[node] = NodeState(frame.record.State).name.lower()
        heard[node] = frame.t
        if len(heard) < len(NODES):
            continue  # the recording has not heard both yet
        up = all(state[n] in UP and frame.t - heard[n] <= HEARD for n in NODES.values())
        if not up and down_since is None:
            down_since = frame.t
        elif up and down_since is not None:
            if frame.t - down_since > RECOVERY_BOUND:
                found.append(
                    Violation(
                        "recovery",
                        down_since,
                        f"not back to ready or running for {frame.t - down_since:.1f} s "
                        f"(bound {RECOVERY_BOUND:g} s)",
                    )
                )
            down_since = None
    return found


@dataclass
class Verdict:
    """The violations found, and how much the checker saw."""

    violations: list[Violation] = field(default_factory=list)
    recordings: int = 0
    frames: int = 0
    states: int = 0
    commands: int = 0
    unjudged_states: int = 0
    """Joint states whose world's upload no recording holds."""

    def counts(self) -> dict[str, int]:
        counted = dict.fromkeys(INVARIANTS, 0)
        for violation in self.violations:
            counted[violation.invariant] += 1
        return counted


def check_frames(
    messages: Iterable[can.Message], worlds: Worlds, verdict: Verdict, name: str
) -> None:
    """Every invariant over one recording's frames, into ``verdict``."""
    seen = decode(messages)
    inside, unjudged = inside_obstacle(seen, worlds)
    found = [
        *stale_commands(seen),
        *collisions(seen),
        *inside,
        *fault_latches(seen),
        *estop_latches(seen),
        *bad_frames_acted(seen),
        *outages(seen),
    ]
    verdict.violations += [
        Violation(v.invariant, v.t, v.detail, name) for v in sorted(found, key=lambda v: v.t)
    ]
    verdict.recordings += 1
    verdict.frames += len(seen)
    verdict.states += sum(1 for _ in _states(seen))
    verdict.commands += sum(1 for f in seen if f.frame_id == COMMAND.frame_id)
    verdict.unjudged_states += unjudged


def readable(path: Path) -> tuple[Path | None, str]:
    """The file to read ``path``'s frames from: itself if it is complete, else its
    ``.recovered.mcap`` twin if that holds every complete chunk of it; None and why not."""
    with tempfile.TemporaryDirectory(prefix="scara-soak-") as folder:
        try:
            report = recover(path, Path(folder) / "check.mcap")
        except RecordingError as error:
            return None, str(error)
        if report.was_complete:
            return path, ""
        twin = path.with_suffix(".recovered.mcap")
        if not twin.exists():
            return None, "cut short and not recovered (scara-record recover)"
        try:
            again = recover(twin, Path(folder) / "twin.mcap")
        except RecordingError as error:
            return None, f"its recovered file: {error}"
    if not again.was_complete or again.frames != report.frames:
        return None, (
            f"its recovered file holds {again.frames} frames of the {report.frames} in its "
            "complete chunks"
        )
    return twin, ""


def _worlds_from(paths: Sequence[Path]) -> Worlds:
    """The robot and the start-up world (number 0) from the first recording that has the
    scenario attached (the recorder's ``--scenario``: the plant's own file)."""
    worlds = Worlds()
    for path in paths:
        try:
            attached = read_attachments(path).get("scenario.json")
        except RecordingError:
            continue
        if attached is not None:
            scenario = parse_scenario(json.loads(attached))
            worlds.robot = scenario.robot
            worlds.obstacles[STARTUP_WORLD] = scenario.obstacle
            break
    return worlds


def recordings_of(target: Path) -> list[Path]:
    """A soak's recordings in the order they were made (a run folder, or its
    ``recordings/``), or the one file named."""
    if target.is_file():
        return [target]
    folder = target / "recordings" if (target / "recordings").is_dir() else target
    return sorted(p for p in folder.glob("*.mcap") if not p.name.endswith(".recovered.mcap"))


def check(target: Path) -> Verdict:
    """Every invariant over the recordings of ``target`` (a soak's folder, or one file)."""
    verdict = Verdict()
    paths = recordings_of(target)
    readable_paths = []
    for path in paths:
        source, why = readable(path)
        if source is None:
            verdict.violations.append(Violation("recording", 0.0, why, path.name))
        else:
            readable_paths.append(source)
    worlds = _worlds_from(readable_paths)
    for source in readable_paths:
        with source.open("rb") as stream:
            check_frames(frames(stream), worlds, verdict, source.name)
    return verdict
