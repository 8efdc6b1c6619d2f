"""The machine side: callbacks at sync points, persistence, tool table, LOG files, MDI, laziness."""

from __future__ import annotations

from pathlib import Path

import pytest
from test_interp_helpers import error, run

from gcode_canon.commands import Pose, Probe, WaitInput
from gcode_canon.errors import GCodeError
from gcode_canon.interpreter import Interpreter
from gcode_canon.machine import DryRunMachine
from gcode_canon.paramfile import read_parameter_file, write_parameter_file
from gcode_canon.settings import InterpreterSettings

PROGRAMS = Path(__file__).resolve().parent / "programs"


class Recorder(DryRunMachine):
    """Answers set by the test; records when each question was asked."""

    def __init__(self) -> None:
        super().__init__()
        self.events: list[str] = []
        self.input_value = 1.0
        self.probe_answer: tuple[Pose, bool] | None = None
        self.position: Pose | None = None

    def wait_input(self, cmd: WaitInput) -> float:
        self.events.append(f"wait {cmd.index}")
        return self.input_value

    def probe(self, cmd: Probe) -> tuple[Pose, bool]:
        self.events.append("probe")
        return self.probe_answer or (cmd.end, True)

    def current_position(self) -> Pose | None:
        self.events.append("position")
        return self.position


def test_m66_callback_runs_when_the_consumer_resumes() -> None:
    machine = Recorder()
    interp = Interpreter(InterpreterSettings(require_program_end=False), machine)
    gen = interp.run_string("M66 P3 L0\n#1 = #5399\nM66 E0\nM2\n", "t.ngc")
    first = next(gen)
    assert isinstance(first, WaitInput) and first.index == 3
    assert machine.events == ["position"]  # at start; no input read before the consumer has the command
    machine.input_value = 0.75
    rest = list(gen)
    assert machine.events == ["position", "wait 3", "wait 0"]
    assert interp.params.get_numbered(1) == 0.75
    assert interp.params.get_numbered(5399) == 0.75
    assert rest[-1].NAME == "PROGRAM_END"


def test_m66_word_errors() -> None:
    assert "exactly one" in error("M66 P1 E1").message
    assert "exactly one" in error("M66").message
    assert "only L0" in error("M66 E1 L3 Q1").message
    assert "needs a Q" in error("M66 P1 L3").message
    assert "L0 to L4" in error("M66 P1 L7 Q1").message


def test_probe_trip_position_and_miss() -> None:
    machine = Recorder()
    machine.probe_answer = (Pose(0, 0, -4), True)
    interp = Interpreter(InterpreterSettings(require_program_end=False), machine)
    out = run("G38.2 Z-10 F50\nG91 G0 Z1", interp)
    assert out[-1].end.z == -3  # continues from where the probe stopped
    assert interp.params.get_numbered(5063) == -4
    machine.probe_answer = (Pose(0, 0, -9), False)
    run("G90 G38.3 Z-10", interp)  # G38.3: a miss is not an error
    assert interp.params.get_numbered(5070) == 0
    with pytest.raises(GCodeError, match="without making contact") as info:
        run("G0 Z0\nG38.2 Z-10", interp)
    assert info.value.line == 2


def test_position_resynchronised_at_start_after_stop_and_tool_change() -> None:
    machine = Recorder()
    interp = Interpreter(InterpreterSettings(require_program_end=False), machine)
    machine.position = Pose(7, 8, 9)
    gen = interp.run_string("G0 Z1\nM0\nG91 G0 X1\nT1 M6\nM1\nM60", "t.ngc")
    first = next(gen)
    assert first.end == Pose(7, 8, 1)  # X and Y stay where the machine really is
    machine.position = Pose(5, 5, 5)
    out = [first, *gen]
    assert out[2].end == Pose(6, 5, 5)
    assert machine.events == ["position"] * 5


def test_mdi_starts_from_the_machine_position() -> None:
    machine = Recorder()
    interp = Interpreter(InterpreterSettings(), machine)
    machine.position = Pose(1, 2, 3)
    assert interp.execute_mdi("G91 G0 X1")[0].end == Pose(2, 2, 3)


def test_var_file_read_at_start_and_written_at_end(tmp_path: Path) -> None:
    var = tmp_path / "params.var"
    write_parameter_file(var, {5221: 10.0, 5241: 20.0, 5220: 2.0, 5161: 1.0})
    interp = Interpreter(InterpreterSettings(var_file=var))
    out = list(interp.run_string("G0 X0\nG10 L2 P1 Y7\n#31 = 4.5\nM2\n", "t.ngc"))
    assert out[0].end.x == 20  # G55 was active in the file
    values = read_parameter_file(var)
    assert values[5222] == 7 and values[31] == 4.5 and values[5161] == 1
    assert values[5220] == 1  # M2 returned to G54


def test_dry_run_never_writes_the_var_file(tmp_path: Path) -> None:
    var = tmp_path / "params.var"
    write_parameter_file(var, {5221: 1.0})
    before = var.read_bytes()
    interp = Interpreter(InterpreterSettings(var_file=var, dry_run=True))
    list(interp.run_string("G10 L2 P1 X5\nM2\n"))
    interp.shutdown()
    assert var.read_bytes() == before


def test_bad_var_file_is_a_located_error(tmp_path: Path) -> None:
    var = tmp_path / "bad.var"
    var.write_text("5222 1\n5221 0\n")
    with pytest.raises(GCodeError, match="out of order") as info:
        Interpreter(InterpreterSettings(var_file=var))
    assert info.value.file


def test_tool_table_offsets_and_unknown_tools() -> None:
    settings = InterpreterSettings(tool_table=PROGRAMS / "tools.tbl", require_program_end=False)
    interp = Interpreter(settings)
    run("T2 M6 G43\nG0 Z0", interp)
    assert interp.pos.z == -2.5
    assert interp.params.get_numbered(5403) == -2.5 and interp.params.get_numbered(5410) == 3
    assert interp.current_tool == 2
    with pytest.raises(GCodeError, match="not in the tool table"):
        run("T9", interp)
    with pytest.raises(GCodeError, match="not in the tool table"):
        run("G43 H9", interp)
    run("M61 Q1", interp)
    assert interp.current_tool == 1
    assert "no tool selected" in error("M6").message


def test_log_files_only_inside_the_log_directory(tmp_path: Path) -> None:
    interp = Interpreter(InterpreterSettings(log_dir=tmp_path, require_program_end=False))
    run("#1 = 3\n(LOGOPEN,out.txt)\n(LOG,one #1)\n(LOGCLOSE)", interp)
    assert (tmp_path / "out.txt").read_text() == "one 3.000000\n"
    run("(LOGAPPEND,out.txt)\n(LOG,two)\n(LOGCLOSE)", interp)
    assert (tmp_path / "out.txt").read_text() == "one 3.000000\ntwo\n"
    with pytest.raises(GCodeError, match="outside the log directory"):
        run("(LOGOPEN,../escape.txt)", interp)
    assert not (tmp_path.parent / "escape.txt").exists()
    assert "no log directory" in error("(LOGOPEN,x.txt)").message


def test_modal_state_save_and_restore() -> None:
    out = run("M70\nG20 G91 F10 M3 S100 M8\nM72\nG0 X1")
    names = [c.NAME for c in out if c.line == 3]
    assert names == ["USE_LENGTH_UNITS", "SET_FEED_RATE", "SET_SPINDLE_SPEED", "STOP_SPINDLE_TURNING",
                     "COOLANT"]
    assert out[-1].end.x == 1  # G90 and mm again
    assert "no saved modal state" in error("M72").message
    assert "no saved modal state" in error("M70\nM71\nM72").message


def test_overrides() -> None:
    out = run("M49\nM48\nM50 P0\nM51\nM52 P1\nM53 P0")
    got = [(c.feed, c.spindle, c.adaptive_feed, c.feed_hold) for c in out]
    assert got == [(False, False, None, None), (True, True, None, None), (False, None, None, None),
                   (None, True, None, None), (None, None, True, None), (None, None, None, False)]


def test_program_end_resets_modes() -> None:
    interp = Interpreter(InterpreterSettings())
    out = list(interp.run_string("G55 G18 G93 M3 S10 M7 M49\nM2\n"))
    names = [c.NAME for c in out if c.line == 2]
    assert names == ["SET_G5X_OFFSET", "SELECT_PLANE", "SET_FEED_MODE", "SET_OVERRIDES",
                     "STOP_SPINDLE_TURNING", "COOLANT", "PROGRAM_END"]
    assert interp.active_gcodes()[:2] == ("G1", "G17")


def test_execute_mdi() -> None:
    machine = Recorder()
    interp = Interpreter(InterpreterSettings(), machine)
    assert interp.execute_mdi("G0 X1")[0].end.x == 1
    out = interp.execute_mdi("M66 P2")
    assert out[0].NAME == "WAIT_INPUT" and machine.events == ["position", "position", "wait 2"]
    with pytest.raises(GCodeError, match="<mdi>:1: Attempt to divide by zero"):
        try:
            interp.execute_mdi("G0 X[1/0]")
        except GCodeError as exc:
            raise GCodeError(str(exc)) from None


def test_reading_is_lazy(tmp_path: Path) -> None:
    path = tmp_path / "lazy.ngc"
    path.write_text("G0 X1\nG0 X2\nthis line is bad\nM2\n")
    gen = Interpreter(InterpreterSettings()).run_file(path)
    assert next(gen).end.x == 1  # the bad line 3 has not been read yet
    assert next(gen).end.x == 2
    with pytest.raises(GCodeError) as info:
        next(gen)
    assert info.value.line == 3


def test_missing_program_file() -> None:
    with pytest.raises(GCodeError, match="Cannot open"):
        Interpreter().run_file("/nonexistent/x.ngc")


def test_g92_offsets_persist_over_program_end() -> None:
    interp = Interpreter(InterpreterSettings())
    list(interp.run_string("G0 X10\nG92 X0\nM2\n"))
    out = list(interp.run_string("G0 X1\nM2\n"))
    assert out[0].end.x == 11


def test_position_accessors() -> None:
    interp = Interpreter(InterpreterSettings(require_program_end=False))
    run("G10 L2 P1 X1\nG54 G20 G0 X1 A5", interp)
    assert interp.position.x == pytest.approx(26.4)
    assert interp.program_position()[:4] == pytest.approx((1, 0, 0, 5))
    assert interp.parameter("#<_x>") == pytest.approx(1)
    assert interp.parameter(5221) == 1
    assert interp.parameter(5220) == 1


def test_line_source_mark_and_jump() -> None:
    from gcode_canon.source import LineSource

    src = LineSource.from_string("a\nb\nc\n")
    assert next(src) == "a"
    mark = src.mark()
    assert [next(src), next(src)] == ["b", "c"]
    src.jump(mark)
    assert (next(src), src.line) == ("b", 2)


def test_probe_log(tmp_path: Path) -> None:
    interp = Interpreter(InterpreterSettings(log_dir=tmp_path, require_program_end=False))
    run("(PROBEOPEN probes.txt)\nG38.2 Z-2 F10\nG38.3 X1\n(PROBECLOSE)\nG38.2 Z-3", interp)
    lines = (tmp_path / "probes.txt").read_text().splitlines()
    assert lines == ["0.000000 0.000000 -2.000000 " + "0.000000 " * 5 + "0.000000",
                     "1.000000 0.000000 -2.000000 " + "0.000000 " * 5 + "0.000000"]
