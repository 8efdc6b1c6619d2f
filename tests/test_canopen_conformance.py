"""The master against drives that behave as strict third-party CiA 402 drives do (issue 12): a drive
that stops itself, shutdown, setpoints from the first SYNC in Operation enabled, optional objects,
EMCY classes, the drive's limits. On the virtual bus; the udp_multicast variants are in
``test_canopen_multiprocess.py``."""

from __future__ import annotations

import time

import pytest
from canopen_helpers import wait_for

from fieldbus.canopen.cia402 import State
from motiond.config_canopen import read_canopen
from motiond.configkit import ConfigError, Table


def _move(start: tuple[float, ...], k0: int = 0, speed: float = 50.0, period: float = 0.002):
    """A steady move of every axis at ``speed`` mm/s from ``start``: positions of cycle ``k``."""
    return lambda k: [p + speed * period * (k0 + k) for p in start]


@pytest.mark.parametrize("layout", ["standard", "compact"])
def test_a_drive_local_quick_stop_mid_move_stops_the_machine_and_is_never_undone(rig, layout):
    """A strict drive takes "enable operation" in Quick stop active at once (transition 16, legal with
    quick stop options 5-8). Its local quick-stop input is tapped mid-move: the master must see it
    within one SYNC, stop every axis, name node, state and reason, and never re-enable the drive."""
    r = rig(2, pdo_layout=layout)
    for sim in r.sims.drives.values():
        sim.reenable_during_quick_stop_ramp = True
    start = r.master.positions()
    r.run(60, _move(start, speed=100.0))
    time.sleep(0.01)  # the last SYNC's TPDOs are in: the master's latest statusword says enabled
    enables = r.sim(2).enables
    r.sim(2).set_quick_stop_input(True)
    r.sim(2).set_quick_stop_input(False)  # a tap: the input is released at once
    r.run(30, _move(start, 60, speed=100.0))
    f = r.master.fault
    assert f is not None, "the drive's own quick stop went unseen"
    assert (f.node, f.axis) == (2, "y")
    # the ramp (100 mm/s at 5000 mm/s^2: 20 ms) shows Quick stop active; a stalled reader thread may
    # see only its end (standard: Switch on disabled), which the reason names as a quick stop too
    assert "quick stop" in f.reason and "not re-enabled" in f.reason
    assert r.sim(2).enables == enables, "the master re-enabled a drive that stopped itself"
    r.run(30)
    assert r.sim(2).enables == enables
    assert wait_for(lambda: all(s.velocity == 0.0 for s in r.sims.drives.values()), 2.0)
    for node in (1, 2):
        assert r.sim(node).state != State.OPERATION_ENABLED
    # compact holds the position (option 6); standard ends in Switch on disabled (option 2)
    ends_in = State.QUICK_STOP_ACTIVE if layout == "compact" else State.SWITCH_ON_DISABLED
    assert wait_for(lambda: r.sim(2).state == ends_in, 2.0)


@pytest.mark.parametrize("layout", ["standard", "compact"])
def test_a_held_quick_stop_input_keeps_the_drive_stopped_until_released(rig, layout):
    r = rig(1, pdo_layout=layout)
    r.run(20)
    r.sim(1).set_quick_stop_input(True)
    r.run(20)
    f = r.master.fault
    # at rest the ramp is over at once: standard (option 2) may already show Switch on disabled
    assert f is not None and f.node == 1 and "not re-enabled" in f.reason
    assert "quick stop" in f.reason
    r.master.reset_faults()
    with pytest.raises(Exception, match="node 1"):
        r.master.enable()  # the input still holds the drive
    r.sim(1).set_quick_stop_input(False)
    r.master.reset_faults()
    r.master.enable()
    r.run(10)
    assert r.master.fault is None
    assert r.master.state[0].state == State.OPERATION_ENABLED


def test_the_standard_layout_writes_quick_stop_option_2_and_compact_6(rig):
    a = rig(1, pdo_layout="standard")
    b = rig(1, pdo_layout="compact")
    assert a.sim(1)._value(0x605A) == 2
    assert b.sim(1)._value(0x605A) == 6


def _canopen(axis: dict, layout: str = "standard") -> None:
    root = Table({"canopen": {"pdo_layout": layout, "axes": {"x": {"node_id": 1, **axis}}}}, "m.toml")
    return read_canopen(root, ["x"], 0.002)


def test_a_holding_quick_stop_option_is_refused_in_the_standard_layout():
    with pytest.raises(ConfigError, match=r"canopen\.axes\.x\.quick_stop_option.*compact"):
        _canopen({"quick_stop_option": 6})
    assert _canopen({"quick_stop_option": 6}, "compact").drives[0].quick_stop_option == 6
    assert _canopen({"quick_stop_option": 1}).drives[0].quick_stop_option == 1
    with pytest.raises(ConfigError, match="quick_stop_option"):
        _canopen({"quick_stop_option": 0})


@pytest.mark.parametrize("layout", ["standard", "compact"])
def test_shutdown_mid_move_leaves_the_drives_disabled_and_nothing_faults_afterwards(rig, layout):
    r = rig(2, pdo_layout=layout, heartbeat_producer_ms=20, heartbeat_consumer_ms=100)
    start = r.master.positions()
    r.run(60, _move(start, speed=100.0))
    r.master.shutdown()  # streaming: quick stop, ramp, disable, consumer heartbeat off, heartbeat off
    for node in (1, 2):
        assert r.sim(node).state == State.SWITCH_ON_DISABLED
        assert r.sim(node)._value(0x1016, 1) == 0
    time.sleep(0.5)  # five consumer times without the master's heartbeat
    assert [r.sim(n).emcys for n in (1, 2)] == [[], []]
    assert [r.sim(n).state for n in (1, 2)] == [State.SWITCH_ON_DISABLED] * 2


def test_shutdown_of_enabled_drives_not_streamed_to(rig):
    r = rig(1, heartbeat_producer_ms=20, heartbeat_consumer_ms=100)
    r.run(30)
    r.master.shutdown()
    time.sleep(0.4)
    assert r.sim(1).emcys == [] and r.sim(1).state == State.SWITCH_ON_DISABLED


def test_the_simulated_drive_watches_the_masters_heartbeat(rig):
    """What the shutdown test relies on: with 0x1016 armed, the drive faults when the heartbeat stops."""
    r = rig(1, heartbeat_producer_ms=20, heartbeat_consumer_ms=100)
    r.run(30)  # CiA 301: the consumer watch starts with the first heartbeat received
    r.master._heartbeat_task.stop()
    assert wait_for(lambda: r.sim(1).emcys == [0x8130], 2.0)


def test_disable_while_streaming_ramps_down_before_dropping_torque(rig):
    r = rig(1)
    start = r.master.positions()
    r.run(60, _move(start, speed=100.0))
    r.master.disable()
    sim = r.sim(1)
    assert sim.state == State.SWITCH_ON_DISABLED
    # the drive got the quick stop first: it travelled on its ramp (100 mm/s at 5000 mm/s^2: 1 mm)
    assert sim.actual / 10000 - r.master.positions()[0] > 0.5


class _Cycling:
    """The master's cycle on its own thread (SYNC only until drives are streamed to), as the daemon
    runs it, while the test thread enables over SDO."""

    def __init__(self, master) -> None:
        from fieldbus.canopen.clock import PeriodicRunner

        self.runner = PeriodicRunner(master.config.cycle_s, lambda k, t: master.cycle(None),
                                     keep_lateness=False).start()

    def stop(self) -> None:
        self.runner.stop()
        assert self.runner.join(5.0) and self.runner.error is None

    def __enter__(self) -> _Cycling:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _sims(n: int, **kw) -> list:
    from fieldbus.canopen.drive_sim import SimDrive

    return [SimDrive(i + 1, **(kw if i == 0 else {})) for i in range(n)]


@pytest.mark.parametrize("layout", [{"pdo_layout": "compact", "following_error_every": 4},
                                    {"pdo_layout": "standard", "cycle_s": 0.004}])
def test_a_drive_with_rpdo_deadline_monitoring_enabled_first_among_six_does_not_fault(rig, layout):
    """Drive 1 faults after 3 SYNCs without a target; it is enabled first, then five more over SDO
    while the cycle runs: it gets its held position every SYNC from the enable on."""
    r = rig(6, sims=_sims(6, rpdo_timeout_syncs=3), up=False, **layout)
    r.master.boot()
    with _Cycling(r.master):
        r.master.enable()
        time.sleep(0.1)
    assert r.master.fault is None, r.master.fault
    assert r.sim(1).emcys == []
    start = r.master.positions()
    r.run(50, _move(start, period=r.config.cycle_s))
    assert r.master.fault is None and r.sim(1).emcys == []
    # after a fault and its reset too
    r.master.quick_stop("test")
    r.master.reset_faults()
    with _Cycling(r.master):
        r.master.enable()
        time.sleep(0.1)
    assert r.master.fault is None and r.sim(1).emcys == []


def test_the_simulated_rpdo_deadline_faults_with_0x8250_and_enable_names_that_emcy(rig, monkeypatch):
    """Were the master to leave drive 1 without targets while it enables the others (as it did), the
    drive's EMCY is the error, not the state the drive is then stuck in."""
    r = rig(3, sims=_sims(3, rpdo_timeout_syncs=3), up=False)
    r.master.boot()
    real = r.master._activate

    def without_targets(d):
        real(d)
        if d.cfg.node_id == 1:
            d.active = False

    monkeypatch.setattr(r.master, "_activate", without_targets)
    enable_drive = r.master._enable_drive

    def as_slow_as_a_real_drive(d):
        # a real drive takes tens of ms to enable; over the in-process bus the other two took less than
        # the three SYNCs drive 1 waits on a fast PC, and enable() returned before its EMCY
        if d.cfg.node_id == 2:
            wait_for(lambda: r.sim(1).emcys != [], 2.0)
        enable_drive(d)

    monkeypatch.setattr(r.master, "_enable_drive", as_slow_as_a_real_drive)
    with _Cycling(r.master), pytest.raises(Exception, match=r"node 1 \(axis x\): EMCY 0x8250"):
        r.master.enable()
    assert r.sim(1).emcys == [0x8250]
    assert r.sim(2).state != State.OPERATION_ENABLED  # the ones enabled were quick-stopped


def test_a_drive_without_quick_stop_deceleration_boots_with_a_warning_and_stops_on_its_own_setting(rig):
    from fieldbus.canopen.drive_sim import SimDrive

    r = rig(2, sims=[SimDrive(1, absent_objects={0x6085}), SimDrive(2)], up=False)
    seen = []
    r.master.add_warning_listener(seen.append)
    r.up()
    assert [(w.node, w.axis) for w in seen] == [(1, "x")]
    assert "no object 0x6085 (quick stop deceleration; SDO abort 0x06020000)" in str(seen[0])
    assert "drive's own deceleration" in str(seen[0])
    assert r.master.drives[0].missing == {0x6085: 0x06020000} and r.master.drives[1].missing == {}
    start = r.master.positions()
    r.run(40, _move(start))
    assert r.master.fault is None
    r.master.quick_stop("test")
    assert wait_for(lambda: r.sim(1).velocity == 0.0 and r.sim(1).state != State.OPERATION_ENABLED, 2.0)


@pytest.mark.parametrize("absent, code", [(0x6060, "0x06020000"), (0x1A00, "0x06020000")])
def test_a_drive_without_a_mandatory_object_is_refused_naming_node_object_and_code(rig, absent, code):
    from fieldbus.canopen.drive_sim import SimDrive
    from fieldbus.canopen.master import CanopenError

    r = rig(1, sims=[SimDrive(1, absent_objects={absent})], up=False)
    with pytest.raises(CanopenError, match=rf"node 1 \(axis x\): SDO write of 0x{absent:04X}:.. .*{code}"):
        r.master.boot()


def test_quick_stop_option_is_mandatory_in_the_standard_layout_only(rig):
    from fieldbus.canopen.drive_sim import SimDrive
    from fieldbus.canopen.master import CanopenError

    r = rig(1, sims=[SimDrive(1, absent_objects={0x605A})], up=False)
    with pytest.raises(CanopenError, match=r"node 1 \(axis x\): SDO write of 0x605A:00 \(quick stop opt"):
        r.master.boot()
    c = rig(1, sims=[SimDrive(1, absent_objects={0x605A})], up=False, pdo_layout="compact")
    c.up()
    assert "0x605A" in str(c.master.warnings[0]) and c.master.fault is None


def test_a_warning_emcy_is_logged_and_published_and_motion_goes_on(rig):
    r = rig(2)
    seen = []
    r.master.add_warning_listener(seen.append)
    start = r.master.positions()
    r.run(20, _move(start))
    r.sim(2).send_warning(0x4210)  # temperature warning, error register 0: the drive goes on
    r.run(40, _move(start, 20))
    assert r.master.fault is None
    assert wait_for(lambda: len(seen) == 1, 1.0)
    assert (seen[0].node, seen[0].axis) == (2, "y") and "EMCY 0x4210" in seen[0].reason
    assert "error register 0x00" in seen[0].reason and "goes on" in seen[0].reason
    assert r.master.positions()[1] == pytest.approx(start[1] + 0.1 * 59)
    # an error register set: it stops, as every other EMCY
    r.sim(2).send_warning(0x4210, register=0x09)
    r.run(5, _move(start, 60))
    assert wait_for(lambda: r.master.fault is not None, 1.0)
    assert r.master.fault.node == 2 and "EMCY 0x4210" in r.master.fault.reason


def test_the_machine_file_classes_emcy_codes(rig):
    from fieldbus.canopen.config import EmcyPolicy

    r = rig(1, emcy=EmcyPolicy(warn=("0xFFxx",), stop=("0x42xx",)))
    seen = []
    r.master.add_warning_listener(seen.append)
    r.sim(1).send_warning(0xFF01, register=0x80)  # manufacturer specific: a warning here
    r.run(10)
    assert r.master.fault is None and wait_for(lambda: len(seen) == 1, 1.0)
    r.sim(1).send_warning(0x4210)  # error register 0, but the file says stop
    r.run(5)
    assert wait_for(lambda: r.master.fault is not None, 1.0) and "EMCY 0x4210" in r.master.fault.reason


def test_emcy_policy_in_the_machine_file():
    root = Table({"canopen": {"emcy": {"warn": ["0xFFxx", "0x4210"], "stop": ["0xff01"]},
                              "axes": {"x": {"node_id": 1}}}}, "m.toml")
    policy = read_canopen(root, ["x"], 0.002).emcy
    assert policy.is_warning(0xFF02, 0x80) and not policy.is_warning(0xFF01, 0)
    assert policy.is_warning(0x4210, 0x01) and policy.is_warning(0x3000, 0)
    assert not policy.is_warning(0x3000, 1)
    bad = Table({"canopen": {"emcy": {"warn": ["0xFFx"]}, "axes": {"x": {"node_id": 1}}}}, "m.toml")
    with pytest.raises(ConfigError, match=r"m.toml: canopen\.emcy\.warn: '0xFFx' is not four hex digits"):
        read_canopen(bad, ["x"], 0.002)


def test_a_sync_the_master_did_not_send_is_the_masters_fault(rig):
    r = rig(2)
    r.run(20)
    time.sleep(r.config.feedback_timeout_s + 0.2)  # the master's cycle stalls: no SYNC, no setpoint
    r.run(2)
    f = r.master.fault
    assert f is not None and f.node == 0, f
    assert str(f).startswith("master: the master sent no SYNC for") and "its cycle stalled" in f.reason


def test_reset_is_refused_while_a_drive_heartbeat_is_missing(rig):
    from fieldbus.canopen.master import CanopenError

    r = rig(2, heartbeat_producer_ms=20, heartbeat_consumer_ms=100)
    r.run(20)
    r.sim(2).drop_heartbeat(1.5)
    for _ in range(100):
        r.run(5)
        if r.master.fault is not None:
            break
    assert r.master.fault is not None and r.master.fault.node == 2
    with pytest.raises(CanopenError, match=r"node 2 \(axis y\): no heartbeat for \d+ ms"):
        r.master.reset_faults()
    assert r.master.fault is not None
    assert wait_for(lambda: time.monotonic() - r.master.drives[1].heartbeat_at < 0.05, 3.0)  # it is back
    r.master.reset_faults()
    r.master.enable()
    assert r.master.fault is None


def test_a_configuration_faster_than_the_motor_is_refused_naming_key_object_and_both_values(rig):
    from fieldbus.canopen.master import CanopenError

    # the simulated motor: 3000 rpm, 50000 counts/rev: 2,500,000 counts/s, 250 mm/s at 10000 counts/mm
    r = rig(1, max_velocity=300.0, up=False)
    message = (r"node 1 \(axis x\): axes\.x\.max_velocity 300 is 3,000,000 counts/s, more than the motor "
               r"allows: 0x6080 max motor speed 3000 rpm = 2,500,000 counts/s \(50000 counts/rev\), i\.e\. "
               r"max_velocity 250 at most")
    with pytest.raises(CanopenError, match=message):
        r.master.boot()
    ok = rig(1, max_velocity=250.0, up=False)
    ok.master.boot()
    assert ok.master.drives[0].limits[(0x6080, 0)] == 3000


def test_counts_per_revolution_from_the_machine_file_and_a_smaller_motor(rig):
    from fieldbus.canopen.drive_sim import SimDrive
    from fieldbus.canopen.master import CanopenError

    r = rig(1, counts_per_revolution=10000, up=False)  # 3000 rpm x 10000 counts: 50 mm/s
    with pytest.raises(CanopenError, match=r"0x6080 max motor speed 3000 rpm = 500,000 counts/s"):
        r.master.boot()
    small = rig(1, sims=[SimDrive(1, parameters={(0x6080, 0): 1500})], up=False)  # 125 mm/s
    with pytest.raises(CanopenError, match=r"max_velocity 200 .* 0x6080 max motor speed 1500 rpm"):
        small.master.boot()


def test_acceleration_and_position_range_beyond_the_drive_are_refused(rig):
    from fieldbus.canopen.drive_sim import SimDrive
    from fieldbus.canopen.master import CanopenError

    r = rig(1, max_acceleration=60000.0, up=False)  # 6e8 counts/s^2 > 5e8
    with pytest.raises(CanopenError, match=r"axes\.x\.max_acceleration 60000 is 600,000,000 counts/s², more "
                                           r"than 0x60C5 max acceleration 500,000,000"):
        r.master.boot()
    lim = {(0x607D, 1): -100000, (0x607D, 2): 100000}
    p = rig(1, sims=[SimDrive(1, parameters=lim)], min_position=-1.0, max_position=300.0, up=False)
    with pytest.raises(CanopenError, match=r"axes\.x\.min_position\.\.max_position \(-1 to 300\) spans "
                                           r"3,010,000 counts, more than .* 0x607D \(-100,000 to 100,000"):
        p.master.boot()


def test_a_drive_without_csp_is_refused_by_name(rig):
    from fieldbus.canopen.drive_sim import SimDrive
    from fieldbus.canopen.master import CanopenError

    r = rig(1, sims=[SimDrive(1, parameters={(0x6502, 0): 0x25})], up=False)  # pp, pv, homing
    with pytest.raises(CanopenError, match=r"node 1 \(axis x\): the drive does not support cyclic "
                                           r"synchronous position \(CSP\): 0x6502 supported drive modes is "
                                           r"0x00000025"):
        r.master.boot()


def test_without_0x608f_the_speed_check_asks_for_counts_per_revolution(rig):
    from fieldbus.canopen.drive_sim import SimDrive

    r = rig(1, sims=[SimDrive(1, absent_objects={0x608F})], up=False)
    r.master.boot()
    assert any("counts_per_revolution" in str(w) and "0x6080" in str(w) for w in r.master.warnings)
    assert 0x608F in r.master.drives[0].missing


def _dcf(tmp_path, values: dict[str, int]):
    """The shipped EDS made a DCF: ``ParameterValue`` added to the named sections."""
    from fieldbus.canopen import SHIPPED_EDS

    text = SHIPPED_EDS.read_text()  # newlines made \n
    for section, value in values.items():
        assert f"[{section}]\n" in text, section
        text = text.replace(f"[{section}]\n", f"[{section}]\nParameterValue={value}\n")
    path = tmp_path / "drive.dcf"
    path.write_text(text)
    return str(path)


def test_the_dcf_values_are_written_at_boot_by_the_library_loader_then_canons_own(rig, tmp_path):
    dcf = _dcf(tmp_path, {"6099sub1": 12345, "6099sub2": 678, "6085": 1})  # 0x6085: canon's wins
    r = rig(1, eds=dcf)
    assert r.sim(1)._value(0x6099, 1) == 12345 and r.sim(1)._value(0x6099, 2) == 678
    assert r.sim(1)._value(0x6085) == 5000 * 10000  # quick_stop_deceleration, written after the DCF
    r.run(10)
    assert r.master.fault is None


def test_a_dcf_value_the_drive_refuses_stops_the_boot_naming_the_file(rig, tmp_path):
    from fieldbus.canopen.master import CanopenError

    dcf = _dcf(tmp_path, {"6099sub1": 12345})
    r = rig(1, eds=dcf, up=False)
    r.sim(1).abort_sdo(0x6099, 1, 0x06090030)
    with pytest.raises(CanopenError, match=r"node 1 \(axis x\): writing the values of .*drive\.dcf: SDO "
                                           r"abort 0x06090030"):
        r.master.boot()


def test_extra_sdo_writes_from_the_machine_file(rig):
    from fieldbus.canopen.master import CanopenError

    root = Table({"canopen": {"axes": {"x": {"node_id": 1, "sdo": [
        {"index": 0x6099, "subindex": 2, "type": "u32", "value": 777}]}}}}, "m.toml")
    drive = read_canopen(root, ["x"], 0.002).drives[0]
    assert drive.sdo == ((0x6099, 2, "I", 777, "canopen.axes.x.sdo[0]"),)
    r = rig(1, sdo=drive.sdo)
    assert r.sim(1)._value(0x6099, 2) == 777
    bad = rig(1, sdo=((0x2F01, 0, "I", 1, "canopen.axes.x.sdo[0]"),), up=False)
    with pytest.raises(CanopenError, match=r"node 1 \(axis x\): SDO write of 0x2F01:00 \(canopen\.axes\.x"
                                           r"\.sdo\[0\] in the machine file\) aborted by the drive: 0x0602"):
        bad.master.boot()


@pytest.mark.parametrize("entry, message", [
    ({"index": 0x605A, "type": "i16", "value": 6}, r"sdo\[0\]\.index: 0x605A is written by canon itself"),
    ({"index": 0x1600, "type": "u32", "value": 6}, r"sdo\[0\]\.index: 0x1600 is written by canon itself"),
    ({"index": 0x6099, "type": "f32", "value": 6}, r"sdo\[0\]\.type"),
    ({"index": 0x6099, "type": "u8", "value": 300}, r"sdo\[0\]\.value: must be between 0 and 255"),
    ({"index": 0x6099, "type": "u8", "value": 1, "sub": 1}, r"sdo\[0\]"),
])
def test_extra_sdo_mistakes_name_the_key(entry, message):
    root = Table({"canopen": {"axes": {"x": {"node_id": 1, "sdo": [entry]}}}}, "m.toml")
    with pytest.raises(ConfigError, match="m.toml: canopen.axes.x." + message):
        read_canopen(root, ["x"], 0.002)


def test_the_simulated_machine_gets_a_motor_sized_for_its_axes(rig):
    from fieldbus.canopen.config import DriveConfig
    from fieldbus.canopen.drive_sim import SimDrive, motor_for

    assert motor_for(DriveConfig("x", 1, max_velocity=200.0)) == {}  # the small motor fits
    fast = DriveConfig("x", 1, max_velocity=400.0, max_acceleration=60000.0)
    params = motor_for(fast)
    assert params[(0x6080, 0)] == 6000  # 400 mm/s x 1.25 x 10000 counts/mm at 50000 counts/rev
    r = rig(1, sims=[SimDrive(1, parameters=params)], max_velocity=400.0, max_acceleration=60000.0)
    assert r.master.fault is None and r.master.drives[0].limits[(0x6080, 0)] == 6000


LIMIT = 20000  # counts: 2 mm at 10000 counts/mm


@pytest.mark.parametrize("layout", ["standard", "compact"])
def test_a_limit_switch_tripped_mid_move_stops_the_machine_naming_axis_node_and_switch(rig, layout):
    """Drive 2's positive limit switch (0x60FD bit 1, from its actual position) trips mid-move; the
    drive itself does not react. The master must stop the machine within a bounded number of SYNCs,
    name axis, node and switch, and never re-enable the drive."""
    from fieldbus.canopen.drive_sim import SimDrive

    r = rig(2, sims=[SimDrive(1), SimDrive(2, positive_limit_counts=LIMIT)], pdo_layout=layout)
    r.sim(2).record_targets = True
    enables = r.sim(2).enables
    start = r.master.positions()
    assert start[1] == 0.0
    r.run(80, _move(start))  # 50 mm/s: 0.1 mm = 1000 counts per SYNC, 4 mm in all
    f = r.master.fault
    assert f is not None, "a limit switch tripped mid-move went unseen"
    assert (f.node, f.axis) == (2, "y") and "positive limit switch" in f.reason, f
    assert "node 2 (axis y)" in str(f)
    # the targets step 1000 counts per SYNC: the last one the drive latched says how many SYNCs the
    # master went on streaming after the commanded position passed the switch (the actual lags one)
    last = r.sim(2).latched[-1][1]
    assert last > LIMIT
    assert (last - LIMIT) // 1000 <= 10, f"streamed {(last - LIMIT) // 1000} SYNCs past the switch"
    assert r.master.feedback().digital_inputs[1] & 0x2
    r.run(30)
    assert r.sim(2).enables == enables, "the master re-enabled a drive stopped on a limit switch"
    assert wait_for(lambda: r.sim(2).state != State.OPERATION_ENABLED, 2.0)


def test_after_a_limit_switch_stop_the_axis_may_move_off_the_switch_but_not_onto_it(rig):
    from fieldbus.canopen.drive_sim import SimDrive

    r = rig(1, sims=[SimDrive(1, negative_limit_counts=-LIMIT)])
    r.run(60, _move(r.master.positions(), speed=-50.0))
    assert r.master.fault is not None and "negative limit switch" in r.master.fault.reason
    assert wait_for(lambda: r.sim(1).velocity == 0.0, 2.0)
    r.master.reset_faults()
    r.master.enable()  # on the switch: enabling is allowed
    r.run(5)
    assert r.master.fault is None, r.master.fault
    here = r.master.positions()
    r.run(3, _move(here, speed=-50.0))  # further onto it: refused at once
    f = r.master.fault
    assert f is not None and f.node == 1 and "negative limit switch" in f.reason and "toward" in f.reason
    assert r.master.positions() == here
    assert wait_for(lambda: r.sim(1).velocity == 0.0, 2.0)
    r.master.reset_faults()
    r.master.enable()
    r.run(40, _move(r.master.positions(), speed=50.0))  # off it
    assert r.master.fault is None, r.master.fault
    assert r.master.feedback().digital_inputs == (0,)


def test_a_drive_without_digital_inputs_boots_with_a_warning(rig):
    from fieldbus.canopen.drive_sim import SimDrive

    r = rig(1, sims=[SimDrive(1, absent_objects={0x60FD})])
    assert any(w.node == 1 and "0x60FD" in w.reason for w in r.master.warnings)
    r.run(20, _move(r.master.positions()))
    assert r.master.fault is None, r.master.fault


def test_a_limit_switch_that_becomes_active_while_the_axis_holds_stops_the_machine(rig):
    """Not moving toward it, the switch still trips (a crash pushed the axis, a wiring fault): an
    edge of 0x60FD while streamed to stops the machine."""
    r = rig(2)
    r.run(10)
    r.sim(1).positive_limit_counts = -5  # the switch now reads active where the axis stands
    r.run(20)
    f = r.master.fault
    assert f is not None and (f.node, f.axis) == (1, "x") and "positive limit switch" in f.reason, f


def test_sim_drives_limit_option_puts_the_switches_on_the_drive_s_sides():
    import argparse

    from fieldbus.canopen.config import AxisScale, DriveConfig
    from motiond.cmd_sim_drives import _limit, limit_counts

    assert _limit("y=-5:120") == ("y", -5.0, 120.0)
    assert _limit("x=:50") == ("x", None, 50.0)
    for bad in ("x=1", "x=:", "=1:2", "x=a:2"):
        with pytest.raises(argparse.ArgumentTypeError, match="AXIS=MIN:MAX"):
            _limit(bad)
    assert limit_counts(AxisScale(DriveConfig("x", 1)), -5.0, 120.0) == (-50000, 1200000)
    # direction -1: the machine's maximum is on the drive's negative side
    assert limit_counts(AxisScale(DriveConfig("y", 2, direction=-1)), None, 1.0) == (-10000, None)
