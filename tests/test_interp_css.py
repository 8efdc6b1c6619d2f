"""G96 (constant surface speed, D the highest rpm) and G97 as LinuxCNC's convert_spindle_mode and
emccanon's SET_SPINDLE_MODE / SPINDLE_SPEED_: the surface speed from the S word (m/min in G21,
ft/min in G20), the centre line at program X0 (G5x + G92 + tool X offsets)."""

from __future__ import annotations

import pytest

from gcode_canon.commands import SetSpindleMode, SetSpindleSpeed
from gcode_canon.interpreter import Interpreter
from gcode_canon.settings import InterpreterSettings
from tests import rs274_oracle as oracle
from tests.test_interp_helpers import error, run


def _modes(text: str) -> list[SetSpindleMode]:
    return [c for c in run(text) if isinstance(c, SetSpindleMode)]


def test_g96_d_gives_the_highest_rpm_and_the_surface_speed_in_mm_per_minute() -> None:
    out = run("G21 G96 D2500 S200 M3")
    i = next(k for k, c in enumerate(out) if isinstance(c, SetSpindleMode))
    mode = out[i]
    assert (mode.css_max, mode.surface, mode.x_centre) == (2500.0, 200 * 1000.0, 0.0)
    assert isinstance(out[i + 1], SetSpindleSpeed) and out[i + 1].rpm == 200.0  # LinuxCNC's order
    # G20: feet of surface per minute; D negative counts by its size (fabs), no D: 1e30 (LinuxCNC)
    (inch,) = _modes("G20\nG96 D-1800 S300")
    assert (inch.css_max, inch.surface) == (1800.0, pytest.approx(300 * 304.8))
    (unlimited,) = _modes("G96 S100")
    assert unlimited.css_max == 1e30


def test_s_and_offset_changes_in_g96_send_the_mode_again_and_g97_ends_it() -> None:
    modes = _modes("G96 D2000 S100\nS150\nG10 L2 P2 X7\nG55\nG92 X1\nG97 S800\nS900\nG54")
    assert [m.css_max for m in modes] == [2000.0, 2000.0, 2000.0, 2000.0, 0.0]
    assert modes[1].surface == 150_000.0
    assert modes[2].x_centre == 7.0  # G55's X origin
    # G92 X1 with the machine at X0: program X0 is then machine X-1
    assert modes[3].x_centre == pytest.approx(-1.0)


def test_program_end_and_status() -> None:
    interp = Interpreter(InterpreterSettings(dry_run=True, require_program_end=False))
    run("G96 D2000 S100", interp)
    assert "G96" in interp.active_gcodes()
    assert (interp.parameter("_spindle_css_mode"), interp.parameter("_spindle_rpm_mode")) == (1.0, 0.0)
    out = run("M2", interp)
    assert any(isinstance(c, SetSpindleMode) and c.css_max == 0.0 for c in out)
    assert "G97" in interp.active_gcodes()
    assert (interp.parameter("_spindle_css_mode"), interp.parameter("_spindle_rpm_mode")) == (0.0, 1.0)


@pytest.mark.parametrize(("text", "message"), [
    ("G96 D2000", "S word missing with G96"),
    ("G97 D2000 S100", "D word with no G code that uses it"),
    ("G96 G97 S1", "same modal group"),
])
def test_refusals(text: str, message: str) -> None:
    assert message in str(error(text))


BINARY = oracle.rs274_binary()


@pytest.mark.rs274
@pytest.mark.skipif(BINARY is None, reason=f"rs274 is not built in {oracle.rs274_dir()}")
@pytest.mark.parametrize("name", ["nurbs/G5/Curva_Delfino #1=1_G5.ngc",
                                  "nurbs/G5/Curva_Mazatrol #1=1_G5.ngc"])
def test_linuxcnc_programs_that_start_in_g96(name: str) -> None:
    assert BINARY is not None
    assert oracle.compare(*oracle.run_both(oracle.nc_file_case(name), BINARY)) is None
