"""Read the ``[canopen]`` part of the machine file into ``fieldbus.canopen.config`` dataclasses.

Every mistake names the file and the dotted key (``machine.toml: canopen.axes.y.node_id: ...``).
With no ``[canopen]`` table, the demo set-up: canon's local bus (``canon_local``, which crosses
processes: the motion side and the simulated drives may each run in a process of their own), one
simulated drive per axis, node ids 1..n in axis order.
"""

from __future__ import annotations

import dataclasses
import ipaddress
import math
import struct
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from fieldbus.canopen.config import (
    CANON_OWNED,
    HOLDING_QUICK_STOP_OPTIONS,
    LOCAL_INTERFACE,
    SDO_TYPES,
    SPINDLE_MODES,
    CanBusConfig,
    CanopenConfig,
    DriveConfig,
    EmcyPolicy,
    SpindleDriveConfig,
    emcy_pattern_problem,
    sync_problem,
)
from fieldbus.canopen.pdo import LAYOUTS
from motiond.configkit import Table, in_range, one_of, positive

_VELOCITY_MARGIN = CanopenConfig.velocity_margin  # the dataclass default: what the master uses


def demo_canopen(axis_names: Sequence[str], cycle_s: float,
                 axis_limits: Mapping[str, Mapping[str, Any]] | None = None) -> CanopenConfig:
    drives = tuple(DriveConfig(name, i + 1, **_limits(name, axis_limits))
                   for i, name in enumerate(axis_names))
    return CanopenConfig(CanBusConfig(LOCAL_INTERFACE), drives, cycle_s=cycle_s, simulate=True)


def _limits(name: str, axis_limits: Mapping[str, Mapping[str, Any]] | None) -> dict[str, Any]:
    lim = (axis_limits or {}).get(name, {})
    out = {k: float(lim[k]) for k in ("max_velocity", "max_acceleration", "quick_stop_deceleration",
                                       "min_position", "max_position") if isinstance(lim.get(k), int | float)}
    return out


def read_canopen(root: Table, axis_names: Sequence[str], cycle_s: float,
                 axis_limits: Mapping[str, Mapping[str, Any]] | None = None) -> CanopenConfig:
    """``root``: the whole machine file; ``axis_names`` in drive order (from ``[axes]``);
    ``axis_limits``: each axis's ``[axes.<name>]`` values (max_velocity, quick_stop_deceleration,
    min_position, max_position), which the drives are configured with."""
    if "canopen" not in root:
        return demo_canopen(axis_names, cycle_s, axis_limits)
    t = root.table("canopen")
    interface = t.get("interface", str, "virtual", check=lambda v: None if v.strip() else "must not be empty")
    channel = t.get("channel", str, "canon")
    if interface == "udp_multicast":
        try:
            group = ipaddress.ip_address(channel)
            ok = group.version == 4 and group.is_multicast
        except ValueError:
            ok = False
        if not ok:
            raise t.error("channel", "udp_multicast needs an IPv4 multicast group such as 239.74.163.1 "
                                     "(python-can's IPv6 default sends frames off this host), "
                                     f"got {channel!r}")
    elif interface == LOCAL_INTERFACE:
        from fieldbus.canopen.localbus import channel_problem

        problem = channel_problem(channel)
        if problem:
            raise t.error("channel", f"{LOCAL_INTERFACE} needs {problem}")
    bitrate = t.get("bitrate", int, 1_000_000, check=in_range(10_000, 1_000_000))
    producer = t.get("heartbeat_producer_ms", int, 100, check=in_range(0, 65535))
    consumer = t.get("heartbeat_consumer_ms", int, 3 * producer, check=in_range(0, 65535))
    if producer and consumer <= producer:
        raise t.error("heartbeat_consumer_ms", f"must be longer than heartbeat_producer_ms ({producer}), "
                                               f"got {consumer}")
    simulate = t.get("simulate", bool, False)
    master_id = t.get("master_node_id", int, 127, check=in_range(1, 127))
    boot_timeout = t.get("boot_timeout_s", float, 5.0, check=positive)
    sdo_timeout = t.get("sdo_timeout_s", float, 0.5, check=positive)
    state_timeout = t.get("state_timeout_s", float, 2.0, check=positive)
    homing_timeout = t.get("homing_timeout_s", float, 30.0, check=positive)
    max_load = t.get("max_bus_load_percent", float, 70.0, check=in_range(1.0, 100.0))
    layout = t.get("pdo_layout", str, "standard", check=one_of(*LAYOUTS))
    fe_every = t.get("following_error_every", int, 1, check=in_range(1, 240))
    refresh = t.get("status_refresh_ms", int, 100, check=in_range(1, 65535))
    rt_priority = t.get("realtime_priority", int, 0, check=in_range(0, 99))
    cpu_latency = t.get("cpu_latency_us", int, 0, check=in_range(-1, 100_000))
    affinity = t.get("cpu_affinity", list, [], check=_cpu_list)
    steer_gc = t.get("steer_gc", bool, True)
    drive_timeout = t.get("drive_setpoint_timeout_ms", float, 0.0, check=in_range(0.0, 60_000.0))
    sync = t.get("sync", str, "master", check=lambda v: sync_problem(v, interface))
    lead = t.get("setpoint_lead", int, 1, check=in_range(1, 8))
    if lead > 1 and sync != "process":
        raise t.error("setpoint_lead", f"{lead} needs sync = \"process\" (the SYNC process sends the "
                                       "setpoints buffered ahead); with the SYNC from the master or the "
                                       "kernel the lead is 1")
    if lead > 1 and "spindle" in t.data:
        raise t.error("setpoint_lead", f"{lead} with a spindle drive ([canopen.spindle]): spindle-"
                                       "synchronized motion predicts the spindle for the next SYNC only; "
                                       "keep setpoint_lead = 1 on this machine")
    options = dict(t.table("options").data)
    emcy_t = t.table("emcy")
    emcy_lists = {}
    for key in ("warn", "stop"):
        patterns = emcy_t.get(key, list, [])
        for p in patterns:
            problem = emcy_pattern_problem(p)
            if problem:
                raise emcy_t.error(key, problem)
        emcy_lists[key] = tuple(patterns)
    emcy_t.check_unknown()

    base = Path(root.file).parent if root.file else Path.cwd()
    axes = t.table("axes", required=True)
    for name in axes.data:
        if name not in axis_names:
            raise axes.error(name, f"no axis {name!r} in [axes] (axes: {', '.join(axis_names)})")
    drives = []
    used: dict[int, str] = {}
    probe_axis = ""
    for name in axis_names:
        if name not in axes.data:
            raise axes.error(name, "missing: every axis needs a drive ([canopen.axes."
                                   f"{name}] with node_id)")
        a = axes.table(name)
        node_id, eds = _node_and_eds(a, base, master_id, used)
        used[node_id] = name
        lim = _limits(name, axis_limits)
        qs_option = a.get("quick_stop_option", int, None, check=one_of(1, 2, 3, 4, 5, 6, 7, 8))
        if layout == "standard" and qs_option in HOLDING_QUICK_STOP_OPTIONS:
            raise a.error("quick_stop_option",
                          f"{qs_option} ends a quick stop in Quick stop active, which the standard layout's "
                          "cyclic controlword (enable operation, 0x0F) would undo: use 1-4 here, or "
                          "pdo_layout = \"compact\" to hold the position after a quick stop")
        drive = DriveConfig(
            axis=name, node_id=node_id, eds=eds,
            counts_per_unit=a.get("counts_per_unit", float, 10000.0, check=positive),
            direction=a.get("direction", int, 1, check=one_of(1, -1)),
            home_offset=a.get("home_offset", float, 0.0),
            following_error_window=a.get("following_error_window", float, 1.0, check=positive),
            homing=a.get("homing", str, "set", check=one_of("set", "cia402")),
            homing_method=a.get("homing_method", int, 35, check=in_range(-128, 127)),
            homing_speed=a.get("homing_speed", float, None, check=positive),
            homing_speed_zero=a.get("homing_speed_zero", float, None, check=positive),
            homing_acceleration=a.get("homing_acceleration", float, None, check=positive),
            vendor_id=a.get("vendor_id", int, None, check=in_range(0, U32)),
            product_code=a.get("product_code", int, None, check=in_range(0, U32)),
            quick_stop_option=qs_option,
            counts_per_revolution=a.get("counts_per_revolution", int, None, check=positive),
            sdo=_extra_sdo(a),
            touch_probe=a.get("touch_probe", int, 0, check=one_of(0, 1, 2)),
            sim_probe_position=a.get("sim_probe_position", float, None),
            touch_probe_level_bit=a.get("touch_probe_level_bit", int, None, check=one_of(6, 7, 14, 15)),
            **lim,
        )
        if drive.touch_probe and probe_axis:
            raise a.error("touch_probe", f"axis {probe_axis} has the machine's probe input already "
                                         f"(canopen.axes.{probe_axis}.touch_probe): G38.x uses one probe")
        probe_axis = probe_axis or (name if drive.touch_probe else "")
        if drive.touch_probe_level_bit is not None and not drive.touch_probe:
            raise a.error("touch_probe_level_bit", "the level of the drive's touch probe input: set "
                                                   "touch_probe = 1 or 2 on this axis too")
        if drive.sim_probe_position is not None and not drive.touch_probe:
            raise a.error("sim_probe_position", "the simulated probe input is the drive's touch probe: set "
                                                "touch_probe = 1 on this axis too")
        check_drive_ranges(a, drive)
        drives.append(drive)
        a.check_unknown()
    axes.check_unknown()
    spindle = _spindle(t.table("spindle"), base, master_id, used, simulate) if "spindle" in t.data else None
    t.check_unknown()
    return CanopenConfig(
        CanBusConfig(interface, channel, bitrate, options), tuple(drives), cycle_s=cycle_s,
        heartbeat_producer_ms=producer, heartbeat_consumer_ms=consumer, simulate=simulate,
        master_node_id=master_id, boot_timeout_s=boot_timeout, sdo_timeout_s=sdo_timeout,
        state_timeout_s=state_timeout, homing_timeout_s=homing_timeout, max_bus_load=max_load / 100.0,
        pdo_layout=layout, following_error_every=fe_every, status_refresh_ms=refresh,
        realtime_priority=rt_priority, cpu_latency_us=None if cpu_latency < 0 else cpu_latency,
        emcy=EmcyPolicy(**emcy_lists), cpu_affinity=tuple(affinity), steer_gc=steer_gc,
        drive_setpoint_timeout_ms=drive_timeout, sync=sync, spindle=spindle, setpoint_lead=lead)


def _node_and_eds(t: Table, base: Path, master_id: int, used: dict[int, str]) -> tuple[int, str]:
    """A drive's ``node_id`` (1-127, not the master's, not another drive's) and ``eds`` (a file,
    relative to the machine file's folder; "" the shipped one)."""
    node_id = t.get("node_id", int, check=in_range(1, 127))
    if node_id == master_id:
        raise t.error("node_id", f"{node_id} is the master's own node id (canopen.master_node_id)")
    if node_id in used:
        raise t.error("node_id", f"{node_id} is already the node id of axis {used[node_id]}")
    eds = t.get("eds", str, "")
    if eds:
        path = Path(eds) if Path(eds).is_absolute() else base / eds
        if not path.is_file():
            raise t.error("eds", f"no such file: {path}")
        eds = str(path)
    return node_id, eds


#: ``[canopen.spindle] max_missed_positions`` on a simulated bus (``simulate = true``)
SIM_MAX_MISSED = 250


def _spindle(s: Table, base: Path, master_id: int, used: dict[int, str],
             simulate: bool) -> SpindleDriveConfig:
    """``[canopen.spindle]``: the spindle as a CiA 402 drive in a velocity mode (docs/canopen.md)."""
    node_id, eds = _node_and_eds(s, base, master_id, used)
    acceleration = s.get("acceleration", float, 1000.0, check=positive)
    cfg = SpindleDriveConfig(
        node_id=node_id, eds=eds, mode=s.get("mode", str, "csv", check=one_of(*SPINDLE_MODES)),
        counts_per_revolution=s.get("counts_per_revolution", int, 4096, check=in_range(1, 2**24)),
        direction=s.get("direction", int, 1, check=one_of(1, -1)),
        max_rpm=s.get("max_rpm", float, 3000.0, check=positive),
        acceleration=acceleration,
        quick_stop_deceleration=s.get("quick_stop_deceleration", float, 3.0 * acceleration, check=positive),
        at_speed_tolerance=s.get("at_speed_tolerance", float, 0.02, check=in_range(0.001, 0.5)),
        at_speed_timeout_s=s.get("at_speed_timeout_s", float, 10.0, check=positive),
        orient_rpm=s.get("orient_rpm", float, 60.0, check=positive),
        orient_tolerance_deg=s.get("orient_tolerance_deg", float, 1.0, check=in_range(0.01, 90.0)),
        orient_timeout_s=s.get("orient_timeout_s", float, 10.0, check=positive),
        vendor_id=s.get("vendor_id", int, None, check=in_range(0, U32)),
        product_code=s.get("product_code", int, None, check=in_range(0, U32)),
        sim_acceleration=s.get("sim_acceleration", float, None, check=positive),
        # simulated drives share the PC with the motion: its load delays their frames by tens of ms; the
        # master's own TPDO timeout (0.1 s) bounds them there
        max_missed_positions=s.get("max_missed_positions", int, SIM_MAX_MISSED if simulate else 10,
                                   check=in_range(1, 250)),
    )
    top = cfg.counts_per_s(cfg.max_rpm)
    if abs(top) > I32[1]:
        raise s.error("counts_per_revolution", f"{cfg.counts_per_revolution} counts/rev x max_rpm "
                      f"{cfg.max_rpm:g} is {abs(top):,.0f} counts/s, beyond the drive's target velocity "
                      f"(0x60FF, INTEGER32)")
    s.check_unknown()
    return cfg


def _extra_sdo(axis: Table) -> tuple[tuple[int, int, str, int, str], ...]:
    """``[[canopen.axes.<a>.sdo]]``: index, subindex, type (u8 i8 u16 i16 u32 i32), value."""
    out = []
    for t in axis.array_of_tables("sdo"):
        index = t.get("index", int, check=in_range(0x1000, 0xFFFF))
        if index in CANON_OWNED or 0x1400 <= index <= 0x1BFF:
            raise t.error("index", f"0x{index:04X} is written by canon itself at boot (the cycle, heartbeat, "
                                   "quick stop, limits or the PDO layout): set it through canon's own keys")
        sub = t.get("subindex", int, 0, check=in_range(0, 255))
        kind = t.get("type", str, check=one_of(*SDO_TYPES))
        code = SDO_TYPES[kind]
        bits = 8 * struct.calcsize(code)
        lo, hi = (-(2 ** (bits - 1)), 2 ** (bits - 1) - 1) if kind.startswith("i") else (0, 2**bits - 1)
        value = t.get("value", int, check=in_range(lo, hi))
        t.check_unknown()
        out.append((index, sub, code, value, t.path))
    return tuple(out)


U32 = 2**32 - 1
I32 = (-(2**31), 2**31 - 1)


def check_drive_ranges(a: Table, d: DriveConfig) -> None:
    """The values the master writes to the drive in counts must fit the CiA 402 objects' 32-bit
    types: the error names ``counts_per_unit`` (the scale that makes them too big) and the other key.

    ``a``: the ``[canopen.axes.<name>]`` table; the limits come from ``[axes.<name>]``.
    """
    scale = d.counts_per_unit
    margin = _VELOCITY_MARGIN
    unit = f"counts_per_unit {scale:.10g}"
    checks = (
        ("max profile velocity 0x607F", f"axes.{d.axis}.max_velocity", d.max_velocity * margin,
         f" (x {margin:g}: the drive's margin over the planner's limit)"),
        ("quick stop deceleration 0x6085", f"axes.{d.axis}.quick_stop_deceleration",
         d.quick_stop_deceleration, ""),
        ("following error window 0x6065", f"{a.key('following_error_window')}", d.following_error_window, ""),
        ("homing speed 0x6099:1", a.key("homing_speed"), d.homing_speed, ""),
        ("homing speed 0x6099:2", a.key("homing_speed_zero"), d.homing_speed_zero, ""),
        ("homing acceleration 0x609A", a.key("homing_acceleration"), d.homing_acceleration, ""),
    )
    for obj, key, value, note in checks:
        if value is None:
            continue
        counts = math.ceil(value * scale)
        if counts > U32:
            raise a.error("counts_per_unit", f"{unit} x {key} {value:g}{note} = {counts:,} counts, beyond "
                          f"the drive's {obj} (UNSIGNED32, at most {U32:,}): fewer counts per unit (scale "
                          f"in the drive, e.g. its position factor 0x6093) or a lower {key}")
    for key, pos in (("min_position", d.min_position), ("max_position", d.max_position)):
        if pos is None:
            continue
        counts = round((pos - d.home_offset) * scale)
        if not I32[0] <= counts <= I32[1]:
            raise a.error("counts_per_unit", f"{unit}: axes.{d.axis}.{key} {pos:g} is {counts:,} counts from "
                          f"home (home_offset {d.home_offset:g}), beyond the drive's 32-bit position "
                          f"(0x607A: {I32[0]:,} to {I32[1]:,})")


def _cpu_list(cpus: list[Any]) -> str | None:
    """``cpu_affinity``: distinct CPU numbers (whether this machine has them is checked, and a refusal
    logged, when the cycle thread starts: the file may be checked on another PC)."""
    for cpu in cpus:
        if not isinstance(cpu, int) or isinstance(cpu, bool) or not 0 <= cpu < 4096:
            return f"must be a list of CPU numbers 0-4095, {cpu!r} is not one"
    if len(set(cpus)) != len(cpus):
        return "must not list a CPU twice"
    return None


def canopen_from_file(data: dict[str, Any], file: str = "") -> CanopenConfig:
    """For stand-alone tools (``canon sim drives``, the bench): the axes and cycle from the same file."""
    root = Table(data, file)
    axes_t = root.table("axes")
    names = list(axes_t.data) or ["x", "y", "z"]
    limits = {n: v for n, v in axes_t.data.items() if isinstance(v, dict)}
    machine = root.table("machine")
    cycle_ms = machine.get("cycle_ms", float, 2.0, check=in_range(1.0, 10.0))
    return read_canopen(root, names, cycle_ms / 1000.0, limits)


def canopen_for_tool(config_path: str | None, interface: str | None = None,
                     channel: str | None = None) -> tuple[CanopenConfig, CanBusConfig]:
    """For the bus tools (``canon sim drives``, ``sim inject``, ``can-dump``): the file's (or the demo's)
    configuration and its bus with ``--interface``/``--channel`` applied. A udp_multicast IPv6 group is
    refused: its frames leave this host (python-can's own default does that)."""
    from motiond.cli import UserError
    from motiond.configkit import load_toml

    config = canopen_from_file(load_toml(config_path) if config_path else {}, config_path or "")
    bus = config.bus
    if interface:
        bus = dataclasses.replace(bus, interface=interface)
    if channel:
        bus = dataclasses.replace(bus, channel=channel)
    if bus.interface == "udp_multicast" and ":" in bus.channel:
        raise UserError("udp_multicast: use an IPv4 group such as 239.74.163.1 (IPv6 leaves this host)")
    return config, bus


def canopen_for_machine(machine: Any) -> CanopenConfig:
    """From ``motiond.config.load_machine``'s result: the axes (drive order), their limits, the cycle."""
    limits: dict[str, dict[str, Any]] = {}
    for a in machine.limits.axes:
        qsd = a.quick_stop_deceleration if a.quick_stop_deceleration is not None else 2 * a.max_acceleration
        limits[a.name] = {"max_velocity": a.max_velocity, "max_acceleration": a.max_acceleration,
                          "quick_stop_deceleration": qsd,
                          "min_position": a.min_position, "max_position": a.max_position}
    root = machine.root if machine.root is not None else Table({}, machine.path or "")
    return read_canopen(root, [a.name for a in machine.limits.axes], machine.limits.cycle_s, limits)
