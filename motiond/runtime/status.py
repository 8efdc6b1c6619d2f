"""Task side: the ``canon.status`` snapshot and the ``canon-status`` thread that publishes it.

:class:`StatusMixin` is the part of :class:`motiond.runtime.machine.Machine` that assembles the status
from the machine states, the job, the interpreter, the Modbus I/O and the motion side's
:class:`~motiond.runtime.motion.MotionSnapshot` (the only thing it reads of the motion side), and
publishes it at ``status_hz``, never on the cycle thread.
"""

from __future__ import annotations

import collections
import linecache
import logging
import math
import threading
import time
from typing import TYPE_CHECKING, Any

from motiond.runtime.parts import MachinePart
from motiond.states import Mode, State

if TYPE_CHECKING:
    from motiond.runtime.records import ModalState

log = logging.getLogger(__name__)


class StatusMixin(MachinePart):
    """The status of :class:`~motiond.runtime.machine.Machine` (module docstring)."""

    if TYPE_CHECKING:  # provided by Machine
        telemetry: Any
        status_pub: Any
        events: Any
        modbus: Any
        homed: list[bool]
        single_block: bool
        optional_stop: bool
        status_seq: int
        status_data_t: collections.OrderedDict[int, float]
        _homing: str
        _status_stop: threading.Event
        def _modal_state(self, file: str, line: int) -> ModalState: ...

    def _status_loop(self) -> None:
        period = 1.0 / self.telemetry.status_hz
        deadline = time.monotonic()
        while not self._status_stop.is_set():
            try:
                snap = self.status()
                self.status_pub.update(snap)
                self.status_pub.publish_now()
            except Exception:
                log.exception("building the status")
            deadline += period
            late = time.monotonic() - deadline
            if late > 0:
                deadline += (int(late / period) + 1) * period
            self._status_stop.wait(max(0.0, deadline - time.monotonic()))

    def status(self) -> Any:
        """A ``canon.status`` snapshot of the machine now (any thread)."""
        from telemetry.lcmtypes.canon import drive_status, status

        s = status()
        self.status_seq += 1
        s.utime = time.time_ns() // 1000
        s.seq = self.status_seq
        s.machine = self.limits.name
        snap = self.states.snapshot()
        mo = self.motion.snapshot()
        state = {State.ESTOP: "estop", State.IDLE: "idle", State.RUNNING: "running", State.PAUSED: "paused",
                 State.FAULTED: "fault"}[snap.state]
        if state == "idle" and self._homing:
            state = "homing"
        elif state == "idle" and mo.jogging:
            state = "jogging"
        s.state = state
        s.mode = snap.mode.value
        s.estop = snap.state is State.ESTOP
        s.enabled = snap.enabled
        job = self._job
        line = mo.line
        s.program = job.program if job is not None and job.mode is Mode.AUTO else ""
        s.line = int(line) if job is not None else 0
        s.block = ""
        if job is not None and line:
            if job.mode is Mode.MDI:
                s.block = job.program
            else:
                s.block = linecache.getline(job.program, int(line)).strip()[:200]
        s.single_block = self.single_block
        s.optional_stop = self.optional_stop
        s.block_delete = bool(self.interp.settings.block_delete)
        s.num_axes = self.n
        s.axis_names = list(self.names)
        s.homed = list(self.homed)
        self.status_data_t[s.seq] = mo.actual_t
        if len(self.status_data_t) > 2000:
            self.status_data_t.popitem(last=False)
        s.commanded = [float(v) for v in mo.commanded]
        s.actual = [float(v) for v in mo.actual]
        s.velocity = [float(v) for v in mo.velocity]
        s.following_error = [float(v) for v in mo.following_error]
        lin = [mo.velocity[i] for i, a in enumerate(self.limits.axes) if not a.rotary]
        s.path_velocity = math.sqrt(sum(v * v for v in lin))
        modal = mo.modal if job is not None else None
        if modal is None:  # no job: the interpreter's state is the machine's
            modal = self._modal_state("", 0)
        s.feed_rate = modal.feed
        s.feed_override = mo.feed_override
        s.rapid_override = 1.0
        s.spindle_override = 1.0
        drives = []
        for d in mo.drives:
            ds = drive_status()
            ds.axis = d.axis
            ds.node_id = d.node
            ds.nmt_state = d.nmt_state
            ds.heartbeat_ok = d.heartbeat_ok
            ds.statusword = d.statusword
            ds.cia402_state = d.cia402_state
            ds.mode_display = 8 if d.operational else 0
            ds.position_actual = d.actual_counts
            ds.following_error = d.following_error
            ds.emcy_code = d.emcy_code
            ds.error = d.error
            drives.append(ds)
        s.num_drives = len(drives)
        s.drives = drives
        g, m = list(modal.gcodes), list(modal.mcodes)
        s.num_gcodes, s.gcodes = len(g), g
        s.num_mcodes, s.mcodes = len(m), m
        s.tool = modal.tool
        s.tool_prepared = mo.tool_prepared
        s.tool_length_offset = modal.tool_length_offset
        s.spindle_direction, s.spindle_speed = mo.spindle[0], float(mo.spindle[1])
        sd = mo.spindle_drive
        s.spindle_drive = sd is not None
        s.spindle_actual_speed = float(sd.rpm) if sd is not None else 0.0
        s.spindle_revolutions = float(sd.revolutions) if sd is not None else 0.0
        s.mist, s.flood = mo.coolant
        if self.io is not None:
            io = self.io.state()
            di, do, ai, ao = io.arrays()
            s.io_ok = io.io_ok
        else:
            di, do, ai, ao = [], [], [], []
            s.io_ok = self.modbus is None
        s.num_digital_inputs, s.digital_inputs = len(di), [bool(v) for v in di]
        s.num_digital_outputs, s.digital_outputs = len(do), [bool(v) for v in do]
        s.num_analog_inputs, s.analog_inputs = len(ai), [float(v) for v in ai]
        s.num_analog_outputs, s.analog_outputs = len(ao), [float(v) for v in ao]
        self.io_hooks.status(s)
        s.last_error = self.last_error
        s.last_error_utime = self.last_error_utime
        s.events_dropped = self.events.dropped
        return s
