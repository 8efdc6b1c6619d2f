"""``[motion] process = "own"``: the motion side in a process of its own (issue 14, docs/daemon.md).

The configuration tests run anywhere. The others put the drives on udp_multicast, simulated in a
third process (``canon sim drives``), so they run only inside the private network namespace
(``tests/run``, ``tests/netns-run``): a program runs through the motion process; an E-stop reaches
the drives; killing the task process mid-move quick-stops the drives (the motion process sees its pipes
close); killing the motion process mid-move makes the drives fault by their heartbeat consumer and the
task side reports which process died and how.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from test_canopen_multiprocess import DriveProcess

from fieldbus.canopen.cia402 import State, decode
from motiond.configkit import ConfigError

ROOT = Path(__file__).resolve().parent.parent

LONG = "%\nG21 G90 G94\nG1 X100 F1500\nG1 X0\nM2\n%\n"
SHORT = "%\nG21 G90 G94\nG1 X5 Y4 Z2 F1500\nM2\n%\n"


def machine_text(interface: str, channel: str, *, simulate: bool, process: str = "own",
                 extra: str = "") -> str:
    axes = "".join(f"""
[axes.{a}]
max_velocity = {v}
max_acceleration = 2000.0
max_jerk = 50000.0
quick_stop_deceleration = 5000.0
""" for a, v in (("x", 200.0), ("y", 200.0), ("z", 100.0)))
    drives = "".join(f"\n[canopen.axes.{a}]\nnode_id = {i + 1}\n" for i, a in enumerate("xyz"))
    return f"""[machine]
name = "two processes"
cycle_ms = 2.0
{axes}
[canopen]
interface = "{interface}"
channel = "{channel}"
heartbeat_producer_ms = 100
heartbeat_consumer_ms = 500
simulate = {str(simulate).lower()}
{drives}
[motion]
process = "{process}"
{extra}"""


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "machine.toml"
    p.write_text(text)
    return p


# ---------------------------------------------------------------------- configuration (anywhere)

def check(path: Path) -> str:
    from motiond.config_check import validate_machine

    with pytest.raises(ConfigError) as info:
        validate_machine(str(path))
    return str(info.value)


def test_own_process_on_the_virtual_bus_is_refused_with_the_key(tmp_path: Path) -> None:
    text = check(write(tmp_path, machine_text("virtual", "canon", simulate=True)))
    assert "motion.process" in text and "virtual" in text and "udp_multicast" in text, text


def test_own_process_with_modbus_io_is_refused(tmp_path: Path) -> None:
    extra = '\n[[modbus.devices]]\nname = "io"\nhost = "127.0.0.1"\nport = 1502\n'
    text = check(write(tmp_path, machine_text("udp_multicast", "239.74.165.1", simulate=True, extra=extra)))
    assert "motion.process" in text and "Modbus" in text, text


def test_an_unknown_process_mode_is_refused(tmp_path: Path) -> None:
    text = check(write(tmp_path, machine_text("udp_multicast", "239.74.165.1", simulate=True,
                                              process="fork")))
    assert "motion.process" in text and "thread, own" in text, text


def test_thread_mode_is_the_default_and_accepted_on_virtual(tmp_path: Path) -> None:
    from motiond.config import load_machine
    from motiond.config_motion import motion_process

    assert motion_process(load_machine(None)) == "thread"
    path = write(tmp_path, machine_text("virtual", "canon", simulate=True, process="thread"))
    assert motion_process(load_machine(str(path))) == "thread"


# ---------------------------------------------------------------------- in the namespace

multicast = [pytest.mark.multicast, pytest.mark.timeout(120)]


def group() -> str:
    return f"239.74.166.{1 + os.getpid() % 250}"


class Bench:
    """The test's own CANopen client on the drives' bus (SDO reads only, as a bench on a real bus)."""

    def __init__(self, channel: str) -> None:
        import canopen

        from fieldbus.canopen import SHIPPED_EDS
        from fieldbus.canopen.config import CanBusConfig

        self.network = canopen.Network()
        self.network.connect(**CanBusConfig("udp_multicast", channel).bus_kwargs())  # hop_limit 0
        self.nodes = []
        for node_id in (1, 2, 3):
            node = self.network.add_node(node_id, str(SHIPPED_EDS))
            node.sdo.RESPONSE_TIMEOUT = 1.0  # a loaded PC; udp_multicast may lose a frame: retry
            node.sdo.MAX_RETRIES = 3
            self.nodes.append(node)

    def states(self) -> list[State]:
        return [decode(node.sdo[0x6041].raw) for node in self.nodes]

    def wait_states(self, ok: object, timeout: float, what: str) -> list[State]:
        deadline = time.monotonic() + timeout
        seen: list[State] = []
        while time.monotonic() < deadline:
            seen = self.states()
            if ok(seen):  # type: ignore[operator]
                return seen
            time.sleep(0.02)
        raise AssertionError(f"{what}: drives in {seen}")

    def close(self) -> None:
        self.network.disconnect()


@pytest.fixture
def rig(tmp_path: Path):
    channel = group()
    path = write(tmp_path, machine_text("udp_multicast", channel, simulate=False))
    drives = DriveProcess(path)
    bench = Bench(channel)
    yield path, channel, bench
    bench.close()
    drives.stop()


def own_machine(path: Path):
    from motiond.config import load_machine
    from motiond.runtime import Machine

    return Machine(load_machine(str(path)), late_fault_s=0.5)


def wait_for(cond: object, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not cond():  # type: ignore[operator]
        if time.monotonic() > deadline:
            raise AssertionError(what)
        time.sleep(0.01)


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
        assert result is not None and result.ok, result
        assert result.final_commanded == pytest.approx((5.0, 4.0, 2.0), abs=1e-6)
        assert m.motion.snapshot().cycle > 0 and m.cycle > 0
        wait_for(lambda: all(abs(a - c) < 0.01 for a, c in zip(m.motion.actual, (5.0, 4.0, 2.0),
                                                                  strict=True)), 5.0, "drives at the end")
        assert bench.states() == [State.OPERATION_ENABLED] * 3


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


TASK = """
import sys, time
from motiond.config import load_machine
from motiond.runtime import Machine
m = Machine(load_machine(sys.argv[1]), late_fault_s=0.5).start()
m.bring_up()
m.run(sys.argv[2])
while m.motion.commanded[0] < 5.0:
    time.sleep(0.01)
print("moving", m.motion.pid, flush=True)
time.sleep(60)
"""


@pytest.mark.multicast
@pytest.mark.timeout(120)
def test_killing_the_task_process_mid_move_quick_stops_the_drives(rig, tmp_path: Path) -> None:
    path, _channel, bench = rig
    prog = tmp_path / "long.ngc"
    prog.write_text(LONG)
    task = subprocess.Popen([sys.executable, "-c", TASK, str(path), str(prog)], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
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
        os.kill(motion_pid, 0)  # alive, holding
        before = [node.sdo[0x6064].raw for node in bench.nodes]
        time.sleep(0.3)
        assert [node.sdo[0x6064].raw for node in bench.nodes] == before, "the axes stand still"
        assert bench.states() == states
    finally:
        if task.poll() is None:
            task.kill()
            task.wait(5.0)
        if motion_pid:
            with contextlib.suppress(ProcessLookupError):
                os.kill(motion_pid, signal.SIGKILL)


@pytest.mark.multicast
@pytest.mark.timeout(120)
def test_killing_the_motion_process_mid_move_faults_the_drives_and_the_task(rig, tmp_path: Path) -> None:
    path, _channel, bench = rig
    prog = tmp_path / "long.ngc"
    prog.write_text(LONG)
    with own_machine(path) as m:
        m.bring_up()
        job = m.run(str(prog))
        wait_for(lambda: m.motion.commanded[0] > 5.0, 30.0, "moving")
        os.kill(m.motion.pid, signal.SIGKILL)
        wait_for(lambda: m.states.state.value == "faulted", 3.0, "the task side reports the fault")
        assert "motion process" in m.last_error and "SIGKILL" in m.last_error, m.last_error
        result = m.wait_job(job, 5.0)
        assert result is not None and not result.ok and "SIGKILL" in result.error
        # the drives miss the master's heartbeat (consumer 500 ms): Fault, EMCY 0x8130
        bench.wait_states(lambda s: s == [State.FAULT] * 3, 3.0, "heartbeat consumer fault")
        assert [node.sdo[0x603F].raw for node in bench.nodes] == [0x8130] * 3
