"""What the CANopen master knows and reports: its errors, faults, feedback, and its book-keeping per
drive (:class:`DriveBook`). Shared by the master's parts (boot, state machine, supervision, cycle)."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import can
import canopen

from fieldbus.canopen import cia402
from fieldbus.canopen.cia402 import State
from fieldbus.canopen.config import AxisScale, CanopenConfig, DriveConfig, quick_stop_option
from fieldbus.canopen.pdo import CONTROLWORD, TARGET_POSITION, PdoLayout
from fieldbus.canopen.sync import KernelSync

#: SDO abort codes a drive answers for an object (or sub-index) it does not have
NO_SUCH_OBJECT = (0x06020000, 0x06090011)

#: 0x60FD digital inputs (CiA 402): bit -> name
INPUT_BITS = {0: "negative limit switch", 1: "positive limit switch", 2: "home switch", 3: "interlock"}
NEGATIVE_LIMIT, POSITIVE_LIMIT = 0x1, 0x2


def input_names(bits: int) -> list[str]:
    """The names of the active inputs in a 0x60FD value."""
    return [name for bit, name in INPUT_BITS.items() if bits >> bit & 1]


class CanopenError(Exception):
    """Boot, enable or homing failed; the message names the node, the axis and what went wrong."""


class BusBudgetError(CanopenError):
    """The configuration would load the bus beyond the allowed fraction."""


@dataclass(frozen=True)
class Fault:
    node: int
    axis: str
    reason: str
    time: float = field(default_factory=time.monotonic)

    def __str__(self) -> str:
        who = f"node {self.node} (axis {self.axis})" if self.node else "master"
        return f"{who}: {self.reason}"


@dataclass(frozen=True)
class DriveState:
    """What the master knows of one drive, from its latest TPDOs."""

    axis: str
    node: int
    state: State
    statusword: int
    position: float  # actual, machine units
    following_error: float  # machine units
    actual_counts: int
    commanded: float  # last commanded position, machine units
    digital_inputs: int = 0  # 0x60FD: limit and home switches (:func:`input_names`)


@dataclass(frozen=True)
class DriveFeedback:
    """Returned by each :meth:`CanopenMaster.cycle`: the machine state the drives reported."""

    cycle: int
    positions: tuple[float, ...]
    following_errors: tuple[float, ...]
    states: tuple[State, ...]
    fault: Fault | None
    digital_inputs: tuple[int, ...] = ()  # 0x60FD per axis (:func:`input_names`); 0 without it


class DriveBook:
    """The master's book-keeping for one drive."""

    def __init__(self, cfg: DriveConfig, node: canopen.RemoteNode, layout: PdoLayout) -> None:
        self.cfg = cfg
        self.node = node
        self.scale = AxisScale(cfg)
        self.window = self.scale.distance_counts(cfg.following_error_window)
        target_pdo = layout.carrying(TARGET_POSITION, tpdo=False)
        cw_pdo = layout.carrying(CONTROLWORD, tpdo=False)
        self.rpdo_id = target_pdo.cob_id(cfg.node_id)
        self.rpdo_struct = target_pdo.struct
        self.rpdo_with_cw = cw_pdo is target_pdo
        self.cw_id = cw_pdo.cob_id(cfg.node_id)
        self.cw_struct = cw_pdo.struct
        self.controlword = cia402.CW_ENABLE_OPERATION
        self.target = 0  # counts, last sent (held on a fault)
        self.statusword = 0
        self.actual = 0
        self.following_error = 0
        self.feedback_at = 0.0
        self.heartbeat_at = 0.0
        self.nmt_state = -1
        self.enabled_at = math.inf  # TPDOs older than this predate the enable
        self.active = False  # the cycle sends this drive its target every SYNC
        self.inputs = 0  # 0x60FD, from TPDO4 (and read by SDO on enable)
        self.has_inputs = False  # the drive has 0x60FD, mapped in TPDO4
        self.outputs = 0  # 0x60FE:01 as commanded (master_outputs)
        self.outputs_mask = 0  # the bits the master drives (0x60FE:02)
        self.outputs_mask_written = 0
        self.sdo_lock = threading.Lock()  # one SDO transfer at a time (canopen's client has no lock)
        self.limits_armed = 0  # limit switch bits active at the last check (a new one is an edge)
        self.missing: dict[int, int] = {}  # optional objects the drive lacks: their abort codes (boot)
        # what the drive said at boot: (index, sub) -> value, None where it lacks the object
        self.limits: dict[tuple[int, int], int | None] = {}
        self.active_at = 0.0
        self.enable_started = 0.0  # EMCYs received since are its enable's
        self.last_emcy_at = 0.0
        self.booted = threading.Event()
        self.homing = False
        self.qs_option = quick_stop_option(cfg, layout.name)
        self.last_emcy: canopen.emcy.EmcyError | None = None

    def describe(self) -> str:
        return f"node {self.cfg.node_id} (axis {self.cfg.axis})"

    def cyclic_rpdo(self) -> bytes:
        """The RPDO sent every cycle: the target (and, in the standard layout, the controlword)."""
        if self.rpdo_with_cw:
            return self.rpdo_struct.pack(self.target, self.controlword)
        return self.rpdo_struct.pack(self.target)

    def controlword_rpdo(self, controlword: int) -> tuple[int, bytes]:
        """COB-ID and data of the RPDO that carries ``controlword`` now."""
        if self.rpdo_with_cw:
            return self.rpdo_id, self.rpdo_struct.pack(self.target, controlword)
        return self.cw_id, self.cw_struct.pack(controlword)


class MasterCore:
    """The state the master's parts share (:class:`~fieldbus.canopen.master.CanopenMaster` sets it in
    its constructor; the boot, state machine and supervision mixins read and change it). The cyclic
    book-keeping (``_stream_t0``, ``_last_sent``, ``streaming``, each drive's ``active``) changes under
    ``_lock`` only: the reader thread, the cycle thread and the SDO-using threads all touch it."""

    config: CanopenConfig
    layout: PdoLayout
    network: canopen.Network | None
    drives: list[DriveBook]
    fault: Fault | None
    fault_log: list[Fault]
    warnings: list[Fault]
    cycles: int
    streaming: bool
    _bus: can.BusABC | None
    _own_bus: bool
    _lock: threading.RLock
    _heartbeat_task: canopen.network.PeriodicMessageTask | None
    _stream_t0: float  # first cycle with a drive streamed to: TPDO ages count from there
    _last_sent: float  # the last cycle's frames sent while streaming to a drive (0: none yet)
    _rpdo_syncs: int  # kernel SYNC: SYNCs seen when the last RPDOs went out (-1: none yet)
    _reader_sync_at: float  # kernel SYNC: when the bus reader thread last saw one (time.monotonic)
    _kernel_sync: KernelSync | None  # the kernel's periodic SYNC, while the master is open with it
    _fault_listeners: list[Callable[[Fault], None]]
    _warning_listeners: list[Callable[[Fault], None]]

    def _streaming_off(self) -> None:
        """No drive streamed to from now on (with ``_lock`` held): the stream's clocks start again at
        the next enable."""
        self.streaming = False
        self._stream_t0 = self._last_sent = 0.0
        self._rpdo_syncs = -1
