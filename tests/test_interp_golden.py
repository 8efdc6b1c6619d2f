"""Golden programs: tests/programs/NAME.ngc must produce exactly NAME.expected.

The expected files were worked out by hand from the LinuxCNC G-code documentation (comments in them
say how); they are compared line by line with ``canon check``'s text form of the commands.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from gcode_canon.interpreter import Interpreter
from gcode_canon.settings import InterpreterSettings
from motiond.cmd_check import format_text

PROGRAMS = Path(__file__).resolve().parent / "programs"
CASES = sorted(p.stem for p in PROGRAMS.glob("*.ngc") if (PROGRAMS / f"{p.stem}.expected").exists())


def expected_lines(path: Path) -> list[str]:
    lines = []
    for raw in path.read_text().splitlines():
        raw = raw.strip()
        if raw and not raw.startswith("#"):
            number, text = raw.split(" ", 1)
            lines.append(f"{int(number)} {text}")
    return lines


@pytest.mark.parametrize("name", CASES)
def test_golden(name: str) -> None:
    table = PROGRAMS / f"{name}.tbl"
    if not table.exists():
        table = PROGRAMS / "tools.tbl"
    settings = InterpreterSettings(dry_run=True, tool_table=table, subroutine_path=[PROGRAMS / "subs"])
    got = [f"{c.line} {format_text(c)}" for c in Interpreter(settings).run_file(PROGRAMS / f"{name}.ngc")]
    assert got == expected_lines(PROGRAMS / f"{name}.expected")


def test_there_are_golden_programs() -> None:
    assert {"arcs", "basic", "offsets", "params", "rotation", "tools_io", "owords", "cycles", "cycles_all",
            "extensions", "backbore"} <= set(CASES)
