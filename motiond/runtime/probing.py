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

A probe already in the state the move seeks when it is armed (in contact for G38.2/G38.3, clear for
G38.4/G38.5) makes no edge; where the drive shows the input's level (``touch_probe_level_bit``) it is
handled as LinuxCNC does: G38.2/G38.4 are an error naming the file and line, G38.3/G38.5 trip at once
where the machine stands (the move is not queued).

The probed position is thus exact to the drive's encoder count, whatever the speed; the machine
itself stops past it by the stopping distance, and the next move starts from where it stopped.
"""

from __future__ import annotations

import contextlib
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


def stopped_at_rest(core: Any, planner: Any, cmd: C.Probe, held: bool) -> None:
    """Cycle thread: a probing move stopped by its trip is at rest: the job thread waiting for its
    sync point wakes (as at the move's end). ``held``: a feed hold during the move outlives the
    planner's stop (which clears it)."""
    if held:
        planner.hold()
    core._sync_point_reached(cmd)


def release(core: Any) -> None:
    """Cycle thread: the probe answered: the planner waiting at its sync point goes on."""
    if core.planner is not None and core.planner.waiting_for is not None:
        core.planner.release()


def unwatch(probing: Any) -> None:
    """Any thread: ``probing``'s move is over (or its job cancelled): no longer watched, and the
    planner waiting at its sync point goes on (on the cycle thread, waited for)."""
    core = probing.core

    def on_cycle() -> None:
        probing._armed = None
        release(core)

    core.run_on_cycle(on_cycle)


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
        #: the probe was in the state the move seeks when it was armed (G38.3/G38.5): no move (job thread)
        self.tripped_at_start = False

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
            level = self.probe.arm(toward=cmd.mode.toward)
        except CanopenError as exc:
            raise GCodeError(f"G{cmd.mode.value}: arming the touch probe: {exc}", cmd.file,
                             cmd.line) from None
        self._start = core.position()
        # the probe already in the state the move seeks (in contact for G38.2/G38.3, clear for
        # G38.4/G38.5), where the drive shows its level: as LinuxCNC, G38.2/G38.4 are an error and
        # G38.3/G38.5 trip at once where the machine stands, nothing moving
        self.tripped_at_start = level is not None and level == cmd.mode.toward
        if self.tripped_at_start:
            if cmd.mode.error_on_miss:
                self.tripped_at_start = False
                with contextlib.suppress(CanopenError):
                    self.probe.disarm()
                state = "tripped (in contact)" if cmd.mode.toward else "clear (out of contact)"
                raise GCodeError(f"G{cmd.mode.value}: the probe (touch probe of axis {self.probe.axis}) is "
                                 f"already {state} at the start of the move; nothing moved", cmd.file,
                                 cmd.line)
            return True

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
            stopped_at_rest(self.core, planner, cmd, self._held)

    def answer(self, cmd: C.Probe, cancel: threading.Event) -> Probed | None:
        """Job thread, the interpreter's probe callback: wait for the move's end, read the latch. None
        when ``cancel`` is set meanwhile."""
        if self.tripped_at_start:
            return self.at_start(cmd)
        if not self.core.wait_sync_point(cmd, cancel):
            self.unwatch()
            return None
        return self.latched(cmd)

    def unwatch(self) -> None:
        unwatch(self)

    def at_start(self, cmd: C.Probe) -> Probed:
        """G38.3/G38.5 with the probe already in that state: tripped where the machine stands."""
        from fieldbus.canopen.master import CanopenError

        self.tripped_at_start = False
        try:
            self.probe.disarm()
        except CanopenError as exc:
            raise GCodeError(f"G{cmd.mode.value}: disarming the touch probe: {exc}", cmd.file,
                             cmd.line) from None
        assert self._start is not None
        here = self._start[self.index]
        return Probed(True, self._start, self.probe.axis, here, self.probe.drive.scale.to_counts(here))

    def latched(self, cmd: C.Probe) -> Probed:
        """The planner stands at the probing move's end (or its stop): the probed point from the latch."""
        from fieldbus.canopen.master import CanopenError

        core = self.core
        try:
            result = self.probe.result()
        except CanopenError as exc:
            raise GCodeError(f"G{cmd.mode.value}: reading the touch probe: {exc}", cmd.file, cmd.line) \
                from None
        finally:
            self.unwatch()
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
