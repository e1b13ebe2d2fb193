"""The plant's joint model: first-order lag, speed and acceleration limits, hard stops."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plant_sim.model import PlantModel
from protocol.config import PlantConfig, RobotConfig
from protocol.errors import ConfigError

ROBOT = RobotConfig()
PLANT = PlantConfig()
TAU = PLANT.time_constant
MID = tuple((low + high) / 2.0 for low, high in zip(ROBOT.joint_min, ROBOT.joint_max, strict=True))


def _model(position: tuple[float, float, float] = MID, config: PlantConfig = PLANT) -> PlantModel:
    return PlantModel(ROBOT, config, position=position)


def test_defaults_are_sane() -> None:
    assert PLANT.time_constant > 0.0
    assert PLANT.substeps >= 1
    model = _model()
    assert model.velocity == (0.0, 0.0, 0.0)
    assert model.at_limit == (False, False, False)


# A step small enough that the lag, not the acceleration limit, sets the response: its
# largest rate, step / tau, stays under each joint's acceleration limit.
STEP = (0.15, -0.2, 0.04)


def test_step_is_below_the_acceleration_limits() -> None:
    for step, accel in zip(STEP, ROBOT.accel_limits, strict=True):
        assert abs(step) / TAU < accel


@pytest.mark.parametrize("dt", [0.002, 0.004, 0.01])
def test_step_command_follows_a_first_order_lag(dt: float) -> None:
    model = _model()
    steps = round(5.0 * TAU / dt)
    assert steps * dt == pytest.approx(5.0 * TAU)
    fractions = []
    for k in range(1, steps + 1):
        model.advance(STEP, dt)
        t = k * dt
        fraction = [v / c for v, c in zip(model.velocity, STEP, strict=True)]
        fractions.append(fraction)
        # 1 - exp(-t / tau), to 0.1 % of the step: a lag with this time constant.
        for value in fraction:
            assert value == pytest.approx(1.0 - math.exp(-t / TAU), abs=1e-3), (t, fraction)
            assert value <= 1.0  # approaches from below, no overshoot
    # After 5 time constants within 1 % of the command ...
    for velocity, command in zip(model.velocity, STEP, strict=True):
        assert abs(velocity - command) <= 0.01 * abs(command)
    # ... but not already after 4 (e^-4 = 1.8 %): it is a lag, not a jump.
    four = round(4.0 * TAU / dt)
    if four * dt == pytest.approx(4.0 * TAU):
        assert all(value < 0.99 for value in fractions[four - 1])
    # The position integrates the velocity: x0 + c (t - tau (1 - e^(-t/tau))); the
    # trapezoid rule per substep h errs by at most t h^2 max|v''| / 12 = t h^2 c / (12 tau^2).
    t = steps * dt
    h = dt / PLANT.substeps
    for position, start, command in zip(model.position, MID, STEP, strict=True):
        expected = start + command * (t - TAU * (1.0 - math.exp(-t / TAU)))
        bound = t * h * h * abs(command) / (12.0 * TAU * TAU)
        assert position == pytest.approx(expected, abs=2.0 * bound + 1e-12)


def test_zero_command_from_rest_stays_still() -> None:
    for start in (MID, ROBOT.joint_min, ROBOT.joint_max, (0.3, -1.2, 0.05)):
        model = _model(start)
        for _ in range(50):
            model.advance((0.0, 0.0, 0.0), 0.004)
        assert model.position == start
        assert model.velocity == (0.0, 0.0, 0.0)
        assert model.at_limit == (False, False, False)


def test_one_step_is_substeps_identical_substeps() -> None:
    """advance(dt) is ``substeps`` steps of dt / substeps (so the per-substep test holds)."""
    coarse = _model()
    fine = _model(config=PlantConfig(time_constant=TAU, substeps=1))
    command = (100.0, -100.0, 3.0)
    for _ in range(20):
        coarse.advance(command, 0.004)
        for _ in range(PLANT.substeps):
            fine.advance(command, 0.004 / PLANT.substeps)
        assert coarse.position == pytest.approx(fine.position, abs=1e-12)
        assert coarse.velocity == pytest.approx(fine.velocity, abs=1e-12)


@pytest.mark.parametrize("joint", range(3))
@pytest.mark.parametrize("direction", [1.0, -1.0])
def test_large_command_is_limited_per_substep(joint: int, direction: float) -> None:
    """A far too large command: every substep's change stays within accel * h, the first
    ones use all of it, and the velocity settles at the speed limit, not the command."""
    h = 0.004 / PLANT.substeps
    accel, speed = ROBOT.accel_limits[joint], ROBOT.speed_limits[joint]
    start = list(MID)
    start[joint] = ROBOT.joint_min[joint] if direction > 0.0 else ROBOT.joint_max[joint]
    model = _model((start[0], start[1], start[2]), PlantConfig(time_constant=TAU, substeps=1))
    command = [0.0, 0.0, 0.0]
    command[joint] = direction * 20.0 * speed
    # The ramp to the speed limit takes speed / accel; then the lag needs a few tau more.
    steps = math.ceil((speed / accel + 10.0 * TAU) / h)
    previous = model.velocity[joint]
    for k in range(steps):
        model.advance((command[0], command[1], command[2]), h)
        change = model.velocity[joint] - previous
        assert abs(change) <= accel * h * (1.0 + 1e-12)
        assert abs(model.velocity[joint]) <= speed * (1.0 + 1e-12)
        if k < 5:
            assert change == pytest.approx(direction * accel * h, rel=1e-12)
        previous = model.velocity[joint]
    assert model.at_limit == (False, False, False)
    assert model.velocity[joint] == pytest.approx(direction * speed, rel=1e-4)


@settings(max_examples=40, deadline=None)
@given(
    commands=st.lists(
        st.tuples(*(st.floats(min_value=-3.0 * s, max_value=3.0 * s) for s in ROBOT.speed_limits)),
        min_size=1,
        max_size=60,
    ),
    dt=st.sampled_from([0.001, 0.002, 0.004, 0.01]),
    start=st.tuples(
        *(
            st.floats(min_value=low, max_value=high)
            for low, high in zip(ROBOT.joint_min, ROBOT.joint_max, strict=True)
        )
    ),
)
def test_random_commands_respect_every_limit(
    commands: list[tuple[float, float, float]], dt: float, start: tuple[float, float, float]
) -> None:
    model = _model(start)
    for command in commands:
        before = model.velocity
        model.advance(command, dt)
        for joint in range(3):
            assert abs(model.velocity[joint]) <= ROBOT.speed_limits[joint] * (1.0 + 1e-12)
            # At most accel * dt over the step, unless a hard stop zeroed the velocity.
            if not model.at_limit[joint]:
                change = abs(model.velocity[joint] - before[joint])
                assert change <= ROBOT.accel_limits[joint] * dt * (1.0 + 1e-9)
            assert ROBOT.joint_min[joint] <= model.position[joint] <= ROBOT.joint_max[joint]


@pytest.mark.parametrize("joint", range(3))
@pytest.mark.parametrize("direction", [1.0, -1.0])
def test_joint_driven_into_its_limit_stops_there(joint: int, direction: float) -> None:
    limit = ROBOT.joint_max[joint] if direction > 0.0 else ROBOT.joint_min[joint]
    gap = 0.02 if joint < 2 else 0.005
    start = list(MID)
    start[joint] = limit - direction * gap
    model = _model((start[0], start[1], start[2]))
    command = [0.0, 0.0, 0.0]
    command[joint] = direction * 0.5 * ROBOT.speed_limits[joint]
    model.advance((command[0], command[1], command[2]), 0.001)
    assert model.at_limit == (False, False, False)  # still short of it after 1 ms
    for _ in range(200):
        model.advance((command[0], command[1], command[2]), 0.004)
        if model.at_limit[joint]:
            break
    assert model.at_limit[joint]
    # It stays stopped at the limit while the command keeps pushing.
    for _ in range(20):
        assert model.position[joint] == limit
        assert model.velocity[joint] == 0.0
        model.advance((command[0], command[1], command[2]), 0.004)
    assert model.position[joint] == limit
    for other in range(3):
        if other != joint:
            assert not model.at_limit[other]
            assert model.position[other] == MID[other]
            assert model.velocity[other] == 0.0
    # And it can be driven back off it.
    for _ in range(10):
        model.advance((-command[0], -command[1], -command[2]), 0.004)
    assert direction * (limit - model.position[joint]) > 0.0


@pytest.mark.parametrize(
    ("values", "field"),
    [
        ({"time_constant": 0.0}, "plant.time_constant"),
        ({"time_constant": -0.01}, "plant.time_constant"),
        ({"time_constant": math.nan}, "plant.time_constant"),
        ({"time_constant": math.inf}, "plant.time_constant"),
        ({"substeps": 0}, "plant.substeps"),
        ({"substeps": -2}, "plant.substeps"),
        ({"substeps": 101}, "plant.substeps"),
        ({"substeps": 2.5}, "plant.substeps"),
        ({"substeps": 4.0}, "plant.substeps"),
    ],
)
def test_plant_config_rejects_bad_values(values: dict[str, float], field: str) -> None:
    with pytest.raises(ConfigError) as raised:
        PlantConfig(**values)  # type: ignore[arg-type]
    assert raised.value.field == field


def test_plant_config_accepts_the_range_ends() -> None:
    assert PlantConfig(time_constant=1e-6, substeps=1).substeps == 1
    assert PlantConfig(time_constant=10.0, substeps=100).time_constant == 10.0
