"""Canned cycles wired into the interpreter: incremental mode with L repeats, inch units, G19, the
motion mode and G80, the fast path. (The expansion rules: test_cycles.py; golden: cycles*.ngc.)"""

from __future__ import annotations

import pytest

from gcode_canon.commands import StraightFeed, StraightTraverse
from gcode_canon.errors import GCodeError
from gcode_canon.interpreter import Interpreter
from gcode_canon.settings import InterpreterSettings


def path(text: str) -> list[tuple]:
    out = Interpreter(InterpreterSettings(dry_run=True)).run_string(text + "\nM2\n", "c.ngc")
    return [("G0" if isinstance(c, StraightTraverse) else "G1", *(round(v, 6) for v in c.end[:3]))
            for c in out if isinstance(c, StraightTraverse | StraightFeed)]


def test_incremental_with_repeats() -> None:
    # G91: R is 8 below the initial level Z10 (R = 2), Z 4 below R (-2); each repeat moves X by 5
    got = path("F100\nG0 Z10\nG91 G98 G81 X5 Z-4 R-8 L3")
    holes = [("G0", x, 0, 10) for x in (5, 10, 15)]
    want = [("G0", 0, 0, 10)]
    for _, x, _, _ in holes:
        want += [("G0", x, 0, 10), ("G0", x, 0, 2), ("G1", x, 0, -2), ("G0", x, 0, 10)]
    assert got == want


def test_inch_units_and_yz_plane() -> None:
    got = path("G20 F1\nG0 Z1\nG98 G81 X1 Y0 Z-0.1 R0.1")
    assert got[1:] == [("G0", 25.4, 0, 25.4), ("G0", 25.4, 0, 2.54), ("G1", 25.4, 0, -2.54),
                       ("G0", 25.4, 0, 25.4)]
    # G19: drill axis X, hole position Y Z
    got = path("F1\nG19 G0 X5\nG99 G81 Y1 Z2 X-1 R1")
    assert got[1:] == [("G0", 5, 1, 2), ("G0", 1, 1, 2), ("G1", -1, 1, 2), ("G0", 1, 1, 2)]


def test_motion_mode_sticks_until_g80_and_plain_lines_after() -> None:
    got = path("F1\nG0 Z5\nG99 G81 X1 Z-1 R1\nX2\nG80\nG0 X0\nX3 Y3")
    assert ("G1", 2, 0, -1) in got
    assert got[-2:] == [("G0", 0, 0, 1), ("G0", 3, 3, 1)]
    with pytest.raises(GCodeError, match="G80"):
        path("F1\nG80 X1")


def test_errors_have_the_line() -> None:
    with pytest.raises(GCodeError) as info:
        path("F1\nG0 Z5\nG81 X1 Z-1")
    assert info.value.line == 3 and "R" in info.value.message
    with pytest.raises(GCodeError, match="G76"):
        path("G76 X1")
    with pytest.raises(GCodeError, match="Spindle not turning in G87") as info:  # G87 runs now (M19)
        path("F1\nG0 Z5\nG87 X1 Z-1 R1 I0.5 J0 K0")
    assert info.value.line == 3
