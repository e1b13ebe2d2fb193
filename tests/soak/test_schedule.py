"""The soak's schedule (``soak/schedule.py``): a pure function of the seed."""

from __future__ import annotations

from controller.planner import check_plan
from soak.schedule import (
    CORRUPT,
    DROP,
    FIRST,
    PAUSE,
    QUIET_END,
    Kind,
    home,
    make_schedule,
    task,
    wire_faults,
)


def test_the_same_seed_gives_the_same_schedule_and_another_seed_another() -> None:
    assert make_schedule(7, 10) == make_schedule(7, 10)
    assert make_schedule(7, 10) != make_schedule(8, 10)
    assert wire_faults(7, "plant", 2) == wire_faults(7, "plant", 2)
    assert wire_faults(7, "plant", 2) != wire_faults(7, "controller", 2)


def test_a_ten_minute_schedule_has_every_kind_within_its_bounds() -> None:
    schedule = make_schedule(3, 10)
    times = [d.at for d in schedule.disturbances]
    assert times == sorted(times) and times[0] == FIRST and times[-1] < 600 - QUIET_END
    assert {d.kind for d in schedule.disturbances} == set(Kind)
    for d in schedule.disturbances:
        if d.kind is Kind.PAUSE:
            assert PAUSE[0] <= d.duration <= PAUSE[1]
        if d.kind in (Kind.PAUSE, Kind.KILL):
            assert d.target
    for start in range(20):
        spec = wire_faults(3, "controller", start)
        assert 0 <= spec.drop <= DROP and 0 <= spec.corrupt <= CORRUPT


def test_tasks_are_the_same_for_a_seed_feasible_and_clear_of_the_home() -> None:
    start = home()
    first = start.waypoints[0]
    tasks = [task(5, number, start) for number in range(6)]
    assert [t.name for t in tasks] == [task(5, n, start).name for n in range(6)]
    assert len({t.mode for t in tasks}) == 2  # both modes
    for scenario in tasks:
        check_plan(scenario)  # raises if the controller would refuse it
        assert scenario.obstacle is None or not scenario.obstacle.holds(first.x, first.y, first.z)
