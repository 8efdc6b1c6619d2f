"""The CANopen scenarios on a real SocketCAN ``vcan0``: in one process, and drives in another.

Runs where vcan0 exists (a Linux PC: ``ip link add dev vcan0 type vcan && ip link set up vcan0``);
``tests/vcan/run-vm`` runs it inside a virtme-ng VM on a machine whose kernel has no CAN. The VM is
emulated and slow, so the cycle here is 20 ms (10 ms with the drives in their own process) and the
timeouts are generous: these tests check behaviour, not timing.
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from canopen_helpers import Rig, make_config, wait_for

from fieldbus.canopen.cia402 import State
from fieldbus.canopen.config import CanBusConfig
from fieldbus.canopen.master import CanopenError, CanopenMaster
from motiond.config_canopen import canopen_from_file
from motiond.configkit import load_toml

ROOT = Path(__file__).resolve().parent.parent.parent
HAVE_VCAN0 = Path("/sys/class/net/vcan0").exists()

pytestmark = [
    pytest.mark.vcan,
    pytest.mark.timeout(180),
    pytest.mark.skipif(not HAVE_VCAN0, reason="no vcan0 here: create it with `ip link add dev vcan0 "
                       "type vcan` and `ip link set up vcan0` (needs a kernel with CAN), or run "
                       "tests/vcan/run-vm"),
]

SLOW = {"cycle_s": 0.02, "boot_timeout_s": 20.0, "sdo_timeout_s": 2.0, "state_timeout_s": 10.0,
        "feedback_timeout_s": 3.0, "heartbeat_producer_ms": 200, "heartbeat_consumer_ms": 5000}
BUS = CanBusConfig("socketcan", "vcan0")


@pytest.fixture
def rig():
    rigs: list[Rig] = []

    def make(n: int = 2, **kw: object) -> Rig:
        r = Rig(make_config(n, bus=BUS, **{**SLOW, **kw}))
        rigs.append(r)
        return r

    yield make
    for r in rigs:
        r.close()


@pytest.mark.parametrize("layout", ["standard", "compact"])
def test_boot_stream_and_feedback_on_vcan0(rig, layout):
    r = rig(2, pdo_layout=layout).up()
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
    r = rig(2, pdo_layout=layout).up()
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


def test_drives_in_another_process_on_vcan0(tmp_path):
    machine = tmp_path / "machine.toml"
    machine.write_text("""
[machine]
cycle_ms = 10
[axes.x]
[axes.y]
[canopen]
interface = "socketcan"
channel = "vcan0"
heartbeat_producer_ms = 200
heartbeat_consumer_ms = 2000
boot_timeout_s = 20.0
sdo_timeout_s = 2.0
state_timeout_s = 10.0
[canopen.axes.x]
node_id = 1
[canopen.axes.y]
node_id = 2
""")
    proc = subprocess.Popen([sys.executable, "-m", "motiond.cli", "sim", "drives", "--config", str(machine)],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ready = threading.Event()

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            if line.startswith("simulating drives"):
                ready.set()

    threading.Thread(target=read, daemon=True).start()
    master = None
    try:
        assert ready.wait(60.0), "canon sim drives did not start"
        config = canopen_from_file(load_toml(machine), str(machine))
        config = dataclasses.replace(config, feedback_timeout_s=1.0)
        master = CanopenMaster(config)
        master.boot()
        master.enable()
        t = time.monotonic()
        for k in range(80):
            master.cycle([0.01 * min(k, 50), 0.005 * min(k, 50)])
            t += 0.01
            time.sleep(max(0.0, t - time.monotonic()))
        want = pytest.approx((0.5, 0.25), abs=2e-3)
        deadline = time.monotonic() + 30.0  # the emulated VM lags: hold until the feedback catches up
        while time.monotonic() < deadline and master.feedback().positions != want:
            master.cycle(None)
            time.sleep(0.01)
        assert master.fault is None, master.fault
        assert master.feedback().positions == pytest.approx((0.5, 0.25), abs=2e-3)
    finally:
        if master is not None:
            master.shutdown()
        proc.terminate()
        try:
            proc.wait(10.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10.0)


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
