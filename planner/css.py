"""Constant surface speed (G96): the spindle's rpm from the X radius, cycle by cycle.

Under G96 the S word is a surface speed, not an rpm (gcode_canon passes it on as LinuxCNC does:
:class:`~gcode_canon.commands.SetSpindleMode` carries the surface speed in mm/min, the X where the
radius is 0 and the highest rpm, the D word). The drives and the I/O map know only rpm, so the planner
turns the surface speed into rpm where it knows the position: on the setpoints. Each setpoint under
G96 gets ``surface / (2 pi r)`` rpm (at most D), r the distance of the commanded X from the centre;
a new :class:`~gcode_canon.commands.SetSpindleSpeed` goes out when that rpm moved by
:data:`CSS_STEP` of itself (or reached D exactly), at most once every :data:`CSS_MIN_INTERVAL_S` (a
Modbus speed register written every cycle would flood the I/O link), and always at a start (M3/M4)
and a mode change.

Feed per revolution (G95) under G96, the usual lathe pairing, is planned as LinuxCNC runs it (its
motion controller scales the feed by the spindle's speed every cycle): a G95 line is planned in pieces
(:meth:`SurfaceSpeed.split_line`) within which the G96 rpm changes by at most :data:`CSS_PIECE_RATIO`,
each at F times the lowest rpm along it (an arc: at the lowest rpm along the whole arc), so that each
revolution advances F (a little less, never more). With the spindle's measured position the pieces run
on its clock as any G95 move (``planner.spindle_sync``), at the rpm each was planned at.

G33 and G76 under G96 are done as LinuxCNC does them (the spindle at the G96 rpm of the commanded X,
the axes on its position): ``planner.spindle_sync`` plans them at D where the spindle is followed.

What is refused, naming the line: G96 on a machine without an X axis; a rigid tap (G33.1) under G96
(:meth:`SurfaceSpeed.intake` says why).
"""

from __future__ import annotations

import dataclasses
import math

from gcode_canon import commands as C
from planner.segments import PlannerError

#: relative change of the computed rpm that sends a new speed
CSS_STEP = 0.01
#: the least time between two speeds sent while the radius changes
CSS_MIN_INTERVAL_S = 0.05
#: G95 under G96: the G96 rpm changes by at most this factor within one planned piece of a line ...
CSS_PIECE_RATIO = 1.02
#: ... in at most this many pieces (a longer line gets coarser pieces)
CSS_MAX_PIECES = 200


def css_rpm(surface: float, radius: float, css_max: float) -> float:
    """The rpm for ``surface`` mm/min at ``radius`` mm, at most ``css_max`` (radius 0: ``css_max``)."""
    r = abs(radius)
    if r <= 0.0:
        return css_max
    return min(css_max, surface / (2.0 * math.pi * r))


class SurfaceSpeed:
    """The G96 state on the planner's two sides: where commands come in (:meth:`intake`, which refuses
    what cannot be planned under G96) and where setpoints go out (:meth:`emit`, which rewrites the speed
    events and adds new ones as the radius changes)."""

    def __init__(self, x_index: int | None) -> None:
        self.x_index = x_index
        self.in_css = False  # G96 as the commands come in (lookahead side)
        self.intake_mode: C.SetSpindleMode | None = None  # ... and its numbers
        self._mode: C.SetSpindleMode | None = None  # G96 as the setpoints go out
        self._rpm = 0.0  # the last rpm sent under G96
        self._sent_t = -math.inf

    # ------------------------------------------------------------------ intake
    def intake(self, cmd: C.Canon) -> None:
        """A command as it enters the planner: G96/G97 tracked, sync motion under G96 refused."""
        if isinstance(cmd, C.SetSpindleMode):
            if cmd.css_max > 0.0 and self.x_index is None:
                raise PlannerError("constant surface speed (G96) needs an X axis on this machine", cmd.file,
                                   cmd.line)
            self.in_css = cmd.css_max > 0.0
            self.intake_mode = cmd if self.in_css else None
        elif self.in_css and isinstance(cmd, C.RigidTap):
            raise PlannerError("rigid tapping (G33.1) under constant surface speed (G96) is not supported "
                               "(the tap reverses the spindle at its own speed, which G96 would change "
                               "with X): use G97 before it", cmd.file, cmd.line)

    def rpm_at(self, x: float) -> float:
        """The G96 rpm at machine X ``x`` (as the commands come in)."""
        mode = self.intake_mode
        assert mode is not None
        return css_rpm(mode.surface, x - mode.x_centre, mode.css_max)

    def highest_rpm(self, x0: float, x1: float) -> float:
        """The highest G96 rpm along a move from machine X ``x0`` to ``x1`` (as the commands come in):
        at its end nearer the centre, or D where it crosses the centre."""
        mode = self.intake_mode
        assert mode is not None
        if (x0 - mode.x_centre) * (x1 - mode.x_centre) <= 0.0:
            return self.rpm_at(mode.x_centre)
        return max(self.rpm_at(x0), self.rpm_at(x1))

    def split_line(self, x0: float, x1: float) -> list[float]:
        """Where (0 < u < 1 along it) a line from machine X ``x0`` to ``x1`` is cut so that within each
        piece the G96 rpm changes by at most :data:`CSS_PIECE_RATIO` (at most :data:`CSS_MAX_PIECES`
        pieces): the radii at which it crosses a geometric series of levels, from its outermost radius
        down to where D caps the rpm."""
        mode = self.intake_mode
        assert mode is not None
        dx = x1 - x0
        r_hi = max(abs(x0 - mode.x_centre), abs(x1 - mode.x_centre))
        r_cap = mode.surface / (2.0 * math.pi * mode.css_max) if mode.css_max > 0 else 0.0
        r_floor = max(r_cap, r_hi * 1e-4)
        if abs(dx) <= 1e-12 or r_hi <= r_floor:
            return []
        ratio = max(CSS_PIECE_RATIO, (r_hi / r_floor) ** (1.0 / CSS_MAX_PIECES))
        cuts: set[float] = set()
        r = r_hi / ratio
        while r > r_floor:
            for side in (r, -r):
                u = (mode.x_centre + side - x0) / dx
                if 1e-9 < u < 1.0 - 1e-9:
                    cuts.add(u)
            r /= ratio
        if r_cap > 0:  # where D starts to cap it
            for side in (r_cap, -r_cap):
                u = (mode.x_centre + side - x0) / dx
                if 1e-9 < u < 1.0 - 1e-9:
                    cuts.add(u)
        return sorted(cuts)

    @property
    def active(self) -> bool:
        """Whether setpoints without events need :meth:`emit` (G96 in force as they go out)."""
        return self._mode is not None

    # ------------------------------------------------------------------ emission
    def emit(self, t: float, pos: tuple[float, ...], events: list[C.Canon]) -> list[C.Canon]:
        """The events of the setpoint at ``t`` with ``pos``: under G96 every speed in rpm."""
        if self._mode is None and not any(isinstance(e, C.SetSpindleMode) for e in events):
            return events
        out: list[C.Canon] = []
        for ev in events:
            if isinstance(ev, C.SetSpindleMode):
                self._mode = ev if ev.css_max > 0.0 else None
                if self._mode is not None:
                    out.append(ev)
                    out.append(self._speed(t, pos, ev))
                    continue
            elif self._mode is not None and isinstance(ev, C.SetSpindleSpeed):
                continue  # the surface number: its mode (just before it) carries it, in rpm
            elif self._mode is not None and isinstance(ev, C.SpindleOn):
                ev = dataclasses.replace(ev, rpm=self._rpm_at(pos))
                self._rpm, self._sent_t = ev.rpm, t
            out.append(ev)
        if self._mode is not None:
            rpm = self._rpm_at(pos)
            moved = abs(rpm - self._rpm) > CSS_STEP * max(self._rpm, 1.0)
            capped = rpm == self._mode.css_max and rpm != self._rpm  # D reached: exactly D
            if (moved or capped) and t - self._sent_t >= CSS_MIN_INTERVAL_S - 1e-9:
                out.append(self._speed(t, pos, self._mode))
        return out

    def _rpm_at(self, pos: tuple[float, ...]) -> float:
        mode = self._mode
        assert mode is not None and self.x_index is not None
        return css_rpm(mode.surface, pos[self.x_index] - mode.x_centre, mode.css_max)

    def _speed(self, t: float, pos: tuple[float, ...], src: C.Canon) -> C.SetSpindleSpeed:
        self._rpm, self._sent_t = self._rpm_at(pos), t
        return C.SetSpindleSpeed(self._rpm, file=src.file, line=src.line)
