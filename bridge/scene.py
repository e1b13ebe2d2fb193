"""The arm in 3D, as Foxglove draws it: frames and scene entities from the robot's parameters,
the joint state, the task and the paths. Pure: no bus, no server, no file.

The bridge serves what :class:`ArmScene` makes to Foxglove live (``bridge/foxglove_server.py``)
and the recorder writes the same into ``run.mcap`` (``recorder/node.py``), on the topics
:data:`SCENE_TOPIC` (``foxglove.SceneUpdate``) and :data:`TF_TOPIC` (``foxglove.FrameTransforms``).

The frames form the arm's kinematic chain: ``world`` (the floor under the base, z up),
``link1`` at the height ``d0`` of joint 1 turned by theta1, ``link2`` at the elbow (``a1``
along link 1) turned by theta2, and ``quill`` at the tool point (``a2`` along link 2, ``d3``
down). Composed, the chain puts ``quill`` where :func:`protocol.kinematics.forward` puts the
tool. The links, the base column and the quill are drawn in their frames (they follow the
transforms); the obstacle (real and inflated), the waypoints, the planned path and the path
travelled in ``world``. Every scene message deletes what came before and holds the whole
scene, so a client that joins late, or a reader that seeks in a recording, needs only the
latest one.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from foxglove.messages import (
    Color,
    CubePrimitive,
    CylinderPrimitive,
    FrameTransform,
    FrameTransforms,
    LinePrimitive,
    LinePrimitiveLineType,
    Point3,
    Pose,
    Quaternion,
    SceneEntity,
    SceneEntityDeletion,
    SceneEntityDeletionType,
    SceneUpdate,
    SpherePrimitive,
    Timestamp,
    Vector3,
)

from controller.planner import plan_of
from protocol.config import RobotConfig
from protocol.geometry import EllipticCylinder
from protocol.kinematics import forward
from protocol.scenario import Scenario

Vec3 = tuple[float, float, float]
Joints = tuple[float, float, float]

STATE_TOPIC_PREFIX = "scara/"
"""Foxglove topics of the decoded state (``scara/joints`` ...), live and in recordings alike,
so one layout (``config/foxglove/scara.json``) serves both."""
SCENE_TOPIC = "scara/scene"
TF_TOPIC = "scara/tf"

WORLD = "world"
LINK1 = "link1"
LINK2 = "link2"
QUILL = "quill"

TF_PERIOD = 1.0 / 30.0
"""s between two transforms: 30 Hz moves the arm smoothly and keeps a recording small."""
SCENE_PERIOD = 0.25
"""s at least between two scenes that changed (the path travelled grows while the arm moves):
each holds the whole path, up to 65 kB, so a recording's scenes stay within 260 kB/s before
compression, 20 kB/s on a run of the reference task."""
SCENE_REFRESH = 1.0
"""s at most between two scenes, changed or not, for a live client that joins late."""
TRAIL_STEP = 0.005
"""m the tool moves before the path travelled takes another point."""
TRAIL_POINTS = 2000
"""Points of the path travelled kept at most (the oldest go): memory stays flat however long
the arm runs."""
PLAN_STEP = 0.02
"""s between the points the planned path is drawn through."""

BASE_DIAMETER = 0.12
LINK_WIDTH = 0.06
LINK_THICKNESS = 0.04
QUILL_DIAMETER = 0.02
WAYPOINT_DIAMETER = 0.02
LINE_THICKNESS = 0.004

GREY = Color(r=0.55, g=0.57, b=0.6, a=1.0)
ARM = Color(r=0.95, g=0.6, b=0.1, a=1.0)
QUILL_COLOUR = Color(r=0.8, g=0.8, b=0.85, a=1.0)
OBSTACLE = Color(r=0.35, g=0.35, b=0.4, a=1.0)
INFLATED = Color(r=0.9, g=0.2, b=0.2, a=0.25)
WAYPOINT = Color(r=0.2, g=0.5, b=1.0, a=1.0)
PLANNED = Color(r=0.2, g=0.5, b=1.0, a=0.6)
TRAVELLED = Color(r=0.1, g=0.8, b=0.3, a=1.0)


@dataclass(frozen=True, slots=True)
class Transform:
    """A child frame in its parent: translated, then turned by ``yaw`` about z."""

    parent: str
    child: str
    translation: Vec3
    yaw: float


def arm_frames(robot: RobotConfig, joints: Joints) -> tuple[Transform, Transform, Transform]:
    """The arm's chain of frames at ``joints`` (theta1, theta2 rad, d3 m)."""
    theta1, theta2, d3 = joints
    return (
        Transform(WORLD, LINK1, (0.0, 0.0, robot.d0), theta1),
        Transform(LINK1, LINK2, (robot.a1, 0.0, 0.0), theta2),
        Transform(LINK2, QUILL, (robot.a2, 0.0, -d3), 0.0),
    )


def about_z(yaw: float) -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2.0), w=math.cos(yaw / 2.0))


def pose(position: Vec3, yaw: float = 0.0) -> Pose:
    return Pose(
        position=Vector3(x=position[0], y=position[1], z=position[2]), orientation=about_z(yaw)
    )


def stamp_of(time: float) -> Timestamp:
    return Timestamp.from_epoch_secs(time)


def frame_transforms(robot: RobotConfig, joints: Joints, time: float) -> FrameTransforms:
    """The arm's frames at ``joints``, stamped ``time`` (s since the epoch)."""
    stamp = stamp_of(time)
    return FrameTransforms(
        transforms=[
            FrameTransform(
                timestamp=stamp,
                parent_frame_id=frame.parent,
                child_frame_id=frame.child,
                translation=Vector3(
                    x=frame.translation[0], y=frame.translation[1], z=frame.translation[2]
                ),
                rotation=about_z(frame.yaw),
            )
            for frame in arm_frames(robot, joints)
        ]
    )


def arm_entities(robot: RobotConfig, stamp: Timestamp) -> list[SceneEntity]:
    """The base column, the links and the quill, each in its own frame."""
    quill_length = robot.d3_max + LINK_THICKNESS
    return [
        SceneEntity(
            timestamp=stamp,
            frame_id=WORLD,
            id="base",
            cylinders=[
                CylinderPrimitive(
                    pose=pose((0.0, 0.0, robot.d0 / 2.0)),
                    size=Vector3(x=BASE_DIAMETER, y=BASE_DIAMETER, z=robot.d0),
                    bottom_scale=1.0,
                    top_scale=1.0,
                    color=GREY,
                )
            ],
        ),
        _link(LINK1, robot.a1, LINK_THICKNESS / 2.0, stamp),
        _link(LINK2, robot.a2, -LINK_THICKNESS / 2.0, stamp),
        SceneEntity(  # from the tool point up: d3 down, the quill's top sinks with it
            timestamp=stamp,
            frame_id=QUILL,
            id=QUILL,
            frame_locked=True,
            cylinders=[
                CylinderPrimitive(
                    pose=pose((0.0, 0.0, quill_length / 2.0)),
                    size=Vector3(x=QUILL_DIAMETER, y=QUILL_DIAMETER, z=quill_length),
                    bottom_scale=1.0,
                    top_scale=1.0,
                    color=QUILL_COLOUR,
                )
            ],
        ),
    ]


def _link(frame: str, length: float, height: float, stamp: Timestamp) -> SceneEntity:
    """A link as a box from its joint (the frame's origin) ``length`` along x."""
    return SceneEntity(
        timestamp=stamp,
        frame_id=frame,
        id=frame,
        frame_locked=True,
        cubes=[
            CubePrimitive(
                pose=pose((length / 2.0, 0.0, height)),
                size=Vector3(x=length + LINK_WIDTH, y=LINK_WIDTH, z=LINK_THICKNESS),
                color=ARM,
            )
        ],
    )


def obstacle_entity(obstacle: EllipticCylinder, stamp: Timestamp) -> SceneEntity:
    """The obstacle standing on the floor, and around it the inflated one the arm must keep
    out of (its section's semi-axes and top, as the geometry measures them)."""
    inflated = obstacle.section()
    return SceneEntity(
        timestamp=stamp,
        frame_id=WORLD,
        id="obstacle",
        cylinders=[
            CylinderPrimitive(
                pose=pose((obstacle.x, obstacle.y, obstacle.height / 2.0), obstacle.yaw),
                size=Vector3(
                    x=obstacle.long_diameter, y=obstacle.short_diameter, z=obstacle.height
                ),
                bottom_scale=1.0,
                top_scale=1.0,
                color=OBSTACLE,
            ),
            CylinderPrimitive(
                pose=pose((obstacle.x, obstacle.y, inflated.top / 2.0), obstacle.yaw),
                size=Vector3(x=2.0 * inflated.a, y=2.0 * inflated.b, z=inflated.top),
                bottom_scale=1.0,
                top_scale=1.0,
                color=INFLATED,
            ),
        ],
    )


def planned_path(task: Scenario) -> list[Vec3]:
    """The planned cubic through the task's waypoints, every :data:`PLAN_STEP`."""
    plan = plan_of(task)
    start = task.waypoints[0].t
    times = np.append(np.arange(start, task.waypoints[-1].t, PLAN_STEP), task.waypoints[-1].t)
    positions, _ = plan.sample(times)
    return [(float(x), float(y), float(z)) for x, y, z in positions]


def task_entities(task: Scenario, plan: list[Vec3], stamp: Timestamp) -> list[SceneEntity]:
    """The waypoints, the planned path and the obstacle (if any) of a task."""
    entities = [
        SceneEntity(
            timestamp=stamp,
            frame_id=WORLD,
            id="waypoints",
            spheres=[
                SpherePrimitive(
                    pose=pose((w.x, w.y, w.z)),
                    size=Vector3(x=WAYPOINT_DIAMETER, y=WAYPOINT_DIAMETER, z=WAYPOINT_DIAMETER),
                    color=WAYPOINT,
                )
                for w in task.waypoints
            ],
        ),
        _line("plan", plan, PLANNED, stamp),
    ]
    if task.obstacle is not None:
        entities.append(obstacle_entity(task.obstacle, stamp))
    return entities


def _line(name: str, points: list[Vec3], color: Color, stamp: Timestamp) -> SceneEntity:
    return SceneEntity(
        timestamp=stamp,
        frame_id=WORLD,
        id=name,
        lines=[
            LinePrimitive(
                type=LinePrimitiveLineType.LineStrip,
                pose=pose((0.0, 0.0, 0.0)),
                thickness=LINE_THICKNESS,
                points=[Point3(x=x, y=y, z=z) for x, y, z in points],
                color=color,
            )
        ],
    )


class SceneMessages(NamedTuple):
    """What is due at one joint state: the arm's frames, the scene, either, both or none."""

    transforms: FrameTransforms | None
    scene: SceneUpdate | None


class ArmScene:
    """The scene of one arm as it moves: the task drawn, the path travelled since the last
    run started, and when each message is due (by the caller's clock: wall time live, the
    bus timestamps in a recording)."""

    def __init__(self, robot: RobotConfig, task: Scenario | None = None) -> None:
        self.robot = robot
        self.travelled: deque[Vec3] = deque(maxlen=TRAIL_POINTS)
        self._task: Scenario | None = None
        self._plan: list[Vec3] = []
        self._changed = True
        self._next_transforms = -math.inf
        self._next_scene = -math.inf
        self._refresh_at = -math.inf
        self.set_task(task)

    def set_task(self, task: Scenario | None) -> None:
        """The task to draw (its waypoints, plan and obstacle); ``None``: none yet."""
        if task is self._task:
            return
        self._task = task
        self._plan = planned_path(task) if task is not None else []
        self._changed = True

    def on_event(self, event: str) -> None:
        """A run that starts begins a new path travelled."""
        if event == "run_started":
            self.travelled.clear()
            self._changed = True

    def on_joints(self, joints: Joints, time: float) -> SceneMessages:
        """Take the joint state at ``time`` (s); the messages due then."""
        tool = forward(self.robot, *joints)
        if not self.travelled or math.dist(tool, self.travelled[-1]) >= TRAIL_STEP:
            self.travelled.append(tool)
            self._changed = True
        transforms = None
        if time >= self._next_transforms:
            # on a grid of the period, started again after a pause (as bridge/rate.py does)
            late = time - self._next_transforms >= TF_PERIOD
            self._next_transforms = (time if late else self._next_transforms) + TF_PERIOD
            transforms = frame_transforms(self.robot, joints, time)
        scene = None
        if (self._changed and time >= self._next_scene) or time >= self._refresh_at:
            self._next_scene = time + SCENE_PERIOD
            self._refresh_at = time + SCENE_REFRESH
            self._changed = False
            scene = self.scene(time)
        return SceneMessages(transforms, scene)

    def scene(self, time: float) -> SceneUpdate:
        """The whole scene at ``time``, replacing every entity drawn before."""
        stamp = stamp_of(time)
        entities = arm_entities(self.robot, stamp)
        if self._task is not None:
            entities += task_entities(self._task, self._plan, stamp)
        entities.append(_line("travelled", list(self.travelled), TRAVELLED, stamp))
        return SceneUpdate(
            deletions=[SceneEntityDeletion(timestamp=stamp, type=SceneEntityDeletionType.All)],
            entities=entities,
        )
