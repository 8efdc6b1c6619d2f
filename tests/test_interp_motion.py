"""Motion and coordinates: G0/G1/G2/G3, units, offsets, G10, G92, G28/G30, G53, polar, rotation."""

from __future__ import annotations

import math

import pytest
from test_interp_helpers import error, last_end, run, xyz

from gcode_canon.commands import ArcFeed, Plane
from gcode_canon.interpreter import Interpreter
from gcode_canon.settings import InterpreterSettings


def arcs(text: str) -> list[ArcFeed]:
    return [c for c in run(text) if isinstance(c, ArcFeed)]


def test_g0_g1_absolute_and_incremental() -> None:
    assert last_end("G0 X1 Y2 Z3 A45") == xyz(1, 2, 3, 45)
    assert last_end("G91 G0 X1\nX1\nY-2") == xyz(2, -2)
    assert last_end("G1 F100 U1 V2 W3") == xyz(0, 0, 0, 0, 0, 0, 1, 2, 3)


def test_inch_programs_are_converted_to_mm_but_rotary_axes_are_not() -> None:
    assert last_end("G20 G0 X1 Y-0.5 A90") == xyz(25.4, -12.7, 0, 90)


def test_feed_emitted_only_when_it_changes_and_in_mm() -> None:
    out = run("G1 X1 F100\nG1 X2 F100\nG1 X3 F200\nG20 F10")
    assert [c.rate for c in out if c.NAME == "SET_FEED_RATE"] == [100, 200, pytest.approx(254)]


def test_arc_radius_mismatch_error() -> None:
    err = error("G0 X0 Y0\nG2 X10 Y0 I4 F100")
    assert "Radius to end of arc differs from radius to start" in err.message and err.line == 2


def test_arc_small_radius_mismatch_tolerated() -> None:
    assert len(arcs("G2 X10.01 Y0 I5 F100")) == 1


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("G2 X1 F1", "R, I, J or K words missing"),
        ("G2 X1 R1 I1 F1", "Mixed radius-ijk"),
        ("G2 X10 R2 F1", "too small to reach end point"),
        ("G2 R5 F1", "same as end point"),
        ("G2 X1 I0 J0 F1", "Zero-radius"),
        ("G2 X2 I1 K1 F1", "K word given for arc in G17"),
        ("G18 G2 X2 I1 J1 F1", "J word given for arc in G18"),
        ("G2 X2 I1 P0 F1", "at least 1"),
        ("G2 X2 I1 P1.5 F1", "integer"),
        ("G2 X2 I1", "zero feed rate"),
    ],
)
def test_arc_errors(text: str, words: str) -> None:
    assert words in error(text).message


def test_r_arcs_short_and_long_way() -> None:
    short = arcs("G2 X10 Y0 R10 F1")[0]
    assert short.center.x == pytest.approx(5)
    assert short.center.y == pytest.approx(-math.sqrt(75))  # clockwise short: centre to the right
    long = arcs("G2 X10 Y0 R-10 F1")[0]
    assert long.center.y == pytest.approx(math.sqrt(75))
    ccw = arcs("G3 X10 Y0 R10 F1")[0]
    assert ccw.center.y == pytest.approx(math.sqrt(75)) and ccw.turns == 1


def test_full_circle_helix_with_turns() -> None:
    arc = arcs("G0 X1 Y1 Z5\nG3 I2 J0 Z0 P3 F100")[0]
    assert arc.end == xyz(1, 1, 0) and arc.turns == 3
    assert arc.center == xyz(3, 1, 5)  # centre at the start's height on the normal axis


def test_planes() -> None:
    xz = arcs("G18 G3 X2 Z0 I1 F1")[0]
    assert xz.plane is Plane.XZ and xz.center.x == 1
    yz = arcs("G19 G2 Y2 Z0 J1 F1")[0]
    assert yz.plane is Plane.YZ and yz.center.y == 1 and yz.turns == -1


def test_g5x_offsets_and_g10_l2_incremental() -> None:
    assert last_end("G10 L2 P3 X10 Y10\nG56 G0 X1 Y1") == xyz(11, 11)
    assert last_end("G10 L2 P1 X10\nG91 G10 L2 P1 X5\nG90 G0 X0") == xyz(5)  # G91: no effect
    assert last_end("G10 L2 P0 Z-5\nG0 Z0") == xyz(0, 0, -5)
    assert "out of range" in error("G10 L2 P10 X1").message
    assert "without offsets has no effect" in error("G10 L1 P1").message


def test_coordinate_rotation() -> None:
    end = last_end("G10 L2 P1 X10 R90\nG0 X1 Y0")
    assert end[:2] == pytest.approx((10, 1))


def test_g10_l20() -> None:
    assert last_end("G0 X5 Y5\nG10 L20 P1 X0 Y0\nG0 X1 Y1") == xyz(6, 6)
    assert last_end("G0 X5 Y5\nG91 G10 L20 P1 X1\nG90 G0 X0 Y0") == xyz(4, 0)  # G91: no effect
    # another system: Y not given keeps what G55 calls the current Y (offset 0 there)
    assert last_end("G0 X5 Y5\nG10 L20 P2 X1\nG55 G0 X0 Y0") == xyz(4, 0)
    end = last_end("G10 L2 P1 R90\nG0 X1 Y0\nG10 L20 P1 X0 Y0\nG0 X1 Y0")
    assert end[:2] == pytest.approx((0, 2))  # new origin at (0, 1); X1 in the rotated system is +Y
    assert "R not allowed" in error("G10 L20 P1 R10").message


def test_g92_family_and_parameters() -> None:
    interp = Interpreter(InterpreterSettings(require_program_end=False))
    out = run("G0 X10\nG92 X0\nG0 X1", interp)
    assert out[-1].end.x == 11
    assert interp.params.get_numbered(5211) == 10 and interp.params.get_numbered(5210) == 1
    out = run("G92.2\nG0 X1", interp)
    assert out[-1].end.x == 1 and interp.params.get_numbered(5211) == 10
    out = run("G92.3\nG0 X1", interp)
    assert out[-1].end.x == 11
    out = run("G92.1\nG0 X1", interp)
    assert out[-1].end.x == 1 and interp.params.get_numbered(5211) == 0


def test_g28_g30() -> None:
    interp = Interpreter(InterpreterSettings(require_program_end=False))
    out = run("G0 X1 Y2 Z3\nG30.1\nG0 X9 Y9 Z9\nG30", interp)
    assert out[-1].end == xyz(1, 2, 3)
    assert interp.params.get_numbered(5181) == 1
    out = run("G0 X5 Y5 Z5\nG30 Z7", interp)
    assert [c.end for c in out[-2:]] == [xyz(5, 5, 7), xyz(5, 5, 3)]
    assert last_end("G0 X5\nG28") == xyz(0)


def test_g53_machine_coordinates() -> None:
    assert last_end("G10 L2 P1 X100\nG0 X1\nG53 G0 X2\nG0 Y1") == xyz(2, 1)
    assert last_end("G10 L2 P1 X100\nG53 G1 X2 F1\nG0 X0") == xyz(100)


def test_polar_coordinates() -> None:
    assert last_end("G1 F1 @1 ^90")[:2] == pytest.approx((0, 1))
    end = last_end("G1 F1 @.5 ^90\nG91 @.5 ^90")
    assert end[:2] == pytest.approx((-1, 0))
    assert "indeterminate" in error("G91 G1 F1 @1").message
    assert "polar" in error("G1 F1 @1 X1").message
    assert "G53" in error("G53 G0 @1").message
    assert "G92" in error("G92 @1").message
    assert last_end("G0 X1\nG1 F1 G4 P1 @2 ^0") == xyz(2)  # G4 and a polar move share a line


def test_tool_length_offset_from_g43_1() -> None:
    out = run("G43.1 Z2\nG0 Z0\nG49\nG0 Z0")
    assert [c.end.z for c in out if c.MOVES] == [2, 0]
    assert "two G codes" in error("G43.1 G0 Z1").message


def test_probe_trips_and_sets_parameters() -> None:
    interp = Interpreter(InterpreterSettings(require_program_end=False))
    out = run("G38.2 Z-10 F100\n#1 = #5063\n#2 = #5070", interp)
    assert out[-1].NAME == "STRAIGHT_PROBE"
    assert interp.params.get_numbered(1) == -10 and interp.params.get_numbered(2) == 1
    assert "zero length" in error("G38.2 Z0 F10").message


def test_huge_coordinates_refused() -> None:
    big = "9" * 308  # finite as a number, infinite once converted from inches
    assert "out of range" in error(f"G20 G0 X{big}", max_line_length=1000).message
    assert "out of range" in error(f"G20 G1 F1 X{big}", max_line_length=1000).message
    assert "out of range" in error(f"G0 X{big}\nG91 G0 X{big}", max_line_length=1000).message


def test_fast_path_keeps_other_axes_and_offsets() -> None:
    out = run("G0 A10 W2\nG0 X1\nG10 L2 P1 A5 Z1\nX2\nG0 X3 A3\nX4\nG43.1 Z2\nX5\nG49 G20\nX1")
    moves = [c.end for c in out if c.MOVES]
    assert moves == [xyz(0, 0, 0, 10, 0, 0, 0, 0, 2), xyz(1, 0, 0, 10, 0, 0, 0, 0, 2),
                     xyz(2, 0, 0, 10, 0, 0, 0, 0, 2), xyz(3, 0, 0, 8, 0, 0, 0, 0, 2),
                     xyz(4, 0, 0, 8, 0, 0, 0, 0, 2), xyz(5, 0, 0, 8, 0, 0, 0, 0, 2),
                     xyz(25.4 + 1 - 1 + 0, 0, 0, 8, 0, 0, 0, 0, 2)]


def test_words_for_axes_the_machine_lacks() -> None:
    assert last_end("G0 X1 Y2 Z3", axes="xyz") == xyz(1, 2, 3)
    err = error("G0 X1\nG0 A10", axes="xyz")
    assert "no A axis" in err.message and err.line == 2
    assert "no X or Y axis" in error("G0 @1", axes="xz").message
    assert "no Y axis" in error("G0 X1 Y1", axes="xz").message  # the fast path checks too
    assert last_end("G0 X1 Z2", axes="xz") == xyz(1, 0, 2)
