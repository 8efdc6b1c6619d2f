"""The tool table, in LinuxCNC's file format: what the interpreter knows about each tool.

One tool per line, words in any order, letters in either case, a comment after ``;``::

    T1 P1 Z+0.511 D0.125 ;1/8 end mill
    T7 P3 X-0.2 Z12.5 D3 I95 J155 Q2 ;lathe tool

``T`` tool number (required, unsigned), ``P`` pocket (0-1000, 0 the spindle; optional, 0 when
absent), ``X Y Z A B C U V W`` offsets, ``D`` diameter, ``I`` front angle, ``J`` back angle,
``Q`` orientation (integer 0-9); words not given are zero. Blank lines and lines starting with
``;`` are ignored. Any other word, a repeated word, a missing ``T``, a number that does not parse
and a tool number given twice are errors naming the file and line (LinuxCNC skips such lines with a
console message; a machine moving with a tool length it silently dropped is worse than an error).
Pocket numbers given twice are logged as warnings, as LinuxCNC does.

Units: LinuxCNC stores the table in machine units. canon's machine unit is the millimetre
(see :mod:`gcode_canon.commands`), so offsets and diameters are read as millimetres, and angles
(A B C offsets, I, J) as degrees. A table written for an inch machine must be converted first.

Tool 0 means "no tool in the spindle". A ``T0`` line is allowed (LinuxCNC's plasma and lathe
configurations use one for the offsets in effect with no tool); without one, ``get(0)`` is None.

Writing is atomic and keeps the previous file as ``FILE.bak`` (see :mod:`gcode_canon.atomicfile`);
numbers are written with ``repr`` so they read back exactly. Whole-line comments are not kept.
"""

from __future__ import annotations

import logging
import math
import operator
import os
import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

from gcode_canon.atomicfile import atomic_write_text, read_lines
from gcode_canon.commands import AXES, ORIGIN, Pose
from gcode_canon.errors import GCodeError

log = logging.getLogger(__name__)

MAX_POCKET = 1000
"""Highest pocket number LinuxCNC accepts (its manual: "The maximum pocket number is 1000")."""

MAX_TOOL = 2**31 - 1
"""Highest tool number (LinuxCNC keeps it in a C ``int``)."""

__all__ = ["MAX_POCKET", "MAX_TOOL", "Tool", "ToolTable", "format_tool_line", "read_tool_table"]


@dataclass(frozen=True, slots=True)
class Tool:
    """One tool: its number, pocket, offsets (mm; degrees for A B C), and the cutter's shape.

    ``front_angle``, ``back_angle`` and ``orientation`` describe a lathe tool (I, J, Q words).
    Invalid values raise ``ValueError`` (``TypeError`` for a non-integer number, pocket or orientation),
    so a bad tool never reaches a written table.
    """

    number: int
    pocket: int = 0
    offset: Pose = field(default=ORIGIN)
    diameter: float = 0.0
    front_angle: float = 0.0
    back_angle: float = 0.0
    orientation: int = 0
    comment: str = ""

    def __post_init__(self) -> None:
        # Normalise so that what is written reads back equal: integers stay integers (a float tool
        # number would be written "T1.0", which no reader accepts), lengths become floats, and the
        # comment loses the surrounding blanks the file format cannot keep.
        for name in ("number", "pocket", "orientation"):
            object.__setattr__(self, name, operator.index(getattr(self, name)))
        for name in ("diameter", "front_angle", "back_angle"):
            object.__setattr__(self, name, float(getattr(self, name)))
        object.__setattr__(self, "offset", Pose(*(float(v) for v in self.offset)))
        object.__setattr__(self, "comment", str(self.comment).strip())
        if not 0 <= self.number <= MAX_TOOL:
            raise ValueError(f"tool number {self.number} out of range (0 to {MAX_TOOL})")
        if not 0 <= self.pocket <= MAX_POCKET:
            raise ValueError(f"pocket {self.pocket} out of range (0 to {MAX_POCKET})")
        if not 0 <= self.orientation <= 9:
            raise ValueError(f"orientation Q{self.orientation} out of range (0 to 9)")
        for name, value in (
            *zip(AXES, self.offset, strict=True),
            ("diameter", self.diameter),
            ("front angle", self.front_angle),
            ("back angle", self.back_angle),
        ):
            if not math.isfinite(value):
                raise ValueError(f"{name} {value!r} is not a finite number")
        if any(c in self.comment for c in "\r\n\0"):
            raise ValueError("a tool comment must be one line of text")


class ToolTable:
    """Tools by number. Iterating gives them sorted by number."""

    def __init__(self, tools: Iterable[Tool] = ()) -> None:
        self._tools: dict[int, Tool] = {}
        for tool in tools:
            self.set(tool)

    def get(self, number: int) -> Tool | None:
        """The tool numbered ``number``, or None if the table has no such tool."""
        return self._tools.get(number)

    def set(self, tool: Tool) -> None:
        """Add ``tool``, replacing any tool with the same number (G10 L1 and friends)."""
        self._tools[tool.number] = tool

    def remove(self, number: int) -> None:
        """Forget tool ``number`` (nothing happens if there is none)."""
        self._tools.pop(number, None)

    def tools(self) -> Iterator[Tool]:
        """Every tool, in ascending tool number."""
        return iter(sorted(self._tools.values(), key=lambda t: t.number))

    __iter__ = tools

    def __len__(self) -> int:
        return len(self._tools)

    def __contains__(self, number: object) -> bool:
        return number in self._tools

    def __eq__(self, other: object) -> bool:
        return isinstance(other, ToolTable) and self._tools == other._tools

    __hash__ = None  # type: ignore[assignment]  # mutable

    def __repr__(self) -> str:
        return f"ToolTable({list(self.tools())!r})"

    def write(self, path: str | os.PathLike[str], *, backup: bool = True) -> None:
        """Save atomically (a crash leaves the old or the new table), the old one kept as ``.bak``.

        Raises :class:`GCodeError` naming the file when it cannot be written.
        """
        name = os.fspath(path)
        text = "".join(format_tool_line(tool) + "\n" for tool in self.tools())
        try:
            atomic_write_text(name, text, backup=backup)
        except OSError as e:
            raise GCodeError(f"cannot save the tool table: {e.strerror or e}", name) from e


def _signed(value: float) -> str:
    text = repr(float(value))
    return text if text.startswith("-") else "+" + text


def format_tool_line(tool: Tool) -> str:
    """One line of the file for ``tool``, without the newline; zero words are left out."""
    words = [f"T{tool.number}", f"P{tool.pocket}"]
    words += [f"{axis.upper()}{_signed(v)}" for axis, v in zip(AXES, tool.offset, strict=True) if v]
    for letter, v in (("D", tool.diameter), ("I", tool.front_angle), ("J", tool.back_angle)):
        if v:
            words.append(f"{letter}{_signed(v)}")
    if tool.orientation:
        words.append(f"Q{tool.orientation}")
    if tool.comment:
        words.append(f";{tool.comment}")
    return " ".join(words)


_INT = re.compile(r"[+-]?[0-9]+")
_FLOAT = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_INT_WORDS = {"T": "tool number", "P": "pocket", "Q": "orientation"}
_FLOAT_WORDS = {
    **{axis.upper(): f"{axis.upper()} offset" for axis in AXES},
    "D": "diameter",
    "I": "front angle",
    "J": "back angle",
}


def _parse_line(text: str, name: str, lineno: int) -> Tool | None:
    words, _, comment = text.partition(";")
    if not words.strip():
        return None
    seen: dict[str, int | float] = {}
    for word in words.split():
        letter, number = (word[0].upper() if word[0].isascii() else "?"), word[1:]
        if letter in _INT_WORDS:
            if not _INT.fullmatch(number):
                raise GCodeError(f"{_INT_WORDS[letter]} in {word!r} is not an integer", name, lineno)
            value: int | float = int(number)
        elif letter in _FLOAT_WORDS:
            if not _FLOAT.fullmatch(number):
                raise GCodeError(f"{_FLOAT_WORDS[letter]} in {word!r} is not a number", name, lineno)
            value = float(number)
            if not math.isfinite(value):
                raise GCodeError(f"{_FLOAT_WORDS[letter]} in {word!r} is not a finite number", name, lineno)
        else:
            raise GCodeError(
                f"unknown word {word!r} (a tool line has T P X Y Z A B C U V W D I J Q and ;comment)",
                name,
                lineno,
            )
        if letter in seen:
            raise GCodeError(f"{letter} word given twice", name, lineno)
        seen[letter] = value
    if "T" not in seen:
        raise GCodeError("tool line without a T word (tool number)", name, lineno)
    try:
        return Tool(
            number=int(seen["T"]),
            pocket=int(seen.get("P", 0)),
            offset=Pose(*(float(seen.get(axis.upper(), 0.0)) for axis in AXES)),
            diameter=float(seen.get("D", 0.0)),
            front_angle=float(seen.get("I", 0.0)),
            back_angle=float(seen.get("J", 0.0)),
            orientation=int(seen.get("Q", 0)),
            comment=comment.strip(),
        )
    except ValueError as e:
        raise GCodeError(str(e), name, lineno) from None


def read_tool_table(path: str | os.PathLike[str]) -> ToolTable:
    """Read a tool table file.

    A missing file raises ``FileNotFoundError``; every other problem raises :class:`GCodeError`
    naming the file and the line.
    """
    name = os.fspath(path)
    table = ToolTable()
    where: dict[int, int] = {}
    pockets: dict[int, int] = {}
    for lineno, text in read_lines(name, "tool table"):
        if text.lstrip().startswith(";"):
            continue
        tool = _parse_line(text, name, lineno)
        if tool is None:
            continue
        if tool.number in where:
            raise GCodeError(
                f"tool T{tool.number} already defined on line {where[tool.number]}", name, lineno
            )
        if tool.pocket and tool.pocket in pockets:
            log.warning(
                "%s:%d: pocket P%d already holds the tool of line %d",
                name,
                lineno,
                tool.pocket,
                pockets[tool.pocket],
            )
        where[tool.number] = lineno
        pockets.setdefault(tool.pocket, lineno)
        table.set(tool)
    return table
