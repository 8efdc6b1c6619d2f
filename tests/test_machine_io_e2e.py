"""The I/O map end to end on the simulated demo machine (in this process: simulated drives, the
simulated Modbus module wired as motiond.config_io.DEMO_FUNCTIONS says): spindle at speed, coolant,
the E-stop chain, a Modbus limit switch, the door, a user M code. docs/wiring.md.

Demo wiring: E-stop DI 8 (active low), machine enable coil 8, spindle on coil 9, at speed DI 9,
flood coil 13, cycle start DI 11, door DI 14, limit_x_max DI 17, M101: coil 14 then DI 15.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from motion_process_helpers import OWN, fifo_allowed, own_mode, thread_policy
from test_run_from_line import Recorder, wait_for

from motiond.config import load_machine
from motiond.runtime import Machine
from motiond.states import CommandRefused, State

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "canon.toml"
"""The demo machine's wiring in a file (the motion in its own process needs one: test_motion_process)."""
OWN_STOP_CYCLES = 50
"""With the motion in its own process: the quick stop of an E-stop input or a limit switch leaves the
motion process within this many cycles of the task's I/O loop acting on the input. Measured on the
loaded 2-core test PC (bench/io_stop_latency.py, docs/wiring.md): median 1-2 ms, p90 up to 6 ms, worst
70 ms in 60 trips (the motion process descheduled); 50 cycles is 100 ms."""


class Rig(Recorder):
    """test_run_from_line's started, enabled demo machine, with its setpoints traced and the cycle of
    every state change kept. ``own``: the same wiring with the motion in a process of its own."""

    def __init__(self, tmp: Path, own: bool = False) -> None:
        if own:
            path = tmp / "own.toml"
            path.write_text(own_mode(EXAMPLE.read_text()))
            super().__init__(tmp, str(path), modbus_port=0)
        else:
            super().__init__(tmp)
        self.tmp = tmp
        self.machine.trace = []
        self.state_cycles: list[tuple[State, int, float]] = []
        self.machine.states.subscribe(lambda b, a: self.state_cycles.append(
            (a.state, self.machine.cycle, time.monotonic())) if a.state != b.state else None)
        self.sim = self.machine.sim_io["io"]

    def program(self, text: str) -> Path:
        p = self.tmp / "part.ngc"
        p.write_text(text)
        return p

    def x(self) -> float:
        return self.machine.motion.commanded[0]


@pytest.fixture(params=["thread", OWN])
def rig(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[Rig]:
    r = Rig(tmp_path, own=request.param == "own")
    try:
        yield r
    finally:
        r.machine.shutdown()


def first_write(rig: Rig, table: str, address: int, value: int, since: int = 0) -> float:
    """When the module got the first write of ``value`` to ``table[address]`` from record ``since``
    on (the safe state written at start comes first: pass ``since``)."""
    w = rig.sim.wait_write(table, address, value, since=since, timeout=10.0)
    assert w is not None, f"{table} {address} never written {value}"
    return w.t


def after_start(rig: Rig) -> int:
    """The record number after the start's safe-state writes (the job's writes come later)."""
    return len(rig.sim.writes)


def test_m3_waits_for_at_speed_before_the_next_feed_move_and_m5_stops_it(rig: Rig) -> None:
    n = after_start(rig)
    job = rig.machine.run(rig.program("%\nG21 G90 G94\nG1 X5 F3000\nM3 S1000\nG1 X10\nM5\nM2\n%\n"))
    result = rig.machine.wait_job(job, 30.0)
    assert result is not None and result.ok, result.error if result else "timeout"
    t_on = first_write(rig, "coil", 9, 1, n)
    assert rig.sim.get("holding_register", 8) == 1000  # the speed command, rpm (scale 1)
    delay = rig.machine.io_hooks.map.spindle.sim_delay_s
    # the first setpoint beyond X5 comes only after the simulated spindle reached speed
    moved = [t for _c, t, pos, _ev in rig.machine.trace if pos[0] > 5.0 + 1e-6]
    assert moved and moved[0] >= t_on + delay, (moved[0] - t_on, delay)
    t_off = first_write(rig, "coil", 9, 0, n)
    assert t_off > moved[0]
    names = [(o.name, o.value, o.line) for o in result.outputs if o.kind == "function"]
    assert ("spindle_on", 1.0, 4) in names and ("spindle_on", 0.0, 6) in names


def test_m8_m9_switch_the_coolant_coil(rig: Rig) -> None:
    n = after_start(rig)
    job = rig.machine.run(rig.program("%\nG21 G90 G94\nM8\nG1 X2 F3000\nM9\nG1 X3\nM2\n%\n"))
    result = rig.machine.wait_job(job, 30.0)
    assert result is not None and result.ok
    t_on = first_write(rig, "coil", 13, 1, n)
    t_off = first_write(rig, "coil", 13, 0, n)
    assert t_on < t_off
    names = [(o.name, o.value, o.line) for o in result.outputs if o.kind == "function"]
    assert names == [("coolant_flood", 1.0, 3), ("coolant_flood", 0.0, 5)]


def test_m62_m63_ride_on_the_next_move_and_switch_their_coil(rig: Rig) -> None:
    """The synchronized outputs go out with their setpoint (with the motion in its own process: as a
    hook in order with its cycle's state, the Modbus worker being the task's)."""
    n = after_start(rig)
    job = rig.machine.run(rig.program("%\nG21 G90 G94\nM62 P0\nG1 X2 F3000\nM63 P0\nG1 X3\nM2\n%\n"))
    result = rig.machine.wait_job(job, 30.0)
    assert result is not None and result.ok, result.error if result else "timeout"
    t_on = first_write(rig, "coil", 0, 1, n)
    t_off = first_write(rig, "coil", 0, 0, n)
    assert t_on < t_off
    digital = [(o.index, o.value, o.line) for o in result.outputs if o.kind == "digital"]
    assert digital == [(0, 1.0, 3), (0, 0.0, 5)], digital


def test_estop_input_during_motion_stops_at_once_and_drops_machine_enable(rig: Rig) -> None:
    wait_for(lambda: rig.sim.get("coil", 8) == 1, "machine enable on once enabled")
    n = len(rig.sim.writes)
    job = rig.machine.run(rig.program("%\nG21 G90 G94\nG1 X100 F6000\nM2\n%\n"))
    wait_for(lambda: rig.x() > 5.0, "the axis moving")
    rig.sim.set("discrete_input", 8, 0)  # the NC chain opens: E-stop pressed
    t_pressed = time.monotonic()
    wait_for(lambda: rig.machine.states.state is State.ESTOP, "ESTOP")
    _state, cycle, t_estop = next(s for s in rig.state_cycles if s[0] is State.ESTOP)
    poll_s = rig.machine.modbus.devices[0].poll_ms / 1000.0
    # seen by the next poll, acted on in the next cycle (generous: the PC may be loaded)
    assert t_estop - t_pressed < poll_s + 1.0
    if rig.machine.motion_mode == "own":  # the motion process's cycles: the quick stop's came by pipe
        cycle = stop_latency(rig, "last_estop", "estop")
        if fifo_allowed():  # the loop that read the input is on the stop path: FIFO two below the cycle
            assert thread_policy(rig.machine.io_loop._thread.native_id) == (os.SCHED_FIFO, 78)
    # no setpoint streamed after the cycle that saw it
    assert max(c for c, _t, _p, _e in rig.machine.trace) <= cycle
    assert rig.x() < 100.0
    assert first_write(rig, "coil", 8, 0, since=n) > t_pressed  # machine enable dropped
    # the event follows the state (Machine.estop: state, quick stop, outputs, then the event)
    wait_for(lambda: any("E-stop input active" in e[1] and "discrete input 8" in e[1] for e in rig.events),
             "the E-stop input's event")
    result = rig.machine.wait_job(job, 5.0)
    assert result is not None and not result.ok
    with pytest.raises(CommandRefused, match="E-stop input is active"):
        rig.machine.estop_reset()
    rig.sim.set("discrete_input", 8, 1)
    wait_for(lambda: rig.machine.io_hooks.mio.estop_problem() == "", "the chain read closed")
    rig.machine.bring_up()
    wait_for(lambda: rig.sim.get("coil", 8) == 1, "machine enable raised on enable")


def test_lost_io_link_with_an_estop_input_is_estop(rig: Rig) -> None:
    rig.sim.stop()
    wait_for(lambda: any("unreadable" in e[1] for e in rig.events if e[2] == "estop"), "the E-stop event",
             timeout=20.0)
    assert rig.machine.states.state is State.ESTOP


def test_a_modbus_limit_switch_during_motion_stops_naming_axis_and_switch(rig: Rig) -> None:
    rig.machine.run(rig.program("%\nG21 G90 G94\nG1 X100 F6000\nM2\n%\n"))
    wait_for(lambda: rig.x() > 5.0, "the axis moving")
    # the operator's hand on the switch: the example's [io.sim] limit_x_max (computed from the position
    # at every read, tests/test_sim_limits.py) is taken off first, or it would read the switch free
    rig.sim.computed[:] = [c for c in rig.sim.computed if c[:2] != ("discrete_input", 17)]
    rig.sim.set("discrete_input", 17, 1)  # limit_x_max
    wait_for(lambda: rig.machine.states.state is State.FAULTED, "FAULTED")
    err = rig.machine.last_error
    assert "axis x" in err and "limit_x_max" in err and "discrete input 17" in err, err
    assert rig.machine.master.fault is not None  # stopped as a drive's limit switch stops it
    assert rig.x() < 100.0
    if rig.machine.motion_mode == "own":
        stop_latency(rig, "last_quick_stop", "limit")


def stop_latency(rig: Rig, which: str, kind: str) -> int:
    """With the motion in its own process: the quick stop (``which``: the motion process's record of
    it, in its states) left the motion process within OWN_STOP_CYCLES of the I/O loop acting on the
    input; the motion process's cycle then."""
    seen = rig.machine.io_hooks.stop_seen
    assert seen is not None and seen[0] == kind, seen
    wait_for(lambda: (getattr(rig.machine.motion, which) or (0.0, 0.0))[1] >= seen[1],
             f"the motion process's {which} in its state")
    _arrived, sent, _cycle, cycle_after = getattr(rig.machine.motion, which)
    assert 0.0 <= sent - seen[1] < OWN_STOP_CYCLES * rig.machine.T, (sent - seen[1], rig.machine.T)
    return cycle_after


def test_door_opened_mid_program_holds_and_resumes_on_close_and_cycle_start(rig: Rig) -> None:
    job = rig.machine.run(rig.program("%\nG21 G90 G94\nG1 X100 F3000\nM2\n%\n"))
    wait_for(lambda: rig.x() > 2.0, "the axis moving")
    rig.sim.set("discrete_input", 14, 1)  # door open
    wait_for(lambda: rig.machine.states.state is State.PAUSED, "PAUSED on the door")
    wait_for(lambda: not any(rig.machine.motion.velocity), "motion held")
    held = rig.x()
    assert held < 100.0
    rig.sim.set("discrete_input", 11, 1)  # cycle start with the door open: refused
    wait_for(lambda: any(e[2] == "io_refused" for e in rig.events), "the refusal")
    assert rig.machine.states.state is State.PAUSED
    with pytest.raises(CommandRefused, match="door is open"):
        rig.machine.resume()
    rig.sim.set("discrete_input", 11, 0)
    rig.sim.set("discrete_input", 14, 0)  # door closed: still held until cycle start
    wait_for(lambda: not rig.machine.io_hooks.mio.door_open, "the door read closed")
    time.sleep(0.1)
    assert rig.machine.states.state is State.PAUSED and rig.x() == held
    rig.sim.set("discrete_input", 11, 1)  # cycle start
    result = rig.machine.wait_job(job, 30.0)
    assert result is not None and result.ok
    assert abs(rig.x() - 100.0) < 1e-9


def test_the_door_stops_spindle_and_coolant_and_cycle_start_restores_them_before_the_motion(rig: Rig) -> None:
    n = after_start(rig)
    job = rig.machine.run(rig.program("%\nG21 G90 G94\nM3 S1000 M8\nG1 X100 F3000\nM5 M9\nM2\n%\n"))
    wait_for(lambda: rig.x() > 2.0, "the axis moving")
    rig.sim.set("discrete_input", 14, 1)  # door open
    wait_for(lambda: rig.machine.states.state is State.PAUSED, "PAUSED on the door")
    first_write(rig, "coil", 9, 0, n)  # spindle off
    first_write(rig, "coil", 13, 0, n)  # flood off
    wait_for(lambda: not any(rig.machine.motion.velocity), "motion held")
    held = rig.x()
    rig.sim.set("discrete_input", 14, 0)  # closed: the spindle stays off until cycle start
    wait_for(lambda: not rig.machine.io_hooks.mio.door_open, "the door read closed")
    with pytest.raises(CommandRefused, match="door stopped the spindle"):
        rig.machine.resume()
    n2 = len(rig.sim.writes)
    rig.sim.set("discrete_input", 11, 1)  # cycle start: spindle and coolant back, then the motion
    t_on = first_write(rig, "coil", 9, 1, n2)
    first_write(rig, "coil", 13, 1, n2)
    result = rig.machine.wait_job(job, 30.0)
    assert result is not None and result.ok, result.error if result else "timeout"
    delay = rig.machine.io_hooks.map.spindle.sim_delay_s
    moved = [t for _c, t, pos, _ev in rig.machine.trace if pos[0] > held + 1e-6]
    assert moved and moved[0] >= t_on + delay, (moved[0] - t_on, delay)  # at speed first


def test_m101_sets_its_output_and_waits_for_its_input(rig: Rig) -> None:
    rig.sim.rules[:] = [r for r in rig.sim.rules if r.when_address != 14]  # nobody answers but us
    job = rig.machine.run(rig.program("%\nG21 G90 G94\nG1 X2 F3000\nM101\nG1 X4\nM2\n%\n"))
    first_write(rig, "coil", 14, 1)
    wait_for(lambda: "M101" in rig.machine.io_hooks.mio.waiting, "the wait for M101's input")
    time.sleep(0.2)
    assert rig.x() == pytest.approx(2.0) and rig.machine.status().io_waiting.startswith(
        f"{rig.tmp / 'part.ngc'}:4: M101")
    t_in = time.monotonic()
    rig.sim.set("discrete_input", 15, 1)
    result = rig.machine.wait_job(job, 30.0)
    assert result is not None and result.ok
    moved = [t for _c, t, pos, _ev in rig.machine.trace if pos[0] > 2.0 + 1e-6]
    assert moved and moved[0] > t_in


def test_status_carries_every_function(rig: Rig) -> None:
    wait_for(lambda: dict(zip(rig.machine.status().io_function_names, rig.machine.status().io_function_values,
                              strict=True))["machine_enable"] == 1.0, "machine enable on in the status")
    s = rig.machine.status()
    assert s.num_io_functions == len(s.io_function_names) == len(s.io_function_values)
    values = dict(zip(s.io_function_names, s.io_function_values, strict=True))
    assert values["machine_enable"] == 1.0 and values["estop"] == 0.0 and values["spindle_on"] == 0.0


def test_a_binding_error_in_the_machine_file_names_the_key(tmp_path: Path) -> None:
    from motiond.configkit import ConfigError

    text = (Path(__file__).resolve().parent.parent / "examples" / "canon.toml").read_text()
    bad = tmp_path / "m.toml"
    bad.write_text(text.replace('coolant_flood = { device = "io", coil = 13 }',
                                'coolant_flood = { device = "io", coil = 9 }'))
    with pytest.raises(ConfigError) as info:
        Machine(load_machine(str(bad)), lc=None)
    assert info.value.key == "io.functions.coolant_flood"
    assert "already written by io.functions.spindle_on" in str(info.value)


def test_canon_run_lists_the_functions_it_switched(tmp_path: Path) -> None:
    import json
    import subprocess
    import sys

    prog = tmp_path / "p.ngc"
    prog.write_text("%\nG21 G90 G94\nM3 S1000 M8\nG1 X2 F3000\nM5 M9\nM2\n%\n")
    r = subprocess.run([sys.executable, "-m", "motiond.cli", "run", "--json", "--no-telemetry", str(prog)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    outs = [(o["name"], o["value"], o["line"]) for o in json.loads(r.stdout)["outputs_switched"]
            if o["kind"] == "function"]
    assert ("spindle_on", 1.0, 3) in outs and ("coolant_flood", 1.0, 3) in outs
    assert ("spindle_on", 0.0, 5) in outs and ("coolant_flood", 0.0, 5) in outs
    r = subprocess.run([sys.executable, "-m", "motiond.cli", "run", "--no-telemetry", str(prog)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "spindle_on=1 (line 3)" in r.stdout.replace("\n", " "), r.stdout
