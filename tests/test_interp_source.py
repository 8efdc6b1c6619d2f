"""The program's lines read a chunk at a time (:mod:`gcode_canon.source`): the same lines, line
numbers and errors as a ``readline`` per line, marks and jumps inside a chunk and across chunks, and
o-word loops and subroutines whose lines cross a chunk's end."""

from __future__ import annotations

import io
import random
from pathlib import Path

import pytest

from gcode_canon import source as source_module
from gcode_canon.commands import ArcFeed, StraightFeed, StraightTraverse
from gcode_canon.errors import GCodeError
from gcode_canon.interpreter import Interpreter
from gcode_canon.settings import InterpreterSettings
from gcode_canon.source import CHUNK, LineSource


class ReadlineSource:
    """The reference: a ``readline`` per line, with a limit (the reading before chunks)."""

    def __init__(self, stream: io.TextIOBase, max_line_length: int) -> None:
        self.stream, self.max, self.line = stream, max_line_length, 0

    def next(self) -> str | None:
        text = self.stream.readline(self.max + 2)
        if not text:
            return None
        self.line += 1
        if text[-1] == "\n":
            text = text[:-1]
        if len(text) > self.max:
            raise GCodeError(f"Line too long (more than {self.max} characters)", "p", self.line)
        return text

    def mark(self) -> tuple[int, int]:
        return self.stream.tell(), self.line

    def jump(self, mark: tuple[int, int]) -> None:
        self.stream.seek(mark[0])
        self.line = mark[1]


def random_program(rng: random.Random, max_length: int) -> bytes:
    """Lines of every length up to a little over ``max_length``, every kind of line end (\\r\\n split
    across chunks included), non-ASCII and undecodable bytes, a BOM or not, a last line without its end."""
    out = [b"\xef\xbb\xbf"] if rng.random() < 0.3 else []
    for _ in range(rng.randint(0, 1500)):
        r = rng.random()
        n = (rng.randint(max_length - 2, max_length + 3) if r < 0.01
             else rng.randint(0, 4) if r < 0.2 else rng.randint(5, 60))
        text = "".join(rng.choice("G1 X2.5 Y-0.1 (ok) #<a>=[1+2]") for _ in range(n)).encode()
        if rng.random() < 0.05:
            text += rng.choice([b"\xc3\xa9", b"\xff", b"\xe2\x82"])
        out.append(text + rng.choice([b"\n", b"\n", b"\n", b"\r\n", b"\r"]))
    if out and rng.random() < 0.5:
        out[-1] = out[-1].rstrip(b"\r\n")
    return b"".join(out)


def opened(path: Path) -> io.TextIOWrapper:
    return open(path, encoding="utf-8-sig", errors="surrogateescape", newline=None)


def outcome(fn):
    try:
        return fn()
    except GCodeError as exc:
        return ("error", exc.message, exc.line)


@pytest.mark.parametrize("seed", range(40))
def test_chunks_give_the_lines_readline_gives_with_marks_and_jumps(seed: int, tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    rng = random.Random(seed)
    max_length = rng.choice([20, 64, 256])
    if seed % 2:  # small chunks: many chunk ends, lines longer than a chunk
        monkeypatch.setattr(source_module, "CHUNK", rng.choice([7, 50, 300]))
    path = tmp_path / "p.ngc"
    path.write_bytes(random_program(rng, max_length))
    ref = ReadlineSource(opened(path), max_length)
    src = LineSource(opened(path), "p", max_length)
    other = LineSource(opened(path), "p", max_length)  # marks of one source used on another of the file
    marks: list[tuple] = []
    for _ in range(3000):
        r = rng.random()
        if r < 0.08:
            marks.append((ref.mark(), src.mark()))
        elif r < 0.14 and marks:
            ref_mark, mark = rng.choice(marks)
            ref.jump(ref_mark)
            if rng.random() < 0.3:  # read on from the other source
                src, other = other, src
            src.jump(mark)
        else:
            expected = outcome(lambda: (ref.next(), ref.line))
            got = outcome(lambda reading=src: (next(reading, None), reading.line))
            assert got == expected
            if expected[0] in (None, "error"):
                if not marks:
                    break
                ref_mark, mark = rng.choice(marks)  # on again from a mark
                ref.jump(ref_mark)
                src.jump(mark)


def test_a_chunk_holds_many_lines() -> None:
    src = LineSource.from_string("".join(f"G1 X{k}\n" for k in range(2000)))
    assert next(src) == "G1 X0"
    assert CHUNK // 10 < len(src.lines) < CHUNK and src.next == 1


def program_across_chunks(body: list[str], loop: str) -> tuple[str, str]:
    """A loop whose body (``body``) starts a few lines before a chunk's end, and the same written out."""
    pad = [f"(padding line {k:05d} {'.' * 40})" for k in range((CHUNK - 150) // 63)]  # 63 characters each
    looped = ["G21 G17 F100", *pad, *loop.format(body="\n".join(body)).splitlines(), "M2"]
    flat = ["G21 G17 F100", *pad, *(body * 3), "M2"]
    return "\n".join(looped) + "\n", "\n".join(flat) + "\n"


def moves(text: str, tmp_path: Path) -> list[tuple]:
    path = tmp_path / "p.ngc"
    path.write_text(text)
    cmds = Interpreter(InterpreterSettings(dry_run=True, subroutine_path=[tmp_path])).run_file(path)
    return [(type(c).__name__, c.end, getattr(c, "center", None))
            for c in cmds if isinstance(c, StraightFeed | StraightTraverse | ArcFeed)]


@pytest.mark.parametrize("loop", [
    "o1 repeat [3]\n{body}\no1 endrepeat",
    "#9 = 0\no2 while [#9 lt 3]\n{body}\n#9 = [#9 + 1]\no2 endwhile",
    "#9 = 0\no3 do\n{body}\n#9 = [#9 + 1]\no3 while [#9 lt 3]",
    "o<s> sub\n{body}\no<s> endsub\no<s> call\no<s> call\no<s> call",
])
def test_loops_and_subroutines_across_a_chunks_end(loop: str, tmp_path: Path) -> None:
    body = [f"G1 X{k} Y{k % 3}" if k % 4 else f"G2 X{k} Y{k % 3 + 1} R5" for k in range(1, 80)]
    looped, flat = program_across_chunks(body, loop)
    assert len(looped.split("o", 1)[0]) < CHUNK < len(looped) - 200
    got, expected = moves(looped, tmp_path), moves(flat, tmp_path)
    assert got == expected and len(got) == 3 * len(body)
