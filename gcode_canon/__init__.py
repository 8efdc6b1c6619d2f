"""gcode_canon: RS274/NGC (LinuxCNC dialect) text in, canonical machining commands out.

Pure Python with no fieldbus imports: the lowest layer of canon.

Entry points (imported lazily, so ``import gcode_canon.commands`` stays light)::

    from gcode_canon import Interpreter, InterpreterSettings
    interp = Interpreter(InterpreterSettings(var_file="params.var"), machine)
    for cmd in interp.run_file("part.ngc"):   # lazy: one line read at a time
        ...                                    # machine callbacks run when the loop resumes
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from gcode_canon.commands import AXES, Canon, Pose
from gcode_canon.errors import GCodeError

if TYPE_CHECKING:
    from gcode_canon.interpreter import Interpreter
    from gcode_canon.machine import DryRunMachine, MachineCallbacks
    from gcode_canon.settings import InterpreterSettings

__all__ = [
    "AXES",
    "Canon",
    "DryRunMachine",
    "GCodeError",
    "Interpreter",
    "InterpreterSettings",
    "MachineCallbacks",
    "Pose",
]

_LAZY = {
    "Interpreter": "gcode_canon.interpreter",
    "InterpreterSettings": "gcode_canon.settings",
    "DryRunMachine": "gcode_canon.machine",
    "MachineCallbacks": "gcode_canon.machine",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'gcode_canon' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(module), name)
