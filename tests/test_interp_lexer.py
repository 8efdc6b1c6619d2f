"""Line format: spaces, case, comments, line numbers, block delete, %, program end, bad input."""

from __future__ import annotations

import pytest
from test_interp_helpers import error, last_end, run, xyz

from gcode_canon.commands import Comment, Message, ProgramEnd, StraightTraverse
from gcode_canon.interpreter import Interpreter
from gcode_canon.settings import InterpreterSettings


def test_spaces_anywhere_and_case_folded() -> None:
    assert last_end("g0X +0. 12 34y 7") == xyz(0.1234, 7)
    assert last_end("G0 x1\tY 2 z-3") == xyz(1, 2, -3)


def test_line_numbers_allowed_first_only() -> None:
    assert last_end("N10 G0 X1\nN56.78 X2") == xyz(2)
    assert "first" in error("G0 N10 X1").message


def test_comments_parenthesis_and_semicolon() -> None:
    out = run("G0 (rapid) X1 ; to X1 (not a paren comment here")
    assert [type(c) for c in out] == [Comment, StraightTraverse]
    assert out[0].text == "to X1 (not a paren comment here"


def test_only_last_comment_is_active() -> None:
    out = run("(MSG,hello)(plain)")
    assert out == [Comment("plain", file="t.ngc", line=1)]
    out = run("(plain)(MSG,hello)")
    assert isinstance(out[0], Message) and out[0].text == "hello"


def test_comment_between_letter_and_value_refused() -> None:
    assert "Comment" in error("S(speed)100").message


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("G0 X1 (open", "Unclosed comment"),
        ("(a (b) c)", "Nested comment"),
        ("G0 X[1+2", "Unclosed expression"),
        ("G0 X1 &", "Bad character"),
        ("G0 X1.2.3", "Bad character"),
        ("G0 X", "Missing value"),
        ("G0 X1 X2", "Multiple X words"),
        ("G0 X1\x00", "control character"),
        ("G0 X1é", "Bad character"),
        ("G0 Xabc", "Unknown function"),
    ],
)
def test_bad_lines(text: str, words: str) -> None:
    err = error(text)
    assert words in err.message
    assert err.file == "t.ngc" and err.line == 1


def test_non_ascii_allowed_in_comments() -> None:
    assert run("(MSG,Grüße)")[0].text == "Grüße"


def test_line_length_limit() -> None:
    ok = "G0 X1" + " " * 251
    assert len(ok) == 256
    assert last_end(ok) == xyz(1)
    err = error("G0 X1\n" + ok + " ")
    assert "too long" in err.message and err.line == 2


def test_ten_megabyte_line_is_refused_quickly(tmp_path) -> None:
    path = tmp_path / "big.ngc"
    path.write_text("G0 X1\n" + "X" * 10_000_000 + "\nM2\n")
    interp = Interpreter(InterpreterSettings(dry_run=True))
    with pytest.raises(Exception) as info:
        list(interp.run_file(path))
    assert "too long" in str(info.value) and ":2:" in str(info.value)


def test_block_delete_switchable() -> None:
    assert last_end("G0 X1\n/G0 X2") == xyz(2)
    assert last_end("G0 X1\n/G0 X2", block_delete=True) == xyz(1)


def test_program_end_and_text_after_it_not_read() -> None:
    interp = Interpreter(InterpreterSettings(dry_run=True))
    out = list(interp.run_string("G0 X1\nM2\nthis is not G-code at all", "t.ngc"))
    assert isinstance(out[-1], ProgramEnd) and out[-1].rewind is False
    out = list(Interpreter(InterpreterSettings()).run_string("M30\n", "t.ngc"))
    assert out[-1].rewind is True


def test_percent_demarcation() -> None:
    interp = Interpreter(InterpreterSettings(dry_run=True))
    out = list(interp.run_string("\n  %\nG0 X1\n%\ngarbage ###", "t.ngc"))
    assert isinstance(out[-1], ProgramEnd)
    err = error("%\nG0 X1\n", require_program_end=True)
    assert "percent" in err.message
    err = error("G0 X1\n", require_program_end=True)
    assert "no percent sign or program end" in err.message and err.line == 1


def test_errors_name_file_and_line() -> None:
    err = error("G0 X1\n\nG0 Y[1/0]")
    assert (err.file, err.line) == ("t.ngc", 3)
    assert str(err) == "t.ngc:3: Attempt to divide by zero"


def test_utf8_byte_order_mark_is_skipped_in_files(tmp_path) -> None:
    path = tmp_path / "bom.ngc"
    path.write_bytes(b"\xef\xbb\xbfG0 X1\nM2\n")
    out = list(Interpreter(InterpreterSettings()).run_file(path))
    assert out[0].end.x == 1


def test_invalid_utf8_is_a_clear_error(tmp_path) -> None:
    path = tmp_path / "latin1.ngc"
    path.write_bytes(b"G0 X1\n(caf\xe9)\nM2\n")
    with pytest.raises(Exception, match="not valid UTF-8") as info:
        list(Interpreter(InterpreterSettings()).run_file(path))
    assert ":2:" in str(info.value)


def _fast_line_candidates(rng) -> list[str]:
    """Random lines near FAST_LINE's grammar: words in and out of order, numbers well and badly
    formed, spaces and tabs anywhere, letters it does not take."""
    lines = []
    for _ in range(20000):
        if rng.random() < 0.3:
            chars = "GgXxYyZzFf0123456789.+- \tQe"
            lines.append("".join(rng.choice(chars) for _ in range(rng.randint(0, 16))))
            continue
        parts = []
        if rng.random() < 0.7:
            codes = ["0", "1", "00", "01", "001", "10", "11", "1.", "0.5", "2"]
            parts.append(rng.choice("Gg") + rng.choice(codes))
        for letter in "XYZF":
            if rng.random() < 0.7:
                parts.append(rng.choice([letter, letter.lower()]) + rng.choice(["", "-", "+", "+-"])
                             + rng.choice(["1", "1.", ".5", "12.25", ".", "", "1.2.3", "1e3", "0"]))
        if rng.random() < 0.2:
            rng.shuffle(parts)
        lines.append(rng.choice(["", " ", "\t"]).join(parts) + rng.choice(["", " ", "\t", "Q", " q"]))
    return lines


def test_the_fast_lines_pattern_reads_as_its_plain_form() -> None:
    # FAST_LINE is written with atomic groups for speed (its docstring); this is the grammar it reads,
    # written plainly with optional groups
    import random
    import re

    from gcode_canon.lexer import _NUM, FAST_LINE

    plain = re.compile(r"[ \t]*(?:[Gg]0?([01])(?![0-9.])[ \t]*)?(?:[Xx]" + _NUM + r"[ \t]*)?(?:[Yy]" + _NUM
                       + r"[ \t]*)?(?:[Zz]" + _NUM + r"[ \t]*)?(?:[Ff]" + _NUM + r"[ \t]*)?\Z")
    matched = 0
    for line in _fast_line_candidates(random.Random(7)):
        ours, theirs = FAST_LINE.match(line), plain.match(line)
        assert (ours and ours.groups()) == (theirs and theirs.groups()), line
        matched += ours is not None
    assert matched > 500  # the lines cover both outcomes
