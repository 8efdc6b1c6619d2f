"""Merging: consecutive programmed lines that lie within a tolerance of one line are planned as that
one line (LinuxCNC's naive-CAM detector, G64 Q).

Why: CAM writes straight stretches as many collinear pieces and curves as dense chords, with
coordinates rounded to 3-4 decimals. Each programmed piece planned on its own costs a profile whose
path acceleration returns to zero at both ends, a cycle at least, and its rounding noise turns into
tangent and curvature steps. Merged, a stretch is one piece: its rounding noise is gone (the
decision looks at whether the points lie within the tolerance, not at their last digit) and a piece
shorter than a cycle costs nothing of its own.

The run of lines being merged is held here, before the queue, until a line does not fit (or a
command that is not such a line comes, or the queue runs short, or the input ends); then it enters
the queue as one :class:`~planner.geometry.MergedLine`, which still says which programmed line each
part of it comes from. What may be merged (docs/planner.md, "Merging"): feed moves and traverses
in G64 or G61 (never under exact stop, G9, a probe, inverse time, or with rotary axes moving beside
linear ones), of the same feed, override switches and mode, with no event between them, each
advancing along the run (no reversal), every programmed point within the merge tolerance of the
merged line.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

from gcode_canon import commands as C
from planner.geometry import MergedLine
from planner.segments import MERGE_EXACT, MERGE_MAX_PIECES, MERGE_MAX_TIME, MERGE_SHARE

log = logging.getLogger(__name__)


class _Run:
    """Lines being merged: from ``start`` through the ``points`` (the interior programmed points) to
    ``end``; ``dev`` bounds the distance of every interior point from the chord ``start``-``end``."""

    __slots__ = ("chord", "cmds", "dev", "end", "events", "exact_from", "feed", "key", "length", "points",
                 "rapid", "start", "tol", "tol_mode")

    def __init__(self, start: tuple[float, ...], end: tuple[float, ...], cmd: C.Canon, feed: float,
                 rapid: bool, key: tuple, tol: float, tol_mode: float, events: list[C.Canon]) -> None:
        self.start, self.end = start, end
        self.chord = [x - y for x, y in zip(end, start, strict=True)]
        self.length = math.hypot(*self.chord)
        self.points: list[tuple[float, ...]] = []
        self.cmds: list[C.Canon] = [cmd]
        self.dev = 0.0
        self.exact_from = 0  # pieces when dev was last computed exactly
        self.feed, self.rapid, self.key, self.tol, self.tol_mode = feed, rapid, key, tol, tol_mode
        self.events = events


def _line_distance(p: Sequence[float], a: Sequence[float], u: Sequence[float]) -> float:
    """Distance of ``p`` from the line through ``a`` with unit direction ``u``."""
    d = [x - y for x, y in zip(p, a, strict=True)]
    along = sum([x * y for x, y in zip(d, u, strict=True)])
    norm = math.hypot(*d)
    return math.sqrt(max(norm * norm - along * along, 0.0))


class MergingMixin:
    """Part of :class:`planner.core.Planner`: the run of lines being merged."""

    def _merge_tolerance(self) -> float:
        """How far a programmed point may lie from the merged line: G64 Q if given (at most P), else
        MERGE_SHARE of P; in G64 without P and in G61, MERGE_EXACT (rounding noise only)."""
        if self._mode is C.MotionControlMode.CONTINUOUS and self._tolerance > 0.0:
            q = self._naive
            tol = min(q, self._tolerance) if q > 0.0 else MERGE_SHARE * self._tolerance
            return max(tol, min(MERGE_EXACT, self._tolerance))
        return MERGE_EXACT

    def _try_merge(self, cmd: C.Canon, start: Sequence[float], end: Sequence[float], length: float,
                   feed: float, rapid: bool, exact: bool) -> bool:
        """Take the line ``start``-``end`` into the run (or start a run with it); False when it is
        not a line that may be merged (the run, if any, is then already emitted)."""
        mode = self._mode
        if (exact or mode not in (C.MotionControlMode.CONTINUOUS, C.MotionControlMode.EXACT_PATH)
                or self._feed_mode is C.FeedMode.INVERSE_TIME
                or abs(math.dist(start, end) - length) > 1e-9 * (1.0 + length)):
            self._emit_run()
            return False
        tol_mode = self._tolerance if mode is C.MotionControlMode.CONTINUOUS else -1.0
        key = (feed, rapid, self._seg_ovr(rapid), tol_mode)
        run = self._run
        end_t = tuple(end)
        if run is not None and run.key == key and not self._pending and self._extend(run, end_t, cmd):
            return True
        self._emit_run()
        self._run = _Run(tuple(start), end_t, cmd, feed, rapid, key, self._merge_tolerance(), tol_mode,
                         self._pending)
        self._pending = []
        return True

    def _extend(self, run: _Run, end: tuple[float, ...], cmd: C.Canon) -> bool:
        """Whether the run with ``end`` added stays within its tolerance (then it is added)."""
        n = len(run.cmds)
        if n >= MERGE_MAX_PIECES:
            return False
        s, e, old, old_len = run.start, run.end, run.chord, run.length
        piece = [x - y for x, y in zip(end, e, strict=True)]
        chord = [x + y for x, y in zip(old, piece, strict=True)]
        length = math.hypot(*chord)
        if length <= 0.0 or length > MERGE_MAX_TIME * run.feed:
            return False
        # each piece advances along the run: the new piece and the run so far point the same way
        if sum([x * y for x, y in zip(piece, chord, strict=True)]) < 0.5 * math.hypot(*piece) * length:
            return False
        along = sum([x * y for x, y in zip(old, chord, strict=True)]) / length
        if along <= 0.0:
            return False
        # The interior points lie within dev of the old chord; the new chord starts at the same point
        # and is at most dist(e, new line) from it along the old chord: dev grows by at most that.
        step = math.sqrt(max(old_len * old_len - along * along, 0.0))
        if step > run.tol:
            return False
        dev = run.dev + step
        if dev > run.tol:
            # the bound is loose: measure exactly (short runs always; long ones at most once every n / 8
            # pieces: amortised O(1) per line)
            if n > 64 and n - run.exact_from < n // 8:
                return False
            dev = step
            u = [x / length for x in chord]
            for p in run.points:
                d = _line_distance(p, s, u)
                if d > dev:
                    dev = d
                    if dev > run.tol:
                        return False
            run.exact_from = n
        run.points.append(e)
        run.cmds.append(cmd)
        run.end, run.chord, run.length = end, chord, length
        run.dev = dev
        return True

    def _emit_run(self) -> None:
        """The run enters the queue as one line."""
        run = self._run
        if run is None:
            return
        self._run = None
        s, e = run.start, run.end
        length = math.dist(s, e)
        u = [(x - y) / length for x, y in zip(e, s, strict=True)]
        starts = [0.0]
        for p in run.points:
            along = sum((x - y) * w for x, y, w in zip(p, s, u, strict=True))
            starts.append(min(max(along, starts[-1]), length))
        piece = MergedLine(s, e, length, starts, run.cmds) if len(run.cmds) > 1 else None
        cmd = run.cmds[0]
        seg = self._new_line_seg(piece, cmd, s, e, length, run.feed, run.rapid, run.key[2], run.tol_mode)
        seg.merge_dev = run.dev
        seg.events = run.events
        self._queue_seg(seg, False)
