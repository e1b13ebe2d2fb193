"""The figure of a comparison run, laid out like the paper's Figs. 8 and 9.

Top view (reachable annulus, waypoints, obstacle, both paths), a 3D view, joint positions
and velocities, and the coordination weights k_T and k_C over time.
"""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.patches import Ellipse, Wedge

from protocol.kinematics import reach_radii
from sim.simulation import SimulationRun

MODE_COLOURS = {"fuzzy": "tab:blue", "conventional": "tab:red"}


def comparison_figure(runs: dict[str, SimulationRun], path: Path) -> Path:
    """Write the figure of ``runs`` (mode name -> run of one scenario) to ``path``."""
    first = next(iter(runs.values())).scenario
    figure = plt.figure(figsize=(16, 10), constrained_layout=True)
    grid = figure.add_gridspec(3, 4)
    top = figure.add_subplot(grid[0:2, 0:2])
    view3d = figure.add_subplot(grid[0:2, 2:4], projection="3d")
    joint_axes = [figure.add_subplot(grid[2, i]) for i in range(3)]
    weights = figure.add_subplot(grid[2, 3])

    r_min, r_max = reach_radii(first.robot)
    top.add_patch(
        Wedge(
            (0, 0),
            r_max,
            math.degrees(first.robot.theta1_min) - 30,
            math.degrees(first.robot.theta1_max) + 30,
            width=r_max - r_min,
            color="0.93",
            label="reachable annulus",
        )
    )
    obstacle = first.obstacle
    if obstacle is not None:
        for inflation, style in (
            (0.0, {"color": "0.45"}),
            (obstacle.inflation, {"fill": False, "ls": "--", "color": "0.3"}),
        ):
            top.add_patch(
                Ellipse(
                    (obstacle.x, obstacle.y),
                    obstacle.long_diameter + 2 * inflation,
                    obstacle.short_diameter + 2 * inflation,
                    angle=math.degrees(obstacle.yaw),
                    **style,
                )
            )
        _cylinder(
            view3d,
            obstacle.x,
            obstacle.y,
            obstacle.long_diameter / 2,
            obstacle.short_diameter / 2,
            obstacle.yaw,
            obstacle.height,
        )
    waypoints = np.array([(w.x, w.y, w.z) for w in first.waypoints])
    reference = next(iter(runs.values())).log.columns("reference_x", "reference_y", "reference_z")
    top.plot(reference[:, 0], reference[:, 1], ":", color="0.4", label="planned (PT)")
    for mode, run in runs.items():
        colour = MODE_COLOURS.get(mode)
        path_xyz = run.log.columns("x", "y", "z")
        top.plot(path_xyz[:, 0], path_xyz[:, 1], color=colour, label=f"{mode} path")
        view3d.plot(path_xyz[:, 0], path_xyz[:, 1], path_xyz[:, 2], color=colour, label=mode)
        t = run.log["t"]
        for axis, (position, command, unit) in zip(
            joint_axes,
            (
                ("theta1", "command_theta1", "rad"),
                ("theta2", "command_theta2", "rad"),
                ("d3", "command_d3", "m"),
            ),
            strict=True,
        ):
            axis.plot(t, run.log[position], color=colour, label=f"{position} ({mode})")
            axis.plot(
                t,
                run.log[command],
                color=colour,
                alpha=0.45,
                lw=0.8,
                label=f"{position} rate cmd ({mode})",
            )
            axis.set_title(f"{position} [{unit}] and commanded rate [{unit}/s]")
            axis.set_xlabel("t [s]")
        weights.plot(t, run.log["k_t"], color=colour, label=f"k_T ({mode})")
        weights.plot(t, run.log["k_c"], color=colour, ls="--", label=f"k_C ({mode})")
    top.plot(waypoints[:, 0], waypoints[:, 1], "ko", label="waypoints")
    for index, (x, y, _) in enumerate(waypoints):
        top.annotate(f"p{index + 1}", (x, y), textcoords="offset points", xytext=(6, 6))
    view3d.scatter(waypoints[:, 0], waypoints[:, 1], waypoints[:, 2], color="k")
    span = np.vstack([waypoints[:, :2]] + [run.log.columns("x", "y") for run in runs.values()])
    margin = 0.05
    top.set_xlim(span[:, 0].min() - margin, span[:, 0].max() + margin)
    top.set_ylim(span[:, 1].min() - margin, span[:, 1].max() + margin)
    top.set_aspect("equal")
    top.set_xlabel("x [m]")
    top.set_ylabel("y [m]")
    top.set_title(f"top view: {first.name}")
    top.legend(loc="best", fontsize=8)
    view3d.set_xlabel("x [m]")
    view3d.set_ylabel("y [m]")
    view3d.set_zlabel("z [m]")
    view3d.set_title("3D view")
    view3d.legend(fontsize=8)
    for axis in joint_axes:
        axis.legend(fontsize=6)
    weights.set_title("coordination weights")
    weights.set_xlabel("t [s]")
    weights.legend(fontsize=7)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


def _cylinder(
    axis: object, x: float, y: float, a: float, b: float, yaw: float, height: float
) -> None:
    angles = np.linspace(0, 2 * np.pi, 48)
    heights = np.array([0.0, height])
    ring_x = x + a * np.cos(angles) * np.cos(yaw) - b * np.sin(angles) * np.sin(yaw)
    ring_y = y + a * np.cos(angles) * np.sin(yaw) + b * np.sin(angles) * np.cos(yaw)
    axis.plot_surface(  # type: ignore[attr-defined]
        np.tile(ring_x, (2, 1)),
        np.tile(ring_y, (2, 1)),
        heights[:, None] * np.ones_like(angles),
        color="0.5",
        alpha=0.35,
    )
