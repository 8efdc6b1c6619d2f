"""MDI lines with a sync point the job answers itself (M66, a simulated probe) finish: the job answers
them before it queues them, so the planner must not stand at them waiting for an answer (it did:
the MDI job stayed RUNNING for ever)."""

from __future__ import annotations

import pytest

from motiond.config import load_machine
from motiond.runtime import Machine


@pytest.fixture(scope="module")
def machine():
    m = Machine(load_machine(None)).start()
    try:
        m.bring_up()
        yield m
    finally:
        m.shutdown()


@pytest.mark.parametrize("line", ["M66 P0 L0", "G38.2 Z-5 F600", "G0 Z0\nG38.3 Z-3 F600"])
def test_mdi_sync_points_finish(machine: Machine, line: str) -> None:
    for text in line.split("\n"):
        job = machine.mdi(text)
        result = machine.wait_job(job, timeout=30)
        assert result is not None, f"MDI {text!r} never finished"
        assert result.ok, result.error
    job = machine.mdi("G0 Z0")  # and the machine takes the next line
    assert machine.wait_job(job, timeout=30) is not None


def test_a_gcode_error_in_mdi_is_refused_not_a_fault(machine: Machine) -> None:
    """An MDI line is interpreted whole before any of it is queued: its error moved nothing, so the
    machine stays IDLE and enabled (it faulted, and needed a reset, for a typo)."""
    from motiond.states import State

    job = machine.mdi("G1 X10 F0")
    result = machine.wait_job(job, timeout=30)
    assert result is not None and not result.ok and "zero feed rate" in result.error
    assert machine.states.state is State.IDLE and machine.last_error.endswith("zero feed rate")
    job = machine.mdi("G0 X1")
    assert machine.wait_job(job, timeout=30).ok


def test_a_finished_job_finds_the_machine_idle(machine: Machine, monkeypatch: pytest.MonkeyPatch) -> None:
    """``wait_job`` returns once the machine is in the state the job's end brings: a client sending the
    next MDI line right after it was refused "while running" (the job was marked done before the state
    went back to IDLE; a slow state change here widens that window to make it certain)."""
    import time

    from motiond.states import State

    finished = machine.states.finished

    def slow_finished() -> None:
        time.sleep(0.3)
        finished()

    monkeypatch.setattr(machine.states, "finished", slow_finished)
    result = machine.wait_job(machine.mdi("G0 X2"), timeout=30)
    assert result is not None and result.ok, result
    assert machine.states.state is State.IDLE
    assert machine.wait_job(machine.mdi("G0 X0"), timeout=30).ok
