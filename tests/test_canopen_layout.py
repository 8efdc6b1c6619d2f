"""PDO layouts (standard and compact), the bus budget they make, and the CPU latency request."""

from __future__ import annotations

import gc
import logging
import os
import time

import can
import pytest
from canopen_helpers import Rig, make_config, wait_for

from fieldbus.canopen import cia402
from fieldbus.canopen.busload import bus_load, frame_bits
from fieldbus.canopen.cia402 import State
from fieldbus.canopen.clock import CpuLatencyRequest, PeriodicRunner
from fieldbus.canopen.config import CanBusConfig
from fieldbus.canopen.drive_sim import SimDrive
from fieldbus.canopen.dump import describe
from fieldbus.canopen.master import BusBudgetError, CanopenError, CanopenMaster
from fieldbus.canopen.pdo import make_layout

pytestmark = pytest.mark.timeout(60)




class Recorder(can.Listener):
    """Every frame on the rig's virtual channel, from a second bus."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.frames: list[tuple[int, bytes]] = []
        self.notifier = can.Notifier(self.bus, [self])

    def on_message_received(self, msg: can.Message) -> None:
        self.frames.append((msg.arbitration_id, bytes(msg.data)))

    def close(self) -> None:
        self.notifier.stop()
        self.bus.shutdown()


# ---------------------------------------------------------------- layouts and the budget
def test_layouts_map_the_objects_the_issue_names():
    for name in ("standard", "compact"):
        lay = make_layout(name, 3)
        rx = {e[0] for p in lay.rpdos for e in p.entries}
        tx = {e[0] for p in lay.tpdos for e in p.entries}
        assert rx == {0x607A, 0x6040}
        assert tx == {0x6041, 0x6064, 0x60F4, 0x60FD}
        fe = lay.carrying((0x60F4, 0, 32), tpdo=True)
        assert fe.transmission == 3
        # the limit switches: on change only, so no cyclic load on the bus budget
        di = lay.carrying((0x60FD, 0, 32), tpdo=True)
        assert (di.transmission, di.event_timer_ms) == (255, 0)
    compact = make_layout("compact", 1, 50)
    sw = compact.carrying((0x6041, 0, 16), tpdo=True)
    assert (sw.transmission, sw.event_timer_ms) == (255, 50)
    with pytest.raises(ValueError, match="1 to 240"):
        make_layout("standard", 0)
    with pytest.raises(ValueError, match="unknown PDO layout"):
        make_layout("tiny")


def test_sdo_steps_disable_before_mapping_and_enable_last():
    steps = make_layout("compact", 4).sdo_steps(5)
    tpdo3 = [(what, index, sub, value) for what, index, sub, _, value in steps if what.startswith("TPDO3")]
    assert tpdo3[0] == ("TPDO3 COB-ID (disable)", 0x1802, 1, 0x80000385)
    assert tpdo3[-1] == ("TPDO3 COB-ID", 0x1802, 1, 0x385)
    assert ("TPDO3 event timer", 0x1802, 5, 100) in tpdo3
    assert ("TPDO3 map 0x6041", 0x1A02, 1, 0x60410010) in tpdo3
    unused = [(p.tpdo, p.number) for p in make_layout("compact").unused_pdos()]
    assert unused == [(False, 3), (False, 4)]


def _bits(data_bytes: int) -> int:
    # classic CAN, 11-bit id: 47 bits around the data, worst-case stuffing of the 34 + 8n stuffable bits
    return 47 + 8 * data_bytes + (34 + 8 * data_bytes - 1) // 4


def test_bus_load_of_each_layout_worked_out_by_hand():
    hb = 100  # ms, drives and master
    # standard, 6 drives at 2 ms: SYNC + per drive 6-byte RPDO, 6-byte TPDO, 4-byte TPDO each SYNC
    std = (_bits(0) + 6 * (2 * _bits(6) + _bits(4))) / 0.002 + 7 * _bits(1) * 1000 / hb
    assert bus_load(6, 0.002, 1_000_000, hb, hb, make_layout("standard")).bits_per_s == pytest.approx(std)
    assert std / 1e6 > 1.0  # the issue's mapping cannot carry 6 drives at 2 ms on 1 Mbit/s
    # compact, following error every 4th SYNC, status refreshed every 100 ms
    cmp_ = ((_bits(0) + 6 * (2 * _bits(4) + _bits(4) / 4)) / 0.002 + 6 * _bits(2) * 10
            + 7 * _bits(1) * 1000 / hb)
    load = bus_load(6, 0.002, 1_000_000, hb, hb, make_layout("compact", 4))
    assert load.bits_per_s == pytest.approx(cmp_)
    assert cmp_ / 1e6 < 0.70
    assert frame_bits(8) == _bits(8)


def test_over_budget_is_refused_with_settings_that_fit():
    config = make_config(6, bus=CanBusConfig("socketcan", "can0", 1_000_000))
    with pytest.raises(BusBudgetError) as err:
        CanopenMaster(config)
    text = str(err.value)
    assert "100.7 %" in text and "standard PDO layout" in text
    assert 'pdo_layout = "compact" with following_error_every = 4 (67.8 %)' in text
    assert "cycle_ms = 3" in text
    ok = make_config(6, bus=CanBusConfig("socketcan", "can0", 1_000_000), pdo_layout="compact",
                     following_error_every=4)
    assert CanopenMaster(ok).load.fraction < 0.70  # built, not opened: no bus needed


# ---------------------------------------------------------------- the compact layout on the bus
def test_compact_layout_frames_per_cycle(rig):
    r = rig(2, pdo_layout="compact", following_error_every=4, status_refresh_ms=1000)
    for node in (1, 2):
        sim = r.sim(node)
        assert [(p.cob_id, p.entries) for p in sim._rpdos] == [
            (0x200 + node, ((0x607A, 0, 4),)), (0x300 + node, ((0x6040, 0, 2),))]
        assert [(p.cob_id, p.transmission) for p in sim._tpdos] == [
            (0x180 + node, 1), (0x280 + node, 4), (0x380 + node, 255), (0x480 + node, 255)]
        # the PDOs the layout does not use are disabled: a factory mapping adds nothing
        assert sim._value(0x1403, 1) & 0x80000000 and sim._value(0x1402, 1) & 0x80000000
    rec = Recorder(r.config.bus.channel)
    try:
        start = r.master.positions()
        r.run(200, lambda k: [start[0] + 0.002 * k, start[1]])
        assert wait_for(lambda: sum(c == 0x80 for c, _ in rec.frames) >= 200, 2.0)
        syncs = sum(c == 0x80 for c, _ in rec.frames)
        assert wait_for(lambda: sum(c == 0x182 for c, _ in rec.frames) >= syncs, 2.0)
        cobs = [c for c, _ in rec.frames]
        for node in (1, 2):
            # every SYNC: one target and one position; the drive answers every SYNC it sees
            assert cobs.count(0x200 + node) == 200
            assert cobs.count(0x180 + node) == syncs
            assert cobs.count(0x300 + node) == 0  # the controlword only on a change
            assert syncs / 4 - 2 <= cobs.count(0x280 + node) <= syncs / 4 + 2
            assert cobs.count(0x380 + node) <= 2  # nothing changed; the 1 s refresh at most once
            assert cobs.count(0x480 + node) == 0  # digital inputs: on a change only
        fb = r.master.feedback()
        assert fb.positions[0] == pytest.approx(start[0] + 0.002 * 199, abs=0.01)
        assert fb.following_errors[0] > 0  # the value arrived, every 4th SYNC
        assert describe(0x181, rec.frames[[c for c, _ in rec.frames].index(0x181)][1],
                        r.master.layout).startswith("TPDO1 node 1")
    finally:
        rec.close()


def test_compact_quick_stop_sends_the_controlword_rpdo(rig):
    r = rig(2, pdo_layout="compact")
    rec = Recorder(r.config.bus.channel)
    try:
        r.run(10)
        r.master.quick_stop("test")
        assert wait_for(lambda: all(r.sim(n).state == State.QUICK_STOP_ACTIVE for n in (1, 2)), 2.0)
        cw = [d for c, d in rec.frames if c == 0x301]
        assert cw == [cia402.CW_QUICK_STOP.to_bytes(2, "little")]
        # the drive's statusword change comes back at once as an event TPDO
        assert wait_for(lambda: cia402.decode(r.master.state[0].statusword) == State.QUICK_STOP_ACTIVE, 2.0)
    finally:
        rec.close()


def test_compact_drive_leaving_operation_enabled_is_seen_by_the_event_tpdo(rig):
    r = rig(2, pdo_layout="compact", status_refresh_ms=60000)
    r.run(10)
    r.sim(2).inject_disable()
    r.run(10)
    assert r.master.fault is not None and r.master.fault.node == 2
    assert "left Operation enabled" in r.master.fault.reason


def test_compact_following_error_fault_does_not_wait_for_the_sparse_pdo(rig):
    sims = [SimDrive(1)]
    sims[0].fault_on_following_error = False  # the drive only reports: statusword bit 13
    r = rig(1, sims, pdo_layout="compact", following_error_every=240)
    r.sim(1).stall()
    t0 = time.monotonic()
    r.run(200, lambda k: [0.02 * k])  # 10 mm/s: past the 1 mm window after 0.1 s (50 cycles)
    assert r.master.fault is not None
    assert "bit 13" in r.master.fault.reason
    # well before the 240th SYNC, when the following-error PDO would first have shown it
    assert r.master.fault.time - t0 < 240 * 0.002


def test_a_drive_without_pdo_3_and_4_boots(rig):
    sims = [SimDrive(1)]
    for index in (0x1402, 0x1403, 0x1802, 0x1803):
        sims[0].abort_sdo(index, 1, 0x06020000)  # object does not exist
    r = rig(1, sims)
    assert r.master.state[0].state == State.OPERATION_ENABLED
    # no TPDO4 for the digital inputs: said, not refused
    assert any(w.node == 1 and "0x1803" in w.reason and "limit" in w.reason for w in r.master.warnings)


def test_other_aborts_while_disabling_a_pdo_stop_the_boot(rig):
    sims = [SimDrive(1)]
    sims[0].abort_sdo(0x1803, 1, 0x08000020)
    r = rig(1, sims, up=False)
    with pytest.raises(CanopenError,
                       match=r"node 1 \(axis x\).*0x1803:01 \(TPDO4 COB-ID \(disable\)\).*0x08000020"):
        r.master.boot()


def test_dump_decodes_the_compact_layout():
    lay = make_layout("compact")
    assert describe(0x181, (-1234).to_bytes(4, "little", signed=True), lay).endswith("position -1234")
    assert describe(0x381, (0x1237).to_bytes(2, "little"), lay).endswith(
        "statusword 0x1237 (Operation enabled)")
    assert describe(0x201, (10000).to_bytes(4, "little"), lay).endswith("target 10000")
    assert describe(0x301, (0x000F).to_bytes(2, "little"), lay).endswith("controlword 0x000F")


# ---------------------------------------------------------------- CPU latency request
def test_runner_holds_the_cpu_latency_request_while_it_runs(tmp_path, monkeypatch):
    qos = tmp_path / "cpu_dma_latency"
    qos.write_bytes(b"")
    monkeypatch.setattr(CpuLatencyRequest, "PATH", str(qos))
    seen: list[bool] = []
    # assigned before start: the first step can run before start() returns (a race seen once in CI)
    runner = PeriodicRunner(0.002, lambda k, t: seen.append(runner.cpu_latency.held), cycles=5,
                            cpu_latency_us=0)
    runner.start()
    assert runner.join(5.0)
    assert runner.cpu_latency_held and seen == [True] * 5
    assert qos.read_bytes() == (0).to_bytes(4, "little", signed=True)
    assert not runner.cpu_latency.held  # released at the end


def test_runner_runs_without_the_cpu_latency_request(tmp_path, monkeypatch, caplog):
    caplog.set_level(logging.INFO, logger="fieldbus.canopen.clock")
    monkeypatch.setattr(CpuLatencyRequest, "PATH", str(tmp_path / "missing"))
    runner = PeriodicRunner(0.002, lambda k, t: None, cycles=5, cpu_latency_us=0).start()
    assert runner.join(5.0)
    assert not runner.cpu_latency_held and runner.stats.cycles == 5
    assert "no CPU latency request" in caplog.text


# ---------------------------------------------------------------- the machine file
def _read(extra: dict) -> object:
    from motiond.config_canopen import read_canopen
    from motiond.configkit import Table

    data = {"canopen": {"axes": {"x": {"node_id": 1}}, **extra}}
    return read_canopen(Table(data, "m.toml"), ["x"], 0.002)


def test_machine_file_chooses_the_layout_and_the_cycle_thread_settings():
    c = _read({"pdo_layout": "compact", "following_error_every": 4, "status_refresh_ms": 50,
               "realtime_priority": 80, "cpu_latency_us": -1})
    assert (c.pdo_layout, c.following_error_every, c.status_refresh_ms) == ("compact", 4, 50)
    assert (c.realtime_priority, c.cpu_latency_us) == (80, None)
    assert c.layout.carrying((0x6041, 0, 16), tpdo=True).event_timer_ms == 50
    d = _read({})
    assert (d.pdo_layout, d.following_error_every, d.realtime_priority, d.cpu_latency_us) == (
        "standard", 1, 0, 0)
    assert (d.cpu_affinity, d.steer_gc) == ((), True)
    e = _read({"cpu_affinity": [1, 0], "steer_gc": False})
    assert (e.cpu_affinity, e.steer_gc) == ((1, 0), False)


@pytest.mark.parametrize("key, value, message", [
    ("pdo_layout", "tiny", "canopen.pdo_layout: must be one of standard, compact"),
    ("following_error_every", 0, "canopen.following_error_every"),
    ("realtime_priority", 100, "canopen.realtime_priority"),
    ("cpu_affinity", 1, "canopen.cpu_affinity: must be list"),
    ("cpu_affinity", [0, "1"], "canopen.cpu_affinity: must be a list of CPU numbers 0-4095, '1' is not one"),
    ("cpu_affinity", [-1], "canopen.cpu_affinity: .*-1 is not one"),
    ("cpu_affinity", [1, 1], "canopen.cpu_affinity: must not list a CPU twice"),
    ("steer_gc", "yes", "canopen.steer_gc: must be bool"),
])
def test_machine_file_mistakes_name_the_key(key, value, message):
    from motiond.configkit import ConfigError

    with pytest.raises(ConfigError, match=message):
        _read({key: value})


def test_enable_right_after_a_quick_stop_waits_for_the_ramp(rig):
    """Quick stop active -> Operation enabled is taken only once the stop ramp has ended: enable()
    straight after reset_faults() must wait for it, then hold where the axis stopped (no jump)."""
    r = rig(2)
    start = r.master.positions()
    r.run(100, lambda k: [start[0] + 0.2 * k, start[1] + 0.2 * k])  # 100 mm/s
    r.master.quick_stop("test")
    r.master.reset_faults()
    r.master.enable()  # the drives are still on their 5000 mm/s^2 ramp (20 ms) here
    assert [s.state for s in r.master.state] == [State.OPERATION_ENABLED] * 2
    held = r.master.positions()
    r.run(50)
    assert r.master.fault is None
    for node, p in zip((1, 2), held, strict=True):
        assert r.sim(node).actual / 10000 == pytest.approx(p, abs=1e-3)


def test_a_failed_homing_leaves_the_drive_in_csp_holding_where_it_stopped(rig):
    """A homing that times out must not leave the drive homing by itself: the master stops it, waits
    for its standstill, puts it back in cyclic synchronous position, and the axis streams again
    without a jump."""
    import dataclasses

    class Watched(SimDrive):
        """Notes the highest position while homing, and whether it still moved when the master
        switched it back to CSP (0x6060 by SDO; this drive would then stop at once, a real one would
        do what its maker chose)."""

        highest = 0.0
        moving_at_mode_change: tuple[bool, ...] = ()

        def _homing_step(self, dt: float) -> None:
            super()._homing_step(dt)
            self.highest = max(self.highest, self.actual)

        def _on_write(self, index: int, subindex: int, od: object, data: bytes) -> None:
            if index == 0x6060:
                self.moving_at_mode_change += (self._homing,)
            super()._on_write(index, subindex, od, data)

    sims = [Watched(1, home_switch_counts=10**8)]  # a switch the drive never reaches
    cfg = make_config(1, homing="cia402", homing_timeout_s=0.3)
    cfg = dataclasses.replace(cfg, drives=(dataclasses.replace(cfg.drives[0], homing_method=19),))
    r = Rig(cfg, sims)
    try:
        r.up()
        runner = PeriodicRunner(cfg.cycle_s, lambda k, t: r.master.cycle(None), cycles=1000,
                                late_s=1.0).start()
        try:
            with pytest.raises(CanopenError, match="homing not attained"):
                r.master.home("x")
        finally:
            runner.stop()
            assert runner.join(5.0)
        sim = r.sim(1)
        assert sim.mode == cia402.MODE_CSP and not sim._homing
        moved = sim.actual
        assert abs(moved) > 1000  # it did travel before the timeout
        # it ramped down (0x609A) after the stop and holds where it stood: not taken back to a position
        # read while it still moved, nor stopped short by the mode change
        assert moved == pytest.approx(sim.highest, abs=2)
        assert sim.moving_at_mode_change[-1:] == (False,)  # back to CSP once it stood
        held = r.master.positions()[0]
        assert held * 10000 == pytest.approx(moved, abs=2)
        r.run(20, lambda k: [held + 0.001 * k])
        r.run(10, lambda k: [held + 0.019])  # and holds there: the drive settles whatever the load
        assert r.master.fault is None, r.master.fault  # no jump: a simulated drive faults on one
        assert sim.actual == pytest.approx(moved + 190, abs=30)  # 19 * 0.001 mm, minus the servo lag
    finally:
        r.close()


def test_the_daemon_runs_its_cycle_thread_as_the_machine_file_says(tmp_path, monkeypatch):
    from motiond.config import load_machine
    from motiond.runtime import Machine

    qos = tmp_path / "cpu_dma_latency"
    qos.write_bytes(b"")
    monkeypatch.setattr(CpuLatencyRequest, "PATH", str(qos))
    machine_file = tmp_path / "m.toml"
    cpu = max(os.sched_getaffinity(0))
    machine_file.write_text(f"""
[axes.x]
max_velocity = 100.0
max_acceleration = 1000.0
max_jerk = 10000.0
[canopen]
simulate = true
realtime_priority = 1
cpu_latency_us = 25
cpu_affinity = [{cpu}]
[canopen.axes.x]
node_id = 1
""")
    m = Machine(load_machine(str(machine_file)), lc=None).start()
    try:
        runner = m.runner
        assert runner.realtime_priority == 1
        assert runner.cpu_latency is not None and runner.cpu_latency.us == 25
        assert wait_for(lambda: runner.cpu_latency_held, 2.0)
        assert qos.read_bytes() == (25).to_bytes(4, "little")
        assert runner.steer_gc and not gc.isenabled()  # collections only in the cycle's slack
        assert runner.affinity_applied and os.sched_getaffinity(runner.native_id) == {cpu}
    finally:
        m.shutdown()
    assert gc.isenabled()
    assert not runner.cpu_latency.held


def test_fitting_layouts_prefer_the_following_error_every_sync():
    from fieldbus.canopen.busload import fitting_layouts

    def names(n: int, cycle: float) -> list[tuple[str, int]]:
        return [(lay.name, lay.following_error_every)
                for lay, _ in fitting_layouts(n, cycle, 1_000_000, 0.70, 100, 100)]

    assert names(3, 0.002) == [("standard", 1), ("compact", 1)]
    assert names(6, 0.002) == [("compact", 4)]  # standard cannot: 71.7 % even without following error
    assert names(6, 0.001) == []
