"""Fitting one circular arc (or helix) to a run of programmed points, with a rigorous bound on how far
the arc strays from the programmed polyline: what lets ``planner.merging`` plan the dense chords CAM
writes for a curve as one arc.

Why an arc and not only lines: merged into lines, chords of a curve become lines of at most
``sqrt(8 R tol)`` each; every join between them is a corner that a blend, span or transition must
ease, and each is a profile of its own. One arc is one piece with a constant speed cap, as if the
program had said G2/G3.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

ARC_MAX_SWEEP = math.pi  # a merged arc turns by at most this (the three-point fit stays well posed)
ARC_MAX_RADIUS = 1e5  # mm: flatter than this is a line (and positions would lose digits)
ARC_MIN_RADIUS = 1e-3  # mm


@dataclass(slots=True)
class ArcFit:
    """An arc from the run's start to its end in the plane of axes ``i0 i1`` about ``(c0, c1)``,
    turning by ``sweep`` (radians, positive from ``i0`` towards ``i1``), the other axes linear in the
    angle; ``length`` along ``s`` (over all axes, as a merged line's); ``starts`` where each
    programmed move begins along ``s``; ``dev`` bounds the distance of the arc from the programmed
    polyline."""

    i0: int
    i1: int
    c0: float
    c1: float
    sweep: float
    length: float
    starts: list[float]
    dev: float


def fit_arc(start: Sequence[float], points: Sequence[Sequence[float]], end: Sequence[float], tol: float,
            planes: Sequence[tuple[int, int]]) -> ArcFit | None:
    """The arc through ``start``, the middle one of ``points`` (the interior programmed points, in
    order) and ``end``, in whichever of ``planes`` the three points span most, if it stays within
    ``tol`` of the polyline ``start, *points, end`` (else None).

    The bound: a programmed point at angle ``f`` (as a share of the sweep) lies ``d`` from the arc's
    point at that angle (the radial difference and the other axes' differences). Between two
    consecutive points (``h`` apart along the arc), the arc is within ``h^2/8 |q''|`` of the chord
    through its own points at their angles (``|q''| = r k^2`` on an arc of curvature ``k`` per unit
    ``s``), and that chord within the larger ``d`` of the programmed chord. Angles must not go back:
    each programmed move advances along the arc.
    """
    if not points or not planes:
        return None
    mid = points[len(points) // 2]
    best = None
    for i0, i1 in planes:
        ax, ay = mid[i0] - start[i0], mid[i1] - start[i1]
        bx, by = end[i0] - start[i0], end[i1] - start[i1]
        cross = ax * by - ay * bx
        if best is None or abs(cross) > abs(best[2]):
            best = (i0, i1, cross, ax, ay, bx, by)
    assert best is not None
    i0, i1, cross, ax, ay, bx, by = best
    a2, b2 = ax * ax + ay * ay, bx * bx + by * by
    if abs(cross) <= 1e-12 * (a2 + b2):
        return None  # the three points are collinear: a line's business
    ux = (by * a2 - ay * b2) / (2.0 * cross)
    uy = (ax * b2 - bx * a2) / (2.0 * cross)
    r = math.hypot(ux, uy)
    if not ARC_MIN_RADIUS <= r <= ARC_MAX_RADIUS:
        return None
    sense = 1.0 if cross > 0.0 else -1.0
    two_pi = 2.0 * math.pi
    th_s = math.atan2(-uy, -ux)
    sweep_abs = (sense * (math.atan2(by - uy, bx - ux) - th_s)) % two_pi
    if not 0.0 < sweep_abs <= ARC_MAX_SWEEP:
        return None
    c0, c1 = start[i0] + ux, start[i1] + uy
    others = [k for k in range(len(start)) if k not in (i0, i1)]
    rise = [end[k] - start[k] for k in others]
    arc_len = sweep_abs * r
    length = math.sqrt(arc_len * arc_len + sum(x * x for x in rise))
    curv = r * (sweep_abs / length) ** 2  # |q''| along s
    sag = 0.125 * curv * length * length  # h^2/8 |q''| = sag * (df)^2
    starts = [0.0]
    prev_f = prev_d = dev = 0.0
    for p in points:
        dx, dy = p[i0] - c0, p[i1] - c1
        phi = (sense * (math.atan2(dy, dx) - th_s)) % two_pi
        if phi > sweep_abs:
            return None
        f = phi / sweep_abs
        if f < prev_f:
            return None  # the move goes back along the arc
        e = math.hypot(dx, dy) - r
        g2 = 0.0
        for k, z in zip(others, rise, strict=True):
            g = p[k] - start[k] - f * z
            g2 += g * g
        d = math.sqrt(e * e + g2)
        df = f - prev_f
        worst = max(d, prev_d) + sag * df * df
        if worst > tol:
            return None
        if worst > dev:
            dev = worst
        starts.append(f * length)
        prev_f, prev_d = f, d
    df = 1.0 - prev_f
    worst = prev_d + sag * df * df
    if worst > tol:
        return None
    return ArcFit(i0, i1, c0, c1, sense * sweep_abs, length, starts, max(dev, worst))
