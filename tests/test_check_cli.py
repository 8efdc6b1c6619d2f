"""``canon check``: text and JSON output, options, and FILE:LINE errors with a non-zero exit."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from gcode_canon.paramfile import write_parameter_file
from motiond.cli import main

PROGRAMS = Path(__file__).resolve().parent / "programs"


def write(tmp_path: Path, text: str, name: str = "p.ngc") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_text_output_names_and_lines(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write(tmp_path, "G0 X1 Y2\nF50\nG1 Z-1\nG2 X3 Y2 I1\nG4 P0.5\nM2\n")
    assert main(["check", str(path)]) == 0
    lines = capsys.readouterr().out.split("\n")
    body = [line.split(None, 1) for line in lines if line]
    assert body == [
        ["1", "STRAIGHT_TRAVERSE(1.0000, 2.0000, 0.0000, 0.0000, 0.0000, 0.0000)"],
        ["2", "SET_FEED_RATE(50.0000)"],
        ["3", "STRAIGHT_FEED(1.0000, 2.0000, -1.0000, 0.0000, 0.0000, 0.0000)"],
        ["4", "ARC_FEED(3.0000, 2.0000, 2.0000, 2.0000, -1, -1.0000, 0.0000, 0.0000, 0.0000)"],
        ["5", "DWELL(0.5000)"],
        ["6", "SET_FEED_RATE(0.0000)"],
        ["6", "PROGRAM_END(FALSE)"],
    ]


def test_json_output(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write(tmp_path, "G20 G0 X1 A10\nG1 F2 Y1\n(MSG,hi)\nM2\n")
    assert main(["check", "--json", str(path)]) == 0
    objs = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert objs[0] == {"line": 1, "file": str(path), "command": "USE_LENGTH_UNITS", "metric": False}
    move = objs[1]
    assert move["command"] == "STRAIGHT_TRAVERSE" and move["line"] == 1
    assert (move["x"], move["y"], move["z"], move["a"], move["b"], move["c"]) == (25.4, 0, 0, 10, 0, 0)
    assert objs[2] == {"line": 2, "file": str(path), "command": "SET_FEED_RATE", "rate": 50.8}
    assert objs[3]["y"] == 25.4
    assert objs[4]["command"] == "MESSAGE" and objs[4]["text"] == "hi"


def test_error_exit_with_file_and_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write(tmp_path, "G0 X1\nG1 X[SQRT[-4]]\nM2\n")
    assert main(["check", str(path)]) == 1
    captured = capsys.readouterr()
    assert captured.err.strip() == f"{path}:2: Negative argument to SQRT: -4"
    assert "Traceback" not in captured.err


def test_missing_program_end_is_an_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write(tmp_path, "G0 X1\n")
    assert main(["check", str(path)]) == 1
    assert "no percent sign or program end" in capsys.readouterr().err


def test_var_and_tool_table_and_block_delete(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    var = tmp_path / "p.var"
    write_parameter_file(var, {5221: 100.0})
    before = var.read_bytes()
    path = write(tmp_path, "T1 M6 G43\nG0 X0 Z0\n/G0 X5\nG10 L2 P1 X1\nM2\n")
    args = ["check", "--var", str(var), "--tool-table", str(PROGRAMS / "tools.tbl"), str(path)]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "STRAIGHT_TRAVERSE(100.0000, 0.0000, 10.0000" in out
    assert "STRAIGHT_TRAVERSE(105.0000" in out
    assert var.read_bytes() == before  # a check never writes the parameter file
    assert main([*args[:-1], "--block-delete", str(path)]) == 0
    assert "STRAIGHT_TRAVERSE(105.0000" not in capsys.readouterr().out


def test_missing_files_are_user_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", str(tmp_path / "none.ngc")]) == 1
    assert "no such file" in capsys.readouterr().err
    path = write(tmp_path, "M2\n")
    assert main(["check", "--var", str(tmp_path / "none.var"), str(path)]) == 1


def test_canon_check_as_a_process(tmp_path: Path) -> None:
    path = write(tmp_path, "G0 X1\nG0 Q1\nM2\n")
    proc = subprocess.run([sys.executable, "-m", "motiond.cli", "check", str(path)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1
    assert proc.stdout.strip() == "1 STRAIGHT_TRAVERSE(1.0000, 0.0000, 0.0000, 0.0000, 0.0000, 0.0000)"
    assert proc.stderr.strip() == f"{path}:2: Q word with no G or M code that uses it"


def test_config_restricts_the_axes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "mill.toml"
    config.write_text(
        '[machine]\nname = "three axes"\n'
        + "".join(f"[axes.{a}]\nmax_velocity = 100.0\nmax_acceleration = 1000.0\nmax_jerk = 10000.0\n"
                  for a in "xyz")
    )
    path = write(tmp_path, "G0 X1 Y2 Z3\nG0 A90\nM2\n")
    assert main(["check", "--config", str(config), str(path)]) == 1
    assert capsys.readouterr().err.strip() == f"{path}:2: A word used, but the machine has no A axis"
    assert main(["check", str(path)]) == 0  # without a configuration all nine axes are accepted


def test_dialect_and_subroutine_path_options(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    subs = tmp_path / "lib"
    subs.mkdir()
    (subs / "side.ngc").write_text("o<side> sub\nG0 X#1\no<side> endsub\n")
    prog = write(tmp_path, "o<side> call [3]\nM2\n")
    assert main(["check", "--subroutine-path", str(subs), str(prog)]) == 0
    assert "STRAIGHT_TRAVERSE(3.0000" in capsys.readouterr().out
    assert main(["check", str(prog)]) != 0
    assert "no file side.ngc on the subroutine path" in capsys.readouterr().err
    assert main(["check", "--dialect", "fanuc9", str(prog)]) != 0
    assert "unknown G-code dialect" in capsys.readouterr().err
    labels = write(tmp_path, "#1=0\nO5\n#1=[#1+1]\no1 if [#1 LT 2]\nM98 P5\no1 endif\nM99\nM2\n", "f.ngc")
    assert main(["check", "--dialect", "gcode-canon", str(labels)]) == 0
    assert main(["check", str(labels)]) != 0  # LinuxCNC: O5 reached in the flow of the main program
    assert "main program must end" in capsys.readouterr().err


def checked_as_format_text(path: Path, capsys: pytest.CaptureFixture[str]) -> list[str]:
    """``canon check``'s text lines for ``path``, checked equal to :func:`format_text`'s for the same
    commands."""
    from gcode_canon.interpreter import Interpreter
    from gcode_canon.settings import InterpreterSettings
    from motiond.cmd_check import format_text

    assert main(["check", str(path)]) == 0
    out = capsys.readouterr().out.splitlines()
    expected = [f"{cmd.line:>6} {format_text(cmd)}"
                for cmd in Interpreter(InterpreterSettings(dry_run=True)).run_file(path)]
    assert out == expected
    return out


def test_straight_moves_are_written_as_format_text_writes_them(tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    """The bulk of the text (straight moves with A B C U V W at zero) is formatted in one go: the same
    text as :func:`motiond.cmd_check.format_text`, "-0.0000" written "0.0000" included."""
    values = ["0", "-0.00004", "0.00004", "-0.00005", "-0.00006", "-10", "12.34565", "-0.000049999", "1e3"]
    body = [f"G{k % 2} X{values[k % 9]} Y{values[(k * 4) % 9]} Z{values[(k * 7 + 1) % 9]}" for k in range(81)]
    body += ["G0 A-0.00004 X1", "G1 A0 B0.5", "G0 X-0.00001 Y2"]
    text = "G21 F100\n" + "\n".join(body).replace("e3", "000") + "\nM2\n"
    out = checked_as_format_text(write(tmp_path, text), capsys)
    assert any("STRAIGHT_FEED(0.0000, 0.0000, 0.0000" in line for line in out)


def test_arcs_are_written_with_four_decimals_and_no_negative_zero(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """ARC_FEED as LinuxCNC orders its arguments, each number as ``_num`` writes it."""
    from gcode_canon.commands import ArcFeed
    from gcode_canon.interpreter import Interpreter
    from gcode_canon.settings import InterpreterSettings
    from motiond.cmd_check import _num

    text = ("G21 G17 F100\nG0 X0 Y0 Z-0.00004\nG2 X-0.00004 Y10 I0 J5\nG3 X0.00004 Y0 J-5 Z-0.00006\n"
            "G18\nG2 Z-0.00004 X4 K0 I2\nG19 G3 Y0 Z-3 J-0.00003 K-1.5 P2\nM2\n")
    path = write(tmp_path, text)
    assert main(["check", str(path)]) == 0
    arcs = [line.split(None, 1)[1] for line in capsys.readouterr().out.splitlines() if "ARC_FEED" in line]
    expected = []
    for cmd in Interpreter(InterpreterSettings(dry_run=True)).run_file(path):
        if isinstance(cmd, ArcFeed):
            f, s, n = cmd.plane.value
            e, c = cmd.end, cmd.center
            values = [_num(e[f]), _num(e[s]), _num(c[f]), _num(c[s]), str(cmd.turns), _num(e[n]),
                      _num(e[3]), _num(e[4]), _num(e[5])]
            expected.append(f"ARC_FEED({', '.join(values)})")
    assert arcs == expected and len(arcs) == 4
    assert not any("-0.0000" in line for line in arcs)


def test_every_command_is_written_as_format_text_writes_it(tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    """Arcs in the three planes (U V W in use or not) and comments, written in one formatting by
    ``canon check``, give :func:`motiond.cmd_check.format_text`'s text."""
    text = ("G21 G17 F100\nG0 X0 Y0 Z-0.00004 (start here)\nG2 X-0.00004 Y10 I0 J5 A-0.00003\n"
            "G3 X0.00004 Y0 J-5 Z-0.00006 (a \"quoted\" comment)\nG18\nG2 Z-0.00004 X4 K0 I2 B1.5\n"
            "G19 G3 Y0 Z-3 J-0.00003 K-1.5 P2\nG17 G2 X1 Y1 R3 U0.00004 V2\nG3 X0 Y0 R-3 W-0.00002\nM2\n")
    out = checked_as_format_text(write(tmp_path, text), capsys)
    assert sum("ARC_FEED" in line for line in out) == 6 and sum("COMMENT" in line for line in out) == 2


def test_text_is_written_in_blocks_whatever_the_commands(tmp_path: Path) -> None:
    """The text goes out in blocks of at most 256 lines, also for a program of straight moves only
    (whose lines once piled up until the end)."""
    import argparse

    from gcode_canon.interpreter import Interpreter
    from gcode_canon.settings import InterpreterSettings
    from motiond.cmd_check import _write

    path = write(tmp_path, "G21 F100\n" + "".join(f"G1 X{k} Y{k % 7}\n" for k in range(2000)) + "M2\n")
    writes: list[str] = []
    _write(Interpreter(InterpreterSettings(dry_run=True)), argparse.Namespace(file=str(path), json=False),
           writes.append, None)
    assert max(chunk.count("\n") for chunk in writes) <= 256
    assert sum(chunk.count("STRAIGHT_FEED") for chunk in writes) == 2000


def test_texts_keep_their_negative_zero_and_percent_signs(tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """A block's moves are formatted in one ``%`` formatting with "-0.0000" replaced over its text: a
    comment or message between them keeps its own "-0.0000" and "%" as written, in any block."""
    body = []
    for k in range(300):  # more than a block of commands
        body.append(f"G1 X-0.00001 Y{k} (at {k} -0.0000 and 100% %s)" if k % 3 else f"G0 X{k} Z-0.00004")
        if k % 50 == 7:
            body.append("(MSG, -0.0000 %d %%)")
    out = checked_as_format_text(write(tmp_path, "G21 F100\n" + "\n".join(body) + "\nM2\n"), capsys)
    assert sum('-0.0000 and 100% %s")' in line for line in out) == 200
    assert sum("MESSAGE(" in line and line.endswith('-0.0000 %d %%")') for line in out) == 6
    assert not any("-0.0000" in line for line in out if "STRAIGHT" in line)


@pytest.mark.parametrize("before", [0, 1, 255, 256, 257, 600])
def test_the_commands_before_an_error_are_written_before_it(tmp_path: Path, before: int,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    """Whatever the error's place in a block of commands (gathered 256 at a time), every command before
    it is written, and nothing after it."""
    lines = "".join(f"G1 X{k + 1}\n" for k in range(before))
    path = write(tmp_path, f"G21 F100\n{lines}G1 X[1 / 0]\nG1 X-1\nM2\n")
    assert main(["check", str(path)]) == 1
    captured = capsys.readouterr()
    assert captured.err.strip() == f"{path}:{before + 2}: Attempt to divide by zero"
    moves = [line for line in captured.out.splitlines() if "STRAIGHT_FEED" in line]
    assert len(moves) == before
    assert moves == [] or moves[-1].split()[0] == str(before + 1)
