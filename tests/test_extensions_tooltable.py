"""G10 tool table edits: LinuxCNC's L1 / L10 / L11, gcode-canon's L1 (radius) and L3 (height,
diameter); the table file is rewritten atomically unless dry run."""

from __future__ import annotations

from pathlib import Path

import pytest

from gcode_canon.errors import GCodeError
from gcode_canon.interpreter import Interpreter
from gcode_canon.settings import InterpreterSettings
from gcode_canon.tooltable import read_tool_table


@pytest.fixture
def table(tmp_path: Path) -> Path:
    path = tmp_path / "tool.tbl"
    path.write_text("T1 P1 Z10 D6 ;end mill\nT2 P2 Z20 D3\n")
    return path


def run(text: str, table: Path | None, dry_run: bool = False, dialect: str = "linuxcnc") -> Interpreter:
    interp = Interpreter(InterpreterSettings(dry_run=dry_run, tool_table=table, dialect=dialect))
    list(interp.run_string(text, "g10.ngc"))
    return interp


def test_g10_l1_sets_the_entry_and_writes_the_file(table: Path) -> None:
    interp = run("G20\nG10 L1 P2 Z1 R0.25 I10 J20 Q3\nT2 M6\nG43\nM2\n", table)
    tool = read_tool_table(table).get(2)
    assert tool is not None
    assert tool.offset.z == pytest.approx(25.4) and tool.diameter == pytest.approx(12.7)
    assert (tool.front_angle, tool.back_angle, tool.orientation) == (10.0, 20.0, 3)
    assert tool.pocket == 2
    assert interp.parameter(5403) == pytest.approx(25.4) and interp.parameter(5410) == pytest.approx(12.7)
    assert read_tool_table(table).get(1).offset.z == 10.0  # untouched
    assert (table.parent / "tool.tbl.bak").exists()


def test_dry_run_never_writes(table: Path) -> None:
    before = table.read_text()
    interp = run("G10 L1 P1 Z5\nT1 M6\nG43\nG0 Z0\nM2\n", table, dry_run=True)
    assert table.read_text() == before
    assert interp.position.z == 5.0  # but the program sees the new value


def test_g10_l10_and_l11_make_the_current_point_read_the_given_value(table: Path) -> None:
    # G54 Z offset 2, G92 Z offset 1 (the point at machine Z 8 is program Z 5); tool 1 loaded
    text = "G10 L2 P1 Z2\nG0 Z8\nG92 Z5\nT1 M6\nG10 L10 P1 Z3\nG43\n#1=#5422\nM2\n"
    interp = run(text, table)
    # machine 8 = 3 + 2 + 1 + T: T = 2; after G43 the position reads Z3
    assert read_tool_table(table).get(1).offset.z == pytest.approx(2.0)
    assert interp.parameter(1) == pytest.approx(3.0)
    text = "G10 L2 P9 Z-1\nG0 Z8\nG92 Z5\nG10 L11 P2 Z3\nM2\n"
    run(text, table)
    assert read_tool_table(table).get(2).offset.z == pytest.approx(8 - 3 + 1)  # G59.3, no G92


def test_gcode_canon_l1_and_l3(table: Path) -> None:
    run("G10 L1 P1 R4\nG10 L3 P2 H7 D9\nM2\n", table, dialect="gcode-canon")
    tools = read_tool_table(table)
    assert tools.get(1).diameter == 8.0 and tools.get(1).offset.z == 10.0
    assert tools.get(2).offset.z == 7.0 and tools.get(2).diameter == 9.0
    # L3 is an extension, accepted in the LinuxCNC dialect too; L1 there keeps LinuxCNC's meaning
    run("G10 L3 P1 H1\nG10 L1 P1 R1 Z4\nM2\n", table)
    assert read_tool_table(table).get(1).offset.z == 4.0 and read_tool_table(table).get(1).diameter == 2.0
    with pytest.raises(GCodeError, match="P and R only"):
        run("G10 L1 P1 R4 Z1\nM2\n", table, dialect="gcode-canon")


def test_errors(table: Path) -> None:
    with pytest.raises(GCodeError, match="tool 7 is not in the tool table") as info:
        run("G0 X1\nG10 L1 P7 Z1\nM2\n", table)
    assert info.value.line == 2 and info.value.file == "g10.ngc"
    with pytest.raises(GCodeError, match="needs a P word"):
        run("G10 L1 Z1\nM2\n", table)
    # no table file: an in-memory table, every tool exists
    interp = run("G10 L1 P7 Z1\nT7 M6\nG43\nG0 Z0\nM2\n", None)
    assert interp.position.z == 1.0
