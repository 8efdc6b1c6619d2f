"""The machine at run time: interpreter, planner, CANopen master, Modbus I/O and telemetry, wired.

Split along the boundary the motion side will cross into a process of its own (issue 14;
docs/daemon.md, "Inside the machine"):

* motion side, :mod:`motiond.runtime.motion`: :class:`~motiond.runtime.motion.MotionCore`, the
  CANopen master's cycle, planner feeding, setpoint tracking, fault checks, quick stop. Its whole
  interface is in that module's docstring: canonical commands in through a bounded queue, urgent
  calls (estop, abort, pause, resume, feed_override) as methods, a snapshot out, hooks back.
* task side, :class:`~motiond.runtime.machine.Machine`, the facade that ``canon run``, ``canon
  daemon`` and the tests use, made of parts by concern: :mod:`~motiond.runtime.jobs` (the
  interpreter's job thread), :mod:`~motiond.runtime.run_from_line`, :mod:`~motiond.runtime.service`
  (enable, disable, estop_reset, reset, home on the ``canon-service`` thread),
  :mod:`~motiond.runtime.status` (``canon.status`` on the ``canon-status`` thread) and
  :mod:`~motiond.runtime.machine` itself (bring-up, shutdown, command verbs, faults, events).
* :mod:`~motiond.runtime.records`: the plain records that cross between them.

The names below are those ``motiond.runtime`` has always offered.
"""

from motiond.runtime.machine import (
    SIM_FEEDBACK_TIMEOUT_S,
    SIM_HEARTBEAT_CONSUMER_MS,
    SIM_LATE_FAULT_S,
    STOP_TIMEOUT_S,
    Machine,
)
from motiond.runtime.motion import FEED_PER_CYCLE, LATE_LOG, LOOKAHEAD, QUEUE_MAX, MotionCore, MotionSnapshot
from motiond.runtime.records import AxisPeaks, JobResult, MachineError, ModalState, OutputSwitch
from motiond.runtime.service import SERVICE_JOIN_S

__all__ = [
    "FEED_PER_CYCLE", "LATE_LOG", "LOOKAHEAD", "QUEUE_MAX", "SERVICE_JOIN_S", "SIM_FEEDBACK_TIMEOUT_S",
    "SIM_HEARTBEAT_CONSUMER_MS", "SIM_LATE_FAULT_S", "STOP_TIMEOUT_S", "AxisPeaks", "JobResult", "Machine",
    "MachineError", "ModalState", "MotionCore", "MotionSnapshot", "OutputSwitch",
]
