"""Hypothesis strategies for obstacles, shared by the geometry and the DM tests."""

from __future__ import annotations

import math

from hypothesis import strategies as st

from protocol.geometry import EllipticCylinder

unit_interval = st.floats(min_value=-1.5, max_value=1.5)


@st.composite
def obstacles(draw: st.DrawFn) -> EllipticCylinder:
    long_diameter = draw(st.floats(min_value=0.01, max_value=0.6))
    ratio = draw(st.one_of(st.just(1.0), st.floats(min_value=0.05, max_value=1.0)))
    return EllipticCylinder(
        x=draw(st.floats(min_value=-1.0, max_value=1.0)),
        y=draw(st.floats(min_value=-1.0, max_value=1.0)),
        long_diameter=long_diameter,
        short_diameter=long_diameter * ratio,
        height=draw(st.floats(min_value=0.01, max_value=0.5)),
        yaw=draw(st.one_of(st.just(0.0), st.floats(min_value=-math.pi, max_value=math.pi))),
        inflation=draw(st.one_of(st.just(0.0), st.floats(min_value=0.0, max_value=0.05))),
    )


def point_at(obstacle: EllipticCylinder, scaled_radius: float, angle: float) -> tuple[float, float]:
    """The world point at local (r a cos angle, r b sin angle): r < 1 inside, r > 1 outside."""
    a, b = obstacle.semi_axes
    return obstacle.to_world(
        scaled_radius * a * math.cos(angle), scaled_radius * b * math.sin(angle)
    )
