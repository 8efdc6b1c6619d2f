"""The door interlock and jogging on the simulated demo machine (door_open: discrete input 14): a jog is
refused while the door is open, and a jog in progress stops when it opens. docs/wiring.md."""

from __future__ import annotations

import time

import pytest
from test_machine_io_e2e import Rig, rig  # noqa: F401  (the fixture)
from test_run_from_line import wait_for

from motiond.states import CommandRefused

DOOR = 14


def test_a_jog_is_refused_while_the_door_is_open(rig: Rig) -> None:  # noqa: F811
    rig.sim.set("discrete_input", DOOR, 1)
    wait_for(lambda: rig.machine.io_hooks.mio.jog_problem() != "", "the door read open")
    with pytest.raises(CommandRefused,
                       match=r"cannot jog: the door is open \(io.functions.door_open, .*discrete input 14\)"):
        rig.machine.jog("x", 10.0, 2.0)
    time.sleep(0.1)
    assert rig.x() == 0.0 and not rig.machine.motion.jogging
    rig.sim.set("discrete_input", DOOR, 0)
    wait_for(lambda: rig.machine.io_hooks.mio.jog_problem() == "", "the door read closed")
    rig.machine.jog("x", 10.0, 2.0)
    wait_for(lambda: abs(rig.x() - 2.0) < 1e-9, "the jog done once the door is closed")


def test_a_jog_in_progress_stops_when_the_door_opens(rig: Rig) -> None:  # noqa: F811
    rig.machine.jog("x", 20.0)  # continuous: until stopped (or the soft limit)
    wait_for(lambda: rig.x() > 1.0, "the jog moving")
    rig.sim.set("discrete_input", DOOR, 1)
    t_open = time.monotonic()
    wait_for(lambda: not rig.machine.motion.jogging and not any(rig.machine.motion.velocity),
             "the jog stopped")
    stopped_at = rig.x()
    lim = rig.machine.limits.axes[0]
    assert lim.max_position is None or stopped_at < lim.max_position - 1.0  # stopped, not at its end
    # seen by the next poll, then stopped on the jog's ramp (generous: the PC may be loaded)
    assert time.monotonic() - t_open < 5.0
    assert any(e[2] == "io_jog_stop" and "door open" in e[1] for e in rig.events), rig.events
    time.sleep(0.2)
    assert rig.x() == stopped_at
