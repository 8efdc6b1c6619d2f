"""G38.x in the motion process (``[motion] process = "own"``): its side of the probing moves, whose
other side is :class:`~motiond.runtime.probing_proxy.ProbeClient` in the task process.

Two kinds of probe, as in one process (:mod:`motiond.runtime.probing`, :mod:`motiond.runtime.probing_io`):

* a drive's touch probe (0x60B8-0x60BA): the master and thus the whole
  :class:`~motiond.runtime.probing.DriveProbing` are here. The task asks, over the request pipe, to
  arm it before it sends the probing move (``probe_arm``: the motion before is at rest, the probe is
  armed by SDO and watched every cycle; the answer says whether it was already tripped), and once the
  planner stands at the move's end or its stop, for the latched point (``probe_latched``), or at once
  for the point where the machine stands (``probe_at_start``), or to stop watching (``probe_unwatch``:
  the job was cancelled).
* the I/O map's probe input (a Modbus discrete input): read in the task process, which sends on the
  urgent pipe the CLOCK_MONOTONIC time it saw the trip (``probe_trip``; the clock is the same in both
  processes). :class:`TripTimeProbing` keeps, while armed, the commanded position of each cycle with
  its time (:data:`HISTORY` cycles); the probed point is the position of the cycle the task saw the
  input in (the last one that began before that time), and the move stops (the planner's jerk-limited
  stop on the path) in the cycle the message arrives in.

The probing move arrives on the command pipe as a copy of the one the arming request carried:
:meth:`ProbeServer.adopt` makes the watcher watch the copy the planner runs (its sync point is told to
the task by that copy's sequence number).
"""

from __future__ import annotations

import collections
import threading
from typing import Any

from gcode_canon import commands as C
from motiond.runtime.probing import Probed, unwatch
from motiond.runtime.probing_io import InputProbing, outcome

HISTORY = 512
"""Cycles of commanded positions kept while a probing move on the probe input runs (1 s at 2 ms): the
task's trip message may arrive this late and still find its cycle."""


class TripTimeProbing(InputProbing):
    """The probe input's side in the motion process: the trip comes as a time (module docstring).
    ``where``: the input's key and place, for the error when it could not be read."""

    def __init__(self, core: Any, where: str) -> None:
        super().__init__(core, None)
        self.where = where
        self._seen: tuple[float, bool] | None = None  # (seen at, unreadable) from the task
        self.history: collections.deque[tuple[float, tuple[float, ...]]] = collections.deque(maxlen=HISTORY)

    def _where(self) -> str:
        return self.where

    def before_move(self, cmd: C.Probe, cancel: threading.Event) -> bool:
        """Request thread (the task saw the motion at rest and the input not yet in the sought state,
        ``tripped_at_start`` stays False): watch the move."""
        self._arm(cmd)
        return True

    def _arm(self, cmd: C.Probe) -> None:
        def clear() -> None:
            self._seen = None
            self.history.clear()

        self.core.run_on_cycle(clear)
        super()._arm(cmd)

    def trip(self, seen_at: float, unreadable: bool) -> None:
        """Urgent reader thread: the task saw the input in the sought state (or unreadable) at ``seen_at``."""
        if self._armed is not None and self._seen is None:
            self._seen = (seen_at, unreadable)

    def position_at(self, t: float) -> tuple[float, ...]:
        """The commanded position of the cycle that was running at ``t`` (the oldest kept if older)."""
        hit = self.history[0][1]
        for t_cycle, pos in self.history:
            if t_cycle > t:
                break
            hit = pos
        return hit

    def _trip(self, cmd: C.Probe, planner: Any) -> tuple[tuple[float, ...], bool] | None:
        """Cycle thread, after this cycle's setpoint went out: kept; the trip once its time came."""
        self.history.append((self.core.actual_t, tuple(planner.position)))
        seen = self._seen
        return None if seen is None else (self.position_at(seen[0]), seen[1])

    def unwatch(self) -> None:
        unwatch(self)

    def latched(self, cmd: C.Probe) -> Probed:
        """The planner stands at the move's end or its stop: the probed point."""
        unwatch(self)
        return outcome(cmd, self.core.limits.pose_index, self._hit, self._unreadable, self.where)


class ProbeServer:
    """The probing requests of the motion process (module docstring). ``core``: its MotionCore."""

    def __init__(self, core: Any) -> None:
        self.core = core

    def use_input(self, where: str) -> None:
        """The task has the I/O map's probe input (and no drive a touch probe)."""
        if self.core.drive_probe is None:
            self.core.drive_probe = TripTimeProbing(self.core, where)

    def adopt(self, item: C.Probe) -> None:
        """Command reader: ``item``, off the command pipe, is the move the watcher was armed for."""
        probing = self.core.drive_probe
        if probing is not None and probing._armed is not None and probing._armed == item:
            probing._armed = item

    def trip(self, seen_at: float, unreadable: bool) -> None:
        probing = self.core.drive_probe
        if isinstance(probing, TripTimeProbing):
            probing.trip(seen_at, unreadable)

    def call(self, name: str, args: tuple[Any, ...]) -> Any:
        """``probe_input`` (the task has the probe input), ``probe_arm`` (True: tripped at the start,
        nothing to move), ``probe_at_start``, ``probe_latched``, ``probe_unwatch``."""
        if name == "probe_input":
            return self.use_input(args[0])
        probing = self.core.drive_probe
        if probing is None:
            raise RuntimeError("no probe in the motion process")
        if name == "probe_arm":
            probing.before_move(args[0], threading.Event())
            return probing.tripped_at_start
        if name == "probe_at_start":
            return probing.at_start(args[0])
        if name == "probe_latched":
            return probing.latched(args[0])
        if name == "probe_unwatch":
            return probing.unwatch()
        raise AttributeError(f"the motion process does not serve {name!r}")
