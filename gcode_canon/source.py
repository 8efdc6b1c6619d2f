"""Where lines come from: a text stream read one line at a time, never the whole file.

:class:`LineSource` numbers the lines, refuses over-long ones without reading them whole (a 10 MB line
costs 258 characters), and can mark a place and jump back to it (``mark``/``jump``), which the o-word
loops of a later issue need without holding the program in memory.
"""

from __future__ import annotations

import io
from collections.abc import Iterator
from pathlib import Path
from typing import TextIO

from gcode_canon.errors import GCodeError


class LineSource:
    def __init__(self, stream: TextIO, name: str, max_line_length: int = 256, *, owned: bool = False) -> None:
        self.stream = stream
        self.name = name
        self.max_line_length = max_line_length
        self.line = 0
        self._owned = owned

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

    def __iter__(self) -> Iterator[str]:
        """The lines from here on: :meth:`__next__`'s, as a generator (cheaper per line than a method
        call); it reads the stream and the line count afresh at each line, so ``jump`` and ``next``
        between its lines are seen."""
        readline = self.stream.readline
        limit = self.max_line_length + 2
        while True:
            try:
                text = readline(limit)
            except OSError as exc:
                raise GCodeError(f"Cannot read program: {exc}", self.name, self.line + 1) from None
            if not text:
                return
            self.line += 1
            if text[-1] == "\n":
                text = text[:-1]
            if len(text) > limit - 2:
                raise GCodeError(f"Line too long (more than {limit - 2} characters)", self.name, self.line)
            yield text

    def __next__(self) -> str:
        """The next line (:meth:`__iter__`'s reading, one line of it)."""
        for text in self:
            return text
        raise StopIteration

    def mark(self) -> tuple[int, int]:
        """A place to come back to: the start of the next line."""
        return self.stream.tell(), self.line

    def jump(self, mark: tuple[int, int]) -> None:
        self.stream.seek(mark[0])
        self.line = mark[1]

    def close(self) -> None:
        if self._owned:
            self.stream.close()
