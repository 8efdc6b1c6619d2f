"""The records that cross between the machine's parts: what a job did, what rides with its commands.

Plain data, no behaviour, so that both sides of the future process boundary (docs/daemon.md) can
hold them: :class:`ModalState` travels with the canonical commands from the task side to the motion
side; :class:`Stream` is the motion side's accounting of one job's motion (peaks, the line reached,
the outputs switched), read back by the task side when the job ends and turned into a
:class:`JobResult`.
"""

from __future__ import annotations

import concurrent.futures
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar

from gcode_canon import commands as C


def deferred(fn: Callable[[], Any]) -> tuple[Callable[[], None], concurrent.futures.Future[Any]]:
    """``fn`` as a call for another thread to run (the cycle thread, the hooks thread), and the future
    that gets its result or its exception."""
    fut: concurrent.futures.Future[Any] = concurrent.futures.Future()

    def call() -> None:
        try:
            fut.set_result(fn())
        except BaseException as exc:
            fut.set_exception(exc)

    return call, fut


class MachineError(Exception):
    """The machine could not be brought up (boot, I/O, telemetry); the message says what and where."""


@dataclass
class AxisPeaks:
    velocity: float = 0.0
    acceleration: float = 0.0
    jerk: float = 0.0
    following_error: float = 0.0


@dataclass
class OutputSwitch:
    """A Modbus output the program switched, in the cycle it was handed to the I/O side."""

    cycle: int
    t: float  # monotonic time of that cycle
    kind: str  # "digital" or "analog"
    index: int
    value: float
    synced: bool
    file: str
    line: int
    name: str = ""  # kind "function": the I/O map's function (spindle_on, coolant_flood ...)


@dataclass
class JobResult:
    """What a finished program (or MDI line) did: ``error`` is empty when it ended normally."""

    program: str
    ok: bool
    error: str = ""
    aborted: bool = False
    duration_s: float = 0.0
    cycles: int = 0
    cycle_s: float = 0.0
    late_cycles: int = 0
    peaks: dict[str, AxisPeaks] = field(default_factory=dict)
    outputs: list[OutputSwitch] = field(default_factory=list)
    final_commanded: tuple[float, ...] = ()
    final_actual: tuple[float, ...] = ()
    expected_final: tuple[float, ...] = ()
    first_cycle: int = 0
    # where the time went (the run summary explains a run longer than its motion with these)
    moving_cycles: int = 0  # cycles in which some axis moved
    first_setpoint_s: float = 0.0  # from the start of the job to its first setpoint
    last_setpoint_s: float = 0.0  # ... to its last
    late_s: list[float] = field(default_factory=list)  # how late each late cycle of the job started


@dataclass(frozen=True, slots=True)
class ModalState(C.Canon):
    """The interpreter's modal state after a line, travelling with the commands to the status.

    Not a machining command. The interpreter reads up to :data:`motiond.runtime.motion.QUEUE_MAX`
    commands ahead of the motion, so its own state describes text not yet cut. The job thread puts one
    of these in front of the first command of a line whose modal state differs from the previous
    line's; the planner passes it on as an event riding on the first setpoint of the next motion (or
    sync point), exactly as it does a synchronized output (M62), and the cycle thread shows it in the
    status from that setpoint on: the state of the block being executed.
    """

    NAME: ClassVar[str] = "MODAL_STATE"
    gcodes: tuple[str, ...] = ()
    mcodes: tuple[str, ...] = ()
    feed: float = 0.0
    tool: int = 0
    tool_length_offset: float = 0.0


class Stream:
    """The motion side's accounting of one job's commands, written by the cycle thread only.

    ``input_done``: the job's end marker reached the planner (everything it sent is planned).
    The task side reads the rest when the job ends (:class:`JobResult`).
    """

    def __init__(self, n_axes: int) -> None:
        self.input_done = False
        # MDI: the job answers M66 and probes before it queues them (the line's moves before have
        # already run), so the planner goes on at once when it reaches their sync point
        self.answered_ahead = False
        self.peaks = [AxisPeaks() for _ in range(n_axes)]
        self.outputs: list[OutputSwitch] = []
        self.line = 0  # the line of the last setpoint that carried one
        self.moving_cycles = 0
        self.t_first = 0.0  # monotonic time of the first and last setpoint (0: none yet)
        self.t_last = 0.0
