"""The two sets of operations the law is written over give the same bits: numpy's against
:mod:`math`, the wire, ties of min, max and clip, row subsets and the per-run iteration; and
the law's formulas themselves, run on many random inputs at once and one by one (to 1e-9
where numpy's atan2, acos or exp are an ulp off libm's: on a CPU with AVX-512)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from support import NOT_LIBM_TOLERANCE, NUMPY_IS_LIBM

from controller.behaviours import Tracking, backward_tracking, plan_tracking
from controller.control_law import turned_towards
from controller.fuzzy import FuzzyInference, RuleBase, infer
from controller.obstacle import NO_OBSTACLE, measure, sense
from plant_sim.model import integrate
from protocol.config import ControllerConfig, RobotConfig
from protocol.geometry import EllipticCylinder, Section, nearest_point, to_local
from protocol.messages import (
    joints_on_the_wire,
    on_the_wire_command,
    on_the_wire_state,
    rates_on_the_wire,
)
from protocol.ops import ARRAY, SCALAR, Ops

RNG_SEED = 3


def test_numpys_functions_are_maths_to_the_last_bit_or_next_to_it() -> None:
    rng = np.random.default_rng(RNG_SEED)
    x, y = rng.uniform(-7.0, 7.0, 20_000), rng.uniform(-2.0, 2.0, 20_000)
    unit = rng.uniform(-1.0, 1.0, 20_000)
    # (name, arguments, ulps apart at most): numpy's own AVX-512 code for atan2, acos and
    # exp, where the CPU has it, is one ulp off libm's in a few per cent.
    for name, arguments, ulps in (
        ("sin", (x,), 0),
        ("cos", (x,), 0),
        ("tanh", (x / 3.0,), 0),
        ("atan2", (y, x), 1),
        ("acos", (unit,), 1),
        ("exp", (-np.abs(x),), 1),
        ("sqrt", (np.abs(x),), 0),
        ("copysign", (x, y), 0),
        ("rint", (x * 1000.0,), 0),
    ):
        ours = getattr(ARRAY, name)(*arguments)
        theirs = np.array(
            [
                getattr(SCALAR, name)(*values)
                for values in zip(*(a.tolist() for a in arguments), strict=True)
            ]
        )
        apart = np.abs(ours - theirs) / np.spacing(np.abs(theirs))
        assert apart.max() <= ulps, name
    assert np.array_equal((x * 3.0) % (2.0 * math.pi), [v * 3.0 % (2.0 * math.pi) for v in x])


def test_the_wire_quantises_arrays_as_the_codec_does_ties_to_even_included() -> None:
    rng = np.random.default_rng(RNG_SEED)
    x, y = rng.uniform(-7.0, 7.0, 200), rng.uniform(-2.0, 2.0, 200)
    positions = np.stack([x / 3.0, y, np.abs(y) / 5.0])
    positions[0, :4] = [0.0000005, 0.0000015, -0.0000025, 0.0000035]
    rates = np.stack([x, y * 5.0, y / 2.0])
    rates[0, :3] = [0.0005, 0.0015, -0.0025]
    wired_positions, wired_velocities = joints_on_the_wire(ARRAY, tuple(positions), tuple(rates))
    wired_rates = rates_on_the_wire(ARRAY, tuple(rates))
    for column in range(200):
        position, velocity = on_the_wire_state(tuple(positions[:, column]), tuple(rates[:, column]))
        assert [axis[column] for axis in wired_positions] == list(position)
        assert [axis[column] for axis in wired_velocities] == list(velocity)
        command = on_the_wire_command(tuple(rates[:, column]))
        assert [axis[column] for axis in wired_rates] == list(command)


def test_ties_of_min_and_max_go_to_the_first_argument_as_in_python() -> None:
    for size in (1, 3, 100):
        first, second = np.full(size, 0.0), np.full(size, -0.0)
        assert not np.signbit(ARRAY.min(first, second)).any()  # min(0.0, -0.0) is 0.0
        assert np.signbit(ARRAY.max(second, first)).all()  # max(-0.0, 0.0) is -0.0
    assert math.copysign(1.0, SCALAR.min(0.0, -0.0)) > 0 > math.copysign(1.0, SCALAR.max(-0.0, 0.0))


def test_a_clip_is_max_then_min_to_the_bit_ties_and_nan_included() -> None:
    # (x, low, high): inside, on each bound with either zero's sign, outside, NaN, and
    # bounds the wrong way round (the last word is min's, as in min(max(x, low), high)).
    cases = [
        (0.5, 0.0, 1.0),
        (-0.0, 0.0, 1.0),
        (0.0, -0.0, 1.0),
        (1.0, 0.0, 1.0),
        (-0.5, -0.0, 1.0),
        (2.0, 0.0, 1.0),
        (-0.0, -1.0, 0.0),
        (0.0, -1.0, -0.0),
        (math.nan, 0.0, 1.0),
        (-math.inf, 0.0, 1.0),
        (0.5, 1.0, 0.0),
    ]
    for ops in (SCALAR, ARRAY):
        for x, low, high in cases:
            if ops is ARRAY:
                x, low, high = np.array([x]), np.array([low]), np.array([high])
            clipped, composed = ops.clip(x, low, high), ops.min(ops.max(x, low), high)
            pair = np.array([clipped, composed], dtype=np.float64).ravel()
            assert np.array_equal(np.signbit(pair[:1]), np.signbit(pair[1:])), (x, low, high)
            assert np.array_equal(pair[:1], pair[1:], equal_nan=True), (x, low, high)


def test_a_branch_computes_only_the_runs_that_take_it() -> None:
    seen: list[int] = []

    def twice(value: Any, pair: tuple[Any, Any]) -> tuple[Any, Any]:
        seen.append(len(value))
        return value * 2.0, (pair[0] + 1.0, pair[1] > 0.0)

    values = np.arange(6.0)
    pairs = (np.arange(6.0) * 10.0, np.array([-1.0, 1.0] * 3))
    taken = values % 2.0 == 1.0
    doubled, (plus_one, positive) = ARRAY.branch(taken, twice, (-1.0, (0.0, False)), values, pairs)
    assert seen == [3]
    assert doubled.tolist() == [-1.0, 2.0, -1.0, 6.0, -1.0, 10.0]
    assert plus_one.tolist() == [0.0, 11.0, 0.0, 31.0, 0.0, 51.0]
    assert positive.tolist() == [False, True] * 3
    assert (
        ARRAY.branch(taken & False, twice, (-1.0, (0.0, False)), values, pairs)[0].tolist()
        == [-1.0] * 6
    )
    everywhere = ARRAY.branch(taken | True, twice, (-1.0, (0.0, False)), values, pairs)
    assert seen == [3, 6] and everywhere[0].tolist() == (values * 2.0).tolist()
    assert SCALAR.branch(True, twice, None, np.ones(2), (1.0, 2.0))[1] == (2.0, True)
    assert SCALAR.branch(False, twice, "otherwise") == "otherwise"


def test_an_iteration_steps_each_run_until_it_is_done_and_then_only_those_going() -> None:
    lengths: list[int] = []

    def halving(ops: Ops) -> Callable[[Any, Any], tuple[Any, Any]]:
        def step(going: Any, value: Any) -> tuple[Any, Any]:
            lengths.append(np.size(value))
            value = ops.where(going, value / 2.0, value)
            return going & (value > 1.0), value

        return step

    starts = [1.5, 3.0, 40.0, 1000.0, 2.0**40, 5.0]
    going, halved = ARRAY.converge(halving(ARRAY), (np.full(6, True), np.array(starts)), 100)
    together = list(lengths)
    one_by_one = [SCALAR.converge(halving(SCALAR), (True, start), 100)[1] for start in starts]
    assert halved.tolist() == one_by_one and not going.any()
    assert together[:3] == [6, 6, 6] and together[-1] == 1  # the last going, alone
    assert max(one_by_one) <= 1.0 < min(starts)


def _points(rng: np.random.Generator, count: int, around: EllipticCylinder) -> np.ndarray:
    points = rng.uniform(-0.3, 0.3, (count, 2)) + np.array([around.x, around.y])
    on_axes = np.array(
        [[around.x, around.y], [around.x + 0.05, around.y], [around.x, around.y + 0.03]]
    )
    return np.concatenate([points, on_axes])


def _sections(obstacle: EllipticCylinder, count: int) -> Section:
    return Section(*(np.full(count, value) for value in obstacle.section()))


def test_the_fuzzy_inference_and_the_obstacles_geometry_give_the_same_bits_both_ways() -> None:
    rng = np.random.default_rng(5)
    rule_base = RuleBase.load()
    inference = FuzzyInference(rule_base)
    corners = [p for t in rule_base.inputs["min_distance"].terms.values() for p in (t.a, t.d)]
    distance = np.concatenate([rng.uniform(-0.05, 0.25, 3000), corners, [0.0, 0.2]])
    beta = np.concatenate([rng.uniform(-3.5, 3.5, 3000), np.zeros(len(corners) + 2)])
    k_t, k_c = infer(ARRAY, inference, distance, beta)
    expected = [
        inference.weights(d, b) for d, b in zip(distance.tolist(), beta.tolist(), strict=True)
    ]
    assert list(zip(k_t.tolist(), k_c.tolist(), strict=True)) == expected

    obstacle = EllipticCylinder(0.4, -0.1, 0.12, 0.05, 0.3, 0.7, 0.02)
    points = _points(rng, 3000, obstacle)
    sections = _sections(obstacle, len(points))
    found = nearest_point(ARRAY, sections, *to_local(sections, points[:, 0], points[:, 1]))
    for index, (x, y) in enumerate(points.tolist()):
        clearance, (nearest_x, nearest_y) = obstacle.nearest_point(x, y)
        assert (clearance, nearest_x, nearest_y) == tuple(column[index] for column in found)


@pytest.mark.parametrize(
    "obstacle", [EllipticCylinder(0.4, -0.1, 0.12, 0.05, 0.3, 0.7, 0.02), None]
)
def test_dm_gives_the_same_bits_both_ways(obstacle: EllipticCylinder | None) -> None:
    rng = np.random.default_rng(7)
    around = obstacle or EllipticCylinder(0.4, -0.1, 0.1, 0.1, 0.3)
    points = _points(rng, 2000, around)
    heights = rng.choice([0.1, 0.35], len(points))  # below the top, or over it
    goals = rng.uniform(-0.5, 0.5, (len(points), 2)) + np.array([around.x, around.y])
    goals[:5] = points[:5]  # on the goal
    headings = rng.uniform(-math.pi, math.pi, len(points))
    section = (
        _sections(obstacle, len(points))
        if obstacle
        else Section(*(np.full(len(points), value) for value in NO_OBSTACLE))
    )
    found = sense(
        ARRAY,
        section,
        0.2,
        (points[:, 0], points[:, 1], heights),
        (goals[:, 0], goals[:, 1]),
        (np.cos(headings), np.sin(headings)),
    )
    for index in range(len(points)):
        tcp = (float(points[index, 0]), float(points[index, 1]), float(heights[index]))
        goal = (float(goals[index, 0]), float(goals[index, 1]))
        one = measure(obstacle, tcp, goal, 0.2, float(headings[index]))
        assert_same(_at(found, index), _at(one, None), index)


def _at(value: Any, index: int | None) -> Any:
    """A (nested) tuple's numbers, of run ``index`` (None: floats already)."""
    if isinstance(value, tuple):
        return tuple(_at(part, index) for part in value)
    return value if index is None else value[index].item()


def assert_same(found: Any, expected: Any, where: object) -> None:
    """The same bits where numpy is libm to the last bit (:data:`support.NUMPY_IS_LIBM`);
    elsewhere within :data:`support.NOT_LIBM_TOLERANCE`, as ``tests/sim/test_one_law.py``
    allows the whole law."""
    if NUMPY_IS_LIBM:
        assert found == expected, where
        return
    flat_found, flat_expected = _flat(found), _flat(expected)
    assert len(flat_found) == len(flat_expected), where
    for got, wanted in zip(flat_found, flat_expected, strict=True):
        if isinstance(wanted, float):
            close = math.isclose(
                got, wanted, rel_tol=NOT_LIBM_TOLERANCE, abs_tol=NOT_LIBM_TOLERANCE
            )
            assert close, (where, found, expected)
        else:
            assert got == wanted, (where, found, expected)


def _flat(value: Any) -> list[Any]:
    if isinstance(value, tuple):
        return [item for part in value for item in _flat(part)]
    return [value]


def test_pt_and_the_plant_give_the_same_bits_both_ways() -> None:
    rng = np.random.default_rng(11)
    count = 2000
    config = ControllerConfig()
    heading = rng.uniform(-math.pi, math.pi, count)
    position = rng.uniform(0.2, 0.5, (2, count))
    reference = position + rng.uniform(-0.01, 0.01, (2, count))
    velocity = rng.uniform(-0.2, 0.2, (2, count))
    velocity[:, :300] *= 0.01  # the plan at rest
    reference[:, :5] = position[:, :5]  # on it
    acceleration = rng.uniform(-1.0, 1.0, (2, count))
    rest = position + rng.uniform(-0.01, 0.01, (2, count))  # ahead of some, behind others
    resting = rng.uniform(size=count) < 0.5
    passed = rng.uniform(size=count) < 0.5
    moving_off = np.where(passed, rng.uniform(0.0, 0.3, count), 0.0)
    kept = np.where(passed, rng.uniform(0.0, 1.0, count) * moving_off, 0.0)
    tracking = plan_tracking(
        ARRAY,
        config,
        heading,
        tuple(position),
        tuple(reference),
        tuple(velocity),
        tuple(acceleration),
        (rest[0], rest[1], resting),
        (moving_off, kept),
    )
    for index in range(count):
        one = plan_tracking(
            SCALAR,
            config,
            float(heading[index]),
            tuple(position[:, index].tolist()),
            tuple(reference[:, index].tolist()),
            tuple(velocity[:, index].tolist()),
            tuple(acceleration[:, index].tolist()),
            (float(rest[0, index]), float(rest[1, index]), bool(resting[index])),
            (float(moving_off[index]), float(kept[index])),
        )
        assert_same(_at(tuple(tracking), index), tuple(one), index)
    backward = backward_tracking(ARRAY, config, tracking)
    for index in range(count):
        one = backward_tracking(SCALAR, config, Tracking(*_at(tracking, index)))
        assert_same(_at(tuple(backward), index), tuple(one), index)
    # The final approach taking over (turned where the two ways point apart); some nothing.
    approach = rng.uniform(-0.2, 0.2, (2, count))
    approach[:, :20] = 0.0
    approach[:, 20:40] = -velocity[:, 20:40] * rng.uniform(0.5, 2.0, 20)  # opposite
    share = rng.uniform(0.0, 1.0, count)
    last = rng.uniform(-0.2, 0.2, (2, count))
    taken_over = turned_towards(ARRAY, tuple(velocity), tuple(approach), share, tuple(last))
    for index in range(count):
        one = turned_towards(
            SCALAR,
            tuple(velocity[:, index].tolist()),
            tuple(approach[:, index].tolist()),
            float(share[index]),
            tuple(last[:, index].tolist()),
        )
        assert_same(_at(taken_over, index), one, index)

    robot = RobotConfig()
    joint = rng.uniform(robot.joint_min[0], robot.joint_max[0], count)
    joint[:50] = robot.joint_max[0] - 1e-4  # runs into the limit
    speed = rng.uniform(-1.0, 1.0, count) * robot.speed_limits[0]
    command = rng.uniform(-2.0, 2.0, count) * robot.speed_limits[0]
    command[:50] = speed[:50] = robot.speed_limits[0]
    limits = (
        robot.speed_limits[0],
        robot.accel_limits[0] * 0.0005,
        robot.joint_min[0],
        robot.joint_max[0],
    )
    together = integrate(ARRAY, joint, speed, command, limits, 0.3, 0.0005, 4)
    assert together[2][:50].all()
    for index in range(count):
        one = integrate(
            SCALAR,
            float(joint[index]),
            float(speed[index]),
            float(command[index]),
            limits,
            0.3,
            0.0005,
            4,
        )
        assert tuple(column[index] for column in together) == one, index
