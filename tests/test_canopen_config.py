"""The [canopen] configuration, the bus budget and the exact count conversion."""

from __future__ import annotations

from fractions import Fraction

import pytest

from fieldbus.canopen import cia402
from fieldbus.canopen.busload import bus_load, frame_bits
from fieldbus.canopen.cia402 import Command, State
from fieldbus.canopen.config import AxisScale, CanBusConfig, CanopenConfig, DriveConfig
from fieldbus.canopen.master import BusBudgetError, CanopenMaster
from motiond.config_canopen import read_canopen
from motiond.configkit import ConfigError, Table

GOOD = {
    "canopen": {
        "interface": "udp_multicast", "channel": "239.74.163.7", "bitrate": 500000,
        "heartbeat_producer_ms": 50, "heartbeat_consumer_ms": 150,
        "axes": {"x": {"node_id": 4, "counts_per_unit": 8192, "direction": -1, "home_offset": 1.5,
                       "following_error_window": 0.5, "homing": "cia402", "homing_method": 19,
                       "vendor_id": 0xCA0, "homing_speed": 5.0, "homing_speed_zero": 0.5,
                       "homing_acceleration": 100.0},
                 "y": {"node_id": 5}},
    }
}


def read(data, names=("x", "y"), limits=None):
    return read_canopen(Table(data, "m.toml"), list(names), 0.002, limits)


def test_reads_the_canopen_table():
    c = read(GOOD, limits={"x": {"max_velocity": 150, "min_position": -1.0, "max_position": 300.0}})
    assert c.bus == CanBusConfig("udp_multicast", "239.74.163.7", 500000, {})
    assert (c.heartbeat_producer_ms, c.heartbeat_consumer_ms, c.cycle_s) == (50, 150, 0.002)
    x = c.drive("x")
    assert (x.node_id, x.counts_per_unit, x.direction, x.home_offset) == (4, 8192.0, -1, 1.5)
    assert (x.following_error_window, x.homing, x.homing_method, x.vendor_id) == (0.5, "cia402", 19, 0xCA0)
    assert (x.max_velocity, x.min_position, x.max_position) == (150.0, -1.0, 300.0)
    assert (x.homing_speed, x.homing_speed_zero, x.homing_acceleration) == (5.0, 0.5, 100.0)
    assert c.drive("y").homing_speed is None  # the drive's own
    assert c.drive("y").node_id == 5 and c.drive("y").product_code is None


def test_no_canopen_table_gives_the_demo():
    c = read({}, ("x", "y", "z"))
    assert c.bus.interface == "canon_local" and c.simulate  # crosses processes: the motion side's own
    assert [(d.axis, d.node_id) for d in c.drives] == [("x", 1), ("y", 2), ("z", 3)]


@pytest.mark.parametrize("patch, key, words", [
    ({"bitrate": 2_000_000}, "canopen.bitrate", "between"),
    ({"channel": "ff02::1"}, "canopen.channel", "IPv4 multicast group"),
    ({"heartbeat_consumer_ms": 40}, "canopen.heartbeat_consumer_ms", "longer than"),
    ({"bitrat": 1}, "canopen.bitrat", "unknown key"),
])
def test_bad_bus_settings_name_the_key(patch, key, words):
    data = {"canopen": {**GOOD["canopen"], **patch}}
    with pytest.raises(ConfigError) as e:
        read(data)
    assert e.value.file == "m.toml" and e.value.key == key and words in e.value.message


@pytest.mark.parametrize("axis_patch, key, words", [
    ({"node_id": 0}, "canopen.axes.x.node_id", "between 1 and 127"),
    ({"node_id": 5}, "canopen.axes.y.node_id", "5 is already the node id of axis x"),
    ({"direction": 2}, "canopen.axes.x.direction", "one of 1, -1"),
    ({"counts_per_unit": -3}, "canopen.axes.x.counts_per_unit", "> 0"),
    ({"homing": "switch"}, "canopen.axes.x.homing", "one of set, cia402"),
    ({"homing_speed": 0}, "canopen.axes.x.homing_speed", "> 0"),
    ({"homing_acceleration": 1e9}, "canopen.axes.x.counts_per_unit", "homing acceleration 0x609A"),
    ({"eds": "nope.eds"}, "canopen.axes.x.eds", "no such file"),
    ({"node_idd": 3}, "canopen.axes.x.node_idd", "unknown key"),
])
def test_bad_axis_settings_name_the_key(axis_patch, key, words):
    axes = {"x": {**GOOD["canopen"]["axes"]["x"], **axis_patch}, "y": {"node_id": 5}}
    data = {"canopen": {**GOOD["canopen"], "axes": axes}}
    with pytest.raises(ConfigError) as e:
        read(data)
    assert e.value.key == key and words in e.value.message, str(e.value)


def test_axes_and_drives_must_match():
    with pytest.raises(ConfigError, match=r"canopen\.axes\.z: missing"):
        read(GOOD, ("x", "y", "z"))
    with pytest.raises(ConfigError, match=r"canopen\.axes\.y: no axis 'y' in"):
        read(GOOD, ("x",))


def test_frame_lengths_count_worst_case_stuffing():
    assert frame_bits(0) == 55
    assert frame_bits(8) == 135  # the 111-135 bit times of an 8-byte frame, worst case
    assert frame_bits(6) == 115
    with pytest.raises(ValueError):
        frame_bits(9)


def test_bus_load_figures():
    load = bus_load(6, 0.001, 1_000_000)
    assert load.frames_per_s == pytest.approx(19000)  # SYNC + 6 x (RPDO + 2 TPDO) per ms
    assert load.bits_per_s == pytest.approx(1000 * (55 + 6 * (115 + 115 + 95)))
    assert bus_load(3, 0.004, 1_000_000).fraction < 0.3


def _config(n, cycle_s, bitrate=1_000_000):
    return CanopenConfig(CanBusConfig("virtual", "budget", bitrate),
                         tuple(DriveConfig("xyzabc"[i], i + 1) for i in range(n)), cycle_s=cycle_s)


def test_over_seventy_percent_is_refused_with_the_figure():
    # 1000 x (55 + 6 x (115 + 115 + 95)) bit/s of cycle traffic + 7 heartbeats of 65 bits, 10 a second
    # = 2,009,550 bit/s: 201.0 % of 1 Mbit/s
    with pytest.raises(BusBudgetError,
                       match=r"bus load 201\.0 % is over the 70 % allowed: 6 drives every 1 ms"):
        CanopenMaster(_config(6, 0.001))
    m = CanopenMaster(_config(3, 0.004))  # 26 %: accepted
    assert 0.2 < m.load.fraction < 0.3
    m2 = CanopenMaster(_config(6, 0.001), check_budget=False)  # the bench, on the virtual bus
    assert m2.load.fraction > 1.0


def test_count_conversion_is_exact_over_a_long_run():
    # 20 million cycles of a 0.1 um step: the absolute position converted each cycle gives every
    # count exactly (sampled every 9973rd cycle), however long the run.
    scale = AxisScale(DriveConfig("x", 1, counts_per_unit=10000, direction=-1, home_offset=12.5))
    step = Fraction(1, 10000)
    for k in range(0, 20_000_000, 9973):
        exact = -k + 125000  # direction -1; drive count 0 is machine position 12.5
        assert scale.to_counts(float(k * step)) == exact
        assert scale.to_units(exact) == pytest.approx(float(k * step), abs=1e-9)
    assert scale.to_counts(12.5) == 0


def test_homing_moves_the_reference_by_whole_counts():
    scale = AxisScale(DriveConfig("x", 1, counts_per_unit=1000, home_offset=-2.0))
    scale.set_home_here(123456)
    assert scale.to_units(123456) == -2.0
    assert scale.to_counts(-2.0) == 123456
    scale.drive_zero_is_home()
    assert scale.to_counts(-2.0) == 0


def test_statusword_decoding_and_commands():
    for state in State:
        if state != State.UNKNOWN:
            assert cia402.decode(cia402.statusword_for(state, cia402.SW_BIT12)) == state
    assert cia402.decode(0x0637) == State.OPERATION_ENABLED
    assert cia402.decode(0x0250) == State.SWITCH_ON_DISABLED
    assert cia402.command_of(0x80, 0x00) == Command.FAULT_RESET
    assert cia402.command_of(0x80, 0x80) != Command.FAULT_RESET  # needs a rising edge
    assert cia402.command_of(0x02) == Command.QUICK_STOP
    assert cia402.command_of(0x06) == Command.SHUTDOWN
    assert cia402.command_of(0x0F) == Command.ENABLE_OPERATION
    assert cia402.next_step(State.FAULT) is None


def test_from_the_machine_file(tmp_path):
    from motiond.config import load_machine
    from motiond.config_canopen import canopen_for_machine

    p = tmp_path / "m.toml"
    p.write_text("[machine]\ncycle_ms = 4\n"
                 "[axes.x]\nmax_velocity = 100\nmax_acceleration = 1000\nmax_jerk = 10000\n"
                 "max_position = 50\n"
                 "[canopen]\ninterface = 'virtual'\n[canopen.axes.x]\nnode_id = 9\n")
    c = canopen_for_machine(load_machine(str(p)))
    x = c.drive("x")
    assert (x.node_id, x.max_velocity, x.quick_stop_deceleration, x.max_position) == (9, 100.0, 2000.0, 50.0)
    assert c.cycle_s == 0.004
    demo = canopen_for_machine(load_machine(None))
    assert demo.bus.interface == "canon_local" and [d.node_id for d in demo.drives] == [1, 2, 3]


def test_bus_tools_share_overrides_and_refuse_ipv6_multicast() -> None:
    """`sim drives`, `sim inject` and `can-dump` read the bus the same way: file (or demo), then options."""
    from motiond.cli import UserError
    from motiond.config_canopen import canopen_for_tool

    config, bus = canopen_for_tool(None, "udp_multicast", "239.74.163.9")
    assert (bus.interface, bus.channel) == ("udp_multicast", "239.74.163.9")
    assert [d.node_id for d in config.drives] == [1, 2, 3]
    with pytest.raises(UserError, match="IPv4 group"):
        canopen_for_tool(None, "udp_multicast", "ff15:7079:7468:6f6e:6465:6d6f:6d63:6173")
