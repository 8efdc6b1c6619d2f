"""The lookahead: each queued segment's ``vb``, the fastest speed at its end from which everything
queued behind it can still be travelled and stopped at the end of the queue. Linking a segment walks
the end speeds back from the tail only until they stop changing; an override change computes them all
again. Part of :class:`planner.core.Planner`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from planner.kinematics import max_reach
from planner.segments import SLACK, Seg


class LookaheadMixin:
    """Planner state used (set by :class:`~planner.core.Planner`): the queue (``_q`` from its head
    ``_h``), the running segment (``_active``) and its end speed (``_v_end``)."""

    stats: dict[str, int]
    _q: list[Any]
    _h: int
    _active: Any
    _v_end: float
    _junction: Callable[[Seg, Seg], float]  # planner.limits
    _set_cap: Callable[[Seg], None]  # planner.limits

    def _link(self, seg: Seg) -> None:
        """Append ``seg``, linking it to the queued segment before it."""
        if self._h < len(self._q):
            prev = self._q[-1]
            if isinstance(prev, Seg):
                prev.jgeom = self._junction(prev, seg)
                prev.jcap = min(prev.jgeom, prev.cap, seg.cap)
        seg.vb = 0.0
        seg.jcap = seg.jgeom = 0.0
        seg.last = self.stats["segments"]
        self._q.append(seg)

    def _append(self, seg: Seg) -> None:
        index = len(self._q)
        self._link(seg)
        for s, vb in self._backward(index):
            s.vb = vb

    def _backward(self, modified_from: int) -> list[tuple[Seg, float]]:
        """New end speeds walking back from the tail, until they stop changing (not yet applied)."""
        q = self._q
        changes: list[tuple[Seg, float]] = []
        nxt_vb = 0.0
        nxt: Seg | None = None
        for i in range(len(q) - 1, self._h - 1, -1):
            item = q[i]
            if not isinstance(item, Seg):
                break
            if nxt is None:
                vb = 0.0
            else:
                vb = min(item.jcap, max_reach(nxt_vb, nxt.length * SLACK, nxt.a, nxt.j))
            if i < modified_from and abs(vb - item.vb) <= 1e-12 * (1.0 + vb):
                break
            changes.append((item, vb))
            nxt, nxt_vb = item, vb
        return changes

    def _head_feasible(self, changes: list[tuple[Seg, float]]) -> bool:
        if self._active is None or self._v_end <= 0.0 or self._h >= len(self._q):
            return True
        head = self._q[self._h]
        if not isinstance(head, Seg):
            return True
        vb = next((v for s, v in changes if s is head), head.vb)
        return self._v_end <= max_reach(vb, head.length, head.a, head.j) * (1 + 1e-9) + 1e-12

    def _recompute_all(self) -> None:
        """After an override change: every cap and end speed again (O(queue), once per change)."""
        q = self._q
        for i in range(self._h, len(q)):
            if isinstance(q[i], Seg):
                self._set_cap(q[i])  # type: ignore[arg-type]
        for i in range(self._h, len(q)):
            item = q[i]
            if isinstance(item, Seg):
                nxt = q[i + 1] if i + 1 < len(q) else None
                item.jcap = min(item.jgeom, item.cap, nxt.cap) if isinstance(nxt, Seg) else 0.0
        nxt_vb, nxt = 0.0, None
        for i in range(len(q) - 1, self._h - 1, -1):
            item = q[i]
            if not isinstance(item, Seg):
                nxt = None
                continue
            if nxt is None:
                item.vb = 0.0
            else:
                item.vb = min(item.jcap, max_reach(nxt_vb, nxt.length * SLACK, nxt.a, nxt.j))
            nxt, nxt_vb = item, item.vb
