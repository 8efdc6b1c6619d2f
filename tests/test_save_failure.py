"""Nothing lost when the parameter file cannot be saved (a full disk), and no stray temporary files.

The disk is a small tmpfs mounted by the test (root only; skipped otherwise, saying why), filled to
the last byte. A program's save at M2 fails: an ERROR event names the .var file (not the M2 line), the
values stay in memory and the next program end saves them once there is room. A daemon that cannot
save at shutdown exits 1 naming the file. Temporary files of interrupted saves go at the next start.
"""

from __future__ import annotations

import contextlib
import errno
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from keys import TEST_KEY

from gcode_canon.atomicfile import remove_stray_temps
from gcode_canon.paramfile import read_parameter_file

ROOT = Path(__file__).resolve().parent.parent


class Disk:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.filler = path / "filler"

    def fill(self) -> None:
        with open(self.filler, "ab", buffering=0) as fh:
            for _ in range(100_000):  # bounded: the tmpfs is 256 kB
                try:
                    fh.write(b"\0" * 512)
                except OSError as exc:
                    assert exc.errno == errno.ENOSPC
                    return
        raise AssertionError("the small tmpfs never filled up")

    def free(self) -> None:
        self.filler.unlink()


@pytest.fixture
def disk(tmp_path: Path) -> Iterator[Disk]:
    if os.geteuid() != 0:
        reason = "needs root to mount a small tmpfs that can be filled (a full disk)"
        print(f"skipped: {reason}")
        pytest.skip(reason)
    mnt = tmp_path / "disk"
    mnt.mkdir()
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k,mode=0755", "tmpfs", str(mnt)],
                         capture_output=True, text=True, timeout=20)
    if res.returncode != 0:
        reason = f"cannot mount a tmpfs here: {res.stderr.strip()}"
        print(f"skipped: {reason}")
        pytest.skip(reason)
    try:
        yield Disk(mnt)
    finally:
        if subprocess.run(["umount", str(mnt)], capture_output=True, timeout=20).returncode != 0:
            subprocess.run(["umount", "-l", str(mnt)], capture_output=True, timeout=20)


PROGRAM = "G10 L2 P1 X5 Y-2\n#31 = 7.5\nG0 X1\nM2\n"


def test_a_failed_save_at_m2_keeps_the_values_reports_and_saves_at_the_next_end(disk: Disk,
                                                                              tmp_path: Path) -> None:
    from motiond.cmd_daemon import start
    from motiond.config import load_machine
    from motiond.control_client import shared_memq
    from telemetry.config import TelemetryConfig
    from telemetry.lcmtypes.canon import event

    lc = shared_memq()
    events: list[Any] = []
    sub = lc.subscribe("CANON_EVENT", lambda _c, d: events.append(event.decode(d)))
    var = disk.path / "p.var"
    machine, server = start(load_machine(None), lc, TelemetryConfig(url="memq://"), key=TEST_KEY,
                            var_file=var, programs=[tmp_path], late_fault_s=2.0)
    stop = threading.Event()

    def pump() -> None:  # the server's thread handles lc; events arrive through it
        while not stop.is_set():
            time.sleep(0.05)

    try:
        machine.bring_up()
        end = tmp_path / "end.ngc"
        end.write_text("M2\n")
        assert machine.wait_job(machine.run(end), 30).ok
        assert var.exists()  # saved once while there was room
        before = var.read_bytes()
        disk.fill()
        prog = tmp_path / "offsets.ngc"
        prog.write_text(PROGRAM)
        result = machine.wait_job(machine.run(prog), 30)
        assert result is not None and result.ok  # the program itself ran
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and not [e for e in events if e.kind == "save_failed"]:
            time.sleep(0.02)
        failed = [e for e in events if e.kind == "save_failed"]
        assert failed and failed[0].severity == event.ERROR
        assert failed[0].file == str(var) and failed[0].line == 0  # the .var file, not the M2 line
        assert "No space left on device" in failed[0].text and "kept in memory" in failed[0].text
        assert var.read_bytes() == before  # the old file intact
        assert sorted(p.name for p in disk.path.iterdir()) == ["filler", "p.var", "p.var.bak"] or \
            sorted(p.name for p in disk.path.iterdir()) == ["filler", "p.var"]  # no temporary left
        assert machine.interp.parameter(5221) == 5.0 and machine.interp.parameter(31) == 7.5  # in memory
        disk.free()
        assert machine.wait_job(machine.run(end), 30).ok  # the next save point
        saved = read_parameter_file(var)
        assert (saved[5221], saved[5222], saved[31]) == (5.0, -2.0, 7.5)
        assert machine.interp.save_error is None
    finally:
        stop.set()
        server.stop()
        machine.shutdown()
        lc.unsubscribe(sub)
    assert not machine.save_error


def test_daemon_exits_1_naming_the_file_when_it_cannot_save_at_shutdown(disk: Disk, tmp_path: Path) -> None:
    var = disk.path / "p.var"
    stray = [disk.path / ".p.var.0123456789ab.tmp", disk.path / ".p.var.ba9876543210.bak.tmp"]
    for f in stray:
        f.write_text("half a save")
        os.utime(f, (time.time() - 3600, time.time() - 3600))
    young = disk.path / ".p.var.00000000abcd.tmp"  # a save in progress elsewhere: left alone
    young.write_text("x")
    proc = subprocess.Popen([sys.executable, "-m", "motiond.cli", "daemon", "--url", "memq://",
                             "--var", str(var), "--state-dir", str(tmp_path)], cwd=ROOT, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    lines: list[str] = []
    try:
        assert proc.stdout is not None
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if "canon daemon: machine" in line:
                break
        assert any("canon daemon: machine" in line for line in lines), "".join(lines)
        assert not any(f.exists() for f in stray) and young.exists()
        young.unlink()
        disk.fill()
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=60)
    finally:
        with contextlib.suppress(ProcessLookupError):
            proc.kill()
        proc.wait(10)
    text = "".join(lines) + out
    assert proc.returncode == 1, text
    assert (f"canon daemon: parameters NOT saved at shutdown: {var}: cannot save the parameter file: "
            "No space left on device") in text
    assert "Traceback" not in text


def test_remove_stray_temps_only_touches_old_temporary_files_of_that_file(tmp_path: Path) -> None:
    var = tmp_path / "m.var"
    old = [tmp_path / ".m.var.0123456789ab.tmp", tmp_path / ".m.var.0123456789ab.bak.tmp"]
    keep = [tmp_path / ".m.var.0123456789ab.txt", tmp_path / ".other.var.0123456789ab.tmp",
            tmp_path / ".m.var.notours.tmp", tmp_path / "m.var"]
    for f in old + keep:
        f.write_text("x")
        os.utime(f, (time.time() - 3600, time.time() - 3600))
    fresh = tmp_path / ".m.var.fedcba987654.tmp"
    fresh.write_text("x")
    assert sorted(remove_stray_temps(var)) == sorted(str(f) for f in old)
    assert all(f.exists() for f in [*keep, fresh])
