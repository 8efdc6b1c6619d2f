"""``canon config check``: every table of the machine file checked offline, each bad key named;
``check``/``plan`` ``--config`` run the same validation; the drives' 32-bit ranges in counts."""

from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path

import pytest

from motiond.config_check import validate_machine
from motiond.configkit import ConfigErrors

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = (ROOT / "examples" / "canon.toml").read_text()
PROGRAM = "%\nG21 G90 G94\nG0 X1 Y2 Z3\nG1 X5 F600\nM2\n%\n"


def canon(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "motiond.cli", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT)


def machine(tmp_path: Path, *edits: tuple[str, str], name: str = "m.toml") -> Path:
    text = EXAMPLE
    for old, new in edits:
        assert old in text, old
        text = text.replace(old, new, 1)
    p = tmp_path / name
    p.write_text(text)
    return p


def test_example_is_valid_and_printed_as_a_table() -> None:
    r = canon("config", "check", "--config", "examples/canon.toml")
    assert r.returncode == 0, r.stderr
    out = r.stdout
    assert "example mill" in out and out.rstrip().endswith("examples/canon.toml: ok")
    rows = [line.split() for line in out.splitlines()]
    assert ["X", "mm", "200", "2000", "50000", "-1", "300", "5000"] in rows  # [axes.x] as written
    assert ["Z", "3", "10000", "-1", "set", "1", "shipped"] in rows  # [canopen.axes.z]
    assert "bus load 51.8 %" in " ".join(out.split())
    assert ["M62-M65", "P1", "io", "coil", "1", "safe", "0"] in rows


def test_every_bad_section_is_named(tmp_path: Path) -> None:
    bad = machine(tmp_path,
                  ("node_id = 2", "node_id = 200"),                  # [canopen]: beyond 127
                  ("coil = 1\n", "coil = 70000\n"),                  # [[modbus.digital_outputs]]
                  ("status_hz = 50", "status_hz = -1"))              # [telemetry]
    r = canon("config", "check", "--config", str(bad))
    assert r.returncode == 1 and "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert any(line.startswith(f"{bad}: canopen.axes.y.node_id: ") for line in lines), lines
    assert any(line.startswith(f"{bad}: modbus.digital_outputs[1].coil: ") for line in lines), lines
    assert any(line.startswith(f"{bad}: telemetry.status_hz: ") for line in lines), lines
    assert len(lines) == 3


@pytest.mark.parametrize("command", ["check", "plan"])
def test_check_and_plan_validate_canopen_and_modbus(tmp_path: Path, command: str) -> None:
    prog = tmp_path / "p.ngc"
    prog.write_text(PROGRAM)
    for edit, key in ((("node_id = 3", "node_id = 1"), "canopen.axes.z.node_id"),
                      (("device = \"io\"\ncoil = 0", "device = \"nowhere\"\ncoil = 0"),
                       "modbus.digital_outputs[0].device")):
        bad = machine(tmp_path, edit)
        r = canon(command, "--config", str(bad), str(prog))
        assert r.returncode == 1, r.stdout
        assert f"{bad}: {key}: " in r.stderr and "Traceback" not in r.stderr


def test_24_bit_encoder_names_the_key_when_out_of_range(tmp_path: Path) -> None:
    bad = machine(tmp_path, ("counts_per_unit = 10000        # drive counts per mm",
                             "counts_per_unit = 1677722"))
    with pytest.raises(ConfigErrors) as info:
        validate_machine(str(bad))
    (err,) = info.value.errors
    assert err.key == "canopen.axes.x.counts_per_unit"
    assert "0x6085" in err.message and "axes.x.quick_stop_deceleration" in err.message
    r = canon("config", "check", "--config", str(bad))
    assert r.returncode == 1 and "'I' format" not in r.stderr and "canopen.axes.x.counts_per_unit" in r.stderr


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_24_bit_encoder_runs_when_the_values_fit(tmp_path: Path) -> None:
    # 1677722 counts/mm x 2000 mm/s² = 3.4e9 counts/s²: within 0x6085's UNSIGNED32
    ok = machine(tmp_path,
                 ("counts_per_unit = 10000        # drive counts per mm", "counts_per_unit = 1677722"),
                 ("quick_stop_deceleration = 5000.0", "quick_stop_deceleration = 2000.0"),
                 ("port = 5020", f"port = {_free_port()}"))
    validate_machine(str(ok))
    prog = tmp_path / "p.ngc"
    prog.write_text(PROGRAM)
    r = canon("run", "--json", "--no-telemetry", "--config", str(ok), str(prog))
    assert r.returncode == 0, r.stderr
    assert '"x": 5.0' in r.stdout


def test_position_range_and_bus_budget(tmp_path: Path) -> None:
    far = machine(tmp_path, ("max_position = 300.0", "max_position = 300000.0"))  # 3e9 counts
    with pytest.raises(ConfigErrors, match=r"canopen.axes.x.counts_per_unit: .*max_position 300000"):
        validate_machine(str(far))
    fast = machine(tmp_path, ("cycle_ms = 2.0", "cycle_ms = 1.0"), name="fast.toml")
    with pytest.raises(ConfigErrors, match=r"fast.toml: canopen: bus load .* over the 70 % allowed"):
        validate_machine(str(fast))


def test_eds_and_two_register_value(tmp_path: Path) -> None:
    (tmp_path / "junk.eds").write_text("[FileInfo]\nFileName=junk.eds\n")
    bad = machine(tmp_path, ('eds = ""', 'eds = "junk.eds"'),
                  ('register = 0\ntype = "int16"', 'register = 65535\ntype = "float32"'))
    with pytest.raises(ConfigErrors) as info:
        validate_machine(str(bad))
    keys = [e.key for e in info.value.errors]
    assert keys == ["canopen.axes.x.eds", "modbus.analog_outputs[0].register"]
    assert "0x6040 controlword" in info.value.errors[0].message


def test_each_bad_axis_is_named(tmp_path: Path) -> None:
    bad = machine(tmp_path, ("max_velocity = 200.0", "max_velocity = -200.0"),
                  ("max_jerk = 40000.0", "max_jerk = 0.0"))
    with pytest.raises(ConfigErrors) as info:
        validate_machine(str(bad))
    keys = [e.key for e in info.value.errors]
    assert keys[:2] == ["axes.x.max_velocity", "axes.z.max_jerk"]


def test_every_bad_key_of_one_section_is_named(tmp_path: Path) -> None:
    """Two bad values and two misspelt keys in [canopen], two bad values in one axis: all six named,
    not just the first of each section."""
    bad = machine(tmp_path,
                  ("heartbeat_producer_ms = 100", "heartbeat_producer_ms = \"fast\""),
                  ("boot_timeout_s = 5.0", "boot_timeout_s = -5.0\nbitrat = 500000\nsimulat = false"),
                  ("following_error_window = 1.0   # mm", "following_error_window = -1.0"),
                  ("direction = 1\n", "direction = 2\n"))
    with pytest.raises(ConfigErrors) as info:
        validate_machine(str(bad))
    keys = sorted(e.key for e in info.value.errors)
    assert keys == sorted(["canopen.heartbeat_producer_ms", "canopen.boot_timeout_s", "canopen.bitrat",
                           "canopen.simulat", "canopen.axes.x.following_error_window",
                           "canopen.axes.x.direction"]), keys
    r = canon("config", "check", "--config", str(bad))
    assert r.returncode == 1 and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 6, r.stderr
