"""Queue items and the planner's budgets: a segment of motion with its limits along the path and its
lookahead state, a sync point, the running profile; the constants every part of the planner shares.
"""

from __future__ import annotations

import dataclasses
import logging
import math

from ruckig import Trajectory

from gcode_canon import commands as C
from gcode_canon.errors import GCodeError
from planner.geometry import (
    Piece,
)

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
SMOOTH_GAIN = 1.1  # a chain starts only where a span inside it would be this much faster than the blends
SMOOTH_START = 0.25  # and its first and last spans (from and to zero curvature) at least this fast
SMOOTH_KEEP = 0.5  # a chain ends where its next span would be slower than this share of the blend
SMOOTH_PAUSE = 16  # after a chain ended on a bad span (not a corner), blend this many vertices
SMOOTH_MERGE = 0.85  # a span joins the chain's profile if the chain keeps this share of its limits
SMOOTH_CHAIN_SPANS = 32  # spans under one profile at most: the queue's length stays a lookahead window
SMOOTH_MERGE_ACC = 0.3  # path acceleration may fall further: it only matters where the speed changes
MERGE_SHARE = 0.25  # lines within this share of G64 P (without Q) of one line are merged into it
MERGE_EXACT = 1e-4  # ... within this (mm) in G64 without P and in G61: coordinate rounding only
MERGE_EXACT_ARC = 2e-4  # ... and of one arc (rounding 7.1e-5 plus the chords' own sagitta; checker: 1e-3)
MERGE_NOP_ARC = 1e-3  # G64 without P: the chords of an arc within this of it (its points within the above)
MERGE_MAX_PIECES = 20_000  # programmed lines in one merged line at most
MERGE_MAX_TIME = 2.0  # seconds of motion at its feed in one merged line at most
ARC_TRY = 4  # an arc is tried once this many programmed lines in a row lie on one line (dense points)
ARC_TRY_EXACT = 1  # ... in G64 without P and G61 (no smoothed chains for arcs to break)
ARC_DENSE = 16  # programmed lines merged into one arc at least (fewer stay lines)
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

WAIT_TYPES: tuple[type[C.Canon], ...] = (C.WaitInput, C.ToolChange, C.ProgramStop, C.PalletShuttle, C.Probe,
                                         C.UserMCode)
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


_LINES = (C.StraightFeed, C.StraightTraverse)


def _finite(cmd: C.Canon) -> None:
    if type(cmd) in _LINES and math.isfinite(sum(cmd.end)):  # type: ignore[attr-defined]
        return  # the common case, at a ninth of the cost (a huge finite sum falls through)
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
        "last",
        "merge_dev",
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
        self.last = 0  # programmed moves fed when it was queued (Planner.queued_moves)
        self.merge_dev = 0.0  # how far the programmed points lie from this (merged) line at most
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


def tol_left(*segs: Seg) -> float:
    """The G64 P of the first of ``segs`` left for a blend, span or transition over them: what their
    merging has not used (the points they were merged from lie up to ``merge_dev`` off them). 0 (no
    limit) and -1 (no blending) as they are."""
    tol = segs[0].blend_tol
    if tol <= 0.0:
        return tol
    return max(tol - max(s.merge_dev for s in segs), 1e-12)


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
