"""The `canon` dispatcher: sub-commands, and user errors as one line with exit status 1."""

from __future__ import annotations

import subprocess
import sys

import pytest

from motiond import cli


def test_help_lists_commands(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as done:
        cli.main(["--help"])
    assert done.value.code == 0
    assert "sim" in capsys.readouterr().out


def test_unknown_command_is_usage_error() -> None:
    with pytest.raises(SystemExit) as done:
        cli.main(["no-such-command"])
    assert done.value.code == 2


def test_console_script_entry_point_runs() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "motiond.cli", "--help"], capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0
    assert "usage: canon" in out.stdout


def test_user_error_is_one_line_under_python_m(tmp_path) -> None:
    # `canon sim io` may be absent in a partial build; use a sub-command that raises UserError.
    out = subprocess.run(
        [sys.executable, "-m", "motiond.cli", "check", str(tmp_path / "missing.ngc")],
        capture_output=True, text=True, timeout=60,
    )
    assert out.returncode == 1
    assert "Traceback" not in out.stderr
    assert "missing.ngc" in out.stderr
