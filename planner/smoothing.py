"""Smoothing of chains of short lines in G64 P (CAM surfacing): each line becomes a quintic span
through its own end points with a tangent and curvature shared at each vertex, within P, and spans
of similar limits run as one profile (docs/planner.md, "Chains of short lines").
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

from planner.geometry import (
    SIGMA1_MAX,
    SIGMA2_MAX,
    Chain,
    Piece,
    Span,
    deviation_of_blend,
    vertex_tangent_curvature,
    vertex_tangent_curvature4,
)
from planner.segments import (
    SMOOTH_CHAIN_SPANS,
    SMOOTH_DEVIATION,
    SMOOTH_GAIN,
    SMOOTH_KEEP,
    SMOOTH_MERGE,
    SMOOTH_MERGE_ACC,
    SMOOTH_PAUSE,
    SMOOTH_START,
    SMOOTH_TURN,
    PlannerError,
    Seg,
    tol_left,
)

log = logging.getLogger(__name__)


class SmoothingMixin:
    """Part of :class:`planner.core.Planner`: smoothed chains."""

    def _euclidean(self, seg: Seg) -> bool:
        """Whether ``s`` is the Euclidean length over all axes (no axis outside the group that measures
        it moves), so that unit tangents and curvature vectors mean what the vertex estimate says."""
        p = seg.piece
        return abs(math.dist(p.start, p.end) - p.length) <= 1e-9 * (1.0 + p.length)

    def _try_smooth(self, new: Seg) -> bool:
        """In G64 P, smooth a chain of short lines that turn by little at each vertex (a sampled curve, as
        CAM surfacing writes it) instead of blending each corner separately.

        Why: a corner blend returns to zero curvature on both sides, so a chain of 0.2 mm lines that
        approximates a smooth surface becomes a chain of blends whose curvature rises and falls every
        segment; its jerk term ``v^3 q'''`` caps the speed far below the feed. Here each line becomes a
        :class:`Span` through its own end points with the tangent and curvature of the circle through
        each vertex and its neighbours, shared by both spans at the vertex: curvature is continuous
        along the chain and close to the smooth curve's. The vertex of ``prev`` and ``new`` is known now,
        so ``prev`` becomes its span; ``new`` stays queued as a line until the next vertex (or
        :meth:`_finish_chain`). Spans of similar limits share one profile (:class:`Chain`), so the path
        acceleration does not return to zero at every programmed point. Each span stays within
        SMOOTH_DEVIATION * P of its line (a rigorous bound), else the chain ends there.
        """
        q = self._q
        h = self._h
        if h >= len(q):
            return False
        prev = q[-1]
        if not isinstance(prev, Seg) or prev.kind != "line" or new.kind != "line":
            return False
        if (prev.stop or prev.s0 > 0.0 or prev.rapid or new.rapid or prev.blend_tol <= 0.0
                or new.blend_tol <= 0.0):
            return False
        n = self._n
        a, b = prev.piece, new.piece
        w1, w2 = a.d1_end, b.d1_start
        turn2 = sum((x - y) ** 2 for x, y in zip(w2, w1, strict=True))
        if turn2 > SMOOTH_TURN * SMOOTH_TURN or (prev.smooth_in is None and turn2 <= 1e-24):
            return False  # a real corner (blended as such), or collinear lines with nothing to smooth
        running = self._active is not None and self._v_end > 0.0
        if running and len(q) - 1 == h:
            return False  # the running profile ends into prev at speed: its limits must not change
        if not (self._euclidean(prev) and self._euclidean(new)):
            return False
        if prev.smooth_in is not None:
            t_in, k_in, w0, l0 = prev.smooth_in
            t, k = vertex_tangent_curvature4(w0, l0, w1, prev.orig_length, w2, b.length)
        elif self._smooth_pause > 0:
            self._smooth_pause -= 1
            return False
        else:
            t_in, k_in = w1, (0.0,) * n
            t, k = vertex_tangent_curvature(w1, prev.orig_length, w2, b.length)
        span = Span(a.start, t_in, k_in, a.end, t, k, a.length)
        if span.chord_deviation() > SMOOTH_DEVIATION * tol_left(prev):
            self._smooth_pause = SMOOTH_PAUSE
            return False
        # decisions compare geometry (caps without the feed): the same pieces at every feed, so a
        # higher feed only lifts the caps
        span_cap = self._speed_cap(span.d1_max, span.d2_max, span.d3_max)
        if prev.smooth_in is not None:
            # noisy points (or a large P): corner blends, free to cut within P, do better; and do not
            # try again at once (each chain's ends cost). Only where the span is also well below the
            # best of the chain before it: compared with the feed instead (85 % of it), a higher feed
            # ended chains a lower one kept, and F3000 took longer than F2500 on some waves; with no
            # such clause, the surfacing raster took 7 % longer.
            before = q[-2] if len(q) - 2 >= h else None
            top = before.best[0] if isinstance(before, Seg) and before.kind == "smooth" else 0.0
            if span_cap < SMOOTH_MERGE * top and span_cap < SMOOTH_KEEP * self._blend_cap(prev, new):
                self._smooth_pause = SMOOTH_PAUSE
                return False
        elif not self._worth_starting(prev, new, span_cap, t, k):
            return False
        chain = q[-2] if len(q) - 2 >= h else None
        merged = None
        if (isinstance(chain, Seg) and chain.kind == "smooth" and chain.s0 == 0.0 and not chain.stop
                and not prev.events and chain.feed == prev.feed and chain.ovr == prev.ovr
                and chain.blend_tol == prev.blend_tol and chain.sides == prev.sides
                and len(chain.piece.spans) < SMOOTH_CHAIN_SPANS  # type: ignore[attr-defined]
                and not (running and len(q) - 2 == h)):
            merged = self._merged_limits(chain, span, span_cap)
        limits: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
        if merged is None:
            try:
                limits = self._path_limits(span.d1_max, span.d2_max, span.d3_max, prev.cmd)
            except PlannerError:
                return False
        snapshot = self._snapshot(len(q) - (3 if merged else 2))
        q.pop()  # prev
        old_limits, old_best = (), (0.0, 0.0, 0.0)
        if merged is not None and isinstance(chain, Seg):
            # the chain grows in place: its start and its link to the item before stay, only its
            # limits (hence that item's jcap) and its end change
            old_limits, old_best = self._limits_of(chain), chain.best
            chain.piece.add(span, prev.cmd, prev.piece)  # type: ignore[attr-defined]
            chain.orig_length = chain.piece.length
            chain.last = self.stats["segments"]
            chain.cap_geom, chain.a, chain.j, chain.qs_a, chain.qs_j = merged
            self._set_cap(chain)
            chain.best = (max(old_best[0], span_cap), max(old_best[1], merged[1]),
                          max(old_best[2], merged[2]))
            if len(q) - 2 >= h:
                before = q[-2]
                if isinstance(before, Seg):
                    before.jcap = min(before.jgeom, before.cap, chain.cap)
            index = len(q) - 1
        else:
            index = len(q)
            self._link(self._span_seg(span, prev, limits, (span_cap, limits[1], limits[2])))
        new.smooth_in = (t, k, w1, prev.orig_length)
        self._link(new)
        changes = self._backward(index)
        if not self._head_feasible(changes):
            del q[index:]
            new.smooth_in = None
            if merged is not None and isinstance(chain, Seg):
                chain.piece.drop_last()  # type: ignore[attr-defined]
                chain.orig_length = chain.piece.length
                self._set_limits(chain, old_limits)
                chain.best = old_best
                q.append(chain)
            q.append(prev)
            self._restore(snapshot)
            return False
        for seg, vb in changes:
            seg.vb = vb
        return True

    def _worth_starting(self, prev: Seg, new: Seg, span_cap: float, t: Sequence[float],
                        k: Sequence[float]) -> bool:
        """Whether to start a smoothed chain at the vertex of ``prev`` and ``new`` (``prev``'s span, from
        zero curvature, has the speed cap ``span_cap``; ``t k`` the vertex's tangent and curvature).

        Start only if a span between two vertices of this stretch (``prev`` as it would be inside a
        chain, estimated with the line fed before it) is clearly faster than the blends (nothing to gain
        where blends already run at the feed; noisy points fail, their vertex estimates disagree so the
        spans wiggle), and if the chain's end spans, from and to zero curvature, are not much slower
        than the blends they replace (they are slower than the spans between, the more so where a
        corner blend has already taken most of ``prev``).
        """
        blend = self._blend_cap(prev, new)
        if blend >= prev.feed:
            return False  # the blends run at the feed: nothing to gain
        b = new.piece
        half = 0.5 * b.length
        end = Span(b.start, t, k, tuple(b.pos(half)), b.d1_start, (0.0,) * self._n, half)
        if end.chord_deviation() > SMOOTH_DEVIATION * tol_left(new):
            return False  # the chain could not end on new
        feed = prev.feed  # the chain's ends must not be much slower than the blends at this feed
        end_cap = self._speed_cap(end.d1_max, end.d2_max, end.d3_max)
        if min(span_cap, end_cap, feed) < SMOOTH_START * min(blend, feed):
            return False
        before = prev.chord_before
        if before is None:
            return False
        w1, l1 = prev.piece.d1_end, prev.orig_length
        tb, kb = vertex_tangent_curvature(before[0], before[1], w1, l1)
        end_pt = prev.piece.end
        start_pt = tuple(end_pt[i] - l1 * w1[i] for i in range(self._n))
        inner = Span(start_pt, tb, kb, end_pt, t, k, l1)
        if inner.chord_deviation() > SMOOTH_DEVIATION * tol_left(prev):
            return False  # the chain would end at the next vertex
        inner_cap = self._speed_cap(inner.d1_max, inner.d2_max, inner.d3_max)
        return inner_cap >= SMOOTH_GAIN * blend

    def _blend_cap(self, prev: Seg, new: Seg) -> float:
        """The speed cap of the corner blend :meth:`_try_blend` would make between the lines ``prev`` and
        ``new`` (without making it), to choose between smoothing and blending at this vertex."""
        w1, w2 = prev.piece.d1_end, new.piece.d1_start
        unit = deviation_of_blend(w1, w2, 1.0, range(self._n))
        d = min(0.5 * prev.orig_length, prev.piece.length, 0.5 * new.piece.length)
        if unit > 0.0:
            d = min(d, tol_left(prev, new) / unit)
        if d <= 1e-9:
            return 0.0
        span = 2.0 * d
        dw = [abs(x - y) for x, y in zip(w2, w1, strict=True)]
        return self._speed_cap([max(abs(x), abs(y)) for x, y in zip(w1, w2, strict=True)],
                               [x * SIGMA1_MAX / span for x in dw],
                               [x * SIGMA2_MAX / (span * span) for x in dw])

    def _span_seg(self, span: Span, line: Seg, limits: tuple[float, ...],
                  best: tuple[float, float, float], sub: Piece | None = None) -> Seg:
        """A queue item for ``span`` (its path limits ``limits``), which replaces (part of) the
        programmed ``line``."""
        piece = Chain(span, line.cmd, line.piece if sub is None else sub)
        sseg = Seg(piece, "smooth", line.cmd, line.feed, False, line.ovr)
        sseg.sides = line.sides
        sseg.orig_length = span.length
        sseg.blend_tol = line.blend_tol
        sseg.merge_dev = line.merge_dev
        sseg.events = line.events
        sseg.cap_geom, sseg.a, sseg.j, sseg.qs_a, sseg.qs_j = limits
        self._set_cap(sseg)
        sseg.best = best
        return sseg

    def _merged_limits(self, chain: Seg, span: Span, span_cap: float,
                       ) -> tuple[float, float, float, float, float] | None:
        """The chain's limits with ``span`` (its own speed cap: ``span_cap``) added, or None
        when they would fall below SMOOTH_MERGE of the best seen in the chain or of the span's own cap
        (then the span starts a new profile: one slow place must not slow a whole row; the path
        acceleration may fall to SMOOTH_MERGE_ACC, as it only matters where the speed changes).
        The limits do not depend on the feed and hold at any override, as every piece's do. (The span's
        own acceleration and jerk limits are not computed: a cost per fed segment for
        little; a span better than its chain in those only makes the chain's speed changes slower.)"""
        cp = chain.piece
        d1 = tuple(map(max, cp.d1_max, span.d1_max))
        d2 = tuple(map(max, cp.d2_max, span.d2_max))
        d3 = tuple(map(max, cp.d3_max, span.d3_max))
        if d1 == cp.d1_max and d2 == cp.d2_max and d3 == cp.d3_max:
            # the span is within the chain's bounds: the same limits (most spans of a long chain)
            merged = (chain.cap_geom, chain.a, chain.j, chain.qs_a, chain.qs_j)
        else:
            try:
                merged = self._path_limits(d1, d2, d3, chain.cmd)
            except PlannerError:
                return None
        top = chain.best
        if (merged[0] < SMOOTH_MERGE * max(top[0], span_cap)
                or merged[1] < SMOOTH_MERGE_ACC * top[1] or merged[2] < SMOOTH_MERGE * top[2]):
            return None
        return merged

    def _finish_chain(self) -> None:
        """End a smoothed chain at the queue's tail: the pending line becomes a span from the chain's
        tangent and curvature to its own direction with zero curvature at its middle, then the straight
        second half (which a corner blend, a transition or a stop may then take as any line).

        If this cannot be done (the running profile ends into it, or the span would leave
        SMOOTH_DEVIATION * P), the line stays: the join then caps the speed as any tangent or
        curvature step does (:meth:`_junction`), which is safe.
        """
        q = self._q
        if self._h >= len(q):
            return
        tail = q[-1]
        if not isinstance(tail, Seg) or tail.smooth_in is None:
            return
        t, k, _w0, _l0 = tail.smooth_in
        tail.smooth_in = None
        if tail.s0 > 0.0 or (len(q) - 1 == self._h and self._active is not None and self._v_end > 0.0):
            return
        b = tail.piece
        half = 0.5 * b.length
        mid = tuple(b.pos(half))
        span = Span(b.start, t, k, mid, b.d1_end, (0.0,) * self._n, half)
        if span.chord_deviation() > SMOOTH_DEVIATION * tol_left(tail):
            return
        try:
            limits = self._path_limits(span.d1_max, span.d2_max, span.d3_max, tail.cmd)
        except PlannerError:
            return
        sseg = self._span_seg(span, tail, limits, (limits[0], limits[1], limits[2]),
                              b.part(0.0, half))  # type: ignore[attr-defined]
        rest = Seg(b.part(half, b.length), "line", tail.cmd, tail.feed, tail.rapid, tail.ovr)
        rest.sides, rest.orig_length, rest.blend_tol = tail.sides, tail.orig_length, tail.blend_tol
        rest.merge_dev = tail.merge_dev
        self._copy_limits(rest, tail)
        snapshot = self._snapshot(len(q) - 2)
        q.pop()
        index = len(q)
        for it in (sseg, rest):
            self._link(it)
        changes = self._backward(index)
        if not self._head_feasible(changes):
            del q[index:]
            q.append(tail)
            self._restore(snapshot)
            return
        for seg, vb in changes:
            seg.vb = vb

    def _snapshot(self, first: int) -> list[tuple[Seg, float, float, float]]:
        """Links and end speeds of the queued segments from ``first`` on (for a rollback)."""
        return [(it, it.jgeom, it.jcap, it.vb) for it in self._q[max(first, self._h):] if isinstance(it, Seg)]

    @staticmethod
    def _restore(snapshot: list[tuple[Seg, float, float, float]]) -> None:
        for it, jgeom, jcap, vb in snapshot:
            it.jgeom, it.jcap, it.vb = jgeom, jcap, vb
