"""Motion commands into queue items: a move's target (axes this machine has, soft limits), its feed
speed (units per minute, inverse time, per revolution, spindle-synchronized), its piece of geometry
(a line, an arc, an arc turned by a rotated coordinate system) and its queue item, merged into a run,
smoothed into a chain, blended at its start or linked as it is. Part of :class:`planner.core.Planner`,
apart from the feeding of the other commands and the sampling of the running profile.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from typing import Any

from gcode_canon import commands as C
from planner.geometry import Arc, Line, Piece, TurnedArc, turn_xy
from planner.machine import MachineLimits
from planner.segments import _TOL, MIN_ARC_RADIUS, MIN_LENGTH, PlannerError, Seg

log = logging.getLogger(__name__)


class MovesMixin:
    """Planner state used (set by :class:`~planner.core.Planner`): the machine's axes (``machine``,
    ``_n``, ``_absent``, ``_pose_index``, ``_machine_index``, ``_groups``, soft limits ``_soft``,
    ``_has_soft``), where the last move ends (``_end``, ``_pose``), the modes (``_mode``, ``_tolerance``,
    ``_exact_next``, ``_feed_rate``, ``_feed_mode``, ``_spindle_rpm``, ``_sync_pitch``) and the events
    waiting for a motion (``_pending``)."""

    machine: MachineLimits
    stats: dict[str, int]
    _n: int
    _absent: list[int]
    _pose: list[float]
    _pose_index: list[int]
    _machine_index: dict[int, int]
    _groups: list[list[int]]
    _soft: list[tuple[float | None, float | None]]
    _has_soft: bool
    _end: list[float]
    _exact_next: bool
    _mode: C.MotionControlMode
    _tolerance: float
    _feed_rate: float
    _feed_mode: C.FeedMode
    _spindle_rpm: float
    _sync_pitch: float | None
    _pending: list[Any]
    _last_chord: Any
    # the other mixins' (planner.limits, merging, smoothing, blending, spindle_sync, lookahead) and core's
    _limits: Callable[[Seg], None]
    _seg_ovr: Callable[[bool], int]
    _try_merge: Callable[..., bool]
    _emit_run: Callable[[], None]
    _try_smooth: Callable[[Seg], bool]
    _finish_chain: Callable[[], None]
    _try_blend: Callable[[Seg], bool]
    _append: Callable[[Seg], None]
    _close_tail: Callable[[], None]
    _per_rev_css_line: Callable[[C.Canon], bool]
    _per_rev_speed: Callable[..., float]
    _synced_speed: Callable[[C.Canon], float]

    def _target(self, cmd: C.Canon, pose: C.Pose) -> list[float]:
        for p in self._absent:
            value = pose[p]
            if abs(value - self._pose[p]) > _TOL:
                raise PlannerError(f"{cmd.NAME} moves axis {C.AXES[p].upper()}, which this machine does "
                                   f"not have (axes: {' '.join(self.machine.names).upper()})",
                                   cmd.file, cmd.line)
        self._pose = list(pose)
        out = [pose[p] for p in self._pose_index]
        self._check_soft(cmd, out)
        return out

    def _check_soft(self, cmd: C.Canon, point: Sequence[float]) -> None:
        if not self._has_soft:
            return
        for i, (lo, hi) in enumerate(self._soft):
            if (lo is not None and point[i] < lo - _TOL) or (hi is not None and point[i] > hi + _TOL):
                name = self.machine.axes[i].name.upper()
                raise PlannerError(f"{cmd.NAME} to {name}{point[i]:g} is outside the soft limits "
                                   f"[{lo}, {hi}]", cmd.file, cmd.line)

    def _length(self, travel2: Sequence[float]) -> float:
        for g in self._groups:
            length = math.sqrt(sum([travel2[i] for i in g]))
            if length > MIN_LENGTH:
                return length
        return 0.0

    def _feed_speed(self, cmd: C.Canon, length: float, piece: Piece | None = None) -> float:
        if isinstance(cmd, C.StraightTraverse):
            return math.inf
        if self._sync_pitch is not None:  # G33, G33.1, G76: the spindle sets the pace, not F
            return self._synced_speed(cmd)
        rate, mode = self._feed_rate, self._feed_mode
        if mode is C.FeedMode.INVERSE_TIME:
            if rate <= 0:
                raise PlannerError("inverse-time feed (G93) needs F > 0 on this move", cmd.file, cmd.line)
            return length * rate / 60.0
        if mode is C.FeedMode.UNITS_PER_REV:
            if rate <= 0 or self._spindle_rpm <= 0:
                raise PlannerError(f"feed per revolution (G95) needs F > 0 and a turning spindle (F{rate:g}, "
                                   f"S{self._spindle_rpm:g})", cmd.file, cmd.line)
            return self._per_rev_speed(cmd, rate, piece)  # planner.spindle_sync: follows a measured spindle
        if rate <= 0:
            raise PlannerError("feed rate is 0: set F before a feed move", cmd.file, cmd.line)
        return rate / 60.0

    def _motion(self, cmd: C.Canon) -> None:
        if self._per_rev_css_line(cmd):
            return  # G95 under G96: queued in pieces (planner.spindle_sync)
        start = self._end
        end = self._target(cmd, cmd.end)  # type: ignore[attr-defined]
        exact = self._exact_next or isinstance(cmd, C.Probe) or self._mode in (
            C.MotionControlMode.EXACT_STOP_MODAL, C.MotionControlMode.EXACT_STOP)
        rapid = isinstance(cmd, C.StraightTraverse)
        # the corner at a move's end is blended by the mode the move was programmed in (LinuxCNC)
        blend_tol = self._tolerance if self._mode is C.MotionControlMode.CONTINUOUS else -1.0
        piece: Piece | None = None
        if isinstance(cmd, C.ArcFeed):
            piece = self._arc(cmd, start, end)
        if piece is None:
            delta = [e - s for e, s in zip(end, start, strict=True)]
            if max(map(abs, delta)) <= MIN_LENGTH:
                log.debug("%s:%d: zero-length move skipped", cmd.file, cmd.line)
                self._end = end
                if exact:
                    self._close_tail()  # a stop asked for here is kept, even without a move
                self._exact_next = False
                return
            length = self._length([x * x for x in delta])
            if length <= MIN_LENGTH:
                length = max(map(abs, delta))
            feed = self._feed_speed(cmd, length)
            self._exact_next = False
            self._end = end
            self.stats["segments"] += 1
            if self._try_merge(cmd, start, end, length, feed, rapid, exact):
                return
            ovr = self._seg_ovr(rapid)
            seg = self._new_line_seg(None, cmd, start, end, length, feed, rapid, ovr, blend_tol)
        else:
            self._emit_run()
            self._last_chord = None
            speed = self._feed_speed(cmd, piece.length, piece)
            seg = Seg(piece, "arc", cmd, speed, rapid, self._seg_ovr(rapid))
            seg.blend_tol = blend_tol
            self._limits(seg)
            self._exact_next = False
            self._end = end
            self.stats["segments"] += 1
        seg.events, self._pending = self._pending, []
        self._queue_seg(seg, exact)

    def _new_line_seg(self, piece: Piece | None, cmd: C.Canon, start: Sequence[float], end: Sequence[float],
                      length: float, feed: float, rapid: bool, ovr: int, blend_tol: float) -> Seg:
        """A queue item for a (merged) line, its limits set."""
        if piece is None:
            piece = Line(tuple(start), tuple(end), length)
        seg = Seg(piece, "line", cmd, feed, rapid, ovr)
        seg.chord_before, self._last_chord = self._last_chord, (piece.d1_start, piece.length)
        seg.blend_tol = blend_tol
        self._limits(seg)
        return seg

    def _queue_seg(self, seg: Seg, exact: bool) -> None:
        """Into the queue: smoothed into a chain, blended at its start, or linked as it is."""
        if not self._try_smooth(seg):
            self._finish_chain()
            if not self._try_blend(seg):
                self._append(seg)
        if exact:
            self._close_tail()

    def _arc(self, cmd: C.ArcFeed, start: list[float], end: list[float]) -> Piece | None:
        p0, p1, _pn = cmd.plane.value
        if p0 not in self._machine_index or p1 not in self._machine_index:
            raise PlannerError(f"arc in plane {cmd.plane.gcode} needs axes {C.AXES[p0].upper()} and "
                               f"{C.AXES[p1].upper()}", cmd.file, cmd.line)
        if cmd.turns == 0:
            raise PlannerError("arc with 0 turns", cmd.file, cmd.line)
        i0, i1 = self._machine_index[p0], self._machine_index[p1]
        centre = cmd.center
        turned = cmd.rotation != 0.0
        if turned:  # planned in the frame turned back about Z, where it lies in its axis plane
            ix, iy = self._machine_index.get(0), self._machine_index.get(1)
            if ix is None or iy is None:
                raise PlannerError(f"arc in plane {cmd.plane.gcode} turned by a rotated coordinate system "
                                   "needs axes X and Y", cmd.file, cmd.line)
            outer = (start, end)
            c, s = math.cos(math.radians(cmd.rotation)), math.sin(math.radians(cmd.rotation))
            start, end = (list(turn_xy(v, ix, iy, c, -s)) for v in outer)
            centre = C.rotate_about_z(centre, -cmd.rotation)
        c0, c1 = centre[p0], centre[p1]
        r0 = math.hypot(start[i0] - c0, start[i1] - c1)
        r1 = math.hypot(end[i0] - c0, end[i1] - c1)
        if max(r0, r1) < MIN_ARC_RADIUS:
            log.warning("%s:%d: arc radius %.3g below %g: run as a straight line", cmd.file, cmd.line,
                        max(r0, r1), MIN_ARC_RADIUS)
            return None
        th0 = math.atan2(start[i1] - c1, start[i0] - c0)
        th1 = math.atan2(end[i1] - c1, end[i0] - c0)
        two_pi = 2.0 * math.pi
        if cmd.turns > 0:
            sweep = (th1 - th0) % two_pi
            if sweep <= 1e-12:
                sweep += two_pi
            sweep += two_pi * (cmd.turns - 1)
        else:
            sweep = -((th0 - th1) % two_pi)
            if sweep >= -1e-12:
                sweep -= two_pi
            sweep -= two_pi * (-cmd.turns - 1)
        arc_len = abs(sweep) * 0.5 * (r0 + r1)
        travel2 = [(end[i] - start[i]) ** 2 for i in range(self._n)]
        travel2[i0] = travel2[i1] = 0.5 * arc_len * arc_len
        length = self._length(travel2)
        if length <= MIN_LENGTH:
            return None
        arc = Arc(tuple(start), tuple(end), i0, i1, c0, c1, sweep, length)
        checked = (i0, i1)
        if turned:
            arc = TurnedArc(arc, ix, iy, cmd.rotation, *outer)
            checked = (i0, i1, ix, iy)
        if any(self._soft[i] != (None, None) for i in checked):
            # the arc's extremes in its plane lie where its angle passes a multiple of 90 degrees (also
            # the turned arc's in X and Y: they are the turned-back frame's in-plane axis, scaled)
            lo, hi = sorted((th0, th0 + sweep))
            k = math.ceil(lo / (0.5 * math.pi))
            while k * 0.5 * math.pi < hi:
                self._check_soft(cmd, arc.pos((k * 0.5 * math.pi - th0) / sweep * length))
                k += 1
        return arc
