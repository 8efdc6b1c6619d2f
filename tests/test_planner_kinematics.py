"""The closed forms the lookahead relies on, against ruckig itself; the geometry pieces' contracts."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from ruckig import InputParameter, Result, Ruckig, Trajectory

from planner.geometry import SIGMA_INT_HALF, Arc, Blend, Line, deviation_of_blend
from planner.kinematics import change_distance, change_time, max_reach, min_reach

speeds = st.floats(0.0, 300.0)
accels = st.floats(50.0, 5000.0)
jerks = st.floats(500.0, 200000.0)


def ruckig_velocity_change(v0: float, v1: float, a: float, j: float) -> tuple[float, float]:
    """Duration and distance of ruckig's time-optimal velocity change with zero end acceleration."""
    from ruckig import ControlInterface

    inp = InputParameter(1)
    inp.control_interface = ControlInterface.Velocity
    inp.current_position, inp.current_velocity, inp.current_acceleration = [0.0], [v0], [0.0]
    inp.target_velocity, inp.target_acceleration = [v1], [0.0]
    inp.max_velocity, inp.max_acceleration, inp.max_jerk = [max(v0, v1, 1e-9)], [a], [j]
    traj = Trajectory(1)
    assert Ruckig(1).calculate(inp, traj) in (Result.Working, Result.Finished)
    return traj.duration, traj.at_time(traj.duration)[0][0]


@settings(max_examples=200, deadline=None)
@given(speeds, speeds, accels, jerks)
def test_change_distance_matches_ruckig(v0: float, v1: float, a: float, j: float) -> None:
    duration, distance = ruckig_velocity_change(v0, v1, a, j)
    assert change_time(abs(v1 - v0), a, j) == pytest.approx(duration, rel=1e-6, abs=1e-9)
    assert change_distance(v0, v1, a, j) == pytest.approx(distance, rel=1e-6, abs=1e-9)


@settings(max_examples=200, deadline=None)
@given(speeds, st.floats(1e-6, 100.0), accels, jerks)
def test_max_and_min_reach_are_inverse_and_tight(w: float, length: float, a: float, j: float) -> None:
    v = max_reach(w, length, a, j)
    assert v >= w
    # tight, up to the rounding of v - w when the change is far below the speeds themselves
    slack = 1e-6 * length + 4.0 * v * math.sqrt(2.3e-16 * max(v, 1.0) / j) + 1e-12
    assert length - 1e-3 * length - slack <= change_distance(v, w, a, j) <= length + slack
    # braking from v within the same length reaches w or lower (to zero can take less distance
    # than to a small speed: the distance is not monotonic in the end speed), and that fits
    low = min_reach(v, length * (1 + 1e-9), a, j)
    assert low <= w * (1 + 1e-5) + 1e-5
    assert change_distance(v, low, a, j) <= length * (1 + 1e-6) + slack
    assert min_reach(w, change_distance(w, 0.0, a, j) + 1e-9, a, j) == 0.0


def test_ruckig_reaches_exactly_what_max_reach_promises() -> None:
    # position interface, as the planner uses it: from rest over 0.2 mm to the promised speed
    a, j, length = 2000.0, 45000.0, 0.2
    v1 = max_reach(0.0, length * (1 - 1e-6), a, j)
    inp = InputParameter(1)
    inp.current_position, inp.current_velocity, inp.current_acceleration = [0.0], [0.0], [0.0]
    inp.target_position, inp.target_velocity, inp.target_acceleration = [length], [v1], [0.0]
    inp.max_velocity, inp.max_acceleration, inp.max_jerk = [v1], [a], [j]
    traj = Trajectory(1)
    assert Ruckig(1).calculate(inp, traj) == Result.Working
    assert traj.position_extrema[0].max <= length + 1e-9


def test_line_piece() -> None:
    line = Line((0.0, 0.0, 0.0), (3.0, 4.0, 0.0), 5.0)
    assert line.pos(2.5) == [1.5, 2.0, 0.0]
    assert line.pos(5.0 + 1e-12) == [3.0, 4.0, 0.0]  # the end exactly, whatever rounding did
    assert line.d1_max == (0.6, 0.8, 0.0) and line.d2_max == (0.0, 0.0, 0.0)


def test_arc_piece_ends_and_curvature() -> None:
    r = 5.0
    arc = Arc((5.0, 0.0, 0.0), (0.0, 5.0, -2.0), 0, 1, 0.0, 0.0, math.pi / 2,
              math.hypot(r * math.pi / 2, 2.0))
    assert arc.pos(arc.length) == [0.0, 5.0, -2.0]
    mid = arc.pos(arc.length / 2)
    assert math.hypot(mid[0], mid[1]) == pytest.approx(5.0)
    assert mid[2] == pytest.approx(-1.0)
    k = (math.pi / 2) / arc.length
    assert arc.d2_max[0] == pytest.approx(r * k * k)  # centripetal: r (dtheta/ds)^2
    assert arc.d1_start[1] == pytest.approx(r * k)  # leaves (5, 0) along +Y


def test_blend_is_tangent_with_zero_curvature_at_both_ends_and_inside_its_bound() -> None:
    w1, w2 = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)
    corner = (10.0, 0.0, 0.0)
    b = Blend(corner, w1, w2, 0.5)
    assert b.pos(0.0) == [9.5, 0.0, 0.0] and b.pos(b.length) == [10.0, 0.5, 0.0]
    h = 1e-6
    start_dir = [(p - q) / h for p, q in zip(b.pos(h), b.pos(0.0), strict=True)]
    end_dir = [(p - q) / h for p, q in zip(b.pos(b.length), b.pos(b.length - h), strict=True)]
    assert start_dir == pytest.approx([1, 0, 0], abs=1e-5) and end_dir == pytest.approx([0, 1, 0], abs=1e-5)
    # second differences at the ends vanish (zero curvature), not in the middle
    def second(s: float) -> float:
        p0, p1, p2 = b.pos(s - 1e-3), b.pos(s), b.pos(s + 1e-3)
        return math.hypot(*[(x - 2 * y + z) / 1e-6 for x, y, z in zip(p0, p1, p2, strict=True)])
    assert second(1e-3) < 0.02 * second(b.length / 2)
    def off_path(p: list[float]) -> float:  # distance from the two lines that meet at the corner
        return min(abs(p[1]) if p[0] <= 10.0 else math.dist(p, corner),
                   abs(p[0] - 10.0) if p[1] >= 0.0 else math.dist(p, corner))

    far = max(off_path(b.pos(b.length * i / 200)) for i in range(201))
    bound = deviation_of_blend(w1, w2, 0.5, range(3))
    assert far <= bound
    assert math.dist(b.pos(b.length / 2), corner) == pytest.approx(bound)
    assert bound == pytest.approx(2 * 0.5 * SIGMA_INT_HALF * math.sqrt(2))
