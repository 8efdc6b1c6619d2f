"""Events on the timeline: synced outputs on the first cycle of the next motion, sync points at rest."""

from __future__ import annotations

import pytest

from gcode_canon.commands import (
    AnalogOutput,
    Coolant,
    DigitalOutput,
    Dwell,
    InputKind,
    MotionControlMode,
    Pose,
    Probe,
    ProbeMode,
    ProgramEnd,
    ProgramStop,
    SetFeedRate,
    SetMotionControlMode,
    SpindleDirection,
    SpindleOn,
    StraightFeed,
    ToolChange,
    WaitInput,
    WaitMode,
)
from planner import DEMO_MACHINE, Planner, check_stream, plan_all

T = DEMO_MACHINE.cycle_s


def where(sps, cmd) -> list[int]:
    return [i for i, s in enumerate(sps) if any(e is cmd for e in s.events)]


def test_synced_output_rides_on_the_first_cycle_of_the_next_motion() -> None:
    m62 = DigitalOutput(0, True, synced=True, line=3)
    m67 = AnalogOutput(1, 2.5, synced=True, line=4)
    prog = [SetMotionControlMode(MotionControlMode.EXACT_STOP_MODAL), SetFeedRate(1200),
            StraightFeed(Pose(5, 0, 0), line=2), m62, m67, StraightFeed(Pose(5, 5, 0), line=5), ProgramEnd()]
    sps = list(plan_all(prog))
    (i,) = where(sps, m62)
    assert where(sps, m67) == [i]
    assert sps[i].line == 5
    # the cycle where the next move starts: at rest on the end of line 2, then it moves
    assert sps[i].positions == (5.0, 0.0, 0.0)
    assert sps[i - 1].positions[0] < 5.0
    assert sps[i + 1].positions[1] > 0


def test_synced_output_in_a_blend_rides_on_its_first_cycle() -> None:
    m62 = DigitalOutput(2, True, synced=True)
    prog = [SetMotionControlMode(MotionControlMode.CONTINUOUS, 0.1), SetFeedRate(1200),
            StraightFeed(Pose(5, 0, 0), line=1), m62, StraightFeed(Pose(5, 5, 0), line=2)]
    sps = list(plan_all(prog))
    (i,) = where(sps, m62)
    assert sps[i - 1].line == 1 and sps[i].line == 2
    assert 4.5 < sps[i].positions[0] < 5.0  # inside the blend, before the corner


def test_immediate_output_rides_on_the_next_setpoint_after_feeding() -> None:
    p = Planner()
    p.feed_many([SetFeedRate(600), StraightFeed(Pose(10, 0, 0))])
    for _ in range(50):
        assert p.next_setpoint() is not None
    m64 = DigitalOutput(1, True, synced=False)
    m68 = AnalogOutput(0, 1.0, synced=False)
    p.feed(m64)
    p.feed(m68)
    sp = p.next_setpoint()
    assert sp is not None and sp.events == (m64, m68)
    assert 0 < sp.positions[0] < 10  # while the move runs


def test_dwell_stops_exactly_then_holds_for_its_time() -> None:
    g4 = Dwell(0.5, line=3)
    prog = [SetFeedRate(1200), StraightFeed(Pose(5, 0, 0), line=2), g4, StraightFeed(Pose(5, 5, 0), line=4)]
    sps = list(plan_all(prog))
    (i,) = where(sps, g4)
    assert sps[i].positions == (5.0, 0.0, 0.0)
    n = round(0.5 / T)
    assert all(s.positions == (5.0, 0.0, 0.0) for s in sps[i: i + n + 1])
    assert sps[i + n + 1].positions != (5.0, 0.0, 0.0)
    report = check_stream(sps, prog)
    assert report.ok, report.problems()


def test_waits_hold_until_released() -> None:
    waits = [WaitInput(InputKind.DIGITAL, 0, WaitMode.HIGH, 1.0, line=3), ToolChange(2, line=5),
             ProgramStop(line=7)]
    prog = [SetFeedRate(1200), StraightFeed(Pose(2, 0, 0)), waits[0], StraightFeed(Pose(2, 2, 0)), waits[1],
            StraightFeed(Pose(0, 2, 0)), waits[2], StraightFeed(Pose(0, 0, 0))]
    p = Planner()
    p.feed_many(prog)
    p.flush()
    seen = []
    stream = []
    for _ in range(20000):
        sp = p.next_setpoint()
        if sp is None:
            break
        stream.append(sp)
        if p.waiting_for is not None:
            cmd = p.waiting_for
            seen.append(cmd)
            assert cmd in sp.events
            rest = sp.positions
            for _ in range(25):  # the stream holds still while the daemon acts
                held = p.next_setpoint()
                assert held is not None and held.positions == rest and held.events == ()
                stream.append(held)
            p.release()
    assert seen == waits
    assert stream[-1].positions == (0.0, 0.0, 0.0)
    assert check_stream(stream, prog).ok


def test_spindle_start_is_a_sync_point_and_coolant_rides_on_the_next_motion() -> None:
    m3 = SpindleOn(SpindleDirection.CW, 8000, line=2)
    m8 = Coolant(mist=False, flood=True, line=3)
    prog = [SetFeedRate(1200), StraightFeed(Pose(3, 0, 0), line=1), m3, m8,
            StraightFeed(Pose(3, 3, 0), line=4)]
    sps = list(plan_all(prog))
    (i,) = where(sps, m3)
    assert sps[i].positions == (3.0, 0.0, 0.0)
    (j,) = where(sps, m8)
    assert j == i + 1 and sps[j].line == 4


def test_pending_events_come_out_at_the_end_of_input() -> None:
    m62 = DigitalOutput(0, False, synced=True)
    sps = list(plan_all([SetFeedRate(600), StraightFeed(Pose(1, 0, 0)), m62]))
    assert sps[-1].events == (m62,) and sps[-1].positions == (1.0, 0.0, 0.0)
    assert sps[-2].positions[0] < 1.0  # on the first cycle at rest


def test_probe_rides_on_its_move_and_waits_at_its_end() -> None:
    g38 = Probe(Pose(0, 0, -5), ProbeMode.TOWARD_ERROR, line=2)
    p = Planner()
    p.feed_many([SetFeedRate(300), g38])
    first = p.next_setpoint()
    assert first is not None and first.events == (g38,) and first.positions[2] < 0
    for _ in range(5000):
        sp = p.next_setpoint()
        assert sp is not None
        if p.waiting_for is not None:
            break
    assert p.waiting_for is g38 and sp.positions == (0.0, 0.0, -5.0)


def test_program_end_rides_on_the_final_rest_cycle() -> None:
    m2 = ProgramEnd(line=9)
    sps = list(plan_all([SetFeedRate(600), StraightFeed(Pose(1, 2, 0)), m2]))
    assert sps[-1].events == (m2,) and sps[-1].positions == (1.0, 2.0, 0.0)
    assert sps[-1].line == 9


@pytest.mark.parametrize("seconds", [0.0, 0.0031])
def test_short_dwell_rounds_up_to_whole_cycles(seconds: float) -> None:
    g4 = Dwell(seconds)
    sps = list(plan_all([SetFeedRate(600), StraightFeed(Pose(1, 0, 0)), g4, StraightFeed(Pose(2, 0, 0))]))
    (i,) = where(sps, g4)
    still = 0
    while sps[i + still + 1].positions == (1.0, 0.0, 0.0):
        still += 1
    assert still == (0 if seconds == 0 else 2)
