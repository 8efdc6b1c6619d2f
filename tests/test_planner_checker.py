"""The checker itself, on streams made by hand: it must see what a drive would see."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gcode_canon.commands import ArcFeed, MotionControlMode, Plane, Pose, SetMotionControlMode, StraightFeed
from planner import DEMO_MACHINE, Setpoint, check_stream

T = DEMO_MACHINE.cycle_s


def stream(points) -> list[Setpoint]:
    return [Setpoint((k + 1) * T, tuple(map(float, p))) for k, p in enumerate(points)]


def test_peaks_of_a_known_polynomial_motion() -> None:
    # x(t) = j t^3 / 6 for 0.1 s, then held: jerk j, acceleration j t, velocity j t^2 / 2
    j = 10000.0
    t = np.arange(1, 51) * T
    x = j * t**3 / 6
    pts = [(xi, 0.0, 0.0) for xi in x]
    prog = [StraightFeed(Pose(x[-1], 0, 0))]
    report = check_stream(stream(pts), prog)
    assert report.peaks["x"].velocity == pytest.approx(j * 0.1**2 / 2, rel=0.03)
    # stopping dead at the end is a huge acceleration step: the checker must see it
    assert report.peaks["x"].acceleration > 1000
    assert report.peaks["x"].jerk > DEMO_MACHINE.axis("x").max_jerk
    assert not report.within_limits and not report.ok
    assert any("x: jerk" in p for p in report.problems())


def test_a_jump_breaks_every_limit() -> None:
    pts = [(0, 0, 0)] * 5 + [(1, 0, 0)] * 5
    report = check_stream(stream(pts), [StraightFeed(Pose(1, 0, 0))])
    assert report.peaks["x"].velocity == pytest.approx(1 / T)
    assert report.ratio("x").jerk > 1000


def test_deviation_from_a_line_and_from_an_arc() -> None:
    # straight along X, but bulging 0.01 mm in Y halfway
    xs = np.linspace(0, 10, 200)
    pts = [(x, 0.01 * math.sin(math.pi * x / 10), 0) for x in xs]
    report = check_stream(stream(pts), [SetMotionControlMode(MotionControlMode.EXACT_PATH),
                                        StraightFeed(Pose(10, 0, 0))])
    assert report.max_deviation == pytest.approx(0.01, rel=1e-3)
    assert report.deviation_excess == pytest.approx(0.009, rel=1e-2)
    assert not report.ok
    # on a quarter circle of radius 5 but 0.002 outside it
    th = np.linspace(0, math.pi / 2, 100)
    pts = [(5.002 * math.cos(a), 5.002 * math.sin(a), 0) for a in th]
    prog = [SetMotionControlMode(MotionControlMode.EXACT_PATH), StraightFeed(Pose(5, 0, 0)),
            ArcFeed(Pose(0, 5, 0), Pose(0, 0, 0), Plane.XY, 1)]
    report = check_stream(stream([(5, 0, 0), *pts[1:-1], (0, 5, 0)]), prog)
    assert report.max_deviation == pytest.approx(0.002, rel=1e-2)
    # within a G64 P0.05 blend the same bulge is allowed
    prog[0] = SetMotionControlMode(MotionControlMode.CONTINUOUS, 0.05)
    report = check_stream(stream([(5, 0, 0), *pts[1:-1], (0, 5, 0)]), prog)
    assert report.deviation_excess < 0


def test_missed_exact_stop_and_final_position() -> None:
    prog = [SetMotionControlMode(MotionControlMode.EXACT_STOP_MODAL, file="s.ngc"),
            StraightFeed(Pose(1, 0, 0), file="s.ngc", line=2),
            StraightFeed(Pose(1, 1, 0), file="s.ngc", line=3)]
    # cuts the corner at (1, 0) and stops short of (1, 1)
    pts = [(0, 0, 0), (0.5, 0, 0), (0.99, 0.01, 0), (1, 0.5, 0), (1, 0.999, 0)]
    report = check_stream(stream(pts), prog)
    assert [m[:2] for m in report.stops_missed] == [("s.ngc", 2), ("s.ngc", 3)]
    assert report.final_error == pytest.approx(0.001)
    assert any("exact stop" in p for p in report.problems())


def test_a_corner_may_be_blended_by_the_mode_of_the_move_ending_there() -> None:
    prog = [SetMotionControlMode(MotionControlMode.CONTINUOUS, 0.05), StraightFeed(Pose(10, 0, 0)),
            SetMotionControlMode(MotionControlMode.EXACT_PATH), StraightFeed(Pose(10, 10, 0))]
    along = [(x, 0, 0) for x in np.linspace(0, 9.9, 50)]
    # 0.01 off the G61 line near its start (inside the blend of the G64 corner): allowed
    early = [(10.01, 1.0, 0), *[(10, y, 0) for y in np.linspace(2, 10, 20)]]
    assert check_stream(stream(along + early), prog).deviation_excess <= 0
    # the same 0.01 late on the G61 line: not allowed
    late = [*[(10, y, 0) for y in np.linspace(0.5, 8, 20)], (10.01, 9.0, 0), (10, 10, 0)]
    assert check_stream(stream(along + late), prog).deviation_excess == pytest.approx(0.009, rel=1e-3)
