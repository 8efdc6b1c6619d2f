"""Progress of ``canon plan`` and ``canon check`` on a terminal (stderr on a pseudo-terminal): line,
percent, rate and time left; nothing with ``--json`` or when stderr is a pipe."""

from __future__ import annotations

import os
import pty
import re
import select
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def long_program(tmp_path: Path, lines: int = 10_000) -> Path:
    p = tmp_path / "long.ngc"
    body = [f"G1 X{(i % 200) * 0.5:.1f} Y{(i // 200) * 0.5:.1f}" for i in range(lines)]
    p.write_text("%\nG21 G90 G94 G64 P0.01 F3000\n" + "\n".join(body) + "\nM2\n%\n")
    return p


def run_on_pty(args: list[str], tmp_path: Path, timeout: float = 200.0) -> tuple[int, str, str]:
    """Run ``canon ARGS`` with stderr on a pseudo-terminal (stdout a file); what each received."""
    master, slave = pty.openpty()
    env = {**os.environ, "COLUMNS": "160", "TERM": "xterm"}
    stdout = (tmp_path / "stdout").open("w+b")
    p = subprocess.Popen([sys.executable, "-m", "motiond.cli", *args], stdout=stdout, stderr=slave,
                         stdin=subprocess.DEVNULL, cwd=ROOT, env=env)
    os.close(slave)
    chunks: list[bytes] = []
    deadline = time.monotonic() + timeout
    try:
        while time.monotonic() < deadline:
            ready, _, _ = select.select([master], [], [], 0.2)
            if ready:
                try:
                    data = os.read(master, 65536)
                except OSError:  # the child closed the terminal
                    break
                if not data:
                    break
                chunks.append(data)
            elif p.poll() is not None:
                break
        p.wait(timeout=max(1.0, deadline - time.monotonic()))
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
        os.close(master)
        stdout.seek(0)
        out = stdout.read()
        stdout.close()
    return p.returncode, out.decode(), b"".join(chunks).decode(errors="replace")


@pytest.mark.slow
@pytest.mark.parametrize("command", ["plan", "check"])
def test_progress_on_a_terminal(tmp_path: Path, command: str) -> None:
    # long enough that the bar is redrawn with a rate before the command ends: check reads some
    # hundred thousand lines a second
    lines = 10_000 if command == "plan" else 200_000
    prog = long_program(tmp_path, lines)
    rc, out, term = run_on_pty([command, str(prog)], tmp_path)
    assert rc == 0, term
    assert f"{'planning' if command == 'plan' else 'checking'} long.ngc" in term
    assert re.search(rf"line [\d,]+/{lines + 4:,}", term), term
    assert re.search(r"\d+%", term) and re.search(r"[\d,]+ lines/s", term) and "ETA" in term
    assert out  # the summary or the commands, on stdout as ever


@pytest.mark.slow
def test_no_progress_with_json_or_a_pipe(tmp_path: Path) -> None:
    prog = long_program(tmp_path, 5_000)
    rc, out, term = run_on_pty(["plan", "--json", str(prog)], tmp_path)
    assert rc == 0 and out.startswith("{") and "lines/s" not in term
    r = subprocess.run([sys.executable, "-m", "motiond.cli", "plan", str(prog)], capture_output=True,
                       text=True, timeout=300, cwd=ROOT)
    assert r.returncode == 0 and "lines/s" not in r.stderr
