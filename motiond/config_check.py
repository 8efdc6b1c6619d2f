"""The whole machine file checked offline, every table, as ``canon config check`` and ``check``/``plan``
``--config`` do: nothing is opened but files.

:func:`validate_machine` reads every section with its own reader (``[machine]``/``[axes]``/
``[interpreter]``, ``[canopen]`` with the drives' 32-bit ranges and the bus budget, ``[modbus]`` with
its I/O bindings, ``[telemetry]``) and the files they name (tool table, EDS files), and collects every
bad key rather than stopping at the first (a bad optional value is recorded and its default used, so
the section's reader goes on: :func:`~motiond.configkit.collect_errors`), so that a machine builder
sees every mistake in one go (:class:`~motiond.configkit.ConfigErrors`). :func:`describe` renders the
machine it describes as rich tables.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from motiond.config import MachineConfig, load_machine
from motiond.configkit import ConfigError, ConfigErrors, Table, collect_errors, load_toml

T = TypeVar("T")

# the objects the master reads or writes on every drive (fieldbus.canopen.master): an EDS without them
# describes a drive the master cannot run in cyclic synchronous position mode
CSP_OBJECTS = {0x6040: "controlword", 0x6041: "statusword", 0x6060: "modes of operation",
               0x6064: "position actual value", 0x607A: "target position"}


@dataclass(frozen=True)
class CheckedMachine:
    """What a valid machine file describes, each layer's own configuration."""

    config: MachineConfig
    canopen: Any  # fieldbus.canopen.config.CanopenConfig
    bus_load: Any  # fieldbus.canopen.busload.BusLoad
    modbus: Any  # fieldbus.modbus.config.ModbusConfig | None
    telemetry: Any  # telemetry.config.TelemetryConfig
    io: Any = None  # motiond.config_io.IoMap
    motion: Any = None  # motiond.config_motion.MotionChoice



#: who sends the SYNC (``CanopenConfig.sync_source``), as ``canon config check`` says it
_SYNC_BY = {"kernel": "the kernel", "process": "a SYNC process", "master": "the master"}

def validate_machine(path: str | None) -> CheckedMachine:
    """Every table of the machine file (None: the demo machine); raises
    :class:`~motiond.configkit.ConfigErrors` naming each bad key found."""
    from motiond.config_canopen import canopen_for_machine, canopen_from_file
    from motiond.config_modbus import modbus_for, read_modbus
    from telemetry.config import TelemetryConfig

    errors: list[ConfigError] = []

    def read(fn: Callable[[], T]) -> T | None:
        """One section's reader run to its end, every bad optional key recorded on the way."""
        with collect_errors() as found:
            try:
                result: T | None = fn()
            except ConfigErrors as exc:
                found.extend(exc.errors)
                result = None
            except ConfigError as exc:
                found.append(exc)
                result = None
        seen = {str(e) for e in errors}
        errors.extend(e for e in found if str(e) not in seen)
        return result

    config: MachineConfig | None = None
    with collect_errors() as found:
        try:
            config = load_machine(path)
        except ConfigError as exc:
            if path is None or not exc.key:  # no file, not TOML: nothing more to read
                raise ConfigErrors([exc]) from None
            found.extend(exc.errors if isinstance(exc, ConfigErrors) else [exc])
    errors.extend(found)
    motion = None
    root = config.root if config is not None and config.root is not None else \
        Table(load_toml(path) if path else {}, path or "")
    file = path or ""
    if config is None:
        errors.extend(e for e in _axis_errors(root) if str(e) not in {str(x) for x in errors})

    def read_canopen() -> tuple[Any, Any]:
        canopen = load = None
        if config is not None:
            canopen = canopen_for_machine(config)
        elif isinstance(root.data.get("axes"), dict):  # [axes] itself was bad: read [canopen] anyway
            canopen = canopen_from_file(root.data, file)
        if canopen is not None:
            load = _bus_budget(canopen, file)
            _eds_files(canopen, root)
        return canopen, load

    canopen, load = read(read_canopen) or (None, None)
    modbus = read(lambda: modbus_for(config) if config is not None else read_modbus(Table(root.data, file)))
    io = None
    if config is not None and (modbus is not None or "modbus" not in root):  # else: [modbus] said why
        from motiond.config_io import io_for

        io = read(lambda: io_for(config, modbus))
    tele = read(lambda: TelemetryConfig.from_table(Table(root.data, file).table("telemetry")))
    if config is not None:
        read(lambda: _tool_table(config))
        if canopen is not None:
            from motiond.config_motion import motion_choice

            motion = read(lambda: motion_choice(config, canopen))
    if errors:
        raise ConfigErrors(errors)
    assert config is not None
    return CheckedMachine(config, canopen, load, modbus, tele, io, motion)


def load_checked(path: str | None) -> MachineConfig:
    """For ``check`` and ``plan``: the machine file validated whole (:func:`validate_machine`), so a
    ``[canopen]`` or ``[modbus]`` mistake is found before a ``run``; the demo machine as it is."""
    return load_machine(None) if path is None else validate_machine(path).config


def _axis_errors(root: Table) -> list[ConfigError]:
    """Each ``[axes.NAME]`` table read on its own, so that a mistake in one does not hide another's."""
    from motiond.config import _axis

    out: list[ConfigError] = []
    axes = root.data.get("axes")
    if not isinstance(axes, dict):
        return out
    for name, data in axes.items():
        try:
            _axis(name, Table(data, root.file, f"axes.{name}"))
        except ConfigError as exc:
            out.append(exc)
    return out


def _bus_budget(canopen: Any, file: str) -> Any:
    """The master's own budget check (it refuses to start over ``max_bus_load_percent``)."""
    import logging

    from fieldbus.canopen.master import BusBudgetError, CanopenMaster

    quiet = logging.getLogger("fieldbus.canopen.master")
    level = quiet.level
    quiet.setLevel(logging.WARNING)  # its "bus load" INFO line belongs to a real start
    try:
        return CanopenMaster(canopen).load  # the constructor checks; nothing is opened
    except BusBudgetError as exc:
        raise ConfigError(file, "canopen", str(exc)) from None
    finally:
        quiet.setLevel(level)


def _eds_files(canopen: Any, root: Table) -> None:
    """Each drive's EDS file parses and has the CiA 402 objects the master needs."""
    import canopen as co

    cache: dict[str, Any] = {}
    for d in canopen.drives:
        key = f"canopen.axes.{d.axis}.eds"
        path = d.eds_path
        if path not in cache:
            try:
                cache[path] = co.objectdictionary.import_od(path, d.node_id)
            except Exception as exc:  # the library raises a variety for a malformed file
                raise ConfigError(root.file, key, f"{path}: not a readable EDS file: {exc}") from None
        od = cache[path]
        missing = [f"0x{i:04X} {name}" for i, name in CSP_OBJECTS.items() if i not in od]
        if missing:
            raise ConfigError(root.file, key, f"{path}: the EDS lacks {', '.join(missing)} (not a CiA 402 "
                                              "drive in cyclic synchronous position mode?)")


def _tool_table(config: MachineConfig) -> None:
    from gcode_canon.errors import GCodeError
    from gcode_canon.tooltable import read_tool_table

    path = config.interpreter.tool_table
    if path is None:
        return
    try:
        read_tool_table(path)
    except GCodeError as exc:
        raise ConfigError(config.path or "", "interpreter.tool_table", str(exc)) from None
    except OSError as exc:
        raise ConfigError(config.path or "", "interpreter.tool_table", f"{path}: {exc.strerror}") from None


def describe(m: CheckedMachine) -> list[Any]:
    """The machine as rich renderables: axes with their drives, the bus, the I/O map, the rest."""
    from rich import box
    from rich.table import Table as RichTable

    config = m.config
    lim = config.limits
    out: list[Any] = []
    out.append(f"[bold]{lim.name}[/] ({config.path or 'built-in demo machine'}): {len(lim.axes)} axes, "
               f"cycle {lim.cycle_s * 1000:g} ms")

    def num(v: float | None) -> str:
        return "-" if v is None else f"{v:g}"

    axes = RichTable(title="axes (machine units)", box=box.SIMPLE_HEAD, title_justify="left")
    for col in ("axis", "velocity /s", "accel. /s²", "jerk /s³", "min", "max", "quick stop /s²"):
        axes.add_column(col, justify="left" if col == "axis" else "right")
    drives_t = RichTable(title=f"drives ({'simulated' if m.canopen.simulate else 'CiA 402 CSP'})",
                         box=box.SIMPLE_HEAD, title_justify="left")
    for col in ("axis", "node", "counts/unit", "dir", "homing", "FE window", "EDS"):
        drives_t.add_column(col, justify="left" if col in ("axis", "homing", "EDS") else "right")
    for a in lim.axes:
        qsd = a.quick_stop_deceleration
        axes.add_row(f"{a.name.upper()} {a.unit}", num(a.max_velocity), num(a.max_acceleration),
                     num(a.max_jerk), num(a.min_position), num(a.max_position),
                     num(qsd) if qsd is not None else f"{2 * a.max_acceleration:g} (2 x accel.)")
    for d in m.canopen.drives:
        drives_t.add_row(d.axis.upper(), str(d.node_id), f"{d.counts_per_unit:.10g}", f"{d.direction:+d}",
                         d.homing + (f" {d.homing_method}" if d.homing == "cia402" else ""),
                         num(d.following_error_window), Path(d.eds).name if d.eds else "shipped")
    out.append(axes)
    out.append(drives_t)
    c = m.canopen
    hb = (f"heartbeat {c.heartbeat_producer_ms} ms (consumer {c.heartbeat_consumer_ms} ms)"
          if c.heartbeat_producer_ms else "no heartbeat")
    lead = f", setpoints sent {c.setpoint_lead} SYNCs ahead" if c.setpoint_lead > 1 else ""
    out.append(f"CAN: {c.bus.interface} {c.bus.channel} at {c.bus.bitrate / 1000:g} kbit/s"
               f"{', drives simulated' if c.simulate else ''}; {c.pdo_layout} PDO layout; {hb}; "
               f"SYNC timed by {_SYNC_BY[c.sync_source]}{lead}; bus load "
               f"{100 * m.bus_load.fraction:.1f} % of {100 * c.max_bus_load:.0f} % allowed "
               f"({m.bus_load.describe()})")
    if m.motion is not None:
        out.append(m.motion.describe())
    if m.modbus is None:
        out.append("Modbus I/O: none (M62-M68 are refused)")
    else:
        io = RichTable(title="Modbus I/O", box=box.SIMPLE_HEAD, title_justify="left")
        for col in ("G-code", "device", "address", "conversion"):
            io.add_column(col)
        for dev in m.modbus.devices:
            where = dev.serial or f"{dev.host}:{dev.port}"
            io.add_row(f"device {dev.name}", where, f"unit {dev.unit}",
                       f"poll {dev.poll_ms:g} ms, timeout {dev.timeout_s:g} s"
                       f"{', simulated' if dev.simulate else ''}")
        for o in m.modbus.digital_outputs:
            io.add_row(f"M62-M65 P{o.index}", o.device, f"coil {o.coil}", f"safe {int(o.safe)}")
        for o in m.modbus.analog_outputs:
            io.add_row(f"M67/M68 E{o.index}", o.device, f"register {o.register}", _conv(o.conversion) +
                       f", safe {o.safe:g}")
        for i in m.modbus.digital_inputs:
            io.add_row(f"M66 P{i.index}", i.device, f"{i.source.value.replace('_', ' ')} {i.address}", "")
        for i in m.modbus.analog_inputs:
            io.add_row(f"M66 E{i.index}", i.device, f"{i.source.value.replace('_', ' ')} {i.register}",
                       _conv(i.conversion))
        out.append(io)
    if m.io is not None and not m.io.empty:
        fn = RichTable(title="I/O map (docs/wiring.md)", box=box.SIMPLE_HEAD, title_justify="left")
        for col in ("function", "in/out", "point", "active"):
            fn.add_column(col)
        for b in m.io.functions.values():
            level = "" if b.kind == "analog" else "low" if b.active_low else "high"
            fn.add_row(b.name, b.direction, b.where, level)
        for mc in m.io.mcodes.values():
            what = [f"set {b.where} = {v:g}" for b, v in mc.sets]
            if mc.wait is not None:
                what.append(f"wait for {mc.wait.where} (timeout {mc.timeout_s:g} s)")
            fn.add_row(f"M{mc.code}", "out/in", "; ".join(what), "")
        out.append(fn)
    it = config.interpreter
    out.append(f"interpreter: dialect {it.dialect}; tool table {it.tool_table or 'none'}; parameter file "
               f"{it.var_file or 'none'}; subroutine path "
               f"{', '.join(map(str, it.subroutine_path)) or '(the program directory)'}")
    t = m.telemetry
    out.append(f"telemetry: {t.url} at {t.status_hz:g} Hz"
               f"; commands signed with the key in {t.key_file or '<state dir>/command.key'}")
    return out


def _conv(c: Any) -> str:
    return (f"{c.type.value}{' little-endian words' if c.word_order.value == 'little' else ''}, "
            f"scale {c.scale:g}, offset {c.offset:g}")

