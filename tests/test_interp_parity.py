"""LinuxCNC parity: the differences measured against LinuxCNC's own interpreter (rs274), each with the
value LinuxCNC gives (worked out from its source: interp_*.cc, emccanon.cc, and its documentation)."""

from __future__ import annotations

import pytest

from tests.test_interp_helpers import last_end, run, xyz

# --- G53, G28, G30 with a tool length offset (find_ends, find_relative, convert_savehome) ------------


def test_g53_goes_to_machine_position_whatever_the_tool_offset() -> None:
    # find_ends: z = Z - origin - axis - tool in program terms; emccanon adds all back: machine Z0
    assert last_end("G43.1 Z5\nG53 G0 Z0") == xyz(0, 0, 0)
    assert last_end("G10 L2 P1 Z7\nG43.1 Z5\nG0 Z1\nG53 G1 Z-2 F100") == xyz(0, 0, -2)
    # then the program coordinate reads machine - G5x - tool
    out = run("G43.1 Z5\nG53 G0 Z0\nG0 X1")
    assert tuple(out[-1].end)[:3] == (1.0, 0.0, 0.0)


def test_g28_g30_go_to_the_stored_machine_position_without_the_tool_offset() -> None:
    assert last_end("#5163 = 10\nG43.1 Z5\nG28") == xyz(0, 0, 10)
    assert last_end("#5183 = -3\nG43.1 Z5\nG30 Z0") == xyz(0, 0, -3)


def test_g28_1_stores_the_machine_position_tool_offset_included() -> None:
    # convert_savehome: current + tool + origin + axis offsets (program Z1 + tool 5 = machine 6)
    from gcode_canon.interpreter import Interpreter
    from gcode_canon.settings import InterpreterSettings

    interp = Interpreter(InterpreterSettings(dry_run=True, require_program_end=False))
    list(interp.run_string("G43.1 Z5\nG0 Z1\nG28.1\nG30.1", "t.ngc"))
    assert interp.parameter(5163) == pytest.approx(6.0)
    assert interp.parameter(5183) == pytest.approx(6.0)
    assert last_end("G43.1 Z5\nG0 Z1\nG28.1\nG49\nG0 Z0\nG28") == xyz(0, 0, 6)


# --- M6 stops the spindle (convert_tool_change, TOOL_CHANGE_WITH_SPINDLE_ON = 0) ------------------------


def test_m6_stops_the_spindle_before_the_change() -> None:
    from gcode_canon.commands import SpindleOff, ToolChange

    out = run("S1000 M3\nT1 M6")
    kinds = [type(c) for c in out]
    assert kinds.index(SpindleOff) < kinds.index(ToolChange)
    # the tap cycle then finds the spindle stopped, as LinuxCNC does
    from tests.test_interp_helpers import error

    assert "Spindle not turning" in error("S1000 M3\nT1 M6\nG0 Z5\nG84 Z-1 R2 F100").message
    # M6 M3 on one line: the tool change runs first, the spindle starts after it
    out = run("S1000 M3\nT1 M6 M3")
    kinds = [type(c).__name__ for c in out]
    assert kinds[-3:] == ["SpindleOff", "ToolChange", "SpindleOn"]


def test_m6_keeps_the_spindle_when_the_machine_allows_it() -> None:
    from gcode_canon.commands import SpindleOff

    out = run("S1000 M3\nT1 M6", tool_change_with_spindle_on=True)
    assert not any(isinstance(c, SpindleOff) for c in out)


# --- G40, M6, then a move: the position is read back after a tool change (refresh_actual_position) -----


@pytest.mark.parametrize("change", ["T2 M6", "M61 Q2"])
def test_tool_change_after_g40_keeps_the_compensated_position(change: str) -> None:
    # G41 radius 1 along +X: the tool runs at Y1. G40 leaves it there; LinuxCNC's M6/M61 read the
    # position back, so a Z-only move keeps Y1 (without the change it would go back to Y0).
    prog = f"G10 L1 P1 R1\nT1 M6\nF100\nG41\nG1 X10 Y0\nX20\nG40\n{change}\nG0 Z5\n"
    assert last_end(prog) == xyz(20, 1, 5)
    assert last_end("G10 L1 P1 R1\nT1 M6\nF100\nG41\nG1 X10 Y0\nX20\nG40\nG0 Z5\n") == xyz(20, 0, 5)
