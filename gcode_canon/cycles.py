"""Canned cycles (G73, G74, G81-G89; G76 in threading_cycle) as a pure expansion into plane-local operations.

Why a separate, pure module: the cycles are the densest set of rules in RS274/NGC (sticky words,
the G98 "initial level" that outlives a block, incremental R and Z, L repeats, the preliminary
moves) and LinuxCNC keeps them apart too (``interp_cycles.cc``). Here they are one function with
no knowledge of the interpreter: the interpreter hands in the block's words, the current position
and the modal state, and gets back a list of :class:`CycleOp` plus the new sticky state. It then
turns each op into canonical commands in machine coordinates.

Coordinates are *plane-local* triples ``(first, second, normal)`` in PROGRAM units of the current
coordinate system, following :class:`~gcode_canon.commands.Plane`'s axis indexes: G17 ``(x, y, z)``,
G18 ``(z, x, y)``, G19 ``(y, z, x)``, G17.1 ``(u, v, w)``, G18.1 ``(w, u, v)``, G19.1 ``(v, w, u)``.
The drill axis is always ``normal``; I/J/K map onto the plane the same way as X/Y/Z
(:func:`offset_letters`). One implementation therefore serves all six planes.

Interface for the interpreter
-----------------------------

::

    state = CycleState()                                   # once per program (LinuxCNC: at reset)
    ...
    words = CycleWords.from_letters(plane, {"x": 1.0, "z": -5.0, "r": 2.0, "l": 3})  # block words
    ctx = CycleContext(plane=..., incremental=G91, retract_mode=98 or 99, feed_rate=F,
                       inverse_time=G93, cutter_comp=G41/G42 on, spindle=SpindleDirection|None,
                       metric=G21)
    result = expand_cycle(810, words, state, ctx, start=to_local(plane, current_program_position))
    state = result.state          # keep it (sticky R/Z/Q/P/IJK, initial level, cycle in effect)
    for op in result.ops: ...     # see CycleOp for the mapping to canonical commands
    current_program_position = from_local(plane, result.end, current_program_position)

    state = cancel(state)         # whenever the motion mode leaves the cycles (G80, G0-G3, G33,
                                  # G38.x, G76 ...): forgets the cycle in effect and the G98 level

``expand_cycle`` raises only :class:`~gcode_canon.errors.GCodeError` (without file/line: the caller
fills them in with ``located``); on error nothing is emitted and the state is unchanged, so the
interpreter keeps the old one. Other axis letters present in the block (A B C, or U V W in an XYZ
plane) go in ``CycleWords.extra_axes`` and are refused as LinuxCNC does.

Op kinds (``CycleOp.kind``) and the canonical commands they stand for:

* ``traverse`` / ``feed``: ``StraightTraverse`` / ``StraightFeed`` to ``point``; the other axes
  (rotary, the other plane family) stay where they are.
* ``dwell``: ``Dwell(seconds)`` (emitted even for 0 s, as LinuxCNC does).
* ``spindle_stop``: ``SpindleOff``. ``spindle_on``: ``SpindleOn(direction, current rpm)``.
  In G74/G84 the reversal at the bottom should not wait for "at speed" (LinuxCNC's comment says
  so), the restore at the end may.
* ``orient``: spindle orientation to angle 0 (LinuxCNC ``ORIENT_SPINDLE``; G87 only); ``direction``
  is the way the spindle was turning. The interpreter emits ``SpindleOrient(0, P, 0)`` with M19's P
  for that direction (1 for M3, 2 for M4).
* ``program_stop``: ``ProgramStop`` (G88: the operator retracts by hand).
* ``overrides_off`` / ``overrides_restore``: around each G74/G84 hole, feed and spindle overrides
  are disabled (``SetOverrides(feed=False, spindle=False)``) then put back as they were.
* ``exact_path_begin`` / ``exact_path_end``: LinuxCNC switches to G61 (exact path) for the cycle
  and restores the previous mode after; emit ``SetMotionControlMode(EXACT_PATH)`` if not already
  in it, and the saved mode at the end.

Behaviour (LinuxCNC master as of 2026: ``interp_cycles.cc`` and the G-code manual), with deliberate
departures marked *canon*:

* Preliminary motion: if the drill-axis position is below R, rapid straight up to R at the current
  in-plane position (once, whatever L). Then for every hole: rapid in the plane to the hole (at the
  current level on the first hole if above R, else at the clear level), rapid down to R, the hole,
  retract to the clear level: R in G99, in G98 the *initial level* (the drill-axis position when
  this series of cycles began, raised to R if lower). The initial level survives consecutive
  cycle blocks, even when the cycle code changes, until :func:`cancel`.
  *canon*: LinuxCNC tests "below R" against the initial level, not the current position; the two
  only differ in a series whose R changes between blocks, where LinuxCNC can make a slanted rapid
  up from below the new R. The documented rule (current position) is used here.
* G91: the hole position is the start plus the X/Y increment, and each L repeat adds it again.
  R is relative to the *initial level* (so consecutive G91 blocks keep the same R plane, as in
  LinuxCNC's source; the manual says "current position", identical on the first block), Z is
  relative to R. G90: L>1 drills the same hole L times.
* Sticky: R, Z (as written: an increment in G91), and the cycle's Q / P / I J K are required on
  the first block of a cycle code and reused by the following blocks of the same code. P for
  G74/G84 is optional (the last P, initially 0). L is not sticky (default 1).
* G73: peck by Q, rapid back up by the peck clearance; G83: peck by Q, rapid out to R, rapid back
  down to the peck clearance above the last depth. The clearance is the D word, else
  ``CycleContext.g73_peck_clearance`` / ``g83_peck_clearance``, else LinuxCNC's built-in default for
  a metric machine: 1 in the program's units (LinuxCNC chooses 0.050 or 1 by the machine's units at
  start-up and never converts it, so a G20 program on a metric machine pecks back 1 inch; the manual
  says 0.010 in / 0.254 mm).
  *canon*: a negative D is refused (it would rapid below the cut depth); peck depths are
  ``R - k*Q`` (no accumulated rounding) and one within rounding of Z is merged into the last feed.
* G74/G84 (floating-chuck tapping, not synchronised in LinuxCNC either): feed in, spindle stop,
  start reversed, dwell P, feed out to the clear level, spindle stop, start in the original
  direction. G84 needs the spindle turning clockwise, G74 counter-clockwise. *canon*: in G18/G19
  LinuxCNC passes the coordinates in the wrong order to its feed moves (the tap feeds along the
  wrong axis, visible in its tests/interp/g84/g18 expected output); the correct geometry is used.
* G85 feed out to R then rapid to clear; G86 dwell, spindle stop, rapid out, spindle restart;
  G87 back bore (offset I/J in the plane, K the top of the counterbore, absolute in G90, from the
  bottom in G91); G88 dwell, spindle stop, program stop, spindle restart (LinuxCNC then assumes
  the tool is at the clear level, and so does :attr:`CycleResult.end`); G89 dwell, feed out.
  *canon*: G87 K must lie between Z and R (LinuxCNC does not check), so no feed leaves the hole.
* *canon*: moves to the point the tool is already at are not emitted (LinuxCNC emits a few such
  zero-length rapids, e.g. G85's rapid to clear in G99).
* G76 (threading) is not a canned cycle here: :mod:`gcode_canon.threading_cycle` expands it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

from gcode_canon.commands import AXES, Plane, Pose, SpindleDirection
from gcode_canon.errors import GCodeError

Local = tuple[float, float, float]
"""A plane-local point ``(first, second, normal)`` in program units."""

OpKind = Literal[
    "traverse",
    "feed",
    "dwell",
    "spindle_stop",
    "spindle_on",
    "orient",
    "program_stop",
    "overrides_off",
    "overrides_restore",
    "exact_path_begin",
    "exact_path_end",
]

CYCLE_CODES: frozenset[int] = frozenset((730, 740, 810, 820, 830, 840, 850, 860, 870, 880, 890))
"""The canned cycles this module expands, as G code times ten (G81 -> 810), like ``modal``."""

MAX_OPS = 100_000
"""Refuse a cycle that would expand to more operations than this (tiny Q, huge L)."""

DEFAULT_PECK_CLEARANCE_MM = 1.0
DEFAULT_PECK_CLEARANCE_INCH = 0.050

_PLANE_NAMES = {
    Plane.XY: "XY",
    Plane.XZ: "XZ",
    Plane.YZ: "YZ",
    Plane.UV: "UV",
    Plane.WU: "UW",
    Plane.VW: "VW",
}
_ROTARY = ("a", "b", "c")


@dataclass(frozen=True, slots=True)
class CycleOp:
    """One step of an expanded cycle. ``point`` is set for traverse/feed only (plane-local, program
    units); ``seconds`` for dwell; ``direction`` for spindle_on and orient."""

    kind: OpKind
    point: Local | None = None
    seconds: float = 0.0
    direction: SpindleDirection | None = None


@dataclass(frozen=True, slots=True)
class CycleWords:
    """The words of the block that matter to a cycle, already mapped onto the plane.

    ``first``/``second``/``normal`` are the axis words (X/Y/Z in G17, Z/X/Y in G18 ...), ``None`` when
    absent; ``offset_*`` the I/J/K words mapped the same way (G87 only). ``l`` may be a float as read
    (it must be a whole number). ``extra_axes`` are the other axis letters present in the block.
    """

    first: float | None = None
    second: float | None = None
    normal: float | None = None
    r: float | None = None
    q: float | None = None
    p: float | None = None
    l: float | None = None  # noqa: E741 - the G-code letter
    d: float | None = None
    offset_first: float | None = None
    offset_second: float | None = None
    offset_normal: float | None = None
    extra_axes: frozenset[str] = field(default_factory=frozenset)
    polar_radius: float | None = None  # @ (G17 only, checked by the interpreter)
    polar_angle: float | None = None  # ^ in degrees

    @classmethod
    def from_letters(cls, plane: Plane, words: Mapping[str, float]) -> CycleWords:
        """Build from a block's ``{letter: value}`` (any case), mapping axes and I/J/K onto ``plane``."""
        lower = {k.lower(): v for k, v in words.items()}
        first, second, normal = plane_axes(plane)
        oi, oj, ok = offset_letters(plane)
        extra = frozenset(a for a in AXES if a in lower and a not in (first, second, normal))
        return cls(
            first=lower.get(first),
            second=lower.get(second),
            normal=lower.get(normal),
            r=lower.get("r"),
            q=lower.get("q"),
            p=lower.get("p"),
            l=lower.get("l"),
            d=lower.get("d"),
            offset_first=lower.get(oi),
            offset_second=lower.get(oj),
            offset_normal=lower.get(ok),
            extra_axes=extra,
            polar_radius=lower.get("@"),
            polar_angle=lower.get("^"),
        )


@dataclass(frozen=True, slots=True)
class CycleContext:
    """The modal state a cycle reads (never changes).

    ``retract_mode`` is 98 (back to the initial level) or 99 (back to R). ``spindle`` is the active
    spindle's direction, ``None`` when stopped. ``metric`` is the program's units (G21), used only for
    the default peck clearance. Peck clearances are in program units; ``None`` = built-in default.
    """

    plane: Plane = Plane.XY
    incremental: bool = False
    retract_mode: int = 98
    feed_rate: float = 0.0
    inverse_time: bool = False
    cutter_comp: bool = False
    spindle: SpindleDirection | None = None
    metric: bool = True
    g73_peck_clearance: float | None = None
    g83_peck_clearance: float | None = None


@dataclass(frozen=True, slots=True)
class CycleState:
    """Sticky values carried from one cycle block to the next (LinuxCNC's ``cycle_*`` settings).

    ``motion`` is the cycle code (times ten) in effect, ``None`` outside a series of cycles;
    ``initial_level`` the drill-axis position when the series began (the G98 level before raising to
    R), ``None`` outside a series. ``normal`` is the last Z (drill-axis) word as written.
    """

    motion: int | None = None
    initial_level: float | None = None
    normal: float = 0.0
    r: float = 0.0
    q: float = 0.0
    p: float = 0.0
    offsets: Local = (0.0, 0.0, 0.0)


@dataclass(frozen=True, slots=True)
class CycleResult:
    ops: tuple[CycleOp, ...]
    state: CycleState
    end: Local
    """Where the interpreter should consider the tool afterwards (last hole, clear level)."""


def cancel(state: CycleState) -> CycleState:
    """The motion mode left the cycles: forget the cycle in effect and the G98 initial level.

    The sticky numbers themselves are kept (LinuxCNC does too), but with ``motion`` cleared the next
    cycle requires them again.
    """
    return replace(state, motion=None, initial_level=None)


def plane_axes(plane: Plane) -> tuple[str, str, str]:
    """Axis letters (lower case) of ``plane``'s (first, second, normal)."""
    first, second, normal = plane.value
    return AXES[first], AXES[second], AXES[normal]


def offset_letters(plane: Plane) -> tuple[str, str, str]:
    """The I/J/K letters that go with ``plane``'s (first, second, normal): I goes with X and U ..."""
    first, second, normal = plane.value
    return "ijk"[first % 3], "ijk"[second % 3], "ijk"[normal % 3]


def to_local(plane: Plane, values: Sequence[float]) -> Local:
    """The plane-local triple of a nine-axis position (indexed as :data:`AXES`, e.g. a Pose)."""
    first, second, normal = plane.value
    return (float(values[first]), float(values[second]), float(values[normal]))


def from_local(plane: Plane, local: Local, base: Pose) -> Pose:
    """``base`` with the plane's three axes replaced by ``local``."""
    values = list(base)
    for index, value in zip(plane.value, local, strict=True):
        values[index] = value
    return Pose(*values)


def _code_number(code: int | str) -> int:
    if isinstance(code, str):
        text = code.strip().upper().removeprefix("G")
        try:
            number = float(text)
        except ValueError:
            raise GCodeError(f"{code!r} is not a G code") from None
        return round(number * 10)
    return int(code)


def _gname(code10: int) -> str:
    return f"G{code10 // 10}" if code10 % 10 == 0 else f"G{code10 // 10}.{code10 % 10}"


def _finite(name: str, value: float | None) -> None:
    if value is not None and not math.isfinite(value):
        raise GCodeError(f"{name} word is not a finite number")


def _repeats(l_word: float | None) -> int:
    if l_word is None:
        return 1
    _finite("L", l_word)
    count = math.floor(l_word)
    fraction = l_word - count
    if fraction > 0.9999:
        count += 1
    elif fraction > 0.0001:
        raise GCodeError(f"L word must be a whole number of repeats, not {l_word:g}")
    if count < 0:
        raise GCodeError("Negative L word used")
    if count == 0:
        raise GCodeError("Cannot do zero repeats of cycle")
    return count


class _Emitter:
    """Collects ops, dropping moves to where the tool already is."""

    def __init__(self, start: Local) -> None:
        self.ops: list[CycleOp] = []
        self.pos: Local | None = start

    def move(self, kind: Literal["traverse", "feed"], point: Local) -> None:
        if point == self.pos:
            return
        self.ops.append(CycleOp(kind, point))
        self.pos = point

    def op(self, kind: OpKind, **kw: object) -> None:
        self.ops.append(CycleOp(kind, **kw))  # type: ignore[arg-type]


def expand_cycle(
    code: int | str,
    words: CycleWords,
    state: CycleState,
    ctx: CycleContext,
    start: Local,
) -> CycleResult:
    """Expand one block of canned cycle ``code`` (810 or "G81" ...) started at ``start``.

    See the module docstring for the conventions. Raises :class:`GCodeError` for every bad input.
    """
    code10 = _code_number(code)
    name = _gname(code10)
    if code10 not in CYCLE_CODES:
        raise GCodeError(f"{name} is not a canned cycle")
    plane = ctx.plane
    plane_name = _PLANE_NAMES[plane]
    first_axis, second_axis, normal_axis = (a.upper() for a in plane_axes(plane))

    # --- checks in LinuxCNC's order (convert_cycle, then convert_cycle_xy and the cycle itself)
    if not all(math.isfinite(v) for v in start):
        raise GCodeError(f"{name}: current position is not finite")
    for letter, value in (
        (first_axis, words.first),
        (second_axis, words.second),
        (normal_axis, words.normal),
        ("R", words.r),
        ("Q", words.q),
        ("P", words.p),
        ("D", words.d),
        *zip(
            (letter.upper() for letter in offset_letters(plane)),
            (words.offset_first, words.offset_second, words.offset_normal),
            strict=True,
        ),
    ):
        _finite(letter, value)
    if ctx.feed_rate == 0.0:
        raise GCodeError("Cannot feed with zero feed rate")
    if ctx.inverse_time:
        raise GCodeError("Cannot use inverse time feed with canned cycles")
    if ctx.cutter_comp:
        raise GCodeError("Cannot use canned cycles with cutter compensation on")
    same = state.motion == code10
    if words.r is not None:
        r_word = words.r
    elif same:
        r_word = state.r
    else:
        raise GCodeError(f"R clearance plane unspecified in cycle ({name} needs an R word)")
    repeats = _repeats(words.l)
    for letter in sorted(words.extra_axes):
        article = "an" if letter in "ax" else "a"
        if letter in _ROTARY:
            raise GCodeError(f"Cannot put {article} {letter.upper()} in canned cycle")
        raise GCodeError(f"Cannot put {article} {letter.upper()} in a canned cycle in the {plane_name} plane")

    if words.normal is None and not same:
        raise GCodeError(f"{normal_axis} value unspecified in {plane_name} plane canned cycle")
    normal_word = words.normal if words.normal is not None else state.normal
    initial = state.initial_level if state.initial_level is not None else start[2]

    polar = words.polar_radius is not None or words.polar_angle is not None
    inc_radius = inc_angle = 0.0
    if ctx.incremental:
        inc_a = words.first if words.first is not None else 0.0
        inc_b = words.second if words.second is not None else 0.0
        hole_a, hole_b = start[0], start[1]
        r_level = r_word + initial
        bottom = r_level + normal_word
        # LinuxCNC's CYCLE_MACRO: each repeat adds @ to the radius and ^ to the angle about the origin
        inc_radius = words.polar_radius or 0.0
        inc_angle = math.radians(words.polar_angle or 0.0)
    else:
        inc_a = inc_b = 0.0
        if polar:  # LinuxCNC convert_cycle_xy: the missing one of @ ^ from the current point
            radius = words.polar_radius if words.polar_radius is not None else math.hypot(start[0], start[1])
            angle = (math.radians(words.polar_angle) if words.polar_angle is not None
                     else math.atan2(start[1], start[0]))
            hole_a, hole_b = radius * math.cos(angle), radius * math.sin(angle)
        else:
            hole_a = words.first if words.first is not None else start[0]
            hole_b = words.second if words.second is not None else start[1]
        r_level = r_word
        bottom = normal_word
    if r_level < bottom:
        raise GCodeError(f"R less than {normal_axis} in cycle in {plane_name} plane")

    # --- per-cycle words
    new_q, new_p, new_offsets = state.q, state.p, state.offsets
    if code10 in (820, 860, 880, 890):
        if words.p is None and not same:
            raise GCodeError(f"Dwell time P word missing with {name}")
        new_p = words.p if words.p is not None else state.p
    elif code10 in (740, 840):
        new_p = words.p if words.p is not None else state.p
    if new_p < 0 and code10 in (740, 820, 840, 860, 880, 890):
        raise GCodeError(f"Negative P word (dwell time) used with {name}")
    if code10 in (730, 830):
        if words.q is None and not same:
            raise GCodeError(f"Q word missing with {name}")
        new_q = words.q if words.q is not None else state.q
        if new_q <= 0.0:
            raise GCodeError("Negative or zero Q value used")
    if code10 == 870:
        given = (words.offset_first, words.offset_second, words.offset_normal)
        if not same:
            for letter, value in zip(offset_letters(plane), given, strict=True):
                if value is None:
                    raise GCodeError(f"{letter.upper()} word missing with G87")
        new_offsets = tuple(  # type: ignore[assignment]
            old if value is None else value for old, value in zip(state.offsets, given, strict=True)
        )
    spindle = ctx.spindle
    if code10 in (860, 870, 880) and spindle is None:
        raise GCodeError(f"Spindle not turning in {name}")
    if code10 in (740, 840):
        if spindle is None:
            raise GCodeError(f"Spindle not turning in {name}")
        if code10 == 840 and spindle is SpindleDirection.CCW:
            raise GCodeError("Spindle turning counterclockwise in G84")
        if code10 == 740 and spindle is SpindleDirection.CW:
            raise GCodeError("Spindle turning clockwise in G74")

    peck = 0.0
    if code10 in (730, 830):
        if words.d is not None:
            peck = words.d
        else:
            configured = ctx.g73_peck_clearance if code10 == 730 else ctx.g83_peck_clearance
            # LinuxCNC picks its default by the machine's units at start-up and uses the bare number
            # in the program's units: canon's machine is metric, so 1 (1 mm in G21, 1 inch in G20)
            peck = configured if configured is not None else DEFAULT_PECK_CLEARANCE_MM
        if peck < 0.0:
            raise GCodeError(f"Negative peck clearance (D word) used with {name}")
    middle = 0.0
    if code10 == 870:
        middle = new_offsets[2] + bottom if ctx.incremental else new_offsets[2]
        if not bottom <= middle <= r_level:
            raise GCodeError(
                f"G87 back-bore top ({offset_letters(plane)[2].upper()} = {middle:g}) must lie between "
                f"the bottom ({normal_axis}{bottom:g}) and R ({r_level:g})"
            )

    pecks = 0
    if code10 in (730, 830) and r_level > bottom:
        ratio = (r_level - bottom) / new_q  # inf for a Q like 5e-324: no integer holds that many pecks
        if not ratio < MAX_OPS:
            raise GCodeError(f"{name} would make more than {MAX_OPS} moves (Q{new_q:g} pecks in a hole "
                             f"{r_level - bottom:g} deep): check Q and L")
        pecks = math.ceil(ratio)
    per_hole = 12 + (3 * pecks)
    if per_hole * repeats > MAX_OPS:
        raise GCodeError(
            f"{name} would make about {per_hole * repeats} moves (more than {MAX_OPS}): check Q and L"
        )

    # --- motion
    out = _Emitter(start)
    current = start[2]
    if current < r_level:
        out.move("traverse", (start[0], start[1], r_level))
        current = r_level
    clear = r_level if ctx.retract_mode == 99 else max(initial, r_level)
    out.op("exact_path_begin")
    for repeat in range(repeats):
        hole_a += inc_a
        hole_b += inc_b
        if inc_radius or inc_angle:
            if hole_a == 0.0 and hole_b == 0.0:
                raise GCodeError("Incremental motion with polar coordinates is indeterminate when at the "
                                 "origin")
            radius = math.hypot(hole_a, hole_b) + inc_radius
            angle = math.atan2(hole_b, hole_a) + inc_angle
            hole_a, hole_b = radius * math.cos(angle), radius * math.sin(angle)
        if repeat == 0 and current > r_level:
            out.move("traverse", (hole_a, hole_b, current))
        else:
            out.move("traverse", (hole_a, hole_b, clear))
        out.move("traverse", (hole_a, hole_b, r_level))
        _hole(
            out,
            code10,
            (hole_a, hole_b),
            r_level,
            clear,
            bottom,
            new_q,
            new_p,
            peck,
            middle,
            new_offsets,
            spindle,
        )
    out.op("exact_path_end")
    if not all(math.isfinite(v) for op in out.ops if op.point for v in op.point):
        raise GCodeError(f"{name}: positions out of range")

    new_state = CycleState(
        motion=code10,
        initial_level=initial,
        normal=normal_word,
        r=r_word,
        q=new_q,
        p=new_p,
        offsets=new_offsets,
    )
    return CycleResult(tuple(out.ops), new_state, (hole_a, hole_b, clear))


def _hole(
    out: _Emitter,
    code10: int,
    hole: tuple[float, float],
    r_level: float,
    clear: float,
    bottom: float,
    q: float,
    p: float,
    peck: float,
    middle: float,
    offsets: Local,
    spindle: SpindleDirection | None,
) -> None:
    """One hole, starting at (hole, R)."""
    a, b = hole

    def at(level: float) -> Local:
        return (a, b, level)

    if code10 in (730, 830):
        tolerance = 1e-9 * max(1.0, abs(r_level), abs(bottom))
        k = 1
        depth = r_level - q
        while depth > bottom + tolerance:
            out.move("feed", at(depth))
            if code10 == 830:
                out.move("traverse", at(r_level))
            out.move("traverse", at(depth + peck))
            k += 1
            depth = r_level - k * q
        out.move("feed", at(bottom))
        out.move("traverse", at(clear))
    elif code10 == 810:
        out.move("feed", at(bottom))
        out.move("traverse", at(clear))
    elif code10 == 820:
        out.move("feed", at(bottom))
        out.op("dwell", seconds=p)
        out.move("traverse", at(clear))
    elif code10 in (740, 840):
        forward = SpindleDirection.CW if code10 == 840 else SpindleDirection.CCW
        reverse = SpindleDirection.CCW if code10 == 840 else SpindleDirection.CW
        out.op("overrides_off")
        out.move("feed", at(bottom))
        out.op("spindle_stop")
        out.op("spindle_on", direction=reverse)
        out.op("dwell", seconds=p)
        out.move("feed", at(clear))
        out.op("spindle_stop")
        out.op("spindle_on", direction=forward)
        out.op("overrides_restore")
    elif code10 == 850:
        out.move("feed", at(bottom))
        out.move("feed", at(r_level))
        out.move("traverse", at(clear))
    elif code10 == 860:
        out.move("feed", at(bottom))
        out.op("dwell", seconds=p)
        out.op("spindle_stop")
        out.move("traverse", at(clear))
        out.op("spindle_on", direction=spindle)
    elif code10 == 870:
        off_a, off_b = a + offsets[0], b + offsets[1]
        out.move("traverse", (off_a, off_b, r_level))
        out.op("spindle_stop")
        out.op("orient", direction=spindle)
        out.move("traverse", (off_a, off_b, bottom))
        out.move("traverse", at(bottom))
        out.op("spindle_on", direction=spindle)
        out.move("feed", at(middle))
        out.move("feed", at(bottom))
        out.op("spindle_stop")
        out.op("orient", direction=spindle)
        out.move("traverse", (off_a, off_b, bottom))
        out.move("traverse", (off_a, off_b, clear))
        out.move("traverse", at(clear))
        out.op("spindle_on", direction=spindle)
    elif code10 == 880:
        out.move("feed", at(bottom))
        out.op("dwell", seconds=p)
        out.op("spindle_stop")
        out.op("program_stop")
        out.pos = None  # the operator moves the tool by hand
        out.op("spindle_on", direction=spindle)
    else:  # 890
        out.move("feed", at(bottom))
        out.op("dwell", seconds=p)
        out.move("feed", at(clear))
