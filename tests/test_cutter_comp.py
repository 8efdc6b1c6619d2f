"""Cutter radius compensation engine, checked against geometry computed here independently.

The reference is plain distance geometry: every point of a compensated path (entry move aside) must
lie exactly one tool radius from the programmed contour, on the side asked for; convex corners must be
rounded by arcs centred on the programmed corner; the path must be continuous. The expected numbers
(corner points, path lengths) are worked out by hand from the shapes, not taken from the code. The
reference geometry and the programs are in tests/cutter_comp_reference.py.
"""

from __future__ import annotations

import math

import pytest
from cutter_comp_reference import (
    ARC_ARC_GOUGE,
    FEED_GOUGE,
    TOL,
    TRAVERSE_GOUGE,
    arc_span,
    assert_at_radius,
    assert_continuous,
    boundary_points,
    closed_contour,
    dist_to_contour,
    inside_polygon,
    lead_in_line,
    outline_program,
    pocket_program,
    polyline,
    rect,
    reverse,
    run,
    samples,
    seg_length,
)
from hypothesis import HealthCheck, assume, event, given, settings
from hypothesis import strategies as st

from gcode_canon.cutter_comp import Arc2, CutterCompensator, Line2
from gcode_canon.errors import GCodeError

# --- rectangles -----------------------------------------------------------------------------------


@pytest.mark.parametrize(("side", "ccw"), [("right", True), ("left", False)])
def test_rectangle_outline_outside_convex_corners(side, ccw):
    w, h, r = 20.0, 10.0, 1.5
    pts = rect(w, h, ccw)
    v0, v1 = pts[0], pts[1]
    d0 = ((v1[0] - v0[0]) / w, (v1[1] - v0[1]) / w)
    start = (v0[0] - 8 * d0[0], v0[1] - 8 * d0[1])  # lead-in along the first edge, from outside
    path = [start, *pts, pts[0], pts[1]]  # once round, then the first edge again to close the corner
    comp, out = run(side, r, start, polyline(path))

    assert_continuous(start, out)
    assert_at_radius(out, closed_contour(pts), r)
    for seg in out[1:]:
        for p in samples(seg, 8):
            assert not inside_polygon(p, pts)
    arcs = [s for s in out if isinstance(s, Arc2)]
    assert len(arcs) == 4
    # each convex corner: a quarter circle of the tool radius centred on the programmed corner
    for arc in arcs:
        assert min(math.dist(arc.center, v) for v in pts) < TOL
        assert abs(math.dist(arc.start, arc.center) - r) < TOL
        assert abs(math.dist(arc.end, arc.center) - r) < TOL
        assert arc.ccw == (side == "right")
        assert abs(abs(arc_span(arc.start, arc.end, arc.center, arc.ccw)) - math.pi / 2) < TOL
    # from the first corner on, one loop: the perimeter plus a full circle of radius r
    loop = out[out.index(arcs[0]) :]
    assert abs(sum(seg_length(s) for s in loop) - (2 * (w + h) + 2 * math.pi * r)) < 1e-9
    # the last edge ends offset perpendicular at its programmed end
    n = (-d0[1], d0[0]) if side == "left" else (d0[1], -d0[0])
    assert math.dist(comp.tool, (v1[0] + r * n[0], v1[1] + r * n[1])) < TOL
    assert out[-1].end == comp.tool


@pytest.mark.parametrize(("side", "ccw"), [("left", True), ("right", False)])
def test_rectangle_pocket_inside_concave_corners(side, ccw):
    w, h, r = 20.0, 10.0, 1.5
    pts = rect(w, h, ccw)
    mid_bottom = (0.0, -h / 2)
    # from the centre to the middle of the bottom wall, round the pocket, back to the middle
    path = [(0.0, 0.0), mid_bottom, *pts[1:], pts[0], mid_bottom]
    _, out = run(side, r, (0.0, 0.0), polyline(path))

    end = assert_continuous((0.0, 0.0), out)
    assert_at_radius(out, closed_contour(pts), r)
    assert not any(isinstance(s, Arc2) for s in out)
    for seg in out:
        for p in samples(seg, 8):
            assert inside_polygon(p, pts)
    # the tool path's corners are the pocket's corners pulled in by r from both walls
    ends = [s.end for s in out]
    for x in (-w / 2 + r, w / 2 - r):
        for y in (-h / 2 + r, h / 2 - r):
            assert any(math.dist(e, (x, y)) < TOL for e in ends)
    # the entry move's end was pulled back onto the bottom wall's offset line
    entry = out[0]
    assert entry.start == (0.0, 0.0) and entry.line == 10
    assert math.dist(entry.end, (r if ccw else -r, -h / 2 + r)) < TOL
    assert math.dist(end, (0.0, -h / 2 + r)) < TOL
    assert [s.line for s in out] == list(range(10, 16))


def test_pocket_narrower_than_tool_is_gouging():
    w, h, r = 20.0, 3.0, 2.0  # the tool cannot fit between top and bottom walls
    pts = rect(w, h)
    path = [(0.0, 3.0), (0.0, -h / 2), *pts[1:], pts[0]]  # entering from above, through the pocket
    comp = CutterCompensator("left", r, (0.0, 3.0))
    with pytest.raises(GCodeError) as err:
        for m in polyline(path):
            comp.add(m)
        comp.finish()
    assert err.value.message == FEED_GOUGE
    assert err.value.line == 13  # reported on the move that showed the corner (the top wall)


def test_rapid_cut_back_past_its_start_is_gouging():
    comp = CutterCompensator("left", 2.0, (0.0, -5.0))
    comp.add(Line2((0.0, -5.0), (10.0, -5.0), line=1))
    comp.add(Line2((10.0, -5.0), (10.0, -2.0), line=2, rapid=True))  # 3 long, needs 2 + 2 of room
    with pytest.raises(GCodeError) as err:
        comp.add(Line2((10.0, -2.0), (0.0, -2.0), line=3))
    assert err.value.message == TRAVERSE_GOUGE


# --- entry, exit, pass-through --------------------------------------------------------------------


@pytest.mark.parametrize(("side", "offset"), [("left", (10.0, 1.0)), ("right", (10.0, -1.0))])
def test_entry_line_ends_offset_perpendicular_to_it(side, offset):
    comp = CutterCompensator(side, 1.0, (0.0, 0.0))
    assert comp.add(Line2((0.0, 0.0), (10.0, 0.0), normal=-1.0, line=5)) == []
    assert comp.pending
    out = comp.finish()
    assert out == [Line2((0.0, 0.0), offset, -1.0, (), 5)]
    assert comp.tool == offset and comp.programmed == (10.0, 0.0)
    with pytest.raises(RuntimeError):
        comp.add(Line2((10.0, 0.0), (20.0, 0.0)))


def test_entry_diagonal_then_convex_corner():
    r = 0.5
    comp = CutterCompensator("left", r, (0.0, 0.0))
    comp.add(Line2((0.0, 0.0), (3.0, 4.0), line=1))
    entry_end = (3.0 - 0.8 * r, 4.0 + 0.6 * r)  # left of the direction (0.6, 0.8)
    assert math.dist(comp.tool, entry_end) < TOL
    # a right turn is convex for G41: the entry keeps its end, an arc goes round (3, 4)
    out = comp.add(Line2((3.0, 4.0), (10.0, 4.0), line=2))
    assert len(out) == 2
    assert out[0].start == (0.0, 0.0) and math.dist(out[0].end, entry_end) < TOL and out[0].line == 1
    arc = out[1]
    assert isinstance(arc, Arc2) and arc.line == 2 and not arc.ccw
    assert arc.center == (3.0, 4.0)
    assert math.dist(arc.end, (3.0, 4.0 + r)) < TOL


def test_entry_too_short():
    comp = CutterCompensator("left", 2.0, (0.0, 0.0))
    with pytest.raises(GCodeError) as err:
        comp.add(Line2((0.0, 0.0), (1.5, 1.0), line=7))
    assert err.value.message == "Length of cutter compensation entry move is not greater than the tool radius"
    assert err.value.line == 7
    # a plunge straight after G41 is an entry with no length, as in LinuxCNC
    comp = CutterCompensator("left", 2.0, (0.0, 0.0))
    with pytest.raises(GCodeError, match="entry move is not greater"):
        comp.add(Line2((0.0, 0.0), (0.0, 0.0), normal=-3.0, line=8))


def test_entry_arc():
    r = 1.0
    comp = CutterCompensator("right", r, (0.0, 0.0))
    # CCW half circle of radius 5 about (5, 0), tool right = outside
    comp.add(Arc2((0.0, 0.0), (10.0, 0.0), (5.0, 0.0), ccw=True, line=3))
    (arc,) = comp.finish()
    assert isinstance(arc, Arc2) and arc.ccw and arc.line == 3
    assert arc.start == (0.0, 0.0)
    assert math.dist(arc.end, (11.0, 0.0)) < TOL  # offset along the end radius, outwards
    # the new centre: on the end's radius line, equally far from the start and the end
    assert math.dist(arc.center, (5.5, 0.0)) < TOL


def test_entry_arc_too_short_and_too_small():
    comp = CutterCompensator("left", 2.0, (0.0, 0.0))
    with pytest.raises(GCodeError) as err:
        comp.add(Arc2((0.0, 0.0), (1.0, 1.0), (1.0, 0.0), ccw=True, line=4))
    assert err.value.message == "Radius of cutter compensation entry arc is not greater than the tool radius"
    comp = CutterCompensator("left", 2.0, (0.0, 0.0))
    with pytest.raises(GCodeError) as err:
        comp.add(Arc2((0.0, 0.0), (3.0, 0.0), (1.5, 0.0), ccw=True, line=4))  # inside a radius 1.5 arc
    assert err.value.message == "Tool radius not less than arc radius with comp"


def test_zero_radius_passes_everything_through():
    moves = [
        Line2((0.0, 0.0), (5.0, 0.0), 1.0, (2.0,), 1),
        Arc2((5.0, 0.0), (5.0, 4.0), (5.0, 2.0), True, 0.5, (3.0,), 2),
        Line2((5.0, 4.0), (5.0, 4.0), -1.0, (3.0,), 3, rapid=True),
        Line2((5.0, 4.0), (0.0, 4.0), -1.0, (3.0,), 4),
    ]
    _, out = run("left", 0.0, (0.0, 0.0), moves)
    assert out == moves


def test_negative_radius_swaps_the_side():
    _, a = run("left", -1.0, (0.0, 0.0), [Line2((0.0, 0.0), (10.0, 0.0))])
    _, b = run("right", 1.0, (0.0, 0.0), [Line2((0.0, 0.0), (10.0, 0.0))])
    assert a == b == [Line2((0.0, 0.0), (10.0, -1.0))]


def test_moves_without_plane_motion_follow_the_concave_corner():
    r = 1.0
    comp = CutterCompensator("left", r, (0.0, -10.0))
    out = comp.add(Line2((0.0, -10.0), (0.0, 0.0), normal=0.0, line=1))  # entry, up
    out += comp.add(Line2((0.0, 0.0), (10.0, 0.0), normal=0.0, line=2))  # right turn: convex, arc
    out += comp.add(Line2((10.0, 0.0), (10.0, 0.0), normal=5.0, line=3))  # retract
    out += comp.add(Line2((10.0, 0.0), (10.0, 0.0), normal=-2.0, line=4))  # plunge
    assert comp.pending
    out += comp.add(Line2((10.0, 0.0), (10.0, 10.0), normal=-2.0, line=5))  # left turn: concave
    out += comp.finish()
    assert_continuous((0.0, -10.0), out)
    assert [s.line for s in out] == [1, 2, 2, 3, 4, 5]
    corner = (10.0 - r, 0.0 + r)
    retract, plunge = out[3], out[4]
    assert math.dist(out[2].end, corner) < TOL
    assert math.dist(retract.start, corner) < TOL and math.dist(retract.end, corner) < TOL
    assert retract.normal == 5.0 and plunge.normal == -2.0
    assert math.dist(plunge.end, corner) < TOL
    assert math.dist(out[5].end, (9.0, 10.0)) < TOL


def test_rapid_convex_corner_is_a_straight_traverse():
    comp = CutterCompensator("left", 1.0, (0.0, 0.0))
    comp.add(Line2((0.0, 0.0), (10.0, 0.0), line=1))
    out = comp.add(Line2((10.0, 0.0), (10.0, -10.0), line=2, rapid=True))  # right turn: convex
    assert len(out) == 2
    corner = out[1]
    assert isinstance(corner, Line2) and corner.rapid and corner.line == 2
    assert math.dist(corner.start, (10.0, 1.0)) < TOL and math.dist(corner.end, (11.0, 0.0)) < TOL
    (last,) = comp.finish()
    assert last.rapid and math.dist(last.end, (11.0, -10.0)) < TOL


def test_corner_moves_normal_on_the_move_and_other_axes_on_the_corner():
    comp = CutterCompensator("left", 1.0, (0.0, 0.0))
    comp.add(Line2((0.0, 0.0), (10.0, 0.0), normal=-1.0, extra=(0.0,), line=1))
    out = comp.add(Line2((10.0, 0.0), (10.0, -10.0), normal=-3.0, extra=(90.0,), line=2))
    arc = out[1]
    assert isinstance(arc, Arc2)
    assert arc.normal == -1.0 and arc.extra == (90.0,)
    (line,) = comp.finish()
    assert line.normal == -3.0 and line.extra == (90.0,)


def test_held_commands_keep_their_place():
    comp = CutterCompensator("left", 1.0, (0.0, 0.0))
    assert comp.hold("before") == ["before"]  # nothing held yet: goes out at once
    comp.add(Line2((0.0, 0.0), (10.0, 0.0), line=1))
    assert comp.hold("feed") == []
    assert comp.hold("coolant") == []
    out = comp.add(Line2((10.0, 0.0), (10.0, 10.0), line=2))  # concave: line 1 is cut back
    assert [getattr(x, "line", x) for x in out] == [1, "feed", "coolant"]
    assert math.dist(out[0].end, (9.0, 1.0)) < TOL
    assert comp.hold("late") == []
    assert [getattr(x, "line", x) for x in comp.finish()] == [2, "late"]


def test_start_must_be_the_programmed_point():
    comp = CutterCompensator("left", 1.0, (0.0, 0.0))
    comp.add(Line2((0.0, 0.0), (10.0, 0.0)))
    assert comp.programmed == (10.0, 0.0)
    with pytest.raises(ValueError):
        comp.add(Line2((10.0, 1.0), (10.0, 5.0)))
    with pytest.raises(ValueError):
        CutterCompensator("up", 1.0, (0.0, 0.0))  # type: ignore[arg-type]


# --- lines and arcs -------------------------------------------------------------------------------


def stadium(length=12.0, radius=4.0):
    """A slot outline, counter-clockwise: two straights joined by tangent half circles."""
    a, b = length / 2, radius
    return [
        Line2((-a, -b), (a, -b), line=1),
        Arc2((a, -b), (a, b), (a, 0.0), True, line=2),
        Line2((a, b), (-a, b), line=3),
        Arc2((-a, b), (-a, -b), (-a, 0.0), True, line=4),
    ]


def d_shape():
    """Counter-clockwise: the chord from (4, 0) to (-4, 0), closed below by the major arc of the
    circle of radius 5 about (0, -3)."""
    return [Line2((4.0, 0.0), (-4.0, 0.0), line=1), Arc2((-4.0, 0.0), (4.0, 0.0), (0.0, -3.0), True, line=2)]


def lens():
    """Counter-clockwise: two arcs of radius 5 through (0, -4) and (0, 4), centres (-3, 0) and (3, 0)."""
    return [
        Arc2((0.0, -4.0), (0.0, 4.0), (-3.0, 0.0), True, line=1),
        Arc2((0.0, 4.0), (0.0, -4.0), (3.0, 0.0), True, line=2),
    ]


SHAPE_CASES = [(True, "left", True), (False, "right", True), (True, "right", False), (False, "left", False)]
"""(counter-clockwise, side, pocket): tool left of a counter-clockwise contour is inside it."""


def oriented(contour, ccw):
    return contour if ccw else reverse(contour)


@pytest.mark.parametrize(("ccw", "side", "pocket"), SHAPE_CASES)
@pytest.mark.parametrize("r", [1.0, 1.5])
def test_stadium_tangent_lines_and_arcs(ccw, side, pocket, r):
    contour = oriented(stadium(), ccw)
    start, moves = pocket_program(contour, (0.0, 0.0)) if pocket else outline_program(contour)
    _, out = run(side, r, start, moves)
    assert_continuous(start, out)
    assert_at_radius(out, contour, r)
    # tangent joints get no extra arcs: only the programmed half circles
    arcs = [s for s in out if isinstance(s, Arc2)]
    assert [a.line for a in arcs] == [m.line for m in moves if isinstance(m, Arc2)]
    for a in arcs:
        assert abs(math.dist(a.end, a.center) - (4.0 - r if pocket else 4.0 + r)) < TOL
    pts = boundary_points(contour)
    for seg in out[1:]:
        for p in samples(seg, 5):
            assert inside_polygon(p, pts) == pocket


@pytest.mark.parametrize(("ccw", "side", "pocket"), SHAPE_CASES)
def test_d_shape_line_arc_corners(ccw, side, pocket):
    r = 0.75
    contour = oriented(d_shape(), ccw)
    start, moves = pocket_program(contour, (0.0, -2.0)) if pocket else outline_program(contour)
    _, out = run(side, r, start, moves)
    assert_continuous(start, out)
    assert_at_radius(out, contour, r)
    corner_arcs = [s for s in out if isinstance(s, Arc2) and s.center in ((4.0, 0.0), (-4.0, 0.0))]
    pts = boundary_points(contour)
    for seg in out[1:]:
        for p in samples(seg, 5):
            assert inside_polygon(p, pts) == pocket
    if pocket:
        assert corner_arcs == []
        # the concave corner between chord and arc: on the chord's offset line y = -r and on the
        # arc's offset circle, radius 5 - r about (0, -3)
        x = math.sqrt((5.0 - r) ** 2 - (3.0 - r) ** 2)
        ends = [s.end for s in out]
        assert any(math.dist(e, (x if ccw else -x, -r)) < TOL for e in ends) or any(
            math.dist(e, (-x if ccw else x, -r)) < TOL for e in ends
        )
    else:
        assert len(corner_arcs) == 2
        for a in corner_arcs:
            assert abs(math.dist(a.start, a.center) - r) < TOL and a.ccw == (side == "right")


@pytest.mark.parametrize(("ccw", "side", "pocket"), SHAPE_CASES)
def test_lens_arc_to_arc_corners(ccw, side, pocket):
    r = 0.5
    contour = oriented(lens(), ccw)
    start, moves = pocket_program(contour, (0.0, 0.0)) if pocket else outline_program(contour)
    _, out = run(side, r, start, moves)
    assert_continuous(start, out)
    assert_at_radius(out, contour, r)
    corner_arcs = [s for s in out if isinstance(s, Arc2) and s.center in ((0.0, 4.0), (0.0, -4.0))]
    pts = boundary_points(contour)
    for seg in out[1:]:
        for p in samples(seg, 5):
            assert inside_polygon(p, pts) == pocket
    if pocket:
        assert corner_arcs == []
        # the offset circles (radius 4.5 about (±3, 0)) meet on the y axis
        yc = math.sqrt(4.5**2 - 3.0**2)
        ends = [s.end for s in out]
        assert any(math.dist(e, (0.0, yc)) < TOL for e in ends)
        assert any(math.dist(e, (0.0, -yc)) < TOL for e in ends)
    else:
        assert len(corner_arcs) == 2


def test_s_curve_tangent_arcs_then_line_at_an_angle():
    r = 0.5
    contour = [
        Arc2((0.0, 0.0), (4.0, 0.0), (2.0, 0.0), False, line=1),  # over the top, clockwise
        Arc2((4.0, 0.0), (8.0, 0.0), (6.0, 0.0), True, line=2),  # underneath, counter-clockwise: tangent
        Line2((8.0, 0.0), (8.0, 5.0), line=3),  # tangent, up
        Arc2((8.0, 5.0), (14.0, 5.0), (11.0, 5.0), False, line=4),  # tangent again
        Line2((14.0, 5.0), (12.0, 0.0), line=5),  # turning right, away from the tool: convex for G41
    ]
    start, lead = lead_in_line(contour)
    _, out = run("left", r, start, [lead, *contour])
    assert_continuous(start, out)
    assert_at_radius(out, contour, r)
    extra = [s for s in out if isinstance(s, Arc2) and s.center == (14.0, 5.0)]
    assert len(extra) == 1 and extra[0].line == 5 and not extra[0].ccw
    assert [s.line for s in out] == [0, 1, 2, 3, 4, 5, 5]


def test_concave_line_into_arc():
    # G41 going +x, then a counter-clockwise arc leaving at 60 degrees: tool inside, concave corner
    r = 1.0
    t = math.radians(60)
    c = (-5.0 * math.sin(t), 5.0 * math.cos(t))  # left of the arc's start tangent (cos 60, sin 60)
    end = (c[0] + 5.0 * math.cos(math.radians(10)), c[1] + 5.0 * math.sin(math.radians(10)))
    contour = [Line2((-10.0, 0.0), (0.0, 0.0), line=1), Arc2((0.0, 0.0), end, c, True, line=2)]
    start = (-10.0, -3.0)
    _, out = run("left", r, start, [Line2(start, (-10.0, 0.0), line=0), *contour])
    assert_continuous(start, out)
    assert_at_radius(out, contour, r)
    # the corner: on y = r and on the circle of radius 5 - r about c, the crossing ahead along +x
    x = c[0] + math.sqrt((5.0 - r) ** 2 - (r - c[1]) ** 2)
    assert math.dist(out[2].end, (x, r)) < TOL


@pytest.mark.parametrize(
    ("kink", "corner_arc", "cut_back"),
    [(0.03, False, False), (-0.03, False, False), (-0.1, True, False), (0.1, False, True)],
)
def test_near_tangent_corners_are_joined_directly(kink, corner_arc, cut_back):
    # LinuxCNC treats corners within 0.05 rad of tangent as tangent: no arc, no cut-back
    r = 1.0
    bend = (10.0 + 10.0 * math.cos(kink), 10.0 * math.sin(kink))  # positive kink: left turn
    _, out = run("left", r, (0.0, 0.0), polyline([(0.0, 0.0), (10.0, 0.0), bend]))
    assert_continuous((0.0, 0.0), out)
    assert any(isinstance(s, Arc2) for s in out) == corner_arc
    assert (out[0].end[0] < 10.0 - TOL) == cut_back
    if not corner_arc and not cut_back:
        assert out[0].end == (10.0, r) and out[1].start == (10.0, r)
    normal = (-math.sin(kink), math.cos(kink))
    assert math.dist(out[-1].end, (bend[0] + r * normal[0], bend[1] + r * normal[1])) < TOL


@pytest.mark.parametrize("turns", [1, 3])
def test_full_circle_outline(turns):
    # a lead-in along the tangent, then a whole circle (start == end), with extra turns carried
    r = 0.5
    circle = Arc2((0.0, -5.0), (0.0, -5.0), (0.0, 0.0), True, line=1, turns=turns)
    _, out = run("right", r, (-8.0, -5.0), [Line2((-8.0, -5.0), (0.0, -5.0), line=0), circle])
    assert len(out) == 2
    arc = out[1]
    assert isinstance(arc, Arc2) and arc.turns == turns and arc.ccw
    assert math.dist(arc.start, (0.0, -5.5)) < TOL and math.dist(arc.end, (0.0, -5.5)) < TOL
    assert_at_radius(out, [circle], r)


def test_h_shape_reversal_from_an_arc_onto_a_line():
    # LinuxCNC's "h": G42 over the hump (counter-clockwise, tool outside), then straight back up the
    # stem. The tool stays above the hump and right of the stem instead of looping round below.
    r = 0.25
    contour = [Arc2((2.0, 0.0), (0.0, 0.0), (1.0, 0.0), True, line=1), Line2((0.0, 0.0), (0.0, 5.0), line=2)]
    start, lead = lead_in_line(contour)
    _, out = run("right", r, start, [lead, *contour])
    assert_continuous(start, out)
    assert_at_radius(out, contour, r)
    corner = (r, 2 * math.sqrt(r))  # x = r meets the offset circle of radius 1 + r about (1, 0)
    assert [s.line for s in out] == [0, 1, 2]
    assert math.dist(out[1].end, corner) < TOL and math.dist(out[2].end, (r, 5.0)) < TOL


def test_h_shape_reversal_from_a_line_onto_an_arc():
    # the same "h" the other way: G41 down the stem, then back up over the hump (clockwise, outside)
    r = 0.25
    contour = [Line2((0.0, 5.0), (0.0, 0.0), line=1), Arc2((0.0, 0.0), (2.0, 0.0), (1.0, 0.0), False, line=2)]
    start, lead = lead_in_line(contour)
    _, out = run("left", r, start, [lead, *contour])
    assert_continuous(start, out)
    assert_at_radius(out, contour, r)
    assert [s.line for s in out] == [0, 1, 2]
    assert math.dist(out[1].end, (r, 2 * math.sqrt(r))) < TOL
    assert math.dist(out[2].end, (2.0 + r, 0.0)) < TOL


def test_m_shape_reversal_between_tangent_arcs():
    # LinuxCNC's "m": over one hump and straight on over the next, G41 outside both; at the middle
    # stroke the tool meets both offset circles above it rather than looping round below
    r = 0.25
    contour = [
        Arc2((0.0, 0.0), (2.0, 0.0), (1.0, 0.0), False, line=1),
        Arc2((2.0, 0.0), (4.0, 0.0), (3.0, 0.0), False, line=2),
    ]
    start, lead = lead_in_line(contour)
    _, out = run("left", r, start, [lead, *contour])
    assert_continuous(start, out)
    assert_at_radius(out, contour, r)
    assert [s.line for s in out] == [0, 1, 2]
    assert math.dist(out[1].end, (2.0, math.sqrt((1 + r) ** 2 - 1))) < TOL


# --- errors ---------------------------------------------------------------------------------------


def test_inside_arc_smaller_than_tool():
    comp = CutterCompensator("left", 2.0, (-10.0, -5.0))
    comp.add(Line2((-10.0, -5.0), (0.0, -5.0), line=1))
    with pytest.raises(GCodeError) as err:
        comp.add(Arc2((0.0, -5.0), (0.0, -1.0), (0.0, -3.0), True, line=2))  # radius 2, tool inside
    assert err.value.message == "Tool radius not less than arc radius with comp"
    assert err.value.line == 2
    # the same arc with the tool outside is fine
    comp = CutterCompensator("right", 2.0, (-10.0, -5.0))
    comp.add(Line2((-10.0, -5.0), (0.0, -5.0), line=1))
    out = comp.add(Arc2((0.0, -5.0), (0.0, -1.0), (0.0, -3.0), True, line=2))
    assert [s.line for s in out] == [1]
    (arc,) = comp.finish()
    assert math.dist(arc.end, (0.0, 1.0)) < TOL and arc.center == (0.0, -3.0)


def test_arc_to_line_corner_the_tool_cannot_fit():
    # tool inside a counter-clockwise arc of radius 2.5 (offset circle radius 0.5 about the origin);
    # the next line turns left so hard that its offset line passes 1.5 from the origin
    comp = CutterCompensator("left", 2.0, (0.0, -12.5))
    comp.add(Line2((0.0, -12.5), (0.0, -2.5), line=1))
    comp.add(Arc2((0.0, -2.5), (2.5, 0.0), (0.0, 0.0), True, line=2))
    with pytest.raises(GCodeError) as err:
        comp.add(Line2((2.5, 0.0), (-2.5, 1.0), line=3))
    assert err.value.message == (
        "Arc to straight motion makes a corner the compensated tool can't fit in without gouging"
    )
    assert err.value.line == 3


def test_line_to_arc_corner_the_tool_cannot_fit():
    comp = CutterCompensator("left", 2.0, (-10.0, 0.0))
    comp.add(Line2((-10.0, 0.0), (0.0, 0.0), line=1))
    with pytest.raises(GCodeError) as err:
        # turning left into a tight arc (radius 2.5): its offset circle (radius 0.5) never reaches y = 2
        comp.add(Arc2((0.0, 0.0), (-2.5, 2.5), (-2.5, 0.0), True, line=2))
    assert err.value.message == "Arc move in concave corner cannot be reached by the tool without gouging"


def test_arc_to_arc_corner_the_tool_cannot_fit():
    # a lens pocket with a tool too big for its tips: the offset circles (radius 0.5) do not meet
    comp = CutterCompensator("left", 4.5, (0.0, -12.0))
    with pytest.raises(GCodeError) as err:
        for m in [Line2((0.0, -12.0), (0.0, -4.0), line=0), *lens()]:
            comp.add(m)
    assert err.value.message == ARC_ARC_GOUGE


def test_arc_cut_back_past_its_start():
    # a short arc (0.1 rad of a radius 5 circle) with the tool outside, then a 120 degree concave turn
    # whose corner lies further back along the offset circle than the arc is long
    r = 2.0
    c = (0.0, 5.0)
    a_end = (5.0 * math.sin(0.1), 5.0 - 5.0 * math.cos(0.1))
    tangent = (math.cos(0.1), math.sin(0.1))
    turn = math.radians(-120)  # right turn: concave for G42
    d = (
        tangent[0] * math.cos(turn) - tangent[1] * math.sin(turn),
        tangent[0] * math.sin(turn) + tangent[1] * math.cos(turn),
    )
    comp = CutterCompensator("right", r, (-10.0, 0.0))
    comp.add(Line2((-10.0, 0.0), (0.0, 0.0), line=1))
    comp.add(Arc2((0.0, 0.0), a_end, c, True, line=2))
    with pytest.raises(GCodeError) as err:
        comp.add(Line2(a_end, (a_end[0] + 10 * d[0], a_end[1] + 10 * d[1]), line=3))
    assert err.value.message == "Arc move in concave corner cannot be reached by the tool without gouging"
    assert err.value.line == 3


def test_finish_checks_the_held_move():
    # a right wall too short for the two concave corners: the last move is reversed when released
    comp = CutterCompensator("left", 2.0, (0.0, 0.0))
    comp.add(Line2((0.0, 0.0), (10.0, 0.0), line=1))
    comp.add(Line2((10.0, 0.0), (10.0, 10.0), line=2))
    comp.add(Line2((10.0, 10.0), (9.0, 10.0), line=3))  # 1 long; starts 2 in from x = 10
    with pytest.raises(GCodeError) as err:
        comp.finish()
    assert err.value.message == FEED_GOUGE
    assert err.value.line == 0  # the core names the G40 / M2 block


# --- random polygons ------------------------------------------------------------------------------


def convex_hull(points):
    pts = sorted(set(points))
    if len(pts) < 3:
        return pts

    def half(seq):
        h = []
        for p in seq:
            while (
                len(h) >= 2
                and (h[-1][0] - h[-2][0]) * (p[1] - h[-2][1]) - (h[-1][1] - h[-2][1]) * (p[0] - h[-2][0]) <= 0
            ):
                h.pop()
            h.append(p)
        return h

    lower, upper = half(pts), half(reversed(pts))
    return lower[:-1] + upper[:-1]  # counter-clockwise


coords = st.floats(min_value=-50.0, max_value=50.0, allow_nan=False)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(st.lists(st.tuples(coords, coords), min_size=3, max_size=12), st.floats(0.01, 8.0))
def test_random_convex_outline_stays_at_radius(points, r):
    hull = convex_hull(points)
    assume(len(hull) >= 3)
    n = len(hull)
    for i in range(n):
        a, b, c = hull[i - 1], hull[i], hull[(i + 1) % n]
        assume(math.dist(a, b) > 1e-2)
        turn = math.atan2(
            (b[0] - a[0]) * (c[1] - b[1]) - (b[1] - a[1]) * (c[0] - b[0]),
            (b[0] - a[0]) * (c[0] - b[0]) + (b[1] - a[1]) * (c[1] - b[1]),
        )
        assume(turn > 0.06)  # LinuxCNC joins corners within 0.05 rad of tangent without an arc
    d = (hull[1][0] - hull[0][0], hull[1][1] - hull[0][1])
    length = math.hypot(*d)
    start = (hull[0][0] - (r + 5) * d[0] / length, hull[0][1] - (r + 5) * d[1] / length)
    path = [start, *hull, hull[0], hull[1]]
    try:
        _, out = run("right", r, start, polyline(path))
    except GCodeError as e:  # pragma: no cover - a convex outline has no gouging corner
        raise AssertionError(f"unexpected {e}") from e
    assert_continuous(start, out)
    contour = closed_contour(hull)
    for seg in out[1:]:
        for p in samples(seg, 12):
            assert abs(dist_to_contour(p, contour) - r) < 1e-9 * max(1.0, r)
    arcs = [s for s in out if isinstance(s, Arc2)]
    assert len(arcs) == n
    assert abs(sum(abs(arc_span(a.start, a.end, a.center, a.ccw)) for a in arcs) - 2 * math.pi) < 1e-9


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.tuples(st.floats(0.0, 2 * math.pi), st.floats(1.0, 30.0)), min_size=3, max_size=10),
    st.floats(0.01, 6.0),
    st.sampled_from(["left", "right"]),
    st.lists(st.booleans(), min_size=10, max_size=10),
)
def test_random_star_polygons_only_gcode_errors(polar, r, side, arcs_at):
    polar = sorted(polar)
    pts = [(rad * math.cos(a), rad * math.sin(a)) for a, rad in polar]
    assume(all(math.dist(p, q) > 1e-3 for p, q in zip(pts, pts[1:] + pts[:1], strict=True)))
    moves = [Line2((0.0, 0.0), pts[0], line=0)]
    for i, (p, q) in enumerate(zip(pts, pts[1:] + pts[:1], strict=True)):
        if arcs_at[i % len(arcs_at)]:
            # a bulging arc through the chord's ends, centre on the chord's perpendicular bisector
            m = ((p[0] + q[0]) / 2, (p[1] + q[1]) / 2)
            half = math.dist(p, q) / 2
            nx, ny = -(q[1] - p[1]) / (2 * half), (q[0] - p[0]) / (2 * half)
            k = half * (0.3 if i % 2 else -0.6)
            moves.append(Arc2(p, q, (m[0] + k * nx, m[1] + k * ny), bool(i % 3), line=i + 1))
        else:
            moves.append(Line2(p, q, line=i + 1))
    comp = CutterCompensator(side, r, (0.0, 0.0))
    out = []
    try:
        for m in moves:
            out += comp.add(m)
        out += comp.finish()
    except GCodeError as e:
        assert e.message and e.line >= 0
        event(e.message)
        return
    event("compensated")
    pos = (0.0, 0.0)
    for seg in out:
        assert math.dist(seg.start, pos) < 1e-6
        pos = seg.end
        assert all(math.isfinite(v) for v in (*seg.start, *seg.end))
