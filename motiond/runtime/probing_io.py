"""Motion side: G38.x with the I/O map's ``probe`` input (a Modbus discrete input or coil, or a drive's
0x60FD bit) when no drive has a touch probe. docs/wiring.md.

It stands in for :class:`~motiond.runtime.probing.DriveProbing` (``MotionCore.drive_probe``) with the
same three parts:

* job thread, when the ``Probe`` command is put (:meth:`InputProbing.before_move`): the motion before
  it comes to rest, then the input is read; already in the state the move seeks (in contact for
  G38.2/G38.3, clear for G38.4/G38.5): G38.2/G38.4 are an error naming the file and line, G38.3/G38.5
  trip at once where the machine stands (the move is not queued). An input that cannot be read is an
  error too.
* cycle thread (:meth:`InputProbing.on_cycle`, every cycle, after this cycle's setpoint is computed):
  the input as of the Modbus executor's latest poll; the first cycle that sees it in the sought state
  keeps this cycle's commanded position as the probed point and stops the move (the planner's
  jerk-limited stop on the path); at rest the job thread is woken as at the move's end.
* job thread (:meth:`InputProbing.answer`): the probed point (:class:`~motiond.runtime.probing.Probed`).

Latency: the input is seen by the first poll after it changes (the device's ``poll_ms`` plus the
request) and acted on in the next cycle, whose setpoint the drives latch one SYNC later (the SYNC goes
out first in each cycle, the setpoint for the next): the probed point lies up to (``poll_ms`` + two
cycles) x the probing feed past the true contact (the drive touch probe, latched by the drive, has
none).
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

from gcode_canon import commands as C
from gcode_canon.errors import GCodeError
from motiond.runtime.probing import IDLE_POLL_S, Probed, stopped_at_rest, unwatch

if TYPE_CHECKING:
    import threading


class InputProbing:
    """Probing moves on the I/O map's probe input (module docstring). ``core``: the MotionCore;
    ``mio``: the :class:`~motiond.machine_io.MachineIO` that reads the input."""

    def __init__(self, core: Any, mio: Any) -> None:
        self.core = core
        self.mio = mio
        self.binding = None if mio is None else mio.f["probe"]
        self._armed: C.Probe | None = None  # the probing move being watched (cycle thread reads)
        self._stopping = False
        self._held = False
        self._hit: tuple[float, ...] | None = None  # the commanded position of the cycle that saw it
        self._unreadable = False
        self._start: tuple[float, ...] | None = None
        self.tripped_at_start = False

    def _where(self) -> str:
        b = self.binding
        return f"{b.key}, {b.where}"

    def before_move(self, cmd: C.Probe, cancel: threading.Event) -> bool:
        """Job thread: wait for rest, read the input. False when ``cancel`` is set meanwhile."""
        core = self.core
        while not core.drained():
            if cancel.is_set():
                return False
            time.sleep(IDLE_POLL_S)
        self._start = core.position()
        self.tripped_at_start = at_start(cmd, self.mio._read(self.binding), self._where())
        if not self.tripped_at_start:
            self._arm(cmd)
        return True

    def _arm(self, cmd: C.Probe) -> None:
        def watch() -> None:
            self._armed, self._stopping, self._hit, self._unreadable = cmd, False, None, False

        self.core.run_on_cycle(watch)

    def on_cycle(self, planner: Any) -> None:
        """Cycle thread, every cycle: stop the probing move on the trip; at rest, wake the job thread."""
        cmd = self._armed
        if cmd is None or planner is None:
            return
        if not self._stopping:
            if planner.waiting_for is cmd:
                return  # the move ended untripped: the sync point answers it
            trip = self._trip(cmd, planner)
            if trip is not None:
                self._stopping = True
                self._hit, self._unreadable = trip
                self._held = planner.holding
                planner.abort()  # the rest of the move (and its sync point) is dropped at rest
                if not self._unreadable:
                    self._note_trip(cmd)
        elif planner.is_idle:
            self._armed = None
            stopped_at_rest(self.core, planner, cmd, self._held)

    def _note_trip(self, cmd: C.Probe) -> None:
        """The trip in the job's record, in the cycle that saw it: the run summary lists it with the
        functions switched (``probe=1 (line N)``)."""
        from motiond.runtime.records import OutputSwitch

        stream = self.core.stream
        if stream is not None:
            stream.outputs.append(OutputSwitch(self.core.cycle, time.monotonic(), "function", -1, 1.0, True,
                                               cmd.file, cmd.line, name="probe"))

    def _trip(self, cmd: C.Probe, planner: Any) -> tuple[tuple[float, ...], bool] | None:
        """Cycle thread: the input in the sought state (or unreadable): the probed point, this cycle's
        setpoint, and whether it was unreadable; None: not tripped."""
        level = self.mio._read(self.binding)
        if level is None or level == cmd.mode.toward:
            return tuple(planner.position), level is None
        return None

    def answer(self, cmd: C.Probe, cancel: threading.Event) -> Probed | None:
        """Job thread, the interpreter's probe callback: wait for the move's end; None when ``cancel``
        is set meanwhile."""
        core = self.core
        if self.tripped_at_start:
            self.tripped_at_start = False
            assert self._start is not None
            return Probed(True, self._start, "probe input")
        try:
            if not core.wait_sync_point(cmd, cancel):
                return None
        finally:
            unwatch(self)
        return outcome(cmd, core.limits.pose_index, self._hit, self._unreadable, self._where())


def at_start(cmd: C.Probe, level: bool | None, where: str) -> bool:
    """The probe input's ``level`` read at rest before a probing move: True when it is already in the
    state the move seeks and the move is not made (G38.3/G38.5: tripped where the machine stands);
    GCodeError naming the line for G38.2/G38.4 there, or an input that cannot be read."""
    if level is None:
        raise GCodeError(f"G{cmd.mode.value}: the probe input cannot be read ({where}: link "
                         "down or not polled yet); nothing moved", cmd.file, cmd.line)
    if level != cmd.mode.toward:
        return False
    if cmd.mode.error_on_miss:
        state = "tripped (in contact)" if cmd.mode.toward else "clear (out of contact)"
        raise GCodeError(f"G{cmd.mode.value}: the probe ({where}) is already {state} at "
                         "the start of the move; nothing moved", cmd.file, cmd.line)
    return True


def outcome(cmd: C.Probe, pose_index: tuple[int, ...], hit: tuple[float, ...] | None, unreadable: bool,
            where: str) -> Probed:
    """A probing move on the probe input has ended: the probed point (``hit``: the commanded position
    of the cycle that saw the trip; None: no trip, the move's end)."""
    if unreadable:
        raise GCodeError(f"G{cmd.mode.value}: the probe input could not be read during the move "
                         f"({where}): the move was stopped", cmd.file, cmd.line)
    if hit is None:
        return Probed(False, tuple(cmd.end[k] for k in pose_index))
    return Probed(True, hit, "probe input")
