"""Modal groups, word checks, order of execution, active codes, unsupported codes."""

from __future__ import annotations

import pytest
from test_interp_helpers import error, run

from gcode_canon.commands import (
    ArcFeed,
)
from gcode_canon.interpreter import Interpreter
from gcode_canon.settings import InterpreterSettings


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("G0 G1 X1", "Two G codes used from the same modal group"),
        ("G20 G21", "same modal group"),
        ("G90 G91", "same modal group"),
        ("G54 G55", "same modal group"),
        ("M3 M4", "Two M codes used from the same modal group"),
        ("M0 M2", "same modal group"),
        ("M62 M65 P2", "same modal group"),
        ("M7 M9", "same modal group"),
        ("M7 M3 M48 M62 P1 M0", "Too many M codes"),
        ("X1", "without a G code that uses them"),
        ("G80 X1", "with G80"),
        ("G1 G92 X1", "two G codes that both use axis values"),
        ("G0 G28 X1", "two G codes that both use axis values"),
        ("G1 X1 I1 F1", "I word with no G2 or G3"),
        ("G0 K1", "K word with no G2 or G3"),
        ("G0 X1 R1", "R word"),
        ("G0 X1 P1", "P word"),
        ("G0 X1 Q1", "Q word"),
        ("G0 X1 L1", "L word"),
        ("G0 X1 E1", "E word"),
        ("G0 H1", "H word"),
        ("G0 D1", "D word"),
        ("G10 P1 X1", "L word"),
        ("G12", "Cannot do G12 with zero feed rate"),
        ("G41 D-1", "G41 D-1: negative tool number"),
        ("G81 X1 Z-1 R1", "Cannot feed with zero feed rate"),
        ("G17.1", "not supported"),
        ("G6.1", "Unknown G code"),
        ("G100", "out of range"),
        ("G1.23", "Unknown G code"),
        ("M1.5", "Unknown M code"),
        ("M200", "out of range"),
        ("M100", "user-defined"),
        ("M47", "Unknown M code"),
        ("o100 sub", "no matching o100 endsub"),
        ("G53 G91 G0 X1", "G53 incremental"),
        ("G53 G2 X1 I1 F1", "G0 or G1 with G53"),
        ("G1 X1", "zero feed rate"),
        ("G93 G1 X1", "F word missing with inverse time"),
        ("F-1", "Negative F"),
        ("S-1", "Negative spindle speed"),
        ("G4", "P word missing"),
        ("G92", "All axes missing"),
    ],
)
def test_line_errors(text: str, words: str) -> None:
    err = error(text)
    assert words in err.message, err.message
    assert err.line == 1


def test_group0_axis_user_suspends_the_motion_mode() -> None:
    out = run("G1 X1 F100\nG92 X0\nX2")
    assert [type(c).__name__ for c in out] == ["SetFeedRate", "StraightFeed", "SetG92Offset", "StraightFeed"]
    assert out[-1].end.x == 3


def test_motion_mode_is_modal_and_g80_cancels() -> None:
    out = run("G1 F100 X1\nY1\nG80\nG0 X0")
    assert [type(c).__name__ for c in out][-3:] == ["StraightFeed", "StraightFeed", "StraightTraverse"]
    assert "with G80" in error("G80\nG80 X1").message
    assert "without a G code" in error("G80\nX1").message


def test_order_of_execution_within_a_line() -> None:
    # Written in reverse of the execution order on purpose.
    out = run("G1 X1 G21 G18 G4 P1 M8 M3 T2 S100 F10 (hi)")
    names = [c.NAME for c in out]
    assert names == [
        "COMMENT", "SET_FEED_RATE", "SET_SPINDLE_SPEED", "SELECT_TOOL", "START_SPINDLE", "COOLANT",
        "DWELL", "SELECT_PLANE", "STRAIGHT_FEED",
    ]


def test_units_apply_to_the_line_they_are_on() -> None:
    out = run("G20 G0 X1 F1")
    assert out[0].NAME == "SET_FEED_RATE" and out[0].rate == pytest.approx(25.4)
    assert out[-1].end.x == pytest.approx(25.4)


def test_active_codes() -> None:
    interp = Interpreter(InterpreterSettings(require_program_end=False))
    assert interp.active_gcodes()[:6] == ("G80", "G17", "G21", "G90", "G91.1", "G94")
    run("G1 F5 X1 G20 G91 G18 G55 G61 M3 S10 M7\nM8", interp)
    g = interp.active_gcodes()
    assert {"G1", "G18", "G20", "G91", "G55", "G61"} <= set(g)
    assert interp.active_mcodes() == ("M3", "M7", "M8", "M48")


def test_mist_and_flood_both_on_but_set_on_two_lines() -> None:
    out = run("M7\nM8")
    assert [(c.mist, c.flood) for c in out] == [(True, False), (True, True)]
    assert "same modal group" in error("M7 M8").message
    assert "same modal group" in error("M3 M70").message  # LinuxCNC's group 7


def test_path_control_and_feed_modes() -> None:
    out = run("G64 P0.1 Q0.05\nG61\nG61.1\nG64\nG93\nG95\nG94")
    names = [(c.NAME, getattr(c, "mode", None)) for c in out]
    assert names[0][0] == "SET_MOTION_CONTROL_MODE" and out[0].tolerance == pytest.approx(0.1)
    assert out[0].naive_cam_tolerance == pytest.approx(0.05)
    assert [c.mode.name for c in out if c.NAME == "SET_MOTION_CONTROL_MODE"] == [
        "CONTINUOUS", "EXACT_PATH", "EXACT_STOP_MODAL", "CONTINUOUS"]
    assert [c.mode.name for c in out if c.NAME == "SET_FEED_MODE"] == [
        "INVERSE_TIME", "UNITS_PER_REV", "UNITS_PER_MINUTE"]
    assert "P word" in error("G64 Q1").message


def test_inverse_time_needs_f_on_every_move() -> None:
    out = run("G93 G1 X1 F2\nG1 X2 F4")
    rates = [c.rate for c in out if c.NAME == "SET_FEED_RATE"]
    assert rates == [2, 4]
    err = error("G93 G1 X1 F2\nG1 X2")
    assert err.line == 2


def test_arc_command_type() -> None:
    assert isinstance(run("G2 X2 I1 F1")[-1], ArcFeed)


def test_io_codes() -> None:
    out = run("M62 P1\nM63 P1\nM64 P2\nM65 P2\nM67 E1 Q2\nM68 E2 Q-1.5")
    assert [(c.index, c.on, c.synced) for c in out[:4]] == [(1, True, True), (1, False, True),
                                                           (2, True, False), (2, False, False)]
    assert [(c.index, c.value, c.synced) for c in out[4:]] == [(1, 2, True), (2, -1.5, False)]
    assert "P word" in error("M62").message
    assert "Q word" in error("M67 E1").message
    assert "integer" in error("M62 P1.5").message


def test_stops_spindle_directions_and_units_of_modes() -> None:
    out = run("M4 S200\nM0\nM1\nM60\nG20 G95 F0.01\nG64 P0.001")
    assert (out[1].NAME, out[1].direction.name, out[1].rpm) == ("START_SPINDLE", "CCW", 200)
    assert [c.NAME for c in out[2:5]] == ["PROGRAM_STOP", "PROGRAM_STOP", "PALLET_SHUTTLE"]
    assert (out[2].optional, out[3].optional) == (False, True)
    feed = [c for c in out if c.NAME == "SET_FEED_RATE"][-1]
    assert feed.rate == pytest.approx(0.254)  # 0.01 in/rev in mm/rev
    assert out[-1].tolerance == pytest.approx(0.0254)


def test_g91_1_is_the_default_and_g90_1_absolute_centres() -> None:
    arc = run("G0 X10\nG90.1 G2 X20 I15 J0 F1")[-1]
    assert arc.center.x == 15
    arc = run("G0 X10\nG2 X20 I5 J0 F1")[-1]
    assert arc.center.x == 15
