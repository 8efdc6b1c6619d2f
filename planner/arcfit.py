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

import numpy as np

ARC_MAX_SWEEP = math.pi  # a merged arc turns by at most this (the three-point fit stays well posed)
ARC_MAX_RADIUS = 1e5  # mm: flatter than this is a line (and positions would lose digits)
ARC_MIN_RADIUS = 1e-3  # mm
REFINE_WITHIN = 4.0  # a three-point arc within this many tolerances of its points gets a better centre
REFINE_STEPS = 40  # bisection steps for that centre


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
            planes: Sequence[tuple[int, int]], refine: bool = False, point_tol: float | None = None,
            ) -> ArcFit | None:
    """The arc through ``start``, the middle one of ``points`` (the interior programmed points, in
    order) and ``end``, in whichever of ``planes`` the three points span most, if it stays within
    ``tol`` of the polyline ``start, *points, end`` and within ``point_tol`` (default ``tol``) of each
    programmed point (else None).

    The bound: a programmed point at angle ``f`` (as a share of the sweep) lies ``d`` from the arc's
    point at that angle (the radial difference and the other axes' differences). Between two
    consecutive points (``h`` apart along the arc), the arc is within ``h^2/8 |q''|`` of the chord
    through its own points at their angles (``|q''| = r k^2`` on an arc of curvature ``k`` per unit
    ``s``), and that chord within the larger ``d`` of the programmed chord. Angles must not go back:
    each programmed move advances along the arc.

    With ``refine`` (where the tolerance is the coordinates' rounding itself, so that the noise of the
    middle point alone can spoil the three-point circle), a circle that misses by at most
    ``REFINE_WITHIN`` tolerances is tried again about the centre that fits all the points best.
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
    sense = 1.0 if cross > 0.0 else -1.0
    point_tol = tol if point_tol is None else min(point_tol, tol)
    give_up = REFINE_WITHIN if refine else 1.0
    fit, miss = _about(start, points, end, tol, point_tol, i0, i1, ux, uy, sense, give_up)
    if fit is None and refine and 1.0 < miss <= REFINE_WITHIN:
        # rounding noise on the middle point moved the circle: the centre that fits all points best
        ux, uy = _refined_centre(start, points, end, i0, i1, ux, uy)
        fit, miss = _about(start, points, end, tol, point_tol, i0, i1, ux, uy, sense, 1.0)
    return fit


def _about(start: Sequence[float], points: Sequence[Sequence[float]], end: Sequence[float], tol: float,
           point_tol: float, i0: int, i1: int, ux: float, uy: float, sense: float, give_up: float,
           ) -> tuple[ArcFit | None, float]:
    """The arc about ``start + (ux, uy)`` in the plane ``i0 i1`` turning in ``sense`` from ``start`` to
    ``end``, checked against the points (:func:`fit_arc`'s bound within ``tol``, each point within
    ``point_tol``), and by how much it misses at most, as a multiple of the tolerance (infinite where
    the arc is refused for another reason: radius, sweep, a move going back); the check stops at a
    miss above ``give_up``."""
    r = math.hypot(ux, uy)
    if not ARC_MIN_RADIUS <= r <= ARC_MAX_RADIUS:
        return None, math.inf
    bx, by = end[i0] - start[i0], end[i1] - start[i1]
    two_pi = 2.0 * math.pi
    th_s = math.atan2(-uy, -ux)
    sweep_abs = (sense * (math.atan2(by - uy, bx - ux) - th_s)) % two_pi
    if not 0.0 < sweep_abs <= ARC_MAX_SWEEP:
        return None, math.inf
    c0, c1 = start[i0] + ux, start[i1] + uy
    others = [k for k in range(len(start)) if k not in (i0, i1)]
    rise = [end[k] - start[k] for k in others]
    arc_len = sweep_abs * r
    length = math.sqrt(arc_len * arc_len + sum(x * x for x in rise))
    curv = r * (sweep_abs / length) ** 2  # |q''| along s
    sag = 0.125 * curv * length * length  # h^2/8 |q''| = sag * (df)^2
    starts = [0.0]
    prev_f = prev_d = dev = miss = 0.0
    for p in points:
        dx, dy = p[i0] - c0, p[i1] - c1
        phi = (sense * (math.atan2(dy, dx) - th_s)) % two_pi
        if phi > sweep_abs:
            return None, math.inf
        f = phi / sweep_abs
        if f < prev_f:
            return None, math.inf  # the move goes back along the arc
        e = math.hypot(dx, dy) - r
        g2 = 0.0
        for k, z in zip(others, rise, strict=True):
            g = p[k] - start[k] - f * z
            g2 += g * g
        d = math.sqrt(e * e + g2)
        df = f - prev_f
        worst = max(d, prev_d) + sag * df * df
        if worst > dev:
            dev = worst
        worst = max(worst / tol, d / point_tol)
        if worst > miss:
            miss = worst
            if miss > give_up:
                return None, miss
        starts.append(f * length)
        prev_f, prev_d = f, d
    df = 1.0 - prev_f
    dev = max(dev, prev_d + sag * df * df)
    miss = max(miss, dev / tol)
    if miss > 1.0:
        return None, miss
    return ArcFit(i0, i1, c0, c1, sense * sweep_abs, length, starts, dev), miss


def _refined_centre(start: Sequence[float], points: Sequence[Sequence[float]], end: Sequence[float], i0: int,
                    i1: int, ux: float, uy: float) -> tuple[float, float]:
    """The centre (relative to ``start``) on the perpendicular bisector of ``start``-``end`` that
    minimises the largest radial distance of the points from the circle through both, to first order
    about ``(ux, uy)``: each point's distance is ``e + b t`` for a shift ``t`` of the centre along the
    bisector's unit normal; the minimum of ``max |e + b t|`` (convex) is found by bisection on the
    sign of its slope."""
    bx, by = end[i0] - start[i0], end[i1] - start[i1]
    chord = math.hypot(bx, by)
    nx, ny = -by / chord, bx / chord
    mx, my = 0.5 * bx, 0.5 * by
    t0 = (ux - mx) * nx + (uy - my) * ny
    r = math.hypot(ux, uy)
    pts = np.asarray(points, dtype=float)
    dx, dy = pts[:, i0] - start[i0] - ux, pts[:, i1] - start[i1] - uy
    rho = np.hypot(dx, dy)
    e = rho - r
    b = -(dx * nx + dy * ny) / rho - t0 / r
    span = 2.0 * float(np.abs(e).max()) / max(float(np.abs(b).max()), 1e-12)
    lo, hi = -span, span
    for _ in range(REFINE_STEPS):
        t = 0.5 * (lo + hi)
        v = e + b * t
        k = int(np.argmax(np.abs(v)))
        if v[k] * b[k] > 0.0:
            hi = t
        else:
            lo = t
    t = t0 + 0.5 * (lo + hi)
    return mx + t * nx, my + t * ny
