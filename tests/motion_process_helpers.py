"""What the motion-process tests share (``[motion] process = "own"``): the test machine file, the
drives simulated in a process of their own on udp_multicast with the test's SDO bench beside them
(``drives_and_bench``, behind each module's ``rig`` fixture), the own-mode rewrite of a machine file,
the task process's script, and the scheduling probes."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from test_canopen_multiprocess import DriveProcess

from fieldbus.canopen.cia402 import State, decode

ROOT = Path(__file__).resolve().parent.parent

LONG = "%\nG21 G90 G94\nG1 X100 F1500\nG1 X0\nM2\n%\n"
SHORT = "%\nG21 G90 G94\nG1 X5 Y4 Z2 F1500\nM2\n%\n"


def machine_text(interface: str, channel: str, *, simulate: bool, process: str = "own",
                 extra: str = "", rt: int = 80) -> str:
    """The test machine: ``rt``, the cycle's SCHED_FIFO priority (realtime_priority), as a machine on
    a busy PC is configured (own_mode says why; refused when not root, and the test runs as it is)."""
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
heartbeat_consumer_ms = 1000
sdo_timeout_s = 1.0
realtime_priority = {rt}
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
def group() -> str:
    return f"239.74.166.{1 + os.getpid() % 250}"


def own_mode(text: str) -> str:
    """A machine file's ``text`` (simulated drives on the virtual bus) with the motion in a process of
    its own: the simulated drives then run in a third process, on udp_multicast (the namespace only),
    answering SDO within 1 s as this file's machine (a loaded PC, udp_multicast). The thread-mode
    tests of the I/O map and the probes run their bodies on it too.

    With a SCHED_FIFO cycle (``realtime_priority``), as a machine on a busy PC is configured: the
    master keeps real drives' limits here (a TPDO 100 ms late is a fault), and at normal priority two
    CPU hogs stalled the drives' process or the master's reader past it ("no TPDO for 102-107 ms") and
    the task's ping past the 500 ms watch. Not root: refused, logged, and the test runs as it is."""
    lines = [line for line in text.splitlines() if not line.startswith(("interface =", "channel ="))]
    lines = [line for line in lines if not line.startswith(("sdo_timeout_s =", "realtime_priority ="))]
    out = "\n".join(lines).replace("[canopen]\n", f'[canopen]\ninterface = "udp_multicast"\n'
                                                 f'channel = "{group()}"\nsdo_timeout_s = 1.0\n'
                                                 'realtime_priority = 80\n', 1)
    return out + '\n[motion]\nprocess = "own"\n'


OWN = pytest.param("own", marks=[pytest.mark.multicast, pytest.mark.timeout(180)])
"""The ``own`` case of a test parametrized over the motion's process mode."""


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


@contextlib.contextmanager
def drives_and_bench(tmp_path: Path) -> Iterator[tuple[Path, str, Bench]]:
    """The test machine file (drives not simulated by the machine), its drives simulated in a process
    of their own on a udp_multicast group, and the test's SDO bench on that group: what each module's
    ``rig`` fixture yields. Both are stopped at the end, also when the bench fails to connect."""
    channel = group()
    path = write(tmp_path, machine_text("udp_multicast", channel, simulate=False))
    drives = DriveProcess(path)
    try:
        bench = Bench(channel)
        try:
            yield path, channel, bench
        finally:
            bench.close()
    finally:
        drives.stop()


def own_machine(path: Path):
    from motiond.config import load_machine
    from motiond.runtime import Machine

    # as tests/test_end_to_end.py's daemon: generous, the test PC is shared and loaded
    return Machine(load_machine(str(path)), late_fault_s=1.0, feedback_timeout_s=0.4)


def wait_for(cond: object, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not cond():  # type: ignore[operator]
        if time.monotonic() > deadline:
            raise AssertionError(what)
        time.sleep(0.01)


def fifo_allowed() -> bool:
    """Whether this process may use SCHED_FIFO (tried on a thread of its own, which then ends)."""
    ok: list[bool] = []

    def probe() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
            ok.append(True)
        except (AttributeError, OSError):
            ok.append(False)

    t = threading.Thread(target=probe)
    t.start()
    t.join()
    return ok[0]


def thread_policies(pid: int) -> list[tuple[int, int]]:
    """(policy, real-time priority) of each thread of ``pid`` (/proc/PID/task/TID/stat)."""
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(OSError):
            out.append(task_policy(task))
    return out


def task_policy(task: Path) -> tuple[int, int]:
    """(policy, real-time priority) of the thread whose /proc directory is ``task``."""
    fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
    return int(fields[38]), int(fields[37])


def thread_policy(native_id: int | None) -> tuple[int, int]:
    """(policy, real-time priority) of this process's thread ``native_id`` (-1, -1: gone)."""
    try:
        return task_policy(Path(f"/proc/self/task/{native_id}"))
    except OSError:
        return -1, -1

TASK = """
import sys, time
from motiond.config import load_machine
from motiond.runtime import Machine
m = Machine(load_machine(sys.argv[1]), late_fault_s=1.0, feedback_timeout_s=0.4).start()
m.bring_up()
m.run(sys.argv[2])
while m.motion.commanded[0] < 5.0:
    time.sleep(0.01)
print("moving", m.motion.pid, flush=True)
time.sleep(60)
"""


def start_task(script: str, path: Path, tmp_path: Path) -> subprocess.Popen[str]:
    """A task process running ``script`` (TASK ...) on the machine file, the long program."""
    prog = tmp_path / "long.ngc"
    prog.write_text(LONG)
    return subprocess.Popen([sys.executable, "-c", script, str(path), str(prog)], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)

def end_task(task: subprocess.Popen[str], motion_pid: int) -> None:
    """The task process (continued, if stopped) and its motion process: killed if still there."""
    with contextlib.suppress(ProcessLookupError):
        task.send_signal(signal.SIGCONT)
    if task.poll() is None:
        task.kill()
        task.wait(5.0)
    if motion_pid:
        with contextlib.suppress(ProcessLookupError):
            os.kill(motion_pid, signal.SIGKILL)


@contextlib.contextmanager
def moving_machine(path: Path, tmp_path: Path):
    """A machine in this process running the long program, past X 5 (its job with it)."""
    prog = tmp_path / "long.ngc"
    prog.write_text(LONG)
    with own_machine(path) as m:
        m.bring_up()
        job = m.run(str(prog))
        wait_for(lambda: m.motion.commanded[0] > 5.0, 30.0, "moving")
        yield m, job

