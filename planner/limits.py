"""Limits along the path: the speed cap and the path acceleration and jerk of a piece from its
derivative bounds (tangential, centripetal and cross terms budgeted together), and the speed cap at
a junction from the steps it makes in one cycle.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

from gcode_canon import commands as C
from planner.segments import (
    CORNER,
    JUNCTION_CURVATURE,
    JUNCTION_TANGENT,
    OVR_ADAPTIVE,
    OVR_FEED,
    PlannerError,
    Seg,
)

log = logging.getLogger(__name__)


class LimitsMixin:
    """Part of :class:`planner.core.Planner`: limits of pieces and junctions."""

    def _limits(self, seg: Seg) -> None:
        """Speed cap and path acceleration/jerk limits that keep every axis inside its limits."""
        p = seg.piece
        (seg.cap_geom, seg.a, seg.j, seg.qs_a, seg.qs_j) = self._path_limits(
            p.d1_max, p.d2_max, p.d3_max, seg.cmd)
        self._set_cap(seg)

    def _path_limits(self, d1: Sequence[float], d2: Sequence[float], d3: Sequence[float],
                     cmd: C.Canon) -> tuple[float, float, float, float, float]:
        """(speed cap, path acceleration, path jerk, quick-stop acceleration and jerk) for derivative
        bounds ``d1 d2 d3``: tangential, centripetal and cross terms budgeted together.

        The centripetal and cross terms are reserved at the piece's own speed cap, not at the fastest
        the feed (times the largest override) would run it: the limits then do not depend on the feed,
        so a higher feed only lifts speed caps. (Reserved at the feed, a higher feed left less path
        acceleration on every curved piece: on some CAM waves F3000 took a cycle longer than F2500.)
        A piece run slower than its cap keeps some acceleration unused: no measurable cost on CAM
        waves and the surfacing raster, but a lone G3 at half its cap takes 3-4 % longer."""
        if not any(d2) and not any(d3):
            return self._line_limits(d1, cmd)
        cap = self._speed_cap(d1, d2, d3)
        vb = cap
        vb2 = vb * vb
        a = j = qs = ratio = math.inf
        for acc, qs_acc, qr, jcross, e1, e2 in zip(self._A, self._QS, self._QR, self._JCROSS, d1, d2,
                                                   strict=True):
            if e1 > 0.0:
                x = (acc - vb2 * e2) / e1
                if x < a:
                    a = x
                x = (qs_acc - vb2 * e2) / e1
                if x < qs:
                    qs = x
                if qr < ratio:
                    ratio = qr
            if e2 > 0.0 and vb > 0.0:
                x = jcross / (vb * e2)
                if x < a:
                    a = x
        vb3, va3 = vb2 * vb, 3.0 * vb * a
        for jc, e1, e2, e3 in zip(self._JC, d1, d2, d3, strict=True):
            if e1 > 0.0:
                x = (jc - vb3 * e3 - va3 * e2) / e1
                if x < j:
                    j = x
        if not (a > 0.0 and j > 0.0 and cap > 0.0 and math.isfinite(a) and math.isfinite(j)):
            raise PlannerError(f"cannot derive path limits for this move (a={a:g}, j={j:g}, v={cap:g})",
                               cmd.file, cmd.line)
        # Quick stop: the tangential deceleration that keeps every axis within its
        # quick_stop_deceleration with the centripetal part at this speed counted (it only shrinks as
        # the axis slows), never weaker than a normal stop; the path jerk scaled with it but by no more
        # than the smallest quick-stop ratio of the moving axes. An emergency stop keeps its braking
        # distance short: on a tight curve the axes' jerk may still exceed ratio x max_jerk through
        # the cross term 3 q'' v a (a drive's own quick-stop ramp has no jerk limit at all).
        qs_a = max(qs, a) if math.isfinite(qs) else a
        ratio = ratio if math.isfinite(ratio) else 1.0
        return cap, a, j, qs_a, j * min(qs_a / a, ratio)

    def _speed_cap(self, d1: Sequence[float], d2: Sequence[float], d3: Sequence[float]) -> float:
        """The speed cap of :meth:`_path_limits` alone: axis velocities, centripetal acceleration and
        centripetal jerk budgets."""
        cap = math.inf
        for v_max, ca, jcent, e1, e2, e3 in zip(self._V, self._CA, self._JCENT, d1, d2, d3, strict=True):
            if e1 > 0.0 and v_max < cap * e1:
                cap = v_max / e1
            if e2 > 0.0 and ca < cap * cap * e2:
                cap = math.sqrt(ca / e2)
            if e3 > 0.0 and jcent < cap * cap * cap * e3:
                cap = (jcent / e3) ** (1.0 / 3.0)
        return cap

    def _line_limits(self, d1: Sequence[float], cmd: C.Canon) -> tuple[float, float, float, float, float]:
        """:meth:`_path_limits` without curvature (a line): the axis limits projected on it. The same
        values, for the cost of a third: every fed line comes here."""
        cap = a = j = qs = ratio = math.inf
        for v_max, acc, qs_acc, qr, jc, d in zip(self._V, self._A, self._QS, self._QR, self._JC, d1,
                                                 strict=True):
            if d > 0.0:  # the smallest of each limit over d: the largest d (ties keep the first)
                if qr < ratio:
                    ratio = qr
                if v_max < cap * d:
                    cap = v_max / d
                if acc < a * d:
                    a = acc / d
                if qs_acc < qs * d:
                    qs = qs_acc / d
                if jc < j * d:
                    j = jc / d
        if not (math.isfinite(a) and math.isfinite(j)):
            raise PlannerError(f"cannot derive path limits for this move (a={a:g}, j={j:g}, v={cap:g})",
                               cmd.file, cmd.line)
        qs_a = max(qs, a)
        # the jerk scaled as the acceleration, but by no more than the smallest quick-stop ratio of
        # the moving axes, so each axis's jerk stays within its ratio x max_jerk
        return cap, a, j, qs_a, j * min(qs_a / a, ratio)

    @staticmethod
    def _copy_limits(dst: Seg, src: Seg) -> None:
        """A part of a line has the line's limits (they depend on its direction and feed only)."""
        dst.cap_geom, dst.cap, dst.a, dst.j, dst.qs_a, dst.qs_j = (
            src.cap_geom, src.cap, src.a, src.j, src.qs_a, src.qs_j)

    def _set_cap(self, seg: Seg) -> None:
        cap = seg.cap_geom
        for feed, ovr in seg.sides:
            scale = self._adaptive if ovr & OVR_ADAPTIVE else 1.0
            if seg.rapid:
                cap = min(cap, seg.cap_geom * scale)
            else:
                cap = min(cap, feed * scale * (self._override if ovr & OVR_FEED else 1.0))
        seg.cap = max(cap, 1e-9)

    def _junction(self, prev: Seg, nxt: Seg) -> float:
        """Speed cap where ``prev`` meets ``nxt``: steps in dq/ds and d2q/ds2 within one cycle."""
        if prev.stop:
            return 0.0
        a, b = prev.piece, nxt.piece
        T = self.T
        cap = math.inf
        for i in range(self._n):
            dd1 = abs(a.d1_end[i] - b.d1_start[i])
            if dd1 > CORNER:
                return 0.0
            if dd1 > 1e-12:
                cap = min(cap, JUNCTION_TANGENT * self._J[i] * T * T / dd1)
            dd2 = abs(a.d2_end[i] - b.d2_start[i])
            if dd2 > 1e-12:
                cap = min(cap, math.sqrt(JUNCTION_CURVATURE / 0.75 * self._J[i] * T / dd2))
        return cap
