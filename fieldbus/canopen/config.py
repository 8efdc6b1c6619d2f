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
    """Which python-can bus: ``interface`` (virtual, canon_local, udp_multicast, socketcan ...), channel,
    bitrate."""

    interface: str = "virtual"
    channel: str = "canon"
    bitrate: int = 1_000_000
    options: dict[str, Any] = field(default_factory=dict)

    def bus_kwargs(self) -> dict[str, Any]:
        """Keyword arguments for ``can.Bus``; udp_multicast keeps to this host (hop_limit 0)."""
        kw: dict[str, Any] = {"interface": self.interface, "channel": self.channel}
        if self.interface == "udp_multicast":
            kw["hop_limit"] = 0
        elif self.interface not in ("virtual", LOCAL_INTERFACE):  # neither has bit timing
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
    #: homing by the drive (``homing = "cia402"``): 0x6099:1 speed during search for switch, 0x6099:2
    #: during search for zero (machine units/s), 0x609A acceleration (units/s^2); None: the drive's own
    homing_speed: float | None = None
    homing_speed_zero: float | None = None
    homing_acceleration: float | None = None
    max_velocity: float = 200.0
    max_acceleration: float | None = None
    quick_stop_deceleration: float = 5000.0
    #: encoder counts per motor revolution, to compare ``max_velocity`` with the drive's max motor speed
    #: (0x6080, rpm); None: read from 0x608F (position encoder resolution) where the drive has it
    counts_per_revolution: int | None = None
    #: extra SDO writes at boot, after the DCF's values and before canon's own: (index, subindex,
    #: struct code, value, where in the machine file)
    sdo: tuple[tuple[int, int, str, int, str], ...] = ()
    vendor_id: int | None = None
    product_code: int | None = None
    #: 0x605A written at boot; None: the layout's safe default (:func:`quick_stop_option`)
    quick_stop_option: int | None = None
    #: the machine's probe input (G38.x) is this drive's touch probe 1 or 2 (0x60B8-0x60BD); 0: none
    touch_probe: int = 0
    #: the bit of 0x60B9 (touch probe status) in which the drive shows the probe input's level
    #: (manufacturer-specific: 6, 7, 14 or 15); None: not shown, a probing move cannot know that the
    #: probe is already in contact when it starts
    touch_probe_level_bit: int | None = None
    #: simulated drives only: the probe input is active at and below this machine position (None: the
    #: simulated probe never trips)
    sim_probe_position: float | None = None

    @property
    def eds_path(self) -> str:
        return self.eds or str(SHIPPED_EDS)


#: ``[canopen.spindle] mode``: CiA 402 modes of operation for a spindle drive
SPINDLE_MODES = {"pv": 3, "csv": 9}


@dataclass(frozen=True)
class SpindleDriveConfig:
    """The spindle as a CiA 402 drive on the same bus (``[canopen.spindle]``), in profile velocity
    (``pv``: the drive ramps to each new target velocity at 0x6083/0x6084) or cyclic synchronous
    velocity (``csv``: the master sends a target velocity every SYNC, ramped at ``acceleration``).
    Velocities on the bus are counts per second (0x60FF, 0x606C); the position actual (0x6064) gives
    the spindle's revolutions, which spindle-synchronized motion follows."""

    node_id: int
    eds: str = ""
    mode: str = "csv"
    #: encoder counts per spindle revolution (the drive's position unit)
    counts_per_revolution: int = 4096
    #: M4 turns the other way (-1: the drive's positive direction is M4)
    direction: int = 1
    max_rpm: float = 3000.0
    #: rpm/s: the master's ramp in csv, 0x6083/0x6084 in pv
    acceleration: float = 1000.0
    #: rpm/s: 0x6085, on a quick stop or fault
    quick_stop_deceleration: float = 3000.0
    #: at speed (M3/M4 wait): measured within this fraction of the commanded speed ...
    at_speed_tolerance: float = 0.02
    #: ... within this time, else a fault naming the line
    at_speed_timeout_s: float = 10.0
    #: M19: the spindle stops, then turns at this speed to the angle (rpm)
    orient_rpm: float = 60.0
    #: M19 done when within this many degrees of the angle, within ``orient_timeout_s``
    orient_tolerance_deg: float = 1.0
    orient_timeout_s: float = 10.0
    vendor_id: int | None = None
    product_code: int | None = None
    #: while motion follows the spindle, its position may be missing (lost or late TPDOs) for at most
    #: this many SYNCs in a row, bridged from its last speed; more is a fault naming the node
    max_missed_positions: int = 10
    #: simulated drives only: the acceleration the spindle's inertia allows (rpm/s; None:
    #: ``acceleration``); below ``acceleration`` the simulated spindle lags the commanded ramp
    sim_acceleration: float | None = None

    @property
    def eds_path(self) -> str:
        return self.eds or str(SHIPPED_EDS)

    @property
    def mode_number(self) -> int:
        return SPINDLE_MODES[self.mode]

    def counts_per_s(self, rpm: float) -> float:
        """A spindle speed (rpm, signed: M3 positive) in the drive's velocity unit (counts/s)."""
        return rpm * self.counts_per_revolution * self.direction / 60.0

    def rpm(self, counts_per_s: float) -> float:
        return counts_per_s * 60.0 * self.direction / self.counts_per_revolution


@dataclass(frozen=True)
class EmcyPolicy:
    """Which EMCY messages stop the machine. Patterns are four hex digits with ``x`` for any digit
    (``"0xFFxx"``: every manufacturer-specific code, ``"0x4210"``: one code).

    A ``stop`` pattern always stops; else a ``warn`` pattern is a warning; else the drive's error
    register (byte 2 of the EMCY) decides: 0, no error set, is a warning (logged and published, motion
    goes on), anything else stops. A drive that does leave Operation enabled is seen by its statusword
    all the same, whatever its EMCY was classed as."""

    warn: tuple[str, ...] = ()
    stop: tuple[str, ...] = ()

    @staticmethod
    def matches(pattern: str, code: int) -> bool:
        digits = pattern.lower().removeprefix("0x")
        return all(p in ("x", c) for p, c in zip(digits, f"{code:04x}", strict=True))

    def is_warning(self, code: int, register: int) -> bool:
        if any(self.matches(p, code) for p in self.stop):
            return False
        if any(self.matches(p, code) for p in self.warn):
            return True
        return register == 0


def emcy_pattern_problem(pattern: object) -> str | None:
    """Why ``pattern`` is not an EMCY code pattern (None when it is one)."""
    if not isinstance(pattern, str):
        return f"must be a string such as \"0xFFxx\", got {pattern!r}"
    digits = pattern.lower().removeprefix("0x")
    if len(digits) != 4 or any(c not in "0123456789abcdefx" for c in digits):
        return f"{pattern!r} is not four hex digits with x for any digit (e.g. \"0xFFxx\", \"0x4210\")"
    return None


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
    #: which EMCYs are warnings and which stop the machine
    emcy: EmcyPolicy = field(default_factory=EmcyPolicy)
    #: CPUs the cycle thread is pinned to (empty: any CPU)
    cpu_affinity: tuple[int, ...] = ()
    #: garbage collection kept out of the cycle (clock.PeriodicRunner's ``steer_gc``)
    steer_gc: bool = True
    #: the drives' own setpoint (RPDO) timeout as commissioned on them, in ms (0: not known); the run
    #: summary judges late cycles against it
    drive_setpoint_timeout_ms: float = 0.0
    #: who times the SYNC (:mod:`fieldbus.canopen.sync`): "master" (the master's cycle, the default),
    #: "kernel" (SocketCAN's broadcast manager), "process" (a SYNC process of its own, for buses without
    #: the kernel's: :mod:`fieldbus.canopen.sync_process`) or "auto" (kernel on socketcan, else master)
    sync: str = "master"
    #: with ``sync = "process"``: the SYNC process also sends the RPDOs, which the cycle computes up to
    #: this many SYNCs ahead (:mod:`fieldbus.canopen.setpoint_buffer`): a cycle up to ``lead - 1``
    #: periods late costs no setpoint, for ``lead - 1`` periods more between a setpoint and the drive
    #: (stops pass the buffer). 1: each setpoint for the next SYNC, as with the kernel's SYNC
    setpoint_lead: int = 1
    #: the spindle as a drive on this bus (None: none; the I/O map may still drive a spindle)
    spindle: SpindleDriveConfig | None = None

    @property
    def layout(self) -> PdoLayout:
        return make_layout(self.pdo_layout, self.following_error_every, self.status_refresh_ms)

    @property
    def kernel_sync(self) -> bool:
        """True when the kernel times the SYNC (``sync`` "kernel", or "auto" on SocketCAN)."""
        return self.sync == "kernel" or (self.sync == "auto" and self.bus.interface in KERNEL_SYNC_INTERFACES)

    @property
    def sync_source(self) -> str:
        """Who sends the SYNC: "kernel" (SocketCAN's broadcast manager), "process" (a SYNC process of
        its own, :mod:`fieldbus.canopen.sync_process`) or "master" (the master's cycle)."""
        if self.kernel_sync:
            return "kernel"
        return "process" if self.sync == "process" else "master"

    def drive(self, axis: str) -> DriveConfig:
        for d in self.drives:
            if d.axis == axis:
                return d
        raise KeyError(f"no drive for axis {axis!r}")


#: ``[canopen] sync`` values
SYNC_MODES = ("auto", "kernel", "process", "master")
#: canon's own bus between the processes of one computer (fieldbus.canopen.localbus): simulated drives
#: in another process, no network
LOCAL_INTERFACE = "canon_local"
#: python-can interfaces whose bus reaches the other processes of this computer: the motion process
#: and simulated drives (or a bench) in another can share it (``[motion] process = "auto"``)
CROSS_PROCESS_INTERFACES = (LOCAL_INTERFACE, "socketcan", "udp_multicast")
#: python-can interfaces whose periodic send the kernel times (SocketCAN: the broadcast manager, BCM)
KERNEL_SYNC_INTERFACES = ("socketcan",)


def sync_problem(sync: str, interface: str) -> str | None:
    """What is wrong with ``sync`` on this interface (a phrase the configuration reader completes with
    the value), or None."""
    if sync not in SYNC_MODES:
        return f"must be one of {', '.join(SYNC_MODES)}"
    if sync == "kernel" and interface not in KERNEL_SYNC_INTERFACES:
        return (f"\"kernel\" needs interface = \"socketcan\" (the kernel's broadcast manager sends the "
                f"SYNC; on {interface!r} only the master's cycle can): use \"master\" or \"auto\"")
    if sync == "process" and interface not in CROSS_PROCESS_INTERFACES:
        return (f"\"process\" needs a bus that crosses processes (interface = \"canon_local\", "
                f"\"udp_multicast\" or \"socketcan\"; the SYNC process cannot reach a {interface!r} bus)")
    return None


#: quick stop options (0x605A) that end in Quick stop active, where "enable operation" (0x0F) is CiA 402's
#: transition 16 back to Operation enabled
HOLDING_QUICK_STOP_OPTIONS = (5, 6, 7, 8)


def quick_stop_option(drive: DriveConfig, layout: str) -> int:
    """The quick stop option written to ``drive`` at boot.

    In the ``standard`` layout the master sends "enable operation" (0x0F) in every cyclic RPDO. A
    drive that stopped itself (its quick-stop input, a limit switch) between the master's last look at
    its statusword and the next RPDO would take that 0x0F as transition 16 and move on, when its quick
    stop option ends in Quick stop active (5-8). Option 2 (ramp down, then Switch on disabled) has no
    transition 16: the cyclic 0x0F cannot undo the stop. The ``compact`` layout sends the controlword
    only on a change, so there option 6 (ramp down and hold the position) is safe and the default.
    """
    if drive.quick_stop_option is not None:
        return drive.quick_stop_option
    return 2 if layout == "standard" else 6


#: objects canon writes at boot itself: extra SDO writes to them are refused (canon's would win)
CANON_OWNED = frozenset({0x1006, 0x1016, 0x1017, 0x6040, 0x605A, 0x6060, 0x6065, 0x607F, 0x6085, 0x60C2})
#: SDO value types for extra writes: name -> struct code
SDO_TYPES = {"u8": "B", "i8": "b", "u16": "H", "i16": "h", "u32": "I", "i32": "i"}


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
