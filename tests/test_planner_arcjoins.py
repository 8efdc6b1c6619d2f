"""Joins with arcs: eased within G64 P by a curvature-continuous transition, limits kept.

The expected join speed is computed from the machine limits with the formula derived in
docs/planner.md ("Transitions"), not read off the planner.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from gcode_canon.commands import (
    ArcFeed,
    MotionControlMode,
    Plane,
    Pose,
    ProgramEnd,
    SetFeedRate,
    SetMotionControlMode,
    StraightFeed,
)
from planner import DEMO_MACHINE, check_stream, plan_all
from planner.segments import (
    CENTRIPETAL_ACC,
    JERK_CENTRIPETAL,
    JERK_CONTINUOUS,
    TRANSITION_ARC,
    TRANSITION_DEVIATION,
)

T = DEMO_MACHINE.cycle_s
X = DEMO_MACHINE.axis("x")
MARGIN = 0.10  # the planner's d search stops within 10 % of the best d, and its deviation bound is loose


def numbered(cmds: list) -> list:
    return [dataclasses.replace(c, line=i + 1, file="j.ngc") for i, c in enumerate(cmds)]


def g64(p: float) -> SetMotionControlMode:
    return SetMotionControlMode(MotionControlMode.CONTINUOUS, p)


def line_arc_line(mode: SetMotionControlMode, feed: float, r: float) -> list:
    """A 50 mm line along X, a tangent quarter circle of radius r to the left, a 50 mm line along Y."""
    return numbered([mode, SetFeedRate(feed), StraightFeed(Pose(50, 0, 0)),
                     ArcFeed(Pose(50 + r, r, 0), Pose(50, r, 0), Plane.XY, 1),
                     StraightFeed(Pose(50 + r, 50 + r, 0)), ProgramEnd()])


def speed_at(sps: list, point: tuple[float, ...]) -> float:
    """Path speed at the setpoint nearest to ``point`` (mean of the steps before and after it)."""
    pts = np.array([s.positions for s in sps])
    k = int(np.argmin(np.linalg.norm(pts - np.array(point), axis=1)))
    return float(0.5 * (np.linalg.norm(pts[k] - pts[k - 1]) + np.linalg.norm(pts[k + 1] - pts[k])) / T)


def expected_join_speed(feed: float, r: float, p: float, half_line: float) -> float:
    """docs/planner.md: a tangent line-arc transition reaching d on both sides deviates 0.0107 d^2 / R,
    curves up to 1.1 / R and has |q'''| <= 1.125 / (R d) across the join; the speed there is capped by
    the feed, the centripetal budget and the jerk budget."""
    d = min(math.sqrt(TRANSITION_DEVIATION * p * r / 0.0107), TRANSITION_ARC * r, half_line)
    v_feed = feed / 60.0
    v_acc = math.sqrt(CENTRIPETAL_ACC * X.max_acceleration * r / 1.1)
    v_jerk = (JERK_CONTINUOUS * JERK_CENTRIPETAL * X.max_jerk * r * d / 1.125) ** (1.0 / 3.0)
    return min(v_feed, v_acc, v_jerk)


@pytest.mark.parametrize("p", [0.01, 0.05])
def test_tangent_line_arc_join_at_f8000_runs_near_the_derived_limit(p: float) -> None:
    r = 10.0
    prog = line_arc_line(g64(p), 8000, r)
    sps = list(plan_all(prog))
    report = check_stream(sps, prog)
    assert report.ok, report.problems()
    assert report.max_deviation <= p
    v_min = (1.0 - MARGIN) * expected_join_speed(8000, r, p, 25.0)
    assert v_min > 40.0  # far above the ~8 mm/s the unblended join allowed
    assert speed_at(sps, (50, 0, 0)) >= v_min  # line -> arc
    assert speed_at(sps, (50 + r, r, 0)) >= v_min  # arc -> line


def test_exact_path_is_not_eased_and_keeps_the_jerk_step_limit() -> None:
    """G61 allows no deviation: the curvature step is passed at the speed one cycle's jerk allows."""
    r = 10.0
    prog = line_arc_line(SetMotionControlMode(MotionControlMode.EXACT_PATH), 8000, r)
    sps = list(plan_all(prog))
    report = check_stream(sps, prog)
    assert report.ok, report.problems()
    assert report.max_deviation < 1e-6
    # an acceleration step v^2/R in one cycle reads as a jerk of up to 0.75 v^2/(R T); 5 % of J for it
    v_step = math.sqrt(0.05 / 0.75 * X.max_jerk * T * r)
    assert speed_at(sps, (50, 0, 0)) <= 1.02 * v_step


def test_corner_into_an_arc_is_blended_within_p_instead_of_stopping() -> None:
    # a line along X into an arc whose start tangent is at 45 degrees: a corner
    r = 8.0
    c = (40 - r / math.sqrt(2), r / math.sqrt(2))
    a0 = math.atan2(0 - c[1], 40 - c[0])
    end = (c[0] + r * math.cos(a0 + 1.2), c[1] + r * math.sin(a0 + 1.2))
    prog = numbered([g64(0.02), SetFeedRate(3000), StraightFeed(Pose(40, 0, 0)),
                     ArcFeed(Pose(end[0], end[1], 0), Pose(c[0], c[1], 0), Plane.XY, 1),
                     StraightFeed(Pose(end[0], end[1] + 30, 0)), ProgramEnd()])
    sps = list(plan_all(prog))
    report = check_stream(sps, prog)
    assert report.ok, report.problems()
    assert report.max_deviation <= 0.02
    assert speed_at(sps, (40, 0, 0)) > 5.0  # no stop at the corner
    pts = np.array([s.positions for s in sps])
    assert np.min(np.linalg.norm(pts - [40, 0, 0], axis=1)) > 1e-4  # the corner point is cut


def test_s_curve_of_two_tangent_arcs() -> None:
    """Curvature flips from +1/R to -1/R: twice the step of a line-arc join."""
    r = 6.0
    prog = numbered([g64(0.01), SetFeedRate(6000), StraightFeed(Pose(20, 0, 0)),
                     ArcFeed(Pose(20 + r, r, 0), Pose(20, r, 0), Plane.XY, 1),
                     ArcFeed(Pose(20 + 2 * r, 2 * r, 0), Pose(20 + 2 * r, r, 0), Plane.XY, -1),
                     StraightFeed(Pose(60, 2 * r, 0)), ProgramEnd()])
    sps = list(plan_all(prog))
    report = check_stream(sps, prog)
    assert report.ok, report.problems()
    assert report.max_deviation <= 0.01
    old_cap = math.sqrt(0.05 / 0.75 * X.max_jerk * T / (2.0 / r))  # the unblended curvature-step cap
    assert speed_at(sps, (20 + r, r, 0)) > 3.0 * old_cap


@pytest.mark.parametrize("p", [0.001, 0.01, 0.1, 0.0])
def test_arc_and_line_mixes_in_every_plane_stay_inside_the_limits(p: float) -> None:
    """Helices, arcs in G17/G18/G19, tangent and kinked joins, short and long pieces."""
    prog = [g64(p), SetFeedRate(4000), StraightFeed(Pose(10, 0, 0)),
            ArcFeed(Pose(20, 10, 0), Pose(10, 10, 0), Plane.XY, 1),  # tangent
            ArcFeed(Pose(30, 20, -2), Pose(30, 10, 0), Plane.XY, -1),  # tangent S with a helix pitch
            StraightFeed(Pose(40, 20, -2)),  # tangent
            ArcFeed(Pose(45, 20, -7), Pose(45, 20, -2), Plane.XZ, 1),  # G18, a corner
            StraightFeed(Pose(45, 20, -9)),
            ArcFeed(Pose(45, 26, -9), Pose(45, 23, -9), Plane.YZ, -1),  # G19 half circle
            ArcFeed(Pose(45, 26.5, -9), Pose(45, 26.25, -9), Plane.XY, 1),  # tiny one
            StraightFeed(Pose(0, 0, 0)), ProgramEnd()]
    prog = numbered(prog)
    sps = list(plan_all(prog, max_cycles=500_000))
    report = check_stream(sps, prog)
    assert report.ok, report.problems()
    if p > 0:
        assert report.max_deviation <= p + 1e-9
