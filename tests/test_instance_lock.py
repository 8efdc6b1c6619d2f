"""One ``canon run`` or ``canon daemon`` per machine file: a second is refused naming the first's PID.

The processes run with ``--no-telemetry`` or ``memq://`` (nothing joins a multicast group) and their
own state directory (``--state-dir`` or ``XDG_STATE_HOME``).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from motiond.instance_lock import InstanceLock, MachineInUse, lock_path

ROOT = Path(__file__).resolve().parent.parent

PROGRAM = "%\nG21 G90 G94\nG0 X0 Y0 Z0\nG1 X100 F600\nM2\n%\n"  # a 10 s move


def canon(*args: str, env: dict[str, str]) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "motiond.cli", *args], cwd=ROOT, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def wait_for_line(p: subprocess.Popen[str], marker: str, timeout: float = 60.0) -> str:
    lines: list[str] = []
    found = threading.Event()

    def reader() -> None:
        assert p.stderr is not None
        for line in p.stderr:
            lines.append(line)
            if marker in line:
                found.set()
                return

    threading.Thread(target=reader, daemon=True).start()
    assert found.wait(timeout), "".join(lines)
    return "".join(lines)


def stop(p: subprocess.Popen[str]) -> None:
    if p.poll() is None:
        p.send_signal(signal.SIGINT)
        try:
            p.wait(30)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


@pytest.fixture
def env(tmp_path: Path) -> dict[str, str]:
    e = dict(os.environ)
    e.pop("STATE_DIRECTORY", None)
    e["XDG_STATE_HOME"] = str(tmp_path / "state")
    return e


@pytest.mark.parametrize("first", ["run", "daemon"])
def test_second_process_for_the_same_machine_is_refused(tmp_path: Path, env: dict[str, str],
                                                         first: str) -> None:
    prog = tmp_path / "long.ngc"
    prog.write_text(PROGRAM)
    if first == "run":
        a = canon("-v", "run", "--no-telemetry", str(prog), env=env)
        marker = "started"
    else:
        a = canon("daemon", "--url", "memq://", "--var", str(tmp_path / "d.var"), env=env)
        marker = "canon daemon: machine"
    try:
        wait_for_line(a, marker)
        b = canon("run", "--no-telemetry", str(prog), env=env)
        _out, err = b.communicate(timeout=60)
        assert b.returncode == 1, err
        assert f"the demo machine is in use by process {a.pid}" in err
        assert "Traceback" not in err
    finally:
        stop(a)
    assert a.returncode in (0, 130)
    # once the first has ended, the machine is free again
    (tmp_path / "short.ngc").write_text("%\nG0 X1\nM2\n%\n")
    c = canon("run", "--no-telemetry", str(tmp_path / "short.ngc"), env=env)
    _out, err = c.communicate(timeout=120)
    assert c.returncode == 0, err


def test_lock_is_per_machine_file_and_released(tmp_path: Path) -> None:
    a_cfg, b_cfg = tmp_path / "a.toml", tmp_path / "b.toml"
    la = lock_path(a_cfg, "mill", tmp_path / "s")
    assert lock_path(str(tmp_path / "." / "a.toml"), "mill", tmp_path / "s") == la
    assert lock_path(b_cfg, "mill", tmp_path / "s") != la
    assert lock_path(None, "mill", tmp_path / "s") != la
    first = InstanceLock(la, "machine file a.toml").acquire()
    with pytest.raises(MachineInUse, match=f"machine file a.toml is in use by process {os.getpid()}"):
        InstanceLock(la, "machine file a.toml").acquire()
    InstanceLock(lock_path(b_cfg, "mill", tmp_path / "s"), "b").acquire().release()
    first.release()
    InstanceLock(la, "machine file a.toml").acquire().release()


def _machine_file(tmp_path: Path, name: str, interface: str, modbus_simulated: bool,
                  drives_simulated: bool = False) -> str:
    text = (ROOT / "examples" / "canon.toml").read_text()
    text = text.replace('name = "example mill"', f'name = "{name}"', 1)
    text = text.replace('interface = "canon_local"', f'interface = "{interface}"', 1)
    text = text.replace('channel = "canon"', 'channel = "can0"', 1)
    if not drives_simulated:
        text = text.replace("simulate = true                # simulated drives", "simulate = false  # drives",
                            1)
    if not modbus_simulated:
        assert "simulate = true" in text.split("[[modbus.devices]]", 1)[1]
        head, tail = text.split("[[modbus.devices]]", 1)
        text = head + "[[modbus.devices]]" + tail.replace("simulate = true", "simulate = false", 1)
    path = tmp_path / f"{name}.toml"
    path.write_text(text)
    return str(path)


def test_two_machine_files_on_one_bus_are_refused(tmp_path: Path) -> None:
    """A second machine file naming the same CAN channel (or the same real Modbus module) is refused
    while the first holds it; python-can's in-process virtual bus is not a shared resource."""
    from motiond.cli import UserError
    from motiond.config import load_machine
    from motiond.instance_lock import lock_machine

    state = str(tmp_path / "s")

    def refused_while_held(first: str, second: str, holds: str) -> None:
        held = lock_machine(first, load_machine(first), state)
        with pytest.raises(UserError, match=rf"{holds} is in use by process {os.getpid()} \(for machine file "
                                            rf"{first}; "):
            lock_machine(second, load_machine(second), state)
        held.release()

    a = _machine_file(tmp_path, "mill-a", "socketcan", modbus_simulated=True)
    b = _machine_file(tmp_path, "mill-b", "socketcan", modbus_simulated=True)
    refused_while_held(a, b, "CAN bus socketcan can0")
    lock_machine(b, load_machine(b), state).release()  # free once the first let go
    # the same real Modbus module behind two machine files on the (in-process) virtual CAN bus
    c = _machine_file(tmp_path, "mill-c", "virtual", modbus_simulated=False)
    d = _machine_file(tmp_path, "mill-d", "virtual", modbus_simulated=False)
    refused_while_held(c, d, r"Modbus TCP 127\.0\.0\.1:\d+ unit \d+")
    # simulated Modbus and the virtual CAN bus live inside each process: no conflict
    e = _machine_file(tmp_path, "mill-e", "virtual", modbus_simulated=True)
    f = _machine_file(tmp_path, "mill-f", "virtual", modbus_simulated=True)
    both = [lock_machine(e, load_machine(e), state), lock_machine(f, load_machine(f), state)]
    for lock in both:
        lock.release()
    # canon's local bus crosses processes: real (not simulated) drives on it are locked like an adapter's;
    # simulated ones get a channel of their machine's own at run time, so nothing to lock
    g = _machine_file(tmp_path, "mill-g", "canon_local", modbus_simulated=True)
    h = _machine_file(tmp_path, "mill-h", "canon_local", modbus_simulated=True)
    refused_while_held(g, h, "CAN bus canon_local can0")
    i = _machine_file(tmp_path, "mill-i", "canon_local", modbus_simulated=True, drives_simulated=True)
    j = _machine_file(tmp_path, "mill-j", "canon_local", modbus_simulated=True, drives_simulated=True)
    both = [lock_machine(i, load_machine(i), state), lock_machine(j, load_machine(j), state)]
    for lock in both:
        lock.release()
