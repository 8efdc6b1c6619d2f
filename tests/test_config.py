"""The machine file's [machine] and [axes.*] tables: read into the planner's limits, errors name the key."""

from __future__ import annotations

from pathlib import Path

import pytest

from motiond.config import load_machine
from motiond.configkit import ConfigError, Table
from planner.machine import DEMO_MACHINE, AxisLimits, MachineError, MachineLimits

GOOD = """
[machine]
name = "test mill"
cycle_ms = 1.0

[axes.x]
max_velocity = 200.0
max_acceleration = 2000.0
max_jerk = 50000
min_position = -1.0
max_position = 300.0
quick_stop_deceleration = 5000.0

[axes.z]
max_velocity = 100.0
max_acceleration = 1500.0
max_jerk = 40000.0

[axes.a]
max_velocity = 3600.0
max_acceleration = 20000.0
max_jerk = 500000.0

[canopen]
interface = "virtual"

[canopen.axes.x]
node_id = 1

[telemetry]
url = "udpm://239.255.76.67:7667?ttl=0"
"""


def write(tmp_path: Path, text: str) -> str:
    path = tmp_path / "machine.toml"
    path.write_text(text)
    return str(path)


def test_no_file_is_the_demo_machine() -> None:
    cfg = load_machine(None)
    assert cfg.limits is DEMO_MACHINE
    assert cfg.path is None
    assert cfg.limits.names == ("x", "y", "z")
    assert cfg.limits.cycle_s == 0.002
    assert isinstance(cfg.canopen, Table) and cfg.canopen.data == {}


def test_reads_axes_in_file_order_with_units(tmp_path: Path) -> None:
    cfg = load_machine(write(tmp_path, GOOD))
    lim = cfg.limits
    assert lim.names == ("x", "z", "a")
    assert lim.cycle_s == pytest.approx(0.001)
    assert lim.name == "test mill"
    x = lim.axis("x")
    assert (x.max_velocity, x.max_acceleration, x.max_jerk) == (200.0, 2000.0, 50000.0)
    assert (x.min_position, x.max_position, x.quick_stop) == (-1.0, 300.0, 5000.0)
    z = lim.axis("z")
    assert z.min_position is None and z.quick_stop == 3000.0  # default: twice the acceleration
    assert lim.axis("a").rotary and lim.axis("a").unit == "deg" and x.unit == "mm"
    # the other layers' tables are passed on untouched, with their dotted paths
    assert cfg.canopen.data["interface"] == "virtual"
    assert cfg.canopen.table("axes").table("x").key("node_id") == "canopen.axes.x.node_id"
    assert cfg.telemetry.data["url"].endswith("ttl=0")
    assert cfg.modbus.data == {}
    assert cfg.root is not None and "canopen" in cfg.root


@pytest.mark.parametrize(
    ("change", "key", "message"),
    [
        (("max_velocity = 200.0", "max_velocity = 0.0"), "axes.x.max_velocity", "must be > 0"),
        (("max_acceleration = 2000.0", "max_acceleration = -5"), "axes.x.max_acceleration", "must be > 0"),
        (("max_jerk = 50000", 'max_jerk = "fast"'), "axes.x.max_jerk", "must be float"),
        (("max_jerk = 50000", "max_jerk = nan"), "axes.x.max_jerk", "finite"),
        (("cycle_ms = 1.0", "cycle_ms = 0.5"), "machine.cycle_ms", "between 1.0 and 10.0"),
        (("cycle_ms = 1.0", "cycle_ms = 20"), "machine.cycle_ms", "between 1.0 and 10.0"),
        (("max_velocity = 100.0", "max_velocty = 100.0"), "axes.z.max_velocty", "unknown key"),
        (("[axes.a]", "[axes.q]"), "axes.q", "not an axis name"),
        (("min_position = -1.0", "min_position = 400.0"), "axes.x.min_position", "below max_position"),
        (("[telemetry]", "[telemetri]"), "telemetri", "unknown table"),
        (("cycle_ms = 1.0", "cycle_ms = 1.0\nspeed = 3"), "machine.speed", "unknown key"),
        (("quick_stop_deceleration = 5000.0", "quick_stop_deceleration = 0"),
         "axes.x.quick_stop_deceleration", "must be > 0"),
    ],
)
def test_errors_name_file_and_key(tmp_path: Path, change: tuple[str, str], key: str, message: str) -> None:
    path = write(tmp_path, GOOD.replace(*change, 1))
    with pytest.raises(ConfigError) as err:
        load_machine(path)
    assert err.value.file == path
    assert err.value.key == key
    assert message in err.value.message
    assert str(err.value).startswith(f"{path}: {key}: ")


def test_missing_axes_and_missing_required_limit(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"axes: missing"):
        load_machine(write(tmp_path, "[machine]\ncycle_ms = 2\n"))
    with pytest.raises(ConfigError, match=r"axes.x.max_jerk: missing \(required\)"):
        load_machine(write(tmp_path, "[axes.x]\nmax_velocity = 1\nmax_acceleration = 1\n"))
    with pytest.raises(ConfigError, match=r"axes.x: must be a table"):
        load_machine(write(tmp_path, "[axes]\nx = 3\n"))


def test_file_problems(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no such file"):
        load_machine(str(tmp_path / "nope.toml"))
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_machine(write(tmp_path, "[axes.x\n"))


def test_machine_dataclasses_refuse_impossible_values() -> None:
    with pytest.raises(MachineError, match="max_jerk must be a finite number > 0"):
        AxisLimits("x", 1.0, 1.0, 0.0)
    with pytest.raises(MachineError, match="max_velocity"):
        AxisLimits("x", float("nan"), 1.0, 1.0)
    with pytest.raises(MachineError, match="not one of"):
        AxisLimits("q", 1.0, 1.0, 1.0)
    x = AxisLimits("x", 1.0, 1.0, 1.0)
    with pytest.raises(MachineError, match="repeat"):
        MachineLimits((x, x))
    with pytest.raises(MachineError, match="between 1 ms and 10 ms"):
        MachineLimits((x,), cycle_s=0.0005)
    with pytest.raises(MachineError, match="at least one axis"):
        MachineLimits(())


def test_the_documented_example_file_reads(tmp_path: Path) -> None:
    """The machine file in docs/DEVELOPING.md is valid as far as [machine] and [axes] go."""
    text = (Path(__file__).resolve().parent.parent / "docs" / "DEVELOPING.md").read_text()
    block = text.split("```toml", 1)[1].split("```", 1)[0]
    (tmp_path / "subs").mkdir()  # [interpreter]'s paths must exist, relative to the file
    (tmp_path / "logs").mkdir()
    (tmp_path / "programs").mkdir()
    (tmp_path / "tools.tbl").write_text("T1 P1 Z10 D6\n")
    cfg = load_machine(write(tmp_path, block))
    assert cfg.interpreter.subroutine_path == (tmp_path / "subs",)
    assert cfg.interpreter.program_path == (tmp_path / "programs",)
    assert cfg.interpreter.tool_table == tmp_path / "tools.tbl"
    assert cfg.limits.names == ("x",)
    assert cfg.limits.cycle_s == pytest.approx(0.002)
    assert cfg.limits.axis("x").quick_stop == 5000.0
    assert cfg.canopen.data["interface"] == "virtual"
    assert isinstance(cfg.modbus.data["devices"], list)


def test_a_machine_file_that_is_not_utf8_is_a_clean_error(tmp_path: Path) -> None:
    """A non-UTF-8 byte gave a traceback from canon check and canon daemon (found by fuzzing)."""
    import subprocess
    import sys

    bad = tmp_path / "m.toml"
    bad.write_bytes(b'[machine]\nname = "mill \xff"\n')
    prog = tmp_path / "p.ngc"
    prog.write_text("M2\n")
    for argv in (["check", "--config", str(bad), str(prog)], ["daemon", "--config", str(bad)]):
        res = subprocess.run([sys.executable, "-m", "motiond.cli", *argv], capture_output=True, text=True,
                             timeout=60)
        assert res.returncode == 1, res.stderr
        want = f"{bad}: line 2: byte 0xff is not UTF-8 text (a TOML file is UTF-8)"
        assert res.stderr.strip().endswith(want)
        assert "Traceback" not in res.stderr
