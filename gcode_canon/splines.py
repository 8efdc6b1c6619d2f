"""Splines and NURBS (G5, G5.1, G5.2/G5.3) as LinuxCNC moves them.

LinuxCNC's interpreter hands the control points to its canon (``NURBS_G5_FEED``), which approximates
the curve by arcs: the curve is sampled at ``4 x (number of control points)`` equal steps of its
parameter, and each pair of samples with their tangents is joined by a biarc (two tangent-continuous
arcs), or by a straight line where the biarc degenerates. This module is that computation, in the
plane's own coordinates ``(first, second)`` (:class:`gcode_canon.commands.Plane`): the same knot
vector (clamped, integer knots), the same basis functions (Cox-de Boor with LinuxCNC's closed
intervals at order 1), the same tangent (a central difference of 1e-5 in the parameter) and the same
biarc construction (equal ratio ``r = 1``), so the moves are LinuxCNC's.

Where LinuxCNC emits nothing for a sample step (no real biarc: the next arc would then start where
the machine is not), canon joins the two samples by a straight line.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from dataclasses import dataclass

_DU = 1e-5  # LinuxCNC nurbs_G5_tangent's parameter step
_SMALL = 1e-6  # emccanon arc(): below it the arc is a straight line
_BETA_MAX = 1.0 / 1e-8  # emccanon biarc(): 1 / CART_FUZZ


@dataclass(frozen=True, slots=True)
class SplineMove:
    """One move in plane coordinates: ``centre`` None is a straight feed; else an arc, ``ccw`` its
    sense seen from the plane's positive normal."""

    end: tuple[float, float]
    centre: tuple[float, float] | None = None
    ccw: bool = True


def knot_vector(n: int, k: int) -> list[float]:
    """Clamped uniform knots for control points 0..n and order k (LinuxCNC's
    ``nurbs_G5_knot_vector_creator``)."""
    return [0.0 if i < k else float(i - k + 1) if i <= n else float(n - k + 2) for i in range(n + k + 1)]


def _basis(n_points: int, k: int, u: float, kv: list[float]) -> list[float]:
    """N(i, k, u) for every control point i, the recursion of ``nurbs_G5_Nmix`` evaluated bottom-up
    (order 1 holds on the closed interval, as LinuxCNC's does; 0/0 terms are left out)."""
    size = n_points + k - 1
    prev = [1.0 if kv[i] <= u <= kv[i + 1] else 0.0 for i in range(size)]
    for order in range(2, k + 1):
        cur = []
        for i in range(size - order + 1):
            left_den = kv[i + order - 1] - kv[i]
            right_den = kv[i + order] - kv[i + 1]
            left = (u - kv[i]) * prev[i] / left_den if left_den != 0 else 0.0
            right = (kv[i + order] - u) * prev[i + 1] / right_den if right_den != 0 else 0.0
            cur.append(left + right)
        prev = cur
    return prev[:n_points]


def point(u: float, k: int, cps: list[tuple[float, float, float]], kv: list[float]) -> tuple[float, float]:
    """The curve at parameter u (``nurbs_G5_point``); cps are (first, second, weight)."""
    basis = _basis(len(cps), k, u, kv)
    den = 0.0
    for b, cp in zip(basis, cps, strict=True):
        den += b * cp[2]
    x = y = 0.0
    for b, cp in zip(basis, cps, strict=True):
        x += _div(cp[0] * b * cp[2], den)  # den 0 (weights not all positive): inf or NaN, as in C
        y += _div(cp[1] * b * cp[2], den)
    return x, y


def tangent(u: float, k: int, cps: list[tuple[float, float, float]], kv: list[float]) -> tuple[float, float]:
    """Unit tangent at u by a central difference (``nurbs_G5_tangent``)."""
    lo, hi = max(kv[0], u - _DU), min(kv[-1], u + _DU)  # G5.2: 0 and n - k + 2
    p1, p3 = point(lo, k, cps, kv), point(hi, k, cps, kv)
    return _unit((p3[0] - p1[0]) / (hi - lo), (p3[1] - p1[1]) / (hi - lo))


def _unit(x: float, y: float) -> tuple[float, float]:
    h = math.hypot(x, y)
    return (x / h, y / h) if h != 0 else (x, y)


def _div(a: float, b: float) -> float:
    """a / b with IEEE results for b == 0, as the C code computes it."""
    if b != 0:
        return a / b
    if a == 0 or math.isnan(a):
        return math.nan
    return math.copysign(math.inf, a) * math.copysign(1.0, b)


def _arc(p0: tuple[float, float], p1: tuple[float, float], d: tuple[float, float]) -> SplineMove:
    """The arc from p0 to p1 leaving p0 along d (emccanon's ``arc``), or a line."""
    x, y = p1[0] - p0[0], p1[1] - p0[1]
    den = 2 * (y * d[0] - x * d[1])
    if abs(den) <= _SMALL:
        return SplineMove(p1)
    r = -(x * x + y * y) / den
    return SplineMove(p1, (p0[0] + d[1] * r, p0[1] - d[0] * r), r < 0)


def biarc(p0: tuple[float, float], ts: tuple[float, float], p4: tuple[float, float],
          te: tuple[float, float], r: float = 1.0) -> list[SplineMove]:
    """Two arcs from p0 (tangent ts) to p4 (tangent te), emccanon's ``biarc``; a straight line where it
    has none or an infinite one."""
    ts, te = _unit(*ts), _unit(*te)
    vx, vy = p0[0] - p4[0], p0[1] - p4[1]
    c = vx * vx + vy * vy
    b = 2 * (vx * (r * ts[0] + te[0]) + vy * (r * ts[1] + te[1]))
    a = 2 * r * (ts[0] * te[0] + ts[1] * te[1] - 1)
    discr = b * b - 4 * a * c
    if discr < 0:
        return [SplineMove(p4)]  # LinuxCNC: nothing (module docstring)
    disq = math.sqrt(discr)
    beta1 = _div(_div(-b - disq, 2), a)
    beta2 = _div(_div(-b + disq, 2), a)
    if beta1 > 0 and beta2 > 0:
        return [SplineMove(p4)]  # LinuxCNC: nothing
    beta = beta2 if beta1 < beta2 else beta1  # std::max
    if beta1 == math.inf or beta2 == math.inf or beta > _BETA_MAX or not math.isfinite(beta):
        return [SplineMove(p4)]
    alpha = beta * r
    ab = alpha + beta
    if ab == 0:  # the samples coincide (repeated control points): nothing to move (LinuxCNC: NaN arcs)
        return []
    p1 = (p0[0] + alpha * ts[0], p0[1] + alpha * ts[1])
    p3 = (p4[0] - beta * te[0], p4[1] - beta * te[1])
    p2 = ((p1[0] * beta + p3[0] * alpha) / ab, (p1[1] * beta + p3[1] * alpha) / ab)
    tm = _unit(p3[0] - p2[0], p3[1] - p2[1])
    return [_arc(p0, p2, ts), _arc(p2, p4, tm)]


def nurbs_moves(cps: list[tuple[float, float, float]], order: int) -> list[SplineMove]:
    """The moves of one NURBS (emccanon's ``NURBS_G5_FEED``); cps (first, second, weight), the first
    being where the tool stands."""
    n = len(cps) - 1
    umax = n - order + 2
    div = len(cps) * 4
    kv = knot_vector(n, order)
    p0, t0 = point(0.0, order, cps, kv), tangent(0.0, order, cps, kv)
    out: list[SplineMove] = []
    for i in range(1, div + 1):
        u = umax * i / div
        p1, t1 = point(u, order, cps, kv), tangent(u, order, cps, kv)
        out.extend(biarc(p0, t0, p1, t1))
        p0, t0 = p1, t1
    return out


def point_local(u: float, k: int, cps: list[tuple[float, float, float]],
                kv: list[float]) -> tuple[float, float]:
    """The curve at u from the ``k`` basis functions that are not 0 there (de Boor's local form, the
    NURBS Book's A2.2): the same point as :func:`point` where the curve is continuous, in O(k^2)
    rather than O(len(cps) k); spans half-open, the last one closed."""
    p, n = k - 1, len(cps) - 1
    i = min(max(bisect_right(kv, u, p, n + 1) - 1, p), n)
    while i > p and kv[i] >= kv[i + 1]:  # the last span that is not empty (u at the end)
        i -= 1
    basis = [1.0] + [0.0] * p
    left, right = [0.0] * (p + 1), [0.0] * (p + 1)
    for j in range(1, p + 1):
        left[j], right[j] = u - kv[i + 1 - j], kv[i + j] - u
        saved = 0.0
        for r in range(j):
            den = right[r + 1] + left[j - r]
            temp = basis[r] / den if den != 0 else 0.0
            basis[r] = saved + right[r + 1] * temp
            saved = left[j - r] * temp
        basis[j] = saved
    x = y = w = 0.0
    for b, cp in zip(basis, cps[i - p: i + 1], strict=True):
        x += b * cp[2] * cp[0]
        y += b * cp[2] * cp[1]
        w += b * cp[2]
    return _div(x, w), _div(y, w)


def _tangent_local(u: float, k: int, cps: list[tuple[float, float, float]],
                   kv: list[float]) -> tuple[float, float]:
    lo, hi = max(kv[0], u - _DU), min(kv[-1], u + _DU)  # LinuxCNC's nurbs_G6_tangent_x
    p1, p3 = point_local(lo, k, cps, kv), point_local(hi, k, cps, kv)
    return _unit((p3[0] - p1[0]) / (hi - lo), (p3[1] - p1[1]) / (hi - lo))


def nurbs_g6_moves(cps: list[tuple[float, float, float]], knots: list[float], order: int) -> list[SplineMove]:
    """The moves of one G6.2 NURBS as LinuxCNC's ``NURBS_FEED_G6_2_WITH_BIARCH_DU_CONST`` makes them:
    cps (first, second, weight R) are the ``len(knots) - order`` control points, ``knots`` the K
    words (not decreasing, the last ``order`` equal); a straight feed to the curve's start, then the
    curve sampled at ``15 x len(cps)`` equal steps of its parameter from 0, each step a biarc (order 2
    and less: a line), then a straight feed to its end."""
    umax = knots[-1]
    du = umax / (len(cps) * 15)
    if not du > 0:
        raise ValueError("the knots must end above 0")
    start, end = point_local(knots[0], order, cps, knots), point_local(umax, order, cps, knots)
    out = [SplineMove(start)]
    p0, t0 = start, _tangent_local(knots[0], order, cps, knots)
    for step in range(1, int(umax / du) + 2):
        u = step * du
        if u > umax - du:
            break
        p1 = point_local(u, order, cps, knots)
        if order >= 3:
            t1 = _tangent_local(u, order, cps, knots)
            out.extend(biarc(p0, t0, p1, t1))
            p0, t0 = p1, t1
        else:
            out.append(SplineMove(p1))
    out.append(SplineMove(end))
    return out
