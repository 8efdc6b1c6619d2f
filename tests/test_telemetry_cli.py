"""``canon spy`` and ``canon log``: what they run, and their messages for the user's mistakes."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import lcm
import pytest

from motiond import cmd_spy
from motiond.cli import main
from telemetry import generate
from telemetry.url import DEFAULT_URL


@pytest.fixture
def display(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("DISPLAY", ":99")


@pytest.fixture
def no_java(monkeypatch: pytest.MonkeyPatch) -> None:
    real = shutil.which
    monkeypatch.setattr(shutil, "which",
                        lambda name, *a, **k: None if name == "java" else real(name, *a, **k))


def test_spy_runs_the_wheels_lcm_spy_with_our_jar_first_on_the_classpath(
        display: None, monkeypatch: pytest.MonkeyPatch) -> None:
    if shutil.which("java") is None:
        pytest.skip("needs a Java runtime (java)")
    monkeypatch.setenv("CLASSPATH", "/opt/other.jar")
    calls = []
    monkeypatch.setattr(os, "execve", lambda path, argv, env: calls.append((path, argv, env)))
    assert main(["spy", "--url", "udpm://239.255.76.67:7667?ttl=0"]) == 0
    (path, argv, env), = calls
    assert Path(path) == Path(lcm.LCM_BIN_DIR).resolve() / "lcm-spy" and argv[0] == path
    assert argv[1:] == ["--lcm-url=udpm://239.255.76.67:7667?ttl=0"]
    classpath = env["CLASSPATH"].split(os.pathsep)
    assert classpath[0] == str(generate.JAR)
    assert Path(classpath[1]).name == "lcm.jar" and Path(classpath[1]).is_file()
    assert classpath[-1] == "/opt/other.jar"


def test_spy_without_java_says_what_to_install(display: None, no_java: None,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["spy"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("canon spy: lcm-spy needs a Java runtime") and "default-jre" in err


def test_spy_without_display_says_so(monkeypatch: pytest.MonkeyPatch,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    if shutil.which("java") is None:
        pytest.skip("needs a Java runtime (java) to get as far as the display check")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert main(["spy"]) == 1
    assert "no display" in capsys.readouterr().err


def test_spy_with_a_bad_url(display: None, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["spy", "--url", "udpm://10.0.0.1:7667"]) == 1
    err = capsys.readouterr().err
    assert "not a multicast address" in err and "Traceback" not in err


def test_spy_command_uses_the_default_url(display: None) -> None:
    if shutil.which("java") is None:
        pytest.skip("needs a Java runtime (java)")
    argv, _ = cmd_spy.spy_command(DEFAULT_URL)
    assert argv[1] == f"--lcm-url={DEFAULT_URL}"


@pytest.mark.parametrize(("args", "message"), [
    (["--url", "memq://", "--duration", "0"], "--duration must be > 0"),
    (["--url", "udp://x"], "unknown LCM provider"),
])
def test_log_refuses_bad_options(tmp_path: Path, args: list[str], message: str,
                                 capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["log", str(tmp_path / "x.log"), *args]) == 1
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x.log").exists()


def test_log_will_not_overwrite_without_force(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "x.log"
    path.write_bytes(b"precious")
    assert main(["log", str(path), "--url", "memq://", "--duration", "0.2"]) == 1
    assert "exists (use --force" in capsys.readouterr().err
    assert path.read_bytes() == b"precious"


def test_log_into_a_missing_directory(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["log", str(tmp_path / "no" / "x.log"), "--url", "memq://"]) == 1
    assert "does not exist" in capsys.readouterr().err


def test_log_runs_lcm_logger_for_the_duration(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """On memq:// (no network) lcm-logger records nothing, but the file is a valid, empty LCM log."""
    path = tmp_path / "x.log"
    path.write_bytes(b"old")
    assert main(["log", str(path), "--url", "memq://", "--duration", "0.5", "--force"]) == 0
    err = capsys.readouterr().err
    assert f"{path}: 0 messages" in err and "lcm-logplayer --lcm-url='memq://'" in err
    log = lcm.EventLog(str(path), "r")
    assert list(log) == []
    log.close()


MACHINE = """
[machine]
name = "t"
[axes.x]
max_velocity = 100.0
max_acceleration = 1000.0
max_jerk = 10000.0
[telemetry]
url = "memq://"
status_hz = 20
"""


def test_log_takes_the_url_from_the_machine_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("motiond.config")
    machine = tmp_path / "machine.toml"
    machine.write_text(MACHINE)
    assert main(["log", str(tmp_path / "x.log"), "--config", str(machine), "--duration", "0.2"]) == 0
    assert "recording memq:// into" in capsys.readouterr().err


def test_a_bad_telemetry_key_names_the_file_and_key(tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("motiond.config")
    machine = tmp_path / "machine.toml"
    machine.write_text(MACHINE.replace('url = "memq://"', 'url = "udpm://10.0.0.1:7667"'))
    assert main(["log", str(tmp_path / "x.log"), "--config", str(machine)]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"{machine}: telemetry.url: ") and "not a multicast address" in err
