"""``#<_ini[section]name>`` reads the machine file's numbers (LinuxCNC's INI variables), read-only;
``(ABORT, text)`` stops the program with the expanded text (both as LinuxCNC's tests/interp
iniparam, iniparam-failassign and abort-hot-comment, which the differential test runs)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from gcode_canon.commands import StraightTraverse
from gcode_canon.errors import GCodeError
from gcode_canon.interpreter import Interpreter
from gcode_canon.settings import InterpreterSettings
from motiond.interp_settings import ini_values

ROOT = Path(__file__).resolve().parent.parent


def run(text: str, values: dict[str, float]) -> list:
    interp = Interpreter(InterpreterSettings(dry_run=True, require_program_end=False, ini_values=values))
    return list(interp.run_string(text, "t.ngc"))


def test_machine_file_numbers_become_ini_values() -> None:
    data = {"machine": {"name": "mill", "cycle_ms": 2.0},
            "axes": {"x": {"max_velocity": 200, "Max_Position": 300.5}},
            "canopen": {"simulate": True, "cpu_affinity": [1], "axes": {"z": {"node_id": 3}}}}
    assert ini_values(data) == {"machine]cycle_ms": 2.0, "axes.x]max_velocity": 200.0,
                                "axes.x]max_position": 300.5, "canopen]simulate": 1.0,
                                "canopen.axes.z]node_id": 3.0}


def test_ini_values_are_read_any_case_and_are_read_only() -> None:
    values = {"vars]toolchange_x": 10.0, "vars]toolchange_z": 30.0}
    out = run("G53 G0 X#<_ini[vars]toolchange_x> Z#<_InI[VARS]ToolChange_Z>\n", values)
    move = next(c for c in out if isinstance(c, StraightTraverse))
    assert (move.end.x, move.end.z) == (10.0, 30.0)
    with pytest.raises(GCodeError, match=r"Named parameter #<_ini\[vars\]nosuch> not defined") as info:
        run("G0 X1\n#1 = #<_ini[vars]nosuch>\n", values)
    assert info.value.line == 2
    with pytest.raises(GCodeError, match=r"Cannot assign to read-only parameter #<_ini\[vars\]toolchange_x>"):
        run("#<_ini[vars]toolchange_x> = 3\n", values)


def test_abort_comment_stops_with_its_expanded_text() -> None:
    with pytest.raises(GCodeError) as info:
        run("#1 = 20\nG0 X1\n(abort, stopped at #1 with #<_ini[a]value>)\nG0 X2\n", {"a]value": 3.14})
    assert info.value.line == 3 and info.value.message == "stopped at 20.000000 with 3.140000"


def test_canon_check_reads_the_machine_file(tmp_path: Path) -> None:
    prog = tmp_path / "p.ngc"
    prog.write_text("%\nG53 G0 Z#<_ini[axes.z]max_position> X[#<_ini[axes.x]max_position> - 1]\nM2\n%\n")
    r = subprocess.run([sys.executable, "-m", "motiond.cli", "check", "--json", "--config",
                        "examples/canon.toml", str(prog)],
                       capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    move = json.loads(r.stdout.splitlines()[0])  # one command per line
    assert move["command"] == "STRAIGHT_TRAVERSE" and (move["x"], move["z"]) == (299.0, 50.0)


@pytest.mark.parametrize(("program", "found"), [
    ("G0 X1\nM98 P1\nM30\nO1\nG0 X2\nM99\n", "M98"),
    ("O1\nG0 X2\nM99\n", "bare O-word O1"),
])
def test_disable_fanuc_style_sub(program: str, found: str) -> None:
    """[interpreter] disable_fanuc_style_sub (LinuxCNC's DISABLE_FANUC_STYLE_SUB): numbered programs
    are refused at the line that uses them; o-word subroutines still work."""
    settings = InterpreterSettings(dry_run=True, require_program_end=False)
    list(Interpreter(settings).run_string(program, "t.ngc"))  # allowed by default
    settings.disable_fanuc_style_sub = True
    with pytest.raises(GCodeError, match=f"DISABLE_FANUC_STYLE_SUB is set, but found {found}") as info:
        list(Interpreter(settings).run_string(program, "t.ngc"))
    assert info.value.line == (2 if found == "M98" else 1)
    ok = "o100 sub\nG0 X3\no100 endsub\no100 call\nM2\n"
    assert any(isinstance(c, StraightTraverse) for c in Interpreter(settings).run_string(ok, "t.ngc"))


def test_disable_fanuc_style_sub_from_the_machine_file(tmp_path: Path) -> None:
    from motiond.config import load_machine
    from motiond.interp_settings import build_settings

    text = (ROOT / "examples" / "canon.toml").read_text()
    path = tmp_path / "m.toml"
    path.write_text(text.replace("[interpreter]", "[interpreter]\ndisable_fanuc_style_sub = true", 1))
    assert build_settings(load_machine(str(path)), dry_run=True).disable_fanuc_style_sub
