"""Spindle-synchronized motion in the planner: G33, G33.1 (rigid tapping) and G76's passes.

Between :class:`~gcode_canon.commands.SpindleSync` and :class:`~gcode_canon.commands.SpindleSyncStop`
a feed move's speed is the pitch times the spindle speed (as G95 feed per revolution), and the feed
override does not apply (the spindle override does, on the spindle). The planner plans with the
commanded spindle speed: on a spindle that turns as commanded (the simulated machine, a spindle drive
in speed control) the motion keeps the pitch. Following a spindle that lags or slips needs its
position feedback in the cycle; the daemon refuses synchronized motion on a real machine without one.
A rigid tap (:class:`~gcode_canon.commands.RigidTap`) is planned as in, stop, spindle reversed, out,
spindle restored: each reversal a spindle start (a sync point). Motion comes to rest where it enters
and where it leaves synchronization (LinuxCNC waits for the spindle's index there and never blends a
synchronized move with a free one): a blend would cut across the thread's start or end. Within it (G76's
tapered entry into the full pitch) moves blend as usual.
"""

from __future__ import annotations

import math
from typing import Any

import gcode_canon.commands as C
from planner.segments import OVR_FEED, PlannerError


class SpindleSyncMixin:
    """Planner state used: ``_sync_pitch``, ``_spindle_rpm``, ``_spindle_dir``, ``_ovr``, ``_pose``."""

    _sync_pitch: float | None
    _spindle_rpm: float
    _spindle_dir: C.SpindleDirection
    _ovr: int
    _pose: list[float]
    _exact_next: bool
    _pending: list[C.Canon]

    def _spindle_sync(self, cmd: C.Canon) -> None:
        if isinstance(cmd, C.RigidTap):
            self._rigid_tap(cmd)
        elif isinstance(cmd, C.SpindleSync):
            if not (math.isfinite(cmd.pitch) and cmd.pitch > 0):
                raise PlannerError(f"spindle-synchronized motion needs a pitch > 0, got {cmd.pitch:g}",
                                   cmd.file, cmd.line)
            if self._sync_pitch is None:
                self._close_tail()  # type: ignore[attr-defined]  # a synchronized move starts at rest
            self._sync_pitch = cmd.pitch
            self._pending.append(cmd)  # passed on: the machine knows a synchronized move comes
        else:
            self._close_tail()  # type: ignore[attr-defined]  # and ends at rest: never blended out
            self._sync_pitch = None
            self._pending.append(cmd)

    def _synced_speed(self, cmd: C.Canon) -> float:
        """Path speed (units/s) of a synchronized feed move: pitch times the spindle's revolutions."""
        assert self._sync_pitch is not None
        if self._spindle_rpm <= 0:
            raise PlannerError("spindle-synchronized motion (G33, G33.1, G76) needs a turning spindle",
                               cmd.file, cmd.line)
        return self._sync_pitch * self._spindle_rpm / 60.0

    def _seg_ovr(self, rapid: bool) -> int:
        """The override switches a new move obeys: a spindle-synchronized feed ignores the feed
        override (its pace is the spindle's; LinuxCNC does the same)."""
        if self._sync_pitch is not None and not rapid:
            return self._ovr & ~OVR_FEED
        return self._ovr

    def _rigid_tap(self, cmd: C.RigidTap) -> None:
        """G33.1: in to ``end`` at the pitch, stop; the spindle reversed (``scale`` times as fast);
        out to where the tap started at the pitch; the spindle as it was. Each reversal is a spindle
        start (a sync point: motion at rest, the spindle up to speed before the next move)."""
        if self._sync_pitch is None:
            raise PlannerError("RIGID_TAP outside spindle-synchronized motion", cmd.file, cmd.line)
        if self._spindle_rpm <= 0:
            raise PlannerError("rigid tapping (G33.1) needs a turning spindle", cmd.file, cmd.line)
        if not (math.isfinite(cmd.scale) and cmd.scale >= 1.0):
            raise PlannerError(f"rigid tap retract scale must be >= 1, got {cmd.scale:g}", cmd.file, cmd.line)
        where: dict[str, Any] = {"file": cmd.file, "line": cmd.line}
        back = C.Pose(*self._pose)
        rpm, forward = self._spindle_rpm, self._spindle_dir
        reverse = C.SpindleDirection.CCW if forward is C.SpindleDirection.CW else C.SpindleDirection.CW
        self._exact_next = True
        self._motion(  # type: ignore[attr-defined]
            C.StraightFeed(cmd.end, **where))
        self.feed(  # type: ignore[attr-defined]
            C.SpindleOn(reverse, rpm * cmd.scale, **where))
        self._exact_next = True
        self._motion(  # type: ignore[attr-defined]
            C.StraightFeed(back, **where))
        self.feed(  # type: ignore[attr-defined]
            C.SpindleOn(forward, rpm, **where))

