"""Lines read again whose shape is the fast path's (an optional G0/G1, X Y Z F words, a comment that
is not active) but whose values are expressions or parameters run the fast path on their cached or
compiled Block (``Block.plain``, ``_fast_block``): the same commands and the same errors, at the same
line, as the general path, with the parameter values in force at each reading."""

from __future__ import annotations

import random

import pytest

from gcode_canon.errors import GCodeError
from gcode_canon.interpreter import Interpreter
from gcode_canon.settings import InterpreterSettings


def _interp() -> Interpreter:
    return Interpreter(InterpreterSettings(dry_run=True))


def _outcome(text: str) -> tuple[list, str | None]:
    """The commands (without file and line) with their lines, and the error, if any."""
    out: list = []
    try:
        for cmd in _interp().run_string(text, "t.ngc"):
            out.append((cmd.line, repr(cmd)))
    except GCodeError as exc:
        return out, str(exc)
    return out, None


def _general(text: str) -> str:
    """The same program with an N word on each G-code line: the fast paths take no line with an N
    word, and the N word changes nothing else."""
    lines = []
    for line in text.splitlines():
        lines.append(line if line.startswith(("o", "#", "%")) or not line else f"N1 {line}")
    return "\n".join(lines) + "\n"


PLAIN_LINES = [
    "G1 X[#1 * 2] Y#<v> F[#2 * 100]",
    "X[#1 + 1] (a note)",
    "G0 Z[#1 - 3]",
    "Y#<v> Z-#1",
    "G1 F#2",
    "G1 X[10 / #2] (MSG, active: the general path)",
    "X[SIN[#1 * 30]] Y[COS[#1 * 30]] Z[#1 MOD 2]",
    "G0 X#1 ; end note",
    "G1 Z[#<v> * 0.5]",
]
MODES = ["G20", "G21", "G90", "G91", "G92 X1 Y-2", "G92.1", "G55", "G54", "G17", "G93", "G94 F300"]


def _program(seed: int) -> str:
    rng = random.Random(seed)
    body = [rng.choice(PLAIN_LINES if rng.random() < 0.8 else MODES) for _ in range(12)]
    return _looped(body, "G21 G90 G94 F500")


def _looped(body: list[str], first: str) -> str:
    """``body`` four times, the parameters it reads changed after each time."""
    return "\n".join([
        first, "G10 L2 P2 X3 Y4 Z5", "#1 = 1", "#2 = 4", "#<v> = 2",
        "o100 repeat [4]", *body,
        "#1 = [#1 + 1.5] #2 = [#2 - 1] #<v> = [#<v> * -1]",
        "o100 endrepeat", "M2"])


@pytest.mark.parametrize("seed", range(60))
def test_plain_lines_read_again_give_what_the_general_path_gives(seed: int) -> None:
    text = _program(seed)
    assert _outcome(text) == _outcome(_general(text))


def _counting_general_lines(monkeypatch) -> tuple[Interpreter, list[int]]:
    """An interpreter, and the list it fills with the number of each line it runs the general way."""
    interp = _interp()
    general: list[int] = []
    execute = interp._execute_block

    def counted(block):
        general.append(interp.line)
        return execute(block)

    monkeypatch.setattr(interp, "_execute_block", counted)
    return interp, general


def test_plain_lines_with_expressions_do_not_take_the_general_path(monkeypatch) -> None:
    interp, general = _counting_general_lines(monkeypatch)
    text = ("G21 G90 F600\n#1 = 0\no1 repeat [5]\n#1 = [#1 + 1]\nG1 X[#1 * 2] Y#1 (note)\nG0 Z[#1]\n"
            "o1 endrepeat\nM2\n")
    ends = [(c.line, c.end[0], c.end[1], c.end[2]) for c in interp.run_string(text) if hasattr(c, "end")]
    # each reading sees the value of #1 set just before it (Z stays where line 6 left it)
    assert ends == [item for k in range(1, 6) for item in ((5, 2.0 * k, float(k), k - 1.0),
                                                            (6, 2.0 * k, float(k), float(k)))]
    # read once by the reader (a line with parameters is compiled when it is read again), then fast;
    # the settings line is compiled at its second reading and set without the general path after
    assert general.count(5) == 1 and general.count(6) == 1 and general.count(4) == 2


ARC_LINES = [
    "G2 X[#1 * 2] Y#<v> R[100 + #2] F[#2 * 100]",
    "G3 X#1 Y[#1 - 3] R-[120 + #2] (a note)",
    "G2 I[#1] J[#<v> / 2]",  # full circles and helixes: the end on the circle whatever the start
    "G3 I[-#2] J1 Z[#1 * 0.1]",
    "G2 X[#1 + 2] Y#<v> Z1 R150",
    "G3 X5 Y-5 R100 (no parameter: one Block for every reading)",
    "G2 X-4 Y3 Z-1 R-90 F450",
]
PLANE_ARC_LINES = ["G2 I1 K#1", "G3 J[#1 / 3] K1 Y[#1 - 1] F#2"]  # G18 / G19 arcs; elsewhere refused
WRONG_ARC_LINES = [
    "G2 X#1 Y[#1 + 1] R[#2 - 4]",  # R 0 when #2 is 4: the general path's error
    "G3 X1 Y1 R10 I1",  # mixed R and IJK
    "G2 X[#1 * 3] Y1 R[#1 / 10] (MSG, active: the general path)",
    "G3 X#1 Y#2 R50 F0",  # zero feed
    "G2 X[#1 + 1] Y#<v> I1 J1",  # radius to the end differs
]


MOVES = [line for line in PLAIN_LINES if line.startswith("G")]  # in G2/G3 mode X Y alone are arcs


def _arc_program(seed: int) -> str:
    """Mostly arcs that run (the loop runs on), some lines in error and modes now and then."""
    rng = random.Random(seed)
    body = []
    for _ in range(14):
        r = rng.random()
        lines = (ARC_LINES if r < 0.55 else MOVES if r < 0.8 else MODES if r < 0.9
                 else ["G18", "G19", "G17", "G90.1", "G91.1", "G81 X1 Y1 Z-1 R2", "G80", *PLANE_ARC_LINES]
                 if r < 0.97 else WRONG_ARC_LINES)
        body.append(rng.choice(lines))
    return _looped(body, "G21 G90 G17 G94 F500")


@pytest.mark.parametrize("seed", range(80))
def test_arcs_read_again_give_what_the_general_path_gives(seed: int) -> None:
    text = _arc_program(seed)
    assert _outcome(text) == _outcome(_general(text))


ROTARY_CHANGES = ["G0 A[#1 * 10] U#2", "G92 A3 W-1", "G92.1", "G10 L2 P2 A7 V[#2]", "G55", "G54",
                  "G1 B#<v> C1"]
"""Lines that move A-W or shift them (the general way): the fast path keeps A-W from one fast line
to the next (``_tail``), so it must see each of these."""


@pytest.mark.parametrize("seed", range(40))
def test_rotary_and_uvw_changes_between_fast_lines_are_seen(seed: int) -> None:
    rng = random.Random(seed)
    body = []
    for _ in range(14):
        r = rng.random()
        lines = (ROTARY_CHANGES if r < 0.3 else ARC_LINES if r < 0.5 else SETTINGS if r < 0.6 else MOVES)
        body.append(rng.choice(lines))
    text = _looped([ROTARY_CHANGES[0], *body], "G21 G90 G17 G94 F500")
    outcome = _outcome(text)
    assert outcome == _outcome(_general(text))
    assert any("a=10.0," in r for _, r in outcome[0])  # A moved from the first line of the loop on


def test_arcs_read_again_do_not_take_the_general_path(monkeypatch) -> None:
    interp, general = _counting_general_lines(monkeypatch)
    text = ("G21 G90 G17 F600\n#1 = 0\no1 repeat [4]\n#1 = [#1 + 1]\nG0 X0 Y0\nG2 X[#1 * 2] Y0 R#1 (n)\n"
            "G3 X0 Y0 I[-#1] J0 F[600 + #1]\no1 endrepeat\nM2\n")
    arcs = [(c.line, c.end[0], c.center[0], c.turns) for c in interp.run_string(text) if c.NAME == "ARC_FEED"]
    assert arcs == [item for k in range(1, 5) for item in ((6, 2.0 * k, float(k), -1), (7, 0.0, float(k), 1))]
    assert general.count(6) == 1 and general.count(7) == 1  # compiled at the second reading: then fast


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("G1 X1 F[#1 - 0.5]", "Negative F word used: F-0.5"),  # the fast path declines, the general reports
        ("G1 X[1 / [#1 + 1]] (note)", "Attempt to divide by zero"),  # the reader's own error
        ("G1 Y[SQRT[#1 - 0.5]] Z1", "Negative argument to SQRT"),
    ],
)
def test_errors_on_plain_lines_read_again_name_their_line(line: str, message: str) -> None:
    # #1 counts down 2, 1, 0, -1: the fourth reading of line 5 is the one in error
    text = f"G21 G90 F600\n#1 = 3\no1 while [1]\n#1 = [#1 - 1]\n{line}\no1 endwhile\nM2\n"
    cmds, error = _outcome(text)
    assert error is not None and error.startswith("t.ngc:5: ") and message in error, error
    assert [n for n, _ in cmds].count(5) >= 2  # the readings before it ran
    assert (cmds, error) == _outcome(_general(text))


# --- the shape a line keeps (Block.shape: its sorted codes, checks and steps, computed once) ---------

def test_a_g_code_from_a_parameter_is_sorted_again_at_each_reading() -> None:
    looped = ("G21 G90 F100\n#3 = 0 #1 = 1\no1 repeat [4]\nG#3 X#1 Y[#1 * 2]\n"
              "#3 = [1 - #3] #1 = [#1 + 1]\no1 endrepeat\nM2\n")
    unrolled = "G21 G90 F100\nG0 X1 Y2\nG1 X2 Y4\nG0 X3 Y6\nG1 X4 Y8\nM2\n"

    def moves(text: str) -> list:
        return [(c.NAME, c.end) for c in _interp().run_string(text) if hasattr(c, "end")]

    assert moves(looped) == moves(unrolled)
    assert [name for name, _ in moves(looped)] == ["STRAIGHT_TRAVERSE", "STRAIGHT_FEED"] * 2


def test_a_line_read_again_is_checked_again_in_the_modal_state_of_then() -> None:
    # line 4 passes its checks in G1 and is refused at its second reading, after G80
    text = "G21 G90 F100\n#1 = 1\no1 repeat [2]\nX#1 Y[#1 + 1]\nG80\n#1 = 2\no1 endrepeat\nM2\n"
    cmds, error = _outcome(text)
    assert error == "t.ngc:4: Cannot use axis values without a G code that uses them"
    assert [n for n, _ in cmds].count(4) == 0  # G80 from the start: refused at the first reading too
    text = "G21 G90 F100 G1\n#1 = 1\no1 repeat [2]\nX#1 Y[#1 + 1] (n)\nG80\n#1 = 2\no1 endrepeat\nM2\n"
    cmds, error = _outcome(text)
    assert error == "t.ngc:4: Cannot use axis values without a G code that uses them"
    assert [n for n, _ in cmds].count(4) == 2  # the comment and the move of the first reading


# --- lines of parameter settings alone -------------------------------------------------------------

SETTINGS = ["#1 = [#1 + 0.5]", "#<v> = [-[#1 MOD 3] * 0.25] #2 = [#2 + 1]", "#3 = #1 #1 = #3",
            "#[#2 + 10] = #1", "#<_g> = [#<_g> + 1]"]
WRONG_SETTINGS = ["#1 = 2 #<_x> = 1", "#5400 = 1", "#2 = [1 / 0]"]  # read-only: none of them set


def _commented(text: str) -> str:
    """The program with a comment on each parameter setting line: the general way for them."""
    return "\n".join(f"{line} (c)" if line.startswith("#") else line for line in text.splitlines()) + "\n"


def _without_c(outcome: tuple[list, str | None]) -> tuple[list, str | None]:
    cmds, error = outcome
    return [(n, r) for n, r in cmds if r != f"Comment(file='t.ngc', line={n}, text='c')"], error


@pytest.mark.parametrize("seed", range(40))
def test_parameter_settings_alone_give_what_the_general_path_gives(seed: int) -> None:
    rng = random.Random(seed)
    body = []
    for _ in range(14):
        r = rng.random()
        lines = (SETTINGS if r < 0.5 else MOVES + ARC_LINES if r < 0.8 else
                 [*MODES, "G81 X1 Y1 Z-1 R2", "G80", "G41 D0", "G40"] if r < 0.985 else WRONG_SETTINGS)
        body.append(rng.choice(lines))
    text = _looped(["#<_g> = 0", *body, "G1 Z[#<_g> + #1 + #2 + #<v>]"], "G21 G90 G17 G94 F500")
    outcome = _outcome(text)
    assert outcome == _without_c(_outcome(_commented(text)))


def test_parameter_settings_alone_run_no_check_and_no_step(monkeypatch) -> None:
    interp = _interp()
    checked: list[int] = []
    check = interp._check_block

    def counted(block, ml, shape):
        checked.append(interp.line)
        return check(block, ml, shape)

    monkeypatch.setattr(interp, "_check_block", counted)
    text = "G21 G90 F600\n#1 = 0\no1 repeat [3]\n#1 = [#1 + 1] #<d> = [#1 * 2]\nG1 X#<d>\no1 endrepeat\nM2\n"
    # the settings of a line read the values of before the line (LinuxCNC): #<d> is twice the old #1
    assert [c.end[0] for c in interp.run_string(text) if c.NAME == "STRAIGHT_FEED"] == [0.0, 2.0, 4.0]
    assert 2 not in checked and 4 not in checked and 1 in checked


# --- a straight line compiled into one function (gcode_canon.fast_lines) against _fast_values --------

def _fast_state(interp: Interpreter) -> tuple:
    return (list(interp.prog), interp.pos, interp.motion, interp.feed, interp._tail)


@pytest.mark.parametrize("seed", range(40))
def test_a_straight_lines_function_does_what_fast_values_does(seed: int) -> None:
    from gcode_canon.fast_lines import straight_function

    rng = random.Random(seed)
    for _ in range(60):
        interp, twin = _interp(), _interp()
        line = rng.randint(1, 99)
        absolute, scale = rng.random() < 0.6, rng.choice([1.0, 25.4])
        motion_in_force, feed = rng.choice([0, 10, 10, 20, 800]), rng.choice([0.0, 300.0, 500.0])
        prog = [rng.uniform(-9, 9) for _ in range(9)]
        sums = tuple(rng.choice([0.0, 1.5, -2.0]) for _ in range(9))
        for one in (interp, twin):
            one.file, one.line, one.absolute, one.scale = "t.ngc", line, absolute, scale
            one.motion, one.feed, one.prog[:] = motion_in_force, feed, prog
            one.frames.sum, one._tail = sums, None
        motion = rng.choice([None, 0, 10])
        letters = rng.sample("xyzf", rng.randint(1, 4))
        if not {"x", "y", "z"} & set(letters):
            letters.append("x")
        plain = {letter: rng.choice([1.0, -2.5, 0.0, 1e308, 600.0, -5.0]) for letter in letters}
        values: dict[str, object] = dict(plain)
        if rng.random() < 0.5:  # computed values (a compiled line's nodes), one failing now and then
            values = {letter: (lambda v=v: v) for letter, v in plain.items()}
        failing = values is not plain and rng.random() < 0.2
        if failing:
            values[rng.choice(letters)] = lambda: 1.0 / 0.0
        comment = rng.choice([None, "note"])
        got = straight_function(interp, motion, values, comment)()
        want = None if failing else twin._fast_values(motion, *(plain.get(k) for k in "xyzf"))
        if want is not None and comment is not None:
            want = twin._commented(lambda want=want: want, comment)()
        assert (None if got is None else [repr(c) for c in got]) == (
            None if want is None else [repr(c) for c in want]), (motion, plain, comment, failing)
        assert _fast_state(interp) == _fast_state(twin)  # the same change, or none when declined


def test_literal_lines_read_again_are_parsed_once_and_kept(monkeypatch) -> None:
    # a line the pattern runs (FAST_LINE) is noted; read again, it is parsed and kept with its fast
    # path; after as many lines as the cache holds with none read again, no more are noted until one
    # noted before comes back
    from gcode_canon.compiled import LineCache

    interp = _interp()
    interp._lines.size = 8
    parsed: list[int] = []
    parse = LineCache.parse

    def counted(self, raw):
        parsed.append(interp.line)
        return parse(self, raw)

    monkeypatch.setattr(LineCache, "parse", counted)
    unique = [f"G1 X{k} Y1" for k in range(1, 15)]
    text = "\n".join(["G21 G90 F600", *unique[:6], unique[0],  # lines 1, 2-7, 8
                      "G0 X20", "G0 X20", "G0 X20", *unique[6:],  # 9-11, 12-19
                      "G0 Y5", "G0 Y5", "M2"]) + "\n"  # 20-21, 22
    cmds = list(interp.run_string(text, "t.ngc"))
    # 8: noted at line 2, so parsed; 9 noted, 10 parsed, 11 kept; 12-19 noted, none read again: 20-21
    # are not, nor parsed
    assert parsed == [1, 8, 10, 22]
    assert [repr(c) for c in cmds] == [repr(c) for c in _interp().run_string(_general(text), "t.ngc")]


def test_a_straight_lines_factory_is_made_once_per_shape(monkeypatch) -> None:
    """Lines of one shape (motion, letters in order, which computed, a comment or not) share their
    factory: its source is not written out again for each line; lines of another shape get their own."""
    from gcode_canon import fast_lines

    made: list[tuple] = []
    factory = fast_lines._factory
    monkeypatch.setattr(fast_lines, "_BY_SHAPE", {})
    monkeypatch.setattr(fast_lines, "_factory", lambda *a: made.append(a) or factory(*a))
    interp = _interp()
    interp.file, interp.line, interp.motion, interp.feed = "t.ngc", 1, 10, 300.0
    for k in range(50):
        cmds = fast_lines.straight_function(interp, None, {"x": float(k), "y": lambda k=k: k / 2}, None)()
        assert cmds is not None and cmds[-1].end[:2] == (k, k / 2)
    assert len(made) == 1
    fast_lines.straight_function(interp, None, {"y": 1.0, "x": 2.0}, None)  # other shapes
    fast_lines.straight_function(interp, 0, {"x": 1.0, "y": 2.0}, None)
    fast_lines.straight_function(interp, None, {"x": 1.0, "y": 2.0}, "note")
    fast_lines.straight_function(interp, None, {"x": 1.0, "y": 2.0}, None)
    assert len(made) == 5
