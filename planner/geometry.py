"""Path geometry along one parameter ``s``: lines, arcs/helices, corner blends, transitions, and the
smoothed spans of chains of short lines (one :class:`Chain` of :class:`Span` under one parameter).

Every piece maps ``s`` in ``[0, length]`` to the positions of the configured axes (a list in the
machine's axis order) and knows bounds on the first three derivatives of each axis with respect to
``s``. Those bounds are all the planner needs to turn axis limits into limits along the path: with
path speed v, acceleration a and jerk j, axis i moves with

    velocity     q' v
    acceleration q'' v^2 + q' a
    jerk         q''' v^3 + 3 q'' v a + q' j

``s`` is the length over the linear axes X Y Z (or U V W, or the rotary axes when nothing else moves),
so that a feed in units per minute is a speed along ``s``.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

Vec = tuple[float, ...]

# Quintic smoothstep sigma(x) = 10x^3 - 15x^4 + 6x^5 and its integral; its first derivative peaks at
# 15/8, its second at 10/sqrt(3). A blend built on it has zero curvature at both ends.
SIGMA1_MAX = 15.0 / 8.0
SIGMA2_MAX = 10.0 / math.sqrt(3.0)
SIGMA_INT_HALF = 0.078125  # integral of sigma from 0 to 1/2


def path_length(delta: Sequence[float], groups: Sequence[Sequence[int]]) -> float:
    """Length of a move ``delta`` (per configured axis) measured over the first group that moves."""
    for group in groups:
        length = math.sqrt(sum(delta[i] * delta[i] for i in group))
        if length > 0.0:
            return length
    return 0.0


@dataclass(slots=True)
class Piece:
    """Common data: the derivative bounds (per axis) and the end tangents/curvatures."""

    length: float
    start: Vec
    end: Vec
    d1_start: Vec
    d1_end: Vec
    d2_start: Vec
    d2_end: Vec
    d1_max: Vec
    d2_max: Vec
    d3_max: Vec

    def pos(self, s: float) -> list[float]:  # pragma: no cover - overridden
        raise NotImplementedError

    def cmd_at(self, s: float) -> Any:
        """The programmed move at ``s`` when the piece carries several (else None: the segment's)."""
        return None

    def sample(self, s: float) -> tuple[list[float], Any]:
        """``(pos(s), cmd_at(s))``, what each cycle reads (one lookup of the part where pieces have
        parts)."""
        return self.pos(s), self.cmd_at(s)


def forward_index(starts: list[float], i: int, s: float) -> int:
    """The index of the part of a piece that holds ``s`` (``starts``: where each part begins), ``i``
    being the last one found: the cycle loop samples forward, so it is almost always still right or
    the next, and only a jump costs a bisection."""
    if starts[i] <= s and (i + 1 == len(starts) or s < starts[i + 1]):
        return i
    return max(bisect_right(starts, s) - 1, 0)


class Line(Piece):
    """A straight move from ``start`` to ``end``; ``s`` runs over ``length``."""

    __slots__ = ("_dir",)

    def __init__(self, start: Vec, end: Vec, length: float) -> None:
        n = len(start)
        d = tuple((end[i] - start[i]) / length for i in range(n))
        zero = (0.0,) * n
        super().__init__(length, tuple(start), tuple(end), d, d, zero, zero,
                         tuple(abs(x) for x in d), zero, zero)
        self._dir = d

    def pos(self, s: float) -> list[float]:
        if s >= self.length:
            return list(self.end)
        if s <= 0.0:
            return list(self.start)
        st, d = self.start, self._dir
        return [st[i] + d[i] * s for i in range(len(st))]

    def part(self, s0: float, s1: float) -> Line:
        """The piece between ``s0`` and ``s1`` (a transition takes the rest)."""
        return Line(tuple(self.pos(s0)), tuple(self.pos(s1)), s1 - s0)


class _Parts:
    """Several programmed moves planned as one piece (``planner.merging``): ``cmds[i]`` is the move
    from ``starts[i]`` on, for the setpoints' file and line."""

    __slots__ = ()
    starts: list[float]
    cmds: list[Any]
    _i: int

    def cmd_at(self, s: float) -> Any:
        self._i = forward_index(self.starts, self._i, s)
        return self.cmds[self._i]

    def _parts(self, s0: float, s1: float) -> tuple[list[float], list[Any]]:
        """``starts`` and ``cmds`` of the part between ``s0`` and ``s1``."""
        lo = max(bisect_right(self.starts, s0) - 1, 0)
        hi = max(bisect_right(self.starts, s1) - 1, lo)
        return [0.0] + [x - s0 for x in self.starts[lo + 1: hi + 1]], self.cmds[lo: hi + 1]


class MergedLine(_Parts, Line):
    """Consecutive programmed lines within a tolerance of one line, planned as this line
    (``planner.merging``). ``cmds[i]`` is the programmed move from ``starts[i]`` on (its start
    projected on the line), for the setpoints' file and line."""

    __slots__ = ("_i", "cmds", "starts")

    def __init__(self, start: Vec, end: Vec, length: float, starts: list[float], cmds: list[Any]) -> None:
        super().__init__(start, end, length)
        self.starts, self.cmds = starts, cmds
        self._i = 0

    def part(self, s0: float, s1: float) -> Line:
        return MergedLine(tuple(self.pos(s0)), tuple(self.pos(s1)), s1 - s0, *self._parts(s0, s1))


class Arc(Piece):
    """An arc or helix: in-plane angle linear in ``s``, radius linear in angle (start and end radii may
    differ by the interpreter's tolerance), every other axis linear in angle."""

    __slots__ = ("_c0", "_c1", "_dr", "_i0", "_i1", "_k", "_lin", "_r0", "_th0")

    def __init__(self, start: Vec, end: Vec, i0: int, i1: int, c0: float, c1: float,
                 sweep: float, length: float) -> None:
        n = len(start)
        self._i0, self._i1, self._c0, self._c1 = i0, i1, c0, c1
        r0 = math.hypot(start[i0] - c0, start[i1] - c1)
        r1 = math.hypot(end[i0] - c0, end[i1] - c1)
        self._r0, self._dr = r0, (r1 - r0) / length  # radius per unit s
        self._th0 = math.atan2(start[i1] - c1, start[i0] - c0)
        self._k = sweep / length  # radians per unit s
        self._lin = tuple(
            (end[i] - start[i]) / length if i not in (i0, i1) else 0.0 for i in range(n))
        k, dr, rmax = abs(self._k), abs(self._dr), max(r0, r1)
        d1 = [abs(x) for x in self._lin]
        d2 = [0.0] * n
        d3 = [0.0] * n
        for i in (i0, i1):
            d1[i] = rmax * k + dr
            d2[i] = rmax * k * k + 2.0 * dr * k
            d3[i] = rmax * k ** 3 + 3.0 * dr * k * k
        super().__init__(length, tuple(start), tuple(end), self._deriv(0.0, 1), self._deriv(length, 1),
                         self._deriv(0.0, 2), self._deriv(length, 2), tuple(d1), tuple(d2), tuple(d3))

    def _deriv(self, s: float, order: int) -> Vec:
        th = self._th0 + self._k * s
        r = self._r0 + self._dr * s
        k, dr = self._k, self._dr
        c, sn = math.cos(th), math.sin(th)
        out = list(self._lin) if order == 1 else [0.0] * len(self._lin)
        if order == 1:
            out[self._i0] = dr * c - r * k * sn
            out[self._i1] = dr * sn + r * k * c
        else:
            out[self._i0] = -2.0 * dr * k * sn - r * k * k * c
            out[self._i1] = 2.0 * dr * k * c - r * k * k * sn
        return tuple(out)

    def pos(self, s: float) -> list[float]:
        if s >= self.length:
            return list(self.end)
        if s <= 0.0:
            return list(self.start)
        st, lin = self.start, self._lin
        out = [st[i] + lin[i] * s for i in range(len(st))]
        th = self._th0 + self._k * s
        r = self._r0 + self._dr * s
        out[self._i0] = self._c0 + r * math.cos(th)
        out[self._i1] = self._c1 + r * math.sin(th)
        return out

    @property
    def radius(self) -> float:
        """The smaller of the end radii (in its plane)."""
        return min(self._r0, self._r0 + self._dr * self.length)

    def part(self, s0: float, s1: float) -> Arc:
        """The piece between ``s0`` and ``s1``: same centre, angle and radius still linear in ``s``."""
        return Arc(tuple(self.pos(s0)), tuple(self.pos(s1)), self._i0, self._i1, self._c0, self._c1,
                   self._k * (s1 - s0), s1 - s0)


def turn_xy(v: Sequence[float], ix: int, iy: int, c: float, s: float) -> Vec:
    """``v`` with its X and Y (indexes ``ix``, ``iy``) turned about Z by the angle of cosine ``c``
    and sine ``s``."""
    out = list(v)
    x, y = v[ix], v[iy]
    out[ix], out[iy] = x * c - y * s, x * s + y * c
    return tuple(out)


class TurnedArc(Arc):
    """An arc in an axis plane turned about machine Z (``ArcFeed.rotation``: G18/G19 in a rotated
    coordinate system): ``inner``, the arc in the frame turned back, with its X and Y (indexes ``ix``
    and ``iy``) turned by ``degrees``. The derivative bounds of X and Y are the turned bounds'
    combination (|cos| bx + |sin| by), an upper bound; ``radius`` is the inner arc's."""

    __slots__ = ("_cs", "_inner", "_ix", "_iy")

    def __init__(self, inner: Arc, ix: int, iy: int, degrees: float, start: Vec, end: Vec) -> None:
        self._inner, self._ix, self._iy = inner, ix, iy
        c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
        self._cs = (c, s)
        self._r0, self._dr = inner._r0, inner._dr
        turn, bound = self._turn, self._bound
        Piece.__init__(self, inner.length, tuple(start), tuple(end), turn(inner.d1_start), turn(inner.d1_end),
                       turn(inner.d2_start), turn(inner.d2_end), bound(inner.d1_max), bound(inner.d2_max),
                       bound(inner.d3_max))

    def _turn(self, v: Sequence[float]) -> Vec:
        return turn_xy(v, self._ix, self._iy, *self._cs)

    def _bound(self, v: Sequence[float]) -> Vec:
        c, s = abs(self._cs[0]), abs(self._cs[1])
        out = list(v)
        x, y = v[self._ix], v[self._iy]
        out[self._ix], out[self._iy] = c * x + s * y, s * x + c * y
        return tuple(out)

    def _deriv(self, s: float, order: int) -> Vec:
        return self._turn(self._inner._deriv(s, order))

    def pos(self, s: float) -> list[float]:
        if s >= self.length:
            return list(self.end)
        if s <= 0.0:
            return list(self.start)
        return list(self._turn(self._inner.pos(s)))

    def part(self, s0: float, s1: float) -> Arc:
        c, s = self._cs
        return TurnedArc(self._inner.part(s0, s1), self._ix, self._iy, math.degrees(math.atan2(s, c)),
                         tuple(self.pos(s0)), tuple(self.pos(s1)))


class MergedArc(_Parts, Arc):
    """Consecutive programmed lines within a tolerance of one circular arc, planned as this arc
    (``planner.merging``, ``planner.arcfit``). ``cmds[i]`` is the programmed move from ``starts[i]``
    on (where the arc passes its start's angle)."""

    __slots__ = ("_i", "cmds", "starts")

    def __init__(self, start: Vec, end: Vec, i0: int, i1: int, c0: float, c1: float, sweep: float,
                 length: float, starts: list[float], cmds: list[Any]) -> None:
        super().__init__(start, end, i0, i1, c0, c1, sweep, length)
        self.starts, self.cmds = starts, cmds
        self._i = 0

    def part(self, s0: float, s1: float) -> Arc:
        return MergedArc(tuple(self.pos(s0)), tuple(self.pos(s1)), self._i0, self._i1, self._c0, self._c1,
                         self._k * (s1 - s0), s1 - s0, *self._parts(s0, s1))


class Blend(Piece):
    """A corner blend between two lines: ``P(s) = A + 2d [w1 x + (w2 - w1) Sigma(x)]``, ``x = s / 2d``.

    ``w1`` and ``w2`` are the lines' ``dq/ds``; the blend starts ``d`` before the corner on the first
    line and ends ``d`` after it on the second, tangent to both with zero curvature at both ends, so
    neither velocity nor acceleration steps where it meets the lines. Its farthest point from the
    corner is ``2d * SIGMA_INT_HALF * |w2 - w1|`` away. ``s`` is not arc length here: the
    Cartesian speed is at most the path speed (the chord of the turn).
    """

    __slots__ = ("_a", "_dw", "_span", "_w1")

    def __init__(self, corner: Vec, w1: Vec, w2: Vec, d: float) -> None:
        n = len(corner)
        span = 2.0 * d
        self._a = tuple(corner[i] - d * w1[i] for i in range(n))
        self._w1 = tuple(w1)
        self._dw = tuple(w2[i] - w1[i] for i in range(n))
        self._span = span
        end = tuple(corner[i] + d * w2[i] for i in range(n))
        zero = (0.0,) * n
        d1 = tuple(max(abs(w1[i]), abs(w2[i])) for i in range(n))
        d2 = tuple(abs(x) * SIGMA1_MAX / span for x in self._dw)
        d3 = tuple(abs(x) * SIGMA2_MAX / span ** 2 for x in self._dw)
        super().__init__(span, self._a, end, tuple(w1), tuple(w2), zero, zero, d1, d2, d3)

    def pos(self, s: float) -> list[float]:
        if s >= self.length:
            return list(self.end)
        if s <= 0.0:
            return list(self.start)
        x = s / self._span
        x3 = x * x * x
        big = x3 * x * (2.5 + x * (-3.0 + x))  # integral of the smoothstep: 2.5x^4 - 3x^5 + x^6
        a, w1, dw, span = self._a, self._w1, self._dw, self._span
        return [a[i] + span * (w1[i] * x + dw[i] * big) for i in range(len(a))]


def deviation_of_blend(w1: Vec, w2: Vec, d: float, linear: Sequence[int]) -> float:
    """Distance of a blend's middle from its corner, over the ``linear`` axes."""
    return 2.0 * d * SIGMA_INT_HALF * math.sqrt(sum((w2[i] - w1[i]) ** 2 for i in linear))


class Transition(Piece):
    """A quintic Hermite join between two pieces of any kind (line, arc, helix): the curve from point
    ``a`` on the first to point ``b`` on the second that matches, at both ends, the position and the
    first and second derivatives along ``s`` of the piece it meets.

    Why: a line meeting an arc tangentially still steps in curvature, so the axis accelerations would
    step by ``v^2 / R`` where they meet, which a finite jerk cannot do; without a transition the join
    must be passed so slowly that the step fits in one cycle's jerk (a few mm/s). Matching ``q'`` and
    ``q''`` at both ends makes velocity and acceleration continuous; only the jerk steps, which the
    path limits (``q'''``) budget like any other piece. ``s`` runs over ``length`` (the original
    path's length between ``a`` and ``b``), so it is close to arc length on tangent joins and longer
    than the chord on corners, as in :class:`Blend`.
    """

    __slots__ = ("_c", "_n")

    def __init__(self, a: Vec, t_a: Vec, k_a: Vec, b: Vec, t_b: Vec, k_b: Vec, length: float) -> None:
        n = len(a)
        L = length
        coeffs = hermite_coefficients(a, t_a, k_a, b, t_b, k_b, L)
        self._c = coeffs
        self._n = n
        d1, d2, d3 = self._bounds(coeffs, L)
        super().__init__(L, tuple(a), tuple(b), tuple(t_a), tuple(t_b), tuple(k_a), tuple(k_b),
                         d1, d2, d3)

    @staticmethod
    def _bounds(coeffs: Sequence[Sequence[float]], L: float) -> tuple[Vec, Vec, Vec]:
        return _hermite_bounds(coeffs, L)

    def pos(self, s: float) -> list[float]:
        if s >= self.length:
            return list(self.end)
        if s <= 0.0:
            return list(self.start)
        u = s / self.length
        return [c0 + u * (c1 + u * (c2 + u * (c3 + u * (c4 + u * c5)))) for c0, c1, c2, c3, c4, c5 in self._c]


HERMITE_GRID = 64


def _hermite_bounds(coeffs: Sequence[Sequence[float]], L: float) -> tuple[Vec, Vec, Vec]:
    """Upper bounds of |dq/ds|, |d2q/ds2|, |d3q/ds3| per axis of a quintic in ``u = s / L``.

    The third derivative is a quadratic: exact (ends and vertex). The first and second are sampled on
    a grid and padded by the next derivative's bound times half the grid step, which bounds them
    rigorously between samples.
    """
    d1, d2, d3 = [], [], []
    h = 1.0 / HERMITE_GRID
    for _c0, c1, c2, c3, c4, c5 in coeffs:
        # q''' (in u) = 6 c3 + 24 c4 u + 60 c5 u^2
        cand = [0.0, 1.0]
        if c5 != 0.0:
            v = -24.0 * c4 / (120.0 * c5)
            if 0.0 < v < 1.0:
                cand.append(v)
        m3 = max(abs(6.0 * c3 + 24.0 * c4 * u + 60.0 * c5 * u * u) for u in cand)
        m2 = m1 = 0.0
        for k in range(HERMITE_GRID + 1):
            u = k * h
            m2 = max(m2, abs(2.0 * c2 + u * (6.0 * c3 + u * (12.0 * c4 + u * 20.0 * c5))))
            m1 = max(m1, abs(c1 + u * (2.0 * c2 + u * (3.0 * c3 + u * (4.0 * c4 + u * 5.0 * c5)))))
        m2 += 0.5 * h * m3
        m1 += 0.5 * h * m2
        d1.append(m1 / L)
        d2.append(m2 / (L * L))
        d3.append(m3 / (L * L * L))
    return tuple(d1), tuple(d2), tuple(d3)


def bernstein_max(coeffs: Sequence[float]) -> float:
    """Upper bound of |p(u)| on [0, 1] for p(u) = sum coeffs[i] u^i (degree 2 to 5).

    The polynomial lies within the range of its Bernstein coefficients on [0, 1] (the k-th is
    ``sum_i C(k, i) / C(n, i) a_i``), so their largest magnitude is a rigorous bound, and a tight one for
    the smooth spans it is used on. Written out per degree: it runs several times per fed segment.
    """
    n = len(coeffs) - 1
    if n == 5:
        a0, a1, a2, a3, a4, a5 = coeffs
        return max(abs(a0), abs(a0 + 0.2 * a1), abs(a0 + 0.4 * a1 + 0.1 * a2),
                   abs(a0 + 0.6 * a1 + 0.3 * a2 + 0.1 * a3),
                   abs(a0 + 0.8 * a1 + 0.6 * a2 + 0.4 * a3 + 0.2 * a4),
                   abs(a0 + a1 + a2 + a3 + a4 + a5))
    if n == 4:
        a0, a1, a2, a3, a4 = coeffs
        return max(abs(a0), abs(a0 + 0.25 * a1), abs(a0 + 0.5 * a1 + a2 / 6.0),
                   abs(a0 + 0.75 * a1 + 0.5 * a2 + 0.25 * a3), abs(a0 + a1 + a2 + a3 + a4))
    if n == 3:
        a0, a1, a2, a3 = coeffs
        return max(abs(a0), abs(a0 + a1 / 3.0), abs(a0 + 2.0 * a1 / 3.0 + a2 / 3.0), abs(a0 + a1 + a2 + a3))
    a0, a1, a2 = coeffs
    return max(abs(a0), abs(a0 + 0.5 * a1), abs(a0 + a1 + a2))


def _bernstein_bounds(coeffs: Sequence[Sequence[float]], L: float) -> tuple[Vec, Vec, Vec]:
    """As :func:`_hermite_bounds`, from Bernstein coefficients instead of a 64-point grid: rigorous
    too, and much cheaper, which matters for a span per fed segment (:func:`bernstein_max` written
    out for the derivatives of a quintic: the first of degree 4, the second 3, the third 2)."""
    d1, d2, d3 = [], [], []
    L2 = L * L
    L3 = L2 * L
    for _c0, c1, c2, c3, c4, c5 in coeffs:
        if c1 == c2 == c3 == c4 == c5 == 0.0:  # an axis that does not move
            d1.append(0.0)
            d2.append(0.0)
            d3.append(0.0)
            continue
        # q'(u) = c1 + 2 c2 u + 3 c3 u^2 + 4 c4 u^3 + 5 c5 u^4
        b1 = c1 + 0.5 * c2
        b2 = c1 + c2 + 0.5 * c3
        b3 = c1 + 1.5 * c2 + 1.5 * c3 + c4
        b4 = c1 + 2.0 * c2 + 3.0 * c3 + 4.0 * c4 + 5.0 * c5
        d1.append(max(abs(c1), abs(b1), abs(b2), abs(b3), abs(b4)) / L)
        # q''(u) = 2 c2 + 6 c3 u + 12 c4 u^2 + 20 c5 u^3
        e0 = 2.0 * c2
        e1 = e0 + 2.0 * c3
        e2 = e0 + 4.0 * c3 + 4.0 * c4
        e3 = e0 + 6.0 * c3 + 12.0 * c4 + 20.0 * c5
        d2.append(max(abs(e0), abs(e1), abs(e2), abs(e3)) / L2)
        # q'''(u) = 6 c3 + 24 c4 u + 60 c5 u^2
        f0 = 6.0 * c3
        f1 = f0 + 12.0 * c4
        f2 = f0 + 24.0 * c4 + 60.0 * c5
        d3.append(max(abs(f0), abs(f1), abs(f2)) / L3)
    return tuple(d1), tuple(d2), tuple(d3)


def hermite_coefficients(a: Vec, t_a: Vec, k_a: Vec, b: Vec, t_b: Vec, k_b: Vec, length: float,
                         ) -> list[tuple[float, float, float, float, float, float]]:
    """Per axis, the power coefficients in ``u = s / length`` of the quintic that has position, first and
    second derivative (along ``s``) ``a t_a k_a`` at ``u = 0`` and ``b t_b k_b`` at ``u = 1``."""
    L = length
    coeffs = []
    for i in range(len(a)):
        c0, c1, c2 = a[i], t_a[i] * L, 0.5 * k_a[i] * L * L
        e0 = b[i] - (c0 + c1 + c2)
        e1 = t_b[i] * L - (c1 + 2.0 * c2)
        e2 = k_b[i] * L * L - 2.0 * c2
        coeffs.append((c0, c1, c2, 10.0 * e0 - 4.0 * e1 + 0.5 * e2, -15.0 * e0 + 7.0 * e1 - e2,
                       6.0 * e0 - 3.0 * e1 + 0.5 * e2))
    return coeffs


def chord_deviation(coeffs: Sequence[Sequence[float]], end: Vec) -> float:
    """Upper bound of the distance of a quintic (:func:`hermite_coefficients`) from its chord.

    The curve minus the chord's point at the same ``u`` is a quintic vanishing at both ends; the
    distance to the line is at most its norm, bounded per axis by its Bernstein coefficients.
    """
    total = 0.0
    for (c0, c1, c2, c3, c4, c5), e in zip(coeffs, end, strict=True):
        r1 = c1 - (e - c0)
        if r1 == c2 == c3 == c4 == c5 == 0.0:
            continue
        m = bernstein_max((0.0, r1, c2, c3, c4, c5))
        total += m * m
    return math.sqrt(total)


class Span(Transition):
    """One short line of a smoothed chain: the quintic from its start to its end point with the tangent
    and curvature estimated at each vertex (shared with the neighbouring spans, so velocity and
    acceleration are continuous where spans meet). It passes through the programmed vertices; only
    between them it leaves the line, by at most :meth:`chord_deviation`."""

    __slots__ = ()

    @staticmethod
    def _bounds(coeffs: Sequence[Sequence[float]], L: float) -> tuple[Vec, Vec, Vec]:
        return _bernstein_bounds(coeffs, L)

    def chord_deviation(self) -> float:
        """Upper bound of the distance of the curve from its chord (the programmed line)."""
        return chord_deviation(self._c, self.end)


def vertex_tangent_curvature(w1: Vec, l1: float, w2: Vec, l2: float) -> tuple[Vec, Vec]:
    """Tangent and curvature vector at the vertex between chords ``l1 w1`` and ``l2 w2`` (unit
    directions): those of the circle through the vertex and both far ends, the curve a sampled smooth
    path most likely came from."""
    n = len(w1)
    t = [l2 * w1[i] + l1 * w2[i] for i in range(n)]
    norm = math.sqrt(sum(x * x for x in t))
    t = [x / norm for x in t]
    dw = [w2[i] - w1[i] for i in range(n)]
    along = sum(dw[i] * t[i] for i in range(n))
    perp = [dw[i] - along * t[i] for i in range(n)]
    pn = math.sqrt(sum(x * x for x in perp))
    if pn <= 1e-15:
        return tuple(t), (0.0,) * n
    cross = sum(w1[i] * w2[i] for i in range(n))
    sin_turn = math.sqrt(max(0.0, 1.0 - cross * cross))
    chord = math.sqrt(sum((l1 * w1[i] + l2 * w2[i]) ** 2 for i in range(n)))
    kappa = 2.0 * sin_turn / chord
    return tuple(t), tuple(kappa * x / pn for x in perp)


class Chain(Piece):
    """Consecutive spans of a smoothed chain of short lines under one path parameter, so that one
    profile runs over all of them: the path acceleration need not return to zero where the
    programmed lines meet. The derivative bounds are the largest of the spans'. ``cmds`` says which
    programmed move each span comes from (for the setpoints' file and line)."""

    __slots__ = ("_i", "cmds", "spans", "starts", "subs")

    def __init__(self, first: Span, cmd: Any, sub: Piece | None = None) -> None:
        super().__init__(first.length, first.start, first.end, first.d1_start, first.d1_end, first.d2_start,
                         first.d2_end, first.d1_max, first.d2_max, first.d3_max)
        self.spans: list[Span] = [first]
        self.starts: list[float] = [0.0]
        self.cmds: list[Any] = [cmd]
        # the line each span replaces, when it carries several programmed moves (a merged line)
        self.subs: list[Piece | None] = [sub if isinstance(sub, MergedLine) else None]
        self._i = 0

    def add(self, span: Span, cmd: Any, sub: Piece | None = None) -> None:
        """Append ``span`` (it starts where the chain ends, with the chain's end tangent and curvature)."""
        self.spans.append(span)
        self.starts.append(self.length)
        self.cmds.append(cmd)
        self.subs.append(sub if isinstance(sub, MergedLine) else None)
        self._set_end()
        self.d1_max = tuple(map(max, self.d1_max, span.d1_max))
        self.d2_max = tuple(map(max, self.d2_max, span.d2_max))
        self.d3_max = tuple(map(max, self.d3_max, span.d3_max))

    def drop_last(self) -> None:
        """Undo :meth:`add` (the planner's rollback when the longer chain turns out infeasible)."""
        self.spans.pop()
        self.starts.pop()
        self.cmds.pop()
        self.subs.pop()
        self._i = 0
        self._set_end()
        self.d1_max, self.d2_max, self.d3_max = (
            tuple(max(xs) for xs in zip(*(getattr(sp, name) for sp in self.spans), strict=True))
            for name in ("d1_max", "d2_max", "d3_max"))

    def _set_end(self) -> None:
        last = self.spans[-1]
        self.length = self.starts[-1] + last.length
        self.end, self.d1_end, self.d2_end = last.end, last.d1_end, last.d2_end

    def _index(self, s: float) -> int:
        self._i = forward_index(self.starts, self._i, s)
        return self._i

    def pos(self, s: float) -> list[float]:
        if s >= self.length:
            return list(self.end)
        if s <= 0.0:
            return list(self.start)
        i = self._index(s)
        return self.spans[i].pos(s - self.starts[i])

    def cmd_at(self, s: float) -> Any:
        s = min(max(s, 0.0), self.length)
        return self._cmd(self._index(s), s)

    def _cmd(self, i: int, s: float) -> Any:
        sub = self.subs[i]
        if sub is not None:  # a span of a merged line: the span's s maps to the line's in proportion
            return sub.cmd_at((s - self.starts[i]) * sub.length / self.spans[i].length)
        return self.cmds[i]

    def sample(self, s: float) -> tuple[list[float], Any]:
        if s >= self.length:
            return list(self.end), self._cmd(self._index(self.length), self.length)
        if s <= 0.0:
            return list(self.start), self._cmd(self._index(0.0), 0.0)
        # as pos() and cmd_at(), written out: this runs every cycle
        starts, i = self.starts, self._i
        if not (starts[i] <= s and (i + 1 == len(starts) or s < starts[i + 1])):
            i = self._i = max(bisect_right(starts, s) - 1, 0)
        span, off = self.spans[i], s - starts[i]
        length = span.length
        if off >= length:
            pos = list(span.end)
        elif off <= 0.0:
            pos = list(span.start)
        else:
            u = off / length
            pos = [c0 + u * (c1 + u * (c2 + u * (c3 + u * (c4 + u * c5))))
                   for c0, c1, c2, c3, c4, c5 in span._c]
        sub = self.subs[i]
        if sub is None:
            return pos, self.cmds[i]
        return pos, sub.cmd_at(off * sub.length / length)


def vertex_tangent_curvature4(w0: Vec, l0: float, w1: Vec, l1: float, w2: Vec, l2: float,
                              ) -> tuple[Vec, Vec]:
    """Tangent and curvature vector at the vertex between chords ``l1 w1`` and ``l2 w2``, with the
    chord ``l0 w0`` before them: from the cubic through the four points (chord-length parameter).

    Why not the circle of three points: its tangent is off by about ``h^2 q'''/6``, and a quintic span
    of length h turns a tangent error e into a third derivative of order ``36 e / h^2``, which caps the
    speed (``v^3 q'''``). The cubic's tangent is off by ``O(h^3)``, its curvature by ``O(h^2)``.
    """
    # Lagrange weights at the vertex (node 0) of the nodes -(l1 + l0), -l1, l2; the vertex's own
    # value is 0. For node j with the other roots r: first derivative sum(r_a r_b) / D_j, second
    # -2 sum(r) / D_j, D_j = prod(node_j - r).
    s0, s1, s3 = -(l1 + l0), -l1, l2
    den0 = (s0 - s1) * s0 * (s0 - s3)
    den1 = (s1 - s0) * s1 * (s1 - s3)
    den3 = (s3 - s0) * (s3 - s1) * s3
    f0, f1, f3 = s1 * s3 / den0, s0 * s3 / den1, s0 * s1 / den3
    g0, g1, g3 = -2.0 * (s1 + s3) / den0, -2.0 * (s0 + s3) / den1, -2.0 * (s0 + s1) / den3
    # points: p0 = -(l1 w1 + l0 w0), p1 = -l1 w1, p3 = l2 w2
    a0, a1, a2 = -f0 * l0, -(f0 + f1) * l1, f3 * l2
    b0, b1, b2 = -g0 * l0, -(g0 + g1) * l1, g3 * l2
    n = len(w1)
    d1 = [a0 * w0[i] + a1 * w1[i] + a2 * w2[i] for i in range(n)]
    d2 = [b0 * w0[i] + b1 * w1[i] + b2 * w2[i] for i in range(n)]
    norm = math.sqrt(sum(x * x for x in d1))
    t = [x / norm for x in d1]
    along = sum(d2[i] * t[i] for i in range(n))
    k = [(d2[i] - along * t[i]) / (norm * norm) for i in range(n)]
    return tuple(t), tuple(k)
