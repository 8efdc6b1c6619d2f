"""Motion side: G38.x with a drive's touch probe as the probe input (``canopen.axes.<a>.touch_probe``).

:class:`~motiond.runtime.motion.MotionCore` holds one :class:`DriveProbing` when a drive has the
machine's probe. Its parts run on two threads:

* job thread, when the ``Probe`` command is put (:meth:`DriveProbing.before_move`, from
  :meth:`MotionCore.put`): the motion before it comes to rest (a probing move starts at rest anyway),
  then the touch probe is armed by SDO for the move's edge (contact made for G38.2/G38.3, lost for
  G38.4/G38.5). Armed before the planner has the move, so no part of the move goes unwatched, and
  after the moves before it, so their contacts are not taken for the probe's.
* cycle thread (:meth:`DriveProbing.on_cycle`, every cycle): once the drive reports the latch
  (TPDO4, the cycle after the edge), the move stops (the planner's jerk-limited stop on the path)
  and, at rest, the job thread is woken as at the move's end.
* job thread, in the interpreter's probe callback (:meth:`DriveProbing.answer`, from
  :meth:`MotionCore.probe`): the latched position by SDO; the probed point is the point of the
  probing line where the probe's axis is at the latched position (the drive latched its own axis
  only; the others are on the commanded line). If the probe's axis does not move in this G38, the
  other axes are where the motion stopped.

The probed position is thus exact to the drive's encoder count, whatever the speed; the machine
itself stops past it by the stopping distance, and the next move starts from where it stopped.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from gcode_canon import commands as C
from gcode_canon.errors import GCodeError

if TYPE_CHECKING:
    import threading

    from fieldbus.canopen.touch_probe import TouchProbe

log = logging.getLogger(__name__)

IDLE_POLL_S = 0.004
"""How often the job thread asks whether the motion before a probing move is at rest."""


@dataclass(frozen=True, slots=True)
class Probed:
    """A probing move's outcome: whether the probe tripped, the probed point (machine axes, machine
    units; the move's end when it did not trip), the axis and what the drive latched (units, counts)."""

    tripped: bool
    positions: tuple[float, ...]
    axis: str = ""
    latched: float = 0.0
    counts: int = 0


class DriveProbing:
    """The probing moves of one machine with a drive touch probe (see the module's text). ``core``:
    the :class:`~motiond.runtime.motion.MotionCore`."""

    def __init__(self, core: Any, probe: TouchProbe) -> None:
        self.core = core
        self.probe = probe
        self.index = core.master.drives.index(probe.drive)  # the probe's axis among the machine's
        self._armed: C.Probe | None = None  # the probing move being watched (cycle thread reads)
        self._stopping = False
        self._held = False
        self._start: tuple[float, ...] | None = None

    def _end(self, cmd: C.Probe) -> tuple[float, ...]:
        return tuple(cmd.end[k] for k in self.core.limits.pose_index)

    def before_move(self, cmd: C.Probe, cancel: threading.Event) -> bool:
        """Job thread: wait for rest, arm. False when ``cancel`` is set meanwhile."""
        from fieldbus.canopen.master import CanopenError

        core = self.core
        while not core.drained():
            if cancel.is_set():
                return False
            time.sleep(IDLE_POLL_S)
        try:
            self.probe.arm(toward=cmd.mode.toward)
        except CanopenError as exc:
            raise GCodeError(f"G{cmd.mode.value}: arming the touch probe: {exc}", cmd.file,
                             cmd.line) from None
        self._start = core.position()

        def watch() -> None:
            self._armed, self._stopping = cmd, False

        core.run_on_cycle(watch)
        return True

    def on_cycle(self, planner: Any) -> None:
        """Cycle thread, every cycle: stop the probing move on the trip; at rest, wake the job thread."""
        cmd = self._armed
        if cmd is None or planner is None:
            return
        if not self._stopping:
            if self.probe.tripped and planner.waiting_for is not cmd:
                self._stopping = True
                self._held = planner.holding
                planner.abort()  # the rest of the move (and its sync point) is dropped at rest
        elif planner.is_idle:
            self._armed = None
            if self._held:
                planner.hold()  # a feed hold during the move outlives the planner's stop (it clears it)
            core = self.core
            with core._sync_cond:
                core._sync_reached = cmd
                core._sync_cond.notify_all()

    def answer(self, cmd: C.Probe, cancel: threading.Event) -> Probed | None:
        """Job thread, the interpreter's probe callback: wait for the move's end, read the latch. None
        when ``cancel`` is set meanwhile."""
        from fieldbus.canopen.master import CanopenError

        core = self.core

        def unwatch() -> None:
            self._armed = None
            if core.planner is not None and core.planner.waiting_for is not None:
                core.planner.release()

        try:
            if not core.wait_sync_point(cmd, cancel):
                return None
            result = self.probe.result()
        except CanopenError as exc:
            raise GCodeError(f"G{cmd.mode.value}: reading the touch probe: {exc}", cmd.file, cmd.line) \
                from None
        finally:
            core.run_on_cycle(unwatch)
        end = self._end(cmd)
        if not result.tripped:
            return Probed(False, end)
        k = self.index
        start = self._start if self._start is not None else end
        travel = end[k] - start[k]
        if abs(travel) > 1e-12:
            t = min(1.0, max(0.0, (result.position - start[k]) / travel))
            point = [s + t * (e - s) for s, e in zip(start, end, strict=True)]
        else:
            point = list(core.position())
        point[k] = result.position
        return Probed(True, tuple(point), self.probe.axis, result.position, result.counts)
