"""Where lines come from: a text stream read a chunk of lines at a time, never the whole file.

:class:`LineSource` numbers the lines, refuses over-long ones without reading them whole (a 10 MB line
costs a chunk and 258 characters), and can mark a place and jump back to it (``mark``/``jump``), which
the o-word loops need without holding the program in memory.
"""

from __future__ import annotations

import io
from collections.abc import Iterator
from pathlib import Path
from typing import TextIO

from gcode_canon.errors import GCodeError

Mark = tuple[int, int, int]
"""A place in a :class:`LineSource` (:meth:`LineSource.mark`): where its chunk starts in the stream
(``tell``), the line's index in the chunk, the line count before it."""

CHUNK = 8192
"""Characters read at a time (then to the end of the line they stop in): about 300 lines of G-code.
A line from a chunk costs a list's index where a ``readline`` cost about 125 ns (5 % of a plain line,
2 % of ``canon check``'s time on bench/interpreter.py's programs); a jump out of the chunk reads one
again, as a text stream's ``seek`` does."""


class LineSource:
    """The lines of a text stream, numbered, read :data:`CHUNK` characters at a time.

    :attr:`lines` holds the chunk's lines (newlines taken off; the last one may lack its end: the
    stream's last line, or one longer than allowed), :attr:`next` the index of the next line to give,
    :attr:`line` the count of lines given. The interpreter's loop reads these itself, as
    :meth:`__iter__` does (a generator in between costs its resumption at every line)."""

    def __init__(self, stream: TextIO, name: str, max_line_length: int = 256, *, owned: bool = False) -> None:
        self.stream = stream
        self.name = name
        self.max_line_length = max_line_length
        self.line = 0
        self._owned = owned
        self.lines: list[str] = []
        self.next = 0
        self._at: int | None = None  # where the chunk of ``lines`` starts in the stream (tell)

    @classmethod
    def from_file(cls, path: Path | str, max_line_length: int = 256) -> LineSource:
        try:
            stream = open(path, encoding="utf-8-sig", errors="surrogateescape", newline=None)  # noqa: SIM115
        except OSError as exc:
            raise GCodeError(f"Cannot open program: {exc.strerror}", str(path), 0) from None
        return cls(stream, str(path), max_line_length, owned=True)

    @classmethod
    def from_string(cls, text: str, name: str = "<string>", max_line_length: int = 256) -> LineSource:
        return cls(io.StringIO(text, newline=None), name, max_line_length, owned=True)

    def fill(self) -> bool:
        """Read the chunk after :attr:`lines` into it (``next`` back to 0); False at the stream's end.
        A chunk ends at the end of a line: the line it stops in is read to its end, or to one
        character more than a line may have (that line is then refused when it is reached, as a
        ``readline`` with a limit refused it)."""
        stream = self.stream
        try:
            at: int | None = stream.tell()
        except OSError:  # a stream that cannot seek: read on, and mark() says it cannot
            at = None
        try:
            text = stream.read(CHUNK)
            if text and text[-1] != "\n":
                text += stream.readline(self.max_line_length + 2)
        except OSError as exc:
            raise GCodeError(f"Cannot read program: {exc}", self.name, self.line + 1) from None
        if not text:
            self.lines = []
            self.next = 0
            self._at = None
            return False
        lines = text.split("\n")
        if not lines[-1]:  # the chunk's last line had its newline
            lines.pop()
        self.lines = lines
        self.next = 0
        self._at = at
        return True

    def too_long(self) -> GCodeError:
        """The error for the line just counted, longer than a line may be."""
        return GCodeError(f"Line too long (more than {self.max_line_length} characters)", self.name,
                          self.line)

    def __iter__(self) -> Iterator[str]:
        """The lines from here on, as a generator; it reads the chunk, its index and the line count
        afresh at each line, so ``jump`` and ``next`` between its lines are seen."""
        while True:
            i = self.next
            if i >= len(self.lines):
                if not self.fill():
                    return
                i = 0
            text = self.lines[i]
            self.next = i + 1
            self.line += 1
            if len(text) > self.max_line_length:
                raise self.too_long()
            yield text

    def __next__(self) -> str:
        """The next line (:meth:`__iter__`'s reading, one line of it)."""
        for text in self:
            return text
        raise StopIteration

    def mark(self) -> Mark:
        """A place to come back to: the start of the next line."""
        if self._at is None or self.next >= len(self.lines):  # nothing of the chunk left: where it ends
            return self.stream.tell(), 0, self.line
        return self._at, self.next, self.line

    def jump(self, mark: Mark) -> None:
        """Go back (or on) to ``mark``, a mark of this source or of another one of the same file: in the
        chunk held, or its chunk read again (the same chunk, read from the same place)."""
        at, index, line = mark
        if at != self._at or index > len(self.lines):
            self.stream.seek(at)
            self._at = None
            self.lines = []
            self.next = 0
            if index:
                self.fill()
        self.next = index
        self.line = line

    def close(self) -> None:
        if self._owned:
            self.stream.close()
