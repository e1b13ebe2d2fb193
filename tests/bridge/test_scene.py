"""The arm's scene for Foxglove (``bridge/scene.py``): its frames compose to the forward
kinematics, its entities draw the task where it is, and its messages come at their rates with
memory that stays flat. The messages are decoded with Foxglove's published schemas
(``foxglove-schemas-protobuf``), not with the SDK that wrote them."""

from __future__ import annotations

import math

import pytest
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

from bridge.scene import (
    LINK1,
    LINK2,
    QUILL,
    SCENE_PERIOD,
    SCENE_REFRESH,
    TRAIL_POINTS,
    WORLD,
    ArmScene,
    Transform,
    arm_frames,
    frame_transforms,
)
from controller.task_rules import load_task
from protocol.config import RobotConfig
from protocol.kinematics import forward

REFERENCE = load_task("reference")
ROBOT = REFERENCE.robot
POSES = [(0.0, 0.0, 0.0), (0.7, -1.9, 0.12), (-2.5, 2.4, 0.2), (1.3, 0.4, 0.05)]


def world_origin(frames: tuple[Transform, ...], child: str) -> tuple[float, float, float]:
    """Where ``child``'s origin is in ``world``, composing the chain from it up."""
    by_child = {frame.child: frame for frame in frames}
    x = y = z = 0.0
    while child != WORLD:
        frame = by_child[child]
        c, s = math.cos(frame.yaw), math.sin(frame.yaw)
        x, y = c * x - s * y, s * x + c * y
        tx, ty, tz = frame.translation
        x, y, z = x + tx, y + ty, z + tz
        child = frame.parent
    return x, y, z


@pytest.mark.parametrize("joints", POSES)
def test_the_quill_frame_is_where_the_forward_kinematics_put_the_tool(
    joints: tuple[float, float, float],
) -> None:
    assert world_origin(arm_frames(ROBOT, joints), QUILL) == pytest.approx(
        forward(ROBOT, *joints), abs=1e-12
    )


@pytest.mark.parametrize("joints", POSES)
def test_link_2_frame_is_at_the_elbow_and_link_1_on_the_column(
    joints: tuple[float, float, float],
) -> None:
    theta1 = joints[0]
    frames = arm_frames(ROBOT, joints)
    assert world_origin(frames, LINK1) == pytest.approx((0.0, 0.0, ROBOT.d0))
    elbow = (ROBOT.a1 * math.cos(theta1), ROBOT.a1 * math.sin(theta1), ROBOT.d0)
    assert world_origin(frames, LINK2) == pytest.approx(elbow, abs=1e-12)


def test_the_quill_follows_d3_down_and_nothing_else_moves() -> None:
    robot = RobotConfig(a1=0.4, a2=0.25, d0=0.5, d3_max=0.3)
    up = arm_frames(robot, (0.3, -0.8, 0.0))
    down = arm_frames(robot, (0.3, -0.8, 0.25))
    assert up[:2] == down[:2]
    assert world_origin(down, QUILL) == pytest.approx(
        (*world_origin(up, QUILL)[:2], world_origin(up, QUILL)[2] - 0.25)
    )
    assert world_origin(down, QUILL)[2] == pytest.approx(robot.d0 - 0.25)


def test_the_encoded_transforms_say_what_the_frames_say() -> None:
    joints = (0.7, -1.9, 0.12)
    decoded = FrameTransforms.FromString(frame_transforms(ROBOT, joints, 1234.5).encode())
    frames = arm_frames(ROBOT, joints)
    assert len(decoded.transforms) == len(frames)
    for message, frame in zip(decoded.transforms, frames, strict=True):
        assert (message.parent_frame_id, message.child_frame_id) == (frame.parent, frame.child)
        translation = message.translation
        assert (translation.x, translation.y, translation.z) == pytest.approx(frame.translation)
        rotation = message.rotation
        assert (rotation.x, rotation.y) == (0.0, 0.0)
        assert 2.0 * math.atan2(rotation.z, rotation.w) == pytest.approx(frame.yaw)
        assert (message.timestamp.seconds, message.timestamp.nanos) == (1234, 500_000_000)


def decoded_scene(scene: ArmScene, time: float) -> SceneUpdate:
    return SceneUpdate.FromString(scene.scene(time).encode())


def test_the_scene_draws_the_arm_in_its_frames_and_the_task_where_it_is() -> None:
    scene = ArmScene(ROBOT, REFERENCE)
    scene.on_joints(REFERENCE.initial_joints(), 10.0)
    update = decoded_scene(scene, 10.0)
    assert [d.type for d in update.deletions] == [SceneEntityDeletion.ALL]
    entities = {entity.id: entity for entity in update.entities}
    assert set(entities) == {
        "base", LINK1, LINK2, QUILL, "waypoints", "plan", "obstacle", "travelled"
    }  # fmt: skip
    for frame in (LINK1, LINK2, QUILL):
        assert entities[frame].frame_id == frame and entities[frame].frame_locked
    link2 = entities[LINK2].cubes[0]
    assert link2.pose.position.x == pytest.approx(ROBOT.a2 / 2)

    waypoints = [(s.pose.position.x, s.pose.position.y, s.pose.position.z)
                 for s in entities["waypoints"].spheres]  # fmt: skip
    assert waypoints == [(w.x, w.y, w.z) for w in REFERENCE.waypoints]
    plan = entities["plan"].lines[0].points
    first, last = REFERENCE.waypoints[0], REFERENCE.waypoints[-1]
    assert (plan[0].x, plan[0].y, plan[0].z) == pytest.approx((first.x, first.y, first.z))
    assert (plan[-1].x, plan[-1].y, plan[-1].z) == pytest.approx((last.x, last.y, last.z))

    obstacle = REFERENCE.obstacle
    assert obstacle is not None and obstacle.inflation > 0
    real, inflated = entities["obstacle"].cylinders
    assert (real.size.x, real.size.y, real.size.z) == pytest.approx(
        (obstacle.long_diameter, obstacle.short_diameter, obstacle.height)
    )
    assert real.pose.position.z == pytest.approx(obstacle.height / 2)  # on the floor
    grown = 2 * obstacle.inflation
    assert (inflated.size.x, inflated.size.y, inflated.size.z) == pytest.approx(
        (obstacle.long_diameter + grown, obstacle.short_diameter + grown,
         obstacle.height + obstacle.inflation)
    )  # fmt: skip
    assert inflated.color.a < 1.0  # see-through: the real one shows inside
    orientation = real.pose.orientation
    assert 2.0 * math.atan2(orientation.z, orientation.w) == pytest.approx(obstacle.yaw)

    travelled = entities["travelled"].lines[0].points
    tool = forward(ROBOT, *REFERENCE.initial_joints())
    assert [(p.x, p.y, p.z) for p in travelled] == [pytest.approx(tool)]


def test_without_a_task_the_scene_is_the_arm_and_its_path() -> None:
    scene = ArmScene(ROBOT)
    assert {entity.id for entity in decoded_scene(scene, 0.0).entities} == {
        "base", LINK1, LINK2, QUILL, "travelled"
    }  # fmt: skip


def test_transforms_come_at_30_hz_and_the_scene_when_it_changed_or_once_a_second() -> None:
    scene = ArmScene(ROBOT, REFERENCE)
    transforms = scenes = 0
    for tick in range(300):  # 3 s at 100 Hz; the arm moves in the first second only
        theta1 = 0.3 + 0.002 * min(tick, 100)
        due = scene.on_joints((theta1, 0.5, 0.1), 100.0 + tick / 100)
        transforms += due.transforms is not None
        scenes += due.scene is not None
    assert 89 <= transforms <= 91
    # moving: at most every SCENE_PERIOD (5 in its first second); still: once a second (2 more)
    moving = 1 / SCENE_PERIOD + 1
    assert moving <= scenes <= moving + 2 / SCENE_REFRESH + 1


def test_a_run_that_starts_begins_a_new_path_and_the_path_keeps_its_latest_points() -> None:
    scene = ArmScene(ROBOT)
    step = 0.01  # rad: about 6 mm of the tool's, more than the path's step
    for tick in range(TRAIL_POINTS + 500):
        scene.on_joints((-2.5 + step * tick, 0.5, 0.0), tick / 100)
        scene.on_joints((-2.5 + step * tick, 0.5, 0.0), tick / 100 + 0.005)  # not moved
    assert len(scene.travelled) == TRAIL_POINTS
    last = forward(ROBOT, -2.5 + step * (TRAIL_POINTS + 499), 0.5, 0.0)
    assert scene.travelled[-1] == pytest.approx(last)
    assert scene.travelled[0] == pytest.approx(forward(ROBOT, -2.5 + step * 500, 0.5, 0.0))
    scene.on_event("waypoint_reached")
    assert len(scene.travelled) == TRAIL_POINTS
    scene.on_event("run_started")
    assert len(scene.travelled) == 0
