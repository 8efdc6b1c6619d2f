"""Where `canon daemon` keeps its parameter file: --var, else the config's var_file, else the state dir."""

from __future__ import annotations

from pathlib import Path

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
