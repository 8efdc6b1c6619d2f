"""What the task side's parts of :class:`motiond.runtime.machine.Machine` share, declared once.

Each part (:mod:`~motiond.runtime.jobs`, :mod:`~motiond.runtime.run_from_line`,
:mod:`~motiond.runtime.service`, :mod:`~motiond.runtime.status`) is a mixin of ``Machine`` and derives
from :class:`MachinePart`, which only declares (for the type checker and the reader) the attributes
``Machine`` gives them all; a part declares what else it uses itself.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from motiond.runtime.jobs import Job
    from motiond.runtime.motion import MotionCore
    from motiond.states import MachineStates


class MachinePart:
    if TYPE_CHECKING:
        motion: MotionCore  # the motion side: only through its interface
        interp: Any  # gcode_canon.interpreter.Interpreter
        states: MachineStates
        limits: Any  # planner.limits.MachineLimits
        names: tuple[str, ...]
        n: int
        T: float  # the cycle, s
        io: Any  # fieldbus.modbus.executor.IoExecutor, or None
        last_error: str
        last_error_utime: int
        _job: Job | None

        def event(self, severity: str, text: str, *, kind: str = "", source: str = "motiond",
                  file: str = "", line: int = 0) -> None: ...
