"""Bad input gets ``FILE:LINE: message`` (or the option / key name), never a traceback, never a hang.

A seeded generator (:mod:`tests.broken_programs`) builds valid and slightly broken programs; each runs
through the in-process interpreter in every dialect and through ``canon check`` / ``canon plan``
(in process): it succeeds or fails with a :class:`GCodeError` naming the file and a line, never another
exception, never an "internal error", within a time bound (the interpreter's own limits,
``max_loop_iterations`` and ``max_call_depth``, stop runaway loops and recursion). Then the command
line given files that are not programs, as separate processes.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from gcode_canon.commands import Plane
from gcode_canon.errors import GCodeError
from gcode_canon.interpreter import Interpreter
from gcode_canon.settings import InterpreterSettings
from motiond.cli import main
from tests.broken_programs import program

ROOT = Path(__file__).resolve().parent.parent
DIALECTS = ("linuxcnc", "gcode-canon", "grbl")
LIMITS = {"max_loop_iterations": 200, "max_call_depth": 5}
SECONDS = 10.0
"""One program's time bound (a loaded machine): far above the few milliseconds each takes."""


@contextmanager
def time_bound(what: str) -> Iterator[None]:
    """Fail (not hang) when the body runs longer than :data:`SECONDS` (the main thread's SIGALRM)."""
    def expired(signum: int, frame: object) -> None:
        raise TimeoutError(f"{what}: still running after {SECONDS} s (a hang?)")

    previous = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, SECONDS)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def assert_user_error(exc: GCodeError, file: str, text: str) -> None:
    assert exc.file == file, f"{exc!s} names the wrong file\n{text}"
    assert 1 <= exc.line <= text.count("\n") + 1, f"{exc!s}: no line of the program\n{text}"
    assert exc.message and "internal error" not in exc.message, f"{exc!s}\n{text}"


def run_interpreter(text: str, dialect: str) -> None:
    interp = Interpreter(InterpreterSettings(dry_run=True, dialect=dialect, **LIMITS))
    with time_bound(f"{dialect}: {text!r}"):
        try:
            for count, _ in enumerate(interp.run_string(text, "fuzz.ngc")):
                assert count < 100_000, text
        except GCodeError as exc:
            assert_user_error(exc, "fuzz.ngc", text)


@pytest.mark.parametrize("block", range(3))
def test_generated_programs_in_every_dialect(block: int) -> None:
    """300 programs (half with odd values and mutations), each in the three dialects."""
    for seed in range(block * 100, block * 100 + 100):
        text = program(seed, broken=seed % 2 == 0)
        for dialect in DIALECTS:
            run_interpreter(text, dialect)


@pytest.fixture(scope="module")
def limited_config(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The example machine with the loop and call limits of the in-process runs."""
    text = (ROOT / "examples" / "canon.toml").read_text()
    text, n = re.subn(r"(?m)^max_call_depth = \d+", "max_call_depth = 5", text)
    text, m = re.subn(r"(?m)^max_loop_iterations = \d+", "max_loop_iterations = 200", text)
    assert n == m == 1
    path = tmp_path_factory.mktemp("config") / "limited.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("command", ["check", "plan"])
def test_generated_programs_through_the_command_line(command: str, limited_config: Path, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """``canon check`` / ``canon plan`` in process: exit 0 (or 2: plan's checks failed), or 1 with
    the last line of stderr ``FILE:LINE: message``; never an exception out of main."""
    path = tmp_path / "fuzz.ngc"
    for seed in range(1000, 1040):
        text = program(seed, broken=seed % 3 == 0)
        path.write_text(text)
        with time_bound(f"canon {command} {text!r}"):
            rc = main([command, "--config", str(limited_config), str(path)])
        err = capsys.readouterr().err
        assert rc in (0, 1, 2), text
        if rc == 1:
            last = err.strip().splitlines()[-1]
            assert re.match(rf"{re.escape(str(path))}:\d+: \S", last), f"{last}\n{text}"
            assert "internal error" not in err and "Traceback" not in err, f"{err}\n{text}"


# ---- the violations the generator found, each pinned ---------------------------------------------------

def test_m98_repeat_count_is_bounded_by_max_loop_iterations() -> None:
    """``M98 P100 L1000000000`` ran its subprogram a billion times: no limit applied to L."""
    text = "M98 P100 L1000000000\nM2\nO100\nM99\n"
    interp = Interpreter(InterpreterSettings(dry_run=True, max_loop_iterations=1000))
    with time_bound("M98 L1e9"), pytest.raises(GCodeError) as info:
        list(interp.run_string(text, "m98.ngc"))
    assert (info.value.file, info.value.line) == ("m98.ngc", 1)
    assert info.value.message == "M98 P100 L1000000000 is more than 1000 iterations (max_loop_iterations)"
    # within the limit: run L times (three arcs of the subprogram)
    text = "G21 F100\nM98 P100 L3\nM2\nO100\nG91 G1 X1\nM99\n"
    out = Interpreter(InterpreterSettings(dry_run=True, max_loop_iterations=3)).run_string(text, "m98.ngc")
    assert [c.line for c in out if c.NAME == "STRAIGHT_FEED"] == [5, 5, 5]


NESTED = "o1 repeat [{n}]\no2 repeat [{n}]\n{body}\no2 endrepeat\no1 endrepeat\nM2\n"


@pytest.mark.parametrize("body", ["#1 = [#1 + 1]", "o3 while [1]\no3 break\no3 endwhile", "M98 P7 L2"])
def test_nested_loops_without_a_move_are_bounded_together(body: str) -> None:
    """Each loop is bounded by max_loop_iterations on its own, but nested loops multiplied: ``repeat
    [1e5]`` in ``repeat [1e5]`` ran 1e10 passes, hours with nothing to show. Loop passes without a move,
    all loops together, are bounded by the same limit (here 1,000 x 1,000 passes, each loop within it)."""
    text = NESTED.format(n=1000, body=body).replace("M2\n", "M2\nO7\n#2 = 1\nM99\n")
    interp = Interpreter(InterpreterSettings(dry_run=True, max_loop_iterations=1000))
    with time_bound(f"nested {body}"), pytest.raises(GCodeError) as info:
        list(interp.run_string(text, "nested.ngc"))
    assert info.value.file == "nested.ngc"
    assert "more than 1000 loop passes without a move" in info.value.message, info.value.message


def test_nested_loops_that_move_are_a_long_program_not_a_runaway() -> None:
    """40 x 40 passes with a move in each: 1,600 passes, over a limit of 1,000 in all, but each moves."""
    text = "G21 G91 F100\n" + NESTED.format(n=40, body="G1 X0.001")
    out = list(Interpreter(InterpreterSettings(dry_run=True, max_loop_iterations=1000)).run_string(text))
    assert sum(c.NAME == "STRAIGHT_FEED" for c in out) == 1600


@pytest.mark.parametrize("dialect", DIALECTS)
@pytest.mark.parametrize("plane", ["G17.1", "G18.1", "G19.1"])
@pytest.mark.parametrize("arc", ["G2 X1 Y1 U1 V1 W1 R1", "G3 U1 I1 J1 K1", "G12 I2", "G83 U1 V1 W-1 R1 Q1",
                                 "G41 D1 G2 U1 V1 R1", "G5 X1 Y1 I1 J1 P1 Q1", "G71 Q10 D1"])
def test_arcs_in_uvw_planes_are_clean_errors(dialect: str, plane: str, arc: str) -> None:
    """Every way into an arc, every UVW plane, every dialect: ``FILE:LINE`` (today the plane itself
    is refused, on its own line or on the arc's)."""
    for text in (f"G21 F100\n{plane}\n{arc}\nM2\n", f"G21 F100\n{plane} {arc}\nM2\n"):
        interp = Interpreter(InterpreterSettings(dry_run=True, dialect=dialect))
        with pytest.raises(GCodeError) as info:
            list(interp.run_string(text, "uvw.ngc"))
        assert (info.value.file, info.value.line) == ("uvw.ngc", 2)
        assert f"{plane} " in info.value.message and "internal error" not in info.value.message


@pytest.mark.parametrize("plane", [Plane.UV, Plane.WU, Plane.VW])
@pytest.mark.parametrize("line", ["G2 X1 Y1 R1", "G3 X1 I1", "G12 I2", "G13 I2"])
def test_an_arc_in_a_uvw_plane_is_refused_as_linuxcnc_does(plane: Plane, line: str) -> None:
    """Should a UVW plane be selected (G17.1 is refused today, see above), an arc in it is LinuxCNC's
    error, not an IndexError out of the arc code (``_IJK[normal]`` with normal > 2)."""
    interp = Interpreter(InterpreterSettings(dry_run=True))
    interp.plane = plane
    with pytest.raises(GCodeError) as info:
        interp.execute_mdi(f"{line} F100")
    assert (info.value.file, info.value.line) == ("<mdi>", 1)
    assert info.value.message == "Cannot do an arc in planes G17.1, G18.1, or G19.1"


# ---- the command line, given files that are not programs (separate processes) ------------------------

def run_canon(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "motiond.cli", *args], capture_output=True, text=True,
                          timeout=60, cwd=ROOT)


@pytest.fixture(scope="module")
def bad_inputs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("bad")
    files = {"missing": d / "missing.ngc", "directory": d / "dir.ngc", "binary": d / "binary.ngc",
             "latin-1": d / "latin1.ngc", "empty": d / "empty.ngc"}
    files["directory"].mkdir()
    files["binary"].write_bytes(bytes(range(256)) * 4)
    files["latin-1"].write_bytes("G0 X1 (café)\nM2\n".encode("latin-1"))
    files["empty"].write_bytes(b"")
    return files


EXPECTED = {"missing": ": no such file", "directory": ": is a directory", "binary": ":1: ",
            "latin-1": ":1: Line is not valid UTF-8 text", "empty": ":1: File ended with no percent sign"}


@pytest.mark.parametrize("command", ["check", "plan"])
def test_program_files_that_are_not_programs(command: str, bad_inputs: dict[str, Path],
                                             capsys: pytest.CaptureFixture[str]) -> None:
    """Exit 1, one line naming the file (and the line), no traceback: in process for each input,
    then as a process for one of them."""
    for kind, path in bad_inputs.items():
        assert main([command, str(path)]) == 1, kind
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and str(path) + EXPECTED[kind] in lines[0], (kind, lines)
    kind = "binary" if command == "check" else "latin-1"
    proc = run_canon(command, str(bad_inputs[kind]))
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.startswith(str(bad_inputs[kind]) + EXPECTED[kind]), proc.stderr


def test_option_files_that_are_not_files(bad_inputs: dict[str, Path], tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    """--tool-table / --var naming a directory said "no such file"; they say what it is now."""
    program_path = tmp_path / "ok.ngc"
    program_path.write_text("G0 X1\nM2\n")
    directory = bad_inputs["directory"]
    for option in ("--tool-table", "--var"):
        assert main(["check", option, str(directory), str(program_path)]) == 1
        assert capsys.readouterr().err == f"canon check: {option} {directory}: is a directory, not a file\n"
        assert main(["check", option, str(bad_inputs["missing"]), str(program_path)]) == 1
        assert capsys.readouterr().err.endswith(": no such file\n")
        assert main(["check", option, "/dev/null", str(program_path)]) == 1
        err = capsys.readouterr().err
        assert err == f"canon check: {option} /dev/null: is a device file, not a regular file\n"
    # canon run may create its --var file, but not in place of a directory (it said "DIR:0: cannot
    # read parameter file" after booting the machine)
    assert main(["run", "--no-telemetry", "--var", str(directory), str(program_path)]) == 1
    assert capsys.readouterr().err == f"canon run: --var {directory}: is a directory, not a file\n"


def test_a_device_or_a_pipe_as_the_machine_file_is_refused_not_read_for_ever(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--config /dev/zero`` read for ever, its memory growing (a process here: a read() that never
    returns is not stopped by a signal); a named pipe waited for a writer."""
    proc = run_canon("config", "check", "--config", "/dev/zero")  # TimeoutExpired: the violation
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert proc.stderr == "/dev/zero: is a device file, not a machine file (a regular file is needed)\n"
    pipe = tmp_path / "machine.toml"
    os.mkfifo(pipe)
    program_path = tmp_path / "ok.ngc"
    program_path.write_text("G0 X1\nM2\n")
    for argv in (["config", "check", "--config", str(pipe)],
                 ["check", "--config", str(pipe), str(program_path)]):
        with time_bound(" ".join(argv)):  # open() of a pipe is interrupted by the alarm
            assert main(argv) == 1
        err = capsys.readouterr().err
        assert err == f"{pipe}: is a pipe file, not a machine file (a regular file is needed)\n", err
    # the same pipe as [interpreter] var_file: canon check waited in its open()
    config = tmp_path / "var_pipe.toml"
    config.write_text((ROOT / "examples" / "canon.toml").read_text()
                      .replace('# var_file = "canon.var"', f'var_file = "{pipe}"', 1))
    with time_bound("var_file a pipe"):
        assert main(["check", "--config", str(config), str(program_path)]) == 1
    err = capsys.readouterr().err
    assert err == f"{config}: interpreter.var_file: is a pipe file, not a parameter file: {pipe}\n", err


def test_plot_file_of_no_image_format_is_refused_before_planning(tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """``canon plan --plot out.txt`` planned the whole program, then died with matplotlib's ValueError."""
    program_path = tmp_path / "ok.ngc"
    program_path.write_text("G21 F600\nG1 X10 Y10\nM2\n")
    plot = tmp_path / "out.txt"
    assert main(["plan", "--plot", str(plot), str(program_path)]) == 1
    captured = capsys.readouterr()
    assert captured.err.startswith(f"canon plan: --plot {plot}: .txt is not an image format (one of: ")
    assert captured.out == "" and not plot.exists()


def test_plan_of_a_feed_rate_slip_stops_at_its_time_bound(tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """``F0.0001`` over 10 mm is 69 days of machine time: canon plan kept every setpoint of it (it ran
    for hours, then out of memory). Past ``--max-time`` (8 h by default) it stops at the line."""
    program_path = tmp_path / "slip.ngc"
    program_path.write_text("G21 F600\nG1 X5\nG1 X10 F0.0001\nM2\n")
    with time_bound("canon plan F0.0001"):
        rc = main(["plan", "--max-time", "30", str(program_path)])
    assert rc == 1
    expected = (f"{program_path}:3: the planned run passes 30 s of machine time (--max-time) in this line: "
                "a feed rate too low, or a move too long?\n")
    assert capsys.readouterr().err == expected
    assert main(["plan", "--max-time", "-1", str(program_path)]) == 1
    assert "--max-time must be a positive number" in capsys.readouterr().err
    program_path.write_text("G21 F600\nG1 X5\nM2\n")  # 0.5 s: within any bound
    assert main(["plan", "--max-time", "30", "--json", str(program_path)]) == 0


def test_config_files_that_are_not_configs(bad_inputs: dict[str, Path], tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    """``canon config check``: the file and what is wrong (a key's name for a wrong type), exit 1."""
    example = (ROOT / "examples" / "canon.toml").read_text()
    wrong = tmp_path / "wrong.toml"
    wrong.write_text(example.replace("cycle_ms = 2.0", 'cycle_ms = "fast"', 1)
                     .replace("max_call_depth = 10", "max_call_depth = 1.5", 1))
    cases = {bad_inputs["missing"]: "no such file", bad_inputs["directory"]: "Is a directory",
             bad_inputs["binary"]: "not UTF-8 text", bad_inputs["latin-1"]: "not UTF-8 text",
             bad_inputs["empty"]: "axes: missing", wrong: "machine.cycle_ms: must be float, got str 'fast'"}
    for path, expected in cases.items():
        assert main(["config", "check", "--config", str(path)]) == 1, path
        err = capsys.readouterr().err
        assert err.startswith(f"{path}: ") and expected in err, err
    assert "interpreter.max_call_depth: must be int" in err  # every bad key is named
    proc = run_canon("config", "check", "--config", str(wrong))  # and as a process
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert proc.stderr.startswith(f"{wrong}: machine.cycle_ms: must be float"), proc.stderr
