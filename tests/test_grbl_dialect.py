"""Grbl programs in the Grbl dialect: the end of the file ends the program, ``$`` system-command
lines are skipped with a warning naming them, and corners blend within Grbl's junction deviation
(0.01 mm) unless the program sets G64 P."""

from __future__ import annotations

import logging
import math
import subprocess
import sys
from pathlib import Path

import pytest

from gcode_canon import Interpreter, InterpreterSettings
from gcode_canon import commands as C
from gcode_canon.errors import GCodeError
from planner import DEMO_MACHINE, plan_all

ROOT = Path(__file__).resolve().parent.parent
GRBL = "G21 G90\n$H\n$X\nG1 X50 F6000\nG1 Y50\n"  # no M2, M30 or %; a 90 degree corner at (50, 0)


def commands(text: str, dialect: str, tmp_path: Path) -> list[C.Canon]:
    p = tmp_path / "part.nc"
    p.write_text(text)
    return list(Interpreter(InterpreterSettings(dialect=dialect, dry_run=True)).run_file(p))


def test_end_of_file_ends_a_grbl_program(tmp_path: Path) -> None:
    cmds = commands(GRBL, "grbl", tmp_path)
    assert isinstance(cmds[-1], C.ProgramEnd) and cmds[-1].line == 5
    with pytest.raises(GCodeError, match="no percent sign or program end"):
        commands(GRBL.replace("$H\n$X\n", ""), "linuxcnc", tmp_path)


def test_dollar_lines_are_skipped_with_a_warning(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger="gcode_canon"):
        cmds = commands(GRBL, "grbl", tmp_path)
    warned = [r.getMessage() for r in caplog.records]
    assert any(m.endswith("part.nc:2: Grbl system command '$H' skipped (not G-code)") for m in warned)
    assert any("part.nc:3:" in m and "'$X'" in m for m in warned)
    assert [c.line for c in cmds if isinstance(c, C.StraightFeed)] == [4, 5]
    with pytest.raises(GCodeError, match=r"Bad character used: '\$'"):
        commands(GRBL + "M2\n", "linuxcnc", tmp_path)


def corner_gap(text: str, dialect: str, tmp_path: Path) -> float:
    """How far the planned path passes from the programmed corner (50, 0)."""
    cmds = commands(text, dialect, tmp_path)
    return min(math.dist(sp.positions[:2], (50.0, 0.0)) for sp in plan_all(iter(cmds), DEMO_MACHINE))


def test_grbl_junction_deviation_unless_g64_p(tmp_path: Path) -> None:
    cmds = commands(GRBL, "grbl", tmp_path)
    first = next(c for c in cmds if isinstance(c, C.SetMotionControlMode))
    assert (first.mode, first.tolerance) == (C.MotionControlMode.CONTINUOUS, 0.01)
    grbl = corner_gap(GRBL, "grbl", tmp_path)
    assert 0.001 < grbl <= 0.0105  # rounded, within Grbl's 0.01 mm
    linuxcnc = corner_gap(GRBL.replace("$H\n$X\n", "") + "M2\n", "linuxcnc", tmp_path)
    assert linuxcnc > 0.05  # LinuxCNC's G64 without P: as fast as the limits allow
    wide = corner_gap(GRBL.replace("G21 G90", "G21 G90 G64 P0.5"), "grbl", tmp_path)
    assert 0.05 < wide <= 0.51  # (sampled every cycle: the nearest setpoint may sit a little further)


def test_canon_run_grbl_program_without_an_end(tmp_path: Path) -> None:
    p = tmp_path / "part.nc"
    p.write_text("G21 G90\n$H\nG0 X5 Y5\nG1 X10 F1200\n")
    r = subprocess.run([sys.executable, "-m", "motiond.cli", "run", "--no-telemetry", "--json", "--dialect",
                        "grbl", str(p)], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert '"x": 10.0' in r.stdout and "'$H' skipped" in r.stderr
