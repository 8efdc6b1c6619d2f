"""The cycle's feeding bounds what it keeps queued in the planner in items and in programmed moves."""

from __future__ import annotations

from gcode_canon.commands import MotionControlMode, Pose, SetFeedRate, SetMotionControlMode, StraightFeed
from motiond.runtime.cycle import LOOKAHEAD, LOOKAHEAD_MOVES, QUEUE_MAX, Cycle
from motiond.runtime.records import Stream
from planner import DEMO_MACHINE, Planner


def staircase(moves: int, per_step: int = 100) -> list:
    """Steps of ``per_step`` collinear 0.01 mm pieces, alternately along X and Y (G64 P0.01): each
    step is merged into one queue item holding ``per_step`` moves."""
    cmds: list = [SetMotionControlMode(MotionControlMode.CONTINUOUS, 0.01), SetFeedRate(600)]
    x = y = 0.0
    for k in range(moves):
        if (k // per_step) % 2:
            y += 0.01
        else:
            x += 0.01
        cmds.append(StraightFeed(Pose(round(x, 4), round(y, 4), 0)))
    return cmds


def test_the_cycle_keeps_at_most_lookahead_moves_in_the_planner() -> None:
    """Merged lines hold many moves per item: 7,000 moves are about 140 items, well below LOOKAHEAD;
    the planner must still not be fed more than LOOKAHEAD_MOVES programmed moves ahead."""
    cycle = Cycle(DEMO_MACHINE, None, late_fault_s=1.0, simulated=True, hooks=None)  # type: ignore[arg-type]
    cycle.stream = Stream(len(DEMO_MACHINE.axes))
    planner = Planner(DEMO_MACHINE)
    todo = iter(staircase(LOOKAHEAD_MOVES + 2000))
    left = True
    for _ in range(1000):  # bounded: each round (a cycle, no setpoint taken) feeds up to 40 commands
        while left and cycle._cmdq.qsize() < QUEUE_MAX:
            cmd = next(todo, None)
            if cmd is None:
                left = False
                break
            cycle._cmdq.put(cmd)
        before = cycle._cmdq.qsize()
        cycle._feed(planner)
        if cycle._cmdq.qsize() == before:
            break  # the planner takes no more
    assert planner.queued_moves <= LOOKAHEAD_MOVES
    assert 2 <= planner.queue_length < LOOKAHEAD
    assert not cycle._cmdq.empty()
