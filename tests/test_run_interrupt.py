"""Ctrl-C and SIGTERM in ``canon run``: a jerk-limited stop on the path, the place to resume from, the
parameters saved.

One test interrupts a real ``canon run`` process (SIGINT, SIGTERM); one drives the same stop on an
in-process demo machine and checks the setpoints through ``Machine.trace``: the motion must come to
rest within the axes' acceleration limit, not be cut off at speed.
"""

from __future__ import annotations

import itertools
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from motiond.cmd_run import _interrupted, stop_report
from motiond.config import load_machine
from motiond.runtime import Machine

ROOT = Path(__file__).resolve().parent.parent

# line 5 moves X 100 mm at 10 mm/s: 10 s, far longer than the time the test waits before the signal
PROGRAM = """%
G21 G90 G94 G64 P0.01
#1000 = 42.5
G0 X0 Y0 Z0
G1 X100 F600
G1 Y100
M2
%
"""


def _read_until(stream: object, marker: str, timeout: float) -> tuple[bool, list[str]]:
    """Read lines from ``stream`` on a thread until one holds ``marker`` (or ``timeout``)."""
    lines: list[str] = []
    found = threading.Event()

    def reader() -> None:
        for line in stream:  # type: ignore[attr-defined]
            lines.append(line)
            if marker in line:
                found.set()
                return

    threading.Thread(target=reader, daemon=True).start()
    return found.wait(timeout), lines


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_stops_names_the_line_and_saves_parameters(tmp_path: Path, sig: signal.Signals) -> None:
    prog = tmp_path / "long.ngc"
    prog.write_text(PROGRAM)
    var = tmp_path / "p.var"
    # -v: the "started" event shows on stderr when the program has been handed to the machine
    p = subprocess.Popen([sys.executable, "-m", "motiond.cli", "-v", "run", "--no-telemetry", "--var",
                          str(var), str(prog)], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True)
    try:
        ok, head = _read_until(p.stderr, "started", 60.0)
        assert ok, "".join(head)
        time.sleep(3.0)  # well into line 5's 10 s move
        p.send_signal(sig)
        _out, err = p.communicate(timeout=60.0)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 130, err
    assert f"stopped at {prog}:5 (resume with --start-line 5)" in err
    assert f"parameters saved to {var}" in err
    assert "Traceback" not in err
    values = dict(line.split() for line in var.read_text().splitlines() if line.strip())
    assert float(values["1000"]) == 42.5


def test_stop_is_jerk_limited_and_reaches_rest(tmp_path: Path) -> None:
    m, prog = _cruising_machine(tmp_path)
    try:
        rc = _interrupted(m, str(prog))
    finally:
        m.shutdown()
    assert rc == 130
    _assert_stopped_within_limits(m)


def _cruising_machine(tmp_path: Path) -> tuple[Machine, Path]:
    """The demo machine running line 5 of PROGRAM at 100 mm/s on X (a stop cut at speed would show),
    ``trace`` recording the setpoints; the caller shuts it down."""
    prog = tmp_path / "long.ngc"
    prog.write_text(PROGRAM.replace("F600", "F6000"))
    m = Machine(load_machine(None), lc=None, var_file=tmp_path / "p.var")
    try:
        m.start()
        m.bring_up()
        m.trace = []
        m.run(prog)
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline:  # wait for cruise: 100 mm/s on X
            tr = m.trace
            if len(tr) > 2 and abs(tr[-1][2][0] - tr[-2][2][0]) / m.T > 99.0:
                return m, prog
            time.sleep(0.01)
        raise AssertionError("never reached 100 mm/s")
    except BaseException:
        m.shutdown()
        raise


def _assert_stopped_within_limits(m: Machine) -> None:
    """The stream ended at rest, and X never braked harder than its acceleration limit."""
    xs = [t[2][0] for t in m.trace]
    v = [(b - a) / m.T for a, b in itertools.pairwise(xs)]
    acc = [(b - a) / m.T for a, b in itertools.pairwise(v)]
    assert abs(v[-1]) < 0.01, f"the stream ended moving at {v[-1]:.1f} mm/s"
    assert max(abs(a) for a in acc) <= m.config.limits.axes[0].max_acceleration * 1.01


def test_stop_report_words() -> None:
    assert stop_report("p.ngc", ("p.ngc", 12)) == "stopped at p.ngc:12 (resume with --start-line 12)"
    assert "before the first motion" in stop_report("p.ngc", ("", 0))
    sub = stop_report("p.ngc", ("subs/drill.ngc", 3))
    assert sub.startswith("stopped at subs/drill.ngc:3, inside a subroutine") and "--start-line 3" not in sub


def test_daemon_sigterm_stops_on_the_path_before_shutting_down(tmp_path: Path) -> None:
    """The daemon's SIGTERM path (``stop_then_shutdown``): the program running at full speed comes to
    rest within the acceleration limit before the drives are disabled, not cut off at speed."""
    from motiond.cmd_daemon import stop_then_shutdown

    m, _prog = _cruising_machine(tmp_path)
    try:
        assert stop_then_shutdown(m)
    finally:
        m.shutdown()
    _assert_stopped_within_limits(m)


def test_a_signal_taken_by_another_thread_still_interrupts_the_wait() -> None:
    """The kernel may hand a process-directed SIGINT to any thread; the main thread, waiting for the
    job, must still see it at once (it waited on one unbounded lock and saw it only when the job ended:
    a Ctrl-C under load was ignored for the rest of the program)."""
    from motiond.cmd_run import wait_for_job

    class Job:
        done = threading.Event()
        result = "finished"

    class Machine:
        def wait_job(self, job: Job, timeout: float | None = None) -> object:
            return job.result if job.done.wait(timeout) else None

    job = Job()
    ends = threading.Timer(10.0, job.done.set)  # the job would end by itself after 10 s
    ends.start()
    other_ready = threading.Event()
    leave = threading.Event()

    def other() -> None:  # a thread of the process that takes the signal
        other_ready.set()
        leave.wait(20.0)

    t = threading.Thread(target=other, daemon=True)
    t.start()
    other_ready.wait(5.0)
    sender = threading.Timer(0.3, lambda: signal.pthread_kill(t.ident, signal.SIGINT))
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)  # Ctrl-C as canon run has it
    sender.start()
    t0 = time.monotonic()
    try:
        with pytest.raises(KeyboardInterrupt):
            wait_for_job(Machine(), job)
        assert time.monotonic() - t0 < 5.0  # long before the job's end
    finally:
        ends.cancel()
        sender.cancel()
        leave.set()
        signal.signal(signal.SIGINT, previous)
