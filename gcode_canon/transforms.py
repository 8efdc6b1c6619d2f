"""Program coordinate transforms (G15/G16 polar, G22/G23 mirror, G50/G51 scaling, G68/G69 rotation)
and the G12/G13 full circle, as pure building blocks for the interpreter core.

Why a separate, pure module: these are the Fanuc-family extensions that gcode-canon (and Haas, Fanuc,
Siemens in ISO mode ...) put on top of RS274/NGC. LinuxCNC has none of them (``Unknown g code used``),
so they must not leak into the LinuxCNC paths of the core: the core asks
:func:`gcode_canon.dialect.resolve` whether a code is accepted, keeps one :class:`ProgramTransform`
per program and runs programmed points through it. Nothing here knows about blocks, words or modal
state; everything is a function of its arguments, immutable, and raises only
:class:`~gcode_canon.errors.GCodeError` (without file/line: the caller fills them in with
``located``) for a user's mistake, ``ValueError`` for a wiring bug (a bad axis letter, a position of
the wrong length).

Coordinates
-----------

All values are in millimetres (degrees for A B C and for every angle) in the *program frame*: the
coordinates the program writes, after G20/G21 conversion and G90/G91 resolution, before any work
offset. Full positions are 9-tuples in :data:`~gcode_canon.commands.AXES` order (the core's
``prog`` list); plane-local points are ``(first, second)`` or ``(first, second, normal)`` on the
plane's axes as :class:`~gcode_canon.commands.Plane` gives them (G17 ``(x, y, z)``, G18 ``(z, x, y)``,
G19 ``(y, z, x)``, G17.1 ``(u, v, w)`` ...), as in :mod:`gcode_canon.cycles` and
:mod:`gcode_canon.cutter_comp`. The transforms are affine, so converting units before or after them
gives the same result as long as centres and points are in the same unit; mm everywhere is simplest.

Order of application (Fanuc's documented order)
-----------------------------------------------

Fanuc (and Siemens' ISO dialect, which copies it) process a programmed point in this order:
programmable mirror image, then scaling, then coordinate rotation ("when a move command is issued,
the scaling is applied first and then the coordinates are rotated"; "processing proceeds from
programmable mirror image to scaling and coordinate rotation in the stated order"). Polar
coordinates (G16) are not a transform of points but a way of *writing* them: they turn the words
into the programmed point before anything else. So, per point::

    words --(G20/G21, G90/G91)--> [G16: polar_target] --> programmed point P   (the core keeps P)
      P --mirror (G22)--> --scale (G51)--> --rotate (G68)--> transformed point T(P)
      T(P) --cutter compensation (G41/G42)--> --G52/G5x/G92 offsets, G10 L2 R, tool length--> machine

The order is fixed, whatever order the program switched the transforms on in: the stored centres are
the ones the program wrote, and each is carried through the stages before its own (the scaling
centre is mirrored, the rotation centre mirrored and scaled, as Fanuc says: "the coordinate value of
the rotation centre will also be scaled, but not the rotation angle"). Consequences, as on Fanuc:
mirroring one in-plane axis swaps G2/G3, swaps G41/G42 and makes a G68 rotation turn the other way
on the machine; a uniform scale about a centre commutes with a rotation about the same centre.

How the core should call it
---------------------------

State: ``self.xform = ProgramTransform()`` at reset (and again at M2/M30, as Fanuc cancels these on
reset), ``self.polar = PolarState()``, ``self.polar_on = False``; keep ``self.prog`` as the
*untransformed* programmed position. Per line, in LinuxCNC's order of execution:

* G17/G18/G19 (plane step): ``self.xform = self.xform.with_plane(plane)``.
* G15/G16: set ``polar_on``. While on, in ``_target`` (after unit conversion, before anything
  else) the plane's first-axis word is the radius and the second-axis word the angle
  (:func:`polar_letters`): ``point, self.polar = polar_target(current, r, a, incremental=G91,
  origin=PolarOrigin.CURRENT if dialect is GCODE_CANON else PolarOrigin.FANUC, state=self.polar)``.
  Words of G10, G52, G53, G92, G22, G51 and G68 blocks are never polar (Fanuc's rule). LinuxCNC's own
  ``@`` ``^`` words are unaffected and stay LinuxCNC's.
* G22 axis words (resolved by the distance mode exactly like a move's target, so ``G91 G22 X10``
  is 10 from the current position, as gcode-canon's example says) / G23:
  ``with_mirror({"x": 10.0})`` / ``cancel_mirror()``.
* G51 (centre words resolved like a target; an omitted centre word is the current programmed
  position, as Haas and Fanuc do; ``P`` uniform or ``I J K`` per axis for X Y Z) / G50:
  ``with_scale(centre9, p or {"x": i, "y": j, "z": k})`` / ``cancel_scale()``.
* G68 (centre words of the active plane's first/second axes, omitted ones = current position; ``R``
  degrees, default 0) / G69: ``with_rotation((c1, c2), r)`` / ``cancel_rotation()``.
* After any of these four change the transform, the machine does not move: re-derive the programmed
  position so that ``new.apply_position(prog') == old.apply_position(prog)``, i.e.
  ``self.prog = list(new.invert_position(old.apply_position(self.prog)))``. (This is what makes
  gcode-canon's G22 example work: after ``G91 G22 X10`` a ``G1 X2`` moves the machine 2 *away* from
  the mirror line.) Refuse these codes while cutter compensation is on, as Fanuc asks.
* Moves: the end point in the program frame is ``target``; the machine end is
  ``frames.to_machine(self.xform.apply_position(target))``, and ``self.prog = target`` as before.
  G53 moves bypass the transforms (machine coordinates).
* Arcs: find the centre from I J K or R in the *untransformed* program frame (``arcs.centre_ijk``
  / ``centre_r``, so all their checks see the program as written), then ``res =
  self.xform.apply_arc(end_local3, centre_local2, clockwise)``; emit the arc with ``res.end``,
  ``res.centre`` and ``res.clockwise`` (the other axes through ``apply_position``). A core that
  prefers to transform the ends first and solve R afterwards scales R with :meth:`scale_radius`.
  Non-uniform in-plane scaling and an arc out of the G68 rotation plane are refused here.
* Cutter compensation works on the *transformed* path (the tool radius is never scaled, as on
  Fanuc): feed it ``apply_point`` results and give it ``self.xform.comp_side(side)``, which swaps
  left/right when the transform mirrors the plane. Canned cycles: expand in the program frame
  (:func:`gcode_canon.cycles.expand_cycle`), then transform each op's point.
* G12/G13: :func:`full_circle` expands at the current programmed position into plane-local moves in
  the program frame; feed each through ``apply_point`` / ``apply_arc`` like any other move.
* Parameters #5420-#5428 (current position) report the untransformed ``prog``, like Fanuc's
  "absolute position" in program coordinates.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

from gcode_canon.commands import AXES, LINEAR_AXES, Plane
from gcode_canon.errors import GCodeError

N_AXES = len(AXES)
_INDEX = {letter: k for k, letter in enumerate(AXES)}

Point = tuple[float, float]
"""A plane-local point ``(first, second)``."""

UNIFORM_TOLERANCE = 1e-9
"""Relative difference below which two in-plane scale factors count as equal (uniform)."""

_NO_MIRROR: tuple[float | None, ...] = (None,) * N_AXES
_ZEROS: tuple[float, ...] = (0.0,) * N_AXES
_ONES: tuple[float, ...] = (1.0,) * N_AXES


def _check_finite(what: str, *values: float) -> None:
    for v in values:
        if not math.isfinite(v):
            raise GCodeError(f"{what} is not a finite number")


def _out_of_range(values: Sequence[float], what: str) -> None:
    if not all(math.isfinite(v) for v in values):
        raise GCodeError(f"Coordinate out of range after {what}")


def cos_sin(degrees: float) -> tuple[float, float]:
    """``(cos, sin)`` of an angle in degrees, exact at multiples of 90 (so ``G16 X1 Y90`` is X0 Y1,
    not X6e-17 Y1)."""
    turn = math.fmod(degrees, 360.0)
    if turn < 0.0:
        turn += 360.0
    exact = {0.0: (1.0, 0.0), 90.0: (0.0, 1.0), 180.0: (-1.0, 0.0), 270.0: (0.0, -1.0), 360.0: (1.0, 0.0)}
    if turn in exact:
        return exact[turn]
    rad = math.radians(turn)
    return math.cos(rad), math.sin(rad)


def _axis_index(letter: str) -> int:
    k = _INDEX.get(letter.lower()) if isinstance(letter, str) else None
    if k is None:
        raise ValueError(f"not an axis letter: {letter!r}")
    return k


# --- G15/G16 polar coordinates --------------------------------------------------------------------


class PolarOrigin(enum.Enum):
    """Where a G16 radius is measured from.

    * ``CURRENT`` (gcode-canon: "X is the radius relative to the current position and Y is the
      angle"): always from the current programmed position, whatever G90/G91 say; the angle is
      absolute (measured from the plane's first axis, counter-clockwise positive).
    * ``FANUC``: G90 measures radius and angle from the program origin of the plane (like LinuxCNC's
      own ``@`` ``^`` words in G90); G91 measures the radius from the current position and adds the
      angle to the last polar angle (Fanuc: "G91 specifies the current position as the origin of the
      polar coordinate system").
    """

    CURRENT = "current"
    FANUC = "fanuc"


@dataclass(frozen=True, slots=True)
class PolarState:
    """The last polar radius and angle (degrees), for omitted words and G91 angles. Reset with G16."""

    radius: float = 0.0
    angle: float = 0.0


def polar_letters(plane: Plane) -> tuple[str, str]:
    """The (radius, angle) word letters in ``plane``: its first and second axes (G17 X Y, G18 Z X,
    G19 Y Z ...), as Fanuc assigns them; gcode-canon's "X radius, Y angle" is the G17 case."""
    first, second, _ = plane.value
    return AXES[first], AXES[second]


def polar_target(
    current: Point,
    radius: float | None,
    angle: float | None,
    *,
    incremental: bool,
    origin: PolarOrigin,
    state: PolarState,
) -> tuple[Point, PolarState]:
    """The programmed plane-local end point of a G16 move, and the new polar state.

    ``current`` is the current programmed (untransformed) position in the plane, ``radius`` and
    ``angle`` the words (mm, degrees) or None when omitted. Omitted words: in ``CURRENT`` mode and in
    ``FANUC`` G91 the last radius / angle is used (registers are sticky in gcode-canon); in ``FANUC``
    G90 the current position's own polar radius / angle about the origin (as LinuxCNC's ``@``/``^``).
    A negative radius points the other way, as on Fanuc.
    """
    _check_finite("Polar coordinate", *current)
    if radius is not None:
        _check_finite("Polar radius", radius)
    if angle is not None:
        _check_finite("Polar angle", angle)
    if origin is PolarOrigin.CURRENT or incremental:
        base = current
        r = state.radius if radius is None else radius
        if origin is PolarOrigin.CURRENT:
            a = state.angle if angle is None else angle
        else:
            a = state.angle + (0.0 if angle is None else angle)
    else:
        base = (0.0, 0.0)
        r = math.hypot(*current) if radius is None else radius
        a = math.degrees(math.atan2(current[1], current[0])) if angle is None else angle
    c, s = cos_sin(a)
    point = (base[0] + r * c, base[1] + r * s)
    _out_of_range(point, "polar conversion")
    return point, PolarState(r, a)


# --- G12/G13 full circle --------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class PlaneMove:
    """One move of an expansion, plane-local in the program frame: ``kind`` is ``"feed"`` (a
    STRAIGHT_FEED to ``end``) or ``"arc"`` (a one-turn ARC_FEED to ``end`` around ``centre``). The
    coordinate along the normal and the other axes stay where they are."""

    kind: str
    end: Point
    centre: Point | None = None
    clockwise: bool = False


def full_circle(
    centre: Point, radius: float | None, clockwise: bool, *, tool_radius: float = 0.0, code: str = ""
) -> list[PlaneMove]:
    """G12 (``clockwise``) / G13: a full circle of ``radius`` (the I word) around ``centre`` (the
    current programmed position: the tool starts at the centre, as on Haas/Fanuc-style controls).

    The expansion is a straight lead-in from the centre along the plane's first axis to
    ``(cx + r, cy)``, one full circle back to that point, and a straight lead-out to the centre, where
    the tool ends. ``r`` is ``radius - tool_radius``: Haas applies the D tool's radius so that the
    *pocket* has the programmed radius (pass 0, the default, to cut on the tool centre line). The lead
    lines are feeds at the current feed rate; the caller adds no traverse.
    """
    name = code or ("G12" if clockwise else "G13")
    if radius is None:
        raise GCodeError(f"{name}: I word (circle radius) missing")
    _check_finite(f"{name} centre", *centre)
    _check_finite(f"{name} radius", radius, tool_radius)
    if radius <= 0.0:
        raise GCodeError(f"{name}: circle radius (I word) must be positive, not {radius:.4f}")
    if tool_radius < 0.0:
        raise GCodeError(f"{name}: negative tool radius {tool_radius:.4f}")
    r = radius - tool_radius
    if r <= 0.0:
        raise GCodeError(f"{name}: circle radius {radius:.4f} is not greater than the tool radius "
                         f"{tool_radius:.4f}")
    cx, cy = float(centre[0]), float(centre[1])
    start = (cx + r, cy)
    _out_of_range(start, name)
    return [
        PlaneMove("feed", start),
        PlaneMove("arc", start, centre=(cx, cy), clockwise=clockwise),
        PlaneMove("feed", (cx, cy)),
    ]


# --- mirror, scale, rotate ------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ArcResult:
    """An arc after the transform: plane-local ``end`` (same length as given), ``centre``
    ``(first, second)``, the new direction, and the factor its radius was scaled by."""

    end: tuple[float, ...]
    centre: Point
    clockwise: bool
    radius_scale: float


def _as_position(values: Sequence[float], what: str) -> tuple[float, ...]:
    if len(values) != N_AXES:
        raise ValueError(f"{what} needs {N_AXES} values (one per axis), got {len(values)}")
    return tuple(float(v) for v in values)


@dataclass(frozen=True, slots=True)
class ProgramTransform:
    """The composed program transform ``T(p) = rotate(scale(mirror(p)))`` (see the module docstring).

    Immutable: every change returns a new object. Fields hold what the program wrote:

    * ``plane``: the active plane (for plane-local points, arcs and compensation side);
    * ``mirror``: per axis (AXES order) the coordinate of the mirror line, or None (G22/G23);
    * ``scale_centre`` / ``scale_factors``: per axis (G51/G50; rotary axes always 1);
    * ``rotation_plane`` / ``rotation_centre`` (plane-local) / ``rotation_angle`` (degrees, positive
      counter-clockwise seen from the plane's positive normal) (G68/G69).
    """

    plane: Plane = Plane.XY
    mirror: tuple[float | None, ...] = _NO_MIRROR
    scale_centre: tuple[float, ...] = _ZEROS
    scale_factors: tuple[float, ...] = _ONES
    rotation_plane: Plane = Plane.XY
    rotation_centre: Point = (0.0, 0.0)
    rotation_angle: float = 0.0
    # Derived (affine form), filled by __post_init__: p -> a*p + b per axis, then the rotation.
    _a: tuple[float, ...] = field(init=False, repr=False, compare=False)
    _b: tuple[float, ...] = field(init=False, repr=False, compare=False)
    _rot: tuple[float, float, float, float] | None = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if {len(self.mirror), len(self.scale_centre), len(self.scale_factors)} != {N_AXES}:
            raise ValueError("mirror, scale_centre and scale_factors need one entry per axis")
        a: list[float] = []
        b: list[float] = []
        for k in range(N_AXES):
            m = self.mirror[k]
            s = self.scale_factors[k]
            c = self.scale_centre[k]
            # mirror: p -> 2m - p; the scaling centre is mirrored too (it is written in the program).
            ma, mb = (-1.0, 2.0 * m) if m is not None else (1.0, 0.0)
            cm = ma * c + mb
            # scale about cm: q -> cm + s (q - cm)
            a.append(s * ma)
            b.append(s * mb + cm * (1.0 - s))
        object.__setattr__(self, "_a", tuple(a))
        object.__setattr__(self, "_b", tuple(b))
        cos, sin = cos_sin(self.rotation_angle)
        if (cos, sin) == (1.0, 0.0):
            rot = None
        else:
            i, j, _ = self.rotation_plane.value
            # The centre goes through mirror and scale like any programmed point.
            qi = a[i] * self.rotation_centre[0] + b[i]
            qj = a[j] * self.rotation_centre[1] + b[j]
            rot = (cos, sin, qi, qj)
        object.__setattr__(self, "_rot", rot)

    # --- state ------------------------------------------------------------------------------------

    @property
    def identity(self) -> bool:
        """True when the transform changes nothing (no mirror, all factors 1, no rotation)."""
        return self._rot is None and all(v == 1.0 for v in self._a) and all(v == 0.0 for v in self._b)

    @property
    def mirrored(self) -> tuple[str, ...]:
        """The mirrored axis letters (G22 in effect)."""
        return tuple(AXES[k] for k, m in enumerate(self.mirror) if m is not None)

    @property
    def scaling(self) -> bool:
        """G51 in effect (some factor is not 1)."""
        return any(v != 1.0 for v in self.scale_factors)

    @property
    def rotating(self) -> bool:
        """G68 in effect with an angle that is not a whole number of turns."""
        return self._rot is not None

    def with_plane(self, plane: Plane) -> ProgramTransform:
        """G17-G19 (and .1): the plane used by plane-local points, arcs and the compensation side. A
        G68 rotation keeps its own plane (arcs in another plane are refused while it is active)."""
        return _replace(self, plane=plane)

    def with_mirror(self, axes: Mapping[str, float]) -> ProgramTransform:
        """G22: mirror each given axis about the given coordinate (program frame, mm or degrees).
        Axes already mirrored and not named keep their mirror; a named one gets the new line."""
        if not axes:
            raise GCodeError("G22 needs at least one axis word (the axes to mirror)")
        mirror = list(self.mirror)
        for letter, value in axes.items():
            k = _axis_index(letter)
            _check_finite(f"G22 {letter.upper()}", value)
            mirror[k] = float(value)
        return _replace(self, mirror=tuple(mirror))

    def cancel_mirror(self, axes: Sequence[str] | None = None) -> ProgramTransform:
        """G23: cancel mirroring (of every axis, or only of ``axes``)."""
        if axes is None:
            return _replace(self, mirror=_NO_MIRROR)
        mirror = list(self.mirror)
        for letter in axes:
            mirror[_axis_index(letter)] = None
        return _replace(self, mirror=tuple(mirror))

    def with_scale(self, centre: Sequence[float], factors: float | Mapping[str, float]) -> ProgramTransform:
        """G51: scale about ``centre`` (a full position, program frame) by ``factors``: one number
        (the P word) for every linear axis, or a mapping axis letter -> factor (I J K give X Y Z;
        axes not named keep 1). A factor may be negative (a mirror image, as on Fanuc) but not zero;
        rotary axes are never scaled."""
        centre_t = _as_position(centre, "G51 centre")
        _check_finite("G51 centre", *centre_t)
        if isinstance(factors, Mapping):
            values = list(_ONES)
            for letter, f in factors.items():
                k = _axis_index(letter)
                if AXES[k] not in LINEAR_AXES:
                    raise GCodeError(f"G51 cannot scale the rotary axis {AXES[k].upper()}")
                values[k] = float(f)
        else:
            values = [float(factors) if AXES[k] in LINEAR_AXES else 1.0 for k in range(N_AXES)]
        for k, f in enumerate(values):
            _check_finite("G51 scale factor", f)
            if f == 0.0:
                raise GCodeError(f"G51 scale factor for {AXES[k].upper()} is zero")
        return _replace(self, scale_centre=centre_t, scale_factors=tuple(values))

    def cancel_scale(self) -> ProgramTransform:
        """G50: no scaling."""
        return _replace(self, scale_centre=_ZEROS, scale_factors=_ONES)

    def with_rotation(
        self, centre: Point, angle: float, *, plane: Plane | None = None, incremental: bool = False
    ) -> ProgramTransform:
        """G68: rotate by ``angle`` degrees (R word; positive counter-clockwise) about ``centre``
        (first, second of ``plane``, default the active plane) in that plane. ``incremental`` adds
        ``angle`` to a rotation already active in the same plane (Fanuc's G91 R option)."""
        plane = self.plane if plane is None else plane
        _check_finite("G68 centre", *centre)
        _check_finite("G68 angle (R word)", angle)
        if incremental and self.rotation_plane is plane:
            angle = self.rotation_angle + angle
        return _replace(self, rotation_plane=plane, rotation_centre=(float(centre[0]), float(centre[1])),
                        rotation_angle=float(angle))

    def cancel_rotation(self) -> ProgramTransform:
        """G69: no rotation."""
        return _replace(self, rotation_centre=(0.0, 0.0), rotation_angle=0.0)

    def cancel_all(self) -> ProgramTransform:
        """Reset (M2/M30, program start): every transform off; the plane is kept."""
        return ProgramTransform(plane=self.plane)

    # --- application ------------------------------------------------------------------------------

    def apply_position(self, position: Sequence[float]) -> tuple[float, ...]:
        """``T(p)`` for a full position (AXES order, program frame)."""
        p = _as_position(position, "position")
        out = [a * v + b for a, v, b in zip(self._a, p, self._b, strict=True)]
        if self._rot is not None:
            cos, sin, qi, qj = self._rot
            i, j, _ = self.rotation_plane.value
            di, dj = out[i] - qi, out[j] - qj
            out[i] = qi + cos * di - sin * dj
            out[j] = qj + sin * di + cos * dj
        _out_of_range(out, "G22/G51/G68 transform")
        return tuple(out)

    def invert_position(self, position: Sequence[float]) -> tuple[float, ...]:
        """``T⁻¹(p)``: the programmed position whose transform is ``p`` (every factor is non-zero, so
        the inverse exists). Used to keep the machine still when the transform changes."""
        out = list(_as_position(position, "position"))
        if self._rot is not None:
            cos, sin, qi, qj = self._rot
            i, j, _ = self.rotation_plane.value
            di, dj = out[i] - qi, out[j] - qj
            out[i] = qi + cos * di + sin * dj
            out[j] = qj - sin * di + cos * dj
        out = [(v - b) / a for a, v, b in zip(self._a, out, self._b, strict=True)]
        _out_of_range(out, "inverse G22/G51/G68 transform")
        return tuple(out)

    def _local_axes(self, plane: Plane, n: int) -> tuple[int, ...]:
        if n not in (2, 3):
            raise ValueError(f"a plane-local point has 2 or 3 coordinates, not {n}")
        axes = plane.value[:n]
        if self._rot is not None:
            ri, rj, _ = self.rotation_plane.value
            if not (ri in axes and rj in axes) and (ri in plane.value or rj in plane.value):
                raise GCodeError(
                    f"A point of the {plane.gcode} plane without its {AXES[plane.value[2]].upper()} "
                    f"coordinate cannot follow the G68 rotation of the {self.rotation_plane.gcode} plane")
        return axes

    def apply_point(self, local: Sequence[float], plane: Plane | None = None) -> tuple[float, ...]:
        """``T`` of a plane-local point ``(first, second)`` or ``(first, second, normal)`` of
        ``plane`` (default the active plane). With a 2-tuple, a G68 rotation of another plane of the
        same axis family needs the normal coordinate: pass a 3-tuple or use :meth:`apply_position`."""
        return self._map_point(local, plane, self.apply_position)

    def invert_point(self, local: Sequence[float], plane: Plane | None = None) -> tuple[float, ...]:
        """``T⁻¹`` of a plane-local point (same rules as :meth:`apply_point`)."""
        return self._map_point(local, plane, self.invert_position)

    def _map_point(self, local: Sequence[float], plane: Plane | None,
                   mapping: Callable[[Sequence[float]], Sequence[float]]) -> tuple[float, ...]:
        """Lift a plane-local point to nine axes (zeros elsewhere), map it, and project it back."""
        plane = self.plane if plane is None else plane
        axes = self._local_axes(plane, len(local))
        full = [0.0] * N_AXES
        for k, v in zip(axes, local, strict=True):
            full[k] = float(v)
        _check_finite("Coordinate", *full)
        out = mapping(full)
        return tuple(out[k] for k in axes)

    def flips(self, plane: Plane | None = None) -> bool:
        """True when the transform reverses orientation in ``plane`` (an odd number of its two axes
        mirrored or negatively scaled): G2/G3 swap and G41/G42 swap."""
        plane = self.plane if plane is None else plane
        i, j, _ = plane.value
        return (self._a[i] < 0.0) != (self._a[j] < 0.0)

    def arc_clockwise(self, clockwise: bool, plane: Plane | None = None) -> bool:
        """The direction a G2 (True) / G3 (False) arc in ``plane`` has after the transform."""
        return clockwise != self.flips(plane)

    def comp_side(self, side: str, plane: Plane | None = None) -> str:
        """The cutter compensation side (``"left"`` / ``"right"``) to use on the transformed path."""
        if side not in ("left", "right"):
            raise ValueError(f"side must be 'left' or 'right', not {side!r}")
        if self.flips(plane):
            return "right" if side == "left" else "left"
        return side

    def radius_factor(self, plane: Plane | None = None) -> float:
        """The factor an arc radius in ``plane`` is scaled by; GCodeError if the in-plane scaling is
        not uniform (an ellipse is no arc)."""
        plane = self.plane if plane is None else plane
        i, j, _ = plane.value
        fi, fj = abs(self._a[i]), abs(self._a[j])
        if abs(fi - fj) > UNIFORM_TOLERANCE * max(fi, fj):
            raise GCodeError(
                f"Non-uniform scaling of an arc: G51 scales {AXES[i].upper()} by {fi:g} and "
                f"{AXES[j].upper()} by {fj:g} in the {plane.gcode} plane")
        return fi

    def scale_radius(self, radius: float, plane: Plane | None = None) -> float:
        """An arc's R word after scaling (the sign, which picks the long arc, is kept)."""
        _check_finite("Arc radius", radius)
        out = radius * self.radius_factor(plane)
        _out_of_range((out,), "G51 scaling")
        return out

    def apply_arc(
        self, end: Sequence[float], centre: Sequence[float], clockwise: bool, plane: Plane | None = None
    ) -> ArcResult:
        """An arc of ``plane`` (default the active plane) ending at plane-local ``end`` (2 or 3
        values; the normal coordinate of a helix is transformed too) around ``centre`` (first,
        second), G2 when ``clockwise``. The arc rotates with its centre; mirrors flip its direction;
        scaling must be uniform in the plane. The number of turns (P word) is unchanged."""
        plane = self.plane if plane is None else plane
        if self._rot is not None:
            ri, rj, _ = self.rotation_plane.value
            if self.rotation_plane is not plane and (ri in plane.value or rj in plane.value):
                raise GCodeError(
                    f"Arc in the {plane.gcode} plane while the G68 rotation of the "
                    f"{self.rotation_plane.gcode} plane is active: the arc would leave its plane")
        if len(centre) != 2:
            raise ValueError("an arc centre is plane-local (first, second)")
        factor = self.radius_factor(plane)
        new_end = self.apply_point(end, plane)
        new_centre = self.apply_point(centre, plane)
        direction = self.arc_clockwise(clockwise, plane)
        return ArcResult(new_end, (new_centre[0], new_centre[1]), direction, factor)


def _replace(t: ProgramTransform, **changes: object) -> ProgramTransform:
    values = {
        "plane": t.plane,
        "mirror": t.mirror,
        "scale_centre": t.scale_centre,
        "scale_factors": t.scale_factors,
        "rotation_plane": t.rotation_plane,
        "rotation_centre": t.rotation_centre,
        "rotation_angle": t.rotation_angle,
    }
    values.update(changes)
    return ProgramTransform(**values)  # type: ignore[arg-type]
