"""G5, G5.1, G5.2/G5.3: LinuxCNC's splines as arcs and lines (gcode_canon/splines.py).

The expected curves are worked out here from their definitions (a clamped B-spline with as many
control points as its order is the Bezier curve of those points; a rational quadratic with the
middle weight cos(45 deg) is a quarter circle), not from canon's output; the differential test
against rs274 checks where the moves leave the tool and what LinuxCNC accepts."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from gcode_canon.commands import ArcFeed, Plane, StraightFeed
from tests import rs274_oracle as oracle
from tests.test_interp_helpers import error, run


def _moves(text: str) -> list:
    return [c for c in run(text) if isinstance(c, (ArcFeed, StraightFeed))]


def _bezier(points: list[tuple[float, float]], t: float) -> tuple[float, float]:
    n = len(points) - 1
    x = y = 0.0
    for i, (px, py) in enumerate(points):
        b = math.comb(n, i) * t ** i * (1 - t) ** (n - i)
        x, y = x + b * px, y + b * py
    return x, y


def _check_chain(moves: list, start: tuple[float, float], axes: tuple[int, int]) -> None:
    """Every arc starts and ends on its circle; each move starts where the last ended."""
    here = start
    for mv in moves:
        end = (mv.end[axes[0]], mv.end[axes[1]])
        if isinstance(mv, ArcFeed):
            c = (mv.center[axes[0]], mv.center[axes[1]])
            assert math.dist(c, here) == pytest.approx(math.dist(c, end), rel=1e-9, abs=1e-9)
        here = end


def test_g5_1_is_the_quadratic_bezier_sampled_12_times_joined_by_biarcs() -> None:
    moves = _moves("G17 G21 F100\nG0 X1 Y2 Z3\nG5.1 X11 Y2 I4 J6")
    control = [(1.0, 2.0), (5.0, 8.0), (11.0, 2.0)]
    # 3 control points: 12 samples, each joined by two arcs (no straight pieces on this curve)
    assert len(moves) == 24 and all(isinstance(m, ArcFeed) for m in moves)
    for i in range(1, 13):  # every second arc ends on a sample of the curve
        assert (moves[2 * i - 1].end[0], moves[2 * i - 1].end[1]) == pytest.approx(_bezier(control, i / 12))
    assert all(m.end[2] == 3.0 for m in moves)  # the other axes stay
    _check_chain(moves, (1.0, 2.0), (0, 1))
    # the curve bends clockwise (to the right of its way) all along
    assert all(m.turns == -1 for m in moves)


def test_g5_is_the_cubic_bezier_and_continues_smoothly_without_i_j() -> None:
    moves = _moves("G21 F100\nG5 X10 Y0 I2 J4 P-3 Q5\nG5 X20 Y0 P-2 Q-3")
    control = [(0.0, 0.0), (2.0, 4.0), (7.0, 5.0), (10.0, 0.0)]
    ends = [m.end[:2] for m in moves]
    for i in range(1, 17):  # 4 control points: 16 samples
        assert any(e == pytest.approx(_bezier(control, i / 16)) for e in ends[:40])
    # the second G5 starts with the mirror of the first's last control point: -P -Q = (3, -5)
    second = [(10.0, 0.0), (13.0, -5.0), (18.0, -3.0), (20.0, 0.0)]
    assert any(e == pytest.approx(_bezier(second, 0.5)) for e in ends)
    assert ends[-1] == pytest.approx((20.0, 0.0))
    _check_chain(moves, (0.0, 0.0), (0, 1))


def test_g5_2_rational_quarter_circle_is_arcs_on_that_circle() -> None:
    w = math.cos(math.radians(45))
    moves = _moves(f"G21 F100\nG0 X10 Y0\nG5.2 X10 Y10 P{w:.15f}\nX0 Y10 P1\nG5.3\nG1 X0 Y0")
    arcs = moves[:-1]
    assert arcs and all(isinstance(m, ArcFeed) for m in arcs)
    for k, m in enumerate(arcs):  # a circle's biarcs are the circle itself: centre (0, 0), radius 10
        # (the first and last two within 2 um: LinuxCNC's tangent is one-sided at the curve's ends)
        ends = k < 2 or k >= len(arcs) - 2
        assert m.center[:2] == pytest.approx((0.0, 0.0), abs=2e-3 if ends else 1e-6)
        assert math.hypot(m.end[0], m.end[1]) == pytest.approx(10.0, abs=1e-5 if ends else 1e-9)
        assert m.turns == 1
    assert arcs[-1].end[:2] == pytest.approx((0.0, 10.0))
    assert moves[-1].end[:2] == pytest.approx((0.0, 0.0))


def test_g5_2_order_and_weights() -> None:
    # L4 with 4 points is the cubic Bezier; weights all 1
    moves = _moves("G21 F100\nG5.2 X0 Y10 P1 L4\nX10 Y10 P1\nX10 Y0 P1\nG5.3")
    control = [(0.0, 0.0), (0.0, 10.0), (10.0, 10.0), (10.0, 0.0)]
    ends = [m.end[:2] for m in moves]
    for i in range(1, 17):
        assert any(e == pytest.approx(_bezier(control, i / 16)) for e in ends)
    # a first line with P alone weighs the start point: a heavier start pulls the curve toward it
    light = _moves("G21 F100\nG5.2 X0 Y10 P1\nX10 Y0 P1\nG5.3")
    heavy = _moves("G21 F100\nG5.2 P5\nX0 Y10 P1\nX10 Y0 P1\nG5.3")
    mid = len(light) // 2
    assert math.hypot(*heavy[mid].end[:2]) < math.hypot(*light[mid].end[:2])


def test_g5_1_in_g18_takes_i_along_x_and_j_along_z() -> None:
    moves = _moves("G18 G21 F100\nG0 X0 Z0\nG5.1 X10 Z0 I5 J5")
    # LinuxCNC convert_spline: x1 = x + I, z1 = z + J; the plane's coordinates are (Z, X)
    control = [(0.0, 0.0), (5.0, 5.0), (0.0, 10.0)]  # (z, x)
    for i in range(1, 13):
        assert (moves[2 * i - 1].end[2], moves[2 * i - 1].end[0]) == pytest.approx(_bezier(control, i / 12))
    assert all(m.plane is Plane.XZ for m in moves if isinstance(m, ArcFeed))
    _check_chain(moves, (0.0, 0.0), (2, 0))


def test_g20_scales_every_word() -> None:
    inch = _moves("G20 F10\nG5.1 X1 Y0 I0.5 J0.5")
    mm = _moves("G21 F100\nG5.1 X25.4 Y0 I12.7 J12.7")
    assert [v for m in inch for v in m.end[:2]] == pytest.approx([v for m in mm for v in m.end[:2]])


@pytest.mark.parametrize(("text", "message"), [
    ("F100\nG5.1 X1 Y1 I1", "Must specify both I and J with G5.1"),
    ("F100\nG5 X1 Y1 I1 J1 P1", "Must specify both P and Q with G5"),
    ("F100\nG5 X1 Y1 I1 P1 Q1", "Must specify both I and J, or neither"),
    ("G5.1 X1 Y1 I1 J1", "Cannot make arc with zero feed rate"),
    ("F100\nG5.1 X1 Y1 A3 I1 J1", "Splines may not have motion in A, B, or C"),
    ("F100\nG5.3", "Cannot use G5.3 without G5.2 first"),
    ("F100\nG5.2 X1 Y1 P1\nX2 Y0 P1\nX3 Y0 P1 L5\nG5.3", "at least equal to the order L = 5"),
    ("F100\nG5.2 X1 Y1 P1\nX2 P1", "You must specify both X and Y coordinates"),
    ("F100\nG5.2 X1 Y1 P1\nX2 Y2", "Must specify positive weight P"),
    ("F100\nG5.2 X1 Y1 P1\nP2", "P word with no G or M code"),
    ("F100\nG5.2 X1 Y1 P1\nG5.2 P2", "Can specify P without X and Y only for the first"),
    ("F100\nG5.1 X1 Y1 I1 J1 K1", "K word"),
    ("F100\nG5.1 X1 Y1 I1 J1 Q1", "Q word"),
    ("F100\nG1 X1 Y1 L3", "L word"),
    ("G93\nG5.1 X1 Y1 I1 J1 F3", "inverse time"),
    ("F100 T1 M6\nG41 D1\nG1 X5\nG5.1 X1 Y1 I1 J1", "Cannot convert spline with cutter radius compensation"),
])
def test_refusals(text: str, message: str) -> None:
    assert message in str(error(text, tool_table=None))


# --- against LinuxCNC's rs274 ---------------------------------------------------------------------

BINARY = oracle.rs274_binary()


@pytest.mark.rs274
@pytest.mark.skipif(BINARY is None, reason=f"rs274 is not built in {oracle.rs274_dir()}")
@pytest.mark.parametrize("program", [
    "G21 F100\nG0 X1 Y2 Z3\nG5.1 X11 Y2 I4 J6\nG1 X0\nG5 X10 Y0 I2 J4 P-3 Q5\nG5 X20 Y0 I3 J-5 P-2 Q-3"
    "\nG1 Y5\nM2",
    "G21 F100\nG0 X10 Y0\nG5.2 X10 Y10 P0.7\nX0 Y10 P1\nX0 Y0 P2 L3\nG5.3\nG1 X3\nG91 G5.2 X1 Y1 P1\nX2 Y0 P1"
    "\nX3 Y1 P1 L4\nG5.3\nG90 G1 X0 Y0\nM2",
    "G18 G21 F100\nG0 X1 Z1\nG5.1 X5 Z3 I1 J2\nG1 Y2\nG19 G5.1 Y3 Z5 I2 J1\nG1 X0\nG18 G5.2 X4 Z4 P1"
    "\nX0 Z4 P1\nG5.3\nG1 X1\nM2",
    "G20 F10\nG10 L2 P1 X1 R30\nG0 X0 Y0\nG5.1 X1 Y1 I0.5 J0\nG1 X2\nG5 X3 Y2 I0 J1 P1 Q0\nG1 Y0\nM2",
    "G21 F100\nG5.2 X1 Y1\nX2 Y2 P1\nX3 Y0 P1\nX5 Y3 P1\nG5.3\nG1 X0\nM2",
    "G21 F100\nG0 X1\nG5.2 X5 Y5 P-0.5\nX10 Y5 P1\nX15 Y0 P2 L3\nG5.3\nG1 X0\nG5.2 X1 Y1 P0\nX2 Y2 P1"
    "\nX3 Y0 P1\nG5.3\nG1 Y4\nM2",
    "G21 F100\nG5.2 X1 Y1 P1\nX2 Y2\nX3 Y0 P1\nG5.3\nM2",
    "G21 F100\nG5.1 X1 Y1 I1\nM2",
    "G21 F100\nG5.3\nM2",
])
def test_against_rs274(program: str, tmp_path: Path) -> None:
    assert BINARY is not None
    theirs, ours = oracle.run_program(program, tmp_path, BINARY)
    assert oracle.compare(theirs, ours) is None
    assert sum(m.kind == "nurbs" for m in theirs.moves) == sum(m.kind == "nurbs" for m in ours.moves)


def test_a_first_nurbs_point_without_p_has_linuxcncs_weight_minus_1() -> None:
    """convert_nurbs checks P on every point but the first line's, which takes P as it is: unset, -1."""
    tail = "\nX2 Y2 P1\nX3 Y0 P1\nX5 Y3 P1\nG5.3"
    without = _moves("G21 F100\nG5.2 X1 Y1" + tail)
    assert without and [m.end for m in without] == [m.end for m in _moves("G21 F100\nG5.2 X1 Y1 P-1" + tail)]
    assert [m.end for m in without] != [m.end for m in _moves("G21 F100\nG5.2 X1 Y1 P1" + tail)]
    assert without[-1].end[:2] == pytest.approx((5.0, 3.0))
    # P0 and negative P there likewise; the points after it still need a positive P
    assert _moves("G21 F100\nG5.2 X1 Y1 P0" + tail)[-1].end[:2] == pytest.approx((5.0, 3.0))
    assert "Must specify positive weight P" in str(error("F100\nG5.2 X1 Y1\nX2 Y2 P0", tool_table=None))


def test_a_nurbs_through_infinity_is_refused_with_its_reason() -> None:
    # weights 1, -1, 1, 1 (order 3): the denominator of the rational curve reaches 0 on a sample
    message = str(error("G21 F100\nG5.2 X1 Y1\nX2 Y2 P1\nX3 Y0 P1\nG5.3", tool_table=None))
    assert "t.ngc:5: NURBS goes through infinity" in message and "weight -1" in message


def test_repeated_control_points_move_nothing_between_them() -> None:
    moves = _moves("G21 F100\nG5.2 X0 Y0 P1\nX0 Y0 P1\nX5 Y5 P1\nX10 Y0 P1 L3\nG5.3")
    assert moves[-1].end[:2] == pytest.approx((10.0, 0.0))
    assert all(math.isfinite(v) for m in moves for v in m.end)
