"""The controller's log of a run: one row per control step, one named column per quantity.

The in-process simulation, the controller node and a replayed log all fill the same
:class:`RunLog`, so the measures of a run are computed the same way whatever produced it.

``t`` is the plan's time of the step and ``clock`` the run's time on the tick grid. They are
equal unless the controller held (no fresh joint state: the plan's clock stops while the
run's goes on), so a held run shows as slower, never hidden. ``progress`` is where on the
plan the reference stood: ``t`` itself, except where the law let the plan wait for an arm
held off it by a detour (``ControlLaw.rate``). ``reference_speed`` is the plan's planar speed
there (the reference moves slower while the plan waits).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from controller.control_law import ControlOutput

COLUMNS = (
    "t",
    "theta1",
    "theta2",
    "d3",
    "theta1_rate",
    "theta2_rate",
    "d3_rate",
    "command_theta1",
    "command_theta2",
    "command_d3",
    "x",
    "y",
    "z",
    "reference_x",
    "reference_y",
    "reference_z",
    "reference_speed",
    "k_t",
    "k_c",
    "v_e",
    "omega_e",
    "v_t",
    "omega_t",
    "v_a",
    "omega_a",
    "clearance",
    "min_distance",
    "beta",
    "blocked",
    "heading",
    "limited",
    "clock",
    "progress",
)
COLUMN = {name: index for index, name in enumerate(COLUMNS)}


def row_of(
    t: float,
    joint_position: Sequence[float],
    joint_velocity: Sequence[float],
    output: ControlOutput,
    clock: float,
) -> tuple[float, ...]:
    """One row of the log, in :data:`COLUMNS` order."""
    measurement = output.measurement
    return (
        t,
        *joint_position,
        *joint_velocity,
        *output.command,
        *output.tcp,
        *output.reference,
        output.reference_speed,
        output.k_t,
        output.k_c,
        output.blended.v,
        output.blended.omega,
        output.tracking.v,
        output.tracking.omega,
        output.avoiding.v,
        output.avoiding.omega,
        measurement.clearance,
        measurement.min_distance,
        measurement.beta,
        float(measurement.blocked),
        output.heading,
        float(output.limited),
        clock,
        output.progress,
    )


class RunLog:
    """A growable table of float64 rows."""

    def __init__(self, capacity: int = 1024) -> None:
        self._data = np.empty((max(capacity, 1), len(COLUMNS)))
        self._size = 0

    def append(self, row: Sequence[float]) -> None:
        if self._size == len(self._data):
            self._data = np.concatenate([self._data, np.empty_like(self._data)])
        self._data[self._size] = row
        self._size += 1

    def __len__(self) -> int:
        return self._size

    @property
    def data(self) -> npt.NDArray[np.float64]:
        return self._data[: self._size]

    def __getitem__(self, name: str) -> npt.NDArray[np.float64]:
        return self._data[: self._size, COLUMN[name]]

    def columns(self, *names: str) -> npt.NDArray[np.float64]:
        return self._data[: self._size, [COLUMN[name] for name in names]]

    @classmethod
    def from_array(cls, data: npt.NDArray[np.float64]) -> RunLog:
        if data.ndim != 2 or data.shape[1] != len(COLUMNS):
            raise ValueError(f"expected an (n, {len(COLUMNS)}) array, got {data.shape}")
        log = cls(len(data))
        log._data[: len(data)] = data
        log._size = len(data)
        return log
