"""LinuxCNC parity: the differences measured against LinuxCNC's own interpreter (rs274), each with the
value LinuxCNC gives (worked out from its source: interp_*.cc, emccanon.cc, and its documentation)."""

from __future__ import annotations

import math

import pytest

from tests.test_interp_helpers import last_end, run, xyz

# --- G53, G28, G30 with a tool length offset (find_ends, find_relative, convert_savehome) ------------


def test_g53_goes_to_machine_position_whatever_the_tool_offset() -> None:
    # find_ends: z = Z - origin - axis - tool in program terms; emccanon adds all back: machine Z0
    assert last_end("G43.1 Z5\nG53 G0 Z0") == xyz(0, 0, 0)
    assert last_end("G10 L2 P1 Z7\nG43.1 Z5\nG0 Z1\nG53 G1 Z-2 F100") == xyz(0, 0, -2)
    # then the program coordinate reads machine - G5x - tool
    out = run("G43.1 Z5\nG53 G0 Z0\nG0 X1")
    assert tuple(out[-1].end)[:3] == (1.0, 0.0, 0.0)


def test_g28_g30_go_to_the_stored_machine_position_without_the_tool_offset() -> None:
    assert last_end("#5163 = 10\nG43.1 Z5\nG28") == xyz(0, 0, 10)
    assert last_end("#5183 = -3\nG43.1 Z5\nG30 Z0") == xyz(0, 0, -3)


def test_g28_1_stores_the_machine_position_tool_offset_included() -> None:
    # convert_savehome: current + tool + origin + axis offsets (program Z1 + tool 5 = machine 6)
    from gcode_canon.interpreter import Interpreter
    from gcode_canon.settings import InterpreterSettings

    interp = Interpreter(InterpreterSettings(dry_run=True, require_program_end=False))
    list(interp.run_string("G43.1 Z5\nG0 Z1\nG28.1\nG30.1", "t.ngc"))
    assert interp.parameter(5163) == pytest.approx(6.0)
    assert interp.parameter(5183) == pytest.approx(6.0)
    assert last_end("G43.1 Z5\nG0 Z1\nG28.1\nG49\nG0 Z0\nG28") == xyz(0, 0, 6)


# --- M6 stops the spindle (convert_tool_change, TOOL_CHANGE_WITH_SPINDLE_ON = 0) ------------------------


def test_m6_stops_the_spindle_before_the_change() -> None:
    from gcode_canon.commands import SpindleOff, ToolChange

    out = run("S1000 M3\nT1 M6")
    kinds = [type(c) for c in out]
    assert kinds.index(SpindleOff) < kinds.index(ToolChange)
    # the tap cycle then finds the spindle stopped, as LinuxCNC does
    from tests.test_interp_helpers import error

    assert "Spindle not turning" in error("S1000 M3\nT1 M6\nG0 Z5\nG84 Z-1 R2 F100").message
    # M6 M3 on one line: the tool change runs first, the spindle starts after it
    out = run("S1000 M3\nT1 M6 M3")
    kinds = [type(c).__name__ for c in out]
    assert kinds[-3:] == ["SpindleOff", "ToolChange", "SpindleOn"]


def test_m6_keeps_the_spindle_when_the_machine_allows_it() -> None:
    from gcode_canon.commands import SpindleOff

    out = run("S1000 M3\nT1 M6", tool_change_with_spindle_on=True)
    assert not any(isinstance(c, SpindleOff) for c in out)


# --- G40, M6, then a move: the position is read back after a tool change (refresh_actual_position) -----


@pytest.mark.parametrize("change", ["T2 M6", "M61 Q2"])
def test_tool_change_after_g40_keeps_the_compensated_position(change: str) -> None:
    # G41 radius 1 along +X: the tool runs at Y1. G40 leaves it there; LinuxCNC's M6/M61 read the
    # position back, so a Z-only move keeps Y1 (without the change it would go back to Y0).
    prog = f"G10 L1 P1 R1\nT1 M6\nF100\nG41\nG1 X10 Y0\nX20\nG40\n{change}\nG0 Z5\n"
    assert last_end(prog) == xyz(20, 1, 5)
    assert last_end("G10 L1 P1 R1\nT1 M6\nF100\nG41\nG1 X10 Y0\nX20\nG40\nG0 Z5\n") == xyz(20, 0, 5)


# --- M73: the state saved in a subroutine comes back at its return (leave_context, restore_settings) ---


def _table(tmp_path) -> str:
    path = tmp_path / "tools.tbl"
    path.write_text("T1 P1 Z10 D6\nT2 P2 Z20 D2\n")
    return str(path)


def test_m73_restores_distance_units_system_and_tool_length_at_return(tmp_path) -> None:
    prog = ("G10 L2 P2 X100\nT1 M6\nG43\nF100\n"
            "o<s> sub\nM73\nG49\nG91 G20 G55 G18 F7\nG0 X1\no<s> endsub\n"
            "o<s> call\nG1 X2 Y3 Z1\n")
    out = run(prog, tool_table=_table(tmp_path))
    moves = [c for c in out if c.MOVES]
    # in the sub: G91 G20 X1 from machine X0 in G55 (X offset 100), tool offset off: machine Z0
    assert tuple(moves[0].end)[:3] == pytest.approx((25.4, 0.0, 0.0))
    # after the return: G90 G21 G54 and G43 (tool 1, Z 10) again, feed back to 100 mm/min
    assert tuple(moves[1].end)[:3] == pytest.approx((2.0, 3.0, 11.0))
    from gcode_canon.commands import SelectPlane, SetFeedRate

    assert [c.rate for c in out if isinstance(c, SetFeedRate)][-1] == pytest.approx(100.0)
    assert out[-2].__class__ is not SelectPlane or out[-2].plane.gcode == "G17"


def test_m73_restores_feed_to_one_decimal_as_linuxcnc_writes_it() -> None:
    from gcode_canon.commands import SetFeedRate

    out = run("F33.37\no<s> sub\nM73\nF5\no<s> endsub\no<s> call\n")
    assert [c.rate for c in out if isinstance(c, SetFeedRate)][-1] == pytest.approx(33.4)


def test_m73_in_the_main_program_restores_nothing_and_levels_are_separate() -> None:
    assert last_end("M73\nG91\nG0 X1\nG0 X1\n") == xyz(2)
    # M70 in the main program, M72 inside a sub: that level has nothing saved (LinuxCNC refuses)
    from tests.test_interp_helpers import error

    assert "no saved modal state" in error("M70\no<s> sub\nM72\no<s> endsub\no<s> call\n").message
    # M70 then a sub with its own M73: the main program's M72 still gets its own state
    assert last_end("M70\no<s> sub\nM73\nG20\no<s> endsub\no<s> call\nG91\nM72\nG0 X1\nG0 X1\n") == xyz(1)


# --- comparisons: LinuxCNC's tolerance on EQ/NE (0.0001) and GE/LE (1e-6) (interp_execute.cc) ---


def _value(expr: str, dialect: str = "linuxcnc") -> float:
    from gcode_canon.interpreter import Interpreter
    from gcode_canon.settings import InterpreterSettings

    interp = Interpreter(InterpreterSettings(dry_run=True, require_program_end=False, dialect=dialect))
    list(interp.run_string(f"#1 = {expr}\n", "t.ngc"))
    return interp.parameter(1)


@pytest.mark.parametrize(("expr", "linuxcnc", "gcode_canon"), [
    ("[0.99999 LT 1]", 1.0, 0.0),
    ("[1.00001 GT 1]", 1.0, 0.0),
    ("[0.99999 GE 1]", 0.0, 1.0),
    ("[1.00001 LE 1]", 0.0, 1.0),
    ("[1 LE 1]", 1.0, 1.0),
    ("[1 GE 1]", 1.0, 1.0),
    ("[0.9999999 GE 1]", 1.0, 1.0),  # LinuxCNC's GE and LE take its own 1e-6 (nc_files/threading.ngc)
    ("[1.0000001 LE 1]", 1.0, 1.0),
    ("[0.9999999 GT 1]", 0.0, 0.0),
    ("[0.99999 EQ 1]", 1.0, 1.0),
    ("[0.99999 NE 1]", 0.0, 0.0),
    ("[0.9998 EQ 1]", 0.0, 0.0),
])
def test_comparison_tolerance_by_dialect(expr: str, linuxcnc: float, gcode_canon: float) -> None:
    assert _value(expr) == linuxcnc
    assert _value(expr, "gcode-canon") == gcode_canon


# --- G43.1 keeps the axes it does not name; G43.2 adds (convert_tool_length_offset) -------------------


def test_g43_1_keeps_unnamed_axes_and_g43_2_adds() -> None:
    assert last_end("G43.1 Z5\nG43.1 X1\nG0 X0 Z0") == xyz(1, 0, 5)
    assert last_end("G43.1 Z5\nG43.2 Z2\nG0 Z0") == xyz(0, 0, 7)
    from tests.test_interp_helpers import error

    assert "H and axis words" in error("G43.2 H1 Z1").message
    assert "No axes specified" in error("G43.2").message


# --- G52: LinuxCNC's local offset, in the G92 registers (convert_axis_offsets) --------------------------


def test_g52_sets_the_offset_itself_and_shares_the_g92_registers() -> None:
    from gcode_canon.interpreter import Interpreter
    from gcode_canon.settings import InterpreterSettings

    assert last_end("G52 X2 Y3\nG0 X0 Y0") == xyz(2, 3)
    # G92 X1 at X10 makes the offset 9; G52 X2 replaces it (Y keeps its G92 value 0)
    assert last_end("G0 X10\nG92 X1\nG52 X2\nG0 X0") == xyz(2)
    # G92.2 suspends, G92.3 restores, G92.1 clears it as any G92 offset
    assert last_end("G52 X2\nG92.2\nG0 X0") == xyz(0)
    assert last_end("G52 X2\nG92.2\nG92.3\nG0 X0") == xyz(2)
    interp = Interpreter(InterpreterSettings(dry_run=True, require_program_end=False))
    list(interp.run_string("G20\nG52 X2 Y3\n", "t.ngc"))
    assert interp.parameter(5210) == 1.0
    assert interp.parameter(5211) == pytest.approx(50.8)  # user units: the machine's mm
    list(interp.run_string("G52 X0 Y0\n", "t.ngc"))
    assert interp.parameter(5210) == 1.0 and interp.parameter(5211) == 0.0  # "leave param 5210 set"


def test_5220_reads_1_before_any_g54_to_g59_3() -> None:
    # LinuxCNC's required parameter 5220 defaults to 1.0 (G54 active), with or without a .var file
    assert _value("#5220") == 1.0


# --- polar coordinates @ ^ (enhance_block, find_ends, CYCLE_MACRO) -------------------------------------


def test_polar_words_only_in_g17() -> None:
    from tests.test_interp_helpers import error

    assert "except in G17" in error("G18\nG0 @1 ^2").message
    assert "except in G17" in error("G19\nG1 ^2 F100").message
    assert "angle" in error("G0 @5").message  # at the origin, @ alone has no direction


def test_incremental_angle_steps_a_hole_circle() -> None:
    # LinuxCNC's nc_files/hole-circle.ngc: six holes 60 degrees apart on a 1.5 radius (inches here mm)
    out = run("G17 G90\nG0 X1.5 Y0 Z0\nG91 G81 R.1 Z-.5 ^60 L6 F10\n")
    feeds = [c.end for c in out if type(c).__name__ == "StraightFeed"]
    assert len(feeds) == 6
    for k, end in enumerate(feeds, start=1):
        a = math.radians(60 * k)
        assert (end.x, end.y, end.z) == pytest.approx((1.5 * math.cos(a), 1.5 * math.sin(a), -0.4), abs=1e-9)
    # absolute: the missing one of @ ^ comes from the current point
    out = run("G0 X3 Y4 Z5\nG81 ^90 Z-1 R1 F10\n")
    assert next(c.end for c in out if type(c).__name__ == "StraightFeed")[:3] == pytest.approx((0, 5, -1))


# --- arcs (convert_arc) ------------------------------------------------------------------------------


def test_bare_g2_is_refused_and_wrong_plane_offsets_too() -> None:
    from tests.test_interp_helpers import error

    assert "missing for arc" in error("F100\nG2").message
    assert "missing for arc" in error("F100\nG2 X2 I1\nG3").message
    assert len(run("F100\nG2 X1 Y1 I1\nF200")) >= 2  # G2 modal, no words: nothing moves, no error
    assert "J word given for arc" in error("G18 F100\nG2 X1 Z1 J1 I1").message
    assert "I word given for arc" in error("G19 F100\nG2 Y1 Z1 I1 K1").message


# --- o-words (interp_o_word.cc: control_back_to, convert_control_functions) ---------------------------


def test_sub_defined_after_its_call_is_found_in_the_main_file() -> None:
    prog = "o100 call [2]\nG0 Y1\nM2\no100 sub\nG0 X#1\no100 endsub\n"
    assert [tuple(e)[:2] for e in [c.end for c in run(prog) if c.MOVES]] == [(2.0, 0.0), (2.0, 1.0)]
    # after the main program's M2, named too, and every later call finds it again
    prog = "o<a> call\no<a> call\nM2\no<a> sub\nG91 G0 X1\no<a> endsub\n"
    assert last_end(prog) == xyz(2)
    from tests.test_interp_helpers import error

    # nothing after a closing percent is read (LinuxCNC: "Failed to find sub ... before EOF")
    assert "o2 call" in error("%\no2 call\n%\no2 sub\nG0 X1\no2 endsub\n").message


def test_nested_sub_definition_refused_return_any_label_comment_between_arguments() -> None:
    from tests.test_interp_helpers import error

    nested = "o<n> sub\no100 sub\no100 endsub\no<n> endsub\no<n> call\nM2\n"
    assert "Nested subroutine definition" in error(nested).message
    # return leaves the running sub whatever its label (LinuxCNC's return-value test)
    assert last_end("o1000 sub\nG0 X1\no1010 return\nG0 X9\no1000 endsub\no1000 call\n") == xyz(1)
    # a comment between call arguments (LinuxCNC's flowsnake)
    assert last_end("o<s> sub\nG0 X#1 Y#2\no<s> endsub\no<s> call [1] (first) [2]\n") == xyz(1, 2)


def test_g64_r_selects_the_planner_as_linuxcnc_master() -> None:
    from gcode_canon.commands import SetMotionControlMode
    from tests.test_interp_helpers import error

    modes = [c for c in run("G64 P1 R0.5\nG64 P1 R0\nG64 P1 R2.5\nG64 P1 R0.05\n")
             if isinstance(c, SetMotionControlMode)]
    assert [(m.planner, m.peak_scale) for m in modes] == [(1, 0.5), (0, -1.0), (1, 1.0), (1, 0.1)]
    assert modes[0].tolerance == 1.0
    assert "R word with no" in error("G61 R0.5").message


# --- probing (convert_probe, set_probe_data) ---------------------------------------------------------


def test_probe_zero_length_only_refused_when_contact_is_required_and_g95_refused() -> None:
    from tests.test_interp_helpers import error

    assert "zero length" in error("G38.4 Z0 F10").message
    assert len([c for c in run("G38.3 Z0 F10\nG38.5 Z0\n") if c.MOVES]) == 2
    assert "feed per rev" in error("G95 F1\nG38.2 Z-1").message


def test_after_a_probe_the_next_move_starts_where_the_machine_stopped(tmp_path) -> None:
    from gcode_canon.commands import Pose
    from gcode_canon.interpreter import Interpreter
    from gcode_canon.machine import DryRunMachine
    from gcode_canon.settings import InterpreterSettings

    class Overshoot(DryRunMachine):
        def probe(self, cmd):
            return Pose(0, 0, -3), True  # tripped at Z-3

        def current_position(self):
            return Pose(0, 0, -3.2)  # stopped 0.2 past it

    interp = Interpreter(InterpreterSettings(dry_run=True, require_program_end=False), Overshoot())
    out = list(interp.run_string("G38.2 Z-10 F100\nG91 G1 X1\n", "t.ngc"))
    assert interp.parameter(5063) == pytest.approx(-3.0)  # the trip point
    assert tuple(out[-1].end)[:3] == pytest.approx((1.0, 0.0, -3.2))  # from where it stopped


def test_canned_cycles_start_in_g99_as_linuxcnc() -> None:
    # interp_setup.cc: retract_mode(RETRACT_MODE::R_PLANE): with no G98/G99 the hole ends at R
    assert last_end("F10\nG0 Z10\nG81 X1 Z-1 R2") == xyz(1, 0, 2)
    assert last_end("F10\nG0 Z10\nG98 G81 X1 Z-1 R2") == xyz(1, 0, 10)


def test_g28_with_x_in_a_rotated_system_moves_the_program_x_as_linuxcnc() -> None:
    # find_relative: the stored (machine) position seen in the rotated program frame; only its X is
    # taken, so machine Y moves too. Rotation 90: program X is machine Y.
    end = last_end("#5161=10 #5162=20\nG10 L2 P1 R90\nG0 X0 Y0\nG28 X0")
    assert end[:2] == pytest.approx((0.0, 20.0))


def test_a_step_added_by_a_module_runs_on_every_line_and_built_in_steps_by_their_codes() -> None:
    from gcode_canon.interpreter import Interpreter
    from gcode_canon.settings import InterpreterSettings

    interp = Interpreter(InterpreterSettings(dry_run=True, require_program_end=False))
    seen: list[int] = []
    interp.steps.insert(0, lambda block, ml: seen.append(interp.line))
    out = list(interp.run_string("G0 X1\n#1=2\nG1 X[#1] F100\nS100 M3\nG4 P1\n", "t.ngc"))
    assert seen == [2, 3, 4, 5]  # line 1 takes the fast path (no steps at all)
    kinds = [type(c).__name__ for c in out]
    assert kinds == ["StraightTraverse", "SetFeedRate", "StraightFeed", "SetSpindleSpeed", "SpindleOn",
                     "Dwell"]
    interp.steps.pop(0)
    list(interp.run_string("G0 X2\nG1 X3\n", "t.ngc"))
    assert seen == [2, 3, 4, 5]


def test_g10_l10_with_x_in_a_rotated_system(tmp_path) -> None:
    # convert_setup_tool: rotation 90, machine at 0,0: "X reads 1 here" gives tool offset X0 Y-1, so
    # after G43 the program point X1 Y0 is machine 0,0 again
    from gcode_canon.interpreter import Interpreter
    from gcode_canon.settings import InterpreterSettings

    table = tmp_path / "t.tbl"
    table.write_text("T1 P1 Z0 D6\n")
    interp = Interpreter(InterpreterSettings(dry_run=True, require_program_end=False, tool_table=table))
    out = list(interp.run_string("G10 L2 P1 R90\nT1 M6\nG0 X0 Y0\nG10 L10 P1 X1\nG43\nG0 X1 Y0\n", "t.ngc"))
    assert interp.tool_table.get(1).offset[:2] == pytest.approx((0.0, -1.0))
    assert tuple(out[-1].end)[:2] == pytest.approx((0.0, 0.0))


def test_disable_g92_persistence_clears_at_start_and_program_end(tmp_path) -> None:
    from gcode_canon.interpreter import Interpreter
    from gcode_canon.settings import InterpreterSettings

    var = tmp_path / "m.var"
    var.write_text("5210 1.0\n5211 5.0\n")
    kept = Interpreter(InterpreterSettings(dry_run=True, var_file=var))
    assert kept.parameter(5211) == 5.0
    interp = Interpreter(InterpreterSettings(dry_run=True, var_file=var, disable_g92_persistence=True))
    assert interp.parameter(5210) == 0.0 and interp.parameter(5211) == 0.0
    list(interp.run_string("G92 X-3\nM2\n", "t.ngc"))
    assert interp.parameter(5210) == 0.0 and interp.parameter(5211) == 0.0
    out = list(interp.run_string("G0 X1\nM2\n", "t.ngc"))
    assert out[0].end.x == pytest.approx(1.0)


# --- G7/G8 lathe diameter mode (read_x, convert_lathe_diameter_mode) -----------------------------------


def test_g7_makes_x_words_diameters() -> None:
    from gcode_canon.commands import ArcFeed
    from gcode_canon.interpreter import Interpreter
    from gcode_canon.settings import InterpreterSettings
    from tests.test_interp_helpers import ends

    program = ("G21 G18 G90 G94 F100\nG0 X10 Z5\nG7\nG1 X10 Z0\nG91 X-2\nG90 G8 X6\nG7 X4 Z-1\n"
               "G2 X8 Z-3 I1 K-1\nG3 X8 Z-5 R1.5\nG92 X20\nG0 X10\nG8\nG0 X5\n")
    # rs274 (LinuxCNC master), machine X and Z of each move; X is halved from the G7 line on, G8 on
    # its own line counts for its X word, G92 X20 is a diameter too (program X10 -> offset -6)
    got = [(round(e[0], 4), round(e[2], 4)) for e in ends(program)]
    assert got == [(10, 5), (5, 0), (4, 0), (6, 0), (2, -1), (4, -3), (4, -5), (-1, -5), (-1, -5)]
    interp = Interpreter(InterpreterSettings(dry_run=True, require_program_end=False))
    arcs = [c for c in interp.run_string(program[:program.index("G92")], "t.ngc") if isinstance(c, ArcFeed)]
    # I and K stay radii: rs274's ARC_FEED centres, Z then X: (-2, 3) and (-4, 2.882)
    assert [(round(a.center[2], 4), round(a.center[0], 4)) for a in arcs] == [(-2, 3), (-4, 2.882)]
    assert interp.active_gcodes(extensions=False)[-1] == "G7"
    # rs274's (PRINT) of #<_lathe_diameter_mode> #<_lathe_radius_mode> #<_x>: 1 0 5
    assert (interp.parameter("_lathe_diameter_mode"), interp.parameter("_lathe_radius_mode")) == (1.0, 0.0)
    assert interp.parameter("_x") == pytest.approx(4.0)  # machine X 4 is program X 4 (a radius)
    list(interp.run_string("G8\n", "t.ngc"))
    assert interp.active_gcodes(extensions=False)[-1] == "G8"
    assert (interp.parameter("_lathe_diameter_mode"), interp.parameter("_lathe_radius_mode")) == (0.0, 1.0)


def test_g7_lines_do_not_take_the_fast_path() -> None:
    from tests.test_interp_helpers import ends

    # plain G1 X lines after G7 must be halved as every other line is
    assert [round(e[0], 4) for e in ends("G7\nG0 X8\nG1 X6 F100\nX4\nG8\nX4")] == [4, 3, 2, 4]
