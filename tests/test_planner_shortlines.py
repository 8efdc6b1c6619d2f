"""Chains of short lines (CAM surfacing) in G64 P: smoothed within P and run as one profile.

A 0.2 mm polyline sampled from a smooth surface used to become a chain of corner blends whose
curvature rose and fell every segment; their jerk term capped the speed near 20 mm/s where the feed
asks for 33. These tests pin the improvement (the cycle time against a bound computed from the
machine's limits) and that everything else still holds: limits, deviation within P, exact stops,
events, line numbers, hold and override in the middle of a chain, a starved queue.
"""

from __future__ import annotations

import math
import random

from gcode_canon.commands import (
    DigitalOutput,
    ExactStopBlock,
    MotionControlMode,
    Pose,
    ProgramEnd,
    SetFeedRate,
    SetMotionControlMode,
    StraightFeed,
)
from planner import DEMO_MACHINE, Planner, check_stream, plan_all
from planner.kinematics import change_distance, change_time

FEED = 2000.0  # mm/min
STEP = 0.2  # mm along X
T = DEMO_MACHINE.cycle_s


def surface(x: float) -> float:
    return 2.0 * math.sin(x / 7.0) + 0.5 * math.sin(x / 2.3)


def row(n: int = 500, tolerance: float = 0.01, noise: float = 0.0, seed: int = 0) -> list:
    """One raster row from machine zero: ``n`` 0.2 mm lines over the wavy surface (z(0) = 0)."""
    rng = random.Random(seed)
    prog: list = [SetMotionControlMode(MotionControlMode.CONTINUOUS, tolerance), SetFeedRate(FEED),
                  StraightFeed(Pose(0.0, 0.0, surface(0.0)), file="row.ngc", line=1)]  # zero-length
    for i in range(1, n + 1):
        x = i * STEP
        prog.append(StraightFeed(Pose(x, rng.uniform(-noise, noise), surface(x) + rng.uniform(-noise, noise)),
                                 file="row.ngc", line=i + 1))
    prog.append(ProgramEnd(file="row.ngc", line=n + 2))
    return prog


def path_length(prog: list) -> float:
    pos, total = (0.0, 0.0, 0.0), 0.0
    for cmd in prog:
        if isinstance(cmd, StraightFeed):
            end = (cmd.end.x, cmd.end.y, cmd.end.z)
            total += math.dist(pos, end)
            pos = end
    return total


def test_short_lines_run_near_the_feed() -> None:
    prog = row()
    sps = list(plan_all(prog))
    report = check_stream(sps, prog)
    assert report.ok, report.problems()
    assert report.max_deviation <= 0.01
    # Bound from the machine's limits: the whole path at the feed, plus starting from rest and
    # stopping at the end as fast as the X axis's acceleration and jerk allow (the path runs mostly
    # along X; each of the two speed changes costs half its duration). Chained corner blends took
    # 1.67 times this.
    v = FEED / 60.0
    ax = DEMO_MACHINE.axes[0]
    bound = path_length(prog) / v + change_time(v, ax.max_acceleration, ax.max_jerk)
    assert len(sps) * T < 1.15 * bound, (len(sps) * T, bound)


def test_chain_profiles_and_line_numbers() -> None:
    """A chain runs under few profiles (not one per line), and setpoints still name the line they
    are on, in order."""
    prog = row(200)
    p = Planner(auto_release=True)
    p.feed_many(prog)
    p.flush()
    lines = []
    while (sp := p.next_setpoint()) is not None:
        if sp.line:
            lines.append(sp.line)
    assert p.stats["solves"] < 60, p.stats
    assert lines == sorted(lines)
    assert len(set(lines)) > 150  # a cycle covers 0.067 mm at the feed: most lines are seen


def test_events_and_exact_stops_inside_a_chain() -> None:
    prog = row(120)
    move = {c.line: c for c in prog if isinstance(c, StraightFeed)}
    at = prog.index(move[42])
    prog.insert(at, ExactStopBlock())  # G9 on line 42: exactly at rest on its end point
    prog.insert(prog.index(move[80]), DigitalOutput(3, True, synced=True, file="row.ngc", line=80))
    sps = list(plan_all(prog))
    report = check_stream(sps, prog)
    assert report.ok, report.problems()
    assert report.stops_total >= 2 and not report.stops_missed
    stop = move[42].end
    assert any(sp.positions == (stop.x, stop.y, stop.z) for sp in sps)
    ev = [sp for sp in sps if any(isinstance(e, DigitalOutput) for e in sp.events)]
    assert len(ev) == 1
    # the synced output rides on the first setpoint of line 80's motion: at its start point, or where
    # a corner blend into it begins (at most half of line 79 before it)
    start = move[79].end
    assert ev[0].line == 80
    assert math.dist(ev[0].positions, (start.x, start.y, start.z)) < 0.5 * STEP + FEED / 60.0 * T


def test_hold_override_and_starved_queue_inside_a_chain() -> None:
    prog = row(300)
    for starved in (False, True):
        p = Planner(auto_release=True)
        it = iter(prog)
        if not starved:
            p.feed_many(prog)
            p.flush()
        done = not starved
        out = []
        for k in range(200_000):
            if not done and k % 2 == 0:  # a daemon that feeds one command every other cycle
                cmd = next(it, None)
                if cmd is None:
                    done = True
                    p.flush()
                else:
                    p.feed(cmd)
            if k == 300:
                p.hold()
            elif k == 700:
                p.resume()
            elif k == 900:
                p.set_feed_override(1.8)
            elif k == 1100:
                p.set_feed_override(0.4)
            elif k == 1300:
                p.set_feed_override(1.0)
            sp = p.next_setpoint()
            if sp is None:
                if done:
                    break
                continue
            out.append(sp)
        report = check_stream(out, prog)
        assert report.ok, (starved, report.problems())


def test_noisy_points_stay_within_p_and_limits() -> None:
    for tolerance, noise in ((0.01, 0.002), (0.005, 0.0005), (0.05, 0.01)):
        prog = row(300, tolerance=tolerance, noise=noise, seed=7)
        sps = list(plan_all(prog))
        report = check_stream(sps, prog)
        assert report.ok, (tolerance, noise, report.problems())


def test_change_distance_is_what_the_bound_assumes() -> None:
    # the bound above charges half of each speed change's duration: true for a change from rest
    v, ax = FEED / 60.0, DEMO_MACHINE.axes[0]
    t = change_time(v, ax.max_acceleration, ax.max_jerk)
    assert math.isclose(change_distance(0.0, v, ax.max_acceleration, ax.max_jerk), 0.5 * v * t)
