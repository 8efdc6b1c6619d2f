"""Typed configuration of the CANopen side: the bus, the drives, the cycle.

No file reading here (``motiond.config_canopen`` reads the TOML into these); only values and the
conversions between machine units and drive counts, which must stay exact over long runs: positions
are converted from absolute values each cycle, never by accumulating deltas.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from fieldbus.canopen import SHIPPED_EDS
from fieldbus.canopen.pdo import PdoLayout, make_layout


@dataclass(frozen=True)
class CanBusConfig:
    """Which python-can bus: ``interface`` (virtual, udp_multicast, socketcan ...), channel, bitrate."""

    interface: str = "virtual"
    channel: str = "canon"
    bitrate: int = 1_000_000
    options: dict[str, Any] = field(default_factory=dict)

    def bus_kwargs(self) -> dict[str, Any]:
        """Keyword arguments for ``can.Bus``; udp_multicast keeps to this host (hop_limit 0)."""
        kw: dict[str, Any] = {"interface": self.interface, "channel": self.channel}
        if self.interface == "udp_multicast":
            kw["hop_limit"] = 0
        elif self.interface not in ("virtual",):
            kw["bitrate"] = self.bitrate
        if self.interface == "virtual":
            kw["receive_own_messages"] = False
        kw.update(self.options)
        return kw


@dataclass(frozen=True)
class DriveConfig:
    """One axis's drive.

    ``home_offset`` is the machine position of the home point, in machine units. Before homing the
    drive's count 0 is taken as home; homing moves that reference (see :class:`AxisScale`).
    """

    axis: str
    node_id: int
    eds: str = ""
    counts_per_unit: float = 10000.0
    direction: int = 1
    min_position: float | None = None
    max_position: float | None = None
    home_offset: float = 0.0
    following_error_window: float = 1.0
    homing: str = "set"
    homing_method: int = 35
    max_velocity: float = 200.0
    quick_stop_deceleration: float = 5000.0
    vendor_id: int | None = None
    product_code: int | None = None

    @property
    def eds_path(self) -> str:
        return self.eds or str(SHIPPED_EDS)


@dataclass(frozen=True)
class CanopenConfig:
    """The whole CANopen side: bus, drives in axis order, cycle and heartbeat times, timeouts."""

    bus: CanBusConfig
    drives: tuple[DriveConfig, ...]
    cycle_s: float = 0.002
    heartbeat_producer_ms: int = 100
    heartbeat_consumer_ms: int = 300
    simulate: bool = True
    master_node_id: int = 127
    boot_timeout_s: float = 5.0
    sdo_timeout_s: float = 0.5
    state_timeout_s: float = 2.0
    homing_timeout_s: float = 30.0
    feedback_timeout_s: float = 0.1
    max_bus_load: float = 0.70
    #: drives are configured with ``max_velocity * velocity_margin`` as their limit (0x607F), so a
    #: planner at its limit never trips the drive, while a real jump does.
    velocity_margin: float = 1.25
    #: PDO layout (:mod:`fieldbus.canopen.pdo`): "standard" or "compact"
    pdo_layout: str = "standard"
    following_error_every: int = 1
    status_refresh_ms: int = 100
    #: SCHED_FIFO priority of the cycle thread (0: normal scheduling)
    realtime_priority: int = 0
    #: CPU wake-up latency asked of the kernel while the cycle runs (/dev/cpu_dma_latency, us);
    #: None leaves the CPUs' idle states alone
    cpu_latency_us: int | None = 0
    #: CPUs the cycle thread is pinned to (empty: any CPU)
    cpu_affinity: tuple[int, ...] = ()
    #: garbage collection kept out of the cycle (clock.PeriodicRunner's ``steer_gc``)
    steer_gc: bool = True

    @property
    def layout(self) -> PdoLayout:
        return make_layout(self.pdo_layout, self.following_error_every, self.status_refresh_ms)

    def drive(self, axis: str) -> DriveConfig:
        for d in self.drives:
            if d.axis == axis:
                return d
        raise KeyError(f"no drive for axis {axis!r}")


class AxisScale:
    """Exact conversion between machine units and drive counts for one axis.

    ``counts = round(position * counts_per_unit * direction) + zero_counts``: the absolute position
    is converted every cycle, so no rounding error accumulates. ``zero_counts`` (the drive count at
    machine position 0) is an integer and changes only when the axis is homed.
    """

    def __init__(self, drive: DriveConfig) -> None:
        self.scale = drive.counts_per_unit * drive.direction
        self.home_offset = drive.home_offset
        self.zero_counts = -round(drive.home_offset * self.scale)

    def to_counts(self, position: float) -> int:
        c = round(position * self.scale) + self.zero_counts
        if not -(2**31) <= c < 2**31:
            raise OverflowError(f"position {position} is {c} counts: beyond the drive's 32-bit range")
        return c

    def to_units(self, counts: int) -> float:
        return (counts - self.zero_counts) / self.scale

    def distance_counts(self, distance: float) -> int:
        """A (positive) distance such as a window, in counts."""
        return max(1, math.ceil(abs(distance * self.scale)))

    def set_home_here(self, actual_counts: int) -> None:
        """The drive's current count becomes machine position ``home_offset``."""
        self.zero_counts = actual_counts - round(self.home_offset * self.scale)

    def drive_zero_is_home(self) -> None:
        """After CiA 402 homing the drive's count 0 is the home point."""
        self.zero_counts = -round(self.home_offset * self.scale)
