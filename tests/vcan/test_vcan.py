"""The CANopen scenarios on a real SocketCAN ``vcan0``, master and drives in one process; with the drives
in another process, ``tests/test_canopen_multiprocess.py`` (its ``vcan0`` half, which
``tests/vcan/run-vm`` runs too).

Runs where vcan0 exists (a Linux PC: ``ip link add dev vcan0 type vcan && ip link set up vcan0``);
``tests/vcan/run-vm`` runs it inside a virtme-ng VM on a machine whose kernel has no CAN. The VM is
emulated and slow, so the cycle here is 20 ms (10 ms with the drives in their own process) and the
timeouts are generous: these tests check behaviour, not timing.
"""

from __future__ import annotations

import os
import re
import signal
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import itertools

import can
from canopen_helpers import Rig, make_config, wait_for

from fieldbus.canopen.cia402 import State
from fieldbus.canopen.clock import PeriodicRunner
from fieldbus.canopen.config import CanBusConfig
from fieldbus.canopen.master import CanopenError, CanopenMaster

ROOT = Path(__file__).resolve().parent.parent.parent
HAVE_VCAN0 = Path("/sys/class/net/vcan0").exists()

pytestmark = [
    pytest.mark.vcan,
    pytest.mark.timeout(180),
    pytest.mark.skipif(not HAVE_VCAN0, reason="no vcan0 here: create it with `ip link add dev vcan0 "
                       "type vcan` and `ip link set up vcan0` (needs a kernel with CAN), or run "
                       "tests/vcan/run-vm"),
]

SLOW = {"cycle_s": 0.02, "boot_timeout_s": 20.0, "sdo_timeout_s": 5.0, "state_timeout_s": 10.0,
        "feedback_timeout_s": 3.0, "heartbeat_producer_ms": 200, "heartbeat_consumer_ms": 5000}
BUS = CanBusConfig("socketcan", "vcan0")


@pytest.fixture
def rig():
    rigs: list[Rig] = []

    def make(n: int = 2, **kw: object) -> Rig:
        # the kernel's SYNC unless a test says otherwise (the configuration's default is the master's)
        r = Rig(make_config(n, bus=BUS, **{**SLOW, "sync": "kernel", **kw}))
        rigs.append(r)
        return r

    yield make
    for r in rigs:
        r.close()


@pytest.mark.parametrize("layout, sync", [("standard", "auto"), ("compact", "auto"), ("standard", "master")])
def test_boot_stream_and_feedback_on_vcan0(rig, layout, sync):
    r = rig(2, pdo_layout=layout, sync=sync).up()
    assert r.master.sync_mode == ("master" if sync == "master" else "kernel")  # auto: kernel on socketcan
    r.run(60, lambda k: [0.01 * min(k, 40), -0.01 * min(k, 40)])
    # the emulated VM processes frames late: hold and let the feedback catch up (bounded)
    deadline = time.monotonic() + 30.0
    want = pytest.approx((0.4, -0.4), abs=1e-3)
    while time.monotonic() < deadline and r.master.feedback().positions != want:
        r.run(10)
    assert r.master.fault is None, r.master.fault
    assert r.master.feedback().positions == pytest.approx((0.4, -0.4), abs=1e-3)
    assert r.sim(1).target == 4000 and r.sim(2).target == -4000


@pytest.mark.parametrize("layout", ["standard", "compact"])
def test_emcy_fault_quick_stop_and_reset_on_vcan0(rig, layout):
    # the master's SYNC: with the kernel's, the SYNC runs on through the seconds of SDO the fault reset
    # takes here, and the drives simulated in this process fall behind it in the emulated guest (their
    # SDO answers time out); the kernel SYNC's own faults are the tests below
    r = rig(2, pdo_layout=layout, sync="master").up()
    r.run(10, lambda k: [0.001 * k, 0.0])
    held = r.master.positions()
    r.sim(1).inject_fault(0x2310)
    assert wait_for(lambda: r.master.fault is not None, 10.0)
    assert r.master.fault.node == 1 and "EMCY 0x2310" in r.master.fault.reason
    r.run(10, lambda k: [5.0, 5.0])
    assert r.master.positions() == held
    # compact: quick stop option 6 holds in Quick stop active; standard: option 2, Switch on disabled
    ends_in = State.QUICK_STOP_ACTIVE if layout == "compact" else State.SWITCH_ON_DISABLED
    assert wait_for(lambda: r.sim(2).state == ends_in, 5.0)
    r.master.reset_faults()
    r.master.enable()
    r.run(10)
    assert r.master.fault is None
    assert [s.state for s in r.master.state] == [State.OPERATION_ENABLED] * 2


def test_sdo_abort_during_boot_on_vcan0(rig):
    r = rig(1)
    r.sim(1).abort_sdo(0x6060, 0, 0x06090030)
    with pytest.raises(CanopenError, match=r"node 1 \(axis x\).*0x6060:00.*0x06090030"):
        r.master.boot()


def test_touch_probe_latches_within_one_count_on_vcan0():
    from fieldbus.canopen.drive_sim import SimDrive
    from fieldbus.canopen.touch_probe import TouchProbe

    trip = -12_345  # counts; x moves 500 counts per 20 ms cycle
    r = Rig(make_config(1, bus=BUS, touch_probe=1, **SLOW), [SimDrive(1, probe_trip_counts=trip)])
    try:
        r.up()
        probe = TouchProbe.of(r.master)
        assert probe is not None
        probe.arm(toward=True)
        r.run(60, lambda k: [-0.05 * min(k, 50)])
        assert wait_for(lambda: probe.tripped, 5.0)
        result = probe.result()
        assert result.tripped and abs(result.counts - trip) <= 1
    finally:
        r.close()


# ---------------------------------------------------------------------- the kernel's SYNC
SYNC, RPDO1 = 0x080, 0x200


class Listener:
    """Every frame on vcan0 with the kernel's receive time, from a socket of its own (as a drive or a
    bus analyser sees the bus): independent of the master."""

    def __init__(self) -> None:
        self.bus = can.Bus(interface="socketcan", channel="vcan0")
        self.frames: list[tuple[float, int]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(0.05)
            if msg is not None:
                self.frames.append((msg.timestamp, msg.arbitration_id))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self.bus.shutdown()

    def syncs(self, after: float = 0.0, before: float = float("inf")) -> list[float]:
        return [t for t, i in self.frames if i == SYNC and after <= t <= before]


@pytest.fixture
def listener():
    lst = Listener()
    yield lst
    lst.close()


def run_on_sync(master: CanopenMaster, cycles: int, positions=None, stall_at: int | None = None,
                stall_s: float = 0.0, stalled: list[float] | None = None) -> PeriodicRunner:
    """``cycles`` cycles paced by the kernel's SYNC (as the daemon runs them), joined. ``stall_at``: the
    executed step (from 0) that sleeps ``stall_s`` first (a stalled master thread; its start and end,
    wall clock, are appended to ``stalled``). Counted in steps run, not in the runner's ``k``: ``k``
    counts ticks and jumps over those a slow guest missed, which can skip ``stall_at`` itself."""
    done = [0]

    def step(k: int, t: float) -> None:
        done[0] += 1
        if done[0] - 1 == stall_at:
            if stalled is not None:
                stalled.append(time.time())
            time.sleep(stall_s)
            if stalled is not None:
                stalled.append(time.time())
        master.cycle(positions(k) if positions else None)

    runner = PeriodicRunner(master.config.cycle_s, step, cycles=cycles, tick=master.sync_tick).start()
    assert runner.join(120.0), "the cycle did not end"
    assert runner.error is None
    return runner


def test_kernel_sync_comes_at_the_period_and_the_rpdos_right_after_it(rig, listener):
    r = rig(2, feedback_timeout_s=10.0).up()  # the emulated guest stalls threads for seconds
    assert r.master.sync_mode == "kernel" and r.master.sync_tick is not None
    period = r.config.cycle_s
    t0 = time.time()
    run_on_sync(r.master, 100, lambda k: [0.001 * k, -0.001 * k])
    t1 = time.time()
    assert r.master.fault is None, r.master.fault
    syncs = listener.syncs(t0, t1)
    gaps = [b - a for a, b in itertools.pairwise(syncs)]
    assert len(syncs) >= 90, len(syncs)
    # the kernel's timer: its median period is the configured one (the emulated VM adds latency)
    assert statistics.median(gaps) == pytest.approx(period, rel=0.2)
    # each drive's RPDO goes out after a SYNC, early in the period (for the next SYNC), the cycle paced
    # by the SYNCs it sees (on its own clock the emulated guest wakes the cycle thread milliseconds late)
    after: dict[int, list[float]] = {1: [], 2: []}
    last_sync = None
    for t, cob in (f for f in listener.frames if t0 <= f[0] <= t1):
        if cob == SYNC:
            last_sync = t
        elif cob in (RPDO1 + 1, RPDO1 + 2) and last_sync is not None:
            after[cob - RPDO1].append(t - last_sync)
    for node, delays in after.items():
        assert len(delays) >= 80, (node, len(delays))
        assert statistics.median(delays) < 0.8 * period, (node, statistics.median(delays))
    # how many SYNC periods got one RPDO is the emulated guest's speed, not canon's: on a loaded host
    # the guest ran 100 cycles in 203 periods (81 with one RPDO). Reported, not judged here. The
    # listener and the master time SYNCs on different sockets, and in the emulated guest an RPDO sent a
    # hair after the master's SYNC is a hair before the listener's (CI: the listener saw one empty
    # period, the master rightly counted none), so the two counts are not compared: that the master
    # counts what it missed is judged where a stall is made on purpose (the next test)
    per_period = [sum(1 for t, cob in listener.frames if cob == RPDO1 + 1 and a < t < b)
                  for a, b in itertools.pairwise(syncs)][1:-1]
    print(f"kernel SYNC in the VM: {len(per_period)} periods, {per_period.count(1)} with one RPDO of node 1, "
          f"{per_period.count(0)} with none; master counted {r.master.missed_setpoints} missed")


def test_a_stalled_cycle_costs_setpoints_but_no_sync(rig, listener):
    r = rig(2, feedback_timeout_s=10.0).up()
    period = r.config.cycle_s
    stalled: list[float] = []
    runner = run_on_sync(r.master, 60, lambda k: [0.001 * k, 0.0], stall_at=30, stall_s=5 * period,
                         stalled=stalled)
    assert r.master.fault is None, r.master.fault
    # the SYNC went on while the master thread slept five periods (with the master's SYNC there would
    # be none in that time)
    assert len(listener.syncs(*stalled)) >= 3, (stalled, listener.syncs(stalled[0] - 0.1, stalled[1] + 0.1))
    # the setpoints it missed are seen: late and skipped cycles, SYNCs that found no new RPDO
    assert runner.stats.late >= 1 and runner.stats.skipped >= 2, runner.stats
    assert r.master.missed_setpoints >= 2


def test_stopping_the_master_stops_the_sync(rig, listener):
    r = rig(1).up()
    run_on_sync(r.master, 20)
    assert listener.syncs()[-1] > time.time() - 5.0  # the kernel's SYNC runs
    r.master.shutdown()
    stopped = time.time()
    time.sleep(20 * r.config.cycle_s)  # frames sent before the stop reach the listener meanwhile
    assert listener.syncs(after=stopped) == []


def test_the_sync_ends_with_the_process(tmp_path, listener):
    # a master killed outright: the kernel removes its socket's periodic SYNC with the process
    script = tmp_path / "m.py"
    script.write_text(f"""
import sys, time
sys.path.insert(0, {str(ROOT / 'tests')!r})
from canopen_helpers import make_config
from fieldbus.canopen.config import CanBusConfig
from fieldbus.canopen.master import CanopenMaster
m = CanopenMaster(make_config(1, bus=CanBusConfig("socketcan", "vcan0"), cycle_s=0.02, sync="kernel"))
m.open()
m.cycle()  # the kernel's SYNC starts with the first cycle
print("open", flush=True)
time.sleep(120)
""")
    proc = subprocess.Popen([sys.executable, str(script)], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "open"
        assert wait_for(lambda: len(listener.syncs(after=time.time() - 1.0)) >= 5, 30.0)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(30.0)
    killed = time.time()
    time.sleep(0.5)
    assert listener.syncs(after=killed) == []


def test_a_stopped_kernel_sync_is_the_masters_fault(rig):
    r = rig(2, feedback_timeout_s=1.0).up()
    run_on_sync(r.master, 10)
    r.master._kernel_sync._task.stop()  # the kernel's task gone (as if removed, or the interface down)
    run_on_sync(r.master, 150)  # the cycle goes on, on its clock
    assert r.master.fault is not None
    assert r.master.fault.node == 0 and "no SYNC on the bus" in r.master.fault.reason, r.master.fault


def test_a_cycle_stalled_beyond_the_timeout_is_the_masters_fault(rig):
    r = rig(2, feedback_timeout_s=1.0).up()
    run_on_sync(r.master, 20, stall_at=10, stall_s=2.0)
    assert r.master.fault is not None
    assert r.master.fault.node == 0, r.master.fault
    assert "sent no setpoint" in r.master.fault.reason and "SYNC went on" in r.master.fault.reason


@pytest.mark.timeout(600)
def test_the_socketcan_bench_runs_on_vcan0():
    """``bench/fieldbus.py --bus socketcan`` (what ``tests/vcan/run-vm --bench`` runs), one short case with
    the kernel's SYNC: it ends, prints its row, and its listener saw the kernel's SYNC through the run.
    Its figures are the emulated guest's: reported by the bench, not judged here."""
    res = subprocess.run([sys.executable, str(ROOT / "bench" / "fieldbus.py"), "--bus", "socketcan",
                          "--seconds", "1", "--drives", "1", "--periods-ms", "20", "--sync", "kernel"],
                         cwd=ROOT, capture_output=True, text=True, timeout=540)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    row = re.search(r"1 drives, 20(?: ms)?\s*│\s*kernel\s*│\s*(\d+)", res.stdout)  # the cell may wrap
    assert row is not None, res.stdout
    assert int(row.group(1)) >= 10, res.stdout  # 50 SYNCs at 20 ms in a second: at least a fifth seen
    print(res.stdout)


def test_a_socketcan_bus_gets_a_receive_buffer_for_seconds_of_traffic():
    """A SocketCAN socket is charged about 1 KiB a frame: at the default buffer a drive process that
    read late lost SYNCs and targets here. Opened by canon, it gets seconds' worth (root may pass
    net.core.rmem_max; the kernel reports twice what it granted)."""
    import socket

    from fieldbus.canopen.busopen import UDP_RECEIVE_BUFFER, open_bus

    bus = open_bus(CanBusConfig("socketcan", "vcan0"))
    try:
        assert bus.socket.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF) >= UDP_RECEIVE_BUFFER
    finally:
        bus.shutdown()
