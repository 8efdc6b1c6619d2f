"""Progress of a long command (``canon plan``, ``canon check``) over a program's lines: the line
reached, percent, lines per second and the time left, on stderr when it is a terminal, erased at the
end. Callers turn it off for ``--json`` and when the output would land in a pipe or a file."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Any

UPDATE_S = 0.1  # redraw at most this often


def count_lines(path: str) -> int:
    n = 0
    last = b"\n"
    with open(path, "rb") as fh:
        while chunk := fh.read(1 << 20):
            n += chunk.count(b"\n")
            last = chunk[-1:]
    return n + (last != b"\n")


@contextlib.contextmanager
def line_progress(description: str, path: str, *, enabled: bool) -> Iterator[Callable[[int], None]]:
    """``with line_progress("planning", file, enabled=...) as advance: advance(line)``: ``advance`` is
    cheap to call for every command (it redraws ten times a second at most)."""
    if not enabled:
        yield lambda _line: None
        return
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        Progress,
        ProgressColumn,
        TaskProgressColumn,
        TextColumn,
        TimeRemainingColumn,
    )
    from rich.text import Text

    class Rate(ProgressColumn):
        def render(self, task: Any) -> Text:
            speed = task.speed
            return Text(f"{speed:,.0f} lines/s" if speed else "- lines/s")

    total = max(count_lines(path), 1)
    console = Console(stderr=True)
    with Progress(TextColumn("{task.description}"), BarColumn(),
                  TextColumn("line {task.completed:,.0f}/{task.total:,.0f}"), TaskProgressColumn(), Rate(),
                  TextColumn("ETA"), TimeRemainingColumn(), console=console, transient=True) as progress:
        task = progress.add_task(description, total=total)
        next_t = 0.0

        def advance(line: int) -> None:
            nonlocal next_t
            now = time.monotonic()
            if now >= next_t:
                next_t = now + UPDATE_S
                progress.update(task, completed=min(line, total))

        yield advance


def tracked(commands: Iterable[Any], main: str, advance: Callable[[int], None]) -> Iterator[Any]:
    """The commands as they are, telling ``advance`` the main program's line each one comes from."""
    for cmd in commands:
        if cmd.file == main:
            advance(cmd.line)
        yield cmd
