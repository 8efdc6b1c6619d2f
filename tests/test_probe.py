"""Probing G38.2-G38.5: the Probe command, the machine's answer, #5061-#5070 in program units."""

from __future__ import annotations

import pytest

from gcode_canon.commands import Pose, Probe, ProbeMode
from gcode_canon.errors import GCodeError
from gcode_canon.interpreter import Interpreter
from gcode_canon.machine import DryRunMachine
from gcode_canon.settings import InterpreterSettings


class Machine(DryRunMachine):
    def __init__(self, where: Pose, tripped: bool) -> None:
        super().__init__()
        self.answer = (where, tripped)
        self.asked: list[Probe] = []

    def probe(self, cmd: Probe) -> tuple[Pose, bool]:
        self.asked.append(cmd)
        return self.answer


def test_probe_results_in_program_frame_and_units() -> None:
    # G54 offset X10 (mm); the probe trips at machine X 35.4 mm = program X 25.4 mm = 1 inch
    machine = Machine(Pose(35.4, 0, 0), True)
    interp = Interpreter(InterpreterSettings(dry_run=True), machine)
    cmds = list(interp.run_string("G10 L2 P1 X10\nG54 G20 F10\nG38.2 X2\nG0 Y[#5061 + #5070]\nM2\n"))
    probe = next(c for c in cmds if isinstance(c, Probe))
    assert probe.mode is ProbeMode.TOWARD_ERROR and probe.end.x == pytest.approx(10 + 50.8)
    assert interp.parameter(5061) == pytest.approx(1.0) and interp.parameter(5070) == 1.0
    assert interp.position.y == pytest.approx(2 * 25.4)  # Y = #5061 + #5070 = 2 inches


@pytest.mark.parametrize(("code", "must_trip"), [("G38.2", True), ("G38.3", False), ("G38.4", True),
                                                 ("G38.5", False)])
def test_a_probe_that_does_not_trip(code: str, must_trip: bool) -> None:
    machine = Machine(Pose(0, 0, -5), False)
    interp = Interpreter(InterpreterSettings(dry_run=True), machine)
    text = f"F100\n{code} Z-5\nM2\n"
    if must_trip:
        with pytest.raises(GCodeError, match="without making contact") as info:
            list(interp.run_string(text, "p.ngc"))
        assert info.value.line == 2
    else:
        list(interp.run_string(text, "p.ngc"))
        assert interp.parameter(5070) == 0.0 and interp.parameter(5063) == -5.0


def test_probe_with_zero_length_or_no_feed_is_an_error() -> None:
    with pytest.raises(GCodeError, match="zero length"):
        list(Interpreter(InterpreterSettings(dry_run=True)).run_string("F10\nG38.2 Z0\nM2\n"))
    with pytest.raises(GCodeError, match="zero feed"):
        list(Interpreter(InterpreterSettings(dry_run=True)).run_string("G38.2 Z1\nM2\n"))
    with pytest.raises(GCodeError, match="inverse time"):
        list(Interpreter(InterpreterSettings(dry_run=True)).run_string("G93 G38.2 Z1 F1\nM2\n"))
    with pytest.raises(GCodeError, match="rotary axes"):
        list(Interpreter(InterpreterSettings(dry_run=True)).run_string("F1\nG38.2 Z1 A3\nM2\n"))
