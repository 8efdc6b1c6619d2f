"""Where `canon daemon` keeps its parameter file: --var, else the config's var_file, else the state dir."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from motiond.cmd_daemon import parameter_file
from motiond.config import load_machine

AXIS = "[axes.x]\nmax_velocity = 100.0\nmax_acceleration = 1000.0\nmax_jerk = 10000.0\n"


def test_var_option_wins(tmp_path: Path) -> None:
    cfg = tmp_path / "m.toml"
    cfg.write_text(AXIS + '[interpreter]\nvar_file = "from_config.var"\n')
    assert parameter_file("cli.var", load_machine(str(cfg)), str(tmp_path / "state")) == "cli.var"


def test_config_var_file_relative_to_the_config(tmp_path: Path) -> None:
    cfg = tmp_path / "m.toml"
    cfg.write_text(AXIS + '[interpreter]\nvar_file = "from_config.var"\n')
    got = parameter_file(None, load_machine(str(cfg)), str(tmp_path / "state"))
    assert Path(got) == tmp_path / "from_config.var"
    assert not (tmp_path / "state").exists()


def test_default_is_in_the_state_directory(tmp_path: Path) -> None:
    got = Path(parameter_file(None, load_machine(None), str(tmp_path / "state")))
    assert got.parent == tmp_path / "state" and got.suffix == ".var"
    assert got.parent.is_dir()


def test_program_directories_option_config_or_state_dir(tmp_path: Path) -> None:
    from motiond.cli import UserError
    from motiond.cmd_daemon import program_dirs
    from motiond.configkit import ConfigError

    (tmp_path / "jobs").mkdir()
    cfg = tmp_path / "m.toml"
    cfg.write_text(AXIS + '[interpreter]\nprogram_path = ["jobs"]\n')
    config = load_machine(str(cfg))
    assert program_dirs(None, config, str(tmp_path / "state")) == [tmp_path / "jobs"]
    assert program_dirs([str(tmp_path)], config, None) == [tmp_path]
    default = program_dirs(None, load_machine(None), str(tmp_path / "state"))
    assert default == [tmp_path / "state" / "programs"]
    assert (tmp_path / "state" / "programs").is_dir()
    try:
        program_dirs([str(tmp_path / "nope")], config, None)
        raise AssertionError("a missing --program-dir was accepted")
    except UserError as exc:
        assert "--program-dir" in str(exc) and "no such directory" in str(exc)
    cfg.write_text(AXIS + '[interpreter]\nprogram_path = ["missing"]\n')
    try:
        load_machine(str(cfg))
        raise AssertionError("a missing program_path directory was accepted")
    except ConfigError as exc:
        assert "interpreter.program_path[0]: no such directory" in str(exc)


def test_the_daemon_warns_when_it_runs_as_root(monkeypatch: pytest.MonkeyPatch) -> None:
    from motiond import cmd_daemon

    monkeypatch.setattr(os, "geteuid", lambda: 0)
    assert "running as root" in (cmd_daemon.root_warning() or "")
    monkeypatch.setattr(os, "geteuid", lambda: 998)
    assert cmd_daemon.root_warning() is None


def test_the_unit_runs_as_a_dedicated_user_with_only_cap_sys_nice() -> None:
    unit = (Path(__file__).resolve().parent.parent / "examples" / "canon.service").read_text()
    settings = {}
    for line in unit.splitlines():
        if "=" in line and not line.startswith("#"):
            key, _, value = line.partition("=")
            settings.setdefault(key, []).append(value)
    assert settings["User"] == ["canon"] and settings["CapabilityBoundingSet"] == ["CAP_SYS_NICE"]
    assert settings["AmbientCapabilities"] == ["CAP_SYS_NICE"]
    for key, value in (("NoNewPrivileges", "yes"), ("ProtectSystem", "strict"), ("PrivateTmp", "yes"),
                       ("ProtectHome", "yes"), ("StateDirectory", "canon")):
        assert settings[key] == [value], key
    assert "RestrictRealtime" not in settings  # it would forbid SCHED_FIFO


def test_systemd_rates_the_unit_ok() -> None:
    """The exposure docs/daemon.md quotes (``systemd-analyze security``, offline: no systemd running)."""
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze is not installed (apt-get install systemd)")
    unit = Path(__file__).resolve().parent.parent / "examples" / "canon.service"
    res = subprocess.run(["systemd-analyze", "security", "--offline=yes", str(unit)], capture_output=True,
                         text=True, timeout=60)
    found = re.search(r"Overall exposure level for canon.service: ([0-9.]+) (\w+)", res.stdout + res.stderr)
    if found is None:
        pytest.skip(f"this systemd-analyze cannot rate a unit offline: {res.stderr.strip()[:200]}")
    assert float(found.group(1)) <= 2.5 and found.group(2) == "OK", res.stdout[-500:]
