"""``canon --version``, the program file named on the command line (clear messages for what is not a
readable regular file), and ``canon check`` naming the file of a subroutine's lines."""

from __future__ import annotations

import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import pytest

from motiond.cli import main

ROOT = Path(__file__).resolve().parent.parent


def test_version() -> None:
    r = subprocess.run([sys.executable, "-m", "motiond.cli", "--version"], capture_output=True, text=True,
                       timeout=60, cwd=ROOT)
    assert r.returncode == 0 and r.stdout.strip() == f"canon {version('canon')}"


@pytest.mark.parametrize("command", ["check", "plan", "run"])
def test_what_is_wrong_with_the_program_file(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                             command: str) -> None:
    afile = tmp_path / "a.ngc"
    afile.write_text("%\nM2\n%\n")
    for name, words in ((str(tmp_path), "is a directory, not a G-code program"),
                        ("/dev/null", "is a device file, not a G-code program"),
                        (str(afile / "x.ngc"), "Not a directory"),
                        (str(tmp_path / "none.ngc"), "no such file")):
        assert main([command, "--no-telemetry", name] if command == "run" else [command, name]) == 1
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"canon {command}: {name}: ") and words in err and "\n" not in err, err


def test_check_names_the_subroutine_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    subs = tmp_path / "subs"
    subs.mkdir()
    (subs / "dr.ngc").write_text("o<dr> sub\nG1 Z-1 F100\no<dr> endsub\nM2\n")
    prog = tmp_path / "main.ngc"
    prog.write_text("%\nG0 X1\no<dr> call\nG0 X2\nM2\n%\n")
    assert main(["check", "--subroutine-path", str(subs), str(prog)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split()[:2] == ["2", "STRAIGHT_TRAVERSE(1.0000,"]
    feed = f"{subs / 'dr.ngc'}:2 STRAIGHT_FEED(1.0000, 0.0000, -1.0000"
    assert any(line.startswith(feed) for line in lines)
    assert lines[-1].split() == ["5", "PROGRAM_END(FALSE)"]


def test_check_imports_only_its_own_sub_command(tmp_path: Path) -> None:
    """canon check's start-up: the other sub-commands (fieldbus, LCM) and importlib.metadata (for
    --version) are not imported; --help still lists every sub-command."""
    program = tmp_path / "a.ngc"
    program.write_text("G0 X1\nM2\n")
    code = ("import sys; from motiond.cli import main; main(['check', sys.argv[1]]); "
            "print(sorted(m for m in sys.modules if m.startswith('motiond.cmd_') "
            "or m == 'importlib.metadata'))")
    r = subprocess.run([sys.executable, "-c", code, str(program)], capture_output=True, text=True, timeout=60,
                       cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == "['motiond.cmd_check']"
    # nor the Modbus stack (pymodbus imports asyncio: a quarter of a second), nor the fieldbus layer
    code = ("import sys; from motiond.cli import main; main(['check', sys.argv[1]]); "
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'pymodbus', 'asyncio', 'fieldbus'}))")
    r = subprocess.run([sys.executable, "-c", code, str(program)], capture_output=True, text=True, timeout=60,
                       cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == "[]"
    r = subprocess.run([sys.executable, "-m", "motiond.cli", "--help"], capture_output=True, text=True,
                       timeout=60, cwd=ROOT)
    assert all(name in r.stdout for name in ("check", "plan", "run", "daemon", "status"))


LEAN = [["check", "a.ngc"], ["-v", "check", "a.ngc"], ["-vv", "--verbose", "plan", "a.ngc"], ["check", "-h"],
        ["check"], ["check", "--bogus", "a.ngc"], ["check", "--json", "check"]]
WHOLE = [["-h", "check"], ["--he", "check"], ["-vh", "check"], ["-", "check"], ["--", "check", "a.ngc"],
         ["--verb", "check", "a.ngc"], ["nothing"], [], ["--version", "check"], ["-x", "check"]]


@pytest.mark.parametrize("words", LEAN + WHOLE)
def test_the_other_sub_commands_are_left_out_only_where_nothing_lists_them(
        words: list[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """``canon check FILE`` (``-v`` before it or not) builds no parser for the other sub-commands; a
    command line whose top-level part could print the list of sub-commands (``-h``, ``--he``, ``-vh``,
    an unknown command or ``-`` as one) builds them all. What ``canon`` prints and returns is the same
    as with every sub-command's parser built."""
    from motiond import cli

    monkeypatch.chdir(tmp_path)  # a.ngc: no such file there
    original = cli.build_parser
    built: list[bool] = []

    def run(build) -> tuple:
        monkeypatch.setattr(cli, "build_parser", build)
        try:
            result: object = cli.main(words)
        except SystemExit as exc:
            result = ("exit", exc.code)
        out = capsys.readouterr()
        return result, out.out, out.err

    def recording(only=None, *, others=True):
        built.append(others)
        return original(only, others=others)

    lean = run(recording)
    whole = run(lambda only=None, *, others=True: original(only, others=True))
    assert lean == whole
    assert built == [words in WHOLE]


def test_check_imports_the_rare_motions_geometry_only_when_a_program_uses_them(tmp_path: Path) -> None:
    """G76's passes, the splines' curves, the lathe cycles' profiles and cutter compensation's geometry
    are imported by the program that uses them, not at every ``canon check``'s start-up."""
    rare = ["gcode_canon.cutter_comp", "gcode_canon.lathe_profile", "gcode_canon.splines",
            "gcode_canon.threading_cycle"]
    code = ("import sys; from motiond.cli import main; main(['check', sys.argv[1]]); "
            f"print(sorted(m for m in sys.modules if m in {rare!r}))")
    programs = {"plain": "G0 X1\nG1 X2 F100\nM2\n", "thread": "G20 G18 G0 X0.3 Z0.1\nS300 M3\n"
                "G76 P0.05 Z-1 I-0.075 J0.008 K0.045 Q29.5 L2 E0.045 H2 R2\nM2\n",
                "spline": "G21 G17 F100\nG5 X10 Y0 I5 J5 P5 Q-5\nM2\n",
                "comp": "G21 G17 F100\nG0 X0 Y0\nG41.1 D2 G1 X10\nG1 Y10\nG40 G0 X20\nM2\n"}
    seen = {}
    for name, text in programs.items():
        program = tmp_path / f"{name}.ngc"
        program.write_text(text)
        r = subprocess.run([sys.executable, "-c", code, str(program)], capture_output=True, text=True,
                           timeout=60, cwd=ROOT)
        assert r.returncode == 0 and r.stderr == "", r.stderr
        seen[name] = r.stdout.strip().splitlines()[-1]
    assert seen == {"plain": "[]", "thread": "['gcode_canon.threading_cycle']",
                    "spline": "['gcode_canon.splines']", "comp": "['gcode_canon.cutter_comp']"}
