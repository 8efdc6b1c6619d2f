"""Active comments: (MSG,...), (DEBUG,...), (PRINT,...), (LOGOPEN/LOGAPPEND/LOGCLOSE/LOG,...),
(PROBEOPEN file) and (PROBECLOSE).

Only the last comment of a line is active (LinuxCNC's rule); a ``;`` comment is always the last.
DEBUG, PRINT and LOG expand ``#123`` and ``#<name>`` to the value with six decimals (``######`` for a
named parameter that does not exist). LOG and probe files are only written inside the configured directory.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import TextIO

from gcode_canon.errors import GCodeError
from gcode_canon.expressions import MAX_PARAMETER
from gcode_canon.parameters import Parameters

log = logging.getLogger(__name__)

_KEYWORDS = ("logappend", "logclose", "logopen", "debug", "print", "msg", "log")
_REF = re.compile(r"#(?:<([^>]*)>|([0-9]+))")


def classify(comment: str) -> tuple[str, str]:
    """(keyword, rest) for an active comment, ("", comment) otherwise.

    The keyword may be written with spaces and in any case before its comma: ``( m s g , hi)``.
    """
    comma = comment.find(",")
    head = comment if comma < 0 else comment[:comma]
    folded = "".join(head.split()).lower()
    if comma >= 0 and folded in ("msg", "debug", "print", "log", "logopen", "logappend", "abort"):
        return folded, comment[comma + 1:]
    if comma < 0 and folded in ("logclose", "probeclose"):
        return folded, ""
    stripped = comment.lstrip()
    if stripped[:9].lower() == "probeopen":
        return "probeopen", stripped[9:].strip()
    return "", comment


def expand(text: str, params: Parameters) -> str:
    """Replace parameter references in ``text`` by their values."""

    def value(m: re.Match[str]) -> str:
        name, number = m.group(1), m.group(2)
        if name is not None:
            folded = "".join(name.split()).lower()
            try:
                return f"{params.get_named(folded):.6f}"
            except GCodeError:
                return "######"
        index = int(number) if len(number) <= 6 else 0
        if not 1 <= index <= MAX_PARAMETER:
            return m.group()
        return f"{params.get_numbered(index):.6f}"

    return _REF.sub(value, text)


class LogFiles:
    """The one open LOG file, confined to ``directory``."""

    def __init__(self, directory: Path | str | None) -> None:
        self.directory = Path(directory).resolve() if directory is not None else None
        self.stream: TextIO | None = None

    def open(self, name: str, append: bool) -> None:
        self.close()
        if self.directory is None:
            raise GCodeError("LOG files are disabled: no log directory is configured")
        name = name.strip()
        if not name:
            raise GCodeError("LOGOPEN needs a file name")
        path = (self.directory / name).resolve()
        if not path.is_relative_to(self.directory) or path == self.directory:
            raise GCodeError(f"LOG file {name!r} is outside the log directory {self.directory}")
        try:
            self.stream = open(path, "a" if append else "w", encoding="utf-8")  # noqa: SIM115
        except OSError as exc:
            raise GCodeError(f"Cannot open LOG file {path}: {exc.strerror}") from None

    def write(self, text: str) -> None:
        if self.stream is None:
            log.debug("(LOG,...) with no open log file: %s", text)
            return
        self.stream.write(text + "\n")

    def close(self) -> None:
        if self.stream is not None:
            self.stream.close()
            self.stream = None
