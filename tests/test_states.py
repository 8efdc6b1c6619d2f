"""The daemon's state rules: what is accepted where, and that a refusal changes nothing."""

from __future__ import annotations

import pytest

from motiond.states import CommandRefused, MachineStates, Mode, State


def ready() -> MachineStates:
    m = MachineStates()
    m.estop_reset()
    m.enable()
    return m


def test_power_up_is_estop_and_nothing_moves() -> None:
    m = MachineStates()
    assert m.state is State.ESTOP and not m.may_move
    with pytest.raises(CommandRefused, match="while estop"):
        m.start(Mode.AUTO)
    with pytest.raises(CommandRefused, match="while estop"):
        m.enable()


def test_reset_estop_leaves_drives_disabled() -> None:
    m = MachineStates()
    m.estop_reset()
    assert m.state is State.IDLE and not m.enabled
    with pytest.raises(CommandRefused, match="drives are disabled"):
        m.start(Mode.AUTO)
    with pytest.raises(CommandRefused, match="drives are disabled"):
        m.manual("jog")


def test_run_pause_resume_finish() -> None:
    m = ready()
    assert m.start(Mode.AUTO).state is State.RUNNING
    with pytest.raises(CommandRefused, match="while running"):
        m.manual("jog")
    with pytest.raises(CommandRefused, match="while running"):
        m.start(Mode.MDI)
    assert m.pause().state is State.PAUSED
    with pytest.raises(CommandRefused, match="while paused"):
        m.pause()
    assert m.resume().state is State.RUNNING
    assert m.finished().state is State.IDLE
    assert m.enabled


def test_fault_from_anywhere_then_reset_needs_enable() -> None:
    m = ready()
    m.start(Mode.AUTO)
    snap = m.fault("node 2: following error 1.3 mm beyond window 1.0 mm")
    assert snap.state is State.FAULTED and not snap.enabled
    with pytest.raises(CommandRefused, match=r"while faulted \(node 2: following error"):
        m.resume()
    assert m.reset().state is State.IDLE
    assert not m.enabled and m.fault_reason == ""
    m.enable()
    assert m.start(Mode.MDI).mode is Mode.MDI


def test_estop_always_wins_and_a_fault_keeps_estop() -> None:
    m = ready()
    m.start(Mode.AUTO)
    m.pause()
    assert m.estop().state is State.ESTOP
    assert m.fault("heartbeat lost").state is State.ESTOP
    assert m.fault_reason == "heartbeat lost"
    with pytest.raises(CommandRefused):
        m.reset()


def test_refusal_changes_nothing_and_listeners_see_changes() -> None:
    m = ready()
    seen: list[tuple[State, State]] = []
    m.subscribe(lambda before, after: seen.append((before.state, after.state)))
    before = m.snapshot()
    with pytest.raises(CommandRefused):
        m.resume()
    assert m.snapshot() == before
    m.start(Mode.AUTO)
    m.abort()
    assert seen == [(State.IDLE, State.RUNNING), (State.RUNNING, State.IDLE)]


def test_start_manual_mode_is_a_programming_error() -> None:
    with pytest.raises(ValueError):
        ready().start(Mode.MANUAL)
