"""M19 / G87 spindle orientation: the interpreter's SpindleOrient, the planner's sync point, the daemon.

M19 R Q P as the LinuxCNC manual ("M19 Orient Spindle") and its checks (interp_check.cc) say: R the
angle 0..360, Q the seconds to wait (> 0), P 0 shortest way, 1 clockwise, 2 counter-clockwise; M19 is
in the spindle group (7) and leaves the spindle stopped.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from gcode_canon.commands import (
    FeedMode,
    Pose,
    SetFeedMode,
    SetFeedRate,
    SpindleDirection,
    SpindleOff,
    SpindleOn,
    SpindleOrient,
    StraightFeed,
)
from gcode_canon.errors import GCodeError
from gcode_canon.interpreter import Interpreter
from gcode_canon.settings import InterpreterSettings
from motiond.cmd_check import format_text, to_json
from planner import Planner, PlannerError, plan_all


def run(text: str) -> list[Any]:
    interp = Interpreter(InterpreterSettings(dry_run=True, require_program_end=False))
    return list(interp.run_string(text, "o.ngc"))


def orients(text: str) -> list[SpindleOrient]:
    return [c for c in run(text) if isinstance(c, SpindleOrient)]


def test_m19_words() -> None:
    assert orients("M19 R90 Q2.5 P1") == [SpindleOrient(90.0, 1, 2.5, file="o.ngc", line=1)]
    assert orients("M19 R360 P2") == [SpindleOrient(360.0, 2, 0.0, file="o.ngc", line=1)]
    assert orients("M19 R0 P0.0005") == [SpindleOrient(0.0, 0, 0.0, file="o.ngc", line=1)]  # within 0.001
    # defaults: angle 0, shortest way, no wait asked for
    assert orients("M19") == [SpindleOrient(0.0, 0, 0.0, file="o.ngc", line=1)]
    assert SpindleOrient.NAME == "ORIENT_SPINDLE" and SpindleOrient.SYNC


def test_m19_stops_the_spindle_and_m3_starts_it() -> None:
    out = run("S1000 M3\nM19 R45\nM4\n")
    kinds = [type(c) for c in out if isinstance(c, SpindleOn | SpindleOff | SpindleOrient)]
    assert kinds == [SpindleOn, SpindleOrient, SpindleOn]
    # the interpreter knows the spindle is not turning: a G86 (needs it turning) after M19 is refused
    with pytest.raises(GCodeError, match="Spindle not turning in G86"):
        run("S1000 M3 F100\nM19\nG86 X1 Z-1 R1 P1\n")


@pytest.mark.parametrize(("line", "message"), [
    ("M19 R361", "R value must be within 0..360 with M19"),
    ("M19 R-1", "R value must be within 0..360 with M19"),
    ("M19 P3", "P value must be 0, 1 or 2 with M19"),
    ("M19 P-1", "P value must be 0, 1 or 2 with M19"),
    ("M19 P1.5", "P value not an integer with M19"),
    ("M19 Q0", "Q word with M19 requires a value > 0"),
    ("M19 Q-2", "Q word with M19 requires a value > 0"),
    ("G64 M19 R10", "R word is ambiguous on a line with both G64 and M19"),
    ("M3 M19", "Two M codes used from the same modal group: M3 and M19"),
    ("M19 M5", "Two M codes used from the same modal group"),
    ("R10", "R word with no G code that uses it"),
    ("Q1", "Q word with no G or M code that uses it"),
])
def test_m19_errors(line: str, message: str) -> None:
    with pytest.raises(GCodeError, match=message) as info:
        run(f"G0 X1\n{line}\n")
    assert info.value.line == 2


def test_g87_orients_the_way_the_spindle_turns() -> None:
    for m, p in (("M3", 1), ("M4", 2)):
        got = orients(f"S500 {m} F100\nG0 Z5\nG99 G87 X1 Z-3 R1 I0.5 J0 K-1\n")
        assert got == [SpindleOrient(0.0, p, 0.0, file="o.ngc", line=3)] * 2


def test_check_prints_it() -> None:
    cmd = SpindleOrient(45.0, 2, 5.0, line=6)
    assert format_text(cmd) == "ORIENT_SPINDLE(45.0000, 2, 5.0000)"
    assert to_json(cmd) == {"line": 6, "file": "", "command": "ORIENT_SPINDLE", "angle": 45.0,
                            "direction": 2, "timeout": 5.0}


def where(sps: list[Any], cmd: Any) -> list[int]:
    return [i for i, s in enumerate(sps) if any(e is cmd for e in s.events)]


def test_planner_stops_exactly_and_rides_on_the_rest_setpoint() -> None:
    m19 = SpindleOrient(90.0, 1, 2.0, line=3)
    prog = [SetFeedRate(1200), SpindleOn(SpindleDirection.CW, 1000, line=1),
            StraightFeed(Pose(5, 0, 0), line=2), m19, StraightFeed(Pose(5, 5, 0), line=4)]
    sps = list(plan_all(prog))
    (i,) = where(sps, m19)
    assert sps[i].positions == (5.0, 0.0, 0.0)  # exactly on the end of line 2, at rest
    assert sps[i - 1].positions[0] < 5.0  # it is the first cycle at rest
    assert any(s.positions[1] > 0 for s in sps[i + 1:])  # then goes on: it does not wait for release


def test_planner_continues_at_once_and_the_spindle_is_stopped() -> None:
    p = Planner()
    m19 = SpindleOrient(0.0, 0, 0.0)
    p.feed_many([SetFeedRate(600), SpindleOn(SpindleDirection.CW, 1000), StraightFeed(Pose(1, 0, 0)), m19])
    seen = False
    for _ in range(2000):
        sp = p.next_setpoint()
        if sp is None:
            break
        seen = seen or m19 in sp.events
        assert p.waiting_for is None
    assert seen
    # G95 feed per revolution needs a turning spindle: after M19 it has stopped
    with pytest.raises(PlannerError, match="turning spindle"):
        list(plan_all([SpindleOn(SpindleDirection.CW, 1000), SpindleOrient(0.0),
                       SetFeedMode(FeedMode.UNITS_PER_REV), SetFeedRate(0.1), StraightFeed(Pose(1, 0, 0))]))


@pytest.mark.parametrize(("cmd", "message"), [
    (SpindleOrient(0.0, 3, 0.0), "direction must be 0, 1 or 2"),
    (SpindleOrient(0.0, 0, -1.0), "timeout must be >= 0"),
    (SpindleOrient(float("nan"), 0, 0.0), "angle is not a finite number"),
])
def test_planner_refuses_bad_values(cmd: SpindleOrient, message: str) -> None:
    with pytest.raises(PlannerError, match=message):
        Planner().feed(cmd)


def test_daemon_completes_it_at_once_with_an_event(tmp_path: Path) -> None:
    from motiond.config import load_machine
    from motiond.runtime import Machine

    prog = tmp_path / "orient.ngc"
    prog.write_text("G21 G90 S800 M3\nG1 X2 F1200\nM19 R30 Q1 P2\nG0 X4\nM3\n"
                    "G87 X6 Z-1 R1 I0.5 J0 K0 F600\nM2\n")
    machine = Machine(load_machine(None), lc=None, var_file=tmp_path / "p.var")
    seen: list[tuple[str, str, int]] = []
    real = machine.event

    def record(severity: str, text: str, **kw: Any) -> None:
        seen.append((kw.get("kind", ""), text, kw.get("line", 0)))
        real(severity, text, **kw)

    machine.event = record  # type: ignore[method-assign]
    try:
        machine.start()
        machine.bring_up()
        result = machine.wait_job(machine.run(prog), 60.0)
    finally:
        machine.shutdown()
    assert result is not None and result.ok, result and result.error
    orient = [(text, line) for kind, text, line in seen if kind == "spindle_orient"]
    # the demo machine wires spindle_orient and spindle_oriented (docs/wiring.md): M19 waits for it
    assert orient[0] == ("spindle orient to 30 deg (P2): spindle_orient on, waiting for spindle_oriented", 3)
    assert [line for _t, line in orient[1:]] == [6, 6]  # G87's two
