"""Fuzzing: random and mutated programs raise only GCodeError (with file, line, message), never
another exception, and never hang. Bounded: a fixed number of examples, each with a deadline."""

from __future__ import annotations

import random
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gcode_canon.errors import GCodeError
from gcode_canon.interpreter import Interpreter
from gcode_canon.settings import InterpreterSettings

SEED_PROGRAM = """%
G21 G90 G17 G94 F300 (set-up)
#1 = 2.5 #<depth> = [-#1 * 2]
#<_g> = [ATAN[1]/[2] + SQRT[4] - LN[EXP[1]] MOD 3]
G0 X0 Y0 Z5
G1 Z#<depth>
G2 X10 Y0 I5 J0
G3 X0 Y0 R5
G2 X0 Y0 I5 P2 Z-6
G91 G1 X1 Y1
G90 G10 L2 P2 X10 R30
G55 G0 @2 ^45
G92 X0 Y0
G92.1 G54
G18 G91 G2 X4 Z0 I2
G90
G17 G20 G1 X1 F10
G21 G43.1 Z1
G0 Z0
G49 T1 M6 M3 S1000 M8
M62 P1
M66 P0 L0
M67 E0 Q3
G4 P0.1
G28.1
G30
(MSG, done #1)
(DEBUG, depth=#<depth>)
M5 M9
G38.2 Z-10
M70
G91
M72
G64 P0.01 Q0.01
G61
G61.1
/N10 G53 G0 X0
M2
"""

TOKENS = [
    "G0", "G1", "G2", "G3", "G4", "G10", "G17", "G18", "G19", "G20", "G21", "G28", "G28.1", "G30", "G38.2",
    "G43", "G43.1", "G49", "G53", "G54", "G55", "G59.3", "G61", "G64", "G80", "G90", "G91", "G90.1",
    "G91.1", "G92", "G92.1", "G92.2", "G92.3", "G93", "G94", "G95", "M0", "M2", "M3", "M5", "M6", "M7",
    "M9", "M48", "M50", "M61", "M62", "M66", "M67", "M70", "M72", "X", "Y", "Z", "A", "I", "J", "K", "R",
    "P", "Q", "L", "E", "F", "S", "T", "H", "@", "^", "#1", "#<a>", "#<_b>", "=", "[", "]", "(", ")", ";",
    "ATAN", "SIN", "SQRT", "LN", "ACOS", "EXISTS", "MOD", "**", "/", "*", "-", "+", "AND", "EQ", "0",
    "1", "-1", "2.5", ".5", "1e5", "9" * 30, "0.0001", "360", "#", "##2", "%", "N5", "\x00", "é", " ",
    "\t", "o100", "#5399", "#5420=1", "(MSG,", "(DEBUG,#1)", "(LOGOPEN,x)", "\r",
    "G41.1", "G42.1", "D5", "G40", "G41", "G81", "G83", "G73", "G82", "G98", "G99", "M98", "M99",
    "G68", "G69", "G51", "G50", "G22", "G23", "G16", "G15", "G12", "G13", "G10L1", "G10L3", "G10L10", "G11",
]


def check(text: str, max_line_length: int = 256, **limits: int) -> None:
    interp = Interpreter(InterpreterSettings(dry_run=True, max_line_length=max_line_length, **limits))
    try:
        for count, _ in enumerate(interp.run_string(text, "fuzz.ngc")):
            assert count < 10_000
    except GCodeError as exc:
        assert exc.file == "fuzz.ngc"
        assert exc.line >= 1
        assert exc.message and "internal error" not in exc.message


FUZZ = settings(max_examples=300, deadline=2000, suppress_health_check=[HealthCheck.too_slow], database=None,
                derandomize=True)


@FUZZ
@given(st.lists(st.lists(st.sampled_from(TOKENS), max_size=12).map("".join), max_size=8).map("\n".join))
def test_random_token_programs(text: str) -> None:
    check(text)


@FUZZ
@given(st.text(max_size=300))
def test_random_text(text: str) -> None:
    check(text)


@FUZZ
@given(st.integers(0, 2**32 - 1), st.integers(1, 8))
def test_mutated_programs(seed: int, n_mutations: int) -> None:
    rng = random.Random(seed)
    chars = list(SEED_PROGRAM)
    for _ in range(n_mutations):
        op = rng.randrange(4)
        pos = rng.randrange(len(chars))
        if op == 0:
            del chars[pos]
        elif op == 1:
            chars.insert(pos, rng.choice("GMXYZIJKRPQLEFST#[]()<>=;%/@^.-+0123456789 \n\x00é"))
        elif op == 2:
            chars[pos] = rng.choice("0123456789.-")
        else:
            chars.insert(pos, rng.choice(TOKENS))
    check("".join(chars))


def test_seed_program_is_valid() -> None:
    out = list(Interpreter(InterpreterSettings(dry_run=True)).run_string(SEED_PROGRAM, "seed.ngc"))
    assert out[-1].NAME == "PROGRAM_END" and len(out) > 40


def test_pathological_inputs() -> None:
    for text in [
        "G0 X" + "[" * 300 + "1" + "]" * 300,
        "#1=" + "-" * 250,
        "#1=" + "#" * 250 + "1",
        "G0 X1\x00",
        "G0 X\udcff",
        "\ufeffG0 X1",
        "(" * 5,
        "G0 X[1" + "+1" * 120,
        "%\n%\n%",
        "G2 X1 Y1 R0.5 F1",
        "G2 X1e-300 I1e-300 F1",
        "G1 F1 X" + "9" * 250,
    ]:
        check(text)


def test_pathological_long_lines() -> None:
    """With the line limit raised, deep nesting and huge numbers still end in a GCodeError."""
    for text in [
        "G0 X" + "[" * 20000 + "1" + "]" * 20000,
        "#1=" + "-" * 20000 + "1",
        "#1=" + "#" * 20000 + "1",
        "(DEBUG,#" + "1" * 5000 + ")\nM2",
        "#1=#" + "1" * 5000,
        "G1 F1 X" + "9" * 5000,
        "X" + "9" * 100000 + "a",
        "N" + "1" * 5000 + " G0 X1\nM2",
        "#1=[1" + "+1" * 20000 + "]\nM2",
        "G0 X1 (" + "x" * 50000,
    ]:
        check(text, max_line_length=200_000)


O_TOKENS = [
    "o1", "o2", "o<s>", "o<t>", "o<../x>", "o<missing>", " sub", " endsub", " call", " return", " if",
    " elseif", " else", " endif", " while", " endwhile", " do", " repeat", " endrepeat", " break",
    " continue", " [1]", " [0]", " [#1]", " [#1 LT 3]", "#1=[#1+1]", "G0 X#1", "M98 P1", "M99", "O1",
    "\n", "M2", "%", "(c)",
]


@FUZZ
@given(st.lists(st.sampled_from(O_TOKENS), max_size=40).map("".join))
def test_random_oword_programs(text: str) -> None:
    """Unbalanced blocks, calls to missing files, runaway loops and recursion: clear errors only."""
    check(text, max_loop_iterations=50, max_call_depth=5)


def test_runaway_loop_and_recursion_stop_with_errors() -> None:
    interp = Interpreter(InterpreterSettings(dry_run=True, max_loop_iterations=1000))
    try:
        list(interp.run_string("o1 while [1]\no1 endwhile\nM2\n", "loop.ngc"))
    except GCodeError as exc:
        assert "max_loop_iterations" in exc.message and exc.line == 2
    else:
        raise AssertionError("no error")
    interp = Interpreter(InterpreterSettings(dry_run=True))
    try:
        list(interp.run_string("o<r> sub\no<r> call\no<r> endsub\no<r> call\nM2\n", "rec.ngc"))
    except GCodeError as exc:
        assert "max_call_depth" in exc.message and exc.line == 2
    else:
        raise AssertionError("no error")


SEED_ISSUE3 = """G21 G90 G17 F300 S1000 M3
o<sq> sub
  G41.1 D2 G1 X#1 Y0
  Y#1
  X0
  G2 X0 Y0 I0 J[-#1 / 2]
  G40 G1 X-5 Y-5
o<sq> endsub
#<n> = 0
o10 while [#<n> LT 2]
  o<sq> call [10 + #<n>]
  #<n> = [#<n> + 1]
o10 endwhile
G0 Z10
G98 G81 X5 Y5 Z-2 R1
G99 G83 X7 Q0.5 Z-3 R1
G80
G18 G99 G82 Z2 X1 Y-3 R1 P0.2
G17 G68 X0 Y0 R30
G51 P1.5
G22 X2
G1 X3 Y4
G13 I2
G69 G50 G23
G16 G1 X5 Y60
G15
o20 repeat [2]
  G10 L1 P1 R1
o20 endrepeat
M2
"""


def test_issue3_seed_is_valid() -> None:
    out = list(Interpreter(InterpreterSettings(dry_run=True)).run_string(SEED_ISSUE3, "seed3.ngc"))
    assert out[-1].NAME == "PROGRAM_END" and len(out) > 40


@FUZZ
@given(st.integers(0, 2**32 - 1), st.integers(1, 8))
def test_mutated_issue3_programs(seed: int, n_mutations: int) -> None:
    """O-words, cycles, compensation and transforms mutated: clear errors only, never a hang."""
    rng = random.Random(seed)
    chars = list(SEED_ISSUE3)
    for _ in range(n_mutations):
        op = rng.randrange(3)
        pos = rng.randrange(len(chars))
        if op == 0:
            del chars[pos]
        elif op == 1:
            chars.insert(pos, rng.choice("GMXYZIJKRPQLDO#[]()<>=\n0123456789.-"))
        else:
            chars.insert(pos, rng.choice(TOKENS + O_TOKENS))
    check("".join(chars), max_loop_iterations=50, max_call_depth=5)


# ---- MDI: the same inputs, one line at a time, on one interpreter (its state carried over) --------------

def check_mdi(lines: list[str], max_line_length: int = 256) -> None:
    interp = Interpreter(InterpreterSettings(dry_run=True, max_line_length=max_line_length,
                                             max_loop_iterations=50, max_call_depth=5))
    for line in lines:
        try:
            out = interp.execute_mdi(line)
            assert len(out) < 10_000
        except GCodeError as exc:
            assert exc.file
            assert exc.line >= 1
            assert exc.message and "internal error" not in exc.message


@FUZZ
@given(st.lists(st.lists(st.sampled_from(TOKENS + O_TOKENS[:-4]), max_size=12).map("".join), max_size=6))
def test_random_mdi_lines(lines: list[str]) -> None:
    check_mdi(lines)


@FUZZ
@given(st.lists(st.text(max_size=300), max_size=4))
def test_random_mdi_text(lines: list[str]) -> None:
    check_mdi(lines)


def test_mdi_obeys_the_line_length_limit() -> None:
    interp = Interpreter(InterpreterSettings(dry_run=True))
    for line in ("G0 X1" + " " * 100_011, "G0 X" + "1" * 300):
        try:
            interp.execute_mdi(line)
        except GCodeError as exc:
            assert (exc.file, exc.line) == ("<mdi>", 1)
            assert exc.message == "Line too long (more than 256 characters)"
        else:
            raise AssertionError(f"a {len(line)}-character MDI line was accepted")
    assert interp.execute_mdi("G0 X1" + " " * 200)  # within the limit: fine


def test_subroutine_name_longer_than_a_file_name_is_a_clean_error(tmp_path: Path) -> None:
    """The file system allows 255 bytes per name: a longer one was 'internal error: OSError 36'."""
    main = tmp_path / "main.ngc"
    name = "a" * 300
    main.write_text(f"o<{name}> call\nM2\n")
    interp = Interpreter(InterpreterSettings(dry_run=True, max_line_length=1000, subroutine_path=[tmp_path]))
    try:
        list(interp.run_file(main))
    except GCodeError as exc:
        assert (exc.file, exc.line) == (str(main), 1)
        assert "File name too long" in exc.message and "internal error" not in exc.message
    else:
        raise AssertionError("no error")
    try:  # and by MDI, where it first came up (MDI had no line limit then)
        Interpreter(InterpreterSettings(dry_run=True, max_line_length=1000,
                                        subroutine_path=[tmp_path])).execute_mdi(f"o<{name}> call")
    except GCodeError as exc:
        assert "File name too long" in exc.message
    else:
        raise AssertionError("no error")
