"""G38.x on the I/O map's ``probe`` input (a Modbus discrete input) when no drive has a touch probe
(motiond.runtime.probing_io), on a simulated machine whose simulated I/O module trips the probe at
``[io.sim] probe_z`` (motiond.sim_wiring). docs/wiring.md.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from motion_process_helpers import OWN, own_mode
from test_machine_io import load
from test_run_from_line import wait_for

from motiond.config import load_machine
from motiond.configkit import ConfigError
from motiond.runtime import Machine
from motiond.states import State

TRIP_Z = -1.0
REQUEST_S = 0.02
MACHINE = f"""[machine]
name = "probe input"
cycle_ms = 2.0
[axes.x]
max_velocity = 100.0
max_acceleration = 1000.0
max_jerk = 10000.0
[axes.z]
max_velocity = 100.0
max_acceleration = 1000.0
max_jerk = 10000.0
[canopen]
simulate = true
[canopen.axes.x]
node_id = 1
[canopen.axes.z]
node_id = 2
[[modbus.devices]]
name = "io"
poll_ms = 10
simulate = true
[io.functions]
probe = {{ discrete_input = 4 }}
[io.sim]
probe_z = {TRIP_Z}
"""


@pytest.fixture(params=["thread", OWN])
def machine(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[Machine]:
    """The probe machine, its motion in the canon process or (``own``) in one of its own."""
    f = tmp_path / "m.toml"
    f.write_text(own_mode(MACHINE) if request.param == "own" else MACHINE)
    m = Machine(load_machine(str(f)), lc=None, var_file=tmp_path / "p.var", modbus_port=0).start()
    try:
        m.bring_up()
        m.trace = []
        yield m
    finally:
        m.shutdown()


def watch_probe_reads(m: Machine) -> list[tuple[float, int]]:
    """(time, level) of every read of the simulated probe input, from now on."""
    sim = m.sim_io["io"]
    table, address, fn = sim.computed[0]
    reads: list[tuple[float, int]] = []

    def level() -> int:
        v = fn()
        reads.append((time.monotonic(), v))
        return v

    sim.computed[0] = (table, address, level)
    return reads


def run(m: Machine, tmp: Path, text: str) -> object:
    p = tmp / "p.ngc"
    p.write_text("%\n" + text + "%\n")
    result = m.wait_job(m.run(p), 60.0)
    assert result is not None, "the program did not finish"
    if result.ok:
        wait_for(lambda: m.states.state is State.IDLE, "IDLE after the job", 20.0)
    return result


def test_g38_2_stops_at_the_modbus_probe_and_stores_the_commanded_point(machine: Machine,
                                                                           tmp_path: Path) -> None:
    feed = 60.0  # mm/min
    reads = watch_probe_reads(machine)
    result = run(machine, tmp_path, f"G21 G90 G94\nG38.2 Z-10 F{feed:g}\n#1 = #5063\n#2 = #5070\nM2\n")
    assert result.ok, result.error
    v = feed / 60.0
    # seen by the next poll, acted on in the next cycle: the probed point (commanded position of the
    # cycle that saw the trip) lies past the trip height by at most one poll's and one cycle's travel,
    # plus a cycle (the simulated probe reads the setpoint last sent) and the request's round trip
    # (REQUEST_S allowed). The poll: poll_ms, or the gap the poller really left before the read that saw
    # the trip where a loaded PC made it later
    first = next(i for i, (_t, level) in enumerate(reads) if level)
    gap = reads[first][0] - reads[first - 1][0]
    poll_s = max(machine.modbus.devices[0].poll_ms / 1000.0, gap)
    bound = v * (poll_s + 2 * machine.T + REQUEST_S)
    z = machine.interp.parameter(1)
    assert TRIP_Z - bound <= z <= TRIP_Z + 1e-9, (z, bound)
    # it is the commanded position of a cycle
    assert any(abs(pos[1] - z) < 1e-12 for _c, _t, pos, _e in machine.trace), z
    if machine.motion_mode == "own":  # the time the task saw it crossed: the cycle running then
        seen = machine.motion.probe_client.seen_at
        at_seen = [pos[1] for _c, t, pos, _e in machine.trace if t <= seen]
        assert at_seen and abs(z - at_seen[-1]) <= v * machine.T + 1e-9, (z, at_seen[-1:], v * machine.T)
    assert machine.interp.parameter(2) == 1.0
    # the move was stopped (jerk-limited) near the trip, far from the programmed end
    assert machine.motion.commanded[1] > -1.5, machine.motion.commanded


def test_g38_4_stops_where_the_contact_is_lost(machine: Machine, tmp_path: Path) -> None:
    feed = 60.0
    result = run(machine, tmp_path, f"G21 G90 G94\nG0 Z-1.5\nG38.4 Z0 F{feed:g}\n#1 = #5063\nM2\n")
    assert result.ok, result.error
    bound = feed / 60.0 * (machine.modbus.devices[0].poll_ms / 1000.0 + 2 * machine.T + REQUEST_S)
    z = machine.interp.parameter(1)
    assert TRIP_Z - 1e-9 <= z <= TRIP_Z + bound, (z, bound)
    assert machine.motion.commanded[1] < -0.5, machine.motion.commanded


@pytest.mark.parametrize("code, start, end, state", [("G38.2", -2.0, -3, "tripped (in contact)"),
                                                     ("G38.4", 0.0, 1, "clear (out of contact)")])
def test_g38_2_and_g38_4_with_the_probe_already_in_that_state_are_errors_naming_the_line(
        machine: Machine, tmp_path: Path, code: str, start: float, end: float, state: str) -> None:
    """As LinuxCNC ("Probe is already tripped when starting G38.2 or G38.3 move", "... already clear
    when starting G38.4 or G38.5 move"): refused before anything moves."""
    result = run(machine, tmp_path, f"G21 G90 G94\nG0 Z{start:g}\n{code} Z{end} F300\nM2\n")
    assert not result.ok
    assert f"p.ngc:4: {code}: the probe (io.functions.probe" in result.error, result.error
    assert f"is already {state} at the start of the move; nothing moved" in result.error, result.error
    assert machine.motion.commanded[1] == pytest.approx(start)  # nothing moved


@pytest.mark.parametrize("code, start, end", [("G38.3", -2.0, -3), ("G38.5", 0.0, 1)])
def test_g38_3_and_g38_5_with_the_probe_already_in_that_state_trip_where_the_machine_stands(
        machine: Machine, tmp_path: Path, code: str, start: float, end: float) -> None:
    """As LinuxCNC's motion (no error for these; the first cycle sees the sought state): nothing moves
    and the probed point is where the machine stands."""
    result = run(machine, tmp_path, f"G21 G90 G94\nG0 Z{start:g}\n{code} Z{end} F300\n#1 = #5063\n"
                                    "#2 = #5070\nM2\n")
    assert result.ok, result.error
    assert (machine.interp.parameter(1), machine.interp.parameter(2)) == pytest.approx((start, 1.0))
    assert machine.motion.commanded[1] == pytest.approx(start)  # nothing moved


def test_g38_2_without_a_trip_is_the_usual_error(machine: Machine, tmp_path: Path) -> None:
    result = run(machine, tmp_path, "G21 G90 G94\nG38.2 Z-0.5 F600\nM2\n")
    assert not result.ok
    assert "p.ngc:3" in result.error, result.error
    assert machine.motion.commanded[1] == pytest.approx(-0.5)


def test_a_probe_bound_to_a_register_is_refused_naming_the_key(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as info:
        load(tmp_path, '\n[io.functions]\nprobe = { device = "io", holding_register = 3 }\n')
    assert "io.functions.probe" in str(info.value) and "digital" in str(info.value), str(info.value)
    with pytest.raises(ConfigError, match=r"io\.sim\.probe_z"):
        load(tmp_path, '\n[io.sim]\nprobe_z = -1.0\n')
