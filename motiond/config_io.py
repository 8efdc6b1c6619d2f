"""The I/O map of the machine file (``[io]``): machine functions bound to points. See docs/wiring.md.

``[io.functions]`` binds each machine function (E-stop, machine enable, spindle, coolant, operator
buttons, door, limit and home switches) to one point: a Modbus coil, discrete input, input or holding
register on any ``[[modbus.devices]]`` device, or a bit of a drive's digital inputs (0x60FD), which the
CANopen master already receives, or outputs (0x60FE), which the master writes. ``[io.spindle]``
holds the spindle's numbers (speed limits, at-speed tolerance and timeouts) and ``[io.mcodes.M100]``
... ``[io.mcodes.M199]`` the user M codes: outputs to set and/or an input to wait for.

:func:`read_io` checks everything against the Modbus devices and the axes and raises
:class:`~motiond.configkit.ConfigError` naming the key: an unknown function, a device that does not
exist, an address out of range, a point of the wrong kind (an output on a discrete input), a function
bound twice (two spindle direction schemes, or two functions writing one coil). The Modbus points
become :class:`~fieldbus.modbus.config.NamedPoint` entries of the Modbus configuration, so that the I/O
worker polls and writes them with the M62-M68 ones (:func:`modbus_with_io`).
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from fieldbus.modbus.config import Conversion, ModbusConfig, NamedPoint, ValueType, WordOrder
from motiond.configkit import ConfigError, Table, in_range, non_negative, one_of, positive
from motiond.mcodes import DEMO_MCODES, MCODE_RE

if TYPE_CHECKING:
    from motiond.config import MachineConfig

IN, OUT = "in", "out"
DIGITAL, ANALOG = "digital", "analog"

FUNCTIONS: dict[str, tuple[str, str, str]] = {
    "estop": (IN, DIGITAL, "E-stop chain (button, safety relay): active stops the machine (ESTOP)"),
    "machine_enable": (OUT, DIGITAL, "on while the machine is enabled; off on E-stop and on any fault"),
    "spindle_on": (OUT, DIGITAL, "spindle runs (M3/M4), off on M5 and M19"),
    "spindle_reverse": (OUT, DIGITAL, "spindle direction: on for M4 (counter-clockwise)"),
    "spindle_cw": (OUT, DIGITAL, "spindle runs clockwise (M3); instead of spindle_on/spindle_reverse"),
    "spindle_ccw": (OUT, DIGITAL, "spindle runs counter-clockwise (M4)"),
    "spindle_speed": (OUT, ANALOG, "speed command in rpm (S, clamped to [io.spindle] min_rpm..max_rpm)"),
    "spindle_at_speed": (IN, DIGITAL, "the spindle drive reports the commanded speed reached"),
    "spindle_speed_measured": (IN, ANALOG, "measured speed in rpm (at speed: within at_speed_tolerance)"),
    "spindle_orient": (OUT, DIGITAL, "M19: orient the spindle (on until the next M3/M4/M5)"),
    "spindle_oriented": (IN, DIGITAL, "M19 done: the spindle stands oriented"),
    "coolant_mist": (OUT, DIGITAL, "M7 on, M9 off"),
    "coolant_flood": (OUT, DIGITAL, "M8 on, M9 off"),
    "cycle_start": (IN, DIGITAL, "operator button: resume a paused program (rising edge)"),
    "feed_hold": (IN, DIGITAL, "operator button: pause the program on its path (rising edge)"),
    "abort": (IN, DIGITAL, "operator button: abort the program (rising edge)"),
    "door_open": (IN, DIGITAL, "door interlock: motion holds while active; cycle start resumes once closed"),
    "probe": (IN, DIGITAL, "probe input for G38.2-G38.5 when no drive has a touch probe: checked every cycle "
                           "of a probing move (latency: one poll plus one cycle)"),
}
AXIS_FUNCTIONS = {
    "limit_{}_min": "limit switch at the axis's negative end: stops the machine while moving",
    "limit_{}_max": "limit switch at the axis's positive end: stops the machine while moving",
    "home_{}": "home switch (shown in the status)",
}
_AXIS_RE = re.compile(r"^(limit_([a-z])_(min|max)|home_([a-z]))$")
ADDRESS_KEYS = ("coil", "discrete_input", "input_register", "holding_register")
BIT_TABLES = ("coil", "discrete_input")
OUTPUT_TABLES = ("coil", "holding_register")


@dataclass(frozen=True)
class Binding:
    """One function (or an M code's point) bound to a point. ``point``: a Modbus point (its key is
    :attr:`name`); otherwise ``drive_axis`` and ``bit`` name a drive's 0x60FD bit (an input) or 0x60FE
    bit (an output). ``active_low``: the
    function is active when the point reads (or is written) 0."""

    name: str
    key: str  # the machine file's key, for messages: "io.functions.estop"
    direction: str
    kind: str
    point: NamedPoint | None = None
    drive_axis: str = ""
    bit: int = -1
    active_low: bool = False

    @property
    def where(self) -> str:
        """``device 'io' discrete input 8`` or ``drive x 0x60FD bit 16``, for messages."""
        if self.point is None:
            return f"drive {self.drive_axis} {'0x60FE' if self.direction == OUT else '0x60FD'} bit {self.bit}"
        p = self.point
        return f"Modbus device {p.device!r} {p.table.replace('_', ' ')} {p.address}"


@dataclass(frozen=True)
class SpindleParams:
    """``[io.spindle]``: speed limits (rpm), at-speed check and the waits' timeouts."""

    min_rpm: float = 0.0
    max_rpm: float | None = None
    at_speed_tolerance: float = 0.05  # fraction of the commanded speed (spindle_speed_measured)
    at_speed_timeout_s: float = 10.0
    orient_timeout_s: float = 10.0  # M19 without Q
    sim_delay_s: float = 0.5  # the simulated module: at speed (and oriented) this long after the command


@dataclass(frozen=True)
class UserMCode:
    """``[io.mcodes.M1nn]``: outputs set in order (``sets``: binding and value), then an input waited
    for (active) up to ``timeout_s``; the program goes on when it is (an error naming the line if not)."""

    code: int
    key: str
    sets: tuple[tuple[Binding, float], ...] = ()
    wait: Binding | None = None
    timeout_s: float = 10.0


@dataclass(frozen=True)
class IoMap:
    """The whole ``[io]`` table, checked."""

    functions: dict[str, Binding] = field(default_factory=dict)
    spindle: SpindleParams = field(default_factory=SpindleParams)
    mcodes: dict[int, UserMCode] = field(default_factory=dict)
    sim_probe_z: float | None = None  # [io.sim] probe_z: the simulated module's probe trips at or below
    # [io.sim] limit_<axis>_<min|max>: the simulated module's limit switch is active at or beyond
    sim_limits: dict[str, float] = field(default_factory=dict)

    @property
    def points(self) -> tuple[NamedPoint, ...]:
        """Every Modbus point, once each (M codes that share an output share its point)."""
        seen: dict[str, NamedPoint] = {}
        bindings = list(self.functions.values())
        for mc in self.mcodes.values():
            bindings += [b for b, _v in mc.sets]
            if mc.wait is not None:
                bindings.append(mc.wait)
        for b in bindings:
            if b.point is not None:
                seen.setdefault(b.point.key, b.point)
        return tuple(seen.values())

    def has(self, name: str) -> bool:
        return name in self.functions

    @property
    def empty(self) -> bool:
        return not self.functions and not self.mcodes


def describe_functions(axes: tuple[str, ...] = ("x", "y", "z")) -> list[tuple[str, str, str, str]]:
    """(name, in/out, digital/analog, what) for every function, for docs and error messages."""
    rows = [(n, d, k, w) for n, (d, k, w) in FUNCTIONS.items()]
    for a in axes:
        rows += [(pat.format(a), IN, DIGITAL, what) for pat, what in AXIS_FUNCTIONS.items()]
    return rows


def io_for(machine: MachineConfig, modbus: ModbusConfig | None) -> IoMap:
    """The I/O map of a loaded machine: the demo's for the built-in demo machine (no file), the
    file's ``[io]`` otherwise (empty when it has none)."""
    if machine.path is None or machine.root is None:
        return demo_io(modbus) if modbus is not None else IoMap()
    return read_io(machine.root, modbus, machine.limits.names, _drive_axes(machine))


def modbus_with_io(modbus: ModbusConfig | None, io: IoMap) -> ModbusConfig | None:
    """The Modbus configuration with the I/O map's points added (the I/O worker polls and writes them)."""
    if modbus is None:
        return None
    return dataclasses.replace(modbus, named=io.points)


def machine_io(machine: MachineConfig) -> tuple[ModbusConfig | None, IoMap]:
    """The Modbus configuration (with the I/O map's points) and the I/O map of a loaded machine."""
    from motiond.config_modbus import modbus_for

    modbus = modbus_for(machine)
    io = io_for(machine, modbus)
    return modbus_with_io(modbus, io), io


def _drive_axes(machine: MachineConfig) -> tuple[str, ...]:
    canopen = machine.canopen
    axes = canopen.data.get("axes") if isinstance(canopen.data, dict) else None
    return tuple(axes) if isinstance(axes, dict) else ()


def read_io(root: Table, modbus: ModbusConfig | None, axes: tuple[str, ...],
            drive_axes: tuple[str, ...] = ()) -> IoMap:
    """The ``[io]`` part of a machine file (an empty map if it has none); :class:`ConfigError`
    names the key of the first mistake."""
    if "io" not in root:
        return IoMap()
    io = root.table("io")
    funcs = io.table("functions")
    bindings: dict[str, Binding] = {}
    for name in list(funcs.data):
        spec = _function_spec(name, axes)
        if spec is None:
            raise funcs.error(name, "unknown function; known: " + ", ".join(
                [*FUNCTIONS, *(p.format("<axis>") for p in AXIS_FUNCTIONS)]))
        direction, kind = spec
        bindings[name] = _binding(funcs.table(name), name, direction, kind, modbus, drive_axes,
                                  default_low=name == "estop")
    for a, b in (("spindle_reverse", "spindle_cw"), ("spindle_reverse", "spindle_ccw"),
                 ("spindle_on", "spindle_cw"), ("spindle_on", "spindle_ccw")):
        if a in bindings and b in bindings:
            raise funcs.error(b, f"the spindle is bound twice: either spindle_on (with spindle_reverse) "
                                 f"or spindle_cw/spindle_ccw, not both ({a} is bound too)")
    if "spindle_reverse" in bindings and "spindle_on" not in bindings:
        raise funcs.error("spindle_reverse", "needs spindle_on too")
    if "spindle_oriented" in bindings and "spindle_orient" not in bindings:
        raise funcs.error("spindle_oriented", "needs spindle_orient (the output that asks for it) too")
    spindle = _spindle(io.table("spindle"), bindings)
    mcodes = _mcodes(io.table("mcodes"), modbus, drive_axes)
    sim = io.table("sim")
    sim_limits = _sim_limits(sim, bindings)
    sim_probe_z = _sim_probe(sim, bindings, axes)
    funcs.check_unknown()
    io.check_unknown()
    result = IoMap(bindings, spindle, mcodes, sim_probe_z, sim_limits)
    _check_outputs(result, modbus, io)
    return shared_points(result)


def _function_spec(name: str, axes: tuple[str, ...]) -> tuple[str, str] | None:
    if name in FUNCTIONS:
        d, k, _ = FUNCTIONS[name]
        return d, k
    m = _AXIS_RE.match(name)
    if m is not None and (m.group(2) or m.group(4)) in axes:
        return IN, DIGITAL
    return None


def _binding(t: Table, name: str, direction: str, kind: str, modbus: ModbusConfig | None,
             drive_axes: tuple[str, ...], default_low: bool = False) -> Binding:
    """One point: ``{ device = "io", coil = 3 }`` (Modbus) or ``{ drive = "x", bit = 16 }``."""
    present = [k for k in ADDRESS_KEYS if k in t]
    active = t.get("active", str, "low" if default_low else "high", check=one_of("high", "low"))
    if "drive" in t:
        if present or "device" in t:
            raise t.error("drive", "a point is either on a drive (drive, bit) or on a Modbus device, "
                                   "not both")
        axis = t.get("drive", str)
        if kind == ANALOG:
            what = "outputs (0x60FE)" if direction == OUT else "inputs (0x60FD)"
            raise t.error("drive", f"a drive's digital {what} are bits; an analog function needs a "
                                   "Modbus register")
        if axis not in drive_axes:
            raise t.error("drive", f"no [canopen.axes.{axis}] drive (drives: "
                                   f"{', '.join(drive_axes) or 'none'})")
        bit = t.get("bit", int, check=in_range(0, 31))
        t.check_unknown()
        return Binding(name, t.path, direction, kind, drive_axis=axis, bit=bit, active_low=active == "low")
    if len(present) != 1:
        raise t.error(ADDRESS_KEYS[0] if not present else present[1],
                      f"give exactly one of {', '.join(ADDRESS_KEYS)} (or drive and bit)"
                      + (f"; found {', '.join(present)}" if present else ""))
    table = present[0]
    if modbus is None:
        raise t.error(table, "this machine file has no [[modbus.devices]] for the point to be on")
    names = [d.name for d in modbus.devices]
    if "device" not in t and len(names) == 1:
        device = names[0]
    else:
        device = t.get("device", str)
        if device not in names:
            raise t.error("device", f"no [[modbus.devices]] is named {device!r} (known: {', '.join(names)})")
    address = t.get(table, int, check=in_range(0, 65535))
    if direction == OUT and table not in OUTPUT_TABLES:
        raise t.error(table, f"{name} is an output: it needs a coil or a holding_register, not a "
                             f"{table.replace('_', ' ')} (read-only)")
    if kind == DIGITAL and table not in BIT_TABLES:
        raise t.error(table, f"{name} is a digital (on/off) function: it needs a "
                             f"{'coil' if direction == OUT else 'discrete_input or coil'}")
    if kind == ANALOG and table in BIT_TABLES:
        raise t.error(table, f"{name} is an analog value: it needs an "
                             f"{'input_register or ' if direction == IN else ''}holding_register")
    conv = Conversion()
    if kind == ANALOG:
        vtype = ValueType(t.get("type", str, "int16", check=one_of(*(v.value for v in ValueType))))
        order = WordOrder(t.get("word_order", str, "big", check=one_of(*(w.value for w in WordOrder))))
        scale = t.get("scale", float, 1.0, check=lambda v: None if v != 0 else "must not be 0")
        conv = Conversion(vtype, order, scale, t.get("offset", float, 0.0))
        if address + vtype.registers - 1 > 65535:
            raise t.error(table, f"{vtype.value} takes registers {address} and {address + 1}: beyond the "
                                 "last Modbus address 65535")
    t.check_unknown()
    low = active == "low"
    safe = (1.0 if low else 0.0) if kind == DIGITAL else 0.0
    if kind == ANALOG and direction == OUT:
        from fieldbus.modbus.codec import CodecError, encode

        try:
            encode(0.0, conv)
        except CodecError as exc:
            raise t.error("offset", f"0 rpm (the safe value) does not fit: {exc}") from None
    point = NamedPoint(name, device, table, address, direction == OUT, conv, safe)
    return Binding(name, t.path, direction, kind, point, active_low=low)


def _spindle(t: Table, bindings: dict[str, Binding]) -> SpindleParams:
    lo = t.get("min_rpm", float, 0.0, check=non_negative)
    hi = t.get("max_rpm", float, None, check=positive)
    if hi is not None and lo > hi:
        raise t.error("min_rpm", f"must not be above max_rpm ({hi:g})")
    p = SpindleParams(
        min_rpm=lo, max_rpm=hi,
        at_speed_tolerance=t.get("at_speed_tolerance", float, 0.05, check=in_range(0.0, 1.0)),
        at_speed_timeout_s=t.get("at_speed_timeout_s", float, 10.0, check=positive),
        orient_timeout_s=t.get("orient_timeout_s", float, 10.0, check=positive),
        sim_delay_s=t.get("sim_delay_s", float, 0.5, check=non_negative))
    t.check_unknown()
    return p


def _sim_probe(t: Table, bindings: dict[str, Binding], axes: tuple[str, ...]) -> float | None:
    """``[io.sim] probe_z``: the simulated I/O module's probe input trips while the commanded machine Z
    is at or below this height (docs/wiring.md)."""
    z = t.get("probe_z", float, None)
    t.check_unknown()
    if z is None:
        return None
    b = bindings.get("probe")
    if b is None or b.point is None:
        raise t.error("probe_z", "needs io.functions.probe bound to a Modbus point (the simulated module "
                                 "drives it)")
    if "z" not in axes:
        raise t.error("probe_z", "the machine has no z axis")
    return z


def _sim_limits(t: Table, bindings: dict[str, Binding]) -> dict[str, float]:
    """``[io.sim] limit_x_max = 290.0`` ...: the simulated I/O module's limit switch input is active
    while the commanded machine position of the axis is at or beyond it (at or below for ``_min``);
    docs/wiring.md."""
    out: dict[str, float] = {}
    for name in [k for k in t.data if k.startswith("limit_")]:
        b = bindings.get(name)
        if _AXIS_RE.match(name) is None or b is None or b.point is None:
            raise t.error(name, f"needs io.functions.{name} bound to a Modbus point (the simulated module "
                                "drives it)")
        out[name] = t.get(name, float)
    return out


def _mcodes(t: Table, modbus: ModbusConfig | None, drive_axes: tuple[str, ...]) -> dict[int, UserMCode]:
    out: dict[int, UserMCode] = {}
    for name in list(t.data):
        m = MCODE_RE.match(name)
        if m is None:
            raise t.error(name, "not a user M code: M100 to M199 (e.g. [io.mcodes.M101])")
        mt = t.table(name)
        code = int(m.group(1))
        sets: list[tuple[Binding, float]] = []
        for i, item in enumerate(mt.get("set", list, [])):
            st = Table(item, mt.file, f"{mt.key('set')}[{i}]") if isinstance(item, dict) else None
            if st is None:
                raise mt.error(f"set[{i}]", "must be a point table, e.g. { coil = 5, value = 1 }")
            analog = "holding_register" in st
            value = st.get("value", float, 1.0)
            b = _binding(st, f"{name}.set[{i}]", OUT, ANALOG if analog else DIGITAL, modbus, drive_axes)
            sets.append((b, value))
        wait = None
        if "wait" in mt:
            wt = mt.table("wait")
            wait = _binding(wt, f"{name}.wait", IN, DIGITAL, modbus, drive_axes)
        timeout = mt.get("timeout_s", float, 10.0, check=positive)
        if not sets and wait is None:
            raise mt.error("set", "an M code needs outputs to set, an input to wait for, or both")
        mt.check_unknown()
        out[code] = UserMCode(code, mt.path, tuple(sets), wait, timeout)
    return out


def _check_outputs(io: IoMap, modbus: ModbusConfig | None, t: Table) -> None:
    """Two owners writing one coil or register would fight: refused naming the second. M codes may
    share an output among themselves (M101 closes a clamp, M102 opens it)."""
    _check_drive_outputs(io, t)
    if modbus is None:
        return
    used: dict[tuple[str, str, int], str] = {}
    for m in modbus.digital_outputs:
        used[(m.device, "coil", m.coil)] = f"modbus.digital_outputs (M62-M65 P{m.index})"
    for a in modbus.analog_outputs:
        for r in range(a.register, a.register + a.conversion.type.registers):
            used[(a.device, "holding_register", r)] = f"modbus.analog_outputs (M67/M68 E{a.index})"
    for b in io.functions.values():
        p = b.point
        if p is None or not p.output:
            continue
        for r in range(p.address, p.address + p.registers):
            k = (p.device, p.table, r)
            if k in used:
                raise ConfigError(t.file, b.key, f"{p.table.replace('_', ' ')} {r} of device {p.device!r} is "
                                                 f"already written by {used[k]}: bound twice")
            used[k] = b.key
    for mc in io.mcodes.values():
        for b, _v in mc.sets:
            p = b.point
            if p is None:
                continue  # a drive's bit: _check_drive_outputs
            k = (p.device, p.table, p.address)
            owner = used.get(k)
            if owner is not None and not owner.startswith("io.mcodes."):
                raise ConfigError(t.file, b.key, f"{p.table.replace('_', ' ')} {p.address} of device "
                                                 f"{p.device!r} is already written by {owner}: bound twice")
            used[k] = b.key


def _check_drive_outputs(io: IoMap, t: Table) -> None:
    """A drive's 0x60FE bit written by two functions (or by a function and an M code) is refused
    naming the second; M codes may share one among themselves, as a coil."""
    used: dict[tuple[str, int], str] = {}
    for b in io.functions.values():
        if b.point is None and b.direction == OUT:
            if (b.drive_axis, b.bit) in used:
                raise ConfigError(t.file, b.key, f"{b.where} is already written by "
                                                 f"{used[(b.drive_axis, b.bit)]}: bound twice")
            used[(b.drive_axis, b.bit)] = b.key
    for mc in io.mcodes.values():
        for b, _v in mc.sets:
            owner = used.get((b.drive_axis, b.bit)) if b.point is None else None
            if owner is not None and not owner.startswith("io.mcodes."):
                raise ConfigError(t.file, b.key, f"{b.where} is already written by {owner}: bound twice")
            if b.point is None:
                used[(b.drive_axis, b.bit)] = b.key


def shared_points(io: IoMap) -> IoMap:
    """M codes writing the same output share one point (the first one's), so that the I/O worker
    holds one safe value and one state per coil."""
    by_addr: dict[tuple[str, str, int], NamedPoint] = {}
    for b in io.functions.values():
        if b.point is not None:
            by_addr.setdefault((b.point.device, b.point.table, b.point.address), b.point)
    mcodes: dict[int, UserMCode] = {}
    for code, mc in io.mcodes.items():
        sets = []
        for b, v in mc.sets:
            if b.point is None:  # a drive's 0x60FE bit: no point to share
                sets.append((b, v))
                continue
            p = by_addr.setdefault((b.point.device, b.point.table, b.point.address), b.point)
            sets.append((dataclasses.replace(b, point=p), v))
        mcodes[code] = dataclasses.replace(mc, sets=tuple(sets))
    return dataclasses.replace(io, mcodes=mcodes)


# --- the demo machine ------------------------------------------------------------------------------

DEMO_FUNCTIONS: dict[str, dict[str, Any]] = {
    "estop": {"discrete_input": 8},  # active low: the simulated chain reads 1 while not pressed
    "machine_enable": {"coil": 8},
    "spindle_on": {"coil": 9},
    "spindle_reverse": {"coil": 10},
    "spindle_speed": {"holding_register": 8},
    "spindle_at_speed": {"discrete_input": 9},
    "spindle_orient": {"coil": 11},
    "spindle_oriented": {"discrete_input": 10},
    "coolant_mist": {"coil": 12},
    "coolant_flood": {"coil": 13},
    "cycle_start": {"discrete_input": 11},
    "feed_hold": {"discrete_input": 12},
    "abort": {"discrete_input": 13},
    "door_open": {"discrete_input": 14},
    "limit_x_min": {"discrete_input": 16}, "limit_x_max": {"discrete_input": 17},
    "limit_y_min": {"discrete_input": 18}, "limit_y_max": {"discrete_input": 19},
    "limit_z_min": {"discrete_input": 20}, "limit_z_max": {"discrete_input": 21},
}
def demo_io(modbus: ModbusConfig) -> IoMap:
    """The demo machine's wiring on its simulated module (coils 8-14, discrete inputs 8-21, holding
    register 8): what examples/canon.toml shows (docs/wiring.md)."""
    data = {"io": {"functions": DEMO_FUNCTIONS, "spindle": {"max_rpm": 24000.0, "at_speed_timeout_s": 5.0,
                                                            "sim_delay_s": 0.3},
                   "mcodes": DEMO_MCODES}}
    return read_io(Table(data, "<demo machine>"), modbus, ("x", "y", "z"))
