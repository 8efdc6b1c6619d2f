"""Simulated limit switches at configured positions (``[io.sim] limit_<axis>_<min|max>``,
motiond.sim_wiring): on examples/canon.toml's machine a program that overruns limit_x_max stops there,
FAULTED, the fault naming axis and switch. docs/wiring.md."""

from __future__ import annotations

import tomllib
from collections.abc import Iterator
from pathlib import Path

import pytest
from test_drive_outputs import started
from test_run_from_line import wait_for

from motiond.config import load_machine
from motiond.configkit import ConfigError
from motiond.runtime import Machine
from motiond.states import State

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "canon.toml"


@pytest.fixture
def machine(tmp_path: Path) -> Iterator[Machine]:
    with started(EXAMPLE, tmp_path) as m:
        yield m


def test_a_program_overrunning_a_simulated_limit_switch_stops_naming_axis_and_switch(
        machine: Machine, tmp_path: Path) -> None:
    trip = tomllib.loads(EXAMPLE.read_text())["io"]["sim"]["limit_x_max"]
    x = machine.limits.axes[0]
    assert x.max_position is not None and trip + 5.0 <= x.max_position  # the planner lets it reach it
    prog = tmp_path / "overrun.ngc"
    prog.write_text(f"%\nG21 G90 G94\nG53 G0 X{trip - 10.0:g}\nG53 G1 X{trip + 5.0:g} F3000\nM2\n%\n")
    result = machine.wait_job(machine.run(prog), 60.0)
    assert result is not None and not result.ok
    wait_for(lambda: machine.states.state is State.FAULTED, "FAULTED")
    reason = machine.last_error
    assert "axis x" in reason and "limit_x_max" in reason and "discrete input 17" in reason, reason
    wait_for(lambda: not any(machine.motion.velocity), "at rest")
    stopped = machine.motion.commanded[0]
    # tripped at the switch (seen within a poll), stopped on the quick-stop ramp well before the target
    assert trip <= stopped < trip + 5.0, stopped


def test_a_simulated_limit_needs_its_function_on_a_modbus_point(tmp_path: Path) -> None:
    text = EXAMPLE.read_text().replace("limit_z_min = -45.0", "limit_y_min = -1.0\nlimit_z_min = -45.0")
    text = text.replace('limit_y_min = { device = "io", discrete_input = 18 }\n', "")
    f = tmp_path / "m.toml"
    f.write_text(text)
    with pytest.raises(ConfigError) as info:
        Machine(load_machine(str(f)), lc=None)
    assert info.value.key == "io.sim.limit_y_min" and "needs io.functions.limit_y_min" in str(info.value)
