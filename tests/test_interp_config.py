"""The machine file's [interpreter] table: read and checked by motiond.config, turned into the
interpreter's settings by motiond.interp_settings for canon check, canon plan, canon run and the daemon,
with the command-line options winning."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from motiond.cli import main
from motiond.config import InterpreterConfig, load_machine
from motiond.configkit import ConfigError
from motiond.interp_settings import build_settings

Cap = pytest.CaptureFixture[str]

MACHINE = """
[machine]
name = "interp test"

[axes.x]
max_velocity = 200.0
max_acceleration = 2000.0
max_jerk = 50000.0

[axes.y]
max_velocity = 200.0
max_acceleration = 2000.0
max_jerk = 50000.0

[axes.z]
max_velocity = 100.0
max_acceleration = 1500.0
max_jerk = 40000.0
"""

# a subroutine that moves X to its first argument; two copies that differ, to see which one was found
SIDE = "o<side> sub\nG1 X#1 F600\no<side> endsub\nM2\n"
SIDE_OTHER = "o<side> sub\nG1 Y#1 F600\no<side> endsub\nM2\n"
PROG = "G21 G90\no<side> call [7]\nM2\n"


def machine_file(tmp_path: Path, interpreter: str, name: str = "machine.toml") -> str:
    path = tmp_path / name
    path.write_text(MACHINE + "\n[interpreter]\n" + interpreter)
    return str(path)


@pytest.fixture
def layout(tmp_path: Path) -> Path:
    """tmp/conf/machine.toml beside tmp/conf/subs/side.ngc (X move); tmp/other/side.ngc (Y move)."""
    conf = tmp_path / "conf"
    (conf / "subs").mkdir(parents=True)
    (conf / "subs" / "side.ngc").write_text(SIDE)
    (conf / "logs").mkdir()
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "side.ngc").write_text(SIDE_OTHER)
    (conf / "tools.tbl").write_text("T1 P1 Z10 D6 ;end mill\n")
    (tmp_path / "prog").mkdir()
    (tmp_path / "prog" / "p.ngc").write_text(PROG)
    return tmp_path


def test_all_keys_read_with_paths_relative_to_the_file(layout: Path) -> None:
    conf = layout / "conf"
    path = machine_file(conf, """dialect = "gcode-canon"
subroutine_path = ["subs", "../other"]
max_call_depth = 4
max_loop_iterations = 500
log_dir = "logs"
block_delete = true
tool_table = "tools.tbl"
var_file = "state/m.var"
""")
    ic = load_machine(path).interpreter
    assert ic == InterpreterConfig(
        dialect="gcode-canon", subroutine_path=(conf / "subs", conf / "../other"), max_call_depth=4,
        max_loop_iterations=500, log_dir=conf / "logs", block_delete=True, tool_table=conf / "tools.tbl",
        var_file=conf / "state/m.var")
    s = build_settings(load_machine(path), dry_run=True)
    assert (s.dialect, s.max_call_depth, s.max_loop_iterations) == ("gcode-canon", 4, 500)
    assert s.block_delete
    assert s.subroutine_path == [conf / "subs", conf / "../other"]
    assert (s.log_dir, s.tool_table, s.var_file) == (conf / "logs", conf / "tools.tbl", conf / "state/m.var")
    assert s.axes == "xyz" and s.dry_run


def test_defaults_without_the_table(tmp_path: Path) -> None:
    path = tmp_path / "m.toml"
    path.write_text(MACHINE)
    assert load_machine(str(path)).interpreter == InterpreterConfig()
    assert load_machine(None).interpreter == InterpreterConfig()
    s = build_settings(load_machine(None))
    assert (s.dialect, s.subroutine_path) == ("linuxcnc", [])
    assert (s.max_call_depth, s.max_loop_iterations) == (10, 1_000_000)
    assert s.axes is None  # the demo machine: any axis word


@pytest.mark.parametrize(("text", "key", "message"), [
    ('dialekt = "grbl"', "interpreter.dialekt", "unknown key"),
    ('dialect = "fanuc"', "interpreter.dialect", "must be one of linuxcnc, gcode-canon, grbl"),
    ("dialect = 3", "interpreter.dialect", "must be str"),
    ('subroutine_path = "subs"', "interpreter.subroutine_path", "must be list"),
    ('subroutine_path = ["subs", "nowhere"]', "interpreter.subroutine_path[1]", "no such directory"),
    ('subroutine_path = [""]', "interpreter.subroutine_path[0]", "must be a directory name"),
    ("subroutine_path = [1]", "interpreter.subroutine_path[0]", "must be a directory name"),
    ("max_call_depth = 0", "interpreter.max_call_depth", "must be >= 1"),
    ("max_call_depth = 2.5", "interpreter.max_call_depth", "must be int"),
    ("max_loop_iterations = -1", "interpreter.max_loop_iterations", "must be >= 1"),
    ('log_dir = "missing"', "interpreter.log_dir", "no such directory"),
    ('block_delete = "yes"', "interpreter.block_delete", "must be bool"),
    ('tool_table = "none.tbl"', "interpreter.tool_table", "no such file"),
    ('tool_table = ""', "interpreter.tool_table", "must not be empty"),
    ('var_file = "subs"', "interpreter.var_file", "is a directory"),
])
def test_errors_name_the_key(layout: Path, text: str, key: str, message: str) -> None:
    path = machine_file(layout / "conf", text + "\n")
    with pytest.raises(ConfigError) as info:
        load_machine(path)
    assert info.value.key == key and message in info.value.message
    assert info.value.file == path


def test_interpreter_must_be_a_table(tmp_path: Path) -> None:
    path = tmp_path / "m.toml"
    path.write_text("interpreter = 3\n" + MACHINE)
    with pytest.raises(ConfigError, match="interpreter: must be a table"):
        load_machine(str(path))


def test_a_bad_key_is_a_one_line_error_from_check(layout: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = machine_file(layout / "conf", "max_call_depth = 0\n")
    assert main(["check", "--config", path, str(layout / "prog" / "p.ngc")]) == 1
    err = capsys.readouterr().err
    assert err.strip() == f"{path}: interpreter.max_call_depth: must be >= 1, got 0"


def check_lines(args: list[str], capsys: pytest.CaptureFixture[str]) -> list[str]:
    assert main(["check", *args]) == 0, capsys.readouterr().err
    return capsys.readouterr().out.splitlines()


def test_check_finds_the_subroutine_on_the_config_path(layout: Path, capsys: Cap) -> None:
    prog = str(layout / "prog" / "p.ngc")
    config = machine_file(layout / "conf", 'subroutine_path = ["subs"]\n')
    out = check_lines(["--config", config, prog], capsys)
    assert "STRAIGHT_FEED(7.0000, 0.0000, 0.0000, 0.0000, 0.0000, 0.0000)" in "\n".join(out)
    # without the table the subroutine is not found
    bare = layout / "conf" / "bare.toml"
    bare.write_text(MACHINE)
    assert main(["check", "--config", str(bare), prog]) == 1
    assert "no file side.ngc on the subroutine path" in capsys.readouterr().err


def test_cli_subroutine_path_wins(layout: Path, capsys: pytest.CaptureFixture[str]) -> None:
    prog = str(layout / "prog" / "p.ngc")
    config = machine_file(layout / "conf", 'subroutine_path = ["subs"]\n')
    args = ["--config", config, "--subroutine-path", str(layout / "other"), prog]
    out = "\n".join(check_lines(args, capsys))
    assert "STRAIGHT_FEED(0.0000, 7.0000, 0.0000" in out  # the other directory's side.ngc moves Y
    assert "STRAIGHT_FEED(7.0000" not in out


def test_plan_finds_the_subroutine_on_the_config_path(layout: Path, capsys: Cap) -> None:
    prog = str(layout / "prog" / "p.ngc")
    config = machine_file(layout / "conf", 'subroutine_path = ["subs"]\n')
    assert main(["plan", "--json", "--config", config, prog]) == 0, capsys.readouterr().err
    summary = json.loads(capsys.readouterr().out)
    assert summary["final_position"]["x"] == pytest.approx(7.0) and summary["final_position"]["y"] == 0.0
    assert main(["plan", "--json", "--config", config, "--subroutine-path", str(layout / "other"), prog]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["final_position"]["y"] == pytest.approx(7.0) and summary["final_position"]["x"] == 0.0


def test_dialect_and_tool_table_overrides(layout: Path, capsys: pytest.CaptureFixture[str]) -> None:
    conf = layout / "conf"
    prog = layout / "prog" / "labels.ngc"
    prog.write_text("G0 X1\nO5\nG0 X2\nM2\n")  # a bare O number: a label in gcode-canon, an error in linuxcnc
    config = machine_file(conf, 'dialect = "gcode-canon"\ntool_table = "tools.tbl"\n')
    check_lines(["--config", config, str(prog)], capsys)
    assert main(["check", "--config", config, "--dialect", "linuxcnc", str(prog)]) == 1
    capsys.readouterr()
    # the tool table: T1 Z10 from the file, T1 Z3 from --tool-table
    tools = layout / "prog" / "tools.ngc"
    tools.write_text("T1 M6\nG43\nM2\n")
    out = "\n".join(check_lines(["--config", config, str(tools)], capsys))
    assert "USE_TOOL_LENGTH_OFFSET(0.0000, 0.0000, 10.0000" in out
    other = layout / "other" / "t.tbl"
    other.write_text("T1 P1 Z3 D6\n")
    out = "\n".join(check_lines(["--config", config, "--tool-table", str(other), str(tools)], capsys))
    assert "USE_TOOL_LENGTH_OFFSET(0.0000, 0.0000, 3.0000" in out


def test_block_delete_and_call_depth_from_the_file(layout: Path, capsys: pytest.CaptureFixture[str]) -> None:
    conf = layout / "conf"
    prog = layout / "prog" / "bd.ngc"
    prog.write_text("G0 X1\n/G0 X5\nM2\n")
    config = machine_file(conf, "block_delete = true\nmax_call_depth = 1\n")
    assert "X5" not in "\n".join(check_lines(["--config", config, str(prog)], capsys))
    assert "5.0000" not in "\n".join(check_lines(["--config", config, str(prog)], capsys))
    nested = layout / "prog" / "nest.ngc"
    nested.write_text("o<a> sub\no<b> call\no<a> endsub\no<b> sub\nG0 X1\no<b> endsub\no<a> call\nM2\n")
    assert main(["check", "--config", config, str(nested)]) == 1
    assert "max_call_depth" in capsys.readouterr().err
    loose = machine_file(conf, "max_call_depth = 2\n", name="loose.toml")
    check_lines(["--config", loose, str(nested)], capsys)


def test_run_and_the_daemon_machine_use_the_table(layout: Path) -> None:
    from motiond.runtime import Machine

    conf = layout / "conf"
    config = load_machine(machine_file(conf, 'subroutine_path = ["subs"]\ntool_table = "tools.tbl"\n'
                                             'var_file = "m.var"\n'))
    machine = Machine(config, lc=None)
    try:
        s = machine.interp.settings
        assert s.subroutine_path == [conf / "subs"] and s.tool_table == conf / "tools.tbl"
        assert s.var_file == conf / "m.var" and not s.dry_run
    finally:
        machine.shutdown()
    # the daemon's own var file (its state directory) wins over the file's
    machine = Machine(config, lc=None, var_file=layout / "state.var")
    try:
        assert machine.interp.settings.var_file == str(layout / "state.var")
    finally:
        machine.shutdown()


def test_canon_run_finds_the_subroutine(layout: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """canon run on the demo machine's parts with a config that names the subroutine directory."""
    conf = layout / "conf"
    example = Path(__file__).resolve().parent.parent / "examples" / "canon.toml"
    text = example.read_text()
    start = text.index("[interpreter]")
    end = text.index("\n[", start + 1)
    text = text[:start] + '[interpreter]\nsubroutine_path = ["subs"]\n' + text[end + 1:]
    config = conf / "run.toml"
    config.write_text(text)
    prog = str(layout / "prog" / "p.ngc")
    code = main(["run", "--no-telemetry", "--json", "--config", str(config), prog])
    assert code == 0, capsys.readouterr().err
    summary = json.loads(capsys.readouterr().out)
    assert summary["ok"] and summary["final_positions"]["x"] == pytest.approx(7.0)


def test_linuxcnc_ini_switches_from_the_file(layout: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """tool_change_with_spindle_on and disable_g92_persistence reach the interpreter from the file
    (LinuxCNC's [EMCIO] / [RS274NGC] settings of the same names)."""
    conf = layout / "conf"
    prog = layout / "prog" / "tc.ngc"
    prog.write_text("M3 S1000\nT1 M6\nM2\n")
    default = check_lines(["--config", machine_file(conf, ""), str(prog)], capsys)
    keep = check_lines(["--config", machine_file(conf, "tool_change_with_spindle_on = true\n", name="k.toml"),
                        str(prog)], capsys)

    def stops_before_change(lines: list[str]) -> bool:
        change = next(i for i, s in enumerate(lines) if "CHANGE_TOOL" in s and "NUMBER" not in s)
        return any("STOP_SPINDLE_TURNING" in s for s in lines[:change])

    assert stops_before_change(default)
    assert not stops_before_change(keep)
    settings = build_settings(load_machine(machine_file(conf, "disable_g92_persistence = true\n",
                                                        name="g92.toml")))
    assert settings.disable_g92_persistence and not settings.tool_change_with_spindle_on
