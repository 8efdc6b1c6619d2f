"""The simulated I/O module wired like the machine file's I/O map says (``canon sim io``, the daemon's
``simulate = true`` devices, the demo machine): docs/wiring.md.

From the map (:class:`motiond.config_io.IoMap`) each simulated device gets

* its inputs' resting levels: an input wired active-low (the E-stop chain, a door switch) reads 1
  while the function is not active, so a freshly started module shows a closed E-stop chain and a shut
  door; the operator then "presses" a button by setting the input (``SimIoModule.set``);
* rules (:class:`fieldbus.modbus.sim.Rule`) that answer outputs like the machine would: the spindle is
  at speed ``[io.spindle] sim_delay_s`` after spindle_on (or spindle_cw/ccw) is switched on, and not at
  speed at once when it is switched off; spindle_oriented follows spindle_orient the same way; a user M
  code's wait input follows its first output.

Limit and home switches are not driven by the module unless ``[io.sim]`` places them (it does not know
where the axes are otherwise): a test or an operator sets them. Where the module runs in the daemon's
process, :func:`apply` is given the commanded machine position and these inputs are computed at each
read: the probe (``[io.sim] probe_z``) active while Z is at or below ``probe_z``; a limit switch
(``[io.sim] limit_x_max = 290.0`` ...) active while the axis is at or beyond its position (at or
below for ``_min``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from fieldbus.modbus.sim import Rule
from motiond.config_io import DIGITAL, Binding, IoMap


@dataclass
class SimWiring:
    """One simulated device's part: resting input levels and rules."""

    levels: list[tuple[str, int, int]] = field(default_factory=list)  # (table, address, value)
    rules: list[Rule] = field(default_factory=list)
    probe: tuple[Binding, float] | None = None  # the probe input and the Z it trips at (or below)
    limits: list[tuple[Binding, float]] = field(default_factory=list)  # limit inputs, where they trip


def wiring_for(io: IoMap) -> dict[str, SimWiring]:
    """Per Modbus device name, what its simulated module must do (module docstring)."""
    out: dict[str, SimWiring] = {}

    def of(b: Binding) -> SimWiring:
        assert b.point is not None
        return out.setdefault(b.point.device, SimWiring())

    def follow(src: Binding, dst: Binding, delay: float, value: float = 1.0) -> None:
        """``dst`` becomes active ``delay`` s after ``src`` is written to ``value``; inactive at once
        after it is written back (for a digital output)."""
        if src.point is None or dst.point is None or src.point.device != dst.point.device \
                or dst.point.table == "input_register":
            return
        on_raw = int(bool(value) != src.active_low) if src.kind == DIGITAL else int(value)
        active, inactive = int(not dst.active_low), int(dst.active_low)
        w = of(dst)
        w.rules.append(Rule(src.point.table, src.point.address, on_raw, delay, dst.point.table,
                            dst.point.address, active))
        if src.kind == DIGITAL:
            w.rules.append(Rule(src.point.table, src.point.address, 1 - on_raw, 0.0, dst.point.table,
                                dst.point.address, inactive))

    for b in io.functions.values():
        if b.point is not None and b.direction == "in" and b.kind == DIGITAL and b.active_low \
                and b.point.table == "discrete_input":
            of(b).levels.append((b.point.table, b.point.address, 1))
    f = io.functions
    delay = io.spindle.sim_delay_s
    if "spindle_at_speed" in f:
        for name in ("spindle_on", "spindle_cw", "spindle_ccw"):
            if name in f:
                follow(f[name], f["spindle_at_speed"], delay)
    if "spindle_oriented" in f and "spindle_orient" in f:
        follow(f["spindle_orient"], f["spindle_oriented"], delay)
    for mc in io.mcodes.values():
        if mc.wait is not None and mc.sets:
            b, value = mc.sets[0]
            follow(b, mc.wait, delay, value)
    probe = f.get("probe")
    if probe is not None and probe.point is not None and io.sim_probe_z is not None:
        of(probe).probe = (probe, io.sim_probe_z)
    for name, where in io.sim_limits.items():
        of(f[name]).limits.append((f[name], where))
    return out


def apply(module: Any, wiring: SimWiring | None, z: Callable[[], float] | None = None,
          position: Callable[[str], float] | None = None) -> None:
    """Give a started or not yet started ``SimIoModule`` its rules and resting levels; ``z``: the
    commanded machine Z, for the probe (none: the probe input is left to the operator); ``position``:
    an axis's commanded machine position, for the limit switches (none: left to the operator)."""
    if wiring is None:
        return
    module.rules.extend(wiring.rules)
    for table, address, value in wiring.levels:
        module.set(table, address, value)
    if wiring.probe is not None and z is not None:
        b, height = wiring.probe
        assert b.point is not None
        module.computed.append((b.point.table, b.point.address,
                                lambda: int((z() <= height) != b.active_low)))
    for b, where in wiring.limits if position is not None else ():
        module.computed.append((b.point.table, b.point.address, _limit(b, where, position)))


def _limit(b: Binding, where: float, position: Callable[[str], float]) -> Callable[[], int]:
    """The raw level of limit switch ``b`` placed at ``where`` (module docstring)."""
    m = b.name.split("_")  # limit_<axis>_<min|max>
    axis, beyond = m[1], (lambda p: p >= where) if m[2] == "max" else (lambda p: p <= where)
    return lambda: int(beyond(position(axis)) != b.active_low)
