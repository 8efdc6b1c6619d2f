"""Master in this process, simulated drives in another (``canon sim drives``), on udp_multicast.

udp_multicast stays on this host: IPv4 group, hop_limit 0, and the tests run inside the private
network namespace (``tests/run``, ``tests/netns-run``).
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from fieldbus.canopen.cia402 import State, decode
from fieldbus.canopen.clock import stream
from fieldbus.canopen.master import CanopenMaster
from motiond.config_canopen import canopen_from_file
from motiond.configkit import load_toml

pytestmark = [pytest.mark.multicast, pytest.mark.timeout(90)]

ROOT = Path(__file__).resolve().parent.parent


def machine_file(tmp_path: Path, interface: str, channel: str, cycle_ms: float = 2.0,
                 layout: str = "standard") -> Path:
    text = f"""
[machine]
cycle_ms = {cycle_ms}
[axes.x]
max_velocity = 200.0
[axes.y]
max_velocity = 200.0
[axes.z]
max_velocity = 100.0
[canopen]
interface = "{interface}"
channel = "{channel}"
heartbeat_producer_ms = 50
heartbeat_consumer_ms = 200
pdo_layout = "{layout}"
following_error_every = {1 if layout == "standard" else 4}
[canopen.axes.x]
node_id = 1
[canopen.axes.y]
node_id = 2
direction = -1
[canopen.axes.z]
node_id = 3
counts_per_unit = 5000
"""
    p = tmp_path / "machine.toml"
    p.write_text(text)
    return p


class DriveProcess:
    """``canon sim drives`` as a child process, waited for until it says it is up."""

    def __init__(self, config: Path, *extra: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "motiond.cli", "sim", "drives", "--config", str(config), *extra],
            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.ready = threading.Event()
        self.lines: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()
        if not self.ready.wait(20.0):
            self.stop()
            raise AssertionError(f"canon sim drives did not start: {self.lines}")

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line)
            if line.startswith("simulating drives"):
                self.ready.set()

    def stop(self) -> str:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5.0)
        return self.proc.stderr.read() if self.proc.stderr else ""


def group() -> str:
    return f"239.74.164.{1 + os.getpid() % 250}"


@pytest.fixture
def setup(tmp_path):
    made: list[tuple[DriveProcess, CanopenMaster]] = []

    def make(cycle_ms: float = 2.0, layout: str = "standard", *extra: str):
        path = machine_file(tmp_path, "udp_multicast", group(), cycle_ms, layout)
        config = canopen_from_file(load_toml(path), str(path))
        drives = DriveProcess(path, *extra)
        drives.config = path
        master = CanopenMaster(config)
        made.append((drives, master))
        return drives, master

    yield make
    for drives, master in made:
        master.shutdown()
        drives.stop()


@pytest.mark.parametrize("layout", ["standard", "compact"])
def test_master_and_drives_in_two_processes_on_udp_multicast(setup, layout):
    drives, master = setup(2.0, layout)
    master.boot()
    master.enable()
    start = master.positions()
    runner = stream(master, lambda t: [start[0] + 5.0 * min(t, 1.0), start[1] - 2.0 * min(t, 1.0), start[2]],
                    1.5, fault_on_late=False)  # this machine is shared: lateness is the bench's business
    assert runner.join(30.0)
    assert runner.error is None
    assert master.fault is None, master.fault
    master.cycle(None)
    time.sleep(0.05)
    fb = master.feedback()
    assert [s.state for s in master.state] == [State.OPERATION_ENABLED] * 3
    assert fb.positions == pytest.approx((5.0, -2.0, 0.0), abs=0.01)
    assert all(abs(e) < 1.0 for e in fb.following_errors)
    master.shutdown()
    report = drives.stop()
    # every SYNC reached the drives' process with its targets: no missed setpoint was counted
    assert "node 1: syncs" in report
    for line in report.splitlines():
        if line.startswith("node "):
            missed = int(line.split("missed setpoints ")[1].split(",")[0])
            assert missed <= 2, report  # udp_multicast is lossy under load; a burst of losses is a bug


def test_the_drive_process_dying_is_a_fault(setup):
    drives, master = setup(4.0)
    master.boot()
    master.enable()
    drives.proc.kill()
    drives.proc.wait(5.0)
    deadline = time.monotonic() + 3.0
    while master.fault is None and time.monotonic() < deadline:
        master.cycle(None)
        time.sleep(0.004)
    assert master.fault is not None
    assert "no TPDO" in master.fault.reason or "heartbeat missed" in master.fault.reason


def _emcys(report: str) -> dict[int, str]:
    """``node n: ... emcy [...]`` lines of ``canon sim drives``' report: node -> its EMCY list."""
    return {int(line.split(":")[0].split()[1]): line.split("emcy ")[1]
            for line in report.splitlines() if line.startswith("node ")}


def test_shutdown_leaves_the_drives_disabled_and_nothing_faults_after_exit(setup):
    drives, master = setup(2.0)
    master.boot()
    master.enable()
    start = master.positions()
    runner = stream(master, lambda t: [start[0] + 20.0 * t, start[1], start[2]], 0.5, fault_on_late=False)
    assert runner.join(30.0) and runner.error is None
    master.shutdown()  # the drive at 20 mm/s: quick stop, disabled, consumer heartbeat off
    time.sleep(0.8)  # four consumer times (200 ms) without the master's heartbeat
    report = drives.stop()
    assert _emcys(report) == {1: "[]", 2: "[]", 3: "[]"}, report


def _quick_stop_input(config: Path, node_id: int, *values: int) -> None:
    """What ``canon sim inject --quick-stop on|off`` does (SDO to 0x2F00:03), from a CANopen client on
    its own bus object in this process: starting the CLI twice would load this 2-core machine enough
    to delay the drives' TPDOs beyond the master's limit."""
    import canopen

    from fieldbus.canopen.drive_sim import SIM_INJECT, SIM_QUICK_STOP_INPUT

    bus = canopen_from_file(load_toml(config), str(config)).bus
    network = canopen.Network()
    network.connect(**bus.bus_kwargs())
    try:
        node = network.add_node(canopen.RemoteNode(node_id, canopen.ObjectDictionary()))
        node.sdo.MAX_RETRIES = 3
        for v in values:
            node.sdo.download(SIM_INJECT, SIM_QUICK_STOP_INPUT, bytes([v]))
    finally:
        network.disconnect()


@pytest.mark.parametrize("layout", ["standard", "compact"])
def test_a_drive_local_quick_stop_in_the_drive_process_stops_the_machine(setup, layout):
    """The drives take transition 16 at once (``--strict``); the quick-stop input of y is tapped mid-move
    by SDO from another client: the machine stops, y is named, and it stays stopped."""
    drives, master = setup(4.0, layout, "--strict")
    master.boot()
    master.enable()
    start = master.positions()
    # slow enough that a burst of frames lost on a loaded machine is no setpoint jump
    runner = stream(master, lambda t: [start[0] + 10.0 * t, start[1] + 10.0 * t, start[2]], 3.0,
                    fault_on_late=False)
    time.sleep(0.5)
    _quick_stop_input(drives.config, 2, 1, 0)  # tapped: on, then off at once
    assert runner.join(30.0) and runner.error is None
    f = master.fault
    assert f is not None and (f.node, f.axis) == (2, "y"), f
    assert "quick stop" in f.reason and "not re-enabled" in f.reason
    for _ in range(50):
        master.cycle(None)
        time.sleep(0.002)
    states = [decode(master._statusword(d)) for d in master.drives]  # by SDO, from the drives
    assert State.OPERATION_ENABLED not in states, states


def test_drives_with_rpdo_deadline_monitoring_enable_without_fault(setup):
    """Every drive of the other process faults after 3 SYNCs without a target (EMCY 0x8250); the
    master enables them over SDO one by one while its cycle runs: none faults."""
    from fieldbus.canopen.clock import PeriodicRunner

    drives, master = setup(4.0, "standard", "--rpdo-timeout-syncs", "3")
    master.boot()
    runner = PeriodicRunner(master.config.cycle_s, lambda k, t: master.cycle(None),
                            keep_lateness=False).start()
    try:
        master.enable()
        time.sleep(0.2)
    finally:
        runner.stop()
        assert runner.join(5.0)
    assert master.fault is None, master.fault
    start = master.positions()
    run = stream(master, lambda t: [start[0] + 10.0 * t, start[1], start[2]], 0.5, fault_on_late=False)
    assert run.join(30.0) and run.error is None
    assert master.fault is None, master.fault
    master.shutdown()
    report = drives.stop()
    assert _emcys(report) == {1: "[]", 2: "[]", 3: "[]"}, report


def test_a_drive_process_without_0x6085_boots_with_a_warning_and_moves(setup):
    _drives, master = setup(4.0, "standard", "--absent", "0x6085")
    master.boot()
    assert {w.node for w in master.warnings if "0x6085" in w.reason} == {1, 2, 3}
    master.enable()
    start = master.positions()
    run = stream(master, lambda t: [start[0] + 10.0 * t, start[1], start[2]], 0.3, fault_on_late=False)
    assert run.join(30.0) and run.error is None
    assert master.fault is None, master.fault


def test_a_motor_slower_than_the_configuration_is_refused_naming_both(setup):
    from fieldbus.canopen.master import CanopenError

    _drives, master = setup(4.0, "standard", "--param", "0x6080=1000")  # 1000 rpm: 83.3 mm/s
    with pytest.raises(CanopenError, match=r"node 1 \(axis x\): axes\.x\.max_velocity 200 is 2,000,000 "
                                           r"counts/s, more than the motor allows: 0x6080 max motor speed "
                                           r"1000 rpm"):
        master.boot()


def test_a_limit_switch_of_a_drive_in_the_drive_process_stops_the_machine(setup):
    """y (direction -1) has a switch at machine position 1 mm: its drive's negative limit switch
    (0x60FD bit 0), reported by the other process in TPDO4. y moves onto it at 10 mm/s: the machine
    stops within a bounded number of SYNCs, y, node 2 and the switch named, and stays stopped."""
    _drives, master = setup(4.0, "standard", "--limit", "y=:1")
    master.boot()
    master.enable()
    start = master.positions()
    assert start[1] == pytest.approx(0.0, abs=1e-3)
    runner = stream(master, lambda t: [start[0], start[1] + 10.0 * t, start[2]], 1.0, fault_on_late=False)
    assert runner.join(30.0) and runner.error is None
    f = master.fault
    assert f is not None and (f.node, f.axis) == (2, "y"), f
    assert "negative limit switch" in f.reason and "not re-enabled" in f.reason
    # 0.04 mm per 4 ms SYNC: the last target sent is at most 25 SYNCs (100 ms, the other process on a
    # loaded machine) past the switch
    assert 1.0 < master.positions()[1] <= 1.0 + 25 * 0.04
    assert master.feedback().digital_inputs[1] & 0x1
    for _ in range(50):
        master.cycle(None)
        time.sleep(0.002)
    states = [decode(master._statusword(d)) for d in master.drives]  # by SDO, from the drives
    assert State.OPERATION_ENABLED not in states, states


def test_touch_probe_of_a_drive_in_the_drive_process_latches_within_one_count(tmp_path):
    """z's drive in the other process has its probe input at Z-1.23457 (``--probe``); z moves down
    through it at 10 mm/s (0.04 mm per 4 ms SYNC): the master sees the latch in TPDO4 and reads a
    position within one count (0.2 µm at 5000 counts/mm) of the trip point."""
    from fieldbus.canopen.touch_probe import TouchProbe

    height = -1.23457
    path = machine_file(tmp_path, "udp_multicast", group(), 4.0)
    path.write_text(path.read_text() + "touch_probe = 1\n")  # [canopen.axes.z] is the file's last table
    config = canopen_from_file(load_toml(path), str(path))
    drives = DriveProcess(path, "--probe", f"z={height}")
    master = CanopenMaster(config)
    try:
        master.boot()
        master.enable()
        probe = TouchProbe.of(master)
        assert probe is not None and probe.axis == "z"
        probe.arm(toward=True)
        start = master.positions()
        seen: list[float] = []

        def path_at(t: float) -> list[float]:
            if probe.tripped and not seen:
                seen.append(t)
            return [start[0], start[1], start[2] - 10.0 * min(t, 0.2)]

        runner = stream(master, path_at, 0.6, fault_on_late=False)
        assert runner.join(30.0) and runner.error is None
        assert master.fault is None, master.fault
        assert seen, "the latch never reached the master"
        result = probe.result()
        assert result.tripped and abs(result.position - height) <= 1.0001 / 5000
    finally:
        master.shutdown()
        drives.stop()
