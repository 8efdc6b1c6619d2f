"""The cycle's feeding bounds what it keeps queued in the planner in items and in programmed moves, and
the time a step spends feeding it."""

from __future__ import annotations

import dataclasses
import time

from gcode_canon.commands import MotionControlMode, Pose, SetFeedRate, SetMotionControlMode, StraightFeed
from motiond.runtime.cycle import FEED_BUDGET, FEED_PER_CYCLE, LOOKAHEAD, LOOKAHEAD_MOVES, QUEUE_MAX, Cycle
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


class SlowPlanner:
    """Takes every command and spends ``cost_s`` on each (busy, as the planner's blends are)."""

    def __init__(self, cost_s: float) -> None:
        self.cost_s = cost_s
        self.fed: list = []

    @property
    def queue_length(self) -> int:
        return len(self.fed)

    @property
    def queued_moves(self) -> int:
        return len(self.fed)

    def feed(self, cmd: object) -> None:
        end = time.perf_counter() + self.cost_s
        while time.perf_counter() < end:
            pass
        self.fed.append(cmd)


def slow_cycle(period_s: float) -> Cycle:
    limits = dataclasses.replace(DEMO_MACHINE, cycle_s=period_s)
    cycle = Cycle(limits, None, late_fault_s=1.0, simulated=True, hooks=None)  # type: ignore[arg-type]
    cycle.stream = Stream(len(DEMO_MACHINE.axes))
    for k in range(QUEUE_MAX):
        cycle._cmdq.put(SetFeedRate(100 + k))
    return cycle


def test_a_step_feeds_the_planner_within_its_budget_past_the_two_items_it_needs() -> None:
    """Commands costing 0.4 ms each, a 2 ms period (budget 0.5 ms): a step feeds the two items the
    planner needs to move on (past the budget already), not FEED_PER_CYCLE; once it has them, a step
    feeds while within the budget (at most two); the lookahead still fills over the following steps."""
    cycle = slow_cycle(0.002)
    assert cycle.feed_budget_s == FEED_BUDGET * 0.002
    planner = SlowPlanner(0.0004)
    cycle._feed_until = time.perf_counter() + cycle.feed_budget_s  # what each step sets
    cycle._feed(planner)
    assert len(planner.fed) == 2  # 0.8 ms: past the budget, so nothing more
    for _ in range(2000):  # bounded: each round one step's feeding
        if len(planner.fed) >= LOOKAHEAD:
            break
        cycle._feed_until = time.perf_counter() + cycle.feed_budget_s
        before = len(planner.fed)
        cycle._feed(planner)
        assert len(planner.fed) - before <= 2  # fewer (even none) when the step is held off
    assert len(planner.fed) == LOOKAHEAD


def test_without_a_budget_a_feed_takes_up_to_feed_per_cycle() -> None:
    """The counterpart: the same slow commands with the budget lifted are fed FEED_PER_CYCLE at once
    (so the test above measures the budget, not the planner)."""
    cycle = slow_cycle(0.002)
    planner = SlowPlanner(0.0004)
    cycle._feed(planner)  # outside a step: no budget
    assert len(planner.fed) == FEED_PER_CYCLE
