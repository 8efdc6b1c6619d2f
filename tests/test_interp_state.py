"""Interpreter state seen from outside and from programs: the active G-code list with the gcode-canon
transform groups, the machine-position parameters (#5021-#5029, #<_abs_x> ...), EXISTS on numbered
parameters, the numbered-parameter range, and the predefined parameters checked against LinuxCNC.

Expected values are LinuxCNC's behaviour (its ``rs274ngc`` source, master 2026) worked out by hand for
each program; see the comments.
"""

from __future__ import annotations

import functools

import pytest
from test_interp_helpers import error, run

from gcode_canon import dialect
from gcode_canon.errors import GCodeError
from gcode_canon.interpreter import Interpreter
from gcode_canon.settings import InterpreterSettings

LINUXCNC_GROUPS = 13
"""Entries of ``active_gcodes()`` for LinuxCNC's own modal groups (motion ... lathe diameter mode)."""


def interp(**settings: object) -> Interpreter:
    options: dict = {"dry_run": True, "require_program_end": False, **settings}
    return Interpreter(InterpreterSettings(**options))


def after(program: str, **settings: object) -> Interpreter:
    i = interp(**settings)
    run(program, i)
    return i


def value(expr: str, before: str = "", **settings: object) -> float:
    """The value of ``expr`` read by a program after ``before`` ran (stored in #4000)."""
    i = after(f"{before}\n#4000 = [{expr}]\n", **settings)
    return i.params.get_numbered(4000)


# --- active_gcodes(): the transform groups -----------------------------------------------------------


def test_fresh_interpreter_lists_every_transform_group_off_after_linuxcncs_groups() -> None:
    i = interp()
    codes = i.active_gcodes()
    assert codes[:LINUXCNC_GROUPS] == i.active_gcodes(extensions=False)
    assert len(i.active_gcodes(extensions=False)) == LINUXCNC_GROUPS
    # polar, scaling, rotation, mirroring: the modal.py group order 16, 17, 18, 19
    assert codes[LINUXCNC_GROUPS:] == ("G15", "G50", "G69", "G23")


def test_transform_groups_follow_the_program() -> None:
    i = after("G16\nG51 X0 Y0 P2\nG68 X0 Y0 R30\nG22 X5\n")
    assert i.active_gcodes()[LINUXCNC_GROUPS:] == ("G16", "G51", "G68", "G22")
    run("G15\nG50\n", i)
    assert i.active_gcodes()[LINUXCNC_GROUPS:] == ("G15", "G50", "G68", "G22")
    run("G69\nG23\n", i)
    assert i.active_gcodes()[LINUXCNC_GROUPS:] == ("G15", "G50", "G69", "G23")


def test_the_linuxcnc_part_keeps_its_positions_with_transforms_on() -> None:
    i = after("G1 F100 X1\nG91\nG16\nG51 X0 Y0 P2\n")
    codes = i.active_gcodes()
    assert codes[0] == "G1" and codes[3] == "G91"
    assert codes[:LINUXCNC_GROUPS] == i.active_gcodes(extensions=False)


def test_programmed_code_is_listed_even_when_it_changes_nothing() -> None:
    # G51 P1 scales by one and G68 R0 rotates by zero: still the codes in force, as on Fanuc
    i = after("G51 X0 Y0 P1\nG68 X0 Y0 R0\n")
    assert i.active_gcodes()[LINUXCNC_GROUPS + 1:LINUXCNC_GROUPS + 3] == ("G51", "G68")


def test_partial_g23_leaves_the_other_mirror_on() -> None:
    i = after("G22 X5 Y5\nG23 X0\n")
    assert i.active_gcodes()[-1] == "G22"  # Y is still mirrored
    run("G23 Y0\n", i)
    assert i.active_gcodes()[-1] == "G23"


def test_program_end_resets_the_transform_groups() -> None:
    i = after("G16\nG51 X0 Y0 P1\nG68 X0 Y0 R0\nG22 X1\nM2\n")
    assert i.active_gcodes()[LINUXCNC_GROUPS:] == ("G15", "G50", "G69", "G23")


def test_a_failed_transform_line_changes_no_listed_code() -> None:
    i = interp()
    with pytest.raises(GCodeError):
        run("G51 X0 Y0 P0\n", i)  # zero scale factor: refused
    assert i.active_gcodes()[LINUXCNC_GROUPS + 1] == "G50"


@pytest.mark.parametrize("name", ["linuxcnc", "gcode-canon", "grbl"])
def test_every_dialect_accepts_the_transforms_so_lists_them(name: str) -> None:
    i = after("G16\nG68 X0 Y0 R10\n", dialect=name)
    assert i.active_gcodes()[LINUXCNC_GROUPS:] == ("G16", "G50", "G68", "G23")


def test_groups_the_dialect_refuses_are_not_listed(monkeypatch: pytest.MonkeyPatch) -> None:
    # strict LinuxCNC meaning (resolve(extensions=False)) refuses all eight codes: nothing is added
    i = after("G16\n")
    monkeypatch.setattr(dialect, "resolve", functools.partial(dialect.resolve, extensions=False))
    assert i.active_gcodes() == i.active_gcodes(extensions=False)


def test_status_message_carries_the_whole_list() -> None:
    # motiond/runtime/status.py copies active_gcodes() into the variable-length canon.status string array
    # (int16 count) and status_view.decode_status reads num_gcodes of them back
    from motiond.status_view import decode_status
    from telemetry.lcmtypes.canon import status

    i = after("G16\nG51 X0 Y0 P2\nG68 X0 Y0 R30\nG22 X5\n")
    s = status()
    g = list(i.active_gcodes())
    s.num_gcodes, s.gcodes = len(g), g
    m = list(i.active_mcodes())
    s.num_mcodes, s.mcodes = len(m), m
    decoded = decode_status(s.encode())
    assert decoded["gcodes"] == g
    assert decoded["gcodes"][-4:] == ["G16", "G51", "G68", "G22"]


# --- #5021-#5029 and #<_abs_x> ... #<_abs_w>: the machine position ---------------------------------


def test_abs_parameters_are_the_machine_position_without_work_offsets() -> None:
    # G54 at X10 Y20 Z30: program X1 Y2 Z3 is machine X11 Y22 Z33
    before = "G10 L2 P1 X10 Y20 Z30\nG0 X1 Y2 Z3"
    assert value("#<_abs_x>", before) == pytest.approx(11)
    assert value("#<_abs_y>", before) == pytest.approx(22)
    assert value("#<_abs_z>", before) == pytest.approx(33)
    assert value("#5021", before) == pytest.approx(11)
    assert value("#5022", before) == pytest.approx(22)
    assert value("#5023", before) == pytest.approx(33)
    assert value("#5420", before) == pytest.approx(1)  # the work position stays what it was


def test_abs_parameters_include_g92_and_the_coordinate_system_rotation() -> None:
    # G92 X0 at program X1 (machine 11): the program frame moves, the machine does not
    assert value("#5021", "G10 L2 P1 X10\nG0 X1\nG92 X0") == pytest.approx(11)
    assert value("#<_x>", "G10 L2 P1 X10\nG0 X1\nG92 X0") == pytest.approx(0)
    # G54 rotated 90 degrees about its origin (machine X10): program X1 Y0 is machine X10 Y1
    before = "G10 L2 P1 X10 R90\nG0 X1 Y0"
    assert value("#5021", before) == pytest.approx(10)
    assert value("#5022", before) == pytest.approx(1)


def test_abs_parameters_include_the_tool_length_offset() -> None:
    # LinuxCNC's get_abs_position adds tool_offset: the controlled point's machine coordinate.
    # G43.1 Z5 then program Z1: machine Z = 1 + 5
    assert value("#<_abs_z>", "G43.1 Z5\nG0 Z1") == pytest.approx(6)
    assert value("#5023", "G43.1 Z5\nG0 Z1") == pytest.approx(6)
    assert value("#<_z>", "G43.1 Z5\nG0 Z1") == pytest.approx(1)


def test_abs_parameters_are_in_program_units_and_rotary_axes_in_degrees() -> None:
    before = "G10 L2 P1 X25.4 A10\nG0 X0 A5\nG20"
    assert value("#5021", before) == pytest.approx(1.0)  # 25.4 mm in G20
    assert value("#<_abs_x>", before) == pytest.approx(1.0)
    assert value("#5024", before) == pytest.approx(15.0)  # degrees are not converted
    assert value("#<_abs_a>", before) == pytest.approx(15.0)


def test_abs_parameters_cover_u_v_w() -> None:
    before = "G10 L2 P1 B1 C2 U1 V2 W3\nG0 B1 C1 U1 V1 W1"
    assert [value(f"#{5025 + k}", before) for k in range(5)] == pytest.approx([2, 3, 2, 3, 4])
    assert [value(f"#<_abs_{a}>", before) for a in "bcuvw"] == pytest.approx([2, 3, 2, 3, 4])


def test_abs_parameters_see_the_canon_transforms() -> None:
    # G51 P2 about X0: program X3 goes to machine X6; #5420 stays the programmed (untransformed) 3
    before = "G51 X0 Y0 P2\nG0 X3"
    assert value("#5021", before) == pytest.approx(6)
    assert value("#5420", before) == pytest.approx(3)


def test_abs_parameters_are_read_only_and_predefined() -> None:
    for target in ("#5021", "#5029", "#<_abs_x>", "#<_abs_w>"):
        assert "read-only" in error(f"{target} = 1").message
    assert value("EXISTS[#<_abs_u>]") == 1


def test_machine_position_parameters_are_not_saved(tmp_path) -> None:
    var = tmp_path / "machine.var"
    i = Interpreter(InterpreterSettings(var_file=var))
    run("G10 L2 P1 X10\nG0 X1\n#4000 = 7\nM2\n", i)
    numbers = {int(line.split()[0]) for line in var.read_text().splitlines() if line.strip()}
    assert 4000 in numbers  # a user parameter set by the program is saved ...
    assert numbers.isdisjoint(range(5021, 5030))  # ... the machine position is not (volatile)


# --- EXISTS on numbered parameters --------------------------------------------------------------------


def test_exists_on_numbered_parameters_tells_whether_the_number_is_in_range() -> None:
    # LinuxCNC read_parameter(check_exists): index >= 1 and index < RS274NGC_MAX_PARAMETERS (5602)
    assert value("EXISTS[#1]") == 1  # never set: still exists (numbered parameters always do)
    assert value("EXISTS[#5601]") == 1
    assert value("EXISTS[#5602]") == 0
    assert value("EXISTS[#0]") == 0
    assert value("EXISTS[#-3]") == 0
    assert value("EXISTS[#[2 + 3]]") == 1


def test_exists_evaluates_the_number_but_not_the_parameter() -> None:
    assert value("EXISTS[##2]", "#2 = 6000") == 0  # the number is #2's value
    assert value("EXISTS[##2]", "#2 = 31") == 1
    # reading #5420 with compensation on is an error, asking whether it exists is not
    assert value("EXISTS[#5420]", "G41.1 D1") == 1


def test_exists_in_a_condition() -> None:
    i = after("#5 = 0\no1 if [EXISTS[#5] AND EXISTS[#<_abs_x>]]\n#6 = 1\no1 else\n#6 = 2\no1 endif\n")
    assert i.params.get_numbered(6) == 1


@pytest.mark.parametrize(
    ("expr", "words"),
    [
        ("EXISTS[#1.5]", "Non integer value for integer"),
        ("EXISTS[#1 + 1]", "Expected ] reading bracketed parameter"),
        ("EXISTS[1]", "EXISTS takes one parameter"),
        ("EXISTS[]", "EXISTS takes one parameter"),
        ("EXISTS[#<a>", "EXISTS takes one parameter"),
    ],
)
def test_exists_errors(expr: str, words: str) -> None:
    err = error(f"#100 = {expr}")
    assert words in err.message
    assert err.line == 1


# --- the numbered-parameter range -----------------------------------------------------------------


def test_highest_numbered_parameter_is_5601() -> None:
    assert value("#5601", "#5601 = 7") == 7


@pytest.mark.parametrize("line", ["#5602 = 1", "#1 = #5602", "#1 = #[5601 + 1]", "#0 = 1"])
def test_numbers_outside_1_to_5601_are_out_of_range(line: str) -> None:
    err = error(line)
    assert err.message.startswith("Parameter number out of range")  # LinuxCNC's text
    assert "(1 to 5601)" in err.message


def test_non_integer_parameter_number_has_linuxcncs_message() -> None:
    assert error("#1 = #2.5").message.startswith("Non integer value for integer")
    assert value("#[2.00005]", "#2 = 4") == 4  # within 0.0001 of an integer: that integer


def test_var_file_with_5602_is_refused_and_5601_is_read(tmp_path) -> None:
    bad = tmp_path / "bad.var"
    bad.write_text("5161 0\n5602 1\n")
    with pytest.raises(GCodeError, match="Parameter number out of range") as info:
        Interpreter(InterpreterSettings(var_file=bad))
    assert info.value.line == 2
    good = tmp_path / "good.var"
    good.write_text("5161 0\n5601 2.5\n")
    assert Interpreter(InterpreterSettings(var_file=good, dry_run=True)).parameter(5601) == 2.5


# --- predefined parameters checked against LinuxCNC -----------------------------------------------


@pytest.mark.parametrize(
    ("before", "expected"),
    [("", 540), ("G55", 550), ("G59", 590), ("G59.1", 591), ("G59.3", 593)],
)
def test_coord_system_is_the_g_code_times_ten(before: str, expected: float) -> None:
    # manual ("550.000000 ... in G55") and lookup_named_param agree: 530 + 10 * index, 584 + index
    assert value("#<_coord_system>", before) == expected


def test_retract_mode_parameters_follow_linuxcncs_code() -> None:
    # lookup_named_param: _retract_r_plane is retract_mode == R_PLANE, set by G99;
    # _retract_old_z is OLD_Z, set by G98 (canon starts in G99, as LinuxCNC's interp_setup.cc)
    assert value("#<_retract_old_z>") == 0 and value("#<_retract_r_plane>") == 1
    assert value("#<_retract_old_z>", "G98") == 1 and value("#<_retract_r_plane>", "G98") == 0
    assert value("#<_retract_r_plane>", "G99") == 1 and value("#<_retract_old_z>", "G99") == 0
    assert value("#<_retract_old_z>", "G99\nG98") == 1


def test_tool_offset_is_on_when_an_offset_is_applied() -> None:
    # lookup_named_param: 1 when any component of the applied tool offset is non-zero
    assert value("#<_tool_offset>") == 0
    assert value("#<_tool_offset>", "G43.1 Z2") == 1
    assert value("#<_tool_offset>", "G43.1 Z0") == 0
    assert value("#<_tool_offset>", "G43.1 Z2\nG49") == 0


def test_metric_machine() -> None:
    # canon keeps lengths in mm: a metric machine whatever G20/G21 say
    assert value("#<_metric_machine>") == 1
    assert value("#<_metric_machine>", "G20") == 1


def test_current_position_numbered_parameters_refused_with_compensation_on() -> None:
    # LinuxCNC read_parameter refuses #5420-#5428 (only those) while cutter compensation is on
    err = error("G41.1 D1\n#1 = #5421")
    assert err.message == "Cannot read current position with cutter radius compensation on"
    assert err.line == 2
    # the named aliases and the machine position are not checked there
    assert value("#<_y>", "G0 Y2\nG41.1 D1") == pytest.approx(2)
    assert value("#5022", "G0 Y2\nG41.1 D1") == pytest.approx(2)
    assert value("#5421", "G0 Y2\nG41.1 D1\nG40") == pytest.approx(2)
