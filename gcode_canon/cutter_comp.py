"""Cutter radius compensation (G41/G42/G41.1/G42.1 .. G40) as a pure, streaming geometry engine.

The interpreter core keeps the modal state (which side, which radius, which plane) and the error
checks that belong to blocks (plane must be G17 or G18, "already on", D word ...); this module only
turns the *programmed* path, one move at a time, into the path of the tool centre, the way LinuxCNC's
rs274ngc does (``convert_straight_comp1/comp2``, ``convert_arc_comp1/comp2``, ``move_endpoint_and_flush``).
It imports nothing from the interpreter and knows nothing of axes: everything is in the active plane's
own 2-D coordinates ``(first, second)`` (G17: X Y, G18: Z X, see :class:`gcode_canon.commands.Plane`),
so "left" is left of the direction of travel seen from the positive end of the plane normal.

How the core uses it
--------------------

* On G41/G42 (or G41.1/G42.1) make ``CutterCompensator(side, radius, start)`` with ``start`` the
  current programmed position in the plane. ``radius`` is the tool table diameter / 2 or the G4x.1 D
  word / 2; a negative radius swaps the side (as LinuxCNC); a zero radius makes the compensator a
  pass-through (every move comes back unchanged, as LinuxCNC turns compensation into a no-op).
  ``orientation`` is the lathe tool orientation (tool table Q, G4x.1 L; 0 for a mill cutter, and
  always 0 or 9 outside G18) and ``normal`` the current coordinate along the plane normal (see
  "Lathe tools" below).
* For every G0/G1/G2/G3 while compensation is on, give the *programmed* move as a :class:`Line2` (G0
  with ``rapid=True``) or :class:`Arc2` (centre already found from I/J/K or R and checked by the
  core), with ``start`` equal to :attr:`CutterCompensator.programmed`, ``normal`` the end coordinate
  along the plane normal, ``extra`` the end coordinates of every other axis (carried unchanged, in
  whatever order the core likes) and ``line`` the source line. :meth:`CutterCompensator.add` returns the
  compensated segments that are now final, in order; emit them as STRAIGHT_TRAVERSE (``Line2.rapid``),
  STRAIGHT_FEED or ARC_FEED. The last compensated move is held back until the next move shows whether
  its corner is convex (an arc of the tool radius around the programmed corner is inserted) or
  concave (its end is moved back to where the tool touches both), so ``add`` often returns ``[]``.
* Non-motion commands that LinuxCNC queues behind a held move (feed rate, feed mode, dwell, coolant,
  spindle, comments, M100-M199) go through :meth:`CutterCompensator.hold`, which returns them at once
  when nothing is held, otherwise later, in order, from ``add``/``finish``. Anything that is neither a
  move nor one of those is not this module's business: LinuxCNC rejects most of them while
  compensation is on (probe, G28/G30, G53, G92, coordinate system change, motion-synchronised I/O,
  M66, override changes, G61/G64 changes ...); the core keeps those errors.
* A move made with the compensation switched off while it stays on (LinuxCNC's G70 pass start):
  emit it at once and call :meth:`CutterCompensator.jump` with its end; the next line's concave
  corner is then worked out as LinuxCNC's ``convert_straight_comp2`` does, from that point.
* On G40, M2/M30 (or before anything else that needs the path final) call
  :meth:`CutterCompensator.finish`: it returns the held segments (the last one ending at its normal
  offset point) and the compensator is done. The tool is then at :attr:`CutterCompensator.tool`
  (plus :attr:`CutterCompensator.tip` for a lathe tool); the next move after G40 is an ordinary,
  uncompensated move from there to its programmed end, and must be a straight line (the core raises
  LinuxCNC's "The move just after exiting cutter compensation mode must be straight, not an arc").
* Errors are :class:`~gcode_canon.errors.GCodeError` with ``line`` set to the move being added (the
  core fills in the file with ``located``); ``finish`` raises with no line, so the block that asked
  for it is named. ``ValueError`` means a wiring bug (a move not starting at ``programmed``, a bad
  side), never a user's mistake.
* Building canonical commands: put ``(first, second)`` back on the plane's axes, ``normal`` on the
  normal axis and ``extra`` on the others; an :class:`Arc2` becomes ``ArcFeed(turns=+turns if ccw else
  -turns)`` with the centre's normal coordinate taken from the arc's start. Feed rates stay as
  programmed (LinuxCNC does the same; in G93 the core decides how an inserted corner arc is timed).

Normal axis and the other axes: each output segment carries the ``normal`` and ``extra`` of the move
it came from, at its end. An inserted corner arc (or, for G0, corner traverse) belongs to the next move
(its ``line``); it keeps the normal coordinate where it was and takes the new ``extra`` values, so the
whole normal motion happens on the programmed move and the whole motion of the other axes on the corner,
as LinuxCNC does. A move with no motion in the plane (a Z plunge, say) is passed through at the tool's
current point; when it sits in a concave corner its point moves with the corner, so the plunge happens
where the tool will turn.

Rules, as LinuxCNC
------------------

* Entry (first move after G41/G42): a line goes from the uncompensated start to the programmed end
  offset by the radius perpendicular to the entry direction ("Length of cutter compensation entry move
  is not greater than the tool radius" when it is not longer than the radius); an arc ends offset
  along its end radius and gets a new centre so that it still starts at the uncompensated point
  ("Radius of cutter compensation entry arc is not greater than the tool radius" when the chord is
  not). The entry move is held like any other, so its end moves if the next corner is concave.
* Corners are classified with the angle ``beta`` between the old and the new direction measured
  towards the tool side, with LinuxCNC's 0.05 rad tolerance: convex (``beta`` > 0.05) gets an arc
  around the programmed corner (a straight traverse for G0), near-tangent (|``beta``| <= 0.05) joins
  directly, concave cuts both offset paths back to their intersection (line-line, line-arc, arc-line,
  arc-arc), including LinuxCNC's "h"/"m" cases (a reversal onto an arc the tool is outside of).
* Errors: "Tool radius not less than arc radius with comp" (inside arc not larger than the tool);
  "Arc move in concave corner cannot be reached by the tool without gouging", "Arc to straight motion
  makes a corner the compensated tool can't fit in without gouging", "Arc to arc motion makes a corner
  the compensated tool can't fit in without gouging", "Arc to arc motion is invalid because the arcs
  have the same center" (no intersection); "Straight feed (traverse) in concave corner cannot be reached
  by the tool without gouging" and "Arc move in concave corner ..." when a held move would be cut back
  past its start (checked on every release of a held move, see below).

Lathe tools (tool orientation 1-8)
----------------------------------

A lathe tool's control point (the one its tool table offsets are measured to) is not the centre of
its nose radius but the "imaginary tip" where the tangents along Z and X to the nose meet; the
orientation (tool table Q for G41/G42, the L word of G41.1/G42.1) says on which side of the centre
that tip lies. LinuxCNC still computes the path of the nose-radius *centre* exactly as for a mill
cutter and then, as each compensated move leaves its queue (``dequeue_canons`` in
``interp_queue.cc``), moves the end point (and an arc's centre) of every STRAIGHT_TRAVERSE,
STRAIGHT_FEED and ARC_FEED by the centre-to-tip vector (``latheorigin_x`` / ``latheorigin_z``), so the
control point is commanded where the tip is when the nose centre is on its path. The interpreter
passes ``orientation`` only in G18, where ``(first, second)`` is ``(Z, X)``: see
:func:`lathe_tip_offset`. Orientations 0 and 9 (and a zero radius) move nothing. The compensator
does the same: its geometry (``tool``, the corners, the gouge checks) is the nose centre's, and every
segment it hands out is shifted by :attr:`CutterCompensator.tip`, except the start of the entry move,
which is where the tool really is (it came there uncompensated).

An entry *arc* with a lathe tool is preceded by a straight feed from the uncompensated start to the
same point shifted by the tip (``convert_arc_comp1``: "need this move for lathes to move the tool
origin first. otherwise, the arc isn't an arc"); it keeps the start's normal coordinate and takes the
arc's end values of the other axes, as LinuxCNC's does. LinuxCNC, though, leaves that straight feed
in its queue ahead of the held arc, and ``move_endpoint_and_flush`` sets the end of *every* queued
move: when the next thing after the entry arc is a line around a convex corner, a concave corner,
G40 or the program end, the straight feed gets the arc's (final) end too, so the control point goes
straight there and the arc runs from its end to itself; a concave corner there is moreover computed
as though the held move were a line (its code looks at the head of the queue), and the "h" reversal
rule (below) does not see the arc. Only a tangent line or an arc next gives what its comment means.
The compensator emits that straight feed at once and treats the held entry arc as an arc, as after
a mill entry arc: what LinuxCNC does in the cases where it works, in all cases.

Known differences from LinuxCNC: the lathe entry arc above; a move with less than 1e-9 of motion in
the plane counts as no motion (LinuxCNC: exactly equal coordinates); a held move reversed by its own
start having been cut forward past its end is an error whatever comes next (LinuxCNC lets it through
when the next move is an arc or a near-tangent join, gouging the part).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Literal

from gcode_canon.errors import GCodeError

Point = tuple[float, float]
Side = Literal["left", "right"]

TOLERANCE_CONCAVE_CORNER = 0.05
"""Radians: corners within this of tangent are joined directly (LinuxCNC's TOLERANCE_CONCAVE_CORNER)."""

ARC_GOUGE_TOLERANCE = 0.0254
"""How much (radians of sweep) a cut-back arc may grow before it counts as reversed (LinuxCNC, mm mode)."""

NO_MOTION = 1e-9
"""A straight move shorter than this in the plane has no motion in the plane."""

_LINE_GOUGE_TOLERANCE = 1e-9

ENTRY_LINE_TOO_SHORT = "Length of cutter compensation entry move is not greater than the tool radius"
ENTRY_ARC_TOO_SHORT = "Radius of cutter compensation entry arc is not greater than the tool radius"
ARC_TOO_SMALL = "Tool radius not less than arc radius with comp"
LINE_LINE_ZERO_CORNER = "Zero degree inside corner is invalid for cutter compensation"
LINE_ARC_GOUGE = "Arc move in concave corner cannot be reached by the tool without gouging"
ARC_LINE_GOUGE = "Arc to straight motion makes a corner the compensated tool can't fit in without gouging"
ARC_ARC_GOUGE = "Arc to arc motion makes a corner the compensated tool can't fit in without gouging"
ARC_ARC_SAME_CENTER = "Arc to arc motion is invalid because the arcs have the same center"
FEED_GOUGE = "Straight feed in concave corner cannot be reached by the tool without gouging"
TRAVERSE_GOUGE = "Straight traverse in concave corner cannot be reached by the tool without gouging"
ARC_GOUGE = "Arc move in concave corner cannot be reached by the tool without gouging"

_LATHE_TIP: dict[int, Point] = {
    1: (1.0, -1.0),
    2: (-1.0, -1.0),
    3: (-1.0, 1.0),
    4: (1.0, 1.0),
    5: (1.0, 0.0),
    6: (0.0, -1.0),
    7: (-1.0, 0.0),
    8: (0.0, 1.0),
}
"""Orientation -> (Z, X) direction from the nose-radius centre to the imaginary tip, in units of the
radius: LinuxCNC's ``latheorigin_z`` / ``latheorigin_x`` (``interp_queue.cc``), X - R for 1 2 6,
X + R for 3 4 8, Z - R for 2 3 7, Z + R for 1 4 5."""


def lathe_tip_offset(orientation: int, radius: float) -> Point:
    """Vector from the nose-radius centre to the control point of a lathe tool, in G18 plane coordinates
    ``(Z, X)``: what is added to every compensated point so that the control point is commanded.

    ``(0, 0)`` for orientations 0 and 9 (the control point is the centre, as on a mill) and for a zero
    radius; ``radius`` is taken as its magnitude (a negative one only swaps the side). ``ValueError``
    for an orientation outside 0-9 (the interpreter refuses those with a G-code error first).
    """
    if isinstance(orientation, bool) or not isinstance(orientation, int) or not 0 <= orientation <= 9:
        raise ValueError(f"lathe tool orientation must be an integer 0 to 9, not {orientation!r}")
    dz, dx = _LATHE_TIP.get(orientation, (0.0, 0.0))
    r = abs(radius)
    return (dz * r + 0.0, dx * r + 0.0)


@dataclass(frozen=True, slots=True)
class Line2:
    """A straight move in the plane: programmed (input) or compensated (output).

    ``normal`` is the end coordinate along the plane normal and ``extra`` the end coordinates of the
    other axes; both are interpolated linearly along the move by the planner.
    """

    start: Point
    end: Point
    normal: float = 0.0
    extra: tuple[float, ...] = ()
    line: int = 0
    rapid: bool = False


@dataclass(frozen=True, slots=True)
class Arc2:
    """A circular (helical, when ``normal`` changes) move in the plane.

    ``turns`` is LinuxCNC's count of circles (P word): ``turns - 1`` full circles are added to the
    partial one from ``start`` to ``end``; a ``start`` equal to ``end`` is a full circle. An output
    arc's ``start`` may sit off its circle by a hair where a near-tangent corner was joined directly
    (as in LinuxCNC); the radius is the one at ``end``.
    """

    start: Point
    end: Point
    center: Point
    ccw: bool
    normal: float = 0.0
    extra: tuple[float, ...] = ()
    line: int = 0
    turns: int = 1


Segment = Line2 | Arc2


# --- plane geometry -------------------------------------------------------------------------------


def _sub(a: Point, b: Point) -> Point:
    return (a[0] - b[0], a[1] - b[1])


def _add(a: Point, b: Point) -> Point:
    return (a[0] + b[0], a[1] + b[1])


def _mul(a: Point, k: float) -> Point:
    return (a[0] * k, a[1] * k)


def _dot(a: Point, b: Point) -> float:
    return a[0] * b[0] + a[1] * b[1]


def _cross(a: Point, b: Point) -> float:
    return a[0] * b[1] - a[1] * b[0]


def _length(a: Point) -> float:
    return math.hypot(a[0], a[1])


def _unit(a: Point) -> Point:
    n = math.hypot(a[0], a[1])
    return (a[0] / n, a[1] / n)


def _rot(a: Point, sign: int) -> Point:
    """``a`` turned a quarter turn counter-clockwise (``sign`` 1) or clockwise (``sign`` -1)."""
    return (-a[1], a[0]) if sign > 0 else (a[1], -a[0])


def sweep(start: Point, center: Point, end: Point, ccw: bool, turns: int = 1) -> float:
    """Angle (radians, > 0) an arc turns from ``start`` to ``end``; equal points make a full circle."""
    a0 = math.atan2(start[1] - center[1], start[0] - center[0])
    a1 = math.atan2(end[1] - center[1], end[0] - center[0])
    d = a1 - a0 if ccw else a0 - a1
    if d <= 0.0:
        d += 2.0 * math.pi
    return d + 2.0 * math.pi * (max(turns, 1) - 1)


def _line_line(p1: Point, d1: Point, p2: Point, d2: Point) -> list[Point]:
    den = _cross(d1, d2)
    if abs(den) < 1e-12:
        return []
    t = _cross(_sub(p2, p1), d2) / den
    return [_add(p1, _mul(d1, t))]


def _line_circle(p: Point, d: Point, c: Point, r: float) -> list[Point]:
    """Crossings of the line through ``p`` along unit ``d`` with the circle (``c``, ``r``)."""
    w = _sub(p, c)
    b = _dot(w, d)
    disc = b * b - (_dot(w, w) - r * r)
    scale = max(r * r, _dot(w, w), 1.0)
    if disc < 0.0:
        if disc < -1e-12 * scale:
            return []
        disc = 0.0
    root = math.sqrt(disc)
    return [_add(p, _mul(d, -b - root)), _add(p, _mul(d, -b + root))]


def _circle_circle(c1: Point, r1: float, c2: Point, r2: float) -> list[Point]:
    v = _sub(c2, c1)
    dist = _length(v)
    if dist == 0.0:
        return []
    a = (r1 * r1 - r2 * r2 + dist * dist) / (2.0 * dist)
    h2 = r1 * r1 - a * a
    if h2 < 0.0:
        if h2 < -1e-12 * max(r1 * r1, 1.0):
            return []
        h2 = 0.0
    h = math.sqrt(h2)
    u = _mul(v, 1.0 / dist)
    base = _add(c1, _mul(u, a))
    off = _mul(_rot(u, 1), h)
    return [_add(base, off), _sub(base, off)]


# --- the engine -----------------------------------------------------------------------------------


@dataclass(slots=True)
class _Held:
    """What the next corner needs to know of the held (last compensated) move."""

    arc: bool
    rapid: bool
    ref: Point = (0.0, 0.0)  # line: direction the move must keep
    direction: Point = (0.0, 0.0)  # line: programmed direction (for the corner intersection)
    center: Point = (0.0, 0.0)  # arc: centre of the compensated arc
    radius: float = 0.0  # arc: radius of the compensated arc
    inside: bool = False  # arc: tool on the centre side
    max_sweep: float = 0.0  # arc: the sweep it may not exceed when its end moves


class CutterCompensator:
    """One G41/G42 .. G40 stretch of cutter radius compensation (see the module docstring)."""

    def __init__(
        self,
        side: Side,
        radius: float,
        start: Point,
        orientation: int = 0,
        normal: float | None = None,
    ) -> None:
        if side not in ("left", "right"):
            raise ValueError(f"side must be 'left' or 'right', not {side!r}")
        if not math.isfinite(radius):
            raise ValueError(f"radius must be finite, not {radius!r}")
        if radius < 0.0:
            side = "right" if side == "left" else "left"
            radius = -radius
        self.side: Side = side
        self.radius = float(radius)
        self._s = 1 if side == "left" else -1
        self._programmed: Point = (float(start[0]), float(start[1]))
        self._tool: Point = self._programmed
        self.orientation = orientation
        self._tip = lathe_tip_offset(orientation, self.radius)
        self._normal: float | None = None if normal is None else float(normal)
        self._entered = False  # a segment went out: the next one no longer starts uncompensated
        self._first = True
        self._closed = False
        self._queue: list[object] = []
        self._held: _Held | None = None
        self._jumped = False  # the tool left the held move's offset end (jump): LinuxCNC's corner rule

    # --- public ---------------------------------------------------------------------------------

    @property
    def programmed(self) -> Point:
        """The programmed point reached so far (the interpreter's current point for the next move)."""
        return self._programmed

    @property
    def tool(self) -> Point:
        """Where the tool centre (a lathe tool's nose-radius centre) is, or will be once the held move
        is released; the point commanded is this plus :attr:`tip`."""
        return self._tool

    @property
    def tip(self) -> Point:
        """Vector from the nose-radius centre to the control point (:func:`lathe_tip_offset`)."""
        return self._tip

    @property
    def pending(self) -> bool:
        """True while a move (and maybe commands behind it) is held back."""
        return bool(self._queue)

    def hold(self, item: object) -> list[object]:
        """Keep a non-motion command in order behind the held move; returns what may go out now."""
        self._check_open()
        if not self._queue:
            return [item]
        self._queue.append(item)
        return []

    def add(self, seg: Segment) -> list[object]:
        """Take the next programmed move; return the compensated segments (and held items) now final."""
        self._check_open()
        if _length(_sub(seg.start, self._programmed)) > 1e-6 * max(1.0, _length(self._programmed)):
            raise ValueError(f"move starts at {seg.start}, the programmed point is {self._programmed}")
        if self.radius == 0.0:
            self._programmed = seg.end
            self._tool = seg.end
            return [seg]
        if isinstance(seg, Line2):
            out = self._entry_line(seg) if self._first else self._line(seg)
        else:
            out = self._entry_arc(seg) if self._first else self._arc(seg)
        self._jumped = False
        self._programmed = seg.end
        self._normal = seg.normal
        return self._to_tip(out)

    def jump(self, point: Point) -> None:
        """The tool went to ``point`` by a move made outside the compensation (LinuxCNC's G70 starts
        each pass with a rapid made with compensation switched off, emitted at once, ahead of the held
        move). Before the entry move the programmed point goes with it (the entry starts where the tool
        is); after it, the programmed point and the held move stay, and the next corner is worked out
        from them and this point, as LinuxCNC's from its current and programmed points."""
        self._check_open()
        self._tool = (float(point[0]), float(point[1]))
        if self._first:
            self._programmed = self._tool
        else:
            self._jumped = True

    def finish(self) -> list[object]:
        """Release the held move at its offset end (G40, program end); the compensator is then done."""
        self._check_open()
        self._closed = True
        if not self._queue:
            return []
        return self._to_tip(self._release(self._tool, 0))

    # --- entry moves ----------------------------------------------------------------------------

    def _entry_line(self, seg: Line2) -> list[object]:
        r = self.radius
        length = _length(_sub(seg.end, self._programmed))
        if length <= r:
            raise GCodeError(ENTRY_LINE_TOO_SHORT, line=seg.line)
        d = _unit(_sub(seg.end, self._programmed))
        n = _rot(d, self._s)
        end = _add(seg.end, _mul(n, r))
        # LinuxCNC keeps the offset direction as the entry move's reference: it cannot reverse.
        self._hold_move(
            Line2(self._tool, end, seg.normal, seg.extra, seg.line, seg.rapid),
            _Held(arc=False, rapid=seg.rapid, ref=n, direction=d),
        )
        self._first = False
        return []

    def _entry_arc(self, seg: Arc2) -> list[object]:
        r = self.radius
        start = self._tool
        if _length(_sub(seg.end, start)) <= r:
            raise GCodeError(ENTRY_ARC_TOO_SHORT, line=seg.line)
        inside = self._tool_inside(seg.ccw)
        if inside and _length(_sub(seg.center, start)) <= r:
            raise GCodeError(ARC_TOO_SMALL, line=seg.line)
        radial = _sub(seg.center, seg.end) if inside else _sub(seg.end, seg.center)
        if _length(radial) == 0.0:
            raise GCodeError(ARC_TOO_SMALL, line=seg.line)
        end = _add(seg.end, _mul(_unit(radial), r))
        # New centre: on the line from the offset end towards the programmed centre, as far from
        # the (uncompensated) start as from the offset end.
        to_center = _sub(seg.center, end)
        if _length(to_center) == 0.0:
            raise GCodeError(ARC_TOO_SMALL, line=seg.line)
        u = _unit(to_center)
        chord = _sub(start, end)
        cos_a = _dot(chord, u) / _length(chord)
        if abs(cos_a) < 1e-6:
            raise GCodeError(ARC_TOO_SMALL, line=seg.line)
        center = _add(end, _mul(u, _dot(chord, chord) / (2.0 * _dot(chord, u))))
        first: list[object] = []
        if self.orientation not in (0, 9):
            # LinuxCNC's convert_arc_comp1: the control point first goes straight to where it is when
            # the nose centre is at the arc's start, at the start's normal coordinate and with the
            # other axes' end values; "otherwise, the arc isn't an arc". Final at once (see the module
            # docstring on why it is not held with the arc).
            normal = self._normal if self._normal is not None else seg.normal
            first.append(Line2(start, start, normal, seg.extra, seg.line))
        out = Arc2(start, end, center, seg.ccw, seg.normal, seg.extra, seg.line, seg.turns)
        self._hold_move(
            out,
            _Held(
                arc=True,
                rapid=False,
                center=center,
                radius=_length(_sub(end, center)),
                inside=inside,
                max_sweep=sweep(start, center, end, seg.ccw, seg.turns),
            ),
        )
        self._first = False
        return first

    # --- moves after the entry ------------------------------------------------------------------

    def _line(self, seg: Line2) -> list[object]:
        r, s = self.radius, self._s
        p = self._programmed
        if _length(_sub(seg.end, p)) <= NO_MOTION:
            self._queue.append(Line2(self._tool, self._tool, seg.normal, seg.extra, seg.line, seg.rapid))
            return []
        d_new = _unit(_sub(seg.end, p))
        n_new = _rot(d_new, s)
        end = _add(seg.end, _mul(n_new, r))
        mid = _add(p, _mul(n_new, r))
        beta = self._beta(d_new)
        held = self._held
        assert held is not None
        concave = (
            beta < -TOLERANCE_CONCAVE_CORNER
            or beta > math.pi + TOLERANCE_CONCAVE_CORNER
            or (beta > math.pi - TOLERANCE_CONCAVE_CORNER and held.arc and not held.inside)
        )
        info = _Held(arc=False, rapid=seg.rapid, ref=d_new, direction=d_new)
        if concave:
            corner = self._corner(seg.line, new_line=(mid, d_new))
            out = self._release(corner, seg.line)
            self._hold_move(Line2(corner, end, seg.normal, seg.extra, seg.line, seg.rapid), info)
        elif beta > TOLERANCE_CONCAVE_CORNER:
            c = self._tool
            out = self._release(c, seg.line)
            out.append(self._corner_move(c, mid, p, seg, rapid=seg.rapid))
            self._hold_move(Line2(mid, end, seg.normal, seg.extra, seg.line, seg.rapid), info)
        else:
            c = self._tool
            out = self._release(c, seg.line)
            self._hold_move(Line2(c, end, seg.normal, seg.extra, seg.line, seg.rapid), info)
        return out

    def _arc(self, seg: Arc2) -> list[object]:
        r = self.radius
        p = self._programmed
        radius = _length(_sub(seg.center, seg.end))
        inside = self._tool_inside(seg.ccw)
        if inside and radius <= r:
            raise GCodeError(ARC_TOO_SMALL, line=seg.line)
        to_center = _sub(seg.center, p)
        if _length(to_center) == 0.0 or radius == 0.0:
            raise GCodeError(ARC_TOO_SMALL, line=seg.line)
        u = _unit(to_center)
        d_new = _rot(u, -1 if seg.ccw else 1)
        n_start = u if inside else _mul(u, -1.0)
        n_end = _unit(_sub(seg.center, seg.end)) if inside else _unit(_sub(seg.end, seg.center))
        mid = _add(p, _mul(n_start, r))
        end = _add(seg.end, _mul(n_end, r))
        beta = self._beta(d_new)
        concave = (
            beta < -TOLERANCE_CONCAVE_CORNER
            or beta > math.pi + TOLERANCE_CONCAVE_CORNER
            or (abs(beta - math.pi) < TOLERANCE_CONCAVE_CORNER and not inside)
        )
        offset_radius = radius - r if inside else radius + r
        info = _Held(
            arc=True,
            rapid=False,
            center=seg.center,
            radius=offset_radius,
            inside=inside,
            max_sweep=sweep(p, seg.center, seg.end, seg.ccw, seg.turns),
        )
        if concave:
            corner = self._corner(seg.line, new_arc=(seg.center, offset_radius, seg.ccw))
            out = self._release(corner, seg.line)
            start = corner
        elif beta > TOLERANCE_CONCAVE_CORNER:
            c = self._tool
            out = self._release(c, seg.line)
            out.append(self._corner_move(c, mid, p, seg, rapid=False))
            start = mid
        else:
            start = self._tool
            out = self._release(start, seg.line)
        self._hold_move(
            Arc2(start, end, seg.center, seg.ccw, seg.normal, seg.extra, seg.line, seg.turns), info
        )
        return out

    # --- helpers --------------------------------------------------------------------------------

    def _to_tip(self, items: list[object]) -> list[object]:
        """Segments from the nose centre's path to the control point's (see "Lathe tools" in the
        module docstring); the first one ever handed out keeps its start, where the tool really is."""
        tip = self._tip
        shift = tip != (0.0, 0.0)
        out: list[object] = []
        for item in items:
            if isinstance(item, Line2 | Arc2):
                if shift:
                    start = _add(item.start, tip) if self._entered else item.start
                    item = replace(item, start=start, end=_add(item.end, tip))
                    if isinstance(item, Arc2):
                        item = replace(item, center=_add(item.center, tip))
                self._entered = True
            out.append(item)
        return out

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("cutter compensation already finished; make a new CutterCompensator")

    def _tool_inside(self, ccw: bool) -> bool:
        """Tool on the centre side of an arc: left of a counter-clockwise one, right of a clockwise one."""
        return ccw == (self._s > 0)

    def _beta(self, d_new: Point) -> float:
        """Turn from the held move's end direction to ``d_new``, positive away from the tool side
        (convex), in [-pi/2, 3pi/2)."""
        n_prev = _unit(_sub(self._tool, self._programmed))
        d_prev = _rot(n_prev, -self._s)
        turn = math.atan2(_cross(d_prev, d_new), _dot(d_prev, d_new))
        beta = -self._s * turn
        if beta < -math.pi / 2:
            beta += 2.0 * math.pi
        return beta

    def _corner_move(self, c: Point, mid: Point, corner: Point, seg: Segment, rapid: bool) -> Segment:
        """The move around a convex corner: an arc of the tool radius (a straight traverse for G0)."""
        normal = self._normal if self._normal is not None else seg.normal
        if rapid:
            return Line2(c, mid, normal, seg.extra, seg.line, rapid=True)
        return Arc2(c, mid, corner, self._s < 0, normal, seg.extra, seg.line)

    def _corner(
        self,
        line: int,
        new_line: tuple[Point, Point] | None = None,
        new_arc: tuple[Point, float, bool] | None = None,
    ) -> Point:
        """Where the held move's offset path meets the new move's in a concave corner.

        Of the crossings, the one where the new offset path passes from the held move's forbidden
        side to its allowed (tool) side; none is a gouging corner.
        """
        held = self._held
        assert held is not None
        c = self._tool
        cands: list[Point]
        if held.arc:
            if new_line is not None:
                cands = _line_circle(new_line[0], new_line[1], held.center, held.radius)
                error = ARC_LINE_GOUGE
            else:
                assert new_arc is not None
                if _length(_sub(new_arc[0], held.center)) == 0.0 or held.radius == 0.0:
                    raise GCodeError(ARC_ARC_SAME_CENTER, line=line)
                cands = _circle_circle(held.center, held.radius, new_arc[0], new_arc[1])
                error = ARC_ARC_GOUGE
        else:
            if new_line is not None and self._jumped:
                # LinuxCNC (convert_straight_comp2) steps back from the tool along the direction its
                # offset from the programmed point gives: the intersection below while the tool is
                # where the held move's offset path ends, not after a jump
                d_prev = _rot(_unit(_sub(c, self._programmed)), -self._s)
                halfcorner = (self._beta(new_line[1]) + math.pi) / 2.0
                if halfcorner == 0.0:
                    raise GCodeError(LINE_LINE_ZERO_CORNER, line=line)
                return _sub(c, _mul(d_prev, self.radius / math.tan(halfcorner)))
            if new_line is not None:
                cands = _line_line(c, held.direction, new_line[0], new_line[1])
                error = LINE_LINE_ZERO_CORNER
            else:
                assert new_arc is not None
                cands = _line_circle(c, held.direction, new_arc[0], new_arc[1])
                error = LINE_ARC_GOUGE
        if not cands:
            raise GCodeError(error, line=line)

        def entering(x: Point) -> float:
            if new_line is not None:
                tangent = new_line[1]
            else:
                assert new_arc is not None
                radial = _sub(x, new_arc[0])
                tangent = _rot(radial, 1 if new_arc[2] else -1)
            if held.arc:
                out = _sub(x, held.center)
                allowed = _mul(out, -1.0) if held.inside else out
            else:
                allowed = _rot(held.direction, self._s)
            return _dot(tangent, allowed)

        return max(cands, key=entering)

    def _hold_move(self, seg: Segment, info: _Held) -> None:
        self._queue = [seg]
        self._held = info
        self._tool = seg.end

    def _release(self, end: Point, line: int) -> list[object]:
        """Let the held move (and what queued behind it) go, ending at ``end``, checking it for reversal."""
        held = self._held
        if not self._queue or held is None:
            return []
        main = self._queue[0]
        assert isinstance(main, Line2 | Arc2)
        if held.arc:
            assert isinstance(main, Arc2)
            swept = sweep(main.start, main.center, end, main.ccw, main.turns)
            if swept > held.max_sweep + ARC_GOUGE_TOLERANCE:
                raise GCodeError(ARC_GOUGE, line=line)
        else:
            move = _sub(end, main.start)
            if _dot(move, held.ref) < -_LINE_GOUGE_TOLERANCE:
                raise GCodeError(TRAVERSE_GOUGE if held.rapid else FEED_GOUGE, line=line)
        out: list[object] = [replace(main, end=end)]
        for item in self._queue[1:]:
            if isinstance(item, Line2):
                item = replace(item, start=end, end=end)
            out.append(item)
        self._queue = []
        self._held = None
        return out
