"""``[motion] process = "own"``: the liveness watch between the task and the motion process
(``[motion] task_timeout_ms``, ``motion_timeout_ms``). Stopping either process (SIGSTOP: alive but
hung) trips the other's watch, in the private network namespace; and each watch trips on silence,
not on a stall of its own (anywhere, with a clock that jumps)."""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from motion_process_helpers import (
    TASK,
    Bench,
    drives_and_bench,
    end_task,
    moving_machine,
    start_task,
    wait_for,
)

from fieldbus.canopen.cia402 import State

WATCHED_TASK = TASK.replace("time.sleep(60)", """
deadline = time.monotonic() + 60
while m.states.state.value != "faulted" and time.monotonic() < deadline:
    time.sleep(0.01)
print("state", m.states.state.value, m.last_error, flush=True)
m.shutdown()
""")


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[tuple[Path, str, Bench]]:
    """The test machine file, its drives in a process of their own, the test's SDO bench."""
    with drives_and_bench(tmp_path) as r:
        yield r



def lines_of(proc: subprocess.Popen[str]) -> queue.Queue[str]:
    """The process's output lines, read by a thread (so that each wait for one is bounded)."""
    q: queue.Queue[str] = queue.Queue()

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            q.put(line)

    threading.Thread(target=read, daemon=True).start()
    return q


def next_line(q: queue.Queue[str], prefix: str, timeout: float) -> str:
    deadline = time.monotonic() + timeout
    seen = []
    while True:
        try:
            line = q.get(timeout=max(0.01, deadline - time.monotonic()))
        except queue.Empty:
            raise AssertionError(f"no line {prefix!r} in {timeout:g} s; saw {seen[-20:]}") from None
        if line.startswith(prefix):
            return line
        seen.append(line)


@pytest.mark.multicast
@pytest.mark.timeout(120)
def test_a_stopped_task_process_quick_stops_the_drives_and_is_told_when_it_runs_again(
        rig, tmp_path: Path) -> None:
    """SIGSTOP the task mid-move: alive, its pipes open, but no ping. The motion process quick-stops
    the drives within task_timeout_ms (500 ms by default) and a bound; SIGCONT: the task faults with
    the motion process's reason."""
    path, _channel, bench = rig
    task = start_task(WATCHED_TASK, path, tmp_path)
    motion_pid = 0
    try:
        out = lines_of(task)
        motion_pid = int(next_line(out, "moving", 60.0).split()[1])
        assert bench.states() == [State.OPERATION_ENABLED] * 3
        t0 = time.monotonic()
        task.send_signal(signal.SIGSTOP)
        # the 100 mm move takes 4 s: without the watch the drives would run on, enabled
        states = bench.wait_states(lambda s: all(x in (State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED)
                                                 for x in s), 3.0, "quick stop after the task stopped")
        took = time.monotonic() - t0
        assert State.FAULT not in states
        assert took < 0.5 + 2.0, took  # the timeout, plus the SDO reads of a loaded PC
        bench.wait_states(lambda s: s == [State.SWITCH_ON_DISABLED] * 3, 3.0, "the ramp's end")
        os.kill(motion_pid, 0)  # alive, its heartbeat going: stopped by the master, not by a fault
        task.send_signal(signal.SIGCONT)
        line = next_line(out, "state", 30.0)
        assert line.startswith("state faulted"), line
        assert "task process" in line and "no ping" in line and "quick-stopped" in line, line
        assert task.wait(30.0) == 0
    finally:
        end_task(task, motion_pid)


@pytest.mark.multicast
@pytest.mark.timeout(120)
def test_a_stopped_motion_process_faults_the_task_naming_it(rig, tmp_path: Path) -> None:
    """SIGSTOP the motion process mid-move: its states stop while it lives. The task faults within
    motion_timeout_ms and a bound, naming the motion process and how long it was silent; the drives
    fault by their heartbeat consumer (the master is stopped too)."""
    path, _channel, bench = rig
    with moving_machine(path, tmp_path) as (m, job):
        pid = m.motion.pid
        t0 = time.monotonic()
        os.kill(pid, signal.SIGSTOP)
        try:
            wait_for(lambda: m.states.state.value == "faulted", 0.5 + 2.0, "the task side faults")
            assert time.monotonic() - t0 >= 0.5, "not before motion_timeout_ms"
            err = m.last_error
            assert f"motion process (pid {pid})" in err and "no state for" in err, err
            silent_ms = float(err.split("no state for ")[1].split(" ms")[0])
            assert 500 <= silent_ms < 2500, err
            result = m.wait_job(job, 5.0)
            assert result is not None and not result.ok
            assert m.motion.proc.is_alive()
            bench.wait_states(lambda s: s == [State.FAULT] * 3, 5.0, "heartbeat consumer fault")
        finally:
            os.kill(pid, signal.SIGCONT)


# ---------------------------------------------------------------------- the watch's own stalls (anywhere)

class Clock:
    """``time`` for a watch under test: monotonic with jumps (the watcher's process stalled)."""

    def __init__(self) -> None:
        self.offset = 0.0
        self.sleep = time.sleep

    def monotonic(self) -> float:
        return time.monotonic() + self.offset


class Recorder:
    """Stands in for the motion core or the task hooks: records the calls."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, tuple[object, ...]]] = []

    def __getattr__(self, name: str):
        return lambda *args, **kw: self.calls.append((name, args))

    def names(self) -> list[str]:
        return [c[0] for c in self.calls]


def test_the_motion_process_watch_trips_on_silence_not_on_its_own_stall(monkeypatch) -> None:
    """The motion process's watch: not before the first ping; not when it was itself away (a jump
    of its clock past the timeout, the pings then on time); on silence, the quick stop and a fault."""
    from motiond.runtime import motion_proc

    clock = Clock()
    monkeypatch.setattr(motion_proc, "time", clock)
    server = object.__new__(motion_proc.MotionServer)
    server.done, server.orphaned = threading.Event(), threading.Event()
    server.task_timeout_s, server.last_ping, server.task_silent, server.closing = 1.0, 0.0, False, False
    server.silent_disabled = False
    server.core = core = Recorder()
    core.master = master = Recorder()
    threading.Thread(target=server._watch, daemon=True).start()
    try:
        time.sleep(1.3)
        assert core.calls == [], "tripped before the first ping"

        pinged = [0.0]  # wall time of the last ping: the silence is counted from it

        def ping_for(seconds: float) -> None:
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                pinged[0] = time.monotonic()  # before the ping: the watch counts from no earlier
                server.last_ping = clock.monotonic()
                time.sleep(0.05)

        ping_for(0.3)
        clock.offset += 2.0  # the whole process away 2 s: the pings waited in the pipe
        time.sleep(0.1)
        ping_for(0.3)
        assert core.calls == [], "its own stall counted as the task's silence"
        wait_for(lambda: "post_fault" in core.names(), 1.0 + 2.0, "the watch trips on silence")
        # not before the timeout after the last ping (counted from the test's loop, not from its end:
        # under load the loop's last sleep overran, and the watch rightly tripped 0.94 s after it)
        assert time.monotonic() - pinged[0] >= 1.0
        assert core.names()[0] == "quick_stop"
        reason = dict(core.calls)["post_fault"][0]
        assert "task process" in reason and "no ping for" in reason and "task_timeout_ms 1000" in reason
        assert master.calls == [], "disabled at once: held first"
        # still silent ORPHAN_HOLD_S later (1 s here, 30 s in service): the held drives are disabled,
        # as for a dead task
        monkeypatch.setattr(motion_proc, "ORPHAN_HOLD_S", 1.0)
        wait_for(lambda: "disable" in master.names(), 5.0, "the drives disabled after the long silence")
        assert time.monotonic() - pinged[0] >= 2.0
        assert master.names() == ["disable"]
    finally:
        server.done.set()


def test_the_task_watch_faults_on_silence_not_on_its_own_stall(monkeypatch) -> None:
    """The task's watch of the motion process's states: not when the task itself was away (a clock
    jump past the timeout); on silence of a live process, a quick stop sent and the fault naming it;
    requests fail at once meanwhile; states again: re-armed."""
    from types import SimpleNamespace

    from motiond.config_motion import Watch
    from motiond.runtime import motion_link, motion_proxy

    clock = Clock()
    monkeypatch.setattr(motion_proxy, "time", clock)  # the states' arrival
    monkeypatch.setattr(motion_link, "time", clock)  # the watch
    hooks = Recorder()
    p = motion_proxy.MotionProxy(SimpleNamespace(names=("x",)), None, late_fault_s=1.0, simulated=True,
                                 hooks=hooks, watch=Watch(1000.0, 1000.0))  # type: ignore[arg-type]
    p.proc = SimpleNamespace(pid=4242)
    p._conns = {"req": None}  # no pipes: the urgent calls go nowhere, requests as if open
    sent: list[str] = []
    p._urgent = lambda name, *args: sent.append(name)  # type: ignore[method-assign]
    threading.Thread(target=p._ping, daemon=True).start()

    def states_for(seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            p._take_state({"late_new": [], "stream": None})
            time.sleep(0.02)

    try:
        states_for(0.3)
        clock.offset += 2.0  # the task process away 2 s: the states waited in the pipe
        time.sleep(0.2)
        states_for(0.3)
        assert not p.silent and "quick_stop" not in sent, p.silent
        assert "ping" in sent
        t0 = time.monotonic()
        wait_for(lambda: p.silent, 1.0 + 2.0, "the task's watch trips")
        assert time.monotonic() - t0 >= 1.0 - 0.05
        assert "quick_stop" in sent
        assert "motion process (pid 4242)" in p.silent and "no state for" in p.silent, p.silent
        with pytest.raises(motion_proxy.MotionProcessGone, match="no state for"):
            p.request("position", timeout=0.1)
        p._dispatch.get(timeout=1.0)()  # the fault hook, as the canon-hooks thread runs it
        assert hooks.calls == [("fault", (p.silent, "motiond"))]
        n = sent.count("ping")
        time.sleep(0.3)
        assert sent.count("ping") == n, "no pings into the pipe of a hung process"
        states_for(0.3)
        assert not p.silent and sent.count("ping") > n, "re-armed when the states run again"
    finally:
        p._closing = True
