"""What canon writes to a drive at boot and what it asks of the drive, apart from the bus.

One description serves the master (boot), ``canon drives scan`` (the drive against the configuration,
read only) and ``canon drives dcf`` (a DCF of what boot writes, for the integrator's records):

* :func:`boot_writes`: the SDO writes of boot, in order, for one drive;
* :data:`OPTIONAL_OBJECTS` / :func:`optional_objects`: the objects boot writes that a drive may lack;
* :data:`LIMIT_OBJECTS` / :func:`limit_problems`: the drive's limits and capabilities against the
  configuration; each problem names the key, the object and both values.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

from fieldbus.canopen import cia402
from fieldbus.canopen.config import AxisScale, CanopenConfig, DriveConfig, quick_stop_option

#: Objects boot writes that CiA 301/402 make optional, and what the master does without them: a
#: drive that lacks one gets a warning naming node and object, and boots. Every other object boot
#: writes is mandatory (modes of operation, the PDO mapping, heartbeat producer): a refusal.
OPTIONAL_OBJECTS: dict[int, str] = {
    0x6085: "its quick stop uses the drive's own deceleration setting",
    0x60C2: "the drive takes the cycle time from 0x1006 (or its own setting)",
    0x1006: "the drive takes the cycle time from 0x60C2 (or its own setting)",
    0x6065: "the master checks the following error against the window itself",
    0x607F: "the drive keeps its own velocity limit",
    0x1016: "the drive does not watch the master's heartbeat",
}


def optional_objects(layout: str) -> dict[int, str]:
    """:data:`OPTIONAL_OBJECTS`, with 0x605A in the compact layout only: in the standard layout the
    quick stop must end in Switch on disabled (:func:`~fieldbus.canopen.config.quick_stop_option`),
    which only 0x605A can ensure."""
    out = dict(OPTIONAL_OBJECTS)
    if layout != "standard":
        out[0x605A] = "the drive's own quick stop option applies"
    return out


#: (index, subindex, struct code, what): the drive's limits and capabilities, read where present
LIMIT_OBJECTS: tuple[tuple[int, int, str, str], ...] = (
    (0x6502, 0, "I", "supported drive modes"),
    (0x6080, 0, "I", "max motor speed"),
    (0x608F, 1, "I", "position encoder increments"),
    (0x608F, 2, "I", "position encoder motor revolutions"),
    (0x60C5, 0, "I", "max acceleration"),
    (0x60C6, 0, "I", "max deceleration"),
    (0x607D, 1, "i", "min position limit"),
    (0x607D, 2, "i", "max position limit"),
)


def boot_writes(conf: CanopenConfig, cfg: DriveConfig) -> list[tuple[str, int, int, str, int]]:
    """``(what, index, subindex, struct code, value)``: canon's own SDO writes of boot for one drive,
    in order (after the DCF's values and the machine file's extra writes)."""
    scale = AxisScale(cfg)
    cycle_us = round(conf.cycle_s * 1e6)
    if cycle_us % 1000 == 0 and cycle_us // 1000 <= 255:
        ip_value, ip_index = cycle_us // 1000, -3
    else:
        ip_value, ip_index = round(conf.cycle_s * 1e4), -4
    vmax = math.ceil(cfg.max_velocity * abs(scale.scale) * conf.velocity_margin)
    qsd = math.ceil(cfg.quick_stop_deceleration * abs(scale.scale))
    return [
        ("modes of operation", 0x6060, 0, "b", cia402.MODE_CSP),
        ("interpolation period", 0x60C2, 1, "B", ip_value),
        ("interpolation index", 0x60C2, 2, "b", ip_index),
        ("communication cycle period", 0x1006, 0, "I", cycle_us),
        ("following error window", 0x6065, 0, "I", scale.distance_counts(cfg.following_error_window)),
        ("max profile velocity", 0x607F, 0, "I", vmax),
        ("quick stop deceleration", 0x6085, 0, "I", qsd),
        ("quick stop option", 0x605A, 0, "h", quick_stop_option(cfg, conf.pdo_layout)),
        *(conf.layout.with_touch_probe() if cfg.touch_probe else conf.layout).sdo_steps(cfg.node_id),
        ("producer heartbeat time", 0x1017, 0, "H", conf.heartbeat_producer_ms),
        ("consumer heartbeat time", 0x1016, 1, "I",
         (conf.master_node_id << 16) | (conf.heartbeat_consumer_ms if conf.heartbeat_producer_ms else 0)),
    ]


def limit_problems(cfg: DriveConfig,
                   values: Mapping[tuple[int, int], int | None]) -> tuple[list[str], list[str]]:
    """``(problems, notes)`` of the configuration of one axis against what its drive said
    (``values``: (index, sub) -> value, None or missing where the drive lacks the object). A problem
    refuses the boot: CSP not among the supported modes (0x6502); max_velocity beyond the max motor
    speed (0x6080, rpm, with counts_per_revolution or 0x608F); max_acceleration beyond 0x60C5/0x60C6;
    the soft-limit span beyond the software position limits (0x607D). A note is a warning."""
    problems: list[str] = []
    notes: list[str] = []
    per_unit = abs(cfg.counts_per_unit)
    modes = values.get((0x6502, 0))
    if modes is not None and not modes & (1 << (cia402.MODE_CSP - 1)):
        problems.append("the drive does not support cyclic synchronous position (CSP): 0x6502 supported "
                        f"drive modes is 0x{modes:08X}, bit 7 (CSP) clear")
    rpm = values.get((0x6080, 0))
    cpr: float | None = cfg.counts_per_revolution
    inc, revs = values.get((0x608F, 1)), values.get((0x608F, 2))
    if cpr is None and inc and revs:
        cpr = inc / revs
    if rpm is not None:
        if not cpr:
            notes.append(f"max motor speed 0x6080 is {rpm} rpm, but the counts per revolution are unknown "
                         f"(no 0x608F): set canopen.axes.{cfg.axis}.counts_per_revolution to have "
                         "max_velocity checked")
        else:
            want = cfg.max_velocity * per_unit
            allowed = rpm * cpr / 60.0
            if rpm and want > allowed * (1 + 1e-9):
                problems.append(
                    f"axes.{cfg.axis}.max_velocity {cfg.max_velocity:g} is {want:,.0f} counts/s, more than "
                    f"the motor allows: 0x6080 max motor speed {rpm} rpm = {allowed:,.0f} counts/s "
                    f"({cpr:g} counts/rev), i.e. max_velocity {allowed / per_unit:g} at most")
    for index, name in ((0x60C5, "max acceleration"), (0x60C6, "max deceleration")):
        value = values.get((index, 0))
        if value and cfg.max_acceleration is not None and cfg.max_acceleration * per_unit > value:
            problems.append(
                f"axes.{cfg.axis}.max_acceleration {cfg.max_acceleration:g} is "
                f"{cfg.max_acceleration * per_unit:,.0f} counts/s², more than 0x{index:04X} {name} "
                f"{value:,} counts/s² allows (max_acceleration {value / per_unit:g} at most)")
    lo, hi = values.get((0x607D, 1)), values.get((0x607D, 2))
    if (lo is not None and hi is not None and (lo, hi) != (0, 0) and cfg.min_position is not None
            and cfg.max_position is not None):
        span = (cfg.max_position - cfg.min_position) * per_unit
        if span > hi - lo:
            problems.append(
                f"axes.{cfg.axis}.min_position..max_position ({cfg.min_position:g} to {cfg.max_position:g}) "
                f"spans {span:,.0f} counts, more than the drive's software position limits 0x607D "
                f"({lo:,} to {hi:,}: {hi - lo:,} counts)")
    return problems, notes
