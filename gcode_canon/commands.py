"""Canonical machining commands: the interpreter's output and the planner's input.

Every command is an immutable, slotted dataclass that carries the file and line it came from, so a
fault anywhere downstream (planner, drive, I/O) can be reported against the user's source.

Conventions, fixed here because every layer below depends on them:

* Positions are *machine* coordinates with every offset already applied (G5x, G92, tool length,
  rotation). Linear axes (X Y Z U V W) are in millimetres, rotary axes (A B C) in degrees, whatever
  G20/G21 said in the program.
* Feed rates are in mm/min (or deg/min for pure rotary moves) in G94; in G93 the rate is the
  inverse time (1/min) for the move; in G95 it is mm per spindle revolution.
* Arcs stay arcs: an :class:`ArcFeed` carries its centre, the plane normal and the number of turns,
  so the planner can follow the geometry exactly instead of a chain of chords.
* ``NAME`` is the name of the matching LinuxCNC canonical function (``STRAIGHT_FEED`` ...), so the
  output of ``canon check`` can be compared with LinuxCNC's ``rs274`` line by line.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar, NamedTuple

AXES: tuple[str, ...] = ("x", "y", "z", "a", "b", "c", "u", "v", "w")
"""The nine RS274/NGC axes, in parameter order (#5061-5069, #5221-5229 ...)."""

LINEAR_AXES = frozenset("xyzuvw")
ROTARY_AXES = frozenset("abc")


class Pose(NamedTuple):
    """A point in machine coordinates: mm for X Y Z U V W, degrees for A B C."""

    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    a: float = 0.0
    b: float = 0.0
    c: float = 0.0
    u: float = 0.0
    v: float = 0.0
    w: float = 0.0


ORIGIN = Pose()


class Plane(enum.Enum):
    """Active plane; the value is the (first, second, normal) axis indexes into :data:`AXES`."""

    XY = (0, 1, 2)  # G17
    XZ = (2, 0, 1)  # G18: LinuxCNC's ZX plane; first axis Z, second X, normal Y
    YZ = (1, 2, 0)  # G19
    UV = (6, 7, 8)  # G17.1
    WU = (8, 6, 7)  # G18.1
    VW = (7, 8, 6)  # G19.1

    @property
    def gcode(self) -> str:
        return _PLANE_GCODE[self]


_PLANE_GCODE = {
    Plane.XY: "G17",
    Plane.XZ: "G18",
    Plane.YZ: "G19",
    Plane.UV: "G17.1",
    Plane.WU: "G18.1",
    Plane.VW: "G19.1",
}


class FeedMode(enum.Enum):
    INVERSE_TIME = 93
    UNITS_PER_MINUTE = 94
    UNITS_PER_REV = 95


class MotionControlMode(enum.Enum):
    EXACT_STOP = 9  # G9, one block (emitted as EXACT_STOP around that block)
    EXACT_PATH = 611  # G61
    EXACT_STOP_MODAL = 6110  # G61.1
    CONTINUOUS = 64  # G64


class SpindleDirection(enum.Enum):
    CW = 3
    CCW = 4


class InputKind(enum.Enum):
    DIGITAL = "digital"
    ANALOG = "analog"


class WaitMode(enum.IntEnum):
    """M66 L modes."""

    IMMEDIATE = 0
    RISE = 1
    FALL = 2
    HIGH = 3
    LOW = 4


class ProbeMode(enum.Enum):
    """G38.2 .. G38.5: direction and whether a missing trip is an error."""

    TOWARD_ERROR = "38.2"
    TOWARD = "38.3"
    AWAY_ERROR = "38.4"
    AWAY = "38.5"

    @property
    def toward(self) -> bool:
        return self in (ProbeMode.TOWARD_ERROR, ProbeMode.TOWARD)

    @property
    def error_on_miss(self) -> bool:
        return self in (ProbeMode.TOWARD_ERROR, ProbeMode.AWAY_ERROR)


@dataclass(frozen=True, slots=True)
class Canon:
    """Base of every canonical command: where it came from."""

    NAME: ClassVar[str] = "CANON"
    MOVES: ClassVar[bool] = False
    SYNC: ClassVar[bool] = False
    """True when the planner must run its queue dry (motion at rest) before the command."""

    file: str = field(default="", kw_only=True)
    line: int = field(default=0, kw_only=True)


# --- motion ---------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class StraightTraverse(Canon):
    """G0: rapid in a straight line at each axis's maximum."""

    NAME: ClassVar[str] = "STRAIGHT_TRAVERSE"
    MOVES: ClassVar[bool] = True
    end: Pose


@dataclass(frozen=True, slots=True)
class StraightFeed(Canon):
    """G1 (and the straight parts of cycles and compensation): straight line at the feed rate."""

    NAME: ClassVar[str] = "STRAIGHT_FEED"
    MOVES: ClassVar[bool] = True
    end: Pose


@dataclass(frozen=True, slots=True)
class ArcFeed(Canon):
    """G2/G3 arc or helix at the feed rate.

    ``center`` is the arc's axis point in machine coordinates (its coordinate along the plane normal is
    the start's). ``turns`` follows LinuxCNC's ``rotation``: positive counter-clockwise seen from the
    positive normal, negative clockwise; ``abs(turns) - 1`` full circles are added (the P word).
    The move along the normal axis (helix) and the other axes are interpolated linearly with the arc
    angle to ``end``.

    ``rotation`` (degrees, counter-clockwise seen from +Z) turns the plane about the machine Z axis: a
    G18/G19 arc in a coordinate system rotated by G10 L2 R lies in the XZ/YZ plane turned with the
    system (LinuxCNC's ARC_FEED turns the plane's axes and normal with the XY rotation). The arc is
    then the axis-plane arc that :meth:`unrotated` gives, turned about Z by ``rotation``. 0 for every
    other arc (a G17 arc stays in the XY plane whatever the rotation).
    """

    NAME: ClassVar[str] = "ARC_FEED"
    MOVES: ClassVar[bool] = True
    end: Pose
    center: Pose
    plane: Plane
    turns: int
    rotation: float = 0.0

    def unrotated(self, start: Pose) -> tuple[Pose, Pose, Pose]:
        """``start``, ``end`` and ``center`` turned about machine Z by ``-rotation``: there the arc
        lies in its axis plane ``plane`` (as every arc with ``rotation`` 0)."""
        return (rotate_about_z(start, -self.rotation), rotate_about_z(self.end, -self.rotation),
                rotate_about_z(self.center, -self.rotation))


def rotate_about_z(p: Pose, degrees: float) -> Pose:
    """``p`` with X and Y turned about machine Z by ``degrees`` (counter-clockwise seen from +Z)."""
    if degrees == 0.0:
        return p
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return p._replace(x=p.x * c - p.y * s, y=p.x * s + p.y * c)


@dataclass(frozen=True, slots=True)
class RigidTap(Canon):
    """G33.1: tap from the current position to ``end`` at ``pitch`` per spindle revolution, reverse the
    spindle there and come back out (``scale`` times the spindle speed, LinuxCNC's I word, at least 1)
    to where it started. Issued between :class:`SpindleSync` and :class:`SpindleSyncStop`."""

    NAME: ClassVar[str] = "RIGID_TAP"
    MOVES: ClassVar[bool] = True
    end: Pose
    scale: float = 1.0


@dataclass(frozen=True, slots=True)
class SpindleSync(Canon):
    """The moves that follow are synchronized to the spindle: ``pitch`` program-independent machine
    units of travel per spindle revolution (G33 K, G33.1 K, G76 P), until :class:`SpindleSyncStop`.
    ``velocity_mode``: LinuxCNC's velocity (not position) synchronization, unused by the interpreter."""

    NAME: ClassVar[str] = "START_SPEED_FEED_SYNCH"
    pitch: float
    velocity_mode: bool = False


@dataclass(frozen=True, slots=True)
class SpindleSyncStop(Canon):
    """End of spindle-synchronized motion (G33, G33.1, a G76 pass): feed moves use F again."""

    NAME: ClassVar[str] = "STOP_SPEED_FEED_SYNCH"


@dataclass(frozen=True, slots=True)
class Probe(Canon):
    """G38.x straight probe toward ``end``. The machine answers through the interpreter's callback."""

    NAME: ClassVar[str] = "STRAIGHT_PROBE"
    MOVES: ClassVar[bool] = True
    SYNC: ClassVar[bool] = True
    end: Pose
    mode: ProbeMode


@dataclass(frozen=True, slots=True)
class Dwell(Canon):
    """G4 (and canned-cycle dwells): motion stops, then waits ``seconds``."""

    NAME: ClassVar[str] = "DWELL"
    SYNC: ClassVar[bool] = True
    seconds: float


# --- feed and path control ------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class SetFeedRate(Canon):
    NAME: ClassVar[str] = "SET_FEED_RATE"
    rate: float


@dataclass(frozen=True, slots=True)
class SetFeedMode(Canon):
    NAME: ClassVar[str] = "SET_FEED_MODE"
    mode: FeedMode


@dataclass(frozen=True, slots=True)
class SetMotionControlMode(Canon):
    """G61/G61.1/G64: ``tolerance`` is G64 P (blend tolerance, mm; 0 = as fast as possible),
    ``naive_cam_tolerance`` is G64 Q."""

    NAME: ClassVar[str] = "SET_MOTION_CONTROL_MODE"
    mode: MotionControlMode
    tolerance: float = 0.0
    naive_cam_tolerance: float = 0.0
    planner: int = -1
    """G64 R (LinuxCNC master's planner dial): -1 unchanged (no R), 0 trapezoidal (R <= 0), 1 smooth."""
    peak_scale: float = -1.0
    """G64 R in (0, 1] (clamped to 0.1..1): the smooth planner's cornering aggressiveness; -1 unchanged."""


@dataclass(frozen=True, slots=True)
class ExactStopBlock(Canon):
    """G9: the move that follows ends at rest exactly on its end point (non-modal)."""

    NAME: ClassVar[str] = "EXACT_STOP_BLOCK"


@dataclass(frozen=True, slots=True)
class SelectPlane(Canon):
    NAME: ClassVar[str] = "SELECT_PLANE"
    plane: Plane


@dataclass(frozen=True, slots=True)
class UseLengthUnits(Canon):
    """Informational (positions are always mm): the program switched G20/G21."""

    NAME: ClassVar[str] = "USE_LENGTH_UNITS"
    metric: bool


@dataclass(frozen=True, slots=True)
class SetG5xOffset(Canon):
    """Informational: the active work offset (``index`` 1..9 for G54..G59.3) in mm/deg."""

    NAME: ClassVar[str] = "SET_G5X_OFFSET"
    index: int
    offset: Pose
    rotation: float = 0.0


@dataclass(frozen=True, slots=True)
class SetG92Offset(Canon):
    NAME: ClassVar[str] = "SET_G92_OFFSET"
    offset: Pose


@dataclass(frozen=True, slots=True)
class UseToolLengthOffset(Canon):
    NAME: ClassVar[str] = "USE_TOOL_LENGTH_OFFSET"
    offset: Pose


# --- spindle, coolant, tools, overrides -----------------------------------------------------------


@dataclass(frozen=True, slots=True)
class SetSpindleSpeed(Canon):
    """The S word. In constant surface speed (:class:`SetSpindleMode` with ``css_max`` > 0) it is
    the program's surface speed number (m/min in G21, ft/min in G20), as LinuxCNC passes it on; the
    spindle's speed then follows :class:`SetSpindleMode`."""

    NAME: ClassVar[str] = "SET_SPINDLE_SPEED"
    rpm: float


@dataclass(frozen=True, slots=True)
class SetSpindleMode(Canon):
    """G96/G97 (LinuxCNC ``SET_SPINDLE_MODE``). ``css_max`` 0: constant speed (G97), the S word in
    rpm. Otherwise constant surface speed (G96): the spindle turns at ``surface / (2 pi r)`` rpm, r
    the distance of the machine X position from ``x_centre`` (mm), at most ``css_max`` rpm (the D
    word; 1e30 without one, as LinuxCNC). ``surface`` in mm of surface per minute. Issued again when
    the S word or the X offsets change while G96 is in force (LinuxCNC resends its speed then)."""

    NAME: ClassVar[str] = "SET_SPINDLE_MODE"
    css_max: float
    surface: float = 0.0
    x_centre: float = 0.0


@dataclass(frozen=True, slots=True)
class SpindleOn(Canon):
    """M3/M4: starts the spindle; the planner treats a start as a sync point (spindle up to speed)."""

    NAME: ClassVar[str] = "START_SPINDLE"
    SYNC: ClassVar[bool] = True
    direction: SpindleDirection
    rpm: float


@dataclass(frozen=True, slots=True)
class SpindleOff(Canon):
    NAME: ClassVar[str] = "STOP_SPINDLE_TURNING"
    SYNC: ClassVar[bool] = True


@dataclass(frozen=True, slots=True)
class SpindleOrient(Canon):
    """M19 (and G87's two stops): motion stops, then the spindle stops at ``angle`` degrees.

    ``direction`` is M19's P: 0 the shortest way, 1 clockwise (as M3), 2 counter-clockwise (as M4).
    ``timeout`` is M19's Q: seconds the machine may take to report the spindle oriented before it is
    a fault; 0.0 means no wait was asked for (LinuxCNC: M19 without Q, and G87). The spindle is not
    turning afterwards (M3/M4 starts it again).
    """

    NAME: ClassVar[str] = "ORIENT_SPINDLE"
    SYNC: ClassVar[bool] = True
    angle: float
    direction: int = 0
    timeout: float = 0.0


@dataclass(frozen=True, slots=True)
class Coolant(Canon):
    """M7 (mist on), M8 (flood on), M9 (both off): the state of both after the command."""

    NAME: ClassVar[str] = "COOLANT"
    mist: bool
    flood: bool


@dataclass(frozen=True, slots=True)
class SelectTool(Canon):
    """T word: prepare tool ``tool`` (pocket chosen by the tool table)."""

    NAME: ClassVar[str] = "SELECT_TOOL"
    tool: int


@dataclass(frozen=True, slots=True)
class ToolChange(Canon):
    """M6: change to the selected tool; motion stops first."""

    NAME: ClassVar[str] = "CHANGE_TOOL"
    SYNC: ClassVar[bool] = True
    tool: int


@dataclass(frozen=True, slots=True)
class SetToolNumber(Canon):
    """M61 Q: declare the tool in the spindle without a change."""

    NAME: ClassVar[str] = "SET_TOOL_NUMBER"
    tool: int


@dataclass(frozen=True, slots=True)
class SetOverrides(Canon):
    """M48-M53: which operator overrides are allowed (None = unchanged)."""

    NAME: ClassVar[str] = "SET_OVERRIDES"
    feed: bool | None = None
    spindle: bool | None = None
    adaptive_feed: bool | None = None
    feed_hold: bool | None = None


# --- I/O ------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class DigitalOutput(Canon):
    """M62/M63 (``synced``: changes when the next motion starts) and M64/M65 (at once)."""

    NAME: ClassVar[str] = "SET_DIGITAL_OUTPUT"
    index: int
    on: bool
    synced: bool


@dataclass(frozen=True, slots=True)
class AnalogOutput(Canon):
    """M67 (``synced``) and M68 (at once) analog output ``index`` to ``value``."""

    NAME: ClassVar[str] = "SET_ANALOG_OUTPUT"
    index: int
    value: float
    synced: bool


@dataclass(frozen=True, slots=True)
class WaitInput(Canon):
    """M66: motion finishes, then input ``index`` is read (or waited for, up to ``timeout`` s).
    The value goes to #5399 through the interpreter's machine callback (-1 on timeout)."""

    NAME: ClassVar[str] = "WAIT_INPUT"
    SYNC: ClassVar[bool] = True
    kind: InputKind
    index: int
    mode: WaitMode
    timeout: float


@dataclass(frozen=True, slots=True)
class UserMCode(Canon):
    """M100-M199, accepted only when the machine binds the code (``InterpreterSettings.user_mcodes``):
    motion stops, the machine sets the code's outputs and waits for its input, then the program goes
    on. ``p`` and ``q`` are the line's P and Q words (None when absent), as LinuxCNC passes them."""

    NAME: ClassVar[str] = "USER_M_CODE"
    SYNC: ClassVar[bool] = True
    code: int
    p: float | None = None
    q: float | None = None


# --- program flow and messages --------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Message(Canon):
    """(MSG,...) and (DEBUG,...): text for the operator."""

    NAME: ClassVar[str] = "MESSAGE"
    text: str
    debug: bool = False


@dataclass(frozen=True, slots=True)
class Comment(Canon):
    NAME: ClassVar[str] = "COMMENT"
    text: str


@dataclass(frozen=True, slots=True)
class ProgramStop(Canon):
    """M0 (``optional`` False) and M1 (True): motion stops and the program pauses."""

    NAME: ClassVar[str] = "PROGRAM_STOP"
    SYNC: ClassVar[bool] = True
    optional: bool = False


@dataclass(frozen=True, slots=True)
class PalletShuttle(Canon):
    """M60: exchange pallets, then pause."""

    NAME: ClassVar[str] = "PALLET_SHUTTLE"
    SYNC: ClassVar[bool] = True


@dataclass(frozen=True, slots=True)
class ProgramEnd(Canon):
    """M2 / M30 (``rewind``), or the closing ``%``: motion finishes, the program is over."""

    NAME: ClassVar[str] = "PROGRAM_END"
    SYNC: ClassVar[bool] = True
    rewind: bool = False


MOTION_TYPES: tuple[type[Canon], ...] = (StraightTraverse, StraightFeed, ArcFeed, Probe)


def slot_setters(cls: type[Canon]) -> tuple[Callable[[Canon, Any], None], ...]:
    """The functions that set each slot of a ``cls`` object (its member descriptors' ``__set__``),
    in the order of its fields with ``file`` and ``line`` last: ``object.__new__(cls)`` and these make
    the object ``cls(...)`` makes (no ``__post_init__`` here), as :func:`_maker`'s constructors do,
    and as the fast paths do it themselves where a call more per command counts."""
    import dataclasses

    names = [f.name for f in dataclasses.fields(cls) if f.name not in ("file", "line")] + ["file", "line"]
    return tuple(getattr(cls, name).__set__ for name in names)


def _maker(cls: type[Canon]):
    """A constructor of ``cls`` taking every field positionally, ``file`` and ``line`` last, that sets
    the slots directly: the frozen dataclass ``__init__`` (keyword arguments, ``object.__setattr__``
    per field) costs a microsecond or more per command, and the interpreter makes one per move. The
    object is the one ``cls(...)`` makes (no ``__post_init__`` here)."""
    setters = slot_setters(cls)
    new = object.__new__
    if len(setters) == 3:
        s0, s1, s2 = setters

        def make3(a, file, line):
            obj = new(cls)
            s0(obj, a)
            s1(obj, file)
            s2(obj, line)
            return obj

        return make3
    assert len(setters) == 7
    s0, s1, s2, s3, s4, s5, s6 = setters

    def make7(a, b, c, d, e, file, line):
        obj = new(cls)
        s0(obj, a)
        s1(obj, b)
        s2(obj, c)
        s3(obj, d)
        s4(obj, e)
        s5(obj, file)
        s6(obj, line)
        return obj

    return make7


new_straight_feed = _maker(StraightFeed)
"""``StraightFeed(end, file=file, line=line)``, faster: ``new_straight_feed(end, file, line)``."""
new_straight_traverse = _maker(StraightTraverse)
new_comment = _maker(Comment)
new_arc_feed = _maker(ArcFeed)
"""``ArcFeed(end, center, plane, turns, rotation, file=file, line=line)``, every argument given."""
