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

import dataclasses
import logging
import math
from collections.abc import Iterable, Iterator, Sequence

from ruckig import ControlInterface, InputParameter, Result, Ruckig, RuckigError, Trajectory

from gcode_canon import commands as C
from gcode_canon.errors import GCodeError
from planner.geometry import (
    SIGMA1_MAX,
    SIGMA2_MAX,
    Arc,
    Blend,
    Chain,
    Line,
    Piece,
    Span,
    Transition,
    deviation_of_blend,
    vertex_tangent_curvature,
    vertex_tangent_curvature4,
)
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
SMOOTH_TURN = 0.2  # chains of short lines are smoothed only where they turn by less (|w2 - w1|, ~11 deg)
SMOOTH_DEVIATION = 0.8  # a smoothed span stays within this share of G64 P of its line (rigorous bound)
SMOOTH_GAIN = 2.0  # a chain starts only where a span inside it would be this much faster than the blends
SMOOTH_START = 0.25  # and its first and last spans (from and to zero curvature) at least this fast
SMOOTH_PAUSE = 16  # after a chain ended on a bad span (not a corner), blend this many vertices
SMOOTH_MERGE = 0.85  # a span joins the chain's profile if the chain keeps this share of its limits
SMOOTH_MERGE_ACC = 0.3  # path acceleration may fall further: it only matters where the speed changes
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


_FIELD_NAMES: dict[type, tuple[str, ...]] = {}


def _finite(cmd: C.Canon) -> None:
    names = _FIELD_NAMES.get(type(cmd))
    if names is None:  # dataclasses.fields() is slow: once per command type
        names = _FIELD_NAMES[type(cmd)] = tuple(f.name for f in dataclasses.fields(cmd))
    for name in names:
        value = getattr(cmd, name)
        if isinstance(value, float) and not math.isfinite(value):
            raise PlannerError(f"{cmd.NAME}: {name} is not a finite number ({value})", cmd.file, cmd.line)
        if isinstance(value, C.Pose) and not all(math.isfinite(x) for x in value):
            raise PlannerError(f"{cmd.NAME}: {name} has a coordinate that is not a finite number",
                               cmd.file, cmd.line)


class Seg:
    """A queued piece of motion with its limits along the path and its lookahead state."""

    __slots__ = (
        "a",
        "best",
        "blend_tol",
        "cap",
        "cap_geom",
        "chord_before",
        "cmd",
        "events",
        "feed",
        "j",
        "jcap",
        "jgeom",
        "kind",
        "orig_length",
        "ovr",
        "piece",
        "qs_a",
        "qs_j",
        "rapid",
        "s0",
        "sides",
        "smooth_in",
        "stop",
        "vb",
    )

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
        # A line whose start continues a smoothed chain: the (tangent, curvature) its span must start
        # with once the next vertex is known (until then it is queued as the plain line).
        # Also the chord before it (direction, length), for the next vertex's four-point estimate.
        self.smooth_in: tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...], float] | None = None
        self.best = (0.0, 0.0, 0.0)  # a chain's best single-span (speed cap, a, j): merging keeps near it
        self.chord_before: tuple[tuple[float, ...], float] | None = None  # the line fed before this one

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
        # quick stop: how much each axis may exceed its acceleration (and, in proportion, its jerk)
        self._QR = [max(1.0, a.quick_stop / a.max_acceleration) for a in machine.axes]
        # per-axis budgets of _path_limits, computed once
        self._JC = [JERK_CONTINUOUS * j for j in self._J]
        self._CA = [CENTRIPETAL_ACC * a for a in self._A]
        self._JCENT = [JERK_CENTRIPETAL * j for j in self._JC]
        self._JCROSS = [JERK_CROSS * j / 3.0 for j in self._JC]
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
        self._finish_chain()
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
        if kind == "line":
            seg.chord_before, self._last_chord = self._last_chord, (piece.d1_start, piece.length)
        else:
            self._last_chord = None
        # the corner at a move's end is blended by the mode the move was programmed in (LinuxCNC)
        seg.blend_tol = self._tolerance if self._mode is C.MotionControlMode.CONTINUOUS else -1.0
        self._limits(seg)
        seg.events, self._pending = self._pending, []
        exact = self._exact_next or isinstance(cmd, C.Probe) or self._mode in (
            C.MotionControlMode.EXACT_STOP_MODAL, C.MotionControlMode.EXACT_STOP)
        self._exact_next = False
        self._end = end
        self.stats["segments"] += 1
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
        (seg.cap_geom, seg.a, seg.j, seg.qs_a, seg.qs_j) = self._path_limits(
            p.d1_max, p.d2_max, p.d3_max, seg.feed, seg.cmd)
        self._set_cap(seg)

    def _path_limits(self, d1: Sequence[float], d2: Sequence[float], d3: Sequence[float], feed: float,
                     cmd: C.Canon) -> tuple[float, float, float, float, float]:
        """(speed cap, path acceleration, path jerk, quick-stop acceleration and jerk) for derivative
        bounds ``d1 d2 d3`` at ``feed``: tangential, centripetal and cross terms budgeted together."""
        if not any(d2) and not any(d3):
            return self._line_limits(d1, cmd)
        cap = self._speed_cap(d1, d2, d3)
        vb = min(cap, MAX_OVERRIDE * feed)
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

    # --- blending -----------------------------------------------------------------------------------

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
        if span.chord_deviation() > SMOOTH_DEVIATION * prev.blend_tol:
            self._smooth_pause = SMOOTH_PAUSE
            return False
        span_cap = min(self._speed_cap(span.d1_max, span.d2_max, span.d3_max), prev.feed)
        if prev.smooth_in is not None:
            # noisy points (or a large P): corner blends, free to cut within P, do better; and do not
            # try again at once (each chain's ends cost)
            if span_cap < SMOOTH_MERGE * prev.feed and span_cap < SMOOTH_MERGE * self._blend_cap(prev, new):
                self._smooth_pause = SMOOTH_PAUSE
                return False
        elif not self._worth_starting(prev, new, span_cap, t, k):
            return False
        chain = q[-2] if len(q) - 2 >= h else None
        merged = None
        if (isinstance(chain, Seg) and chain.kind == "smooth" and chain.s0 == 0.0 and not chain.stop
                and not prev.events and chain.feed == prev.feed and chain.ovr == prev.ovr
                and chain.blend_tol == prev.blend_tol and chain.sides == prev.sides
                and not (running and len(q) - 2 == h)):
            merged = self._merged_limits(chain, span, span_cap)
        limits: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
        if merged is None:
            try:
                limits = self._path_limits(span.d1_max, span.d2_max, span.d3_max, prev.feed, prev.cmd)
            except PlannerError:
                return False
        snapshot = self._snapshot(len(q) - (3 if merged else 2))
        q.pop()  # prev
        old_limits, old_best = (), (0.0, 0.0, 0.0)
        if merged is not None and isinstance(chain, Seg):
            # the chain grows in place: its start and its link to the item before stay, only its
            # limits (hence that item's jcap) and its end change
            old_limits, old_best = self._limits_of(chain), chain.best
            chain.piece.add(span, prev.cmd)  # type: ignore[attr-defined]
            chain.orig_length = chain.piece.length
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
            self._link(self._span_seg(span, prev, limits, (min(limits[0], prev.feed), limits[1], limits[2])))
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
        blend = min(self._blend_cap(prev, new), prev.feed)
        if SMOOTH_GAIN * blend > prev.feed:
            return False  # the blends run at (nearly) the feed: nothing to gain
        b = new.piece
        half = 0.5 * b.length
        end = Span(b.start, t, k, tuple(b.pos(half)), b.d1_start, (0.0,) * self._n, half)
        if end.chord_deviation() > SMOOTH_DEVIATION * new.blend_tol:
            return False  # the chain could not end on new
        if min(span_cap, self._speed_cap(end.d1_max, end.d2_max, end.d3_max)) < SMOOTH_START * blend:
            return False
        before = prev.chord_before
        if before is None:
            return False
        w1, l1 = prev.piece.d1_end, prev.orig_length
        tb, kb = vertex_tangent_curvature(before[0], before[1], w1, l1)
        end_pt = prev.piece.end
        start_pt = tuple(end_pt[i] - l1 * w1[i] for i in range(self._n))
        inner = Span(start_pt, tb, kb, end_pt, t, k, l1)
        if inner.chord_deviation() > SMOOTH_DEVIATION * prev.blend_tol:
            return False  # the chain would end at the next vertex
        inner_cap = self._speed_cap(inner.d1_max, inner.d2_max, inner.d3_max)
        return min(inner_cap, prev.feed) >= SMOOTH_GAIN * blend

    def _blend_cap(self, prev: Seg, new: Seg) -> float:
        """The speed cap of the corner blend :meth:`_try_blend` would make between the lines ``prev`` and
        ``new`` (without making it), to choose between smoothing and blending at this vertex."""
        w1, w2 = prev.piece.d1_end, new.piece.d1_start
        unit = deviation_of_blend(w1, w2, 1.0, self._linear)
        d = min(0.5 * prev.orig_length, prev.piece.length, 0.5 * new.piece.length)
        if unit > 0.0:
            d = min(d, prev.blend_tol / unit)
        if d <= 1e-9:
            return 0.0
        span = 2.0 * d
        dw = [abs(x - y) for x, y in zip(w2, w1, strict=True)]
        return self._speed_cap([max(abs(x), abs(y)) for x, y in zip(w1, w2, strict=True)],
                               [x * SIGMA1_MAX / span for x in dw],
                               [x * SIGMA2_MAX / (span * span) for x in dw])

    def _span_seg(self, span: Span, line: Seg, limits: tuple[float, ...],
                  best: tuple[float, float, float]) -> Seg:
        """A queue item for ``span`` (its path limits ``limits``), which replaces (part of) the
        programmed ``line``."""
        sseg = Seg(Chain(span, line.cmd), "smooth", line.cmd, line.feed, False, line.ovr)
        sseg.sides = line.sides
        sseg.orig_length = span.length
        sseg.blend_tol = line.blend_tol
        sseg.events = line.events
        sseg.cap_geom, sseg.a, sseg.j, sseg.qs_a, sseg.qs_j = limits
        self._set_cap(sseg)
        sseg.best = best
        return sseg

    def _merged_limits(self, chain: Seg, span: Span, span_cap: float,
                       ) -> tuple[float, float, float, float, float] | None:
        """The chain's limits with ``span`` (its own speed cap at the feed: ``span_cap``) added, or None
        when they would fall below SMOOTH_MERGE of the best seen in the chain or of the span's own cap
        (then the span starts a new profile: one slow place must not slow a whole row; the path
        acceleration may fall to SMOOTH_MERGE_ACC, as it only matters where the speed changes).
        Compared at the programmed feed; the limits themselves hold at any override, as every piece's
        do. (The span's own acceleration and jerk limits are not computed: a cost per fed segment for
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
                merged = self._path_limits(d1, d2, d3, chain.feed, chain.cmd)
            except PlannerError:
                return None
        top = chain.best
        if (min(merged[0], chain.feed) < SMOOTH_MERGE * max(top[0], span_cap)
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
        if span.chord_deviation() > SMOOTH_DEVIATION * tail.blend_tol:
            return
        try:
            limits = self._path_limits(span.d1_max, span.d2_max, span.d3_max, tail.feed, tail.cmd)
        except PlannerError:
            return
        sseg = self._span_seg(span, tail, limits, (min(limits[0], tail.feed), limits[1], limits[2]))
        rest = Seg(Line(mid, b.end, b.length - half), "line", tail.cmd, tail.feed, tail.rapid, tail.ovr)
        rest.sides, rest.orig_length, rest.blend_tol = tail.sides, tail.orig_length, tail.blend_tol
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
        return self._splice(index, prev, new, items, orig_piece, orig_events)

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
                if target <= 0.0 and self._tight_stop(seg, t0, v0, length, a, j):
                    return
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
        if seg.vb <= 0.0 and self._tight_stop(seg, t0, v0, length, a, j):
            return
        for eps in (1e-9, 1e-7, 1e-5, 1e-3):  # at the very edge of feasibility: a hair faster
            target = min(lo + eps * (v0 + lo + 1e-9), max(v0, lo))
            traj = self._solve(v0, 0.0, length, target, max(seg.cap, v0), a, j)
            if traj is not None:
                self._active = _Active(seg, t0, traj, seg.s0, seg.piece.length, target, True)
                return
        raise PlannerError(f"no feasible profile for this move (length {length:g}, from speed {v0:g} to "
                           f"{target:g})", seg.cmd.file, seg.cmd.line)

    def _tight_stop(self, seg: Seg, t0: float, v0: float, length: float, a: float, j: float) -> bool:
        """Start ``seg`` as a stop at its end when that stop is at the very edge of what its length
        allows (rounding): with a hair more acceleration and jerk (at most 1e-4), never with an end
        speed above 0. ``seg`` must end at rest (a stop, the end of the queue), and braking to a low
        speed needs more room than stopping (the mean speed is higher), so the lowest speed reachable
        short of a stop may be far above 0: taking it would end the stream while moving."""
        for eps in (0.0, 1e-9, 1e-7, 1e-6, 1e-5, 1e-4):
            traj = self._solve(v0, 0.0, length, 0.0, max(seg.cap, v0), a * (1 + eps), j * (1 + eps))
            if traj is not None:
                self._active = _Active(seg, t0, traj, seg.s0, seg.piece.length, 0.0, True)
                return True
        log.warning("%s:%d: cannot stop at the end of this move from %g (length %g)", seg.cmd.file,
                    seg.cmd.line, v0, length)
        return False

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
            # as the backward pass plans it (length * SLACK): a hair more and the head could not keep
            # its own end speed (at the end of the queue: stop) within its length
            vb = min(seg.jgeom, seg.cap, head.cap, max_reach(head.vb, head.length * SLACK, head.a, head.j))
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
            self._last_chord = None  # the next line does not continue the dropped ones
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
                    src = act.seg.cmd if act.seg.kind != "smooth" else act.seg.piece.cmd_at(p)  # type: ignore[attr-defined]
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
