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

import dataclasses
import logging
import math
from collections.abc import Iterable, Iterator, Sequence

from ruckig import ControlInterface, InputParameter, Result, Ruckig, RuckigError, Trajectory

from gcode_canon import commands as C
from gcode_canon.errors import GCodeError
from planner.geometry import Arc, Blend, Line, Piece, Transition, deviation_of_blend
from planner.kinematics import change_distance, max_reach, min_reach
from planner.machine import DEMO_MACHINE, MachineLimits
from planner.setpoints import Setpoint

log = logging.getLogger(__name__)

# Budgets, as fractions of each axis's limits.
CENTRIPETAL_ACC = 0.5  # v^2 q'' (the rest of the acceleration is left for speed changes)
JERK_CONTINUOUS = 0.9  # the jerk of the continuous motion; the rest is for steps at junctions
JERK_CENTRIPETAL = 0.35  # v^3 q''' (of the continuous share)
JERK_CROSS = 0.15  # 3 v a q'' (of the continuous share)
JUNCTION_TANGENT = 0.05  # a velocity step dv in one cycle reads as a jerk of up to dv / T^2
JUNCTION_CURVATURE = 0.05  # an acceleration step da reads as a jerk of up to 0.75 da / T
CORNER = 1e-3  # a tangent change (in dq/ds) above this is a corner: stop there unless blended
TRANSITION_DEVIATION = 0.8  # a transition stays within this share of G64 P (its deviation is sampled)
TRANSITION_ARC = 0.5  # a transition reaches at most this many radii along an arc (about 29 degrees)
TRANSITION_SAMPLES = 32  # samples of a transition's deviation on each side of the join
MAX_OVERRIDE = 2.0
# Which online inputs a move obeys (LinuxCNC's FS/AF/FH "enables", queued with each move by M48-M53).
OVR_FEED = 1  # the feed override (M48/M49, M50 P1/P0)
OVR_ADAPTIVE = 2  # the adaptive feed input (M52 P1/P0); off by default, as in LinuxCNC
OVR_FEED_STOP = 4  # the feed stop input (M53 P1/P0)
OVR_DEFAULT = OVR_FEED | OVR_FEED_STOP
MIN_LENGTH = 1e-10  # moves shorter than this (machine units) are skipped: they take no time
MIN_ARC_RADIUS = 1e-7  # arcs of smaller radius are run as the straight line to their end
LOOP_CAP = 100_000  # pieces a single cycle may pass through before the planner gives up loudly
_TOL = 1e-9
SLACK = 1.0 - 1e-6  # the lookahead plans with segments this much shorter, so profiles are never tight

WAIT_TYPES: tuple[type[C.Canon], ...] = (C.WaitInput, C.ToolChange, C.ProgramStop, C.PalletShuttle, C.Probe)
"""Sync commands after which the stream stays at rest until :meth:`Planner.release`. The others
(dwell, spindle start/stop, spindle orient M19/G87, program end) continue at once: the machine acts on
the event riding on the rest setpoint before it takes the next one."""

CONSUMED_TYPES: tuple[type[C.Canon], ...] = (
    C.SetFeedRate, C.SetFeedMode, C.SetMotionControlMode, C.ExactStopBlock, C.SelectPlane,
    C.UseLengthUnits, C.SetG5xOffset, C.SetG92Offset, C.UseToolLengthOffset, C.Comment,
)
"""Commands that only change the planner's state; they are not passed on as events."""


class PlannerError(GCodeError):
    """A command the planner cannot execute (bad value, impossible move), or an internal failure."""


def _finite(cmd: C.Canon) -> None:
    for f in dataclasses.fields(cmd):
        value = getattr(cmd, f.name)
        if isinstance(value, float) and not math.isfinite(value):
            raise PlannerError(f"{cmd.NAME}: {f.name} is not a finite number ({value})", cmd.file, cmd.line)
        if isinstance(value, C.Pose) and not all(math.isfinite(x) for x in value):
            raise PlannerError(f"{cmd.NAME}: {f.name} has a coordinate that is not a finite number",
                               cmd.file, cmd.line)


class Seg:
    """A queued piece of motion with its limits along the path and its lookahead state."""

    __slots__ = ("a", "blend_tol", "cap", "cap_geom", "cmd", "events", "feed", "j", "jcap", "jgeom", "kind",
                 "orig_length", "ovr", "piece", "qs_a", "qs_j", "rapid", "s0", "sides", "stop", "vb")

    def __init__(self, piece: Piece, kind: str, cmd: C.Canon, feed: float, rapid: bool,
                 ovr: int = OVR_DEFAULT) -> None:
        self.piece = piece
        self.kind = kind
        self.cmd = cmd
        self.feed = feed
        self.rapid = rapid
        # The override switches in force when the move was queued (LinuxCNC queues them with each move,
        # so an M49 changes the moves after it, not the one running). ``sides``: (feed, switches) of
        # each programmed move the piece belongs to; a corner blend has two and obeys both.
        self.ovr = ovr
        self.sides: tuple[tuple[float, int], ...] = ((feed, ovr),)
        self.s0 = 0.0
        self.orig_length = piece.length
        self.events: list[C.Canon] = []
        self.stop = False  # must be at rest at the end (G61.1, G9, before a sync point)
        self.blend_tol = -1.0  # G64 P of the move (0: no limit), -1: no blend at its end
        self.jgeom = 0.0  # speed cap at the end junction from geometry (0 = stop)
        self.jcap = 0.0
        self.vb = 0.0
        self.cap = self.cap_geom = self.a = self.j = self.qs_a = self.qs_j = 0.0

    @property
    def length(self) -> float:
        return self.piece.length - self.s0


class SyncItem:
    """A sync point in the queue: motion is at rest before it; ``cmd`` rides on that rest cycle."""

    __slots__ = ("cmd", "emit", "events")

    def __init__(self, cmd: C.Canon, events: list[C.Canon], emit: bool = True) -> None:
        self.cmd = cmd
        self.events = events
        self.emit = emit


class _Active:
    """The running profile: path position ``s_off + p(t - t0)`` on ``seg``, ending at ``s_end``."""

    __slots__ = ("first", "s_end", "s_off", "seg", "t0", "t_end", "traj", "v1")

    def __init__(self, seg: Seg, t0: float, traj: Trajectory, s_off: float, s_end: float, v1: float,
                 first: bool) -> None:
        self.seg, self.t0, self.traj, self.s_off, self.s_end, self.v1 = seg, t0, traj, s_off, s_end, v1
        self.t_end = t0 + traj.duration
        self.first = first


class Planner:
    """Canonical commands in (:meth:`feed`), one :class:`Setpoint` per cycle out (:meth:`next_setpoint`).

    ``start`` is the position at rest when planning begins (machine zero by default), one value per
    configured axis. With ``auto_release`` (previews), waits are released at once.
    """

    def __init__(self, machine: MachineLimits = DEMO_MACHINE, start: Sequence[float] | None = None,
                 auto_release: bool = False) -> None:
        self.machine = machine
        self.T = machine.cycle_s
        self.auto_release = auto_release
        n = len(machine.axes)
        self._n = n
        self._pose_index = machine.pose_index
        self._machine_index = {p: i for i, p in enumerate(self._pose_index)}
        self._V = [a.max_velocity for a in machine.axes]
        self._A = [a.max_acceleration for a in machine.axes]
        self._J = [a.max_jerk for a in machine.axes]
        self._QS = [a.quick_stop for a in machine.axes]
        self._soft = [(a.min_position, a.max_position) for a in machine.axes]
        groups = []
        for names in ("xyz", "uvw", "abc"):
            g = [i for i, a in enumerate(machine.axes) if a.name in names]
            if g:
                groups.append(g)
        self._groups = groups
        self._linear = [i for i, a in enumerate(machine.axes) if not a.rotary] or list(range(n))
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
        self._exact_next = False
        self._spindle_rpm = 0.0
        self._pending: list[C.Canon] = []  # ride on the start of the next motion
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

    # --- state ------------------------------------------------------------------------------------

    @property
    def is_idle(self) -> bool:
        """Nothing running, nothing queued, nothing waiting: the machine is at rest."""
        return (self._active is None and self._h >= len(self._q) and self.waiting_for is None
                and not self._immediate and self._free_t <= self._k * self.T + 1e-12)

    @property
    def queue_length(self) -> int:
        return len(self._q) - self._h

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
        elif isinstance(cmd, C.SetFeedRate):
            if cmd.rate < 0:
                raise PlannerError(f"feed rate must be >= 0, got {cmd.rate:g}", cmd.file, cmd.line)
            self._feed_rate = cmd.rate
        elif isinstance(cmd, C.SetFeedMode):
            self._feed_mode = cmd.mode
        elif isinstance(cmd, C.SetMotionControlMode):
            if cmd.tolerance < 0:
                raise PlannerError(f"G64 P must be >= 0, got {cmd.tolerance:g}", cmd.file, cmd.line)
            self._mode, self._tolerance = cmd.mode, cmd.tolerance
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
        if self._h < len(self._q):
            last = self._q[-1]
            if isinstance(last, Seg):
                last.stop = True
                last.jgeom = last.jcap = 0.0

    # --- building segments --------------------------------------------------------------------------

    def _target(self, cmd: C.Canon, pose: C.Pose) -> list[float]:
        for p, value in enumerate(pose):
            if p not in self._machine_index and abs(value - self._pose[p]) > _TOL:
                raise PlannerError(f"{cmd.NAME} moves axis {C.AXES[p].upper()}, which this machine does "
                                   f"not have (axes: {' '.join(self.machine.names).upper()})",
                                   cmd.file, cmd.line)
        self._pose = list(pose)
        out = [pose[p] for p in self._pose_index]
        self._check_soft(cmd, out)
        return out

    def _check_soft(self, cmd: C.Canon, point: Sequence[float]) -> None:
        for i, (lo, hi) in enumerate(self._soft):
            if (lo is not None and point[i] < lo - _TOL) or (hi is not None and point[i] > hi + _TOL):
                name = self.machine.axes[i].name.upper()
                raise PlannerError(f"{cmd.NAME} to {name}{point[i]:g} is outside the soft limits "
                                   f"[{lo}, {hi}]", cmd.file, cmd.line)

    def _length(self, travel2: Sequence[float]) -> float:
        for g in self._groups:
            length = math.sqrt(sum(travel2[i] for i in g))
            if length > MIN_LENGTH:
                return length
        return 0.0

    def _feed_speed(self, cmd: C.Canon, length: float) -> float:
        if isinstance(cmd, C.StraightTraverse):
            return math.inf
        rate, mode = self._feed_rate, self._feed_mode
        if mode is C.FeedMode.INVERSE_TIME:
            if rate <= 0:
                raise PlannerError("inverse-time feed (G93) needs F > 0 on this move", cmd.file, cmd.line)
            return length * rate / 60.0
        if mode is C.FeedMode.UNITS_PER_REV:
            if rate <= 0 or self._spindle_rpm <= 0:
                raise PlannerError(f"feed per revolution (G95) needs F > 0 and a turning spindle (F{rate:g}, "
                                   f"S{self._spindle_rpm:g})", cmd.file, cmd.line)
            return rate * self._spindle_rpm / 60.0
        if rate <= 0:
            raise PlannerError("feed rate is 0: set F before a feed move", cmd.file, cmd.line)
        return rate / 60.0

    def _motion(self, cmd: C.Canon) -> None:
        start = self._end
        end = self._target(cmd, cmd.end)  # type: ignore[attr-defined]
        n = self._n
        piece: Piece | None = None
        kind = "line"
        if isinstance(cmd, C.ArcFeed):
            piece = self._arc(cmd, start, end)
            kind = "arc" if isinstance(piece, Arc) else "line"
        if piece is None:
            delta = [end[i] - start[i] for i in range(n)]
            if max(abs(x) for x in delta) <= MIN_LENGTH:
                log.debug("%s:%d: zero-length move skipped", cmd.file, cmd.line)
                self._end = end
                if self._exact_next or self._mode in (C.MotionControlMode.EXACT_STOP_MODAL,
                                                      C.MotionControlMode.EXACT_STOP):
                    self._close_tail()  # a stop asked for here is kept, even without a move
                self._exact_next = False
                return
            length = self._length([x * x for x in delta])
            if length <= MIN_LENGTH:
                length = max(abs(x) for x in delta)
            piece = Line(tuple(start), tuple(end), length)
        feed = self._feed_speed(cmd, piece.length)
        seg = Seg(piece, kind, cmd, feed, isinstance(cmd, C.StraightTraverse), self._ovr)
        # the corner at a move's end is blended by the mode the move was programmed in (LinuxCNC)
        seg.blend_tol = self._tolerance if self._mode is C.MotionControlMode.CONTINUOUS else -1.0
        self._limits(seg)
        seg.events, self._pending = self._pending, []
        exact = self._exact_next or isinstance(cmd, C.Probe) or self._mode in (
            C.MotionControlMode.EXACT_STOP_MODAL, C.MotionControlMode.EXACT_STOP)
        self._exact_next = False
        self._end = end
        self.stats["segments"] += 1
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
        c0, c1 = cmd.center[p0], cmd.center[p1]
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
        if any(lim != (None, None) for lim in (self._soft[i0], self._soft[i1])):
            # the arc's extremes in its plane lie where its angle passes a multiple of 90 degrees
            lo, hi = sorted((th0, th0 + sweep))
            k = math.ceil(lo / (0.5 * math.pi))
            while k * 0.5 * math.pi < hi:
                self._check_soft(cmd, arc.pos((k * 0.5 * math.pi - th0) / sweep * length))
                k += 1
        return arc

    def _limits(self, seg: Seg) -> None:
        """Speed cap and path acceleration/jerk limits that keep every axis inside its limits."""
        p = seg.piece
        d1, d2, d3 = p.d1_max, p.d2_max, p.d3_max
        cap = math.inf
        for i in range(self._n):
            jc = JERK_CONTINUOUS * self._J[i]
            if d1[i] > 0.0:
                cap = min(cap, self._V[i] / d1[i])
            if d2[i] > 0.0:
                cap = min(cap, math.sqrt(CENTRIPETAL_ACC * self._A[i] / d2[i]))
            if d3[i] > 0.0:
                cap = min(cap, (JERK_CENTRIPETAL * jc / d3[i]) ** (1.0 / 3.0))
        seg.cap_geom = cap
        vb = min(cap, MAX_OVERRIDE * seg.feed)
        a = j = qs = math.inf
        for i in range(self._n):
            if d1[i] > 0.0:
                a = min(a, (self._A[i] - vb * vb * d2[i]) / d1[i])
                qs = min(qs, self._QS[i] / d1[i])
            if d2[i] > 0.0 and vb > 0.0:
                a = min(a, JERK_CROSS * JERK_CONTINUOUS * self._J[i] / (3.0 * vb * d2[i]))
        for i in range(self._n):
            if d1[i] > 0.0:
                jc = JERK_CONTINUOUS * self._J[i]
                j = min(j, (jc - vb ** 3 * d3[i] - 3.0 * vb * a * d2[i]) / d1[i])
        if not (a > 0.0 and j > 0.0 and cap > 0.0 and math.isfinite(a) and math.isfinite(j)):
            raise PlannerError(f"cannot derive path limits for this move (a={a:g}, j={j:g}, v={cap:g})",
                               seg.cmd.file, seg.cmd.line)
        seg.a, seg.j = a, j
        seg.qs_a = max(qs, a)
        seg.qs_j = j * seg.qs_a / a
        self._set_cap(seg)

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

    # --- blending -----------------------------------------------------------------------------------

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
        tolerance = prev.blend_tol
        if tolerance < 0.0:
            return False
        w1, w2 = prev.piece.d1_end, new.piece.d1_start
        dw = max(abs(w2[i] - w1[i]) for i in range(self._n))
        if dw <= 1e-12:
            return False  # collinear: no corner
        d = min(0.5 * prev.orig_length, prev.piece.length, 0.5 * new.piece.length)
        unit = deviation_of_blend(w1, w2, 1.0, self._linear)
        if unit <= 0.0:
            unit = deviation_of_blend(w1, w2, 1.0, range(self._n))
        if tolerance > 0.0:
            d = min(d, tolerance / unit)
        is_head = len(self._q) - 1 == self._h
        if is_head and self._active is not None and self._v_end > 0.0:
            d = min(d, prev.piece.length - change_distance(self._v_end, 0.0, prev.a, prev.j) - 1e-9)
        if d <= 1e-9:
            return False
        keep = prev.piece.length - d
        if 0.0 < keep < 0.25 * d and prev.piece.length <= 0.6 * new.piece.length and (
                tolerance <= 0.0 or prev.piece.length <= tolerance / unit):
            d = prev.piece.length  # no sliver of line between two blends: one piece less to plan
        corner = prev.piece.end
        n = self._n
        blend = Blend(corner, w1, w2, d)
        bseg = Seg(blend, "blend", new.cmd, min(prev.feed, new.feed), prev.rapid and new.rapid,
                   prev.ovr | new.ovr)
        bseg.sides = prev.sides + new.sides
        self._limits(bseg)
        orig_piece, orig_events = new.piece, new.events
        new.piece = Line(blend.end, orig_piece.end, orig_piece.length - d)  # same direction: same limits
        bseg.events, new.events = list(orig_events), []
        # replace prev by its trimmed part (or drop it when the blend takes it all)
        index = len(self._q) - 1
        self._q.pop()
        keep = prev.piece.length - d
        items: list[Seg] = []
        if keep > MIN_LENGTH:
            trimmed = Seg(Line(prev.piece.start, tuple(corner[i] - d * w1[i] for i in range(n)), keep),
                          "line", prev.cmd, prev.feed, prev.rapid, prev.ovr)
            trimmed.orig_length, trimmed.blend_tol = prev.orig_length, prev.blend_tol
            self._copy_limits(trimmed, prev)
            trimmed.events = prev.events
            items.append(trimmed)
        else:
            bseg.events = prev.events + bseg.events
        items += [bseg, new]
        saved = self._save_tail_links(index)
        for it in items:
            self._link(it)
        changes = self._backward(index)
        if not self._head_feasible(changes):
            del self._q[index:]
            self._restore_tail_links(saved)
            self._q.append(prev)
            new.piece, new.events = orig_piece, orig_events
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
        tolerance = prev.blend_tol
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
        if self._allowed(new.blend_tol) < self._allowed(tolerance):
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
            trimmed.sides = prev.sides
            self._limits(trimmed)
            trimmed.events = prev.events
            items.append(trimmed)
        else:
            tseg.events = prev.events + tseg.events
        items += [tseg, new]
        saved = self._save_tail_links(index)
        for it in items:
            self._link(it)
        changes = self._backward(index)
        if not self._head_feasible(changes):
            del self._q[index:]
            self._restore_tail_links(saved)
            self._q.append(prev)
            new.piece, new.events = orig_piece, orig_events
            self._set_limits(new, orig_limits)
            return False
        for seg, vb in changes:
            seg.vb = vb
        self.stats["blends"] += 1
        return True

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

    # --- the lookahead ------------------------------------------------------------------------------

    def _link(self, seg: Seg) -> None:
        """Append ``seg``, linking it to the queued segment before it."""
        if self._h < len(self._q):
            prev = self._q[-1]
            if isinstance(prev, Seg):
                prev.jgeom = self._junction(prev, seg)
                prev.jcap = min(prev.jgeom, prev.cap, seg.cap)
        seg.vb = 0.0
        seg.jcap = seg.jgeom = 0.0
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

    # --- profiles -----------------------------------------------------------------------------------

    def _solve(self, v0: float, a0: float, length: float, v1: float, vmax: float, a: float, j: float,
               ) -> Trajectory | None:
        """1-D profile from (0, v0, a0) to (length, v1, 0); None if it fails or leaves [0, length]."""
        inp = self._inp
        inp.control_interface = ControlInterface.Position
        inp.current_position = [0.0]
        inp.current_velocity = [v0]
        inp.current_acceleration = [a0]
        inp.target_position = [length]
        inp.target_velocity = [v1]
        inp.target_acceleration = [0.0]
        inp.max_velocity = [max(vmax, v1, 1e-9)]
        inp.max_acceleration = [a]
        inp.max_jerk = [j]
        traj = self._calculate(inp)
        if traj is None:
            return None
        ext = traj.position_extrema[0]
        slack = 1e-9 + 1e-9 * length
        if ext.max > length + slack or ext.min < -slack:
            return None
        if v0 > inp.max_velocity[0] * (1.0 + 1e-9):
            # Starting above the velocity limit, ruckig brakes first, and its position_extrema do not
            # cover that phase (seen: a profile that passes its target and comes back, extrema saying
            # otherwise). Check what the cycle loop will sample.
            h = 0.5 * self.T
            steps = min(int(traj.duration / h) + 2, 100_000)
            for k in range(steps):
                pos = traj.at_time(min(k * h, traj.duration))[0][0]
                if pos > length + slack or pos < -slack:
                    return None
        return traj

    def _solve_stop(self, v0: float, a0: float, a: float, j: float) -> Trajectory | None:
        inp = self._inp
        inp.control_interface = ControlInterface.Velocity
        inp.current_position = [0.0]
        inp.current_velocity = [v0]
        inp.current_acceleration = [a0]
        inp.target_velocity = [0.0]
        inp.target_acceleration = [0.0]
        inp.max_velocity = [max(abs(v0), 1e-9)]
        inp.max_acceleration = [a]
        inp.max_jerk = [j]
        try:
            return self._calculate(inp)
        finally:
            inp.control_interface = ControlInterface.Position

    def _calculate(self, inp: InputParameter) -> Trajectory | None:
        """One ruckig solve; None when ruckig refuses or fails (callers then lower their target)."""
        traj = Trajectory(1)
        self.stats["solves"] += 1
        try:
            result = self._otg.calculate(inp, traj)
        except (RuntimeError, RuckigError):  # RuckigError is no RuntimeError: both mean "no profile"
            return None
        if result not in (Result.Working, Result.Finished):
            return None
        return traj

    def _stop_limits(self, seg: Seg) -> tuple[float, float]:
        return (seg.qs_a, seg.qs_j) if self._quick else (seg.a, seg.j)

    def _stops(self, ovr: int) -> bool:
        """Whether a move with switches ``ovr`` must stop now: hold, abort and quick stop always; the
        feed override at 0, the adaptive feed at 0 and the feed stop input only where switched on."""
        return (self._hold or self._abort or self._quick
                or (ovr & OVR_FEED != 0 and self._override <= 0.0)
                or (ovr & OVR_ADAPTIVE != 0 and self._adaptive <= 0.0)
                or (ovr & OVR_FEED_STOP != 0 and self._feed_stop))

    def _ovr_now(self) -> int:
        """The switches of the running move, or at rest those of the next queued move (else the next
        fed one)."""
        if self._active is not None:
            return self._active.seg.ovr
        for i in range(self._h, len(self._q)):
            item = self._q[i]
            if isinstance(item, Seg):
                return item.ovr
        return self._ovr

    @property
    def _stopping(self) -> bool:
        return self._stops(self._ovr_now())

    def _start(self, seg: Seg, t0: float) -> None:
        """Commit ``seg``: solve its profile from the current end speed."""
        self._start_profile(seg, t0)
        assert self._active is not None
        self._v_end = self._active.v1

    def _start_profile(self, seg: Seg, t0: float) -> None:
        v0 = self._v_end
        length = seg.length
        a, j = seg.a, seg.j
        if self._stops(seg.ovr):
            a, j = self._stop_limits(seg)
            if change_distance(v0, 0.0, a, j) <= length:
                traj = self._solve_stop(v0, 0.0, a, j)
                if traj is not None:
                    stop = min(traj.at_time(traj.duration)[0][0], length)
                    self._active = _Active(seg, t0, traj, seg.s0, seg.s0 + stop, 0.0, True)
                    return
            target = lo = min_reach(v0, length, a, j)
        else:
            target = min(seg.vb, max_reach(v0, length * SLACK, a, j))
            lo = target
            if target < v0 and change_distance(v0, target, a, j) > length:
                lo = target = min_reach(v0, length, a, j)  # after an override cut: brake all the way
        for _attempt in range(60):
            traj = self._solve(v0, 0.0, length, target, seg.cap, a, j)
            if traj is None:
                traj = self._solve(v0, 0.0, length, target, max(seg.cap, v0), a, j)
            if traj is not None:
                self._active = _Active(seg, t0, traj, seg.s0, seg.piece.length, target, True)
                return
            if self.stats["retries"] < 20:
                log.debug("%s:%d: profile %g -> %g over %g (cap %g) failed; lowering", seg.cmd.file,
                          seg.cmd.line, v0, target, length, seg.cap)
            self.stats["retries"] += 1
            if _attempt == 0:
                lo = min(lo, min_reach(v0, length, a, j))
            if target <= lo * (1 + 1e-12):
                break
            target = lo + 0.5 * (target - lo) if target - lo > 1e-9 else lo
        for eps in (1e-9, 1e-7, 1e-5, 1e-3):  # at the very edge of feasibility: a hair faster
            target = min(lo + eps * (v0 + lo + 1e-9), max(v0, lo))
            traj = self._solve(v0, 0.0, length, target, max(seg.cap, v0), a, j)
            if traj is not None:
                self._active = _Active(seg, t0, traj, seg.s0, seg.piece.length, target, True)
                return
        raise PlannerError(f"no feasible profile for this move (length {length:g}, from speed {v0:g} to "
                           f"{target:g})", seg.cmd.file, seg.cmd.line)

    def _replan(self) -> None:
        """Re-solve the running profile from the current state (override, hold, resume, stops)."""
        act = self._active
        if act is None:
            return
        t_now = self._k * self.T
        tau = min(max(t_now - act.t0, 0.0), act.traj.duration)
        p, v, acc = (x[0] for x in act.traj.at_time(tau))
        s_cur = min(act.s_off + p, act.seg.piece.length)
        seg = act.seg
        remaining = seg.piece.length - s_cur
        self._set_cap(seg)
        head = self._q[self._h] if self._h < len(self._q) else None
        if isinstance(head, Seg) and not seg.stop:
            vb = min(seg.jgeom, seg.cap, head.cap, max_reach(head.vb, head.length, head.a, head.j))
        else:
            vb = 0.0
        stopping = self._stops(seg.ovr)
        if stopping:
            a, j = self._stop_limits(seg)
            traj = self._solve_stop(v, acc, a, j)
            if traj is not None:
                dist = traj.at_time(traj.duration)[0][0]
                if dist <= remaining + 1e-12:
                    self._active = _Active(seg, t_now, traj, s_cur, s_cur + dist, 0.0, act.first)
                    self._v_end = 0.0
                    return
            candidates = [min_reach(max(v, 0.0), remaining, a, j) + k * 0.1 * act.v1 for k in range(11)]
        else:
            a, j = seg.a, seg.j
            top = min(vb, max_reach(max(v, 0.0), remaining, a, j))
            candidates = [top * (1.0 - 0.1 * k) for k in range(11)]
        for target in candidates:
            if target < 0.0 or (stopping and target > act.v1):
                continue
            traj = self._solve(v, acc, remaining, target, seg.cap, a, j)
            if traj is not None:
                self._active = _Active(seg, t_now, traj, s_cur, seg.piece.length, target, act.first)
                self._v_end = target
                return
        log.debug("replan found nothing better; the running profile continues")

    # --- online control -----------------------------------------------------------------------------

    def set_feed_override(self, factor: float) -> None:
        """Feed override, 0 to 2 (0 stops on the path as a hold does); takes effect smoothly.

        It scales the feed of G1/G2/G3 moves (rapids keep their speed, as in LinuxCNC, where they
        follow a separate rapid override this planner does not have; 0 stops them too). Moves queued
        while the override is switched off (M49, M50 P0) run at their programmed feed and do not
        stop at 0; the switch is the one in force when the move was fed, as LinuxCNC queues it.
        """
        if not math.isfinite(factor):
            raise PlannerError(f"feed override must be a number, got {factor!r}")
        factor = min(max(factor, 0.0), MAX_OVERRIDE)
        was_stopping = self._stopping
        self._override = factor
        if factor > 0.0:
            self._recompute_all()
        if self._stopping != was_stopping or factor > 0.0:
            self._replan()

    def set_adaptive_feed(self, factor: float) -> None:
        """Adaptive feed input, 0 to 1 (LinuxCNC's ``motion.adaptive-feed``): scales every move, rapids
        included, queued while M52 P1 is in force, on top of the feed override; 0 stops them on the
        path. Each change re-plans the queue (O(queue length)): feed it at a modest rate."""
        if not math.isfinite(factor):
            raise PlannerError(f"adaptive feed must be a number, got {factor!r}")
        factor = min(max(factor, 0.0), 1.0)
        if factor == self._adaptive:
            return
        was_stopping = self._stopping
        self._adaptive = factor
        if factor > 0.0:
            self._recompute_all()
        if self._stopping != was_stopping or factor > 0.0:
            self._replan()

    def set_feed_stop(self, on: bool) -> None:
        """Feed stop input (LinuxCNC's ``motion.feed-hold``): while on, moves queued with M53 P1 in
        force (the default) stop on the path as in a hold; M53 P0 moves ignore it. :meth:`hold` is the
        operator's pause and is not switched by M53."""
        on = bool(on)
        if on == self._feed_stop:
            return
        was_stopping = self._stopping
        self._feed_stop = on
        if self._stopping != was_stopping:
            self._replan()

    def hold(self) -> None:
        """Feed hold: a jerk-limited stop on the path; :meth:`resume` continues from there."""
        if not self._hold:
            self._hold = True
            self._replan()

    def resume(self) -> None:
        if self._hold:
            self._hold = False
            if not self._stopping:
                self._replan()

    def abort(self) -> None:
        """Jerk-limited stop on the path, then the queue is dropped."""
        self._abort = True
        self._replan()
        self._finish_abort_if_at_rest()

    def quick_stop(self) -> None:
        """Stop at each axis's quick-stop deceleration, then drop the queue as :meth:`abort` does."""
        self._abort = True
        self._quick = True
        self._replan()
        self._finish_abort_if_at_rest()

    def release(self) -> None:
        """Continue after the sync point in :attr:`waiting_for` (input read, tool changed, M0 ...)."""
        self.waiting_for = None
        self._free_t = max(self._free_t, self._k * self.T)

    def _finish_abort_if_at_rest(self) -> None:
        if self._active is None and self._abort:
            self._q.clear()
            self._h = 0
            self._pending = []
            self._abort = self._quick = self._hold = False
            self.waiting_for = None
            self._end = list(self._rest)
            self._v_end = 0.0
            for i, p in enumerate(self._pose_index):
                self._pose[p] = self._rest[i]

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

    def next_setpoint(self) -> Setpoint | None:
        """The setpoint for the next cycle, or None when idle at rest with nothing to say."""
        self._k += 1
        t = self._k * self.T
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
                    p = act.traj.at_time(t - act.t0)[0][0] + act.s_off
                    if p > act.s_end:
                        p = act.s_end
                    pos = act.seg.piece.pos(p)
                    src = act.seg.cmd
                    moving = True
                    if act.first:
                        act.first = False
                        if act.seg.events:
                            events += act.seg.events
                            act.seg.events = []
                    break
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
                elif isinstance(item.cmd, WAIT_TYPES) and not self.auto_release:
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
        if src is None:
            return Setpoint(t, tuple(pos), events=tuple(events))
        return Setpoint(t, tuple(pos), src.file, src.line, tuple(events))


def plan_all(commands: Iterable[C.Canon], machine: MachineLimits = DEMO_MACHINE,
             start: Sequence[float] | None = None, window: int = 400,
             max_cycles: int | None = None) -> Iterator[Setpoint]:
    """Plan a whole program faster than real time (previews, tests, ``canon plan``).

    Commands are read lazily, keeping ``window`` items queued ahead; waits are released at once. The
    stream starts at rest at ``start`` and ends at rest on the last point. ``max_cycles`` bounds it.
    """
    planner = Planner(machine, start, auto_release=True)
    it = iter(commands)
    exhausted = False
    cap = max_cycles if max_cycles is not None else 10**12
    for _ in range(cap):
        while not exhausted and planner.queue_length < window:
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
