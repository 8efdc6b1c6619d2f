"""Cutter radius compensation with lathe tools: tool table orientation Q 1-8, G41.1/G42.1 L.

What LinuxCNC does (``interp_queue.cc`` ``latheorigin_x``/``latheorigin_z``, applied by
``dequeue_canons``; ``convert_cutter_compensation_on`` and ``convert_arc_comp1`` in
``interp_convert.cc``): the path of the nose-radius *centre* is computed as for a mill cutter, then
every compensated point (move ends, arc centres) is moved by the vector from the nose centre to the
tool's control point, the "imaginary tip" where the tool table offsets are measured. With R the nose
radius, that vector is, per orientation, in (Z, X):

    1: (+R, -R)   2: (-R, -R)   3: (-R, +R)   4: (+R, +R)
    5: (+R, 0)    6: (0, -R)    7: (-R, 0)    8: (0, +R)      0 and 9: (0, 0) (like a mill cutter)

The expected paths below are worked out by hand from the programmed contour: first the nose-centre
path (offset lines, corner arcs around convex corners, intersections in concave ones), then that
vector added. Coordinates in comments are (Z, X), the G18 plane's (first, second) axes; the tool is
right of the path for G42, left for G41 (seen from +Y, with Z to the right and X up, "right" of a move
towards -Z is +X).
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from gcode_canon.commands import ArcFeed, StraightFeed, StraightTraverse
from gcode_canon.cutter_comp import Arc2, CutterCompensator, Line2, lathe_tip_offset
from gcode_canon.errors import GCodeError
from gcode_canon.interpreter import Interpreter
from gcode_canon.settings import InterpreterSettings

R = 0.4  # nose radius of every tool below (D0.8)

TIP = {  # orientation -> (dZ, dX) from the nose centre to the control point, in units of R
    0: (0, 0), 1: (1, -1), 2: (-1, -1), 3: (-1, 1), 4: (1, 1),
    5: (1, 0), 6: (0, -1), 7: (-1, 0), 8: (0, 1), 9: (0, 0),
}

Move = tuple  # ("G0" | "G1", z, x) or ("ARC", z, x, centre z, centre x, turns)


@pytest.fixture
def table(tmp_path: Path) -> Path:
    path = tmp_path / "lathe.tbl"
    path.write_text(
        "T1 P1 D0.8 Q2 ;orientation 2\n"
        "T2 P2 D0.8 Q3 ;orientation 3\n"
        "T3 P3 D0.8 Q6 ;orientation 6\n"
        "T4 P4 D0.8 Q9 ;orientation 9: the control point is the nose centre\n"
        "T5 P5 D0.8 ;orientation 0: a mill cutter\n"
        "T6 P6 D0.8 Q1\nT7 P7 D0.8 Q4\nT8 P8 D0.8 Q5\nT9 P9 D0.8 Q7\nT10 P10 D0.8 Q8\n"
    )
    return path


def moves(text: str, table: Path) -> list[Move]:
    """The moves of ``text``, as (kind, Z, X[, centre Z, centre X, turns]); Y must stay 0."""
    settings = InterpreterSettings(dry_run=True, tool_table=table)
    out: list[Move] = []
    for c in Interpreter(settings).run_string(text, "lathe.ngc"):
        if isinstance(c, StraightTraverse | StraightFeed | ArcFeed):
            assert c.end[1] == 0.0
        if isinstance(c, StraightTraverse):
            out.append(("G0", c.end[2], c.end[0]))
        elif isinstance(c, StraightFeed):
            out.append(("G1", c.end[2], c.end[0]))
        elif isinstance(c, ArcFeed):
            out.append(("ARC", c.end[2], c.end[0], c.center[2], c.center[0], c.turns))
    return out


def shifted(path: list[Move], tip: tuple[float, float], keep_last: int = 1) -> list[Move]:
    """``path`` (nose centre) moved by ``tip`` (Z, X), but for the last ``keep_last`` moves (the
    uncompensated exit after G40)."""
    dz, dx = tip
    out: list[Move] = []
    for k, m in enumerate(path):
        if k >= len(path) - keep_last:
            out.append(m)
        elif m[0] == "ARC":
            out.append(("ARC", m[1] + dz, m[2] + dx, m[3] + dz, m[4] + dx, m[5]))
        else:
            out.append((m[0], m[1] + dz, m[2] + dx))
    return out


def assert_path(got: list[Move], want: list[Move]) -> None:
    assert len(got) == len(want), (got, want)
    for g, w in zip(got, want, strict=True):
        assert g[0] == w[0], (got, want)
        if g[0] == "ARC":
            assert g[5] == w[5], (g, w)
        for a, b in zip(g[1:5], w[1:5], strict=False):
            assert a == pytest.approx(b, abs=1e-9), (g, w)


# --- the profile, turned towards the chuck with G42 -----------------------------------------------
#
# From the centre line at the face (Z0 X0): face up to X10, a taper to (Z-8, X16) whose direction
# (-0.8, 0.6) is a 3-4-5 triangle, a convex R5 radius (G3, centre (-11, 12): start radial (3, 4), end
# radial (0, 5)) tangent to the taper and ending at (-11, 17) heading -Z, straight turning to Z-20,
# then up a shoulder to X22, where the corner is concave; G40 and a rapid away.
PROFILE = (
    "G18 G21 G90 G94 F100\nT{tool} M6\nG0 X0 Z0\n"
    "{comp} G1 X2 (entry, along the face)\n"
    "X10 (facing)\n"
    "X16 Z-8 (taper)\n"
    "G3 X17 Z-11 K-3 I-4 (R5 radius, centre Z-11 X12)\n"
    "G1 Z-20\n"
    "X22 (shoulder)\n"
    "G40 G0 X25\nM2\n"
)

# Nose-centre path. Right of +X travel is +Z, so the entry (+X, from X0 to X2) ends at (0.4, 2) and the
# facing line joins it tangentially, on Z = +0.4, ending offset at (0.4, 10). Face -> taper turns left
# (cross((0, 1), (-0.8, 0.6)) = 0.8 > 0), the tool is on the right: convex, so a counter-clockwise arc
# of radius R around the corner (0, 10) goes to the taper's offset start, (0, 10) + R (0.6, 0.8) (the
# taper's right normal is (0.6, 0.8)). The taper's offset end (-8, 16) + R (0.6, 0.8) is also the
# offset start of the radius (the tool is outside a G3 on the right; radial (0.6, 0.8)): tangent, no
# corner. The radius ends R further out on its end radial: (-11, 17 + R), centre unchanged. The
# straight turning joins tangentially on X = 17 + R; the shoulder (+X) turns right from -Z: concave,
# the corner is where X = 17 + R meets the shoulder's offset Z = -20 + R. G40 flushes the shoulder at
# its own offset end (-20 + R, 22); the rapid after G40 goes to the programmed (-20, 25).
CENTRE_PATH = [
    ("G0", 0.0, 0.0),
    ("G1", R, 2.0),
    ("G1", R, 10.0),
    ("ARC", 0.6 * R, 10 + 0.8 * R, 0.0, 10.0, 1),
    ("G1", -8 + 0.6 * R, 16 + 0.8 * R),
    ("ARC", -11.0, 17 + R, -11.0, 12.0, 1),
    ("G1", -20 + R, 17 + R),
    ("G1", -20 + R, 22.0),
    ("G0", -20.0, 25.0),
]


@pytest.mark.parametrize(("tool", "orientation"), [(1, 2), (2, 3), (3, 6), (4, 9), (5, 0), (6, 1),
                                                   (7, 4), (8, 5), (9, 7), (10, 8)])
def test_profile_with_tool_table_orientation(tool: int, orientation: int, table: Path) -> None:
    got = moves(PROFILE.format(tool=tool, comp="G42"), table)
    tip = (TIP[orientation][0] * R, TIP[orientation][1] * R)
    want = [CENTRE_PATH[0], *shifted(CENTRE_PATH[1:], tip)]
    assert_path(got, want)


def test_negative_g42_1_diameter_is_g41_1_and_shifts_by_the_radius(table: Path) -> None:
    # a negative D swaps the side and LinuxCNC makes the radius positive before using it: G41.1 D-0.8
    # is G42.1 D0.8, and the tip is still R away from the centre
    got = moves(PROFILE.format(tool=5, comp="G41.1 D-0.8 L2"), table)
    assert_path(got, [CENTRE_PATH[0], *shifted(CENTRE_PATH[1:], (-R, -R))])


# --- the same contour the other way, with G41.1 D0.8 L3 -------------------------------------------
#
# From beyond the shoulder (Z-20 X25): down the shoulder, along Z+, the radius as a G2 (centre from
# its start (-11, 17): K0 I-5), the taper to (0, 10), down the face to X2, G40, rapid to Z2. The tool
# is left of the path, on the outside again.
REVERSED = (
    "G18 G21 G90 G94 F100\nT5 M6\nG0 X25 Z-20\n"
    "G41.1 D0.8 L3 G1 X22 (entry, down the shoulder's line)\n"
    "X17 (shoulder)\n"
    "Z-11\n"
    "G2 X16 Z-8 K0 I-5 (R5 radius)\n"
    "G1 X10 Z0 (taper)\n"
    "X2 (facing)\n"
    "G40 G0 Z2\nM2\n"
)

# Left of -X travel is +Z: the entry ends at (-20 + R, 22) and the shoulder continues on Z = -20 + R.
# Shoulder -> Z+ turns left (cross((0, -1), (1, 0)) = 1 > 0) with the tool on the left: concave, the
# corner is (-20 + R, 17 + R) (the line's left offset is X = 17 + R). That line ends tangentially at
# the radius' offset start (-11, 17 + R); the G2 (tool outside) ends at (-8, 16) + R (0.6, 0.8). The
# taper (0.8, -0.6) is tangent to it there and ends at (0, 10) + R (0.6, 0.8) (its left normal). Taper
# -> face (0, -1) turns right: convex, a clockwise arc of radius R around (0, 10) to (R, 10); the face
# ends at (R, 2) at G40. Orientation 3: the tip is at (-R, +R) from the nose centre.
REVERSED_CENTRE_PATH = [
    ("G0", -20.0, 25.0),
    ("G1", -20 + R, 22.0),
    ("G1", -20 + R, 17 + R),
    ("G1", -11.0, 17 + R),
    ("ARC", -8 + 0.6 * R, 16 + 0.8 * R, -11.0, 12.0, -1),
    ("G1", 0.6 * R, 10 + 0.8 * R),
    ("ARC", R, 10.0, 0.0, 10.0, -1),
    ("G1", R, 2.0),
    ("G0", 2.0, 2.0),
]


def test_profile_with_g41_1_d_and_l(table: Path) -> None:
    got = moves(REVERSED, table)  # T5 has orientation 0: G41.1 takes D and L, not the table
    assert_path(got, [REVERSED_CENTRE_PATH[0], *shifted(REVERSED_CENTRE_PATH[1:], (-R, R))])


def test_g41_1_without_l_is_orientation_0(table: Path) -> None:
    got = moves(REVERSED.replace(" L3", ""), table)
    assert_path(got, REVERSED_CENTRE_PATH)


def test_zero_diameter_moves_nothing(table: Path) -> None:
    # radius 0: compensation is a no-op in LinuxCNC, and the tip vector is R = 0 long
    got = moves(REVERSED.replace("D0.8 L3", "D0 L3"), table)
    assert got[1:-1] == [("G1", -20.0, 22.0), ("G1", -20.0, 17.0), ("G1", -11.0, 17.0),
                         ("ARC", -8.0, 16.0, -11.0, 12.0, -1), ("G1", 0.0, 10.0), ("G1", 0.0, 2.0)]


# --- entry arc: the control point first moves to the shifted start (convert_arc_comp1) ------------


def test_lathe_entry_arc_starts_with_a_straight_move_to_the_shifted_start(table: Path) -> None:
    # From (4, 10), a G2 entry arc around (0, 10) to (0, 6), G41 with orientation 2 (T1). The tool is
    # left of a clockwise arc: outside, so the arc ends R further out on its end radial (0, -1), at
    # (0, 6 - R). The entry arc's new centre is on the line from that end towards the programmed centre,
    # (0, 6 - R + t), as far from the start as from the end: 4^2 + (10 - (6 - R) - t)^2 = t^2, so
    # t = (16 + (4 + R)^2) / (2 (4 + R)). LinuxCNC first feeds the control point straight from where it
    # is, (4, 10), to (4, 10) + tip, as the arc (shifted by the tip) starts there. The arc ends heading
    # -Z (its end radial is still (0, -1)), so G1 Z-5 joins it tangentially, offset to X = 6 - R, and
    # G40 ends it at (-5, 6 - R). (A tangent line: the case where LinuxCNC's queue gives exactly this;
    # see the cutter_comp module docstring for the others.) Everything shifted by the tip (-R, -R).
    text = "G18 G21 F100\nT1 M6\nG0 X10 Z4\nG41 G2 X6 Z0 K-4\nG1 Z-5\nG40 G1 X0\nM2\n"
    got = moves(text, table)
    t = (16 + (4 + R) ** 2) / (2 * (4 + R))
    want = [("G0", 4.0, 10.0),
            ("G1", 4.0 - R, 10.0 - R),
            ("ARC", 0.0 - R, 6 - R - R, 0.0 - R, 6 - R + t - R, -1),
            ("G1", -5.0 - R, 6 - R - R),
            ("G1", -5.0, 0.0)]
    assert_path(got, want)
    # the new centre really is equidistant from the (shifted) start and end
    arc = got[2]
    assert math.dist(arc[3:5], got[1][1:3]) == pytest.approx(math.dist(arc[3:5], arc[1:3]), abs=1e-9)


def test_lathe_entry_arc_then_g40(table: Path) -> None:
    # G40 right after the entry arc: the straight move still goes to the shifted start only (LinuxCNC
    # would move its end to the arc's end as well; see the cutter_comp module docstring)
    text = "G18 G21 F100\nT1 M6\nG0 X10 Z4\nG41 G2 X6 Z0 K-4\nG40 G1 X0\nM2\n"
    got = moves(text, table)
    assert got[1] == pytest.approx(("G1", 4.0 - R, 10.0 - R), abs=1e-9)
    assert got[2][0] == "ARC" and got[2][1:3] == pytest.approx((0.0 - R, 6 - R - R), abs=1e-9)


def test_mill_entry_arc_has_no_extra_move(table: Path) -> None:
    text = "G18 G21 F100\nT4 M6\nG0 X10 Z4\nG41 G2 X6 Z0 K-4\nG40 G1 X0\nM2\n"  # T4: orientation 9
    assert [m[0] for m in moves(text, table)] == ["G0", "ARC", "G1"]


def test_entry_arc_pre_move_keeps_the_start_y_and_takes_the_end_a() -> None:
    # LinuxCNC's pre-move: STRAIGHT_FEED(cx, cy, cz, AA_end, ...) with cz the current normal coordinate
    comp = CutterCompensator("left", R, (4.0, 10.0), orientation=2, normal=5.0)
    out = comp.add(Arc2((4.0, 10.0), (0.0, 6.0), (0.0, 10.0), False, normal=-1.0, extra=(30.0,), line=7))
    assert out == [Line2((4.0, 10.0), (4.0 - R, 10.0 - R), 5.0, (30.0,), 7)]


# --- LinuxCNC's own regression test, tests/ccomp/lathe-comp ---------------------------------------


def test_linuxcnc_lathe_comp_regression(tmp_path: Path) -> None:
    # The G41 (orientation 2) and G42 (orientation 7) passes of LinuxCNC's tests/ccomp/lathe-comp, a
    # 0.1 in diameter tool, in inches; the expected numbers are that test's `expected` file (rs274
    # output, inches), converted to mm. canon reads tool tables in mm: D0.1 in is D2.54.
    tbl = tmp_path / "t.tbl"
    tbl.write_text("T2 P2 D2.54 I85 J25 Q2\nT7 P7 D2.54 I-30 J30 Q7\nT9 P9\n")
    text = (
        "g20 g64 g18 f30\n"
        "t2 m6\ng43 h2\ng0x.3z0\ng41\ng1x.1\ng3x0z.1r.1\ng1z1\ng2r.25x-.25z1.25\ng3r.25x-.5z1.5\n"
        "g1z1.75\ng40\ng0x.3\n"
        "t7 m6\ng43 h9\ng0z1.85\ng0x-.3\ng42\ng1x-.4\ng2x-.5z1.75r.1\ng1z1.5\ng2r.25x-.25z1.25\n"
        "g3r.25x0z1\ng1z.1\ng2r.1x.1z0\ng40\ng0x.3\nm2\n"
    )
    inch = [  # (kind, Z, X[, centre Z, centre X, turn]) from `expected`
        ("G0", 0.0, 0.3),
        ("G1", 0.0, 0.05),
        ("ARC", 0.05, 0.0, 0.05, 0.05, 1),
        ("G1", 0.95, 0.0),
        ("ARC", 1.25, -0.3, 0.95, -0.3, -1),
        ("ARC", 1.45, -0.5, 1.45, -0.3, 1),
        ("G1", 1.7, -0.5),
        ("G0", 1.75, 0.3),
        ("G0", 1.85, 0.3),
        ("G0", 1.85, -0.3),
        ("G1", 1.75, -0.4),
        ("ARC", 1.7, -0.45, 1.7, -0.4, -1),
        ("G1", 1.45, -0.45),
        ("ARC", 1.25, -0.25, 1.45, -0.25, -1),
        ("ARC", 0.95, 0.05, 0.95, -0.25, 1),
        ("G1", 0.05, 0.05),
        ("ARC", 0.0, 0.1, 0.05, 0.1, -1),
        ("G0", 0.0, 0.3),
    ]
    want = [(m[0], *(v * 25.4 for v in m[1:5]), *m[5:]) for m in inch]
    assert_path(moves(text, tbl), want)


# --- the tip vector itself ------------------------------------------------------------------------


def test_lathe_tip_offset_table() -> None:
    for orientation, (dz, dx) in TIP.items():
        assert lathe_tip_offset(orientation, -0.5) == (dz * 0.5, dx * 0.5)
    for bad in (-1, 10, 2.0, True):
        with pytest.raises(ValueError):
            lathe_tip_offset(bad, 1.0)  # type: ignore[arg-type]


# --- errors ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "words"),
    [
        # an orientation is only meaningful in G18 (convert_cutter_compensation_on)
        ("G17 G41.1 D0.8 L3\n", "G41.1 with L word, but plane is not G18"),
        ("G17 G42.1 D0.8 L0\n", "G42.1 with L word, but plane is not G18"),
        ("G17\nT1 M6\nG41\n", "G41 with lathe tool, but plane is not G18"),
        ("G17\nG42 D2\n", "G42 with lathe tool, but plane is not G18"),
        # L: a whole number 0-9 (the manual; LinuxCNC's reader refuses negative and fractional L)
        ("G18 G41.1 D0.8 L10\n", "invalid tool orientation"),
        ("G18 G41.1 D0.8 L-1\n", "L word of G41.1"),
        ("G18 G41.1 D0.8 L2.5\n", "must be an integer"),
        ("G18 G41.1 L3\n", "needs a D word"),
        # L is still refused where nothing uses it
        ("G18 G40 L3\n", "L word with no"),
        ("G18 G1 X1 L3\n", "L word with no"),
    ],
)
def test_errors(text: str, words: str, table: Path) -> None:
    with pytest.raises(GCodeError) as info:
        moves("F100\n" + text + "M2\n", table)
    assert words in info.value.message, info.value.message
    assert info.value.file == "lathe.ngc" and info.value.line >= 1


def test_mill_orientations_are_fine_outside_g18(table: Path) -> None:
    # orientations 9 and 0 are mill cutters, allowed in G17 and compensated as ever: up +Y to (0, 0)
    # with the tool on the left (-X), so the entry ends at (-R, 0); the turn to +X is convex (right
    # turn, tool left): a clockwise arc of R around (0, 0) to (0, R); X10 ends at (10, R)
    for tool in (4, 5):
        text = f"G17 F100\nT{tool} M6\nG0 X0 Y-5\nG41 G1 Y0\nX10\nG40 G1 Y-5\nM2\n"
        settings = InterpreterSettings(dry_run=True, tool_table=table)
        cmds = [c for c in Interpreter(settings).run_string(text, "m.ngc") if c.MOVES]
        got = [(type(c).__name__, *(round(v, 9) for v in c.end[:2])) for c in cmds]
        assert got == [("StraightTraverse", 0, -5), ("StraightFeed", -R, 0), ("ArcFeed", 0, R),
                       ("StraightFeed", 10, R), ("StraightFeed", 10, -5)]
        assert cmds[2].center[:2] == (0, 0) and cmds[2].turns == -1


def test_g41_l_word_is_accepted_and_ignored(table: Path) -> None:
    # LinuxCNC's check_other_codes lets L stand with G41/G42, and convert_cutter_compensation_on only
    # reads it for G41.1/G42.1: the tool table's orientation (T1: 2) holds
    with_l = moves(PROFILE.format(tool=1, comp="G42 L3"), table)
    assert_path(with_l, [CENTRE_PATH[0], *shifted(CENTRE_PATH[1:], (-R, -R))])
