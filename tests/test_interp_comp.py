"""Cutter radius compensation wired into the interpreter (the geometry itself: test_cutter_comp.py).

The expected paths are computed geometrically here: every compensated point lies at the tool radius
from the programmed contour, inside a pocket the corners are intersections, outside they are arcs
around the programmed corners."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from gcode_canon.commands import ArcFeed, Coolant, StraightFeed, StraightTraverse
from gcode_canon.errors import GCodeError
from gcode_canon.interpreter import Interpreter
from gcode_canon.settings import InterpreterSettings


@pytest.fixture
def table(tmp_path: Path) -> Path:
    path = tmp_path / "tools.tbl"
    path.write_text("T1 P1 D6 ;6 mm end mill\nT2 P2 D10 ;10 mm end mill\n")
    return path


def run(text: str, table: Path) -> list:
    settings = InterpreterSettings(dry_run=True, tool_table=table)
    return list(Interpreter(settings).run_string(text, "c.ngc"))


def seg_dist(p, a, b) -> float:
    ax, ay = a
    bx, by = b
    t = ((p[0] - ax) * (bx - ax) + (p[1] - ay) * (by - ay)) / ((bx - ax) ** 2 + (by - ay) ** 2)
    t = max(0.0, min(1.0, t))
    return math.hypot(p[0] - (ax + t * (bx - ax)), p[1] - (ay + t * (by - ay)))


def contour_dist(p, corners) -> float:
    return min(seg_dist(p, corners[k], corners[(k + 1) % len(corners)]) for k in range(len(corners)))


def test_pocket_with_g41_is_the_contour_shrunk_by_the_radius(table: Path) -> None:
    # a 50 x 30 pocket, counter-clockwise with G41: the tool (T2, r = 5) stays inside; corners are
    # concave: the tool path is the rectangle [5, 45] x [5, 25], no arcs
    text = ("T2 M6\nF500\nG0 X25 Y15 Z1\nG1 Z-2\nG41 G1 X25 Y0\nX50\nY30\nX0\nY0\nX25\nG40 G1 X25 Y15\nM2\n")
    cmds = run(text, table)
    feeds = [c for c in cmds if isinstance(c, StraightFeed | ArcFeed)]
    assert not any(isinstance(c, ArcFeed) for c in feeds)
    points = [tuple(round(v, 9) for v in c.end[:2]) for c in feeds]
    # entry (south from the centre): its end is offset perpendicular to it, to x = 25 + 5, and cut back
    # at the concave corner with the first edge's offset y = 5; the last edge ends offset at (25, 5)
    assert points[1:8] == [(30, 5), (45, 5), (45, 25), (5, 25), (5, 5), (25, 5), (25, 15)]
    assert all(c.end[2] == -2 for c in feeds[1:])
    corners = [(0, 0), (50, 0), (50, 30), (0, 30)]
    for p in points[1:7]:
        assert contour_dist(p, corners) == pytest.approx(5.0)


def test_outside_contour_with_g42_gets_corner_arcs(table: Path) -> None:
    # counter-clockwise around a 40 x 40 square with G42 (tool on the right = outside), r = 3 (T1)
    text = "T1 M6\nF100\nG0 X20 Y-10\nG42 G1 X20 Y0\nX40\nY40\nX0\nY0\nX20\nG40 G0 X20 Y-10\nM2\n"
    cmds = run(text, table)
    moves = [c for c in cmds if isinstance(c, StraightFeed | ArcFeed | StraightTraverse)]
    corners = [(0, 0), (40, 0), (40, 40), (0, 40)]
    arcs = [c for c in moves if isinstance(c, ArcFeed)]
    assert [tuple(round(v, 9) for v in a.center[:2]) for a in arcs] == [(40, 0), (40, 40), (0, 40), (0, 0)]
    for a in arcs:
        assert a.turns == 1  # counter-clockwise around the outside corner
        assert math.dist(a.end[:2], a.center[:2]) == pytest.approx(3.0)
    for c in moves[1:-1]:
        assert contour_dist(c.end[:2], corners) == pytest.approx(3.0)
    assert moves[-1].end[:2] == (20, -10)  # G40: the next move is plain


def test_held_commands_keep_their_order(table: Path) -> None:
    cmds = run("T1 M6\nF100\nG0 X0 Y-10\nG41 G1 X0 Y0\nM8\nX10\nG40 G1 X10 Y-10\nM2\n", table)
    kinds = [(type(c).__name__, c.line) for c in cmds if isinstance(c, StraightFeed | Coolant)]
    assert kinds[:3] == [("StraightFeed", 4), ("Coolant", 5), ("StraightFeed", 6)]


def test_ccomp_parameter_and_active_codes(table: Path) -> None:
    interp = Interpreter(InterpreterSettings(dry_run=True, tool_table=table))
    list(interp.run_string("T1 M6\nF1\nG0 X-5\nG42.1 D4 G1 X0\n#1=#<_ccomp>\nG40 G1 X1\n#2=#<_ccomp>\nM2\n"))
    assert interp.parameter(1) == 421.0 and interp.parameter(2) == 400.0


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("G41 G1 X10\nG40\nG2 X0 Y0 I-5\nM2\n", "must be straight, not an arc"),
        ("G0 X-10\nG41 G1 X-9\nM2\n", "entry move is not greater than the tool radius"),
        ("G41\nG41\nM2\n", "already on"),
        ("G41\nG18\nM2\n", "Cannot change planes"),
        ("G19 G41\nM2\n", "G17 or G18 only"),
        ("G41\nG38.2 Z-1\nM2\n", "Cannot probe"),
        ("G41\nG28\nM2\n", "Cannot use G28"),
        ("G41\nG55\nM2\n", "coordinate systems"),
        ("G41\nG81 X1 Z-1 R1\nM2\n", "cutter"),
        ("G41.1\nM2\n", "needs a D word"),
        ("G0 X-20\nG41 G1 X0\nX20\nY1\nX0\nM2\n", "cannot be reached by the tool without gouging"),
        ("G0 X-20\nG41 G1 X0 Y0\nG3 X2 Y0 I1\nM2\n", "Tool radius not less than arc radius"),
    ],
)
def test_comp_errors(text: str, words: str, table: Path) -> None:
    with pytest.raises(GCodeError) as info:
        run("T1 M6 F100\n" + text, table)
    assert words in info.value.message, info.value.message
    assert info.value.file == "c.ngc" and info.value.line >= 1
