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
from planner.arcfit import ArcFit, fit_arc
from planner.geometry import MergedArc, MergedLine
from planner.segments import (
    ARC_DENSE,
    ARC_TRY,
    ARC_TRY_EXACT,
    MERGE_EXACT,
    MERGE_EXACT_ARC,
    MERGE_MAX_PIECES,
    MERGE_MAX_TIME,
    MERGE_NOP_ARC,
    MERGE_SHARE,
    Seg,
)

log = logging.getLogger(__name__)


class _Run:
    """Lines being merged: from ``start`` through the ``points`` (the interior programmed points) to
    ``end``; ``dev`` bounds the distance of every interior point from the chord ``start``-``end``."""

    __slots__ = ("arc", "arc_n", "chord", "cmds", "dev", "end", "events", "exact_from", "feed", "key",
                 "length", "line_n", "points", "rapid", "start", "tol", "tol_mode", "travel")

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
        self.travel = self.length  # the programmed length so far
        self.arc: ArcFit | None = None  # once the points no longer lie on one line: the arc they lie on
        self.arc_n = 0  # pieces when ``arc`` was fitted (the pieces after it are not checked yet)
        self.line_n = 1  # pieces the line (chord, length, dev) holds: all of them until ``arc`` is set


def _line_distance(p: Sequence[float], a: Sequence[float], u: Sequence[float]) -> float:
    """Distance of ``p`` from the line through ``a`` with unit direction ``u``."""
    d = [x - y for x, y in zip(p, a, strict=True)]
    along = sum([x * y for x, y in zip(d, u, strict=True)])
    norm = math.hypot(*d)
    return math.sqrt(max(norm * norm - along * along, 0.0))


def _arc_fit(run: _Run, planes: list[tuple[int, int]], end: tuple[float, ...]) -> ArcFit | None:
    """The arc the run's points to ``end`` lie on (``planner.arcfit``), within the run's tolerance.

    In G64 P: the run's tolerance. In G61: MERGE_EXACT_ARC (4-decimal rounding plus a chord's own
    sagitta), the centre refitted where the rounding spoils the three-point circle. In G64 without
    P: each programmed point within MERGE_EXACT_ARC of the arc, as in G61, and the chords within
    MERGE_NOP_ARC of it (their sagitta ``h^2/8R``: 0.1 mm chords on R 10 mm bulge 1.25e-4 mm from
    the arc, which with the rounding left no margin in 2e-4 and split the arc where a point's
    rounding was near its largest; the corner blends of the chords, which that mode otherwise
    makes, cut each vertex by 0.08 h^2/R, of the same order)."""
    if run.tol_mode > 0.0:
        return fit_arc(run.start, run.points, end, run.tol, planes)
    tol = max(run.tol, MERGE_EXACT_ARC)
    return fit_arc(run.start, run.points, end, MERGE_NOP_ARC if run.tol_mode == 0.0 else tol, planes,
                   refine=True, point_tol=tol)


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
        if run is not None and run.key == key and not self._pending and self._extend_open(end_t, cmd):
            return True
        self._emit_run()
        self._run = _Run(tuple(start), end_t, cmd, feed, rapid, key, self._merge_tolerance(), tol_mode,
                         self._pending)
        self._pending = []
        return True

    def _extend(self, run: _Run, end: tuple[float, ...], cmd: C.Canon) -> bool:
        """Whether the run with ``end`` added stays within its tolerance of one line, or else of one
        arc (then it is added)."""
        if len(run.cmds) >= MERGE_MAX_PIECES:
            return False
        if run.arc is None and self._extend_line(run, end, cmd):
            return True
        return self._extend_arc(run, end, cmd)

    def _extend_line(self, run: _Run, end: tuple[float, ...], cmd: C.Canon) -> bool:
        n = len(run.cmds)
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
        run.travel += math.hypot(*piece)
        run.dev = dev
        run.line_n = n + 1
        return True

    def _extend_arc(self, run: _Run, end: tuple[float, ...], cmd: C.Canon) -> bool:
        """Add ``end`` if the run stays within its tolerance of one arc (``planner.arcfit``). The fit
        costs O(run): it is redone for every piece of a short run and past that each time the run has
        grown by half (amortised O(1) per line, about 3 point checks per piece; every n/8 pieces cost
        9, half the spiral's planning); the pieces in between are checked when the run is emitted
        (:meth:`_emit_one`), which falls back to the last arc that was checked."""
        try_from = ARC_TRY if run.tol_mode > 0.0 else ARC_TRY_EXACT
        if run.rapid or (run.arc is None and len(run.cmds) < try_from):
            return False
        travel = run.travel + math.dist(run.end, end)
        if travel > MERGE_MAX_TIME * run.feed:
            return False
        n = len(run.cmds)
        run.points.append(run.end)
        if run.arc is None or n + 1 - run.arc_n >= max(1, n // 2):
            fit = _arc_fit(run, self._arc_planes, end)
            if fit is None:
                run.points.pop()
                return False
            run.arc, run.arc_n = fit, n + 1
        run.cmds.append(cmd)
        run.end, run.travel = end, travel
        return True

    def _emit_run(self, keep_last: bool = False) -> None:
        """The run enters the queue as one line or arc. An arc that holds only as far as it was
        checked (or is too short) enters that far, and the pieces after it are merged again; with
        ``keep_last`` the last run they make stays open (the next line may still join it)."""
        run = self._run
        if run is None:
            return
        self._run = None
        rest = self._emit_one(run)
        if not rest:
            return
        start = run.points[len(run.cmds) - len(rest) - 1]
        for end, cmd in rest:
            self._add_to_run(start, end, cmd, run)
            start = end
        if not keep_last:
            self._emit_run()

    def _add_to_run(self, start: tuple[float, ...], end: tuple[float, ...], cmd: C.Canon, like: _Run) -> None:
        """Add the piece ``start``-``end`` to the open run, or open another (with the feed, mode and
        tolerance of ``like``)."""
        if not self._extend_open(end, cmd):
            self._run = _Run(start, end, cmd, like.feed, like.rapid, like.key, like.tol, like.tol_mode, [])

    def _extend_open(self, end: tuple[float, ...], cmd: C.Canon) -> bool:
        """Extend the open run with a piece to ``end``. Where it does not fit, the run is emitted; what
        an arc leaves out of it stays open and is tried again, so a line ends up in the run it would
        have joined had no arc been tried (False: it opens a run of its own)."""
        while self._run is not None:
            if self._extend(self._run, end, cmd):
                return True
            self._emit_run(keep_last=True)
        return False

    def _emit_one(self, run: _Run) -> list[tuple[tuple[float, ...], C.Canon]]:
        """Queue the run as one piece; return the pieces left out (``(end, cmd)`` each, in order, the
        first starting where the queued piece ends) when its arc holds only as far as it was checked."""
        s, n = run.start, len(run.cmds)
        if run.arc is not None:
            fit, k = run.arc, n
            if run.arc_n < n:
                full = _arc_fit(run, self._arc_planes, run.end)
                if full is not None:
                    fit = full
                else:
                    k = run.arc_n
            ends = [*run.points, run.end]
            if k < ARC_DENSE:
                # too few pieces to gain from an arc: the line they were, then the rest again
                k = run.line_n
                self._emit_line(run, ends[k - 1], run.points[: k - 1], run.cmds[:k])
                return list(zip(ends[k:], run.cmds[k:], strict=True))
            piece = MergedArc(s, ends[k - 1], fit.i0, fit.i1, fit.c0, fit.c1, fit.sweep, fit.length,
                              fit.starts, run.cmds[:k])
            seg = Seg(piece, "arc", run.cmds[0], run.feed, run.rapid, run.key[2])
            seg.blend_tol = run.tol_mode
            self._limits(seg)
            self._last_chord = None
            seg.merge_dev = fit.dev
            seg.events = run.events
            self._queue_seg(seg, False)
            return list(zip(ends[k:], run.cmds[k:], strict=True))
        self._emit_line(run, run.end, run.points, run.cmds)
        return []

    def _emit_line(self, run: _Run, end: tuple[float, ...], points: list[tuple[float, ...]],
                   cmds: list[C.Canon]) -> None:
        """Queue the line from the run's start to ``end`` through ``points``, merged from ``cmds``."""
        s = run.start
        length = math.dist(s, end)
        u = [(x - y) / length for x, y in zip(end, s, strict=True)]
        starts = [0.0]
        for p in points:
            along = sum((x - y) * w for x, y, w in zip(p, s, u, strict=True))
            starts.append(min(max(along, starts[-1]), length))
        piece = MergedLine(s, end, length, starts, cmds) if len(cmds) > 1 else None
        seg = self._new_line_seg(piece, cmds[0], s, end, length, run.feed, run.rapid, run.key[2],
                                 run.tol_mode)
        seg.merge_dev = run.dev
        seg.events = run.events
        self._queue_seg(seg, False)
