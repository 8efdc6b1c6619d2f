"""O-word flow control: errors that name both lines, limits, the search path, MDI, lazy files,
Fanuc-style M98/M99. The golden program tests/programs/owords.ngc covers the normal flow."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import pytest

from gcode_canon.commands import StraightFeed, StraightTraverse
from gcode_canon.errors import GCodeError
from gcode_canon.interpreter import Interpreter
from gcode_canon.settings import InterpreterSettings


def run(text: str, **kw) -> list:
    return list(Interpreter(InterpreterSettings(dry_run=True, **kw)).run_string(text, "t.ngc"))


def error(text: str, **kw) -> GCodeError:
    with pytest.raises(GCodeError) as info:
        run(text, **kw)
    return info.value


def xs(cmds) -> list[float]:
    return [c.end[0] for c in cmds if isinstance(c, (StraightTraverse, StraightFeed))]


@pytest.mark.parametrize(
    ("text", "line", "words"),
    [
        ("o1 if [1]\nG0 X1\no2 endif\nM2\n", 3, ["o2 endif does not match the open o1 if (line 1)"]),
        ("o1 while [1]\no1 endif\nM2\n", 2, ["o1 endif does not match", "o1 while (line 1)"]),
        ("o1 if [1]\nG0 X1\nM2\n", 2, []),  # M2 ends the program: nothing is left open (as LinuxCNC)
        ("o1 if [0]\nG0 X1\n", 2, ["o1 if at line 1 has no matching", "file ended at line 2"]),
        ("o1 while [1]\nG0 X1\n", 2, ["o1 while at line 1 is not closed", "file ended at line 2"]),
        ("o7 endwhile\nM2\n", 1, ["o7 endwhile with no open o7 while"]),
        ("o1 break\nM2\n", 1, ["not inside an o1 while, do or repeat"]),
        ("o<a> return\nM2\n", 1, ["outside a subroutine call"]),
        ("o<a> sub\nG0 X1\n", 2, ["o<a> sub at line 1 has no matching o<a> endsub"]),
        ("o<a> sub\no1 if [1]\no<a> endsub\no<a> call\nM2\n", 3,
         ["o<a> endsub with o1 if (line 2) still open"]),
        ("o1 frob\nM2\n", 1, ["Unknown o-word keyword 'frob'"]),
        ("o1 if\nM2\n", 1, ["needs a condition"]),
        ("o<nope> call\nM2\n", 1, ["no file nope.ngc on the subroutine path"]),
        ("o<../etc/passwd> call\nM2\n", 1, ["may not contain"]),
        ("o</etc/x> call\nM2\n", 1, ["may not contain"]),
        ("o1 repeat [5000000]\no1 endrepeat\nM2\n", 1, ["max_loop_iterations"]),
    ],
)
def test_errors_name_the_lines(text: str, line: int, words: list[str]) -> None:
    if not words:
        run(text)
        return
    err = error(text)
    assert err.file == "t.ngc" and err.line == line, str(err)
    for w in words:
        assert w in err.message, err.message


def test_loop_and_call_limits_are_settings() -> None:
    err = error("#1=0\no1 while [1]\n#1=[#1+1]\no1 endwhile\nM2\n", max_loop_iterations=10)
    assert "more than 10 iterations" in err.message and err.line == 4
    err = error("o<r> sub\no<r> call\no<r> endsub\no<r> call\nM2\n", max_call_depth=3)
    assert "more than 3 nested calls" in err.message
    # within the limits: recursion with a base case works
    text = ("o<down> sub\nG0 X#1\no2 if [#1 GT 0]\no<down> call [#1 - 1]\no2 endif\no<down> endsub\n"
            "o<down> call [3]\nM2\n")
    assert xs(run(text, max_call_depth=4)) == [3, 2, 1, 0]


def test_locals_and_arguments_are_restored() -> None:
    text = ("#1=11 #5=55 #<n>=1\no<s> sub\n#5=1 #<n>=2\nG0 X#1 Y#2 Z[EXISTS[#<n>]]\no<s> endsub\n"
            "o<s> call [7]\nG0 X#1 Y#5 Z#<n>\nM2\n")
    cmds = [c for c in run(text) if isinstance(c, StraightTraverse)]
    assert cmds[0].end[:3] == (7.0, 0.0, 1.0)  # #2 not passed: 0; #<n> of the caller not visible
    assert cmds[1].end[:3] == (11.0, 55.0, 1.0)


def test_value_returned_flags() -> None:
    text = ("o<a> sub\no<a> return [5]\no<a> endsub\no<b> sub\no<b> endsub\n"
            "o<a> call\nG0 X#<_value> Y#<_value_returned>\n"
            "o<b> call\nG0 X#<_value> Y#<_value_returned>\nM2\n")
    cmds = [c.end[:2] for c in run(text) if isinstance(c, StraightTraverse)]
    assert cmds == [(5.0, 1.0), (0.0, 0.0)]


def test_subroutine_file_on_search_path(tmp_path: Path) -> None:
    subs = tmp_path / "subs"
    subs.mkdir()
    (subs / "peck.ngc").write_text("(lead-in ignored)\no<peck> sub\nG0 X#1\no<peck> endsub\n")
    (subs / "broken.ngc").write_text("o<broken> sub\nG0 X1\n")
    cmds = run("o<peck> call [4]\no<peck> call [6]\nM2\n", subroutine_path=[subs])
    assert xs(cmds) == [4.0, 6.0]
    assert cmds[0].file == str(subs / "peck.ngc") and cmds[0].line == 3
    err = error("o<broken> call\nM2\n", subroutine_path=[subs])
    assert err.file == str(subs / "broken.ngc") and "File ended inside subroutine o<broken>" in err.message
    assert "called from t.ngc:1" in err.message
    # the main program's own directory is searched last
    main = tmp_path / "main.ngc"
    (tmp_path / "side.ngc").write_text("o<side> sub\nG0 Y3\no<side> endsub\n")
    main.write_text("o<side> call\nM2\n")
    got = list(Interpreter(InterpreterSettings(dry_run=True)).run_file(main))
    assert got[0].end[1] == 3.0


def test_mdi_call(tmp_path: Path) -> None:
    (tmp_path / "m.ngc").write_text("o<m> sub\nG0 X#1\nG0 Y#1\no<m> endsub\n")
    interp = Interpreter(InterpreterSettings(dry_run=True, subroutine_path=[tmp_path]))
    out = interp.execute_mdi("o<m> call [2]")
    assert [c.end[:2] for c in out] == [(2.0, 0.0), (2.0, 2.0)]
    assert interp.parameter("_call_level") == 0.0
    with pytest.raises(GCodeError, match="need a program"):
        interp.execute_mdi("o1 if [1]")


def test_loops_on_a_long_file_are_not_held_in_memory(tmp_path: Path) -> None:
    path = tmp_path / "long.ngc"
    with path.open("w") as f:
        f.write("G1 F100\n#<i>=0\no1 while [#<i> LT 3]\n")
        for k in range(50_000):
            f.write(f"G1 X{k % 100} Y{k % 7}\n")
        f.write("#<i>=[#<i>+1]\no1 endwhile\nM2\n")
    tracemalloc.start()
    count = sum(1 for _ in Interpreter(InterpreterSettings(dry_run=True)).run_file(path))
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert count == 3 * 50_000 + 3
    assert peak < 2_000_000  # the file is ~700 kB; three passes hold none of it


def test_fanuc_numbered_programs_linuxcnc() -> None:
    text = "O1\nG0 X1\nM98 P100 L2\nG0 X9\nM2\nO100\nG91 G0 Y1\nG90\nM99\n"
    cmds = run(text)
    assert [c.end[:2] for c in cmds if isinstance(c, StraightTraverse)] == [
        (1.0, 0.0), (1.0, 1.0), (1.0, 2.0), (9.0, 2.0)]
    err = error("G0 X1\nO100\nM2\n")
    assert "main program must end" in err.message and err.line == 2


def test_fanuc_labels_gcode_canon_dialect() -> None:
    text = "#1=0\nO5\n#1=[#1+1]\no1 if [#1 LT 3]\nM98 P5\no1 endif\nG0 X#1\nM99\nM2\n"
    cmds = run(text, dialect="gcode-canon")
    assert xs(cmds)[:3] == [3.0, 3.0, 3.0]
    err = error("M98 P7\nM2\nO7\nM99\n", dialect="gcode-canon")
    assert "no program number O7 read before the call" in err.message


def test_bolt_circle_example_drills_the_holes_of_both_circles() -> None:
    """examples/bolt_circle.ngc: a subroutine with arguments, a while loop, an if, G81 and G83."""
    import math

    path = Path(__file__).resolve().parent.parent / "examples" / "bolt_circle.ngc"
    cmds = list(Interpreter(InterpreterSettings(dry_run=True)).run_file(path))
    bottoms = [c.end[:3] for c in cmds if isinstance(c, StraightFeed) and c.end[2] in (-14.0, -15.0)]
    want = [(60 + 40 * math.cos(math.radians(22.5 + 45 * k)), 50 + 40 * math.sin(math.radians(22.5 + 45 * k)),
             -14.0) for k in range(8)]
    want += [(60 + 20 * math.cos(math.radians(60 * k)), 50 + 20 * math.sin(math.radians(60 * k)), -15.0)
             for k in range(6)]
    assert len(bottoms) == len(want)
    for got, exp in zip(bottoms, want, strict=True):
        assert all(abs(a - b) < 1e-9 for a, b in zip(got, exp, strict=True))
    # G83 pecks of 3 mm from R2 down to -15: feeds end at -1, -4, -7, -10, -13, -15 for each inner hole
    inner = [c.end[2] for c in cmds if isinstance(c, StraightFeed) and c.line == 22]
    assert inner == [-1.0, -4.0, -7.0, -10.0, -13.0, -15.0] * 6
    messages = [c.text for c in cmds if type(c).__name__ == "Message"]
    assert messages == [" outer circle: 8.000000 holes", " inner circle: 6.000000 holes"]


def test_computed_label_call_and_labels_reused_in_other_subroutines() -> None:
    # LinuxCNC: O#<sub> CALL; control-flow labels are local to their subroutine (o1 used in both)
    text = ("o100 sub\no1 if [#1 GT 0]\nG0 X#1\no1 endif\no100 endsub\n"
            "o200 sub\no1 repeat [2]\nG0 Y#1\no1 endrepeat\no200 endsub\n"
            "#<sub> = 100\no#<sub> call [5]\no[#<sub> * 2] call [7]\nM2\n")
    cmds = [c.end[:2] for c in run(text) if isinstance(c, StraightTraverse)]
    assert cmds == [(5.0, 0.0), (5.0, 7.0), (5.0, 7.0)]
