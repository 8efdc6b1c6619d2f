"""``canon check``'s text of a block of commands: the number texts it keeps, and its two ways (numbers
looked up, or formatted with one ``%`` over the block) giving the same text as ``format_text``."""

from __future__ import annotations

import math
import random

import pytest

from gcode_canon.commands import (
    ArcFeed,
    Comment,
    Message,
    Plane,
    Pose,
    SetFeedRate,
    StraightFeed,
    StraightTraverse,
)
from motiond.cmd_check import _RETRY_FIRST, _NumberTexts, _TextBlock, format_text

MAIN = "main.ngc"

EDGES = [
    0.0, -0.0, 0.00004, -0.00004, 0.00005, -0.00005, 0.000049999, -0.000049999, 0.00006, -0.00006,
    5e-324, -5e-324, 1e-300, -1e-300,
    0.03125, -0.03125, 1.03125, 2.5, -2.5, 0.00015, -0.00025, 1.00005, -1.00005, 12.34565, -12.34575,
    1e15 + 0.5, 1e16, -1e16, 1e300, -1e300, math.inf, -math.inf, math.nan,
]
"""Zeros of both signs, values that print as "-0.0000" and just do not, exact binary halves at the
5th decimal (0.03125: rounded to even) and decimal ones that are not exact, large and extreme values."""


def reference(value: float) -> str:
    """``%.4f`` with "0.0000" for "-0.0000": the text ``_TextBlock.direct`` writes for a number."""
    text = "%.4f" % value  # noqa: UP031 (the reference is the % formatting itself)
    return "0.0000" if text == "-0.0000" else text


def random_values(rng: random.Random, n: int) -> list[float]:
    values = []
    for _ in range(n):
        kind = rng.random()
        if kind < 0.3:
            values.append(rng.uniform(-1000, 1000))
        elif kind < 0.5:  # as a program's words give them: 3 to 6 decimals
            values.append(float(f"{rng.uniform(-500, 500):.{rng.randint(3, 6)}f}"))
        elif kind < 0.65:  # exact binary halves at the 5th decimal
            values.append(rng.randint(-40000, 40000) / 32)
        elif kind < 0.8:  # around zero
            values.append(rng.uniform(-0.0002, 0.0002))
        else:
            values.append(rng.choice(EDGES))
    return values


def test_number_texts_are_percent_4f_without_negative_zero() -> None:
    rng = random.Random(18)
    texts = _NumberTexts()
    values = EDGES + random_values(rng, 20_000) + [1, -3, True, 0]
    for round_ in range(2):  # made, then found
        for v in values:
            assert texts[v] == reference(v) + ", ", (v, round_)
    assert texts[-0.0] == texts[0.0] == "0.0000, "
    assert texts[math.nan] == "nan, " and texts[math.inf] == "inf, " and texts[-math.inf] == "-inf, "


def random_commands(rng: random.Random, n: int, pool: list[float]) -> list:
    """Moves, arcs in every plane (A-W at zero or not), comments and messages with "-0.0000" and "%"
    in them, other commands, some from a subroutine's file; numbers drawn from ``pool``."""

    def pose(extra: float) -> Pose:
        axes = [rng.choice(pool) for _ in range(3)]
        more = [rng.choice(pool) if rng.random() < extra else 0.0 for _ in range(6)]
        return Pose(*axes, *more)

    out = []
    for k in range(n):
        line = rng.randint(0, 1_000_000) if rng.random() < 0.1 else k + 1
        file = "sub.ngc" if rng.random() < 0.05 else (MAIN if rng.random() < 0.95 else "")
        r = rng.random()
        if r < 0.45:
            cls = StraightFeed if rng.random() < 0.6 else StraightTraverse
            out.append(cls(pose(0.05), file=file, line=line))
        elif r < 0.8:
            plane = rng.choice(list(Plane)) if rng.random() < 0.2 else Plane.XY
            out.append(ArcFeed(pose(0.1), pose(0.05), plane, rng.choice([1, -1, 2, -3]),
                               file=file, line=line))
        elif r < 0.88:
            out.append(Comment(rng.choice(["plunge", "at -0.0000 and 100% %s", 'a "quote"', ""]),
                               file=file, line=line))
        elif r < 0.93:
            out.append(Message(rng.choice(["-0.0000 %d %%", "done"]), file=file, line=line))
        else:
            out.append(SetFeedRate(rng.choice(pool), file=file, line=line))
    return out


def expected_text(commands: list) -> str:
    """The block's text as ``format_text`` writes each command (the reference)."""
    return "".join(f"{c.file}:{c.line} {format_text(c)}\n" if c.file and c.file != MAIN
                   else f"{c.line:>6} {format_text(c)}\n" for c in commands)


@pytest.mark.parametrize("seed", range(6))
def test_both_ways_write_what_format_text_writes(seed: int) -> None:
    rng = random.Random(seed)
    pool = random_values(rng, 40 if seed % 2 else 5000)  # numbers that come back, or mostly new ones
    text = _TextBlock(MAIN)
    for _ in range(4):
        commands = random_commands(rng, rng.choice([1, 17, 256, 300]), pool)
        expected = expected_text(commands)
        assert text.cached(commands) == expected
        assert text.direct(commands) == expected
        assert text(commands) == expected


def moves(values: list[float]) -> list:
    return [StraightFeed(Pose(v, v + 0.5, -v), file=MAIN, line=k + 1) for k, v in enumerate(values)]


def test_known_numbers_are_looked_up_not_formatted_again() -> None:
    text = _TextBlock(MAIN)
    block = moves([float(k % 40) for k in range(256)])
    first = text(block)
    known = dict(text.texts)
    assert len(known) == len({v for c in block for v in c.end[:3]})
    assert text(block) == first and text.texts == known  # nothing made the second time
    assert text.wait == 0


def test_a_block_of_new_numbers_sends_the_next_blocks_the_direct_way() -> None:
    """A block whose numbers are mostly new: the next ``_RETRY_FIRST`` blocks are formatted directly,
    then the lookup is tried again (waiting twice as long after another such block); a block where it
    pays keeps it."""
    text = _TextBlock(MAIN)
    ways: list[str] = []
    cached, direct = text.cached, text.direct
    text.cached = lambda cmds: ways.append("cached") or cached(cmds)  # type: ignore[method-assign]
    text.direct = lambda cmds: ways.append("direct") or direct(cmds)  # type: ignore[method-assign]
    fresh = iter(range(10**6))

    def new_block() -> list:
        return moves([next(fresh) / 7 for _ in range(256)])

    text(new_block())
    assert ways == ["cached"] and text.wait == _RETRY_FIRST
    for _ in range(_RETRY_FIRST):
        text(new_block())
    assert ways == ["cached"] + ["direct"] * _RETRY_FIRST
    text(new_block())  # tried again, new numbers again: a longer wait
    assert ways[-1] == "cached" and text.wait == 2 * _RETRY_FIRST
    text.wait = 0
    repeated = moves([float(k % 10) for k in range(256)])
    text(repeated)
    text(repeated)
    assert ways[-2:] == ["cached", "cached"] and text.wait == 0
