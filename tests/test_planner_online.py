"""Online control in the cycle loop: override, hold/resume, abort, quick stop. Never a jump."""

from __future__ import annotations

import numpy as np
import pytest

from gcode_canon.commands import (
    ArcFeed,
    MotionControlMode,
    Plane,
    Pose,
    SetFeedRate,
    SetMotionControlMode,
    StraightFeed,
)
from planner import DEMO_MACHINE, Planner, check_stream

T = DEMO_MACHINE.cycle_s
PROGRAM = [
    SetMotionControlMode(MotionControlMode.CONTINUOUS, 0.01),
    SetFeedRate(3000),
    StraightFeed(Pose(150, 0, 0), line=1),
    StraightFeed(Pose(150, 50, 0), line=2),
    ArcFeed(Pose(100, 50, 0), Pose(125, 50, 0), Plane.XY, 1, line=3),
    StraightFeed(Pose(0, 0, 0), line=4),
]


def run(actions: dict[int, tuple], program=PROGRAM, limit: int = 30000):
    """Pull cycles, calling planner methods at given cycle numbers; returns planner and setpoints."""
    p = Planner()
    p.feed_many(program)
    p.flush()
    out = []
    for k in range(limit):
        if k in actions:
            name, *args = actions[k]
            getattr(p, name)(*args)
        sp = p.next_setpoint()
        if sp is None:
            assert p.is_idle
            break
        out.append(sp)
    else:
        pytest.fail("the stream did not end")
    return p, out


def speeds(out) -> np.ndarray:
    pts = np.array([s.positions for s in out])
    return np.linalg.norm(np.diff(pts, axis=0), axis=1) / T


def test_plain_run_reference() -> None:
    _p, out = run({})
    report = check_stream(out, PROGRAM)
    assert report.ok, report.problems()
    assert speeds(out)[100:300].max() == pytest.approx(50.0, rel=1e-6)  # F3000 cruise on line 1


def test_feed_override_changes_speed_smoothly() -> None:
    _p, out = run({200: ("set_feed_override", 0.4), 1200: ("set_feed_override", 1.6)})
    report = check_stream(out, PROGRAM)
    assert report.ok, report.problems()
    v = speeds(out)
    assert v[600:1000].max() == pytest.approx(20.0, rel=1e-3)  # 40 % of 50 mm/s
    assert v[1300:1500].max() == pytest.approx(80.0, rel=1e-3)  # 160 %
    assert np.all(np.diff([s.t for s in out]) == pytest.approx(T))


def test_override_is_clamped_to_200_percent_and_to_the_axis_limits() -> None:
    p, out = run({10: ("set_feed_override", 9.0)})
    assert p.feed_override == 2.0
    report = check_stream(out, PROGRAM)
    assert report.ok, report.problems()
    assert speeds(out)[100:400].max() == pytest.approx(100.0, rel=1e-3)


def test_override_zero_stops_on_the_path_and_continues() -> None:
    _p, out = run({300: ("set_feed_override", 0.0), 900: ("set_feed_override", 1.0)})
    report = check_stream(out, PROGRAM)
    assert report.ok, report.problems()
    v = speeds(out)
    assert v[700:890].max() == 0.0


def test_hold_stops_within_the_braking_distance_and_resume_continues() -> None:
    _p, out = run({400: ("hold",), 1000: ("resume",)})
    report = check_stream(out, PROGRAM)
    assert report.ok, report.problems()
    v = speeds(out)
    assert v[398] == pytest.approx(50.0, rel=1e-6)
    # a jerk-limited stop from 50 mm/s with 2000 mm/s^2 and 45000 mm/s^3 takes about 70 ms
    stopped = 400 + int(np.argmax(v[400:] == 0.0))
    assert stopped - 400 < 60
    assert v[stopped:999].max() == 0.0
    held = out[stopped].positions
    at_hold = out[399].positions[0]
    # on line 1: from 50 mm/s with jerk 45000 mm/s^3 (0.9 of the limit) the stop takes
    # 2 sqrt(50 / 45000) = 66.7 ms and 25 mm/s * 66.7 ms = 1.67 mm
    assert held[1] == 0.0 and held[0] - at_hold == pytest.approx(1.667, abs=0.06)
    assert v[1005] > 0.0
    # the whole program is still done, exactly
    assert out[-1].positions == (0.0, 0.0, 0.0)


def test_hold_inside_a_blend_and_an_arc() -> None:
    _, plain = run({})
    lines = [s.line for s in plain]
    blend = lines.index(2) - 3  # the corner blend before line 2 carries line 2's number
    for k in (blend, lines.index(3) + 200, lines.index(4) - 2):
        _p, out = run({k: ("hold",), k + 400: ("resume",)})
        report = check_stream(out, PROGRAM)
        assert report.ok, (k, report.problems())
        assert speeds(out)[k + 150: k + 390].max() == 0.0


def test_abort_stops_smoothly_and_drops_the_queue() -> None:
    p, out = run({400: ("abort",)})
    report = check_stream(out, PROGRAM)
    assert report.within_limits, report.problems()
    assert report.max_deviation < 1e-9
    end = out[-1].positions
    at_abort = out[399].positions[0]
    assert end[0] - at_abort == pytest.approx(1.667, abs=0.06) and end[1] == 0.0
    assert p.is_idle and p.queue_length == 0
    # the planner takes new commands from where it stopped
    p.feed(StraightFeed(Pose(end[0], 10.0, 0.0)))
    more = [p.next_setpoint() for _ in range(2000)]
    more = [s for s in more if s is not None]
    assert more[-1].positions == (end[0], 10.0, 0.0)
    both = check_stream(out + more, [*PROGRAM[:3], StraightFeed(Pose(end[0], 10.0, 0.0))])
    assert both.within_limits, both.problems()


def test_quick_stop_uses_the_quick_stop_deceleration() -> None:
    p, out = run({400: ("quick_stop",)})
    _q, slow = run({400: ("abort",)})
    report = check_stream(out, PROGRAM)
    x = DEMO_MACHINE.axis("x")
    assert report.peaks["x"].velocity <= x.max_velocity
    assert x.max_acceleration * 1.05 < report.peaks["x"].acceleration <= x.quick_stop * 1.01
    assert out[-1].positions[0] < slow[-1].positions[0]  # a shorter stop
    assert p.is_idle


def test_abort_at_rest_and_while_waiting_clears_everything() -> None:
    p = Planner()
    p.feed(SetFeedRate(600))
    p.feed(StraightFeed(Pose(1, 0, 0)))
    p.abort()
    assert p.is_idle and p.next_setpoint() is None


@pytest.mark.parametrize("every", [1, 7, 40])
def test_feeding_while_running_starves_safely(every: int) -> None:
    """The daemon feeds as the interpreter yields: a short queue may run dry, never past its end."""
    import math

    prog = [SetMotionControlMode(MotionControlMode.CONTINUOUS, 0.05), SetFeedRate(4000)]
    for i in range(1, 80):
        prog.append(StraightFeed(Pose(3 * i, 4 * math.sin(i / 3), 0), line=i))
    p = Planner()
    out = []
    todo = list(prog)
    for k in range(50000):
        if todo and k % every == 0:
            p.feed(todo.pop(0))
        sp = p.next_setpoint()
        if sp is None:
            if not todo:
                break
            out.append(None)  # an idle cycle: the drive holds the last position
            continue
        out.append(sp)
    else:
        pytest.fail("the stream did not end")
    last = (0.0, 0.0, 0.0)
    stream = []
    for sp in out:  # idle cycles repeat the last position, as the cycle loop does
        last = sp.positions if sp is not None else last
        stream.append(last)
    report = check_stream(np.array(stream), prog)
    assert report.ok, report.problems()
