"""The planner: canonical commands in, one setpoint per cycle out.

Design (see docs/planner.md for the whole story):

* Each move becomes a piece of geometry with a path parameter ``s`` (``planner.geometry``). From the
  bounds on ``dq/ds``, ``d2q/ds2`` and ``d3q/ds3`` each piece gets a speed cap and an acceleration
  and jerk limit along ``s`` that keep every axis inside its own limits, tangential and centripetal
  terms budgeted together.
* Corners between lines in G64 are replaced by curvature-continuous blends inside the tolerance P,
  and joins with arcs by curvature-continuous transitions (quintic Hermite) inside P. Every other
  junction gets a speed cap from the step it makes in axis velocity (tangent change) or acceleration
  (curvature change) within one cycle; a real corner caps it to zero (a stop).
* Chains of short lines in G64 P that turn by little at each vertex (CAM surfacing) are smoothed
  instead: each line becomes a quintic span through its own end points with a tangent and curvature
  shared at each vertex, within P, and spans of similar limits run as one profile (``_try_smooth``).
* Override switches (M48-M53) are queued with each move, as LinuxCNC does.
* Lookahead: each queued segment keeps ``vb``, the fastest speed at its end from which everything
  queued behind it can still be travelled and stopped at the end of the queue. It is maintained
  incrementally on every append with closed forms (``planner.kinematics``), so feeding is O(1)
  amortised and the end of the queue is always a place the machine can stop.
* Solve once, step many: a segment's 1-D profile (ruckig, one degree of freedom, position interface,
  zero acceleration at both ends) is computed when the segment starts; every cycle then samples it.
  A profile that would overshoot the segment end is rejected (``position_extrema``) and the end speed
  lowered; ruckig's intermediate waypoints are never used.
* Online control (override, hold, abort, quick stop) re-solves the running segment from its current
  position, velocity and acceleration, so the stream stays continuous.

Not thread-safe: the cycle loop owns the planner (feed and pull from the same thread or under a lock).
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Iterable, Iterator, Sequence

from ruckig import InputParameter, Ruckig

from gcode_canon import commands as C
from planner.blending import BlendingMixin
from planner.controls import ControlsMixin
from planner.css import SurfaceSpeed
from planner.limits import LimitsMixin
from planner.lookahead import LookaheadMixin
from planner.machine import DEMO_MACHINE, MachineLimits
from planner.merging import MergingMixin, _Run
from planner.moves import MovesMixin
from planner.profiles import ProfilesMixin
from planner.segments import (
    CENTRIPETAL_ACC,
    CONSUMED_TYPES,
    JERK_CENTRIPETAL,
    JERK_CONTINUOUS,
    JERK_CROSS,
    LOOP_CAP,
    OVR_ADAPTIVE,
    OVR_DEFAULT,
    OVR_FEED,
    OVR_FEED_STOP,
    WAIT_TYPES,
    PlannerError,
    Seg,
    SyncItem,
    _Active,
    _finite,
)
from planner.setpoints import Setpoint, new_setpoint
from planner.smoothing import SmoothingMixin
from planner.spindle_sync import SpindleSyncMixin

log = logging.getLogger(__name__)


class Planner(MovesMixin, LookaheadMixin, LimitsMixin, MergingMixin, BlendingMixin, SmoothingMixin,
              ProfilesMixin, SpindleSyncMixin, ControlsMixin):
    """Canonical commands in (:meth:`feed`), one :class:`Setpoint` per cycle out (:meth:`next_setpoint`).

    ``start`` is the position at rest when planning begins (machine zero by default), one value per
    configured axis. With ``auto_release`` (previews), waits are released at once. ``waits``: sync
    commands beyond :data:`WAIT_TYPES` that the machine completes before the motion goes on (M3/M4 on a
    machine with an at-speed signal, M19 with an oriented signal): the stream stays at rest there until
    :meth:`release`, as at an M66.
    """

    def __init__(self, machine: MachineLimits = DEMO_MACHINE, start: Sequence[float] | None = None,
                 auto_release: bool = False, waits: tuple[type[C.Canon], ...] = ()) -> None:
        self.machine = machine
        self.T = machine.cycle_s
        self.auto_release = auto_release
        self._wait_types = WAIT_TYPES + tuple(waits)
        n = len(machine.axes)
        self._n = n
        self._pose_index = machine.pose_index
        self._machine_index = {p: i for i, p in enumerate(self._pose_index)}
        self._absent = [p for p in range(9) if p not in self._machine_index]  # pose axes not here
        self._V = [a.max_velocity for a in machine.axes]
        self._A = [a.max_acceleration for a in machine.axes]
        self._J = [a.max_jerk for a in machine.axes]
        self._QS = [a.quick_stop for a in machine.axes]
        # quick stop: how much each axis may exceed its acceleration (and, in proportion, its jerk)
        self._QR = [max(1.0, a.quick_stop / a.max_acceleration) for a in machine.axes]
        # per-axis budgets of _path_limits, computed once
        self._JC = [JERK_CONTINUOUS * j for j in self._J]
        self._CA = [CENTRIPETAL_ACC * a for a in self._A]
        self._JCENT = [JERK_CENTRIPETAL * j for j in self._JC]
        self._JCROSS = [JERK_CROSS * j / 3.0 for j in self._JC]
        self._soft = [(a.min_position, a.max_position) for a in machine.axes]
        self._has_soft = any(lim != (None, None) for lim in self._soft)
        groups = []
        for names in ("xyz", "uvw", "abc"):
            g = [i for i, a in enumerate(machine.axes) if a.name in names]
            if g:
                groups.append(g)
        self._groups = groups
        self._linear = [i for i, a in enumerate(machine.axes) if not a.rotary] or list(range(n))
        # the planes a run of lines may be merged into an arc in: pairs of X Y Z (planner.merging)
        xyz = [i for i, a in enumerate(machine.axes) if a.name in "xyz" and not a.rotary]
        self._arc_planes = list(itertools.combinations(xyz, 2))
        start_pos = [0.0] * n if start is None else [float(x) for x in start]
        if len(start_pos) != n:
            raise PlannerError(f"start position needs {n} values, got {len(start_pos)}")
        # interpretation state
        self._end = list(start_pos)  # where the queued motion ends
        self._pose = [0.0] * 9  # last commanded pose, to catch moves of axes the machine lacks
        for i, p in enumerate(self._pose_index):
            self._pose[p] = start_pos[i]
        self._feed_rate = 0.0
        self._feed_mode = C.FeedMode.UNITS_PER_MINUTE
        self._mode = C.MotionControlMode.CONTINUOUS
        self._tolerance = 0.0
        self._naive = 0.0  # G64 Q
        self._run: _Run | None = None  # lines being merged, not yet queued (planner.merging)
        self._exact_next = False
        self._spindle_rpm = 0.0
        self._spindle_dir = C.SpindleDirection.CW
        xs = [i for i, a in enumerate(machine.axes) if a.name == "x"]
        self._css = SurfaceSpeed(xs[0] if xs else None)  # G96: rpm from the X radius (planner.css)
        self._sync_pitch: float | None = None  # spindle-synchronized feed (G33, G33.1, G76): per rev
        self._pending: list[C.Canon] = []  # ride on the start of the next motion
        # direction and length of the last line fed (a hint for where a smoothed chain may start)
        self._last_chord: tuple[tuple[float, ...], float] | None = None
        self._smooth_pause = 0  # vertices to blend before trying to smooth again (after a failed chain)
        self._immediate: list[C.Canon] = []  # ride on the next setpoint emitted
        self._flushed = False
        # queue: a list with a head index (cheap pops at the front, indexing near the tail)
        self._q: list[Seg | SyncItem] = []
        self._h = 0
        # execution state
        self._k = 0  # cycles pulled so far; the setpoint of pull k has t = k * T
        self._rest = list(start_pos)
        self._v_end = 0.0  # path speed where the running profile ends
        self._free_t = 0.0  # earliest start of the next queue item
        self._active: _Active | None = None
        self._override = 1.0
        self._adaptive = 1.0  # the adaptive feed input, 0 .. 1 (M52)
        self._feed_stop = False  # the feed stop input (M53)
        self._ovr = OVR_DEFAULT  # switches M48-M53 give the moves fed from now on
        self._hold = False
        self._abort = False
        self._quick = False
        self.waiting_for: C.Canon | None = None
        self._otg = Ruckig(1)
        self._inp = InputParameter(1)
        self._last_pos = list(start_pos)
        self._rest_emitted = True
        self.stats = {"segments": 0, "solves": 0, "retries": 0, "blends": 0}
        self._started = 0  # stats["segments"] when the last started segment was queued

    # --- state ------------------------------------------------------------------------------------

    @property
    def is_idle(self) -> bool:
        """Nothing running, nothing queued, nothing waiting: the machine is at rest."""
        return (self._active is None and self._h >= len(self._q) and self.waiting_for is None
                and self._run is None
                and not self._immediate and self._free_t <= self._k * self.T + 1e-12)

    @property
    def queue_length(self) -> int:
        return len(self._q) - self._h

    @property
    def queued_moves(self) -> int:
        """Programmed moves fed and not yet started (queued, or being merged): how far ahead the
        input is, whatever the queue's items hold (a smoothed chain or a merged line holds many)."""
        return self.stats["segments"] - self._started

    @property
    def position(self) -> tuple[float, ...]:
        """Where the last setpoint was (or the rest position)."""
        return tuple(self._last_pos)

    @property
    def feed_override(self) -> float:
        return self._override

    @property
    def holding(self) -> bool:
        return self._hold

    @property
    def adaptive_feed(self) -> float:
        return self._adaptive

    @property
    def feed_stop(self) -> bool:
        return self._feed_stop

    @property
    def feed_override_enabled(self) -> bool:
        """Whether the feed override acts now: the running move's switch (M48-M50), or when at rest
        the one the next fed move gets (LinuxCNC reports ``enables_queued`` the same way)."""
        return bool(self._ovr_now() & OVR_FEED)

    # --- feeding ----------------------------------------------------------------------------------

    def feed_many(self, commands: Iterable[C.Canon]) -> None:
        for cmd in commands:
            self.feed(cmd)

    def feed(self, cmd: C.Canon) -> None:
        """Queue one canonical command (raises :class:`PlannerError` naming its file and line)."""
        _finite(cmd)
        self._css.intake(cmd)
        self._flushed = False
        if isinstance(cmd, C.StraightTraverse | C.StraightFeed | C.ArcFeed):
            self._motion(cmd)
        elif isinstance(cmd, C.Probe):
            self._sync(cmd, queue_item=False)
            self._pending.append(cmd)  # rides on the first cycle of the probing move
            self._motion(cmd)
            self._close_tail()
            self._q.append(SyncItem(cmd, self._pending, emit=False))
            self._pending = []
        elif isinstance(cmd, C.RigidTap | C.SpindleSync | C.SpindleSyncStop):
            self._spindle_sync(cmd)
        elif isinstance(cmd, C.SetFeedRate):
            if cmd.rate < 0:
                raise PlannerError(f"feed rate must be >= 0, got {cmd.rate:g}", cmd.file, cmd.line)
            self._feed_rate = cmd.rate
        elif isinstance(cmd, C.SetFeedMode):
            self._feed_mode = cmd.mode
        elif isinstance(cmd, C.SetMotionControlMode):
            if cmd.tolerance < 0:
                raise PlannerError(f"G64 P must be >= 0, got {cmd.tolerance:g}", cmd.file, cmd.line)
            if not (cmd.naive_cam_tolerance >= 0):
                raise PlannerError(f"G64 Q must be >= 0, got {cmd.naive_cam_tolerance:g}", cmd.file, cmd.line)
            self._mode, self._tolerance = cmd.mode, cmd.tolerance
            self._naive = cmd.naive_cam_tolerance
        elif isinstance(cmd, C.ExactStopBlock):
            self._exact_next = True
        elif isinstance(cmd, C.SetOverrides):
            self._set_switches(cmd)
            self._pending.append(cmd)  # passed on as well: the spindle override switch is the drive's
        elif isinstance(cmd, CONSUMED_TYPES):
            pass
        elif isinstance(cmd, C.DigitalOutput | C.AnalogOutput) and not cmd.synced:
            self._immediate.append(cmd)
        elif cmd.SYNC:
            if isinstance(cmd, C.Dwell) and cmd.seconds < 0:
                raise PlannerError(f"dwell must be >= 0 s, got {cmd.seconds:g}", cmd.file, cmd.line)
            if isinstance(cmd, C.SpindleOn):
                self._spindle_rpm = abs(cmd.rpm)
                self._spindle_dir = cmd.direction
            elif isinstance(cmd, C.SpindleOff | C.SpindleOrient):
                self._spindle_rpm = 0.0
            if isinstance(cmd, C.SpindleOrient):
                self._check_orient(cmd)
            self._sync(cmd)
        else:
            if isinstance(cmd, C.SetSpindleSpeed):
                self._spindle_rpm = abs(cmd.rpm)
            self._pending.append(cmd)

    def _set_switches(self, cmd: C.SetOverrides) -> None:
        """M48-M53: the switches the moves fed after this obey (None leaves one as it is)."""
        for flag, on in ((OVR_FEED, cmd.feed), (OVR_ADAPTIVE, cmd.adaptive_feed),
                         (OVR_FEED_STOP, cmd.feed_hold)):
            if on is not None:
                self._ovr = (self._ovr | flag) if on else (self._ovr & ~flag)

    @staticmethod
    def _check_orient(cmd: C.SpindleOrient) -> None:
        if not math.isfinite(cmd.angle):
            raise PlannerError(f"spindle orientation angle must be finite, got {cmd.angle:g}", cmd.file,
                               cmd.line)
        if cmd.direction not in (0, 1, 2):
            raise PlannerError(f"spindle orientation direction must be 0, 1 or 2, got {cmd.direction}",
                               cmd.file, cmd.line)
        if not (math.isfinite(cmd.timeout) and cmd.timeout >= 0):
            raise PlannerError(f"spindle orientation timeout must be >= 0 s, got {cmd.timeout:g}",
                               cmd.file, cmd.line)

    def flush(self) -> None:
        """The input is over for now: events still waiting for a motion ride on the next setpoint."""
        self._close_tail()
        self._flushed = True

    def _sync(self, cmd: C.Canon, queue_item: bool = True) -> None:
        self._close_tail()
        if queue_item:
            self._q.append(SyncItem(cmd, self._pending))
            self._pending = []

    def _close_tail(self) -> None:
        """The last queued segment must end at rest (already so for the backward pass: mark it)."""
        self._emit_run()
        self._finish_chain()
        if self._h < len(self._q):
            last = self._q[-1]
            if isinstance(last, Seg):
                last.stop = True
                last.jgeom = last.jcap = 0.0

    # --- the cycle ----------------------------------------------------------------------------------

    def _finish_active(self) -> None:
        act = self._active
        assert act is not None
        self._active = None
        self._rest_emitted = False
        seg = act.seg
        if act.s_end < seg.piece.length - 1e-12:
            seg.s0 = act.s_end  # stopped inside the segment: the rest goes back to the queue
            self._h -= 1
            if self._h < 0:
                self._q.insert(0, seg)
                self._h = 0
            else:
                self._q[self._h] = seg
            self._rest = seg.piece.pos(act.s_end)
            self._v_end = 0.0
        else:
            self._rest = list(seg.piece.end)
            self._v_end = act.v1
        if act.v1 > 0.0:
            self._free_t = act.t_end
        else:
            self._free_t = math.ceil(act.t_end / self.T - 1e-9) * self.T
            self._finish_abort_if_at_rest()

    def _pop(self) -> Seg | SyncItem:
        item = self._q[self._h]
        self._q[self._h] = None  # type: ignore[call-overload]
        self._h += 1
        if self._h > 4096 and self._h * 2 > len(self._q):
            del self._q[: self._h]
            self._h = 0
        return item

    @staticmethod
    def _sample(act: _Active, t: float) -> tuple[list[float], C.Canon]:
        """Where the running profile puts the axes at ``t``, and the programmed move there."""
        p = act.traj.at_time(t - act.t0)[0][0] + act.s_off
        if p > act.s_end:
            p = act.s_end
        pos, src = act.seg.piece.sample(p)
        return pos, (act.seg.cmd if src is None else src)

    def next_setpoint(self) -> Setpoint | None:
        """The setpoint for the next cycle, or None when idle at rest with nothing to say."""
        self._k += 1
        t = self._k * self.T
        if self._run is not None and len(self._q) - self._h <= 1:
            self._emit_run()  # the queue runs short: the lines merged so far go in now
        act = self._active
        if act is not None and not act.first and not self._immediate and t < act.t_end - 1e-12:
            # the common cycle: inside a running profile, nothing to emit (the loop below, shortened)
            pos, src = self._sample(act, t)
            self._last_pos = pos
            self._rest_emitted = False
            pos = tuple(pos)
            events = self._css.emit(t, pos, []) if self._css.active else ()
            return new_setpoint(t, pos, src.file, src.line, tuple(events))
        events: list[C.Canon] = []
        if self._immediate:
            events += self._immediate
            self._immediate = []
        src: C.Canon | None = None
        pos: list[float] | None = None
        moving = False
        for _ in range(LOOP_CAP):
            act = self._active
            if act is not None:
                if t < act.t_end - 1e-12:
                    pos, src = self._sample(act, t)
                    moving = True
                    if act.first:
                        act.first = False
                        if act.seg.events:
                            events += act.seg.events
                            act.seg.events = []
                    break
                if act.first and act.seg.events:
                    # a piece passed between two samples (shorter than a cycle's travel): its events
                    # ride on the first setpoint after it, never dropped
                    events += act.seg.events
                    act.seg.events = []
                self._finish_active()
                continue
            if self.waiting_for is not None or self._free_t > t + 1e-9:
                pos = self._rest  # waiting or dwelling
                break
            if self._h >= len(self._q):
                if self._abort:
                    self._finish_abort_if_at_rest()
                if self._flushed and self._pending:
                    events += self._pending
                    self._pending = []
                if not events and self._rest_emitted:
                    return None
                pos = self._rest  # the last cycle of the motion, at rest on its end point
                break
            item = self._q[self._h]
            if isinstance(item, SyncItem):
                self._pop()
                events += item.events
                if item.emit:
                    events.append(item.cmd)
                src = item.cmd
                pos = self._rest
                self._free_t = t
                if isinstance(item.cmd, C.Dwell):
                    self._free_t = t + math.ceil(item.cmd.seconds / self.T - 1e-9) * self.T
                elif isinstance(item.cmd, self._wait_types) and not self.auto_release:
                    self.waiting_for = item.cmd
                break
            if self._stops(item.ovr) and self._v_end <= 0.0:
                if self._abort:
                    self._finish_abort_if_at_rest()
                pos = self._rest  # held at rest
                break
            seg = self._pop()
            assert isinstance(seg, Seg)
            t0 = self._free_t if self._v_end > 0.0 else max(self._free_t, t - self.T)
            self._start(seg, t0)
        else:
            raise PlannerError(f"planner loop passed {LOOP_CAP} items in one cycle at t={t:.6f} s")
        self._last_pos = pos
        self._rest_emitted = not moving
        pos = tuple(pos)
        if events or self._css.active:
            events = self._css.emit(t, pos, events)
        if src is None:
            return new_setpoint(t, pos, "", 0, tuple(events))
        return new_setpoint(t, pos, src.file, src.line, tuple(events))


def plan_all(commands: Iterable[C.Canon], machine: MachineLimits = DEMO_MACHINE,
             start: Sequence[float] | None = None, window: int = 400,
             max_cycles: int | None = None, window_moves: int = 5000) -> Iterator[Setpoint]:
    """Plan a whole program faster than real time (previews, tests, ``canon plan``).

    Commands are read lazily, keeping ``window`` items and at most ``window_moves`` programmed moves
    queued ahead (a merged line or a smoothed chain is one item holding many moves: memory stays flat
    in the program's length); waits are released at once. The stream starts at rest at ``start`` and
    ends at rest on the last point. ``max_cycles`` bounds it.
    """
    planner = Planner(machine, start, auto_release=True)
    it = iter(commands)
    exhausted = False
    cap = max_cycles if max_cycles is not None else 10**12
    for _ in range(cap):
        while not exhausted:
            queued = len(planner._q) - planner._h  # queue_length, read once per command
            if queued >= 2 and (queued >= window or planner.queued_moves >= window_moves):
                break
            try:
                cmd = next(it)
            except StopIteration:
                exhausted = True
                planner.flush()
                break
            planner.feed(cmd)
        sp = planner.next_setpoint()
        if sp is None:
            if exhausted:
                return
            continue
        yield sp
    raise PlannerError(f"plan_all: more than {cap} cycles")
