"""The I/O map (``[io]``, motiond.config_io) and its run-time side (motiond.machine_io.MachineIO) on a
real simulated Modbus module: E-stop chain, machine enable, spindle waits, user M codes, limits, door.

The whole machine (runtime hooks, planner waits) is tested in tests/test_machine_io_e2e.py.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from fieldbus.modbus.executor import IoExecutor
from fieldbus.modbus.sim import SimIoModule
from gcode_canon import commands as C
from motiond.config import load_machine
from motiond.config_io import io_for, machine_io, modbus_with_io
from motiond.config_modbus import modbus_for
from motiond.configkit import ConfigError
from motiond.machine_io import ABORT, ESTOP, FAULT, LIMIT, PAUSE, RELEASE, RESUME, MachineIO, MachineState

BASE = """[machine]
name = "io test"
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
port = 5020
simulate = true
[[modbus.devices]]
name = "plc"
port = 5021
[[modbus.digital_outputs]]
index = 0
device = "io"
coil = 0
"""


def load(tmp_path: Path, io: str) -> tuple[object, object]:
    f = tmp_path / "m.toml"
    f.write_text(BASE + io)
    m = load_machine(str(f))
    return m, io_for(m, modbus_for(m))


def test_a_full_map_reads(tmp_path: Path) -> None:
    _m, io = load(tmp_path, """
[io.functions]
estop = { device = "io", discrete_input = 8 }
machine_enable = { device = "io", coil = 8 }
spindle_on = { device = "io", coil = 9 }
spindle_reverse = { device = "io", coil = 10 }
spindle_speed = { device = "plc", holding_register = 3, type = "float32", scale = 0.1 }
spindle_speed_measured = { device = "plc", input_register = 4, type = "int16", scale = 10.0 }
limit_x_max = { drive = "x", bit = 1 }
door_open = { device = "io", discrete_input = 9, active = "low" }
[io.spindle]
max_rpm = 12000
at_speed_tolerance = 0.1
[io.mcodes.M101]
set = [{ device = "io", coil = 14 }]
wait = { device = "io", discrete_input = 15 }
timeout_s = 3.0
[io.mcodes.M102]
set = [{ device = "io", coil = 14, value = 0 }]
""")
    f = io.functions
    assert f["estop"].active_low and not f["spindle_on"].active_low  # E-stop: NC by default
    assert f["door_open"].active_low
    assert f["spindle_speed"].point.conversion.scale == 0.1
    assert f["limit_x_max"].drive_axis == "x" and f["limit_x_max"].bit == 1
    assert io.spindle.max_rpm == 12000.0
    # M101 and M102 share coil 14: one point, written by both
    assert io.mcodes[101].sets[0][0].point is io.mcodes[102].sets[0][0].point
    assert io.mcodes[102].sets[0][1] == 0.0
    keys = [p.key for p in io.points]
    assert len(keys) == len(set(keys)) and "limit_x_max" not in keys  # drive inputs are no Modbus points


@pytest.mark.parametrize(("io", "key", "message"), [
    ("[io.functions]\nestop = { device = \"nope\", discrete_input = 1 }\n", "io.functions.estop.device",
     "no [[modbus.devices]] is named 'nope'"),
    ("[io.functions]\nestop = { device = \"io\", discrete_input = 70000 }\n",
     "io.functions.estop.discrete_input", "must be between 0 and 65535"),
    ("[io.functions]\nspindle_speed = { device = \"io\", holding_register = 65535, type = \"float32\" }\n",
     "io.functions.spindle_speed.holding_register", "beyond the last Modbus address"),
    ("[io.functions]\nlaser = { device = \"io\", coil = 1 }\n", "io.functions.laser", "unknown function"),
    ("[io.functions]\nlimit_y_min = { device = \"io\", discrete_input = 1 }\n", "io.functions.limit_y_min",
     "unknown function"),  # the machine has no y axis
    ("[io.functions]\nspindle_on = { device = \"io\", discrete_input = 1 }\n",
     "io.functions.spindle_on.discrete_input", "is an output"),
    ("[io.functions]\ncoolant_flood = { device = \"io\", coil = 0 }\n", "io.functions.coolant_flood",
     "already written by modbus.digital_outputs (M62-M65 P0): bound twice"),
    ("[io.functions]\ncoolant_flood = { device = \"io\", coil = 3 }\n"
     "coolant_mist = { device = \"io\", coil = 3 }\n",
     "io.functions.coolant_mist", "already written by io.functions.coolant_flood: bound twice"),
    ("[io.functions]\nspindle_on = { device = \"io\", coil = 3 }\n"
     "spindle_cw = { device = \"io\", coil = 4 }\n",
     "io.functions.spindle_cw", "the spindle is bound twice"),
    ("[io.functions]\nmachine_enable = { drive = \"y\", bit = 3 }\n", "io.functions.machine_enable.drive",
     "no [canopen.axes.y]"),
    ("[io.functions]\nmachine_enable = { drive = \"x\", bit = 32 }\n", "io.functions.machine_enable.bit",
     "between 0 and 31"),
    ("[io.functions]\nmachine_enable = { drive = \"x\", bit = 3 }\n"
     "coolant_flood = { drive = \"x\", bit = 3 }\n",
     "io.functions.coolant_flood", "drive x 0x60FE bit 3 is already written by io.functions.machine_enable: "
                                   "bound twice"),
    ("[io.functions]\ncoolant_flood = { drive = \"z\", bit = 4 }\n[io.mcodes.M103]\n"
     "set = [{ drive = \"z\", bit = 4 }]\n", "io.mcodes.M103.set[0]", "already written by "
                                                                      "io.functions.coolant_flood"),
    ("[io.functions]\nspindle_speed = { drive = \"x\", bit = 3 }\n", "io.functions.spindle_speed.drive",
     "digital outputs (0x60FE) are bits"),
    ("[io.functions]\nestop = { drive = \"y\", bit = 3 }\n", "io.functions.estop.drive",
     "no [canopen.axes.y]"),
    ("[io.functions]\nestop = { device = \"io\", discrete_input = 1, active = \"open\" }\n",
     "io.functions.estop.active", "must be one of high, low"),
    ("[io.functions]\nestop = { device = \"io\", discrete_input = 1, invert = true }\n",
     "io.functions.estop.invert", "unknown key"),
    ("[io.mcodes.M200]\nset = [{ device = \"io\", coil = 5 }]\n", "io.mcodes.M200", "M100 to M199"),
    ("[io.mcodes.M105]\ntimeout_s = 2.0\n", "io.mcodes.M105.set", "needs outputs to set"),
    ("[io.spindle]\nmin_rpm = 500\nmax_rpm = 100\n", "io.spindle.min_rpm", "must not be above max_rpm"),
])
def test_binding_errors_name_the_key(tmp_path: Path, io: str, key: str, message: str) -> None:
    with pytest.raises(ConfigError) as info:
        load(tmp_path, io)
    assert info.value.key == key, str(info.value)
    assert message in info.value.message
    assert str(tmp_path / "m.toml") in str(info.value)


def test_a_function_bound_twice_in_the_table_is_a_toml_error(tmp_path: Path) -> None:
    line = BASE.count("\n") + 3  # the second estop
    with pytest.raises(ConfigError, match=f"Cannot overwrite a value \\(at line {line},"):
        load(tmp_path, "[io.functions]\nestop = { device = \"io\", discrete_input = 1 }\n"
                       "estop = { device = \"io\", discrete_input = 2 }\n")


def test_config_check_reports_an_io_binding_error(tmp_path: Path) -> None:
    from motiond.config_check import validate_machine
    from motiond.configkit import ConfigErrors

    f = tmp_path / "m.toml"
    f.write_text(BASE + "[io.functions]\nestop = { device = \"io\", discrete_input = 1 }\n"
                        "spindle_at_speed = { device = \"io\", input_register = 0 }\n")
    with pytest.raises(ConfigErrors) as info:
        validate_machine(str(f))
    keys = [e.key for e in info.value.errors]
    assert "io.functions.spindle_at_speed.input_register" in keys, str(info.value)


# --- MachineIO on a simulated module --------------------------------------------------------------

MAP = """
[io.functions]
estop = { device = "io", discrete_input = 8 }
machine_enable = { device = "io", coil = 8 }
spindle_on = { device = "io", coil = 9 }
spindle_reverse = { device = "io", coil = 10 }
spindle_speed = { device = "io", holding_register = 8 }
spindle_at_speed = { device = "io", discrete_input = 9 }
coolant_flood = { device = "io", coil = 13 }
cycle_start = { device = "io", discrete_input = 11 }
feed_hold = { device = "io", discrete_input = 12 }
abort = { device = "io", discrete_input = 13 }
door_open = { device = "io", discrete_input = 14 }
limit_x_max = { device = "io", discrete_input = 17 }
[io.spindle]
max_rpm = 10000
at_speed_timeout_s = 1.0
[io.mcodes.M101]
set = [{ device = "io", coil = 14 }]
wait = { device = "io", discrete_input = 15 }
timeout_s = 1.0
"""


class Rig:
    def __init__(self, sim: SimIoModule, ex: IoExecutor, mio: MachineIO) -> None:
        self.sim, self.ex, self.mio = sim, ex, mio

    def state(self, **kw: object) -> MachineState:
        base = {"estop": False, "enabled": True, "running": True, "paused": False, "velocity": (0.0, 0.0)}
        base.update(kw)
        return MachineState(**base)  # type: ignore[arg-type]

    def poll_until(self, pred: Callable[[list], bool], timeout: float = 3.0, **kw: object) -> list | None:
        """Poll like the cycle does (every 2 ms) until ``pred(actions)``; the actions then (None: it
        never held)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            acts = self.mio.poll(self.state(**kw))
            if pred(acts):
                return acts
            time.sleep(0.002)
        return None


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[Rig]:
    sim = SimIoModule(size=64).start()
    sim.set("discrete_input", 8, 1)  # the E-stop chain closed: not pressed
    f = tmp_path / "m.toml"
    f.write_text((BASE + MAP).replace("port = 5020", f"port = {sim.port}").replace(
        '[[modbus.devices]]\nname = "plc"\nport = 5021\n', ""))
    mb, io = machine_io(load_machine(str(f)))
    ex = IoExecutor(mb).start()
    mio = MachineIO(io, ex, ("x", "z"))
    r = Rig(sim, ex, mio)
    assert r.poll_until(lambda a: mio.estop_problem() == "") is not None, mio.estop_problem()
    yield r
    ex.stop()
    sim.stop()


def kinds(acts: list) -> list[str]:
    return [a.kind for a in acts]


def test_estop_input_opening_asks_for_estop_and_drops_machine_enable(rig: Rig) -> None:
    assert rig.sim.wait_write("coil", 8, 1, timeout=2.0) is not None  # enabled, chain closed: on
    n = len(rig.sim.writes)
    rig.sim.set("discrete_input", 8, 0)  # the button pressed: the NC chain opens
    t0 = time.monotonic()
    acts = rig.poll_until(lambda a: ESTOP in kinds(a))
    seen = time.monotonic() - t0
    assert acts and "E-stop input active" in acts[0].reason and "discrete input 8" in acts[0].reason
    assert seen < 20e-3 + 1.0  # a poll period and a request (bounded loosely: a loaded PC)
    assert "E-stop input is active" in rig.mio.estop_problem()
    # the machine goes to ESTOP; the next poll drops machine enable
    rig.mio.poll(rig.state(estop=True, enabled=False))
    assert rig.sim.wait_write("coil", 8, 0, since=n, timeout=2.0) is not None


def test_lost_link_with_an_estop_input_is_estop(rig: Rig) -> None:
    rig.sim.stop()
    acts = rig.poll_until(lambda a: ESTOP in kinds(a), timeout=10.0)
    assert acts and "unreadable" in acts[0].reason and "treated as E-stop" in acts[0].reason
    assert "cannot be read" in rig.mio.estop_problem()


def test_m3_waits_for_at_speed_and_m5_drops_the_spindle(rig: Rig) -> None:
    cmd = C.SpindleOn(C.SpindleDirection.CCW, 12000.0, file="p.ngc", line=4)
    switched = rig.mio.on_event(cmd)
    assert {s.name: s.value for s in switched} == {"spindle_speed": 10000.0, "spindle_reverse": 1.0,
                                                    "spindle_on": 1.0}  # clamped to max_rpm
    assert C.SpindleOn in rig.mio.wait_types and rig.mio.on_wait(cmd)
    assert rig.sim.wait_write("coil", 9, 1) is not None and rig.sim.get("holding_register", 8) == 10000
    assert rig.poll_until(lambda a: RELEASE in kinds(a), timeout=0.2) is None  # not at speed yet
    rig.sim.set("discrete_input", 9, 1)
    assert RELEASE in kinds(rig.poll_until(lambda a: RELEASE in kinds(a)))
    rig.mio.on_event(C.SpindleOff(file="p.ngc", line=9))
    assert rig.sim.wait_write("coil", 9, 0) is not None


def test_at_speed_timeout_names_the_line(rig: Rig) -> None:
    cmd = C.SpindleOn(C.SpindleDirection.CW, 1000.0, file="p.ngc", line=7)
    rig.mio.on_event(cmd)
    rig.mio.on_wait(cmd)
    acts = rig.poll_until(lambda a: FAULT in kinds(a))
    assert acts and acts[-1].reason.startswith("p.ngc:7: M3 S1000: spindle at speed")
    assert "not done within 1 s" in acts[-1].reason


def test_user_mcode_sets_its_output_and_waits_for_its_input(rig: Rig) -> None:
    cmd = C.UserMCode(101, file="p.ngc", line=3)
    assert rig.mio.on_wait(cmd)
    assert rig.sim.wait_write("coil", 14, 1) is not None
    assert rig.poll_until(lambda a: RELEASE in kinds(a), timeout=0.2) is None
    rig.sim.set("discrete_input", 15, 1)
    assert RELEASE in kinds(rig.poll_until(lambda a: RELEASE in kinds(a)))


def test_limit_switch_while_moving_names_axis_and_switch(rig: Rig) -> None:
    rig.sim.set("discrete_input", 17, 1)
    acts = rig.poll_until(lambda a: LIMIT in kinds(a), velocity=(5.0, 0.0))
    assert acts and acts[0].axis == "x"
    assert "axis x: positive limit switch limit_x_max active" in acts[0].reason
    # the switch still active after a reset: moving away is allowed, toward it is not
    rig.mio.poll(rig.state(enabled=False))
    assert LIMIT not in kinds(rig.mio.poll(rig.state(velocity=(-5.0, 0.0))))
    assert LIMIT in kinds(rig.mio.poll(rig.state(velocity=(5.0, 0.0))))


def test_operator_buttons_and_door(rig: Rig) -> None:
    rig.sim.set("discrete_input", 14, 1)  # door opened while running: hold
    acts = rig.poll_until(lambda a: PAUSE in kinds(a))
    assert acts and "door open" in acts[0].reason and rig.mio.door_open
    rig.sim.set("discrete_input", 14, 0)
    assert rig.poll_until(lambda a: not rig.mio.door_open, running=False, paused=True) is not None
    rig.sim.set("discrete_input", 11, 1)  # cycle start
    assert RESUME in kinds(rig.poll_until(lambda a: RESUME in kinds(a), running=False, paused=True))
    rig.sim.set("discrete_input", 12, 1)
    assert PAUSE in kinds(rig.poll_until(lambda a: PAUSE in kinds(a)))
    rig.sim.set("discrete_input", 13, 1)
    assert ABORT in kinds(rig.poll_until(lambda a: ABORT in kinds(a)))


def test_status_lists_every_function(rig: Rig) -> None:
    rig.mio.on_event(C.Coolant(False, True))
    names, values = rig.mio.status()
    assert names == list(rig.mio.io.functions)
    assert values[names.index("coolant_flood")] == 1.0
    assert values[names.index("estop")] == 0.0  # chain closed: not active


def test_named_points_ride_with_the_modbus_configuration() -> None:
    mb, io = machine_io(load_machine(None))
    assert mb is not None and {p.key for p in mb.named} == {p.key for p in io.points}
    assert modbus_with_io(None, io) is None


def test_the_simulated_module_is_wired_like_the_map() -> None:
    from motiond.config_io import demo_io
    from motiond.config_modbus import demo_modbus
    from motiond.sim_wiring import apply, wiring_for

    io = demo_io(demo_modbus())
    wiring = wiring_for(io)
    with SimIoModule(size=64) as sim:
        apply(sim, wiring["io"])
        assert sim.get("discrete_input", 8) == 1  # the NC E-stop chain reads closed
        ex = IoExecutor(modbus_with_io(demo_modbus(port=sim.port), io)).start()
        try:
            t0 = time.monotonic()
            ex.write_point("spindle_on", 1).result(2.0)
            deadline = time.monotonic() + 3.0
            while sim.get("discrete_input", 9) == 0 and time.monotonic() < deadline:
                time.sleep(0.005)
            assert sim.get("discrete_input", 9) == 1
            assert time.monotonic() - t0 >= io.spindle.sim_delay_s - 0.01  # after the configured delay
            ex.write_point("spindle_on", 0).result(2.0)
            deadline = time.monotonic() + 3.0
            while sim.get("discrete_input", 9) == 1 and time.monotonic() < deadline:
                time.sleep(0.005)
            assert sim.get("discrete_input", 9) == 0
        finally:
            ex.stop()


def test_the_interpreter_accepts_exactly_the_bound_user_mcodes() -> None:
    from gcode_canon.errors import GCodeError
    from gcode_canon.interpreter import Interpreter
    from motiond.interp_settings import build_settings

    settings = build_settings(load_machine(None), dry_run=True)
    assert settings.user_mcodes == frozenset({101, 102})  # the demo machine's [io.mcodes]
    settings.require_program_end = False
    out = [c for c in Interpreter(settings).run_string("G0 X1\nM101 P2 Q0.5\nM102\n", "p.ngc")
           if isinstance(c, C.UserMCode)]
    assert out == [C.UserMCode(101, 2.0, 0.5, file="p.ngc", line=2), C.UserMCode(102, file="p.ngc", line=3)]
    with pytest.raises(GCodeError, match="M150: user-defined M code not bound") as info:
        list(Interpreter(settings).run_string("G0 X1\nM150\n", "p.ngc"))
    assert info.value.line == 2


def test_a_limit_switch_on_a_drive_input_bit(tmp_path: Path) -> None:
    _m, io = load(tmp_path, "[io.functions]\nlimit_z_min = { drive = \"z\", bit = 20 }\n")
    mio = MachineIO(io, None, ("x", "z"))  # no Modbus needed: the master's 0x60FD words

    def poll(word: int, vz: float) -> list[str]:
        return kinds(mio.poll(MachineState(estop=False, enabled=True, running=True, paused=False,
                                           velocity=(0.0, vz), drive_inputs=(0, word))))

    assert poll(0, -3.0) == []
    acts = mio.poll(MachineState(False, True, True, False, (0.0, -3.0), (0, 1 << 20)))
    assert kinds(acts) == [LIMIT] and "axis z: negative limit switch limit_z_min" in acts[0].reason
    assert "drive z 0x60FD bit 20" in acts[0].reason
    assert poll(1 << 20, 3.0) == []  # moving off it


def test_at_speed_from_the_measured_speed_within_the_tolerance(tmp_path: Path) -> None:
    with SimIoModule(size=64) as sim:
        f = tmp_path / "m.toml"
        f.write_text((BASE + """
[io.functions]
spindle_on = { device = "io", coil = 9 }
spindle_speed = { device = "io", holding_register = 8 }
spindle_speed_measured = { device = "io", input_register = 2, scale = 10.0 }
[io.spindle]
at_speed_tolerance = 0.05
""").replace("port = 5020", f"port = {sim.port}").replace(
            '[[modbus.devices]]\nname = "plc"\nport = 5021\n', ""))
        mb, io = machine_io(load_machine(str(f)))
        ex = IoExecutor(mb).start()
        try:
            rig = Rig(sim, ex, MachineIO(io, ex, ("x", "z")))
            cmd = C.SpindleOn(C.SpindleDirection.CW, 1000.0, file="p.ngc", line=2)
            rig.mio.on_event(cmd)
            assert rig.mio.on_wait(cmd)
            sim.set("input_register", 2, 90)  # 900 rpm: 10 % off
            assert rig.poll_until(lambda a: RELEASE in kinds(a), timeout=0.3) is None
            sim.set("input_register", 2, 97)  # 970 rpm: within 5 %
            assert rig.poll_until(lambda a: RELEASE in kinds(a)) is not None
        finally:
            ex.stop()
