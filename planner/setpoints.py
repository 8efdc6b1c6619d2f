"""What the planner hands the cycle loop: one timed setpoint per cycle.

This is the contract between ``planner`` and ``fieldbus``/``motiond``: the CANopen master turns
``positions`` into drive counts, the Modbus side performs the synchronized ``events`` in the same
cycle, and telemetry reports ``file``/``line``.
"""

from __future__ import annotations

from dataclasses import dataclass

from gcode_canon.commands import Canon


@dataclass(frozen=True, slots=True)
class Setpoint:
    """Commanded state for one cycle.

    ``positions`` holds one value per configured axis, in the machine's axis order and machine units
    (mm, degrees). ``events`` are the non-motion canonical commands that take effect in this cycle:
    synchronized outputs (M62/M63/M67) ride on the first cycle of the motion they belong to; sync
    points (dwell, M66, M0, tool change, program end) ride on the cycle where motion is at rest.
    """

    t: float
    positions: tuple[float, ...]
    file: str = ""
    line: int = 0
    events: tuple[Canon, ...] = ()


_new = object.__new__
_set_t, _set_positions, _set_file, _set_line, _set_events = (
    Setpoint.__dict__[name].__set__ for name in ("t", "positions", "file", "line", "events"))


def new_setpoint(t: float, positions: tuple[float, ...], file: str, line: int,
                 events: tuple[Canon, ...]) -> Setpoint:
    """``Setpoint(t, positions, file, line, events)`` for the cycle loop: the same frozen object, built
    through its slots (a frozen dataclass's ``__init__`` sets each field through
    ``object.__setattr__``, three times the cost, once per cycle)."""
    sp = _new(Setpoint)
    _set_t(sp, t)
    _set_positions(sp, positions)
    _set_file(sp, file)
    _set_line(sp, line)
    _set_events(sp, events)
    return sp
