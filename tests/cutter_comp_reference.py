"""The independent reference of the cutter-compensation tests: plain distance geometry (a point's
distance to a programmed contour, samples along a move, a point inside a polygon), the checks built on
it (continuous, one radius from the contour), the programs the tests compensate, and LinuxCNC's error
texts spelled out. Nothing here comes from the compensator: a change in it shows up as a failure."""

from __future__ import annotations

import itertools
import math

from gcode_canon.cutter_comp import Arc2, CutterCompensator, Line2

TOL = 1e-9

# LinuxCNC's texts, spelled out here (not imported) so a change in the module shows up as a failure
FEED_GOUGE = "Straight feed in concave corner cannot be reached by the tool without gouging"
TRAVERSE_GOUGE = "Straight traverse in concave corner cannot be reached by the tool without gouging"
ARC_ARC_GOUGE = "Arc to arc motion makes a corner the compensated tool can't fit in without gouging"

# --- independent reference geometry ---------------------------------------------------------------


def angle_of(p, c):
    return math.atan2(p[1] - c[1], p[0] - c[0])


def arc_span(a, b, c, ccw):
    """Signed angle swept from a to b around c (full circle when a == b)."""
    d = (angle_of(b, c) - angle_of(a, c)) % (2 * math.pi)
    if ccw:
        return d if d > 1e-15 else 2 * math.pi
    d = (2 * math.pi - d) % (2 * math.pi)
    return -(d if d > 1e-15 else 2 * math.pi)


def dist_to_segment(p, seg):
    if isinstance(seg, Line2):
        (ax, ay), (bx, by) = seg.start, seg.end
        vx, vy = bx - ax, by - ay
        ll = vx * vx + vy * vy
        t = 0.0 if ll == 0 else max(0.0, min(1.0, ((p[0] - ax) * vx + (p[1] - ay) * vy) / ll))
        return math.hypot(p[0] - ax - t * vx, p[1] - ay - t * vy)
    c = seg.center
    radius = math.hypot(seg.start[0] - c[0], seg.start[1] - c[1])
    span = arc_span(seg.start, seg.end, c, seg.ccw)
    rel = (angle_of(p, c) - angle_of(seg.start, c)) % (2 * math.pi)
    if not seg.ccw:
        rel = (2 * math.pi - rel) % (2 * math.pi)
    if rel <= abs(span) + 1e-12:
        return abs(math.hypot(p[0] - c[0], p[1] - c[1]) - radius)
    return min(math.dist(p, seg.start), math.dist(p, seg.end))


def dist_to_contour(p, contour):
    return min(dist_to_segment(p, s) for s in contour)


def samples(seg, n=60):
    if isinstance(seg, Line2):
        (x0, y0), (x1, y1) = seg.start, seg.end
        return [(x0 + (x1 - x0) * k / n, y0 + (y1 - y0) * k / n) for k in range(n + 1)]
    c = seg.center
    radius = math.hypot(seg.end[0] - c[0], seg.end[1] - c[1])
    a0 = angle_of(seg.start, c)
    span = arc_span(seg.start, seg.end, c, seg.ccw)
    return [
        (c[0] + radius * math.cos(a0 + span * k / n), c[1] + radius * math.sin(a0 + span * k / n))
        for k in range(n + 1)
    ]


def seg_length(seg):
    if isinstance(seg, Line2):
        return math.dist(seg.start, seg.end)
    radius = math.hypot(seg.end[0] - seg.center[0], seg.end[1] - seg.center[1])
    return radius * abs(arc_span(seg.start, seg.end, seg.center, seg.ccw))


def inside_polygon(p, pts):
    """Ray casting, for points clearly inside or outside."""
    x, y = p
    inside = False
    for (x1, y1), (x2, y2) in zip(pts, pts[1:] + pts[:1], strict=True):
        if (y1 > y) != (y2 > y) and x < x1 + (y - y1) * (x2 - x1) / (y2 - y1):
            inside = not inside
    return inside


def assert_continuous(start, out):
    pos = start
    for seg in out:
        assert math.dist(seg.start, pos) < TOL, (seg, pos)
        pos = seg.end
    return pos


def assert_at_radius(out, contour, r, skip_first=True):
    for seg in out[1:] if skip_first else out:
        for p in samples(seg):
            d = dist_to_contour(p, contour)
            assert abs(d - r) < TOL, (seg, p, d)


# --- programs -------------------------------------------------------------------------------------


def polyline(points, line0=10):
    return [Line2(a, b, line=line0 + i) for i, (a, b) in enumerate(itertools.pairwise(points))]


def run(side, radius, start, moves):
    comp = CutterCompensator(side, radius, start)
    out = []
    for m in moves:
        out += comp.add(m)
    out += comp.finish()
    return comp, out


def rect(w, h, ccw=True):
    """Corners of a w x h rectangle about the origin, bottom edge first, in the given sense."""
    p0, p1, p2, p3 = (-w / 2, -h / 2), (w / 2, -h / 2), (w / 2, h / 2), (-w / 2, h / 2)
    return [p0, p1, p2, p3] if ccw else [p1, p0, p3, p2]


def closed_contour(pts):
    return polyline([*pts, pts[0]])


def reverse(contour):
    out = []
    for i, s in enumerate(reversed(contour)):
        if isinstance(s, Line2):
            out.append(Line2(s.end, s.start, line=i + 1))
        else:
            out.append(Arc2(s.end, s.start, s.center, not s.ccw, line=i + 1))
    return out


def first_half(seg):
    """The first half of a programmed move (to end a program in the middle of an edge)."""
    if isinstance(seg, Line2):
        return Line2(seg.start, ((seg.start[0] + seg.end[0]) / 2, (seg.start[1] + seg.end[1]) / 2), line=99)
    c = seg.center
    radius = math.dist(seg.start, c)
    a = angle_of(seg.start, c) + arc_span(seg.start, seg.end, c, seg.ccw) / 2
    return Arc2(seg.start, (c[0] + radius * math.cos(a), c[1] + radius * math.sin(a)), c, seg.ccw, line=99)


def lead_in_line(contour, dist=6.0):
    """A lead-in along the tangent at the contour's start, from outside."""
    first = contour[0]
    if isinstance(first, Line2):
        d = ((first.end[0] - first.start[0]), (first.end[1] - first.start[1]))
    else:
        rx, ry = first.start[0] - first.center[0], first.start[1] - first.center[1]
        d = (-ry, rx) if first.ccw else (ry, -rx)
    n = math.hypot(*d)
    start = (first.start[0] - dist * d[0] / n, first.start[1] - dist * d[1] / n)
    return start, Line2(start, first.start, line=0)


def outline_program(contour):
    start, lead = lead_in_line(contour)
    return start, [lead, *contour, contour[0]]


def pocket_program(contour, start):
    return start, [Line2(start, contour[0].start, line=0), *contour, first_half(contour[0])]


def boundary_points(contour):
    return [p for s in contour for p in samples(s, 40)[:-1]]
