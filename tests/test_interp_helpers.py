"""Helpers shared by the interpreter tests (no tests here)."""

from __future__ import annotations

import pytest

from gcode_canon.commands import Canon, Pose
from gcode_canon.errors import GCodeError
from gcode_canon.interpreter import Interpreter
from gcode_canon.settings import InterpreterSettings


def run(text: str, interp: Interpreter | None = None, **settings: object) -> list[Canon]:
    """All commands of ``text`` (no M2 needed)."""
    if interp is None:
        options: dict = {"dry_run": True, "require_program_end": False, **settings}
        interp = Interpreter(InterpreterSettings(**options))
    return list(interp.run_string(text, "t.ngc"))


def ends(text: str, **settings: object) -> list[Pose]:
    return [c.end for c in run(text, **settings) if c.MOVES]


def last_end(text: str, **settings: object) -> tuple[float, ...]:
    return tuple(round(v, 6) for v in ends(text, **settings)[-1])


def error(text: str, **settings: object) -> GCodeError:
    with pytest.raises(GCodeError) as info:
        run(text, **settings)
    return info.value


def xyz(*values: float) -> tuple[float, ...]:
    return tuple(float(v) for v in values) + (0.0,) * (9 - len(values))
