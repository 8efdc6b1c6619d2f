"""Planned streams for the hard cases: every axis inside its limits, the path followed, stops exact.

Each program is built from canonical commands directly and judged by ``check_stream``, which reads
the programmed geometry itself and measures the stream by finite differences, as a drive sees it.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from gcode_canon.commands import (
    ArcFeed,
    ExactStopBlock,
    FeedMode,
    MotionControlMode,
    Plane,
    Pose,
    ProgramEnd,
    SetFeedMode,
    SetFeedRate,
    SetMotionControlMode,
    SetSpindleSpeed,
    SpindleDirection,
    SpindleOn,
    StraightFeed,
    StraightTraverse,
)
from planner import DEMO_MACHINE, AxisLimits, MachineLimits, check_stream, plan_all

G61 = SetMotionControlMode(MotionControlMode.EXACT_PATH)
G61_1 = SetMotionControlMode(MotionControlMode.EXACT_STOP_MODAL)


def g64(p: float = 0.0) -> SetMotionControlMode:
    return SetMotionControlMode(MotionControlMode.CONTINUOUS, p)


def plan(program, machine=DEMO_MACHINE, start=None):
    sps = list(plan_all(program, machine, start=start, max_cycles=2_000_000))
    report = check_stream(sps, program, machine, start=start)
    return sps, report


def assert_good(report, deviation: float = 1e-3) -> None:
    assert report.within_limits, report.problems()
    assert report.max_deviation < deviation, report.problems()
    assert report.deviation_excess <= 0.0, report.problems()
    assert not report.stops_missed, report.problems()
    assert report.final_error <= 1e-9


def path_speed(sps, T: float) -> np.ndarray:
    pts = np.array([s.positions for s in sps])
    return np.linalg.norm(np.diff(pts, axis=0), axis=1) / T


def numbered(cmds):
    return [dataclass_with_line(c, i + 1) for i, c in enumerate(cmds)]


def dataclass_with_line(cmd, line):
    import dataclasses

    return dataclasses.replace(cmd, line=line, file="test.ngc")


def small_arc_chain(p: float, kink_deg: float) -> list:
    """Arcs of 0.5-2 mm radius, joined with a tangent kink of ``kink_deg`` (as CAM output rounds)."""
    prog = [g64(p), SetFeedRate(3000), StraightFeed(Pose(0, 0, 0))]
    x, y, heading = 0.0, 0.0, 0.0
    for i in range(40):
        r = 0.5 + 1.5 * ((i * 7) % 5) / 4
        turn = (1 if i % 2 else -1) * math.radians(40 + 10 * (i % 3))
        heading += math.radians(kink_deg) * (1 if i % 3 else -1)
        # centre to the left (CCW) or right (CW) of the heading
        side = 1 if turn > 0 else -1
        cx = x - side * r * math.sin(heading)
        cy = y + side * r * math.cos(heading)
        a0 = math.atan2(y - cy, x - cx)
        x, y = cx + r * math.cos(a0 + turn), cy + r * math.sin(a0 + turn)
        heading += turn
        prog.append(ArcFeed(Pose(x, y, 0), Pose(cx, cy, 0), Plane.XY, side))
    prog.append(ProgramEnd())
    return numbered(prog)


@pytest.mark.parametrize("p", [0.01, 0.1])
@pytest.mark.parametrize("kink", [0.0, 0.5])
def test_small_arcs_blended_stay_inside_limits(p: float, kink: float) -> None:
    _sps, report = plan(small_arc_chain(p, kink))
    assert_good(report, deviation=p)


def test_short_lines_blended_within_tolerance_and_faster_than_exact_stop() -> None:
    def program(mode):
        prog = [mode, SetFeedRate(3000)]
        for i in range(1, 150):
            th = i * 0.03
            prog.append(StraightFeed(Pose(20 * math.cos(th) - 20, 20 * math.sin(th), 0)))
        return numbered([*prog, ProgramEnd()])

    blended, r_blend = plan(program(g64(0.01)))
    assert_good(r_blend, deviation=0.01)
    assert r_blend.max_deviation > 1e-4  # it really blends
    stopped, r_stop = plan(program(G61_1))
    assert_good(r_stop)
    assert r_stop.stops_total >= 149
    assert len(blended) * 3 < len(stopped)


def test_dense_surface_toolpath() -> None:
    prog = [g64(0.005), SetFeedRate(2400), StraightTraverse(Pose(0, 0, 3))]
    for row in range(6):
        xs = [i * 0.25 for i in range(160)]
        for x in xs if row % 2 == 0 else xs[::-1]:
            prog.append(StraightFeed(Pose(x, row * 0.4, 1.5 * math.sin(x / 6) * math.cos(row / 4))))
    prog = numbered([*prog, ProgramEnd()])
    _sps, report = plan(prog)
    assert_good(report, deviation=0.005)


def test_line_arc_line_at_high_feed() -> None:
    prog = numbered([g64(0.01), SetFeedRate(8000), StraightFeed(Pose(40, 0, 0)),
                     ArcFeed(Pose(50, 10, 0), Pose(40, 10, 0), Plane.XY, 1),
                     StraightFeed(Pose(50, 60, 0)),
                     ArcFeed(Pose(30, 60, 0), Pose(40, 60, 0), Plane.XY, 1),
                     StraightFeed(Pose(30, 0, 0)), ProgramEnd()])
    sps, report = plan(prog)
    assert_good(report, deviation=0.01)  # line-arc joins are now eased within P
    # the long lines reach the programmed feed (within the axis velocity limit)
    assert path_speed(sps, DEMO_MACHINE.cycle_s).max() == pytest.approx(8000 / 60, rel=0.01)


@pytest.mark.parametrize("turns", [1, -3])
def test_helix(turns: int) -> None:
    prog = numbered([SetFeedRate(1500), StraightFeed(Pose(5, 0, 0)),
                     ArcFeed(Pose(5, 0, -6), Pose(0, 0, 0), Plane.XY, turns), ProgramEnd()])
    sps, report = plan(prog)
    assert_good(report, deviation=math.inf)  # G64 without P: the line-helix corner is blended, any size
    z = np.array([s.positions[2] for s in sps])
    assert np.all(np.diff(z) <= 1e-12)  # z goes down monotonically along the helix
    r = np.hypot([s.positions[0] for s in sps], [s.positions[1] for s in sps])
    assert np.abs(r[len(r) // 4: -len(r) // 4] - 5).max() < 1e-6


def test_g18_and_g19_arcs() -> None:
    prog = numbered([SetFeedRate(2000), G61,
                     ArcFeed(Pose(0, 0, 10), Pose(0, 0, 5), Plane.XZ, 1),   # G18: in Z-X, normal Y
                     ArcFeed(Pose(0, 0, 0), Pose(0, 0, 5), Plane.XZ, -1),
                     ArcFeed(Pose(0, 8, 4), Pose(0, 4, 4), Plane.YZ, 2),  # G19, 1.x turns
                     ProgramEnd()])
    sps, report = plan(prog)
    assert_good(report)
    pts = np.array([s.positions for s in sps])
    # the G18 arcs never move Y; the G19 arc never moves X
    assert np.abs(pts[:, 1]).max() > 7.9
    assert np.abs(pts[: len(pts) // 3, 1]).max() == 0.0


def test_zigzag_of_very_short_segments() -> None:
    prog = [g64(0.02), SetFeedRate(3000)]
    for i in range(400):
        prog.append(StraightFeed(Pose(0.02 * i, 0.02 * (i % 2), 0)))
    _sps, report = plan(numbered([*prog, ProgramEnd()]))
    assert_good(report, deviation=0.02)


def test_move_of_one_micrometre_fraction() -> None:
    prog = numbered([SetFeedRate(1000), StraightFeed(Pose(1e-6, 0, 0)),
                     StraightFeed(Pose(1e-6, 1e-6, 1e-6)), ProgramEnd()])
    sps, report = plan(prog)
    assert_good(report)
    assert sps[-1].positions == (1e-6, 1e-6, 1e-6)


def test_exact_stop_modes_reach_every_point_at_rest() -> None:
    corners = [Pose(10, 0, 0), Pose(10, 10, 0), Pose(0, 10, 0), Pose(0, 0, 0)]
    prog = numbered([G61_1, SetFeedRate(3000), *[StraightFeed(c) for c in corners], ProgramEnd()])
    sps, report = plan(prog)
    assert_good(report)
    assert report.stops_total == 4
    pts = [s.positions for s in sps]
    for c in corners:
        hit = [i for i, p in enumerate(pts) if p == (c.x, c.y, c.z)]
        assert hit, c
    # G9 on one block in G64: that block ends at rest exactly on its point, the others blend
    prog = numbered([g64(0.5), SetFeedRate(3000), StraightFeed(Pose(10, 0, 0)), ExactStopBlock(),
                     StraightFeed(Pose(10, 10, 0)), StraightFeed(Pose(0, 10, 0)), StraightFeed(Pose(0, 0, 0)),
                     ProgramEnd()])
    sps, report = plan(prog)
    assert_good(report, deviation=0.5)
    pts = [s.positions for s in sps]
    assert (10.0, 10.0, 0.0) in pts
    assert (10.0, 0.0, 0.0) not in pts and (0.0, 10.0, 0.0) not in pts  # blended corners


def test_g61_exact_path_does_not_blend_corners() -> None:
    prog = numbered([G61, SetFeedRate(3000), StraightFeed(Pose(10, 0, 0)), StraightFeed(Pose(10, 10, 0)),
                     ProgramEnd()])
    sps, report = plan(prog)
    assert_good(report)
    assert (10.0, 0.0, 0.0) in [s.positions for s in sps]


def test_rapid_runs_each_axis_at_its_limit_and_feed_is_clamped() -> None:
    _, report = plan(numbered([StraightTraverse(Pose(0, 0, -60)), ProgramEnd()]))
    assert_good(report)
    assert report.peaks["z"].velocity == pytest.approx(100.0, rel=0.01)
    # a feed far above the machine's limits: the diagonal runs at the X/Y limit
    _sps, report = plan(numbered([SetFeedRate(1e6), StraightFeed(Pose(300, 300, 0)), ProgramEnd()]))
    assert_good(report)
    assert report.peaks["x"].velocity == pytest.approx(200.0, rel=0.01)


def test_inverse_time_feed() -> None:
    # G93 F30: the 20 mm move takes 2 minutes^-1... i.e. 60/30 = 2 s at 10 mm/s
    prog = numbered([G61, SetFeedMode(FeedMode.INVERSE_TIME), SetFeedRate(30), StraightFeed(Pose(20, 0, 0)),
                     SetFeedRate(120), StraightFeed(Pose(20, 10, 0)), ProgramEnd()])
    sps, report = plan(prog)
    assert_good(report)
    speed = path_speed(sps, DEMO_MACHINE.cycle_s)
    assert speed[: len(speed) // 2].max() == pytest.approx(10.0, rel=1e-3)
    assert speed.max() == pytest.approx(20.0, rel=1e-3)  # 10 mm in 0.5 min^-1 ... 120/min: 0.5 s
    assert 2.5 < report.duration_s < 3.0


def test_feed_per_revolution() -> None:
    prog = numbered([SpindleOn(SpindleDirection.CW, 1000), SetFeedMode(FeedMode.UNITS_PER_REV),
                     SetFeedRate(0.1), StraightFeed(Pose(20, 0, 0)), SetSpindleSpeed(2000),
                     StraightFeed(Pose(40, 0, 0)), ProgramEnd()])
    sps, report = plan(prog)
    assert_good(report)
    speed = path_speed(sps, DEMO_MACHINE.cycle_s)
    assert speed.max() == pytest.approx(0.1 * 2000 / 60, rel=1e-3)


ROTARY = MachineLimits(
    axes=(AxisLimits("x", 100.0, 1000.0, 20000.0), AxisLimits("y", 100.0, 1000.0, 20000.0),
          AxisLimits("z", 50.0, 800.0, 10000.0), AxisLimits("a", 90.0, 300.0, 3000.0)),
    cycle_s=0.004,
)


def test_rotary_axis_with_its_own_limits() -> None:
    prog = numbered([G61, SetFeedRate(3000), StraightFeed(Pose(50, 0, 0, a=360)),  # A limits the move
                     StraightFeed(Pose(50, 0, 0, a=0)),  # pure rotary: deg/min
                     ArcFeed(Pose(50, 20, 0, a=90), Pose(50, 10, 0), Plane.XY, 1), ProgramEnd()])
    sps, report = plan(prog, ROTARY)
    assert_good(report)
    assert report.peaks["a"].velocity == pytest.approx(90.0, rel=0.01)  # the first move: A's limit
    a = np.array([s.positions[3] for s in sps if s.line == 4])  # the pure rotary move: F in deg/min
    assert np.abs(np.diff(a)).max() / ROTARY.cycle_s == pytest.approx(50.0, rel=0.01)
    assert report.peaks["a"].acceleration <= 300 * 1.01


def test_start_position_and_cycle_time_from_the_machine() -> None:
    machine = MachineLimits(DEMO_MACHINE.axes, cycle_s=0.001)
    prog = numbered([SetFeedRate(600), StraightFeed(Pose(5, 5, 5)), ProgramEnd()])
    sps, report = plan(prog, machine, start=(1.0, 2.0, 3.0))
    assert_good(report)
    assert sps[0].t == pytest.approx(0.001)
    assert np.allclose(np.diff([s.t for s in sps]), 0.001)
    assert np.allclose(sps[0].positions, (1, 2, 3), atol=1e-4)


def test_corner_is_blended_by_the_mode_of_the_move_that_ends_there() -> None:
    prog = numbered([g64(0.05), SetFeedRate(3000), StraightFeed(Pose(10, 0, 0)), G61,
                     StraightFeed(Pose(10, 10, 0)), g64(0.05), StraightFeed(Pose(0, 10, 0)),
                     StraightFeed(Pose(0, 0, 0)), ProgramEnd()])
    sps, report = plan(prog)
    assert_good(report, deviation=0.05)
    pts = [s.positions for s in sps]
    assert (10.0, 0.0, 0.0) not in pts  # ends a G64 move: blended
    assert (10.0, 10.0, 0.0) in pts  # ends a G61 move: stopped on, though the next is G64
    assert (0.0, 10.0, 0.0) not in pts
