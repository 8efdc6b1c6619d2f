"""``[motion] process = "own"``: the motion side in a process of its own (issue 14, docs/daemon.md).

The configuration tests run anywhere. The others put the drives on udp_multicast, simulated in a
third process (``canon sim drives``), so they run only inside the private network namespace
(``tests/run``, ``tests/netns-run``): a program runs through the motion process; an E-stop reaches
the drives; killing the task process mid-move quick-stops the drives (the motion process sees its pipes
close); killing the motion process mid-move makes the drives fault by their heartbeat consumer and the
task side reports which process died and how; stopping either process (SIGSTOP: alive but hung)
trips the liveness watch of the other: tests/test_motion_process_watch.py. What the two share is in
tests/motion_process_helpers.py.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from motion_process_helpers import (
    LONG,
    ROOT,
    SHORT,
    TASK,
    Bench,
    drives_and_bench,
    end_task,
    fifo_allowed,
    group,
    machine_text,
    moving_machine,
    own_machine,
    own_mode,
    start_task,
    thread_policies,
    thread_policy,
    wait_for,
    write,
)
from test_canopen_multiprocess import DriveProcess

from fieldbus.canopen.cia402 import State
from motiond.configkit import ConfigError


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[tuple[Path, str, Bench]]:
    """The test machine file, its drives in a process of their own, the test's SDO bench."""
    with drives_and_bench(tmp_path) as r:
        yield r



def check(path: Path) -> str:
    from motiond.config_check import validate_machine

    with pytest.raises(ConfigError) as info:
        validate_machine(str(path))
    return str(info.value)


def test_own_process_on_the_virtual_bus_is_refused_with_the_key(tmp_path: Path) -> None:
    text = check(write(tmp_path, machine_text("virtual", "canon", simulate=True)))
    assert "motion.process" in text and "virtual" in text and "udp_multicast" in text, text


def test_own_process_with_the_io_map_and_a_touch_probe_is_accepted(tmp_path: Path) -> None:
    """The Modbus I/O, the I/O map and a drive's touch probe cross the boundary (docs/daemon.md)."""
    from motiond.config import load_machine
    from motiond.config_check import validate_machine
    from motiond.config_motion import motion_process

    path = tmp_path / "own.toml"
    path.write_text(own_mode((ROOT / "examples" / "canon.toml").read_text()))
    validate_machine(str(path))
    assert motion_process(load_machine(str(path))) == "own"


def test_an_unknown_process_mode_is_refused(tmp_path: Path) -> None:
    text = check(write(tmp_path, machine_text("udp_multicast", "239.74.165.1", simulate=True,
                                              process="fork")))
    assert "motion.process" in text and "thread, own" in text, text


def test_thread_mode_is_accepted_on_virtual(tmp_path: Path) -> None:
    from motiond.config import load_machine
    from motiond.config_motion import motion_process

    path = write(tmp_path, machine_text("virtual", "canon", simulate=True, process="thread"))
    assert motion_process(load_machine(str(path))) == "thread"


def test_auto_is_the_default_own_where_the_bus_crosses_processes_else_thread_saying_why(
        tmp_path: Path) -> None:
    """"auto": "own" on canon_local, udp_multicast and socketcan; "thread" on virtual, and where the
    machine has the Modbus I/O or a drive's touch probe (carried across when "own" is asked for
    explicitly: test_machine_io_e2e, test_touch_probe)."""
    from motiond.config import load_machine
    from motiond.config_check import describe, validate_machine
    from motiond.config_motion import motion_choice

    def choice(interface: str, channel: str, *, extra: str = "", z: str = "") -> tuple[str, str]:
        text = machine_text(interface, channel, simulate=True, process="auto", extra=extra)
        if z:
            text = text.replace("[canopen.axes.z]\nnode_id = 3\n", f"[canopen.axes.z]\nnode_id = 3\n{z}")
        path = write(tmp_path, text)
        c = motion_choice(load_machine(str(path)))
        return c.mode, c.reason

    assert choice("canon_local", "auto-test") == ("own", "the canon_local bus crosses processes")
    assert choice("udp_multicast", "239.74.165.1")[0] == "own"
    assert choice("socketcan", "vcan0")[0] == "own"
    assert choice("virtual", "canon") == ("thread", "the virtual bus does not cross processes")
    modbus = '\n[[modbus.devices]]\nname = "io"\nhost = "127.0.0.1"\nport = 1502\nsimulate = true\n'
    mode, why = choice("canon_local", "auto-test", extra=modbus)
    assert mode == "thread" and "[modbus]" in why and '"own" takes it when asked' in why, why
    mode, why = choice("canon_local", "auto-test", z="touch_probe = 1\n")
    assert mode == "thread" and "touch probe (axis z)" in why, why
    # no [motion] table: "auto"; the built-in demo machine is on canon_local but has its simulated
    # Modbus module: "thread" ("auto" keeps the I/O map beside the motion)
    path = write(tmp_path, machine_text("canon_local", "auto-test", simulate=True).split("[motion]")[0])
    assert motion_choice(load_machine(str(path))).mode == "own"
    demo = motion_choice(load_machine(None))
    assert (demo.mode, demo.asked) == ("thread", "auto") and "Modbus" in demo.reason, demo
    lines = " ".join(str(x) for x in describe(validate_machine(str(path))))
    assert 'motion side in its own process (process = "auto": the canon_local bus crosses processes)' in lines


def test_simulated_drives_out_of_the_motion_process_keep_the_configured_limits(tmp_path: Path) -> None:
    """The loosened limits for simulated drives (machine.SIM_*) only where the drives share the motion
    side's process ("thread"); with "own" they run in a third process and the master gets the
    configured heartbeat consumer, the 0.1 s TPDO limit and the late-cycle limit of real drives."""
    from fieldbus.canopen.config import CanopenConfig
    from motiond.config import load_machine
    from motiond.runtime import SIM_FEEDBACK_TIMEOUT_S, SIM_HEARTBEAT_CONSUMER_MS, SIM_LATE_FAULT_S, Machine

    own = Machine(load_machine(str(write(tmp_path, machine_text("canon_local", "limits", simulate=True,
                                                                   process="auto")))))
    assert own.motion_mode == "own" and not own.sim_shares_motion
    sent = own.motion.canopen  # what the motion process's master is made with
    assert sent.feedback_timeout_s == CanopenConfig.feedback_timeout_s == 0.1
    assert sent.heartbeat_consumer_ms == 1000  # the file's
    assert own.motion.late_fault_s == own.late_fault_s == 0.050  # ten 2 ms cycles, at least 50 ms
    assert sent.bus.channel.startswith("limits-") and sent.bus.channel != "limits"  # the machine's own
    thread = Machine(load_machine(str(write(tmp_path, machine_text("canon_local", "limits", simulate=True,
                                                                      process="thread")))))
    assert thread.motion_mode == "thread" and thread.sim_shares_motion
    assert thread.canopen.feedback_timeout_s == SIM_FEEDBACK_TIMEOUT_S
    assert thread.canopen.heartbeat_consumer_ms == SIM_HEARTBEAT_CONSUMER_MS
    assert thread.late_fault_s == SIM_LATE_FAULT_S
    # and there master and drives share the process: python-can's virtual bus, no sockets; canon_local
    # where the drives are in another process
    assert thread.canopen.bus.interface == "virtual" and sent.bus.interface == "canon_local"


@pytest.mark.timeout(180)
def test_a_program_runs_with_the_motion_and_the_drives_in_processes_of_their_own_on_the_local_bus(
        tmp_path: Path) -> None:
    """canon_local, anywhere (no network): "auto" puts the motion side in a child process and the
    simulated drives in another; a program runs through both."""
    path = write(tmp_path, machine_text("canon_local", f"run-{os.getpid()}", simulate=True, process="auto"))
    prog = tmp_path / "short.ngc"
    prog.write_text(SHORT)
    with own_machine(path) as m:
        pids = {os.getpid(), m.motion.pid, m.sim_bus.proc.pid}
        assert m.motion_mode == "own" and len(pids) == 3, pids
        m.bring_up()
        result = m.wait_job(m.run(str(prog)), 60.0)
        assert result is not None and result.ok, result.error if result is not None else "no result"
        wait_for(lambda: all(abs(a - c) < 0.01 for a, c in zip(m.motion.actual, (5.0, 4.0, 2.0),
                                                                  strict=True)), 5.0, "drives at the end")
        # at shutdown the pipes from the motion process are closed only after their readers ended (at
        # the pipes' end): closed under a reader's recv, it died with a TypeError on stderr
        readers_alive_at_close: list[bool] = []
        readers = [t for t in threading.enumerate() if t.name in ("canon-motion-out", "canon-motion-req")]
        assert len(readers) == 2, readers
        for name in ("out", "req"):
            conn = m.motion._conns[name]
            conn.close = lambda real=conn.close: (readers_alive_at_close.append(
                any(t.is_alive() for t in readers)), real())
    assert readers_alive_at_close == [False, False], readers_alive_at_close


def test_a_homed_axis_shows_its_new_coordinate_with_the_motion_in_its_own_process(tmp_path: Path) -> None:
    """Homing ("set": here is 0) rebases the commanded position in the motion process; when home()
    returns, the task's state already shows it. Before, the newest state here had been built before the
    new planner, and a status taken then showed the axis homed at its old coordinate."""
    path = write(tmp_path, machine_text("canon_local", f"home-{os.getpid()}", simulate=True))
    with own_machine(path) as m:
        m.bring_up()
        seen: list[tuple[bool, float]] = []  # (homed, commanded X) as a status would take them
        event = m.event

        def homed_event(*args: object, **kw: object) -> None:  # right after the axis is marked homed
            if kw.get("kind") == "homed":
                seen.append((m.homed[0], m.motion.commanded[0]))
            event(*args, **kw)

        m.event = homed_event  # type: ignore[method-assign]
        for x in (3.0, 5.0, 7.0):
            done = m.wait_job(m.mdi(f"G0 X{x:g}"), 30.0)
            assert done is not None and done.ok, done
            wait_for(lambda: m.states.state.value == "idle", 10.0, "IDLE after the MDI line")
            assert m.motion.commanded[0] == pytest.approx(x, abs=1e-9)
            m.home(["x"])
        assert seen == [(True, 0.0)] * 3, seen


def test_the_liveness_timeouts_default_and_are_checked_with_their_key(tmp_path: Path) -> None:
    from motiond.config import load_machine
    from motiond.config_motion import Watch, motion_settings

    path = write(tmp_path, machine_text("udp_multicast", "239.74.165.1", simulate=True))
    assert motion_settings(load_machine(str(path))) == ("own", Watch(500.0, 500.0))
    path = write(tmp_path, machine_text("udp_multicast", "239.74.165.1", simulate=True,
                                        extra="task_timeout_ms = 800\nmotion_timeout_ms = 300\n"))
    assert motion_settings(load_machine(str(path)))[1] == Watch(800.0, 300.0)
    bad = (("task_timeout_ms", "20"), ("motion_timeout_ms", "60000"), ("task_timeout_ms", '"1s"'))
    for key, value in bad:
        text = check(write(tmp_path, machine_text("udp_multicast", "239.74.165.1", simulate=True,
                                                  extra=f"{key} = {value}\n")))
        assert f"motion.{key}" in text, text


def test_the_motion_process_ranks_its_threads_below_a_realtime_cycle(monkeypatch) -> None:
    """``rank_threads``: SCHED_FIFO one below the cycle's priority for the calling thread (its later
    threads inherit it); nothing without a real-time cycle; a refusal is a warning, not an error."""
    from motiond.runtime import motion_proc

    calls: list[tuple[int, int, int]] = []
    monkeypatch.setattr(os, "sched_setscheduler", lambda pid, policy, param: calls.append(
        (pid, policy, param.sched_priority)))
    motion_proc.rank_threads(0)
    assert calls == []
    motion_proc.rank_threads(80)
    motion_proc.rank_threads(1)
    assert calls == [(0, os.SCHED_FIFO, 79), (0, os.SCHED_FIFO, 1)]

    def refuse(pid: int, policy: int, param: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    warned: list[str] = []  # the module's logger itself (caplog saw nothing once an earlier test of the
    # suite had reconfigured logging)

    class Log:
        def warning(self, fmt: str, *args: object) -> None:
            warned.append(fmt % args)

    monkeypatch.setattr(motion_proc, "log", Log())
    motion_proc.rank_threads(80)
    assert len(warned) == 1, warned
    assert "stay at normal priority" in warned[0] and "SCHED_FIFO 79" in warned[0], warned


@pytest.mark.multicast
@pytest.mark.timeout(120)
def test_a_program_runs_through_the_motion_process(rig, tmp_path: Path) -> None:
    path, _channel, bench = rig
    prog = tmp_path / "short.ngc"
    prog.write_text(SHORT)
    with own_machine(path) as m:
        assert m.motion_mode == "own"
        assert m.motion.pid not in (None, os.getpid())
        assert not any(t.name == "canon-cycle" for t in threading.enumerate()), "the cycle runs here"
        m.bring_up()
        result = m.wait_job(m.run(str(prog)), 60.0)
        assert result is not None and result.ok, result.error if result is not None else "no result"
        assert result.final_commanded == pytest.approx((5.0, 4.0, 2.0), abs=1e-6)
        assert m.motion.snapshot().cycle > 0 and m.cycle > 0
        wait_for(lambda: all(abs(a - c) < 0.01 for a, c in zip(m.motion.actual, (5.0, 4.0, 2.0),
                                                                  strict=True)), 5.0, "drives at the end")
        assert bench.states() == [State.OPERATION_ENABLED] * 3


@pytest.mark.multicast
@pytest.mark.timeout(120)
def test_a_program_right_after_an_mdi_line_runs_to_its_end(rig, tmp_path: Path) -> None:
    """The MDI line's end is told once, for its stream: a late one does not end the next job."""
    path, _channel, _bench = rig
    prog = tmp_path / "short.ngc"
    prog.write_text(SHORT)
    with own_machine(path) as m:
        m.bring_up()
        for x in (1.0, 2.0, 3.0):
            done = m.wait_job(m.mdi(f"G0 X{x:g}"), 30.0)
            assert done is not None and done.ok, done
            wait_for(lambda: m.states.state.value == "idle", 10.0, "IDLE after the MDI line")
            result = m.wait_job(m.run(str(prog)), 60.0)
            assert result is not None and result.ok, result
            assert result.final_commanded == pytest.approx((5.0, 4.0, 2.0), abs=1e-6), result.final_commanded


@pytest.mark.multicast
@pytest.mark.timeout(120)
def test_an_mdi_line_after_a_fault_while_idle_and_a_reset_runs(rig, tmp_path: Path) -> None:
    """A fault the motion process handles with no job running (as the I/O module's death while idle)
    fences its commands there; the task's next ones, after the reset, must still run (they were all
    discarded: the MDI line stayed "running" for ever)."""
    path, _channel, _bench = rig
    prog = tmp_path / "short.ngc"
    prog.write_text(SHORT)
    with own_machine(path) as m:
        m.bring_up()
        result = m.wait_job(m.run(str(prog)), 60.0)
        assert result is not None and result.ok, result
        wait_for(lambda: m.states.state.value == "idle", 10.0, "IDLE after the program")
        m.motion.post_fault("a test fault while idle", "test")
        wait_for(lambda: m.states.state.value == "faulted", 10.0, "the fault")
        m.reset()
        m.enable()
        done = m.wait_job(m.mdi("G0 X1"), 30.0)
        assert done is not None and done.ok, done
        assert done.final_commanded[0] == pytest.approx(1.0, abs=1e-6)


@pytest.mark.multicast
@pytest.mark.timeout(120)
def test_estop_on_the_urgent_pipe_stops_the_drives_mid_move(rig, tmp_path: Path) -> None:
    path, _channel, bench = rig
    prog = tmp_path / "long.ngc"
    prog.write_text(LONG)
    with own_machine(path) as m:
        m.bring_up()
        m.run(str(prog))
        wait_for(lambda: m.motion.commanded[0] > 5.0, 30.0, "moving")
        t0 = time.monotonic()
        m.estop()
        # the drives leave Operation enabled (quick stop; option 2 ends in Switch on disabled)
        wait_for(lambda: all(d.cia402_state != "operation_enabled" for d in m.motion.snapshot().drives),
                 2.0, "drives quick-stopped after the E-stop")
        took = time.monotonic() - t0
        assert m.states.state.value == "estop"
        x = m.motion.commanded[0]
        time.sleep(0.2)
        assert m.motion.commanded[0] == x, "the setpoints stopped"
        assert took < 2.0
        assert all(s is not State.OPERATION_ENABLED for s in bench.states())



@pytest.mark.multicast
@pytest.mark.timeout(120)
def test_every_thread_of_the_motion_process_runs_fifo_below_a_realtime_cycle(tmp_path: Path) -> None:
    """With ``realtime_priority``, the motion process's other threads (python-can's reader, the
    heartbeat, the pipes' threads) run SCHED_FIFO one below the cycle thread: an ordinary thread holding
    the interpreter lock, preempted by a busy process, would stall the cycle (priority inversion).
    The task's threads on the stop path (the pipes' readers, the hooks, the liveness ping) run two
    below it; the others of the task (here: the test's own) stay ordinary."""
    if not fifo_allowed():
        pytest.skip("SCHED_FIFO needs root or CAP_SYS_NICE")
    channel = group()
    text = machine_text("udp_multicast", channel, simulate=False, rt=20).replace(
        "simulate = false\n", "simulate = false\ncpu_latency_us = -1\n")
    path = write(tmp_path, text)
    drives = DriveProcess(path)
    stop_path = ("canon-hooks", "canon-motion-out", "canon-motion-req", "canon-motion-watch",
                 "canon-motion-ping")
    try:
        with own_machine(path) as m:
            policies = thread_policies(m.motion.pid)
            drive_policies = thread_policies(drives.proc.pid)
            wait_for(lambda: all(any(t.name == n for t in threading.enumerate()) for n in stop_path), 5.0,
                     "the task's stop-path threads")
            time.sleep(0.2)  # each ranks itself as it starts
            task = {t.name: thread_policy(t.native_id) for t in threading.enumerate()}
    finally:
        drives.stop()
    fifo = os.SCHED_FIFO
    assert len(policies) >= 5, policies  # the pipes' threads, python-can's reader, the cycle
    assert policies.count((fifo, 20)) == 1, policies  # the cycle thread
    assert all(p in ((fifo, 20), (fifo, 19)) for p in policies), policies
    assert all(task[n] == (fifo, 18) for n in stop_path), task
    # `canon sim drives` with the same file: hardware's stand-in, just below the cycle
    assert drive_policies and all(p == (fifo, 19) for p in drive_policies), drive_policies
    assert task[threading.current_thread().name] == (os.SCHED_OTHER, 0), task


def test_the_simulated_drives_process_runs_fifo_above_a_realtime_cycle(tmp_path: Path) -> None:
    """With ``realtime_priority`` the simulated drives' process (own mode) runs every thread at
    SCHED_FIFO one above the cycle: they stand in for hardware, which the PC never holds off; at
    ordinary priority two CPU hogs stalled them past their heartbeat watch (EMCY 0x8130 at enable),
    one below (level with the motion process's other threads) they missed TPDOs for 101 ms."""
    if not fifo_allowed():
        pytest.skip("SCHED_FIFO needs root or CAP_SYS_NICE")
    from motiond.config import load_machine
    from motiond.config_canopen import canopen_for_machine
    from motiond.runtime.sim_drives_proc import SimDrivesProcess

    text = machine_text("canon_local", f"fifo-{os.getpid()}", simulate=True, rt=20).replace(
        "simulate = true\n", "simulate = true\ncpu_latency_us = -1\n")
    canopen = canopen_for_machine(load_machine(str(write(tmp_path, text))))
    sim = SimDrivesProcess(canopen, 0.0)
    try:
        policies = thread_policies(sim.proc.pid)
    finally:
        sim.close()
    assert len(policies) >= 2, policies  # the main thread and the bus's reader at least
    assert all(p == (os.SCHED_FIFO, 21) for p in policies), policies


def test_the_motion_process_leaves_even_with_a_worker_thread_stuck() -> None:
    """The motion process's end does not wait for its non-daemon pool threads: a normal interpreter
    exit joins them, and one stuck there kept an orphaned motion process alive after its drives were
    off."""
    script = (
        "import concurrent.futures, threading\n"
        "from motiond.runtime.motion_proc import leave\n"
        "pool = concurrent.futures.ThreadPoolExecutor(1)\n"
        "pool.submit(threading.Event().wait)\n"  # stuck for good
        "print('leaving', flush=True)\n"
        "leave(3)\n")
    p = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True,
                       timeout=60)
    assert p.returncode == 3 and "leaving" in p.stdout, p.stderr



@pytest.mark.multicast
@pytest.mark.timeout(120)
def test_killing_the_task_process_mid_move_quick_stops_the_drives(rig, tmp_path: Path) -> None:
    path, _channel, bench = rig
    task = start_task(TASK, path, tmp_path)
    motion_pid = 0
    try:
        assert task.stdout is not None
        deadline = time.monotonic() + 60.0
        for line in task.stdout:
            if line.startswith("moving"):
                motion_pid = int(line.split()[1])
                break
            assert time.monotonic() < deadline, "the task never started moving"
        assert motion_pid, "the task process ended before moving"
        assert bench.states() == [State.OPERATION_ENABLED] * 3
        task.send_signal(signal.SIGKILL)
        task.wait(5.0)
        # the motion process quick-stops them (the program's 100 mm move was queued whole: without the
        # watch the drives would run it to its end, enabled); it still lives, its heartbeat with it, so
        # the drives are stopped by the master, not faulted by their heartbeat consumer
        states = bench.wait_states(lambda s: all(x in (State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED)
                                                 for x in s), 2.0, "quick stop after the task died")
        assert State.FAULT not in states
        # the quick stop's ramp ends in Switch on disabled (the standard layout's option code 2)
        states = bench.wait_states(lambda s: s == [State.SWITCH_ON_DISABLED] * 3, 3.0, "the ramp's end")
        os.kill(motion_pid, 0)  # alive, its heartbeat going
        before = [node.sdo[0x6064].raw for node in bench.nodes]
        time.sleep(0.3)
        assert [node.sdo[0x6064].raw for node in bench.nodes] == before, "the axes stand still"
        assert bench.states() == states, "no heartbeat fault later: the master is still there"
    finally:
        end_task(task, motion_pid)



@pytest.mark.multicast
@pytest.mark.timeout(120)
def test_killing_the_motion_process_mid_move_faults_the_drives_and_the_task(rig, tmp_path: Path) -> None:
    path, _channel, bench = rig
    with moving_machine(path, tmp_path) as (m, job):
        os.kill(m.motion.pid, signal.SIGKILL)
        wait_for(lambda: m.states.state.value == "faulted", 5.0, "the task side reports the fault")
        assert "motion process" in m.last_error and "SIGKILL" in m.last_error, m.last_error
        result = m.wait_job(job, 5.0)
        assert result is not None and not result.ok and "SIGKILL" in result.error
        # the drives miss the master's heartbeat (consumer 1000 ms): Fault, EMCY 0x8130
        bench.wait_states(lambda s: s == [State.FAULT] * 3, 5.0, "heartbeat consumer fault")
        assert [node.sdo[0x603F].raw for node in bench.nodes] == [0x8130] * 3


@pytest.mark.multicast
@pytest.mark.timeout(180)
def test_the_daemon_with_the_motion_process_answers_as_with_the_thread(tmp_path: Path) -> None:
    """The daemon's verbs and status, unchanged from outside: service operations (enable, jog, home)
    served in the motion process, a program, pause / resume, an E-stop and recovery; the simulated
    drives in a third process."""
    from test_daemon import Daemon

    from motiond.config import load_machine

    path = write(tmp_path, machine_text("udp_multicast", group(), simulate=True))
    # the drives out of the motion process keep the real 0.1 s TPDO limit by default; this test is about
    # the verbs, on a shared loaded PC: as own_machine
    d = Daemon(tmp_path, config=load_machine(str(path)), feedback_timeout_s=0.4)
    try:
        assert d.machine.motion_mode == "own" and d.machine.motion.pid != os.getpid()
        d.ready()
        d.ok("jog", ["y"], (20.0, 5.0))
        d.wait_status(lambda s: s.commanded[1] == 5.0 and s.state == "idle", what="jogged 5 mm")
        d.ok("home", ["x"])
        d.wait_status(lambda s: s.homed[0] and s.state == "idle", what="x homed")
        d.ok("mdi", ["G0 X2 Y0"])
        d.wait_status(lambda s: s.state == "idle" and tuple(s.commanded[:2]) == (2.0, 0.0), what="mdi")
        d.ok("run", [d.program(LONG)])
        d.wait_status(lambda s: s.state == "running" and s.commanded[0] > 10, what="running")
        d.ok("pause")
        d.wait_status(lambda s: s.state == "paused", what="paused")
        x = d.wait_status(lambda s: s.state == "paused" and not any(s.velocity), 10.0,
                          what="held").commanded[0]
        time.sleep(0.2)
        assert d.latest().commanded[0] == x
        d.ok("resume")
        d.wait_status(lambda s: s.state == "running" and s.commanded[0] > x + 1, what="resumed")
        d.ok("estop")
        s = d.wait_status(lambda s: s.state == "estop", what="estop")
        assert not s.enabled
        d.wait_event(lambda e: e.kind == "estop", what="estop")  # on its own channel: may come after
        d.ready()
        d.ok("mdi", ["G0 X1"])
        d.wait_status(lambda s: s.state == "idle" and s.commanded[0] == 1.0, what="moving after reset")
    finally:
        d.close()
    assert d.machine.motion.proc.exitcode == 0, "the motion process closed cleanly"


@pytest.mark.multicast
@pytest.mark.timeout(180)
def test_canon_run_with_the_motion_process(tmp_path: Path) -> None:
    """``canon run`` on a machine file with ``process = "own"``: same CLI, same summary; the motion
    in a child process, the simulated drives in another."""
    import json

    path = write(tmp_path, machine_text("udp_multicast", group(), simulate=True))
    prog = tmp_path / "short.ngc"
    prog.write_text(SHORT)
    r = subprocess.run([sys.executable, "-m", "motiond.cli", "run", "--json", "--no-telemetry",
                        "--config", str(path), str(prog)], capture_output=True, text=True, timeout=150,
                       cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert "no ping" not in r.stderr, r.stderr  # the close is not a silence of the task
    d = json.loads(r.stdout)
    assert d["ok"] and d["final_positions"] == {"x": 5.0, "y": 4.0, "z": 2.0}
    for a, want in zip("xyz", (5.0, 4.0, 2.0), strict=True):
        assert d["final_actual"][a] == pytest.approx(want, abs=1e-3)


@pytest.mark.multicast
@pytest.mark.timeout(180)
def test_estop_during_a_flood_reaches_the_drives_within_a_cycle_of_its_arrival(tmp_path: Path) -> None:
    """Another process floods the daemon's command server with 1,000 signed commands per second; an
    E-stop published meanwhile puts the machine in ESTOP within 50 ms, and in the motion process its
    quick stop goes to the drives within one cycle of the E-stop's arrival on the urgent pipe (the
    motion process's own record of both times and of its cycle count then)."""
    import random

    import lcm
    from keys import TEST_KEY
    from test_estop_flood import FLOOD

    from motiond.cmd_daemon import start
    from motiond.config import load_machine
    from telemetry.commands import make_command
    from telemetry.config import TelemetryConfig
    from telemetry.url import with_receive_buffer

    path = write(tmp_path, machine_text("udp_multicast", group(), simulate=True))
    url = with_receive_buffer(f"udpm://239.79.{random.randint(1, 250)}.{random.randint(1, 250)}:"
                              f"{random.randint(20000, 60000)}?ttl=0")
    lc = lcm.LCM(url)
    machine, server = start(load_machine(str(path)), lc, TelemetryConfig(url=url), key=TEST_KEY,
                            var_file=tmp_path / "p.var", late_fault_s=2.0, feedback_timeout_s=0.4)
    flood = None
    try:
        machine.bring_up()
        prog = tmp_path / "long.ngc"
        prog.write_text(LONG)  # 25 mm/s: a few frames lost on udp_multicast under load stay within
        # the simulated drives' setpoint-jump check (EMCY 0x8400 at 1.25 times max_velocity per period)
        machine.run(prog)
        flood = subprocess.Popen([sys.executable, "-c", FLOOD, url, TEST_KEY.hex(), "2.5"], cwd=ROOT,
                                 text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        assert flood.stdout is not None and flood.stdout.readline().startswith("flooding")
        time.sleep(1.0)
        assert machine.states.state.value == "running", machine.last_error
        assert machine.motion.commanded[0] > 1.0
        t0 = time.monotonic()
        lc.publish("CANON_COMMAND", make_command("estop", request_id=1, sender="operator",
                                                 key=TEST_KEY).encode())
        wait_for(lambda: machine.states.state.value == "estop", 2.0, "ESTOP")
        state_at = time.monotonic() - t0
        wait_for(lambda: machine.motion.last_estop is not None, 2.0, "the motion process's E-stop record")
        arrived, sent, cycle_then, cycle_after = machine.motion.last_estop
        still_flooding = flood.poll() is None
        wait_for(lambda: all(d.cia402_state != "operation_enabled" for d in machine.motion.snapshot().drives),
                 5.0, "the drives quick-stopped")
    finally:
        if flood is not None:
            flood.kill()
            flood.wait(5)
        server.stop()
        machine.shutdown()
    assert still_flooding, "the E-stop came in the middle of the flood"
    took = sent - t0
    print(f"ESTOP after {state_at * 1e3:.1f} ms, quick stop sent {took * 1e3:.1f} ms after the publish, "
          f"{(sent - arrived) * 1e3:.2f} ms after its arrival in the motion process")
    assert t0 < arrived <= sent
    assert took < 0.050 and state_at < 0.050
    # "within one cycle": at most one cycle of the motion process ran between the E-stop's arrival and
    # its quick stop (a wall-clock bound would count the whole process being descheduled on a loaded PC)
    assert cycle_after - cycle_then <= 1, (cycle_then, cycle_after)


