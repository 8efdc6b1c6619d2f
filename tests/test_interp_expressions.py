"""Expressions, functions, precedence, parameters (numbered, named, indirection, read-only)."""

from __future__ import annotations

import math

import pytest
from test_interp_helpers import error, run

from gcode_canon.interpreter import Interpreter
from gcode_canon.settings import InterpreterSettings


def value(expr: str, prelude: str = "") -> float:
    interp = Interpreter(InterpreterSettings(dry_run=True, require_program_end=False))
    run(prelude + f"\n#100 = {expr}\n", interp)
    return interp.params.get_numbered(100)


@pytest.mark.parametrize(
    ("expr", "expected"),
    [
        ("[2.0 / 3 * 1.5 - 5.5 / 11.0]", 0.5),  # the overview's example
        ("[1 + 2 * 3]", 7),
        ("[2 ** 3 ** 2]", 64),  # left to right within a level
        ("[2 * 3 ** 2]", 18),
        ("[7 MOD 3]", 1),
        ("[-7 MOD 3]", 2),  # result has the divisor's sign
        ("[1 + 1 EQ 2]", 1),
        ("[1 EQ 1.00001]", 1),  # 0.0001 tolerance
        ("[1 EQ 1.001]", 0),
        ("[1 NE 2]", 1), ("[2 GT 1]", 1), ("[1 GT 1]", 0), ("[1 GE 1]", 1), ("[1 LT 2]", 1),
        ("[2 LE 1]", 0),
        ("[1 AND 0]", 0), ("[1 OR 0]", 1), ("[1 XOR 1]", 0), ("[0.5 AND 2]", 1),
        ("[1 OR 0 AND 0]", 0),  # same level: left to right
        ("[1 LT 2 AND 3 GT 2]", 1),
        ("ABS[-3]", 3), ("ACOS[0]", 90), ("ASIN[1]", 90), ("COS[60]", 0.5), ("SIN[30]", 0.5),
        ("TAN[45]", 1), ("EXP[0]", 1), ("LN[1]", 0), ("SQRT[16]", 4),
        ("FIX[2.8]", 2), ("FIX[-2.8]", -3), ("FUP[2.8]", 3), ("FUP[-2.8]", -2),
        ("ROUND[2.5]", 3), ("ROUND[-2.5]", -3), ("ROUND[2.4]", 2),
        ("ATAN[1]/[1]", 45), ("ATAN[1]/[-1]", 135), ("ATAN[-1]/[-1]", -135),
        ("[1 + acos[0] - [3 ** [4.0/2]]]", 82),  # the overview's example with #3 = 3
        ("-[2]", -2), ("-SIN[90]", -1), ("[-#5]", 0),
        ("[[[[[[1]]]]]]", 1),
    ],
)
def test_expression_values(expr: str, expected: float) -> None:
    assert value(expr) == pytest.approx(expected, abs=1e-9)


@pytest.mark.parametrize(
    ("expr", "words"),
    [
        ("[1/0]", "divide by zero"),
        ("[1 MOD 0]", "divide by zero"),
        ("SQRT[-1]", "SQRT"),
        ("LN[0]", "LN"),
        ("LN[-1]", "LN"),
        ("ACOS[2]", "ACOS"),
        ("ASIN[-1.5]", "ASIN"),
        ("[-8 ** 0.5]", "negative to non-integer"),
        ("[10 ** 400]", "out of range"),
        ("EXP[1000]", "out of range"),
        ("[1e5]", "Unknown operation"),
        ("[1 ? 2]", "Unknown operation"),
        ("FOO[1]", "Unknown function"),
        ("SIN 30", "Left bracket"),
        ("ATAN[1]", "Slash missing"),
        ("ATAN[1]/2", "Left bracket"),
        ("EXISTS[1]", "EXISTS"),
        ("[" * 100 + "1" + "]" * 100, "nested too deeply"),
        ("#0", "Parameter number out of range"),
        ("#5603", "Parameter number out of range"),
        ("#1.5", "Non integer value for integer"),
        ("#<nope>", "not defined"),
    ],
)
def test_expression_errors(expr: str, words: str) -> None:
    err = error(f"#100 = {expr}")
    assert words in err.message
    assert err.line == 1


def test_deep_nesting_and_huge_numbers_on_long_lines() -> None:
    deep = "[" * 5000 + "1" + "]" * 5000
    assert "nested too deeply" in error("#1 = " + deep, max_line_length=20000).message
    assert "nested too deeply" in error("#1 = " + "-" * 5000 + "#2", max_line_length=20000).message
    assert "nested too deeply" in error("#1 = " + "#" * 5000 + "2", max_line_length=20000).message
    assert "out of range" in error("#1 = " + "9" * 400, max_line_length=1000).message


def test_numbers() -> None:
    assert value("+.5") == 0.5
    assert value("007.2500") == 7.25
    assert value("12345678901234567890") == pytest.approx(1.2345678901234567e19)


def test_hash_binds_tighter_and_indirection() -> None:
    assert value("[#1+2]", "#1=5 #3=100") == 7
    assert value("#[1+2]", "#1=5 #3=100") == 100
    assert value("##2", "#2=7 #7=42") == 42


def test_assignments_take_effect_after_the_line_is_read() -> None:
    interp = Interpreter(InterpreterSettings(dry_run=True, require_program_end=False))
    out = run("#3=15\n#3=6 G0 X#3\n#4=1 #4=2", interp)
    assert out[-1].end.x == 15
    assert interp.params.get_numbered(3) == 6
    assert interp.params.get_numbered(4) == 2  # last setting wins


def test_named_parameters_fold_case_and_spaces() -> None:
    assert value("#<P a R am>", "#<param> = 3") == 3
    assert value("#<_glob>", "#<_GLOB> = 4") == 4
    assert value("EXISTS[#<_glob>]", "#<_glob> = 4") == 1
    assert value("EXISTS[#<_other>]") == 0
    assert value("EXISTS[#<_metric>]") == 1


def test_read_only_parameters_refused() -> None:
    for target in ("#5400", "#5420", "#<_x>", "#<_metric>"):
        err = error(f"{target} = 1")
        assert "read-only" in err.message


def test_read_only_check_happens_before_any_assignment() -> None:
    interp = Interpreter(InterpreterSettings(dry_run=True, require_program_end=False))
    with pytest.raises(Exception, match="read-only"):
        run("#1 = 5 #5420 = 1", interp)
    assert interp.params.get_numbered(1) == 0


def test_predefined_parameters_follow_state() -> None:
    assert value("#<_metric>") == 1
    assert value("#<_imperial>", "G20") == 1
    assert value("#<_incremental>", "G91") == 1
    assert value("#<_coord_system>", "G56") == 560
    assert value("#<_motion_mode>", "G1 F1") == 10
    assert value("#<_plane>", "G18") == 180
    assert value("#<_feed>", "G20 F10") == pytest.approx(10)
    assert value("#<_line>", "\n\n") == 4
    assert value("#<_x>", "G0 X3 Y4") == 3
    assert value("#5421", "G0 X3 Y4") == 4
    assert value("#5420", "G20 G0 X1") == pytest.approx(1)  # program units
    assert value("#<_spindle_on>", "M3 S100") == 1
    assert value("#<_flood>", "M8") == 1
    assert value("#<_selected_tool>") == -1
    assert value("#<_current_tool>", "T3 M6") == 3
    assert value("#5400", "T3 M6") == 3
    assert value("#5599") == 1


def test_debug_print_and_expansion() -> None:
    out = run("#1 = 2.5 #<_aa> = 1\n(DEBUG, v=#1 a=#<_aa> missing=#<zz>)\n#5599 = 0\n(DEBUG, hidden)")
    assert len(out) == 1
    assert out[0].debug and out[0].text == " v=2.500000 a=1.000000 missing=######"


def test_print_goes_to_the_machine_callback() -> None:
    printed: list[str] = []

    class Machine:
        def wait_input(self, cmd):
            return 0.0

        def probe(self, cmd):
            return cmd.end, True

        def current_position(self):
            return None

        def print_text(self, text: str) -> None:
            printed.append(text)

    interp = Interpreter(InterpreterSettings(require_program_end=False), Machine())
    assert run("#2 = 7\n(PRINT,seven=#2)", interp) == []
    assert printed == ["seven=7.000000"]


def test_math_degrees() -> None:
    assert value("SIN[90]") == pytest.approx(1)
    assert value("COS[180]") == pytest.approx(-1)
    assert value("ACOS[-1]") == pytest.approx(180)
    assert math.isclose(value("TAN[30]"), math.tan(math.pi / 6))
