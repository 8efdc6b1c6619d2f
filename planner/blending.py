"""Corner blends between lines and curvature-continuous transitions at joins with arcs, in G64
(docs/planner.md, "Blends" and "Transitions").
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

from gcode_canon import commands as C
from planner.geometry import (
    SIGMA1_MAX,
    SIGMA2_MAX,
    Arc,
    Blend,
    Piece,
    Transition,
    deviation_of_blend,
)
from planner.kinematics import change_distance
from planner.segments import (
    CORNER,
    MAX_OVERRIDE,
    MIN_LENGTH,
    TRANSITION_ARC,
    TRANSITION_DEVIATION,
    TRANSITION_SAMPLES,
    PlannerError,
    Seg,
    tol_left,
)

log = logging.getLogger(__name__)


class BlendingMixin:
    """Part of :class:`planner.core.Planner`: blends and transitions."""

    def _try_blend(self, new: Seg) -> bool:
        """In G64, replace the corner between the queued line and ``new`` (a line) by a blend, or a
        join involving an arc by a :class:`Transition`."""
        if self._h >= len(self._q):
            return False
        prev = self._q[-1]
        if not isinstance(prev, Seg) or prev.kind not in ("line", "arc") or prev.stop or prev.s0 > 0.0:
            return False
        if new.kind == "arc" or prev.kind == "arc":
            return self._try_transition(prev, new)
        if new.kind != "line":
            return False
        tolerance = tol_left(prev, new)
        if tolerance < 0.0:
            return False
        w1, w2 = prev.piece.d1_end, new.piece.d1_start
        dw = max(abs(w2[i] - w1[i]) for i in range(self._n))
        if dw <= 1e-12:
            return False  # collinear: no corner
        d = min(0.5 * prev.orig_length, prev.piece.length, 0.5 * new.piece.length)
        # the deviation over every axis (rotary ones included, degrees counted as millimetres): the
        # tolerance then holds in each axis and in XYZ alike, as the checker measures it
        unit = deviation_of_blend(w1, w2, 1.0, range(self._n))
        sized = False
        if tolerance > 0.0:
            d = min(d, tolerance / unit)
        else:
            # G64 without P (LinuxCNC's rule): only as large as the speed it must keep needs
            need = self._blend_size(w1, w2, min(prev.feed, new.feed, prev.cap_geom, new.cap_geom))
            if need < d:
                d, sized = need, True
        is_head = len(self._q) - 1 == self._h
        if is_head and self._active is not None and self._v_end > 0.0:
            d = min(d, prev.piece.length - change_distance(self._v_end, 0.0, prev.a, prev.j) - 1e-9)
        if d <= 1e-9:
            return False
        keep = prev.piece.length - d
        if not sized and 0.0 < keep < 0.25 * d and prev.piece.length <= 0.6 * new.piece.length and (
                tolerance <= 0.0 or prev.piece.length <= tolerance / unit):
            d = prev.piece.length  # no sliver of line between two blends: one piece less to plan
        corner = prev.piece.end
        blend = Blend(corner, w1, w2, d)
        bseg = Seg(blend, "blend", new.cmd, min(prev.feed, new.feed), prev.rapid and new.rapid,
                   prev.ovr | new.ovr)
        bseg.sides = prev.sides + new.sides
        self._limits(bseg)
        orig_piece, orig_events = new.piece, new.events
        new.piece = orig_piece.part(d, orig_piece.length)  # type: ignore[attr-defined]  # same limits
        bseg.events, new.events = list(orig_events), []
        # replace prev by its trimmed part (or drop it when the blend takes it all)
        index = len(self._q) - 1
        self._q.pop()
        keep = prev.piece.length - d
        items: list[Seg] = []
        if keep > MIN_LENGTH:
            trimmed = Seg(prev.piece.part(0.0, keep),  # type: ignore[attr-defined]
                          "line", prev.cmd, prev.feed, prev.rapid, prev.ovr)
            trimmed.orig_length, trimmed.blend_tol = prev.orig_length, prev.blend_tol
            trimmed.merge_dev = prev.merge_dev
            self._copy_limits(trimmed, prev)
            trimmed.events = prev.events
            items.append(trimmed)
        else:
            bseg.events = prev.events + bseg.events
        items += [bseg, new]
        return self._splice(index, prev, new, items, orig_piece, orig_events)

    def _blend_size(self, w1: Sequence[float], w2: Sequence[float], v: float) -> float:
        """The smallest half-length ``d`` of a corner blend from direction ``w1`` to ``w2`` whose own
        speed cap (:meth:`_speed_cap`: centripetal acceleration and jerk within their budgets) is at
        least ``v``; the blend's second and third derivatives along s fall as 1/d and 1/d^2. Its
        deviation is then ``0.15625 d |w2 - w1|``: of the order of v^2/a, not half a segment."""
        d = 0.0
        v2 = v * v
        for ca, jcent, x, y in zip(self._CA, self._JCENT, w1, w2, strict=True):
            dw = abs(y - x)
            if dw > 0.0:
                d = max(d, v2 * dw * SIGMA1_MAX / (2.0 * ca),
                        math.sqrt(v2 * v * dw * SIGMA2_MAX / (4.0 * jcent)))
        return d * (1.0 + 1e-6)

    def _splice(self, index: int, prev: Seg, new: Seg, items: list[Seg], orig_piece: Piece,
                orig_events: list[C.Canon], orig_limits: tuple[float, ...] | None = None) -> bool:
        """Put ``items`` (``prev`` trimmed, a blend or transition, ``new`` shortened) in the queue at
        ``index`` where ``prev`` was, and walk the speeds back. When the running profile could then no
        longer keep its committed speed, undo it all (``prev`` back, ``new`` as it was) and say False."""
        saved = self._save_tail_links(index)
        for it in items:
            self._link(it)
        changes = self._backward(index)
        if not self._head_feasible(changes):
            del self._q[index:]
            self._restore_tail_links(saved)
            self._q.append(prev)
            new.piece, new.events = orig_piece, orig_events
            if orig_limits is not None:
                self._set_limits(new, orig_limits)
            return False
        for seg, vb in changes:
            seg.vb = vb
        self.stats["blends"] += 1
        return True

    def _try_transition(self, prev: Seg, new: Seg) -> bool:
        """In G64, replace the join of ``prev`` and ``new`` (one an arc) by a curvature-continuous
        :class:`Transition` within P, when the join would otherwise cap the speed.

        The transition starts ``d`` before the join on ``prev`` and ends ``d`` after it on ``new``; d
        is the largest that keeps the sampled deviation within TRANSITION_DEVIATION * P (and at most
        half of each move), found by shrinking from that bound.
        """
        tolerance = tol_left(prev, new)
        if tolerance < 0.0:
            return False
        a, b = prev.piece, new.piece
        n = self._n
        if (max(abs(a.d1_end[i] - b.d1_start[i]) for i in range(n)) <= 1e-12
                and max(abs(a.d2_end[i] - b.d2_start[i]) for i in range(n)) <= 1e-9):
            return False  # already continuous in curvature
        top = min(prev.cap_geom, new.cap_geom, MAX_OVERRIDE * max(prev.feed, new.feed))
        if self._junction(prev, new) >= top:
            return False  # the join does not limit the speed: a transition would only add a piece
        d = min(0.5 * prev.orig_length, a.length, 0.5 * b.length)
        for piece in (a, b):
            if isinstance(piece, Arc):
                d = min(d, TRANSITION_ARC * piece.radius)  # never across a good part of a circle
        if self._allowed(new.blend_tol) < self._allowed(prev.blend_tol):
            # the checker (and the user) grant P near the start of the next move only within 0.6 of
            # its chord: stay within half of it
            d = min(d, 0.5 * math.dist(b.start, b.end))
        is_head = len(self._q) - 1 == self._h
        if is_head and self._active is not None and self._v_end > 0.0:
            d = min(d, a.length - change_distance(self._v_end, 0.0, prev.a, prev.j) - 1e-9)
        corner = max(abs(a.d1_end[i] - b.d1_start[i]) for i in range(n)) > CORNER
        target = TRANSITION_DEVIATION * tolerance
        for _attempt in range(40):
            if d <= 1e-9:
                return False
            head, tr, tail = self._transition(a, b, d)
            if tolerance <= 0.0:
                break
            dev = self._transition_deviation(a, b, tr, d)
            if dev <= target:
                break
            ratio = target / dev
            d *= max(0.05, min(0.9, ratio if corner else math.sqrt(ratio)))  # dev ~ d (corner), d^2
        else:
            return False
        tseg = Seg(tr, "blend", new.cmd, min(prev.feed, new.feed), prev.rapid and new.rapid,
                   prev.ovr | new.ovr)
        tseg.sides = prev.sides + new.sides
        try:
            self._limits(tseg)
        except PlannerError:
            return False
        orig_piece, orig_events, orig_limits = new.piece, new.events, self._limits_of(new)
        new.piece = tail
        self._limits(new)
        tseg.events, new.events = list(orig_events), []
        index = len(self._q) - 1
        self._q.pop()
        items: list[Seg] = []
        if head is not None:
            trimmed = Seg(head, prev.kind, prev.cmd, prev.feed, prev.rapid, prev.ovr)
            trimmed.orig_length, trimmed.blend_tol = prev.orig_length, prev.blend_tol
            trimmed.merge_dev = prev.merge_dev
            trimmed.sides = prev.sides
            self._limits(trimmed)
            trimmed.events = prev.events
            items.append(trimmed)
        else:
            tseg.events = prev.events + tseg.events
        items += [tseg, new]
        return self._splice(index, prev, new, items, orig_piece, orig_events, orig_limits)

    @staticmethod
    def _allowed(blend_tol: float) -> float:
        """The deviation a move's mode allows (as the checker reads it): P, any in G64 without P."""
        if blend_tol < 0.0:
            return 1e-3
        return math.inf if blend_tol == 0.0 else max(blend_tol, 1e-3)

    @staticmethod
    def _limits_of(seg: Seg) -> tuple[float, ...]:
        return (seg.cap_geom, seg.cap, seg.a, seg.j, seg.qs_a, seg.qs_j)

    @staticmethod
    def _set_limits(seg: Seg, values: tuple[float, ...]) -> None:
        seg.cap_geom, seg.cap, seg.a, seg.j, seg.qs_a, seg.qs_j = values

    @staticmethod
    def _transition(a: Piece, b: Piece, d: float) -> tuple[Piece | None, Transition, Piece]:
        """The part of ``a`` kept before the transition (None: none), the transition, the rest of ``b``."""
        keep = a.length - d
        head = a.part(0.0, keep) if keep > MIN_LENGTH else None  # type: ignore[attr-defined]
        tail = b.part(d, b.length)  # type: ignore[attr-defined]
        if head is None:
            pa, ta, ka = a.start, a.d1_start, a.d2_start
        else:
            pa, ta, ka = head.end, head.d1_end, head.d2_end
        da = d if head is not None else a.length
        tr = Transition(pa, ta, ka, tail.start, tail.d1_start, tail.d2_start, da + d)
        return head, tr, tail

    def _transition_deviation(self, a: Piece, b: Piece, tr: Transition, d: float) -> float:
        """An upper bound of the distance of ``tr`` from the path it replaces.

        Each sample compares the transition with the original path at the same ``s`` (a point of the
        path, so at least as far as the path's nearest point); between samples the gap can grow by at
        most h^2/8 times the sum of both curves' second-derivative bounds. The join itself is a sample.
        """
        n = self._n
        da = tr.length - d  # the transition covers the last da of a and the first d of b
        worst = 0.0
        for part, piece, s_base, span in ((0, a, a.length - da, da), (1, b, 0.0, d)):
            h = span / TRANSITION_SAMPLES
            for k in range(TRANSITION_SAMPLES + 1):
                s_loc = k * h
                p_orig = piece.pos(s_base + s_loc)
                p_tr = tr.pos((da if part else 0.0) + s_loc)
                worst = max(worst, math.sqrt(sum((p_orig[i] - p_tr[i]) ** 2 for i in range(n))))
            curv = math.sqrt(sum(x * x for x in tr.d2_max)) + math.sqrt(sum(x * x for x in piece.d2_max))
            worst += h * h / 8.0 * curv
        return worst

    def _save_tail_links(self, index: int) -> tuple[Seg, float, float] | None:
        if index - 1 >= self._h:
            before = self._q[index - 1]
            if isinstance(before, Seg):
                return (before, before.jgeom, before.jcap)
        return None

    def _restore_tail_links(self, saved: tuple[Seg, float, float] | None) -> None:
        if saved is not None:
            saved[0].jgeom, saved[0].jcap = saved[1], saved[2]
