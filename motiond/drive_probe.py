"""G38.x on a machine whose probe input is a drive's touch probe (``canopen.axes.<a>.touch_probe``).

The three threads of :class:`~motiond.runtime.Machine` each do their part:

* job thread, before the ``Probe`` command is queued (:meth:`DriveProbing.before_move`): the motion
  before it comes to rest (a probing move starts at rest anyway), then the touch probe is armed by
  SDO for the move's edge (contact made for G38.2/G38.3, lost for G38.4/G38.5). Armed before the
  planner has the move, so no part of the move goes unwatched, and after the moves before it, so
  their contacts are not taken for the probe's.
* cycle thread (:meth:`DriveProbing.on_cycle`, every cycle): once the drive reports the latch
  (TPDO4, the cycle after the edge), the move stops (the planner's jerk-limited stop on the path)
  and, at rest, the job thread is woken as at the move's end.
* job thread, in the interpreter's probe callback (:meth:`DriveProbing.answer`): the latched
  position by SDO; the probed pose is the point of the probing line where the probe's axis is at the
  latched position (the drive latched its own axis only; the others are on the commanded line). If
  the probe's axis does not move in this G38, the other axes are where the motion stopped.

The probed position is thus exact to the drive's encoder count, whatever the speed; the machine
itself stops past it by the stopping distance, and the next move starts from where it stopped.
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, Any

from gcode_canon import commands as C
from gcode_canon.errors import GCodeError
from motiond.states import Mode

if TYPE_CHECKING:
    from fieldbus.canopen.touch_probe import TouchProbe

log = logging.getLogger(__name__)

IDLE_POLL_S = 0.004
"""How often the job thread asks whether the motion before a probing move is at rest."""


class DriveProbing:
    """The probing moves of one machine with a drive touch probe (see the module's text)."""

    def __init__(self, machine: Any, probe: TouchProbe) -> None:
        self.m = machine
        self.probe = probe
        self.pose_index = machine.limits.pose_index[machine.master.drives.index(probe.drive)]
        self._armed: C.Probe | None = None  # the probing move being watched (cycle thread reads)
        self._stopping = False
        self._held = False
        self._start: C.Pose | None = None

    def before_move(self, cmd: C.Probe, job: Any) -> bool:
        """Job thread: wait for rest, arm. False when the job was cancelled meanwhile."""
        m = self.m
        from fieldbus.canopen.master import CanopenError

        def at_rest() -> bool:
            return m.planner is not None and m.planner.is_idle and m._cmdq.empty()

        while not m._on_cycle(at_rest):
            if job.cancel.is_set():
                return False
            time.sleep(IDLE_POLL_S)
        try:
            self.probe.arm(toward=cmd.mode.toward)
        except CanopenError as exc:
            raise GCodeError(f"G{cmd.mode.value}: arming the touch probe: {exc}", cmd.file,
                             cmd.line) from None
        self._start = m._machine_pose()

        def watch() -> None:
            self._armed, self._stopping = cmd, False

        m._on_cycle(watch)
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
            m = self.m
            with m._sync_cond:
                m._sync_reached = cmd
                m._sync_cond.notify_all()

    def answer(self, cmd: C.Probe, job: Any) -> tuple[C.Pose, bool]:
        """Job thread, the interpreter's probe callback: wait for the move's end, read the latch."""
        from fieldbus.canopen.master import CanopenError

        m = self.m
        if job.mode is not Mode.AUTO:
            # an MDI line's probe callback runs before the line's commands are queued: the move
            # could not have run yet
            raise GCodeError(f"G{cmd.mode.value} in MDI: probing with the drive's touch probe needs the "
                             "move to run first; put the probing move in a program", cmd.file, cmd.line)

        def unwatch() -> None:
            self._armed = None
            m._release_wait()

        try:
            m._wait_sync_point(cmd, job)
            result = self.probe.result()
        except CanopenError as exc:
            raise GCodeError(f"G{cmd.mode.value}: reading the touch probe: {exc}", cmd.file, cmd.line) \
                from None
        finally:
            m._on_cycle(unwatch)
        if not result.tripped:
            return cmd.end, False
        k = self.pose_index
        start = self._start if self._start is not None else cmd.end
        travel = cmd.end[k] - start[k]
        if abs(travel) > 1e-12:
            t = min(1.0, max(0.0, (result.position - start[k]) / travel))
            pose = [s + t * (e - s) for s, e in zip(start, cmd.end, strict=True)]
        else:
            pose = list(m._machine_pose())
        pose[k] = result.position
        m.event("INFO", f"probe: touch probe of axis {self.probe.axis} latched at {result.position:.6g} "
                        f"({result.counts} counts)", kind="probe", source="motiond", file=cmd.file,
                line=cmd.line)
        return C.Pose(*pose), True
