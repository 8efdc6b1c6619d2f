"""Compiled lines (gcode_canon.compiled) give what parse_line gives: the same Block, or the same error,
for the parameter values in force when the line is read again."""

from __future__ import annotations

import random

import pytest

from gcode_canon.compiled import CompiledLine, LineCache, _Compiler
from gcode_canon.errors import GCodeError
from gcode_canon.expressions import ExpressionReader
from gcode_canon.lexer import Block, parse_line
from gcode_canon.parameters import Parameters

LINES = [
    "G1 X[#1 + 0.5] Y[#2 * COS[30]] F600",
    "#1 = [#1 + 0.5] #<depth> = [-[#1 MOD 3] * 0.25]",
    "G1 Z#<depth> (plunge)",
    "G1 X[10 + SIN[#1] * 2] Y[20 * COS[30]]",
    "G#3 X#1",
    "G[#3 * 1e307]",  # G code from a parameter: 0, 1, 2.5 (unknown), 1000 (out of range) ...
    "M#4",
    "##5 = 7",
    "#[#5 + 1] = [#1 / #2]",  # divide by zero when #2 is 0
    "X[#1 ** #2] Y[#1 MOD #2]",
    "X[ATAN[#1]/[#2]] Y[EXISTS[#<depth>]] Z[EXISTS[#[#5]]]",
    "X[SQRT[#1]] Y[LN[#2]] Z[ACOS[#1]]",
    "X[#1 EQ #2] Y[#1 LT #2] Z[[#1 GT #2] AND [#2 OR 0] XOR 1]",
    "/N20 G1 X-#1 Y+#2 ; note #3",
    "X#<undefined> Y[1/0]",
    "X[1/#2] Y#<undefined>",
    "#<_g> = [ATAN[1]/[2] + SQRT[4] - LN[EXP[1]] MOD 3]",
    "X#[#1]",  # out of range or a non-integer index, depending on #1
    "G1 X1 X#1",  # repeated word: the compiler refuses, parse_line says which error comes first
    "X[#1 + 1",  # unclosed: not compiled
    "X[#1 * 10] Y[10 * #2] Z[#3 * #4]",  # overflow with a constant on either side or none (1e308)
    "X[#1 + #2] Y[-1 - #3 - #4] Z[#5 - 1 + [2 - #6]]",
    "X[TAN[#1] + ABS[-#2]] Y[SIN[#3] * COS[#4 * 10]] Z[ABS[#5 * #6]]",
]

VALUES = [0.0, 1.0, 2.0, -1.0, 0.5, 3.0, 1000.0, 2.5, 1e308, 5601.0, 5602.0, 0.99999]


def _outcome(fn):
    try:
        block = fn()
    except GCodeError as exc:
        return ("error", str(exc))
    return ("block", block.g, block.m, block.words, block.assigns, block.comments, block.deleted,
            block.line_number, block.o_text, block.axes)


def _reader(seed: int) -> tuple[ExpressionReader, Parameters]:
    params = Parameters()
    rng = random.Random(seed)
    for k in range(1, 8):
        params.numbered[k] = rng.choice(VALUES)
    if rng.random() < 0.7:
        params.assign("depth", rng.choice(VALUES))
    return ExpressionReader(params), params


@pytest.mark.parametrize("seed", range(40))
def test_compiled_lines_give_what_parse_line_gives(seed: int) -> None:
    reader, _ = _reader(seed)
    cache = LineCache(reader)
    for raw in LINES:
        first = _outcome(lambda raw=raw: cache.parse(raw))
        assert first == _outcome(lambda raw=raw: parse_line(raw, reader)), raw
        for _ in range(2):  # the second and third readings: compiled (or cached) where possible
            assert _outcome(lambda raw=raw: cache.parse(raw)) == first, raw


def test_lines_are_compiled_or_kept_and_refused_ones_go_to_parse_line() -> None:
    reader, params = _reader(1)
    params.numbered[2] = 1.0
    cache = LineCache(reader)
    for raw in ("G1 X1 Y2", "G1 X[#1 + 1]", "o100 if [#1 GT 0]"):
        cache.parse(raw)
        cache.parse(raw)
    for _ in range(2):
        with pytest.raises(GCodeError, match="Multiple X words"):
            cache.parse("G1 X1 X#1")
    entries = cache._entries
    assert isinstance(entries["G1 X1 Y2"], Block)  # no parameter: parsed once, the Block reused
    assert cache.parse("G1 X1 Y2") is entries["G1 X1 Y2"]
    assert isinstance(entries["o100 if [#1 GT 0]"], Block)  # the flow evaluates o-word lines itself
    assert isinstance(entries["G1 X[#1 + 1]"], CompiledLine)
    assert "G1 X1 X#1" not in entries  # a line in error is not kept: parse_line says it each time
    params.numbered[1] = 41.0  # a compiled line reads the parameters in force
    assert cache.parse("G1 X[#1 + 1]").words == {"x": 42.0}


def test_the_cache_is_bounded() -> None:
    reader, _ = _reader(2)
    cache = LineCache(reader, size=16)
    for k in range(100):
        cache.parse(f"G1 X{k}")
    assert len(cache._entries) <= 16


def test_a_g_code_too_large_to_round_is_out_of_range() -> None:
    reader, params = _reader(3)
    params.numbered[3] = 1e308  # ten times it is infinite: was an internal error (OverflowError)
    cache = LineCache(reader)
    for _ in range(3):
        with pytest.raises(GCodeError, match="G code out of range"):
            cache.parse("G#3")


def test_compiled_arithmetic_and_trigonometry_call_no_helper(monkeypatch) -> None:
    """+ - * check their result inline (``_finite`` only to say the error) and SIN COS TAN ABS are
    computed directly, not through ``_unary``'s chain of name tests."""
    import gcode_canon.compiled as compiled

    calls: list[str] = []
    finite, unary = compiled._finite, compiled._unary
    monkeypatch.setattr(compiled, "_finite", lambda *a: calls.append("finite") or finite(*a))
    monkeypatch.setattr(compiled, "_unary", lambda *a: calls.append("unary") or unary(*a))
    reader, params = _reader(3)
    params.numbered[1], params.numbered[2], params.numbered[3] = 30.0, 1.0, 0.5
    cache = LineCache(reader)
    raw = "X[[#1 + 1] * [2 - #2] * #3 - 4] Y[SIN[#1] + COS[#2] + TAN[#3] + ABS[-#1]]"
    cache.parse(raw)  # read by the reader, compiled at the next reading
    cache.parse(raw)
    calls.clear()
    words = cache.parse(raw).words
    assert calls == []
    assert words == parse_line(raw, reader).words
    params.numbered[3] = 1e308
    with pytest.raises(GCodeError, match="Result out of range"):
        cache.parse("X[[#1 + 1] * [2 - #2] * #3 * 10]")
        cache.parse("X[[#1 + 1] * [2 - #2] * #3 * 10]")


# --- the program loop's shortcut (CompiledLine.quick): the values or settings run() would give ------

QUICK_VALUES = ["#1", "[#1 + 0.5]", "-#2", "[#2 * COS[30]]", "[1 / #3]", "[SQRT[#4]]", "#<depth>", "2.5",
                "[10 - 3]", "#<undefined>", "[#1 * 10]", "[ABS[#5] - #6]"]
QUICK_KEYS = ["1", "2", "<depth>", "<_g>", "[#5 + 1]", "[#2]", "5400", "[1 / #3]"]


def _quick_lines(rng: random.Random) -> list[str]:
    """Random straight fast-path lines (X Y Z F in any order, an optional G0/G1 and comment) and lines
    of parameter settings alone."""
    lines = []
    for _ in range(30):
        letters = rng.sample("xyzf", rng.randint(1, 4))
        words = " ".join(f"{c.upper()}{rng.choice(QUICK_VALUES)}" for c in letters)
        lines.append(rng.choice(["", "G0 ", "G1 "]) + words + rng.choice(["", " (note)"]))
        lines.append(" ".join(f"#{rng.choice(QUICK_KEYS)} = {rng.choice(QUICK_VALUES)}"
                              for _ in range(rng.randint(1, 3))))
    return lines


def _quick_outcome(fn):
    try:
        return ("value", fn())
    except GCodeError as exc:
        return ("error", str(exc))


@pytest.mark.parametrize("seed", range(30))
def test_a_compiled_lines_shortcut_gives_what_its_block_holds(seed: int) -> None:
    rng = random.Random(seed)
    reader, params = _reader(seed)
    for raw in _quick_lines(rng):
        try:
            line = CompiledLine(raw, _Compiler(reader))
        except GCodeError:
            continue
        assert line.quick is not None, raw
        for k in range(1, 8):  # the values change between readings: evaluated now, not kept
            params.numbered[k] = rng.choice(VALUES)
            quick = _quick_outcome(line.quick)
            block = _quick_outcome(lambda raw=raw: parse_line(raw, reader))
            assert _outcome(lambda raw=raw: parse_line(raw, reader)) == _outcome(line.run), raw
            if block[0] == "error":
                assert quick == block, raw
            elif line.plain is None:
                assert quick == ("value", block[1].assigns), raw
            else:
                w = block[1].words
                assert quick == ("value", (w.get("x"), w.get("y"), w.get("z"), w.get("f"))), raw


def test_compiled_straight_lines_and_settings_are_run_without_a_block(monkeypatch) -> None:
    from gcode_canon.interpreter import Interpreter
    from gcode_canon.settings import InterpreterSettings

    runs: list[str] = []
    run = CompiledLine.run

    def counted(self):
        runs.append("".join(kind_letter[1] for kind_letter in self.items) or "#")
        return run(self)

    monkeypatch.setattr(CompiledLine, "run", counted)
    text = ("G21 G90 F600\n#1 = 0\no1 repeat [5]\n#1 = [#1 + 1]\nG1 X[#1 * 2] Y#1 (n)\n"
            "G0 Z[#1]\no1 endrepeat\nM2\n")
    interp = Interpreter(InterpreterSettings(dry_run=True))
    ends = [c.end[:3] for c in interp.run_string(text) if hasattr(c, "end")]
    assert ends == [e for k in range(1, 6) for e in ((2.0 * k, k, k - 1.0), (2.0 * k, k, k))]
    # each line's Block is built once, at the reading that compiles it (the second); then its shortcut
    assert sorted(runs) == ["#", "xy", "z"]
