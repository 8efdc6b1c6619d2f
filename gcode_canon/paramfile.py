"""The parameter (.var) file: numbered parameters that outlive the program, in LinuxCNC's format.

LinuxCNC's interpreter reads this file at start and writes it at exit so that G28/G30 positions,
the G92 offset and the nine work offsets (#5161-5390) survive a restart; user parameters (#31-5000)
present in the file are kept too. The format is two columns per line, the parameter number and its
value, in ascending order of number::

    5161    0.0
    5220    1.0

Reading follows LinuxCNC: a line is a parameter line when it begins with two numbers (an integer
and a value; anything after them that is not a number is ignored as a comment); every other line
(blank, a header, a comment) is skipped. Beyond LinuxCNC, these are errors naming the file and line
rather than silent surprises: numbers not ascending (LinuxCNC's "Parameter file out of order"),
a number outside 1-5601 or one of the read-only system parameters, a non-integer parameter number,
a value that is NaN or infinite, a third number on the line. Skipped lines that begin with a number
(``5221 1,5``: a decimal comma) are logged as warnings, since they are most likely mistakes.

A missing file raises ``FileNotFoundError``: the interpreter treats "no file yet" as all zeros, as
LinuxCNC does, and :func:`write_parameter_file` creates it. Every other problem is a
:class:`GCodeError`.

Writing is atomic (see :mod:`gcode_canon.atomicfile`): a crash at any moment leaves a readable file
with either the old or the new values, and the previous file is kept as ``FILE.bak``. Values are
written with ``repr`` so that they read back bit for bit (LinuxCNC writes six decimals).
"""

from __future__ import annotations

import logging
import math
import os
import re
from collections.abc import Mapping

from gcode_canon.atomicfile import BACKUP_SUFFIX, atomic_write_text, read_lines
from gcode_canon.errors import GCodeError
from gcode_canon.expressions import MAX_PARAMETER as _EXPRESSION_MAX_PARAMETER

log = logging.getLogger(__name__)

PERSISTENT = range(5161, 5391)
"""Numbered parameters saved in the file whatever it held before (G28, G30, G92, G54-G59.3)."""

USER = range(31, 5001)
"""User parameters: saved when present in the file before, or when non-zero."""

MAX_PARAMETER = _EXPRESSION_MAX_PARAMETER
"""Highest parameter number, 5601, as :mod:`gcode_canon.expressions` has it: LinuxCNC's
``restore_parameters`` (``rs274ngc_pre.cc``) refuses a number not below RS274NGC_MAX_PARAMETERS (5602,
the size of its array from 0) with "Parameter number out of range"."""

READ_ONLY = frozenset([*range(5021, 5030), *range(5400, 5414), *range(5420, 5429)])
"""LinuxCNC's read-only numbered parameters (``Interp::readonly_parameters``): machine position
#5021-5029, current tool #5400-5413, current position #5420-5428. The interpreter computes them,
so a value for one in a file would be meaningless and the file is rejected."""

__all__ = [
    "BACKUP_SUFFIX",
    "MAX_PARAMETER",
    "PERSISTENT",
    "READ_ONLY",
    "USER",
    "read_parameter_file",
    "write_parameter_file",
]

_INT = re.compile(r"[+-]?[0-9]+")
_FLOAT = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_NON_FINITE = re.compile(r"[+-]?(?:nan|inf|infinity)", re.IGNORECASE)


def _is_number(field: str) -> bool:
    return bool(_FLOAT.fullmatch(field) or _NON_FINITE.fullmatch(field))


def read_parameter_file(path: str | os.PathLike[str]) -> dict[int, float]:
    """Read a parameter file; return ``{number: value}`` for the parameters it holds, nothing more.

    Parameters the file does not mention are zero (the caller fills them in). A missing file raises
    ``FileNotFoundError``; anything else wrong raises :class:`GCodeError` with the file and line.
    """
    name = os.fspath(path)
    values: dict[int, float] = {}
    last = 0
    for lineno, text in read_lines(name, "parameter file"):
        fields = text.split()
        if len(fields) < 2 or not (_is_number(fields[0]) and _is_number(fields[1])):
            if fields and _is_number(fields[0]):
                log.warning("%s:%d: skipped, not a parameter number and a value: %r", name, lineno, text)
            continue
        if len(fields) > 2 and _is_number(fields[2]):
            raise GCodeError(
                f"expected a parameter number and a value, found a third number {fields[2]!r}", name, lineno
            )
        if not _INT.fullmatch(fields[0]):
            raise GCodeError(f"parameter number {fields[0]!r} is not an integer", name, lineno)
        number = int(fields[0])
        if not 1 <= number <= MAX_PARAMETER:
            raise GCodeError(f"Parameter number out of range: {number} (1 to {MAX_PARAMETER})", name, lineno)
        if number in READ_ONLY:
            raise GCodeError(
                f"#{number} is a read-only system parameter and cannot be set from a file", name, lineno
            )
        if number <= last:
            raise GCodeError(f"Parameter file out of order: #{number} after #{last}", name, lineno)
        value = float(fields[1])
        if not math.isfinite(value):
            raise GCodeError(f"#{number}: value {fields[1]!r} is not a finite number", name, lineno)
        values[number] = value
        last = number
    return values


def write_parameter_file(path: str | os.PathLike[str], values: Mapping[int, float]) -> None:
    """Save parameters atomically, keeping the previous file as ``path + ".bak"``.

    Written, in ascending order: every persistent parameter (#5161-5390), every parameter the
    existing file held (as LinuxCNC does), and every user parameter (#31-5000) whose value is not
    zero. Each gets ``values.get(number, 0.0)``. Raises :class:`GCodeError` naming the file when the
    existing file cannot be read (it is left as it is, like any file this fails to replace), when a
    value to write is not a finite number, or when the file cannot be written (read-only directory,
    disk full...).
    """
    name = os.fspath(path)
    try:
        before = read_parameter_file(name)
    except FileNotFoundError:
        before = {}
    except GCodeError as e:
        raise GCodeError(f"not saved, the existing parameter file is bad: {e.message}", e.file, e.line) from e
    numbers = set(PERSISTENT) | before.keys()
    numbers.update(n for n, v in values.items() if type(n) is int and n in USER and v != 0)
    lines = []
    for number in sorted(numbers):
        value = float(values.get(number, 0.0))
        if not math.isfinite(value):
            raise GCodeError(f"not saved: #{number} = {value!r} is not a finite number", name)
        lines.append(f"{number}\t{value!r}\n")
    try:
        atomic_write_text(name, "".join(lines), backup=True)
    except OSError as e:
        raise GCodeError(f"cannot save the parameter file: {e.strerror or e}", name) from e
