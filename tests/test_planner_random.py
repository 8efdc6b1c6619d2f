"""Random programs (lines, arcs and helices in all planes, every mode, tiny and huge moves, dwells) and
random operator actions: every stream stays inside the limits, on the path, and ends where it must."""

from __future__ import annotations

import math
import random

import pytest

from gcode_canon.commands import (
    ArcFeed,
    Dwell,
    ExactStopBlock,
    MotionControlMode,
    Plane,
    Pose,
    ProgramEnd,
    SetFeedRate,
    SetMotionControlMode,
    StraightFeed,
    StraightTraverse,
)
from planner import Planner, check_stream, plan_all


def random_program(rng: random.Random) -> list:
    prog: list = [SetFeedRate(rng.choice([600, 2000, 6000, 20000]))]
    pos = [0.0, 0.0, 0.0]
    for i in range(1, rng.randint(2, 30)):
        r = rng.random()
        if r < 0.1:
            prog.append(SetMotionControlMode(rng.choice(list(MotionControlMode)),
                                             rng.choice([0, 0.001, 0.01, 0.1, 1.0])))
        elif r < 0.15:
            prog.append(ExactStopBlock())
        elif r < 0.2:
            prog.append(SetFeedRate(rng.choice([300, 2000, 6000])))
        elif r < 0.25:
            prog.append(Dwell(rng.choice([0.0, 0.01])))
        elif r < 0.55:
            scale = rng.choice([1e-6, 1e-3, 0.05, 1, 10])
            end = [p + rng.uniform(-1, 1) * scale * (rng.random() < 0.8) for p in pos]
            kind = StraightTraverse if rng.random() < 0.2 else StraightFeed
            prog.append(kind(Pose(*end), file="r.ngc", line=i))
            pos = end
        else:
            plane = rng.choice([Plane.XY, Plane.XZ, Plane.YZ])
            i0, i1, normal = plane.value
            radius = rng.choice([1e-9, 0.01, 0.5, 5, 12])
            angle = rng.uniform(0, 2 * math.pi)
            centre = list(pos)
            centre[i0] -= radius * math.cos(angle)
            centre[i1] -= radius * math.sin(angle)
            sweep = rng.uniform(0.05, 6)
            end = list(pos)
            end[i0] = centre[i0] + radius * math.cos(angle + sweep)
            end[i1] = centre[i1] + radius * math.sin(angle + sweep)
            end[normal] += rng.choice([0, 0, 1, -3])
            turns = rng.choice([1, -1, 2])
            prog.append(ArcFeed(Pose(*end), Pose(*centre), plane, turns, file="r.ngc", line=i))
            pos = end
    return [*prog, ProgramEnd()]


@pytest.mark.parametrize("seed", range(8))
def test_random_programs(seed: int) -> None:
    prog = random_program(random.Random(seed))
    sps = list(plan_all(prog, max_cycles=2_000_000))
    report = check_stream(sps, prog)
    assert report.ok, report.problems()


@pytest.mark.parametrize("seed", range(100, 106))
def test_random_programs_with_operator_actions(seed: int) -> None:
    rng = random.Random(seed)
    prog = random_program(rng)
    choices = [("hold",), ("set_feed_override", 0.3), ("set_feed_override", 1.8), ("set_feed_override", 0.0),
               ("resume",)]
    actions = {rng.randint(0, 1500): rng.choice(choices) for _ in range(4)}
    p = Planner(auto_release=True)
    p.feed_many(prog)
    p.flush()
    out = []
    for k in range(2_000_000):
        if k in actions:
            name, *args = actions[k]
            getattr(p, name)(*args)
        if k == 2000:
            p.resume()
            p.set_feed_override(1.0)
        sp = p.next_setpoint()
        if sp is None:
            break
        out.append(sp)
    report = check_stream(out, prog)
    assert report.ok, (actions, report.problems())
