"""M62/M63/M67 go on the wire in the cycle in which their motion starts.

The simulated module runs as ``canon sim io`` in its own process, as a real module is outside the
daemon, and stamps each write with the system-wide monotonic clock when the request arrives; the
stand-in cycle loop here stamps each setpoint when it hands it over. Each synchronized write must
land after its setpoint was handed over and less than one cycle later. (Several outputs on the same
setpoint go out one round trip apart, in order: test_modbus_io.py checks that order.)

Order is checked on every run. The one-cycle bound is a wall-clock figure, and on a shared machine
the OS can deschedule the module's process for longer than a cycle; so a stream is replayed up to
three times and one clean run is required. A systematic delay (a write held for the next poll, sent
a cycle late) misses in every run and fails.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterator

import pytest
from test_modbus_cli import SimProcess
from test_modbus_io import CycleLoop, m62, m63, m67, make_config, motion_stream

from fieldbus.modbus.executor import IoExecutor
from gcode_canon.commands import (
    AnalogOutput,
    DigitalOutput,
    MotionControlMode,
    Pose,
    ProgramEnd,
    SetFeedRate,
    SetMotionControlMode,
    StraightFeed,
)
from planner.setpoints import Setpoint

ATTEMPTS = 3


@pytest.fixture
def sim() -> Iterator[SimProcess]:
    proc = SimProcess("--port", "0", "--size", "64")
    try:
        yield proc
    finally:
        proc.stop()


def settled(sim: SimProcess, quiet_s: float = 0.2, timeout_s: float = 5.0) -> int:
    """The number of writes the module has recorded once no more came for ``quiet_s`` (bounded)."""
    n = len(sim.writes())
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        time.sleep(quiet_s)
        m = len(sim.writes())
        if m == n:
            break
        n = m
    return n


def replay(sim: SimProcess, stream: list[Setpoint], period: float, io_cycles: list[int],
           expect: list[tuple[str, int, tuple[int, ...]]]) -> list[str]:
    """Replay ``stream`` at ``period`` through an executor; check the order of the writes and return
    the ones that missed their cycle (empty: all in time)."""
    assert sim.port is not None
    base = settled(sim)  # a replay again (in_time): the writes of the one before, its safe stop too
    with IoExecutor(make_config(sim.port, poll_ms=20.0)) as ex:
        # the safe state written at start (5 requests), awaited whole: under load it took over 5 s
        n = len(sim.wait_writes(base + 5, timeout=30.0))
        assert n >= base + 5, f"the safe state was not written at start: {n - base} of 5 requests"
        loop = CycleLoop(ex, stream, period)
        loop.run()
        writes = sim.wait_writes(n + len(expect))[n:n + len(expect)]
    assert [w[1:] for w in writes] == expect
    misses = []
    if max(loop.call_s) >= period:  # handing a setpoint over must not hold the cycle loop up
        misses.append(f"on_setpoint took {max(loop.call_s) * 1000:.2f} ms")
    for (t, table, address, _values), k in zip(writes, io_cycles, strict=True):
        late = t - loop.sent[k]
        assert late >= 0.0, f"{table} {address} was written before its motion started"
        if late >= period:
            misses.append(f"{table} {address} for cycle {k} landed {late * 1000:.2f} ms after its setpoint")
    return misses


def in_time(run: Callable[[], list[str]], period: float) -> None:
    report = []
    for attempt in range(ATTEMPTS):
        misses = run()
        if not misses:
            return
        report.append(f"run {attempt + 1}: " + "; ".join(misses))
    pytest.fail(f"a write missed its {period * 1000:g} ms cycle in every run:\n" + "\n".join(report))


def test_synchronized_outputs_land_within_one_cycle_of_their_motion_start(sim: SimProcess) -> None:
    period = 0.004
    starts = {10: (m62(0),), 30: (m63(0),), 45: (m67(0, 1.0),), 55: (m62(2),)}
    stream = motion_stream(period, starts)
    expect = [("coil", 0, (1,)), ("coil", 0, (0,)), ("holding_register", 0, (100,)), ("coil", 2, (1,))]
    in_time(lambda: replay(sim, stream, period, sorted(starts), expect), period)


def test_planner_stream_drives_the_outputs_in_time(sim: SimProcess) -> None:
    """G-code level: the planner puts M62/M63/M67 on the first cycle of their motion and M64 on the
    next cycle it emits; replayed at the cycle time, each write lands within that cycle."""
    planner = pytest.importorskip("planner")
    machine = dataclasses.replace(planner.DEMO_MACHINE, cycle_s=0.004)
    prog = [SetMotionControlMode(MotionControlMode.EXACT_STOP_MODAL), SetFeedRate(1200.0),
            StraightFeed(Pose(5, 0, 0), line=2),
            DigitalOutput(0, True, synced=True, line=3),  # M62 P0: laser on with the next move
            StraightFeed(Pose(5, 5, 0), line=4),
            AnalogOutput(0, 1.5, synced=True, line=5),  # M67 E0 Q1.5: its power with the next move
            StraightFeed(Pose(0, 5, 0), line=6),
            DigitalOutput(1, True, synced=False, line=7),  # M64 P1: at once
            DigitalOutput(0, False, synced=True, line=8),  # M63 P0: off with the next move
            StraightFeed(Pose(0, 0, 0), line=9), ProgramEnd(line=10)]
    stream = list(planner.plan_all(prog, machine))
    io_cycles = [i for i, sp in enumerate(stream)
                 if any(isinstance(e, DigitalOutput | AnalogOutput) for e in sp.events)]
    assert len(io_cycles) == 4
    for i in io_cycles:
        ev = next(e for e in stream[i].events if isinstance(e, DigitalOutput | AnalogOutput))
        if ev.synced:  # on the first cycle of a motion: at rest before, moving after
            assert stream[i].positions == pytest.approx(stream[i - 1].positions, abs=1e-6)
            assert stream[i + 1].positions != stream[i].positions
    expect = [("coil", 1, (1,)), ("coil", 0, (1,)), ("holding_register", 0, (150,)), ("coil", 0, (0,))]
    in_time(lambda: replay(sim, stream, machine.cycle_s, io_cycles, expect), machine.cycle_s)
