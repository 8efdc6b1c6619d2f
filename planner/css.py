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

What is refused, naming the line: G96 on a machine without an X axis; feed per revolution (G95) and
spindle-synchronized motion (G33, G33.1, G76) under G96 (their rate would have to follow an rpm that
changes along the move: not planned yet; LinuxCNC does it in its motion controller).
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
        self._mode: C.SetSpindleMode | None = None  # G96 as the setpoints go out
        self._rpm = 0.0  # the last rpm sent under G96
        self._sent_t = -math.inf

    # ------------------------------------------------------------------ intake
    def intake(self, cmd: C.Canon) -> None:
        """A command as it enters the planner: G96/G97 tracked, G95 and sync motion under G96 refused."""
        if isinstance(cmd, C.SetSpindleMode):
            if cmd.css_max > 0.0 and self.x_index is None:
                raise PlannerError("constant surface speed (G96) needs an X axis on this machine", cmd.file,
                                   cmd.line)
            self.in_css = cmd.css_max > 0.0
        elif self.in_css and isinstance(cmd, C.SpindleSync | C.RigidTap):
            raise PlannerError("spindle-synchronized motion (G33, G33.1, G76) under constant surface "
                               "speed (G96) is not supported: use G97 before it", cmd.file, cmd.line)

    def check_per_rev(self, cmd: C.Canon) -> None:
        """A G95 move as it is planned: refused under G96."""
        if self.in_css:
            raise PlannerError("feed per revolution (G95) under constant surface speed (G96) is not "
                               "supported: use G94, or G97 with an rpm", cmd.file, cmd.line)

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
