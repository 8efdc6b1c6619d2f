"""The CANopen master against simulated CiA 402 drives on python-can's virtual bus (one process)."""

from __future__ import annotations

import dataclasses
import logging
import time

import can
import pytest
from canopen_helpers import Rig, make_config, unique_channel, wait_for

from fieldbus.canopen import cia402
from fieldbus.canopen.cia402 import State
from fieldbus.canopen.clock import PeriodicRunner
from fieldbus.canopen.config import CanBusConfig
from fieldbus.canopen.drive_sim import EMCY_VELOCITY, SimDrive
from fieldbus.canopen.master import CanopenError

pytestmark = pytest.mark.timeout(60)




def test_boot_configures_drives_and_enables(rig):
    r = rig(3)
    assert [s.state for s in r.master.state] == [State.OPERATION_ENABLED] * 3
    for node in (1, 2, 3):
        sim = r.sim(node)
        assert sim.mode == cia402.MODE_CSP
        assert [p.cob_id for p in sim._rpdos] == [0x200 + node]
        assert [p.entries for p in sim._rpdos] == [((0x607A, 0, 4), (0x6040, 0, 2))]
        assert [p.cob_id for p in sim._tpdos] == [0x180 + node, 0x280 + node, 0x480 + node]
        assert sim._value(0x1017) == 100
        assert sim._value(0x1016, 1) == (127 << 16) | 300
        assert sim._value(0x60C2, 1) == 2 and sim._value(0x60C2, 2) == -3
        assert sim._value(0x6065) == 10000  # 1.0 mm window at 10000 counts/mm


def test_streaming_sends_counts_and_reads_back_positions(rig):
    r = rig(2, direction=-1, home_offset=2.0)
    r.master.home("x")  # "set": here (count 0) is machine position 2.0
    assert r.master.positions()[0] == pytest.approx(2.0)
    start = r.master.positions()
    r.run(150, lambda k: [start[0] + 0.01 * min(k, 100), start[1]])
    r.run(40)  # hold: the lag settles
    sim = r.sim(1)
    # 3.0 mm at 10000 counts/mm, direction -1, home (2.0 mm) at count 0: -10000 counts
    assert sim.target == -10000
    fb = r.master.feedback()
    assert fb.positions[0] == pytest.approx(3.0, abs=1e-4)
    assert fb.positions[1] == pytest.approx(start[1], abs=1e-4)
    assert fb.fault is None
    assert sim.missed_setpoints == 0
    # Every one of the 190 SYNCs reaches the drive; its reader thread may still be a few frames behind
    # the master when run() returns, so give delivery a bounded moment before counting.
    deadline = time.monotonic() + 2.0
    while sim.syncs < 190 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert sim.syncs >= 190


def test_following_error_is_reported(rig):
    r = rig(1)
    r.run(60, lambda k: [0.005 * k])  # 2.5 mm/s with a 2 ms lag: about 0.005 mm behind
    fe = r.master.feedback().following_errors[0]
    assert 0.002 < fe < 0.02
    assert r.master.state[0].following_error == fe


def test_each_cycle_sends_the_sync_first_then_every_drives_target_for_the_next_sync(rig):
    """The master's SYNC goes out first in each cycle, then one RPDO per drive; the drives latch those
    targets at the next SYNC (the next cycle's), all of them at the same one."""
    r = rig(3, up=False)
    spy = can.Bus(interface="virtual", channel=r.config.bus.channel, receive_own_messages=False)
    try:
        r.master.boot()
        r.master.enable()
        # no cycle ran during the enable here (the daemon's runs all along): the first SYNC finds no
        # target yet, the second latches the first cycle's
        r.run(1)
        for s in r.sims.drives.values():
            s.record_targets = True
        time.sleep(0.05)  # no cycle runs: the drives' SYNC counts stand still
        while spy.recv(timeout=0) is not None:
            pass
        first = {n: r.sim(n).syncs + 1 for n in (1, 2, 3)}  # each drive's number of the run's first SYNC
        missed = [r.sim(n).missed_setpoints for n in (1, 2, 3)]
        r.run(50, lambda k: [0.001 * (k + 1), -0.001 * (k + 1), 0.002 * (k + 1)])
        frames = []
        while (m := spy.recv(timeout=0)) is not None and len(frames) < 100000:
            if m.arbitration_id == 0x80 or 0x200 <= m.arbitration_id < 0x280:  # SYNC, RPDO1s
                frames.append(m.arbitration_id)
    finally:
        spy.shutdown()
    # the first frame is a SYNC; after each SYNC exactly one RPDO per drive, before the next SYNC
    assert frames[0] == 0x80
    cycles: list[list[int]] = []
    for cob in frames:
        if cob == 0x80:
            cycles.append([])
        else:
            cycles[-1].append(cob)
    assert len(cycles) == 50
    assert all(sorted(c) == [0x201, 0x202, 0x203] for c in cycles)
    # the drives' reader thread may still be on the last SYNCs on a loaded machine
    assert wait_for(lambda: all(r.sim(n).syncs >= first[n] + 49 for n in (1, 2, 3)), 2.0)
    counts = r.master.drives[0].scale.to_counts
    latched = [dict(r.sim(n).latched) for n in (1, 2, 3)]
    for k in range(49):  # cycle k's targets at the drives' SYNC of cycle k + 1
        assert latched[0][first[1] + k + 1] == counts(0.001 * (k + 1))
        assert latched[1][first[2] + k + 1] == -latched[0][first[1] + k + 1]
        assert latched[2][first[3] + k + 1] == 2 * latched[0][first[1] + k + 1]
    assert [r.sim(n).missed_setpoints for n in (1, 2, 3)] == missed


def test_drives_enabled_while_the_cycle_runs_miss_no_setpoint(rig):
    """The cycle runs (SYNC, then the RPDOs for the next one) while the drives are enabled by SDO, one
    by one: the enable command lands between a cycle's RPDO and the next SYNC, and that SYNC latches
    the RPDO's target (a drive keeps the last 0x607A it received). No SYNC goes without a setpoint."""
    r = rig(3, up=False)
    r.master.boot()
    runner = PeriodicRunner(r.config.cycle_s, lambda k, t: r.master.cycle(None), cycles=3000,
                            late_s=1.0).start()
    try:
        r.master.enable()
        assert wait_for(lambda: all(r.sim(n).syncs > 100 for n in (1, 2, 3)), 5.0)
    finally:
        runner.stop()
        assert runner.join(5.0)
    assert r.master.fault is None, r.master.fault
    assert [r.sim(n).state for n in (1, 2, 3)] == [State.OPERATION_ENABLED] * 3
    assert [r.sim(n).missed_setpoints for n in (1, 2, 3)] == [0, 0, 0]


def test_emcy_stops_all_axes_names_the_node_and_can_be_reset(rig):
    r = rig(3)
    r.run(50, lambda k: [0.002 * k, 0.001 * k, 0.0])
    held = r.master.positions()
    # the last target a SYNC latched: cycle 48's (cycle 49's went out after the last SYNC, for the next)
    latched = 0.002 * 48
    r.sim(2).inject_fault(0x2310)
    assert wait_for(lambda: r.master.fault is not None, 2.0)
    f = r.master.fault
    assert (f.node, f.axis) == (2, "y")
    assert "EMCY 0x2310" in f.reason
    r.run(50, lambda k: [50.0, 50.0, 50.0])  # ignored: the master holds
    assert r.master.positions() == held
    # standard layout: quick stop option 2, the stop ends in Switch on disabled (never re-enabled by
    # the cyclic controlword)
    assert r.sim(1).state == State.SWITCH_ON_DISABLED
    assert r.sim(3).state == State.SWITCH_ON_DISABLED
    assert r.sim(2).state == State.FAULT
    assert abs(r.sim(1).target - round(latched * 10000)) <= 10  # stopped where its last SYNC left it
    with pytest.raises(CanopenError, match="reset_faults"):
        r.master.enable()
    r.master.reset_faults()
    r.master.enable()
    assert r.master.fault is None
    start = r.master.positions()
    r.run(30, lambda k: [start[0] + 0.001 * k, start[1], start[2]])
    assert r.master.fault is None
    assert [s.state for s in r.master.state] == [State.OPERATION_ENABLED] * 3


def test_missed_heartbeat_is_a_fault(rig):
    r = rig(2, heartbeat_producer_ms=50, heartbeat_consumer_ms=150)
    r.sim(2).drop_heartbeat(2.0)
    r.run(200)
    assert r.master.fault is not None
    assert r.master.fault.node == 2
    assert "heartbeat missed" in r.master.fault.reason


def test_a_stalled_axis_faults_on_following_error(rig):
    r = rig(1)
    r.sim(1).stall()
    r.run(300, lambda k: [0.02 * k])  # 10 mm/s: past the 1 mm window after 0.1 s
    assert r.master.fault is not None
    assert "following error" in r.master.fault.reason or "0x8611" in r.master.fault.reason


def test_master_checks_the_following_error_window_itself(rig):
    r = rig(1)
    r.sim(1).node.data_store.setdefault(0x6065, {})[0] = (0xFFFFFFFF).to_bytes(4, "little")
    r.sim(1)._params_dirty = True  # the drive's own check is off; the master's must catch it
    r.sim(1).stall()
    r.run(300, lambda k: [0.02 * k])
    assert r.master.fault is not None
    assert "following error" in r.master.fault.reason and "beyond its window 1" in r.master.fault.reason
    assert r.sim(1).emcys == []


def test_a_drive_leaving_operation_enabled_is_a_fault(rig):
    r = rig(2)
    r.run(10)
    r.sim(1).inject_disable()
    for _ in range(50):  # bounded: a loaded machine may hold the TPDO back a few cycles
        r.run(2)
        if r.master.fault is not None:
            break
    assert r.master.fault is not None and r.master.fault.node == 1
    assert "left Operation enabled" in r.master.fault.reason
    assert "Switch on disabled" in r.master.fault.reason
    assert "disabled itself" in r.master.fault.reason
    for _ in range(50):  # bounded: the other drive's reader takes the quick stop when it is scheduled
        if r.sim(2).state in (State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED):
            break
        r.run(1)
    assert r.sim(2).state in (State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED)  # its quick stop
    assert r.sim(2).controlword == 0x0002


def test_a_setpoint_jump_faults_the_drive(rig):
    r = rig(1, max_velocity=100.0)
    r.run(5)
    r.run(5, lambda k: [10.0])  # 10 mm in 2 ms: 5 m/s
    assert wait_for(lambda: r.master.fault is not None, 1.0)
    assert f"EMCY 0x{EMCY_VELOCITY:04X}" in r.master.fault.reason
    assert r.sim(1).state == State.FAULT


def test_sync_without_a_setpoint_and_late_sync_are_counted(rig):
    r = rig(1)
    r.run(20)
    sim = r.sim(1)
    missed, late = sim.missed_setpoints, sim.late_syncs
    spy = can.Bus(interface="virtual", channel=r.config.bus.channel)
    try:
        # the first latches the last cycle's target (sent after its SYNC, for the next); the second
        # finds none
        for _ in range(2):
            spy.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
    finally:
        spy.shutdown()
    assert wait_for(lambda: sim.missed_setpoints == missed + 1, 1.0)
    time.sleep(0.02)  # ten periods without SYNC
    r.run(3)
    assert sim.late_syncs > late


@pytest.mark.parametrize("layout, ends_in", [("compact", State.QUICK_STOP_ACTIVE),
                                              ("standard", State.SWITCH_ON_DISABLED)])
def test_quick_stop_holds_position_and_reenables(rig, layout, ends_in):
    """compact: quick stop option 6, the drives hold the position in Quick stop active; standard:
    option 2 (its cyclic 0x0F would undo option 6), the stop ends in Switch on disabled."""
    r = rig(2, pdo_layout=layout)
    r.run(100, lambda k: [0.01 * k, 0.0])
    r.master.quick_stop()
    r.run(50)
    assert wait_for(lambda: [s.state for s in r.sims.drives.values()] == [ends_in] * 2, 1.0)
    assert r.master.fault is not None and "quick stop requested" in r.master.fault.reason
    assert r.sim(1).velocity == 0.0
    r.master.reset_faults()
    r.master.enable()
    assert r.master.state[0].state == State.OPERATION_ENABLED


def test_bus_error_on_send_is_a_fault(rig):
    r = rig(1)
    r.run(5)

    def broken(msg, timeout=None):
        raise can.CanOperationError("bus off")

    r.master.network.bus.send = broken
    r.run(2)
    assert r.master.fault is not None and "bus error" in r.master.fault.reason


def test_homing_cia402_current_position_and_switch(rig):
    sims = [SimDrive(1), SimDrive(2, home_switch_counts=20000)]
    cfg = make_config(2, homing="cia402", home_offset=-1.0)
    y = dataclasses.replace(cfg.drives[1], homing_method=19)
    cfg = dataclasses.replace(cfg, drives=(cfg.drives[0], y))
    r = Rig(cfg, sims)
    try:
        r.up()
        runner = PeriodicRunner(r.config.cycle_s, lambda k, t: r.master.cycle(None), cycles=3000,
                                late_s=1.0).start()
        try:
            assert r.master.home("x") == pytest.approx(-1.0)  # method 35: here is home
            t = time.monotonic()
            assert r.master.home("y") == pytest.approx(-1.0)  # method 19: travel to the switch
            assert time.monotonic() - t > 0.1  # 20000 counts at the EDS's 100000 counts/s
        finally:
            runner.stop()
            assert runner.join(5.0)
        assert r.master.fault is None, r.master.fault
        assert r.sim(2).mode == cia402.MODE_CSP
        assert r.sim(2)._value(0x6098) == 19
        r.run(5)
        assert r.master.feedback().positions == pytest.approx((-1.0, -1.0), abs=1e-4)
        r.run(20, lambda k: [-1.0 + 0.001 * k, -1.0])
        assert r.master.fault is None
    finally:
        r.close()


def test_sdo_abort_during_boot_names_node_and_object(rig):
    r = rig(2, up=False)
    r.sim(2).abort_sdo(0x60C2, 1, 0x06090030)
    with pytest.raises(CanopenError) as e:
        r.master.boot()
    msg = str(e.value)
    assert "node 2 (axis y)" in msg and "0x60C2:01" in msg and "0x06090030" in msg


def test_sdo_timeout_during_boot(rig):
    r = rig(1, up=False, sdo_timeout_s=0.1)
    r.sim(1).sdo_silent.add(0x6065)
    with pytest.raises(CanopenError, match=r"node 1 \(axis x\): SDO write of 0x6065:00 .* timed out"):
        r.master.boot()


def test_slow_boot_is_waited_for_and_a_missing_drive_is_named(rig):
    r = rig(1, sims=[SimDrive(1, boot_delay_s=0.3)], boot_timeout_s=2.0)
    assert r.master.state[0].state == State.OPERATION_ENABLED
    r2 = rig(2, sims=[SimDrive(1)], up=False, boot_timeout_s=0.3)
    with pytest.raises(CanopenError, match=r"node 2 \(axis y\): no boot-up message within 0.3 s"):
        r2.master.boot()


def test_identity_mismatch_is_refused(rig):
    r = rig(1, up=False, vendor_id=0x1234)
    with pytest.raises(CanopenError,
                       match=r"node 1 .*vendor id is 0x00000CA0, the configuration expects 0x00001234"):
        r.master.boot()


def test_a_drive_stuck_in_a_state_times_out_with_its_name(rig):
    r = rig(2, up=False, state_timeout_s=0.2)
    r.master.boot()
    r.sim(2).ignore_controlword = True
    with pytest.raises(CanopenError,
                       match=r"node 2 \(axis y\): stuck in 'Switch on disabled'.*'Ready to switch on'"):
        r.master.enable()


def test_late_cycle_is_detected_and_skipped_not_burst():
    calls: list[int] = []
    late: list[tuple[int, float]] = []

    def step(k: int, t: float) -> None:
        calls.append(k)
        if len(calls) == 6:
            time.sleep(0.03)  # a 30 ms stall in a 5 ms cycle

    runner = PeriodicRunner(0.005, step, cycles=20, on_late=lambda k, by: late.append((k, by))).start()
    assert runner.join(5.0)
    assert runner.error is None
    stalled = calls[5]
    assert stalled + 1 in [k for k, _ in late]  # the deadline after the stall is reported late
    assert runner.stats.skipped >= 4
    assert calls[6] - stalled >= 5  # deadlines gone are skipped, not made up in a burst
    assert len(calls) == 20  # ``cycles`` counts steps done


def test_second_order_dynamics_lag_and_settle(rig):
    r = rig(1, sims=[SimDrive(1, order=2, lag_s=0.003, damping=0.8)])
    r.run(100, lambda k: [0.01 * min(k, 50)])
    r.run(100, lambda k: [0.5])
    assert r.master.feedback().positions[0] == pytest.approx(0.5, abs=1e-3)


def test_bus_config_keeps_udp_multicast_local():
    kw = CanBusConfig("udp_multicast", "239.74.163.9").bus_kwargs()
    assert kw["hop_limit"] == 0
    assert unique_channel() != unique_channel()


def test_fault_reaction_completes_without_sync_and_reset_works(rig):
    r = rig(1)
    r.run(20, lambda k: [0.01 * k])
    r.sim(1).inject_fault(0x5000)
    # no cycle runs now: the drive's stop ramp runs on its own clock, and the reset needs no SYNC
    assert wait_for(lambda: r.sim(1).state == State.FAULT, 2.0)
    assert r.master.fault is not None and "EMCY 0x5000" in r.master.fault.reason
    r.master.reset_faults()
    r.master.enable()
    assert r.master.state[0].state == State.OPERATION_ENABLED


def test_drives_fault_when_the_master_heartbeat_stops(rig):
    r = rig(2, heartbeat_producer_ms=20, heartbeat_consumer_ms=100)
    r.run(10)
    r.master._heartbeat_task.stop()  # as if the master process had died
    r.run(150)
    assert r.sim(1).emcys == [0x8130] and r.sim(2).emcys == [0x8130]
    assert r.master.fault is not None and "EMCY 0x8130" in r.master.fault.reason


def test_error_frames_on_the_bus_are_a_fault(rig):
    r = rig(1)
    r.run(5)
    spy = can.Bus(interface="virtual", channel=r.config.bus.channel)
    try:
        spy.send(can.Message(arbitration_id=0x20000004, is_error_frame=True, data=bytes(8)))
    finally:
        spy.shutdown()
    assert wait_for(lambda: r.master.fault is not None, 2.0)
    assert r.master.fault.node == 0 and "bus error frame" in r.master.fault.reason
    assert r.sim(1).controlword == 0x0002  # quick stop sent (the drive ends in Switch on disabled)


def test_a_position_beyond_the_soft_limits_is_refused(rig):
    r = rig(1, min_position=-1.0, max_position=10.0)
    r.run(5, lambda k: [0.001 * k])
    r.run(2, lambda k: [10.5])
    assert r.master.fault is not None and "beyond the soft limits [-1.0, 10.0]" in r.master.fault.reason
    assert r.sim(1).target < 100  # 10.5 mm never reached the drive


def test_disable_takes_the_drives_to_switch_on_disabled_and_back(rig):
    r = rig(2)
    r.run(5)
    r.master.disable()
    assert not r.master.streaming
    assert [s.state for s in r.sims.drives.values()] == [State.SWITCH_ON_DISABLED] * 2
    assert r.master.not_operational() == []
    r.master.enable()
    r.run(5)
    assert r.master.fault is None and r.master.state[1].state == State.OPERATION_ENABLED


def test_disable_stops_every_drive_when_one_quick_stop_cannot_be_sent(rig, caplog):
    """A bus error on the first drive's quick stop is logged; the next drive still gets its own, and
    both end disabled (before, the error left disable() half done, the second drive enabled)."""
    r = rig(2)
    r.run(5)
    bus = r.master.network.bus
    send = bus.send
    quick_stops = [d.controlword_rpdo(cia402.CW_QUICK_STOP) for d in r.master.drives]
    sent: list[tuple[int, bytes]] = []

    def broken_for_node_1(msg, timeout=None):
        frame = (msg.arbitration_id, bytes(msg.data))
        if frame == quick_stops[0]:
            raise can.CanOperationError("bus off")
        sent.append(frame)
        return send(msg, timeout)

    bus.send = broken_for_node_1
    with caplog.at_level(logging.ERROR):
        r.master.disable()
    bus.send = send
    assert "quick stop to node 1 (axis x) not sent: bus off" in caplog.text
    assert quick_stops[1] in sent  # the second drive's quick stop went out
    assert [s.state for s in r.sims.drives.values()] == [State.SWITCH_ON_DISABLED] * 2


def test_a_restarted_drive_is_seen_as_not_operational_and_boots_again(rig):
    r = rig(2)
    r.sims[2].power_on()  # power cycle: boot-up, pre-operational
    assert wait_for(lambda: r.master.not_operational() == ["node 2 (axis y)"], 2.0)
    r.master.boot()
    r.master.enable()
    r.run(5)
    assert r.master.fault is None and r.master.not_operational() == []


def test_a_fault_scheduled_at_a_time_happens_then(rig):
    r = rig(1)
    at = time.monotonic() + 0.3
    r.sim(1).inject_fault(0x3210, at=at)
    while time.monotonic() < at - 0.1:
        r.run(5)
    assert r.master.fault is None  # not yet
    while time.monotonic() < at + 0.2 and r.master.fault is None:
        r.run(5)
    assert r.master.fault is not None and "EMCY 0x3210" in r.master.fault.reason
    assert r.master.fault.time >= at


def test_homing_cia402_on_the_home_switch_with_the_machine_file_s_speeds(rig):
    """Method 19 on a home switch the drive reports (0x60FD bit 2, 5000 counts wide around 20000):
    the machine file's speeds go to 0x6099:1/2 and 0x609A in counts; the drive searches at 5 mm/s,
    slows to 1 mm/s on the switch, and ends on it, which the master's feedback shows."""
    sims = [SimDrive(1, home_switch_counts=20000, home_switch_window_counts=5000)]
    cfg = make_config(1, homing="cia402", homing_method=19, homing_speed=5.0, homing_speed_zero=1.0,
                      homing_acceleration=100.0)
    r = Rig(cfg, sims)
    try:
        r.up()
        runner = PeriodicRunner(r.config.cycle_s, lambda k, t: r.master.cycle(None), cycles=3000,
                                late_s=1.0).start()
        try:
            t = time.monotonic()
            assert r.master.home("x") == pytest.approx(0.0)
            # 15000 counts at 50000 counts/s, then 5000 at 10000 counts/s: 0.8 s at least
            assert time.monotonic() - t > 0.75
        finally:
            runner.stop()
            assert runner.join(5.0)
        sim = r.sim(1)
        assert (sim._value(0x6099, 1), sim._value(0x6099, 2), sim._value(0x609A)) == (50000, 10000, 1000000)
        assert r.master.fault is None, r.master.fault
        r.run(5)
        assert r.master.feedback().digital_inputs[0] & 0x4  # on the home switch
        assert r.master.fault is None, r.master.fault
    finally:
        r.close()
