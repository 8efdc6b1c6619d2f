"""The drive's CiA 402 touch probe (0x60B8-0x60BD): the simulated drive latches at its trip point inside
the cycle, the master arms it, sees the trip in TPDO4 and reads the latched position."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from canopen_helpers import Rig, make_config, wait_for
from motion_process_helpers import own_mode

from fieldbus.canopen.drive_sim import SimDrive
from fieldbus.canopen.master import CanopenError
from fieldbus.canopen.touch_probe import TouchProbe

TRIP = -12_345  # counts: -1.2345 mm at 10000 counts/mm
STEP = 0.0137  # mm per cycle: the trip falls inside a cycle, 137 counts of travel each


def probe_rig(**sim_kw: object) -> Rig:
    config = make_config(1, touch_probe=1)
    return Rig(config, [SimDrive(1, probe_trip_counts=TRIP, **sim_kw)])  # type: ignore[arg-type]


def test_the_probe_latches_the_trip_point_not_the_cycle() -> None:
    r = probe_rig()
    try:
        r.up()
        tp = TouchProbe.of(r.master)
        assert tp is not None and tp.axis == "x"
        tp.arm(toward=True)
        assert not tp.tripped
        seen: list[int] = []

        def down(k: int) -> list[float]:
            if tp.tripped and not seen:
                seen.append(k)
            return [-STEP * min(k, 200)]

        r.run(220, down)
        assert seen, "the trip never reached the master in TPDO4"
        result = tp.result()
        assert result.tripped
        assert abs(result.counts - TRIP) <= 1  # the drive's latch: one count, not a cycle's 137
        assert result.position == pytest.approx(TRIP / 10000.0, abs=1e-4)
        assert r.sim(1)._value(0x60B8) == 0  # disarmed after reading
        # armed for the negative edge (contact lost), moving further into contact: no latch
        tp.arm(toward=False)
        r.run(20, lambda k: [-STEP * (200 + k)])
        assert not tp.tripped and not tp.result().tripped
    finally:
        r.close()


def test_first_event_only_and_rearming_clears() -> None:
    r = probe_rig()
    try:
        r.up()
        tp = TouchProbe.of(r.master)
        assert tp is not None
        tp.arm(toward=True)
        # into contact and out; then the surface is higher and the probe goes in again: the first
        # edge is the one kept
        path = [-0.02 * k for k in range(80)] + [-1.6 + 0.02 * k for k in range(81)]
        r.run(len(path), lambda k: [path[k]])
        with r.sim(1).lock:
            r.sim(1).probe_trip_counts = TRIP // 2
        r.run(100, lambda k: [-0.01 * k])
        assert wait_for(lambda: tp.tripped, 1.0)
        first = tp.result()
        assert first.tripped and abs(first.counts - TRIP) <= 1
        tp.arm(toward=True)  # re-armed: the stored edge is cleared
        assert not tp.tripped and not tp.result().tripped
    finally:
        r.close()


def test_a_drive_without_touch_probe_objects_is_refused_naming_node_and_object() -> None:
    r = probe_rig(absent_objects={0x60B9})
    try:
        with pytest.raises(CanopenError, match=r"node 1 \(axis x\).*touch_probe = 1.*0x60B9 \(touch probe "
                                               r"status"):
            r.master.boot()
    finally:
        r.close()


# ---------------------------------------------------------------------------------- G38.x end to end
MACHINE = """
[machine]
name = "probe test"
cycle_ms = 2.0
[axes.x]
max_velocity = 100.0
max_acceleration = 1000.0
max_jerk = 20000.0
[axes.z]
max_velocity = 50.0
max_acceleration = 1000.0
max_jerk = 20000.0
[canopen]
simulate = true
channel = "{channel}"
[canopen.axes.x]
node_id = 1
[canopen.axes.z]
node_id = 2
{probe}
"""
OWN_PROBE = pytest.param({"own": True}, marks=[pytest.mark.multicast, pytest.mark.timeout(180)])
"""The probe machine with the motion in a process of its own (motion_process_helpers.own_mode)."""
HEIGHT = -3.21237  # the surface the probe touches, mm: between two cycles' positions at any feed here


def machine_file(tmp_path: Path, probe: str = f"touch_probe = 1\nsim_probe_position = {HEIGHT}") -> Path:
    from canopen_helpers import unique_channel

    path = tmp_path / "probe.toml"
    path.write_text(MACHINE.format(channel=unique_channel(), probe=probe))
    return path


def z_table(direction: int = 1, probe: int = 1, level_bit: int | None = 7) -> str:
    """The probe's lines of ``[canopen.axes.z]``: the simulated drive shows the probe input's level in
    0x60B9 bits 7 and 15."""
    level = "" if level_bit is None else f"touch_probe_level_bit = {level_bit}\n"
    return f"touch_probe = {probe}\nsim_probe_position = {HEIGHT}\ndirection = {direction}\n{level}"


@pytest.fixture
def machine(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[Any]:
    """The probe machine; parametrized indirectly with :func:`z_table`'s arguments (a dict)."""
    from motiond.config import load_machine
    from motiond.runtime import Machine

    param = dict(getattr(request, "param", {}))
    own = param.pop("own", False)  # the motion in a process of its own (the touch probe crosses)
    path = machine_file(tmp_path, z_table(**param))
    if own:
        path.write_text(own_mode(path.read_text()))
    m = Machine(load_machine(str(path)), lc=None, var_file=tmp_path / "p.var").start()
    try:
        m.bring_up()
        yield m
    finally:
        m.shutdown()


def run(m: Any, tmp_path: Path, text: str) -> Any:
    from motiond.states import State

    path = tmp_path / "p.ngc"
    path.write_text(text)
    result = m.wait_job(m.run(path), 30.0)
    assert result is not None, "the program did not end within 30 s"
    assert wait_for(lambda: m.states.state in (State.IDLE, State.FAULTED), 5.0)
    return result


@pytest.mark.parametrize("machine", [{}, {"direction": -1}, {"probe": 2, "level_bit": 15}, OWN_PROBE],
                         indirect=True, ids=["z up", "z counts down", "touch probe 2", "own process"])
def test_g38_2_stops_at_the_surface_and_stores_the_latched_height(machine: Any, tmp_path: Path) -> None:
    m = machine
    m.trace = []  # (cycle, time, setpoint, events) of every cycle
    result = run(m, tmp_path, "G21 G90 G94\nG0 X2 Z0\nG38.2 X4 Z-10 F300\n#1 = [#5061]\n#3 = [#5063]\n"
                              "G0 Z[#5063 + 2]\nM2\n")
    assert result.ok, result.error
    z = m.interp.parameter(3)
    # the drive's latch: one count (0.1 µm); a cycle's travel at F300 is 10 µm, the stop's far more
    assert abs(z - HEIGHT) <= 1.0001e-4
    assert m.interp.parameter(5070) == 1.0
    # X on the probing line where Z touched: X2 + (Z travelled / 10) * 2
    assert m.interp.parameter(1) == pytest.approx(2 + 2 * (-z / 10.0), abs=1e-6)
    assert m.motion.position()[1] == pytest.approx(z + 2, abs=1e-9)  # #5063 in the next line
    lowest = min(positions[1] for _, _, positions, _ in m.trace)
    assert HEIGHT - 0.5 < lowest < HEIGHT  # stopped past the surface (a jerk-limited stop), not at Z-10


@pytest.mark.parametrize("machine", [{}, {"probe": 2, "level_bit": 15}], indirect=True,
                         ids=["touch probe 1", "touch probe 2"])
def test_g38_4_latches_where_contact_is_lost(machine: Any, tmp_path: Path) -> None:
    """The negative edge's latch: 0x60BB of touch probe 1, 0x60BD of touch probe 2."""
    result = run(machine, tmp_path, "G21 G90 G94\nG0 Z-4\nG38.4 Z0 F450\n#3 = [#5063]\nM2\n")
    assert result.ok, result.error
    assert abs(machine.interp.parameter(3) - HEIGHT) <= 1.0001e-4
    assert machine.interp.parameter(5070) == 1.0


def test_g38_3_without_contact_goes_on_and_g38_2_without_contact_is_an_error(machine: Any,
                                                                             tmp_path: Path) -> None:
    m = machine
    result = run(m, tmp_path, "G21 G90 G94\nG0 Z0\nG38.3 Z-2 F600\n#3 = [#5063]\nM2\n")
    assert result.ok, result.error
    assert m.interp.parameter(5070) == 0.0 and m.interp.parameter(3) == pytest.approx(-2.0)
    result = run(m, tmp_path, "G21 G90 G94\nG0 Z0\n\nG38.2 Z-2 F600\nM2\n")
    assert not result.ok
    assert "p.ngc:4:" in result.error and "without making contact" in result.error


@pytest.mark.parametrize("machine", [{}, OWN_PROBE], indirect=True, ids=["thread", "own process"])
@pytest.mark.parametrize("code, start, state", [("G38.2", -4, "tripped (in contact)"),
                                                ("G38.4", 0, "clear (out of contact)")])
def test_g38_2_and_g38_4_with_the_probe_already_in_that_state_are_errors(machine: Any, tmp_path: Path,
                                                                         code: str, start: float,
                                                                         state: str) -> None:
    """As LinuxCNC ("Probe is already tripped when starting G38.2 ..."): a probe that cannot make the
    edge the move seeks is an error before anything moves, naming the file and line."""
    m = machine
    m.trace = []
    result = run(m, tmp_path, f"G21 G90 G94\nG0 Z{start}\n\n{code} Z-10 F300\nM2\n")
    assert not result.ok
    assert f"p.ngc:4: {code}: the probe (touch probe of axis z) is already {state} at the start of the " \
           "move; nothing moved" in result.error, result.error
    zs = [positions[1] for _, _, positions, _ in m.trace]
    assert min(zs, default=0.0) >= min(start, 0) - 1e-9  # the G0 went there; G38 moved nothing
    assert m.motion.position()[1] == pytest.approx(start, abs=1e-3)


@pytest.mark.parametrize("machine", [{}, OWN_PROBE], indirect=True, ids=["thread", "own process"])
@pytest.mark.parametrize("code, start, end", [("G38.3", -4.0, -10), ("G38.5", 0.0, 5)])
def test_g38_3_and_g38_5_with_the_probe_already_in_that_state_trip_where_the_machine_stands(
        machine: Any, tmp_path: Path, code: str, start: float, end: float) -> None:
    m = machine
    m.trace = []
    result = run(m, tmp_path, f"G21 G90 G94\nG0 X1 Z{start}\n{code} X3 Z{end} F300\n#1 = [#5061]\n"
                              "#3 = [#5063]\nG0 Z[#5063]\nM2\n")
    assert result.ok, result.error
    assert m.interp.parameter(5070) == 1.0
    assert (m.interp.parameter(1), m.interp.parameter(3)) == pytest.approx((1.0, start))
    zs = [positions[1] for _, _, positions, _ in m.trace]
    assert min(start, 0.0) - 1e-9 <= min(zs, default=0.0) and max(zs, default=0.0) <= max(start, 0.0) + 1e-9


def test_touch_probe_key_is_checked_naming_it(tmp_path: Path) -> None:
    from motiond.config import load_machine
    from motiond.config_canopen import canopen_for_machine
    from motiond.configkit import ConfigError

    with pytest.raises(ConfigError, match=r"canopen\.axes\.z\.touch_probe.*must be one of 0, 1, 2"):
        canopen_for_machine(load_machine(str(machine_file(tmp_path, "touch_probe = 3"))))
    two = machine_file(tmp_path).read_text().replace("node_id = 1\n", "node_id = 1\ntouch_probe = 2\n")
    path = tmp_path / "two.toml"
    path.write_text(two)
    with pytest.raises(ConfigError, match=r"canopen\.axes\.z\.touch_probe.*axis x has the machine's probe"):
        canopen_for_machine(load_machine(str(path)))
    with pytest.raises(ConfigError, match=r"canopen\.axes\.z\.sim_probe_position.*set touch_probe = 1"):
        canopen_for_machine(load_machine(str(machine_file(tmp_path, "sim_probe_position = -1.0"))))
    level = r"canopen\.axes\.z\.touch_probe_level_bit"
    with pytest.raises(ConfigError, match=level + r".*set touch_probe = 1 or 2"):
        canopen_for_machine(load_machine(str(machine_file(tmp_path, "touch_probe_level_bit = 7"))))
    with pytest.raises(ConfigError, match=level + r".*6, 7, 14, 15"):
        bit_1 = machine_file(tmp_path, "touch_probe = 1\ntouch_probe_level_bit = 1")
        canopen_for_machine(load_machine(str(bit_1)))


def test_g38_in_mdi_is_refused_with_a_drive_touch_probe(machine: Any) -> None:
    result = machine.wait_job(machine.mdi("G38.2 Z-1 F300"), 10.0)
    assert result is not None and not result.ok
    assert result.error.startswith("<mdi>:1: G38.2 in MDI") and "program" in result.error


def test_the_simulated_probe_position_is_on_the_drive_s_side() -> None:
    import argparse

    from fieldbus.canopen.config import AxisScale, DriveConfig
    from fieldbus.canopen.drive_sim_probe import sim_probe
    from motiond.cmd_sim_drives import _probe

    assert _probe("z=-3.2") == ("z", -3.2)
    with pytest.raises(argparse.ArgumentTypeError, match="AXIS=POSITION"):
        _probe("-3.2")
    up = DriveConfig("z", 3, counts_per_unit=1000.0, sim_probe_position=-3.2)
    down = DriveConfig("z", 3, counts_per_unit=1000.0, direction=-1)
    assert sim_probe(up) == {"probe_trip_counts": -3200, "probe_active_below": True}
    assert sim_probe(down) == {}
    kw = sim_probe(down, -3.2)
    assert kw == {"probe_trip_counts": 3200, "probe_active_below": False}
    sim = SimDrive(3, **kw)  # type: ignore[arg-type]
    for z, touching in ((-3.0, False), (-3.2, True), (-3.5, True)):
        assert sim.probe_input(AxisScale(down).to_counts(z)) is touching


def test_a_trip_during_a_feed_hold_leaves_the_planner_holding() -> None:
    """The trip stops the move with the planner's abort, which ends a hold at rest: a hold the operator
    asked for during the probing move is put back (the machine stays PAUSED until resume)."""
    import threading
    from types import SimpleNamespace

    from gcode_canon.commands import Pose, Probe, ProbeMode
    from motiond.runtime.probing import DriveProbing

    class Planner:
        def __init__(self) -> None:
            self.holding, self.waiting_for, self.is_idle = True, None, False
            self.calls: list[str] = []

        def abort(self) -> None:
            self.calls.append("abort")
            self.holding = False

        def hold(self) -> None:
            self.calls.append("hold")
            self.holding = True

    drive = object()
    probe = SimpleNamespace(drive=drive, tripped=False)
    m = SimpleNamespace(limits=SimpleNamespace(pose_index=(2,)), master=SimpleNamespace(drives=[drive]),
                        _sync_cond=threading.Condition(), _sync_reached=None)
    m._sync_point_reached = lambda w: setattr(m, "_sync_reached", w)
    dp = DriveProbing(m, probe)  # type: ignore[arg-type]
    cmd = Probe(Pose(0, 0, -5), ProbeMode.TOWARD_ERROR)
    dp._armed = cmd
    p = Planner()
    dp.on_cycle(p)
    assert p.calls == []  # no trip yet
    probe.tripped = True
    dp.on_cycle(p)
    assert p.calls == ["abort"]
    p.is_idle = True
    dp.on_cycle(p)
    assert p.calls == ["abort", "hold"] and p.holding and m._sync_reached is cmd
