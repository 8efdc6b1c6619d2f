"""The SYNC timed by a process of its own (``[canopen] sync = "process"``) on canon's local bus: the
cycle paced by it with each RPDO after a SYNC, the SYNC going on while the master's process is held
up, no SYNC outliving the master (shut down or killed), and the key checked with its name."""

from __future__ import annotations

import itertools
import os
import signal
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace

import pytest
from canopen_helpers import LocalListener as Listener
from canopen_helpers import unique_channel

from fieldbus.canopen.clock import PeriodicRunner
from fieldbus.canopen.master import CanopenMaster
from fieldbus.canopen.master_records import Fault
from fieldbus.canopen.master_supervision import SupervisionMixin
from fieldbus.canopen.sync_process import SyncProcess, SyncProcessError
from motiond.config_canopen import read_canopen
from motiond.configkit import ConfigError, Table

ROOT = Path(__file__).resolve().parent.parent
SYNC, RPDO1 = 0x80, 0x200


def run_on_sync(master: CanopenMaster, cycles: int) -> PeriodicRunner:
    n = len(master.drives)
    runner = PeriodicRunner(master.config.cycle_s, lambda k, t: master.cycle([0.001 * k] * n),
                            cycles=cycles, tick=master.sync_tick).start()
    assert runner.join(60.0), "the cycle did not end"
    assert runner.error is None
    return runner


def test_the_sync_process_paces_the_cycle_and_each_rpdo_follows_a_sync(local_rig):
    rig, listener = local_rig(2, cycle_s=0.004, feedback_timeout_s=2.0)
    rig.up()
    master = rig.master
    assert master.sync_mode == "process" and master.sync_tick is not None
    t0 = time.time()
    run_on_sync(master, 150)
    t1 = time.time()
    assert master.fault is None, master.fault
    listener.drain()
    syncs = listener.syncs(t0, t1)
    assert len(syncs) >= 120, len(syncs)
    # the SYNC process's own clock: its median period is the configured one
    gaps = [b - a for a, b in itertools.pairwise(syncs)]
    assert statistics.median(gaps) == pytest.approx(0.004, rel=0.2)
    # each drive's RPDO goes out after a SYNC, early in the period (for the next SYNC)
    after: dict[int, list[float]] = {1: [], 2: []}
    last = None
    for t, cob in sorted(f for f in listener.frames if t0 <= f[0] <= t1):
        if cob == SYNC:
            last = t
        elif cob in (RPDO1 + 1, RPDO1 + 2) and last is not None:
            after[cob - RPDO1].append(t - last)
    for node, delays in after.items():
        assert len(delays) >= 100, (node, len(delays))
        assert statistics.median(delays) < 0.5 * 0.004, (node, statistics.median(delays))
    # the drives latched the targets: they followed the stream
    assert rig.sim(1).target != 0 and rig.sim(1).syncs >= 120


def test_the_sync_stops_with_the_cycle_so_enabled_drives_miss_no_setpoint(local_rig):
    """The cycle stopped for good (the machine closing, drives still enabled until shutdown parks
    them): the SYNC process stops with it, as the master's own SYNC does. It went on before, and each
    of its SYNCs was a missed setpoint to every enabled drive (24 in 50 ms at 2 ms)."""
    rig, listener = local_rig(2, cycle_s=0.002, feedback_timeout_s=2.0)
    rig.up()
    master = rig.master
    run_on_sync(master, 100)
    sims = [rig.sim(1), rig.sim(2)]
    master.stop_sync()
    stopped = time.time()
    time.sleep(0.02)  # a SYNC in flight at the call
    missed = [s.missed_setpoints for s in sims]  # a loaded PC's late cycles may have cost some before
    time.sleep(0.1)  # 50 SYNC periods
    listener.drain()
    late = listener.syncs(stopped + 0.01)
    assert [s.missed_setpoints for s in sims] == missed
    assert late == []
    assert master.sync_tick is None
    master.stop_sync()  # safe twice


def test_the_sync_goes_on_while_the_masters_process_holds_its_interpreter_lock(local_rig):
    """The point of the SYNC process: whatever holds the motion process's interpreter lock, the SYNC
    keeps its period (with the master's own SYNC none goes out while the cycle cannot run)."""
    rig, listener = local_rig(1, cycle_s=0.002, feedback_timeout_s=5.0)
    rig.up()
    run_on_sync(rig.master, 20)  # the SYNC process started with the first tick
    before = sys.getswitchinterval()
    sys.setswitchinterval(1.0)  # no other thread of this process runs until the loop below ends
    try:
        t0 = time.time()
        n = 0
        while time.time() - t0 < 0.3:
            n += 1
        t1 = time.time()
    finally:
        sys.setswitchinterval(before)
    listener.drain()
    held = listener.syncs(t0, t1)
    # 150 periods in 0.3 s; at least half of them on a loaded machine
    assert len(held) >= 75, (len(held), t1 - t0)


def test_no_sync_outlives_the_master_shut_down(local_rig):
    rig, listener = local_rig(1, cycle_s=0.002)
    rig.up()
    run_on_sync(rig.master, 10)
    timer = rig.master._kernel_sync.timer  # type: ignore[union-attr]
    assert timer is not None
    rig.master.shutdown()
    after = time.time()
    assert timer._proc.poll() is not None  # reaped by the shutdown
    time.sleep(0.1)
    listener.drain()
    assert listener.syncs(after + 0.01) == []
    assert listener.syncs(0.0, after)  # it did send before


def master_fault_after(local_rig, act: Callable[[CanopenMaster], None]) -> Fault:
    """A 2 ms cycle paced by the SYNC process with one drive (timeout 300 ms), ``act`` done before its
    50th cycle, run until the master faults (at most 3,000 cycles): that fault, the master's own."""
    rig, _listener = local_rig(1, cycle_s=0.002, feedback_timeout_s=0.3)
    rig.up()
    master = rig.master
    done = [0]

    def step(k: int, t: float) -> bool:
        done[0] += 1
        if done[0] == 50:
            act(master)
        master.cycle([0.0])
        return master.fault is None

    runner = PeriodicRunner(0.002, step, cycles=3000, tick=master.sync_tick).start()
    assert runner.join(60.0)
    assert master.fault is not None and master.fault.node == 0, (master.fault, runner.error, done[0])
    return master.fault


def test_a_killed_sync_process_is_a_fault_of_the_master_naming_it(local_rig):
    """Seen either way, the same words: by the SYNC's silence on the bus, or (first, when the cycle
    writes to it) by the SYNC process's input being gone."""
    fault = master_fault_after(
        local_rig, lambda m: os.kill(m._kernel_sync.timer.pid, signal.SIGKILL))  # type: ignore[union-attr]
    assert "no SYNC on the bus" in fault.reason and "the SYNC process stopped" in fault.reason


def test_a_cycle_stalled_while_the_sync_process_goes_on_is_named_so(local_rig):
    """The other side of the same watch: the SYNC process goes on sending while the cycle stalls
    beyond the timeout: the master names its own cycle, not the SYNC."""
    # the cycle thread held up; the SYNC process's SYNC goes on
    fault = master_fault_after(local_rig, lambda m: time.sleep(0.8))
    assert "sent no setpoint" in fault.reason and "SYNC went on" in fault.reason, fault


class _Watch:
    """The state the master's SYNC watch reads, set by hand: a race made exact."""

    def __init__(self, *, last_sent: float, reader_sync_at: float) -> None:
        self.config = SimpleNamespace(feedback_timeout_s=0.3)
        self._kernel_sync = SimpleNamespace(timer=object())  # the SYNC process
        self._last_sent, self._reader_sync_at, self._stream_t0 = last_sent, reader_sync_at, 1.0
        self.faults: list[str] = []

    def raise_fault(self, node: int, reason: str) -> None:
        self.faults.append(reason)


def test_the_last_sync_read_after_the_last_push_is_still_the_syncs_silence():
    """Seen in CI: the SYNC process killed, the bus reader read its last SYNC 1 ms after the cycle's
    last push. The clock then passed the limit since the push before the one since the SYNC: the watch
    named a stalled cycle "while the SYNC went on", though no SYNC came after the push. It waits for
    the SYNC's own silence, and names that."""
    w = _Watch(last_sent=10.000, reader_sync_at=10.001)
    assert not SupervisionMixin._sync_stalled(w, 10.3005)  # type: ignore[arg-type]
    assert w.faults == []
    assert SupervisionMixin._sync_stalled(w, 10.3015)  # type: ignore[arg-type]
    assert len(w.faults) == 1 and "no SYNC on the bus" in w.faults[0], w.faults
    assert "the SYNC process stopped" in w.faults[0]
    # SYNCs still read long after the last push: the cycle's stall, named so
    w = _Watch(last_sent=10.000, reader_sync_at=10.302)
    assert SupervisionMixin._sync_stalled(w, 10.3025)  # type: ignore[arg-type]
    assert len(w.faults) == 1 and "SYNC went on" in w.faults[0], w.faults


KILLED = """
import sys, time
from fieldbus.canopen.sync_process import SyncProcess
t = SyncProcess({{"interface": "canon_local", "channel": {channel!r}}}, 0.002)
t.start()
print(t.pid, flush=True)
time.sleep(60)
"""


def test_no_sync_outlives_a_killed_parent():
    """SIGKILL gives the parent no chance to stop its SYNC process: the process sees its input end
    (the kernel closed the dead parent's files) and stops, as the kernel ends a BCM task with its
    socket."""
    channel = unique_channel()
    listener = Listener(channel)
    parent = subprocess.Popen([sys.executable, "-c", KILLED.format(channel=channel)], cwd=ROOT,
                              stdout=subprocess.PIPE, text=True)
    try:
        line = parent.stdout.readline() if parent.stdout else ""
        child = int(line)
        deadline = time.monotonic() + 20
        while not listener.syncs() and time.monotonic() < deadline:
            listener.drain(0.05)
        assert listener.syncs(), "no SYNC before the kill"
        parent.send_signal(signal.SIGKILL)
        parent.wait(10)
        killed = time.time()
        gone = False
        for _ in range(200):  # bounded: 10 s
            try:
                os.kill(child, 0)
            except ProcessLookupError:
                gone = True
                break
            with open(f"/proc/{child}/stat") as f:  # a zombie has sent its last SYNC
                if f.read().split(")")[-1].split()[0] == "Z":
                    gone = True
                    break
            time.sleep(0.05)
        assert gone, "the SYNC process outlived its parent"
        listener.drain()
        assert not listener.syncs(killed + 0.05), "SYNCs after the parent was killed"
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait(10)
        listener.close()


def test_the_sync_process_records_when_it_sent_each_sync_where_asked(tmp_path, monkeypatch):
    """``CANON_SYNC_TRACE``: the bench's view of the SYNC at its sender (its send times, written at its
    end), apart from what the sockets and the receivers add."""
    from array import array

    from fieldbus.canopen.sync_process import TRACE_ENV

    monkeypatch.setenv(TRACE_ENV, str(tmp_path))
    t = SyncProcess({"interface": "canon_local", "channel": unique_channel()}, 0.004)
    t.start()
    got = [t.read(5.0) for _ in range(20)]
    t.stop()
    files = list(tmp_path.glob(f"sync-{t.pid}.f64"))
    assert len(files) == 1
    sent = array("d")
    sent.frombytes(files[0].read_bytes())
    assert len(sent) >= 20 and list(sent[:20]) == got  # the times it reported, in order
    assert statistics.median(b - a for a, b in itertools.pairwise(sent)) == pytest.approx(0.004, rel=0.2)


def test_a_write_to_a_killed_sync_process_says_the_sync_stopped():
    """The write that finds the SYNC process's input gone says what the drives see (no SYNC) in the
    words the SYNC's silence is reported in."""
    t = SyncProcess({"interface": "canon_local", "channel": unique_channel()}, 0.004)
    try:
        t.start()
        assert t.read(5.0) is not None
        os.kill(t.pid, signal.SIGKILL)
        t._proc.wait(10)
        with pytest.raises(SyncProcessError, match=r"no SYNC on the bus: the SYNC process stopped"):
            for tag in range(1, 100):  # the pipe's buffer may take a few before the write fails
                t.push(tag, [(RPDO1 + 1, bytes(8))], 0)
    finally:
        t.stop()


def test_a_sync_process_whose_bus_does_not_open_says_why():
    with pytest.raises(SyncProcessError, match=r"did not open the bus: .*nosuch"):
        SyncProcess({"interface": "nosuch", "channel": "x"}, 0.01)


def canopen_table(**canopen: object) -> Table:
    return Table({"canopen": {"axes": {"x": {"node_id": 1}}, **canopen}}, "m.toml")


def test_the_sync_key_takes_process_on_a_bus_that_crosses_processes():
    for interface, channel in (("canon_local", "a"), ("udp_multicast", "239.74.163.9")):
        c = read_canopen(canopen_table(interface=interface, channel=channel, sync="process"), ["x"], 0.002)
        assert c.sync_source == "process" and not c.kernel_sync
    with pytest.raises(ConfigError, match=r'^m\.toml: canopen\.sync: "process" needs a bus that crosses '
                                          r"processes .*'virtual'"):
        read_canopen(canopen_table(sync="process"), ["x"], 0.002)


def test_config_check_says_a_sync_process_times_the_sync(tmp_path):
    text = (ROOT / "examples" / "canon.toml").read_text()
    cfg = tmp_path / "m.toml"
    cfg.write_text(text.replace('sync = "master"', 'sync = "process"', 1))
    r = subprocess.run([sys.executable, "-m", "motiond.cli", "config", "check", "--config", str(cfg)],
                       capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert "SYNC timed by a SYNC process;" in " ".join(r.stdout.split())
    cfg.write_text(text.replace('sync = "master"', 'sync = "process"', 1).replace(
        "setpoint_lead = 1 ", "setpoint_lead = 6 ", 1))
    r = subprocess.run([sys.executable, "-m", "motiond.cli", "config", "check", "--config", str(cfg)],
                       capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert "SYNC timed by a SYNC process, setpoints sent 6 SYNCs ahead;" in " ".join(r.stdout.split())
