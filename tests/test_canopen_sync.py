"""Who times the SYNC (``[canopen] sync``), on the host: the mode chosen per bus, the key checked with
its name, the kernel's SYNC refused on a bus without kernel timing, and the cycle paced by ticks.

The kernel's SYNC itself runs on a real SocketCAN interface: tests/vcan/test_vcan.py (in the VM)."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import can
import pytest
from canopen_helpers import make_config

from fieldbus.canopen.clock import PeriodicRunner
from fieldbus.canopen.config import CanBusConfig, sync_problem
from fieldbus.canopen.master import CanopenError, CanopenMaster
from motiond.config_canopen import read_canopen
from motiond.configkit import ConfigError, Table

ROOT = Path(__file__).resolve().parent.parent
SOCKETCAN = CanBusConfig("socketcan", "can0")


@pytest.mark.parametrize("sync, bus, kernel", [
    ("auto", SOCKETCAN, True),
    ("auto", CanBusConfig("virtual", "x"), False),
    ("auto", CanBusConfig("udp_multicast", "239.74.163.9"), False),
    ("master", SOCKETCAN, False),
    ("kernel", SOCKETCAN, True),
])
def test_the_sync_mode_follows_the_key_and_the_bus(sync, bus, kernel):
    config = make_config(1, bus=bus, sync=sync)
    assert config.kernel_sync is kernel
    assert CanopenMaster(config, check_budget=False).sync_mode == ("kernel" if kernel else "master")


def canopen_table(**canopen: object) -> Table:
    return Table({"canopen": {"axes": {"x": {"node_id": 1}}, **canopen}}, "m.toml")


def test_the_sync_key_is_read_with_master_as_default():
    # the master's SYNC until the kernel's is proven on real drives (docs/canopen.md)
    assert read_canopen(canopen_table(), ["x"], 0.002).sync == "master"
    assert not read_canopen(canopen_table(interface="socketcan", channel="can0"), ["x"], 0.002).kernel_sync
    assert read_canopen(canopen_table(interface="socketcan", channel="can0", sync="master"), ["x"],
                        0.002).sync == "master"
    assert read_canopen(canopen_table(interface="socketcan", channel="can0", sync="kernel"), ["x"],
                        0.002).kernel_sync


@pytest.mark.parametrize("canopen, words", [
    ({"sync": "kernel"}, r'"kernel" needs interface = "socketcan".*on \'virtual\'.*got \'kernel\''),
    ({"sync": "bcm"}, r"must be one of auto, kernel, process, master, got 'bcm'"),
    ({"sync": 1}, r"must be str"),
])
def test_a_bad_sync_names_the_key(canopen, words):
    with pytest.raises(ConfigError, match=r"^m\.toml: canopen\.sync: " + words):
        read_canopen(canopen_table(**canopen), ["x"], 0.002)
    assert sync_problem("kernel", "socketcan") is None


def test_config_check_names_the_sync_key(tmp_path):
    text = (ROOT / "examples" / "canon.toml").read_text()
    assert 'sync = "master"' in text
    bad = tmp_path / "m.toml"
    bad.write_text(text.replace('sync = "master"', 'sync = "kernel"', 1))
    r = subprocess.run([sys.executable, "-m", "motiond.cli", "config", "check", "--config", str(bad)],
                       capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 1 and "Traceback" not in r.stderr
    assert r.stderr.startswith(f'{bad}: canopen.sync: "kernel" needs interface = "socketcan"'), r.stderr
    good = subprocess.run([sys.executable, "-m", "motiond.cli", "config", "check", "--config",
                           str(ROOT / "examples" / "canon.toml")], capture_output=True, text=True,
                          timeout=120, cwd=ROOT)
    assert good.returncode == 0 and "SYNC timed by the master" in " ".join(good.stdout.split())


def test_kernel_sync_on_a_bus_without_kernel_timing_is_refused_at_open():
    # a configuration built in code skips the file's check: the master refuses by itself, and lets the
    # bus go (python-can's periodic send on the virtual bus is a Python thread, not the kernel)
    master = CanopenMaster(make_config(1, sync="kernel"), check_budget=False)
    with pytest.raises(CanopenError, match=r'\[canopen\] sync = "kernel": .*Python thread.*socketcan'):
        master.open()
    assert master.network is None and master.sync_tick is None


def test_master_sync_has_no_tick():
    master = CanopenMaster(make_config(1), check_budget=False)
    assert master.sync_mode == "master" and master.sync_tick is None


class Ticks:
    """A tick source as :class:`~fieldbus.canopen.sync.KernelSync` is one: ticks appear at the times the
    test puts them; ``wait`` returns (first, last, count) of those not yet taken, or None by ``until``."""

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.pending: list[float] = []

    def put(self, n: int = 1, at: float | None = None) -> None:
        """``n`` ticks, stamped now (or ``at``: a tick that was out earlier and is seen only now)."""
        with self.cond:
            self.pending.extend([time.monotonic() if at is None else at] * n)
            self.cond.notify_all()

    def wait(self, until: float) -> tuple[float, float, int] | None:
        with self.cond:
            self.cond.wait_for(lambda: self.pending, max(0.0, until - time.monotonic()))
            if not self.pending:
                return None
            got, self.pending = self.pending, []
            return got[0], got[-1], len(got)


def test_ticks_pace_the_runner_and_missed_ones_are_late_and_skipped():
    ticks = Ticks()
    period = 1.0  # long: a loaded machine must not make the runner give up on a tick the test sends
    steps: list[int] = []
    late: list[int] = []
    stepped = threading.Semaphore(0)

    def step(k: int, t: float) -> None:
        steps.append(k)
        stepped.release()

    runner = PeriodicRunner(period, step, tick=ticks.wait, on_late=lambda k, by: late.append(k))
    ticks.put(5)  # queued before the start: not the runner's (it takes them with tick(0.0))
    runner.start()
    try:
        for _ in range(3):  # one step per tick
            ticks.put()
            assert stepped.acquire(timeout=10.0)
        assert steps == [0, 1, 2] and runner.stats.skipped == 0
        ticks.put(3)  # three ticks before the runner took one: one step, two skipped, late
        assert stepped.acquire(timeout=10.0)
        assert steps[-1] == 5 and runner.stats.skipped == 2 and late == [5]
        # no tick: the runner steps on its clock a period after the tick was due, late and skipped
        t = time.monotonic()
        assert stepped.acquire(timeout=10.0)
        assert time.monotonic() - t >= period
        assert steps[-1] == 7 and runner.stats.skipped == 3 and late == [5, 7]
    finally:
        runner.stop()
        ticks.put()
        assert runner.join(5.0)
    assert runner.error is None


def test_a_tick_seen_only_after_the_step_that_ran_on_the_clock_brings_no_second_step():
    """A SYNC that was on the bus before a step began but reached the master only after it (its reader
    held up, so the step ran on the clock): that step's setpoints already wait for the next SYNC. A
    step for the late one would put two setpoints between two SYNCs: two periods' travel in one."""
    ticks = Ticks()
    period = 1.0
    steps: list[tuple[int, float]] = []
    stepped = threading.Semaphore(0)

    def step(k: int, t: float) -> None:
        steps.append((k, time.monotonic()))
        stepped.release()

    runner = PeriodicRunner(period, step, tick=ticks.wait)
    runner.start()
    try:
        ticks.put()
        assert stepped.acquire(timeout=10.0)
        sync_out = time.monotonic() + period  # the next SYNC goes out on time, but is not seen
        assert stepped.acquire(timeout=10.0)  # a period later the runner steps on its clock
        assert steps[-1][1] > sync_out
        ticks.put(at=sync_out)  # now the SYNC reaches the master, stamped before that step began
        assert not stepped.acquire(timeout=0.3)  # no step for it
        assert len(steps) == 2
        ticks.put()  # the SYNC after it: one step
        assert stepped.acquire(timeout=10.0)
        assert len(steps) == 3 and runner.stats.skipped == 1  # the clock step's tick only
    finally:
        runner.stop()
        ticks.put()
        assert runner.join(5.0)
    assert runner.error is None


class Flood:
    """A listening socket on a machine that reads slower than the SYNCs come: every read finds one
    more, stamped when it is read (``backlog`` first, stamped a second ago); at most ``limit`` reads."""

    def __init__(self, backlog: int, limit: int = 10_000) -> None:
        self.backlog = backlog
        self.reads = 0
        self.limit = limit

    def recv(self, timeout: float | None = None) -> can.Message | None:
        self.reads += 1
        if self.reads > self.limit:
            return None
        stamp = time.time() - (1.0 if self.reads <= self.backlog else 0.0)
        return can.Message(arbitration_id=0x80, data=b"", is_extended_id=False, timestamp=stamp)


def test_taking_the_waiting_syncs_ends_at_the_first_that_came_after_it_began():
    """poll() and wait() take the SYNCs already there, not "until none is left": read slower than the
    SYNCs come (the emulated VM), that held the cycle for seconds (4.0 s for 299)."""
    from fieldbus.canopen.sync import KernelSync

    sync = KernelSync(None, {}, 0.01)  # type: ignore[arg-type]  (never opened: start() does nothing)
    sync._listener = Flood(backlog=3)  # type: ignore[assignment]
    assert sync.poll() == 4  # the three waiting, and the first stamped after the poll began
    sync._listener = Flood(backlog=5)  # type: ignore[assignment]
    got = sync.wait(time.monotonic() + 1.0)
    assert got is not None and got[2] == 6, got
    assert got[0] < got[1]  # the first of the backlog, then the one that ended the drain


class Seen:
    """What the master reads of a kernel SYNC (:class:`~fieldbus.canopen.sync.KernelSync`): how many
    SYNCs its listener has taken and the time of the latest; the test moves both."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self.seen = 0
        self.last_at = 0.0

    def poll(self) -> int:
        return 0

    def stop(self) -> None:
        pass


def test_targets_sent_after_the_next_sync_was_due_count_as_missed_once():
    """With the kernel's SYNC the master counts the SYNCs its targets missed: those its listener saw
    more than one at a time, and those the period made due before its RPDOs were all out, although
    the listener has not read them yet (in the emulated VM it lagged, and the drives counted up to 38
    misses in 1.5 s where the master counted none). Each is counted once."""
    from canopen_helpers import Rig

    rig = Rig(make_config(2, cycle_s=0.01)).up()
    try:
        master = rig.master
        seen = Seen(0.01)
        master._kernel_sync = seen  # type: ignore[assignment]  (the virtual bus has no kernel timing)
        counts = []
        for n, late_by in ((10, 0.0), (11, 0.0), (12, 0.015), (13, 0.0), (15, 0.0), (16, 0.025)):
            seen.seen, seen.last_at = n, time.monotonic() - late_by  # woke ``late_by`` after SYNC n
            master.cycle(None)
            assert master.fault is None, master.fault
            counts.append(master.missed_setpoints)
        # on time; on time; 15 ms late: SYNC 13 came before the targets; 13 read now, not counted
        # again; 15 read next to 14: 15 found no new target; 25 ms late: 17 and 18 came before them
        assert counts == [0, 0, 1, 1, 2, 4]
    finally:
        rig.close()
