"""gcode-canon extensions wired into the interpreter: G15/G16, G22/G23, G50/G51, G68/G69, G12/G13,
and where the dialect changes their meaning (golden program: tests/programs/extensions.ngc)."""

from __future__ import annotations

import math

import pytest

from gcode_canon.commands import ArcFeed, StraightFeed, StraightTraverse
from gcode_canon.errors import GCodeError
from gcode_canon.interpreter import Interpreter
from gcode_canon.settings import InterpreterSettings


def moves(text: str, dialect: str = "linuxcnc") -> list:
    interp = Interpreter(InterpreterSettings(dry_run=True, dialect=dialect))
    kinds = StraightFeed | StraightTraverse | ArcFeed
    return [c for c in interp.run_string(text, "x.ngc") if isinstance(c, kinds)]


def test_polar_origin_depends_on_the_dialect() -> None:
    text = "G0 X3 Y4\nG16\nG1 X2 Y90 F10\nM2\n"
    fanuc = moves(text)[-1].end[:2]
    canon = moves(text, "gcode-canon")[-1].end[:2]
    assert fanuc == pytest.approx((0, 2))  # from the origin (G90)
    assert canon == pytest.approx((3, 6))  # from the current position


def test_mirror_swaps_arc_direction_and_incremental_g22() -> None:
    # gcode-canon's example: G91 G22 X10 mirrors about the line 10 away from the current position
    # (X1: the line X11); the machine stays at X1, which is now programmed X21
    out = moves("G0 X1\nG91 G22 X10\nG90 G2 X21 Y2 I0 J1 F10\nG1 X19\nM2\n")
    arc = out[1]
    assert arc.turns == 1  # G2 mirrored in X becomes counter-clockwise
    assert arc.end[:2] == pytest.approx((1, 2)) and arc.center[:2] == pytest.approx((1, 1))
    assert out[2].end[:2] == pytest.approx((3, 2))  # programmed 2 less moves the machine 2 more


def test_machine_does_not_move_when_a_transform_changes() -> None:
    interp = Interpreter(InterpreterSettings(dry_run=True))
    list(interp.run_string("G0 X4 Y2\nG51 X0 Y0 P2\n#1=#5420\nG68 X0 Y0 R90\n#2=#5421\nG0 X0 Y0\nM2\n"))
    assert interp.parameter(1) == pytest.approx(2.0)  # the same point, programmed in the scaled frame
    assert interp.parameter(2) == pytest.approx(-2.0)  # rotated back: (1, -2)


def test_scale_per_axis_and_rotation_centre() -> None:
    out = moves("G51 X0 Y0 I2 J3\nG0 X1 Y1\nG50\nG68 X10 Y0 R180\nG0 X12 Y0\nM2\n")
    assert out[0].end[:2] == pytest.approx((2, 3))
    assert out[1].end[:2] == pytest.approx((8, 0))


def test_full_circle_with_tool_radius_and_g12_direction() -> None:
    text = "G0 X10 Y10\nG12 I5 F100\nM2\n"
    lead_in, arc, lead_out = moves(text)[1:]
    assert lead_in.end[:2] == (15, 10) and arc.turns == -1 and arc.center[:2] == (10, 10)
    assert lead_out.end[:2] == (10, 10)


def test_resets_and_errors() -> None:
    out = moves("G51 P2\nM2\n")
    assert out == []
    with pytest.raises(GCodeError, match="G51 needs P"):
        moves("G51 X0\nM2\n")
    with pytest.raises(GCodeError, match="G22 needs the axis words"):
        moves("G22\nM2\n")
    with pytest.raises(GCodeError, match="radius"):
        moves("F1\nG13\nM2\n")
    with pytest.raises(GCodeError, match="cutter radius compensation on"):
        moves("G41.1 D2\nG68 R10\nM2\n")


def test_after_m2_the_transforms_are_gone() -> None:
    interp = Interpreter(InterpreterSettings(dry_run=True))
    list(interp.run_string("G68 R90\nG22 X1\nG16\nM2\n"))
    out = list(interp.run_string("G0 X1 Y1\nM2\n"))
    assert math.isclose(out[0].end[0], 1) and math.isclose(out[0].end[1], 1)


def test_cutter_compensation_on_the_transformed_path() -> None:
    """G41 under G22 X mirroring: the mirror swaps the side (Fanuc), so the tool stays on the
    programmed side of the mirrored contour; G68 rotates the compensated path rigidly."""
    plain = moves("F1\nG0 X-10\nG41.1 D2 G1 X0\nX10\nG40 G1 X10 Y-10\nM2\n")
    mirrored = moves("F1\nG22 X0\nG0 X-10\nG41.1 D2 G1 X0\nX10\nG40 G1 X10 Y-10\nM2\n")
    # going +X with G41 the tool is at Y+1; mirrored in X the path goes -X and the tool still at Y+1
    assert [m.end[1] for m in plain[1:3]] == pytest.approx([1, 1])
    assert [m.end[:2] for m in mirrored[1:3]] == [pytest.approx((0, 1)), pytest.approx((-10, 1))]
    rotated = moves("F1\nG68 X0 Y0 R90\nG0 X-10\nG41.1 D2 G1 X0\nX10\nG40 G1 X10 Y-10\nM2\n")
    # rotated by 90 degrees: (x, y) -> (-y, x)
    assert [m.end[:2] for m in rotated[1:3]] == [pytest.approx((-1, 0)), pytest.approx((-1, 10))]
