"""Bad input: a clear error naming file and line, or a defined behaviour; never a crash or a hang."""

from __future__ import annotations

import math

import pytest

from gcode_canon.commands import (
    ArcFeed,
    Dwell,
    FeedMode,
    MotionControlMode,
    Plane,
    Pose,
    ProgramEnd,
    SetFeedMode,
    SetFeedRate,
    SetMotionControlMode,
    StraightFeed,
    StraightTraverse,
)
from gcode_canon.errors import GCodeError
from planner import DEMO_MACHINE, AxisLimits, MachineError, MachineLimits, Planner, PlannerError, check_stream
from planner import plan_all as _plan_all


def plan_all(prog, machine=DEMO_MACHINE):
    return list(_plan_all(prog, machine, max_cycles=200_000))


@pytest.mark.parametrize(
    ("commands", "message"),
    [
        ([StraightFeed(Pose(1, 0, 0), file="p.ngc", line=7)], "feed rate is 0"),
        ([SetFeedRate(0.0), StraightFeed(Pose(1, 0, 0), file="p.ngc", line=7)], "feed rate is 0"),
        ([SetFeedRate(-3.0, file="p.ngc", line=7)], "feed rate must be >= 0"),
        ([SetFeedRate(100), StraightFeed(Pose(math.nan, 0, 0), file="p.ngc", line=7)], "not a finite number"),
        ([SetFeedRate(math.inf, file="p.ngc", line=7)], "not a finite number"),
        ([SetFeedMode(FeedMode.INVERSE_TIME), StraightFeed(Pose(1, 0, 0), file="p.ngc", line=7)], "G93"),
        ([SetFeedMode(FeedMode.UNITS_PER_REV), SetFeedRate(0.1),
          StraightFeed(Pose(1, 0, 0), file="p.ngc", line=7)], "G95"),
        ([SetFeedRate(100), StraightFeed(Pose(1, 0, 0, a=5), file="p.ngc", line=7)], "axis A"),
        ([SetFeedRate(100), ArcFeed(Pose(1, 0, 0), Pose(0, 0, 0), Plane.UV, 1, file="p.ngc", line=7)],
         "needs axes U and V"),
        ([SetFeedRate(100), ArcFeed(Pose(2, 0, 0), Pose(1, 0, 0), Plane.XY, 0, file="p.ngc", line=7)],
         "0 turns"),
        ([Dwell(-1.0, file="p.ngc", line=7)], "dwell must be >= 0"),
        ([SetMotionControlMode(MotionControlMode.CONTINUOUS, -0.1, file="p.ngc", line=7)], "G64 P"),
    ],
)
def test_errors_name_file_and_line(commands, message: str) -> None:
    with pytest.raises(PlannerError) as err:
        plan_all(commands)
    assert isinstance(err.value, GCodeError)  # the CLI prints it as FILE:LINE: message, no traceback
    assert str(err.value).startswith("p.ngc:7: ")
    assert message in str(err.value)


def test_soft_limits() -> None:
    machine = MachineLimits((AxisLimits("x", 100, 1000, 10000, min_position=-1.0, max_position=50.0),))
    with pytest.raises(PlannerError, match=r"q.ngc:3: .*X60 is outside the soft limits"):
        plan_all([StraightTraverse(Pose(60), file="q.ngc", line=3)], machine)
    assert plan_all([StraightTraverse(Pose(50))], machine)[-1].positions == (50.0,)
    # an arc whose ends are inside but whose bulge is not: from (0, 0) to (0, 20) round (0, 10)
    xy = MachineLimits((AxisLimits("x", 100, 1000, 10000, min_position=-1.0, max_position=50.0),
                        AxisLimits("y", 100, 1000, 10000)))
    cw = [SetFeedRate(600), ArcFeed(Pose(0, 20, 0), Pose(0, 10, 0), Plane.XY, -1, file="q.ngc", line=4)]
    with pytest.raises(PlannerError, match=r"q.ngc:4: .*X-10 is outside"):
        plan_all(cw, xy)
    ccw = [SetFeedRate(600), ArcFeed(Pose(0, 20, 0), Pose(0, 10, 0), Plane.XY, 1)]  # through X10: fine
    assert plan_all(ccw, xy)[-1].positions == (0.0, 20.0)


def test_zero_length_move_takes_no_time() -> None:
    sps = plan_all([SetFeedRate(100), StraightFeed(Pose(0, 0, 0)), StraightFeed(Pose(1e-12, 0, 0))])
    assert sps == []
    prog = [SetFeedRate(600), StraightFeed(Pose(1, 0, 0)), StraightFeed(Pose(1, 0, 0)),
            StraightFeed(Pose(2, 0, 0))]
    report = check_stream(plan_all(prog), prog)
    assert report.ok, report.problems()


def test_arc_of_radius_1e9_runs_as_the_line_to_its_end() -> None:
    prog = [SetFeedRate(600), StraightFeed(Pose(1, 0, 0)),
            ArcFeed(Pose(1, 2e-9, 0), Pose(1, 1e-9, 0), Plane.XY, 1), StraightFeed(Pose(2, 0, 0))]
    sps = plan_all(prog)
    assert sps[-1].positions == (2.0, 0.0, 0.0)
    report = check_stream(sps, prog)
    assert report.ok, report.problems()


def test_impossible_machines_are_refused() -> None:
    for bad in (0.0, -1.0, math.nan):
        with pytest.raises(MachineError):
            AxisLimits("x", bad, 1000, 10000)
        with pytest.raises(MachineError):
            AxisLimits("x", 100, 1000, bad)


def test_feed_override_must_be_a_number() -> None:
    with pytest.raises(PlannerError, match="override"):
        Planner().set_feed_override(math.nan)


def test_start_position_of_the_wrong_size() -> None:
    with pytest.raises(PlannerError, match="3 values"):
        Planner(start=(0.0, 0.0))


def test_tiny_and_huge_feeds_terminate() -> None:
    # 1 mm at F0.001 would take 16 hours: bounded by max_cycles, it raises rather than spin
    with pytest.raises(PlannerError, match="more than 1000 cycles"):
        list(_plan_all([SetFeedRate(0.001), StraightFeed(Pose(1, 0, 0))], max_cycles=1000))
    prog = [SetFeedRate(1e12), StraightFeed(Pose(0.001, 0, 0)), ProgramEnd()]
    assert check_stream(plan_all(prog), prog).ok
