"""The CANopen CiA 402 master: boots the drives, streams a target per drive per cycle, stops on faults.

Life of a master (the daemon's loop thread calls :meth:`CanopenMaster.cycle` once per cycle)::

    master = CanopenMaster(config)          # refuses a bus load over config.max_bus_load
    master.open(); master.boot(); master.enable()
    fb = master.cycle(positions)            # RPDO per drive (its target), then one SYNC
    ...                                     # on a fault: master.fault, drives quick-stopped
    master.reset_faults(); master.enable()  # and stream again from master.positions()
    master.shutdown()

Design choices:

* Boot and enable use SDO (0x6040/0x6041) before streaming starts; once streaming, the controlword
  travels by PDO (with the target in the standard layout, in its own RPDO on a change in the compact
  one: :mod:`fieldbus.canopen.pdo`), so an SDO write could not override it.
* Every PDO a drive has beyond the layout's is disabled at boot: a factory mapping adds no traffic.
* All RPDOs of a cycle are sent before its SYNC, so the targets of every drive land in the same SYNC
  period (the drive latches on SYNC).
* Counts are converted from absolute positions each cycle (``AxisScale``): no drift.
* Quick stop (on any fault, or asked for): every drive gets the CiA 402 quick-stop controlword at once
  and no new target is streamed; the drives decelerate on their own 0x6085 ramp. The quick stop option
  boot writes to 0x605A depends on the layout (:func:`~fieldbus.canopen.config.quick_stop_option`):
  ``compact`` 6, the drives stay in Quick stop active holding position (a vertical axis does not drop);
  ``standard`` 2, the drives end in Switch on disabled, because its cyclic controlword 0x0F would
  otherwise re-enable a drive that stopped itself (transition 16). The master keeps the last commanded
  positions; the planner restarts from :meth:`positions` after :meth:`reset_faults` and :meth:`enable`.
* A drive that leaves Operation enabled by itself (its own quick stop, disabled, fault) is seen in the
  first statusword after it (every SYNC in ``standard``, on the change in ``compact``): the machine
  stops, the fault names node, state and reason, and the master never re-enables it.
* Limit switches (0x60FD bits 0/1, in TPDO4 on change): a switch that becomes active while the drive
  is streamed to, or a target that moves toward an active one, stops the machine (quick stop, as any
  fault), naming axis, node and switch. After a reset the axis may move off the switch, not onto it.
* Faults are reported once (the first, which caused the stop) in :attr:`fault`; later ones go to
  :attr:`fault_log`.
"""

from __future__ import annotations

import contextlib
import logging
import math
import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import can
import canopen
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from fieldbus.canopen import cia402, touch_probe
from fieldbus.canopen.busload import BusLoad, alternatives, bus_load
from fieldbus.canopen.cia402 import State
from fieldbus.canopen.commissioning import LIMIT_OBJECTS, boot_writes, limit_problems, optional_objects
from fieldbus.canopen.config import (
    HOLDING_QUICK_STOP_OPTIONS,
    AxisScale,
    CanopenConfig,
    DriveConfig,
    quick_stop_option,
)
from fieldbus.canopen.pdo import CONTROLWORD, DIGITAL_INPUTS, TARGET_POSITION, Pdo, PdoLayout

log = logging.getLogger(__name__)

#: SDO abort codes a drive answers for an object (or sub-index) it does not have
_NO_SUCH_OBJECT = (0x06020000, 0x06090011)

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


class _Drive:
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


class CanopenMaster:
    """Master of the configured drives on one bus. ``bus``: an open python-can bus to use (else one is
    made from ``config.bus``). ``check_budget=False`` only reports the bus load (benchmarks on the
    virtual bus, which has no bitrate)."""

    def __init__(self, config: CanopenConfig, bus: can.BusABC | None = None, *,
                 check_budget: bool = True) -> None:
        self.config = config
        self.layout = config.layout
        hb = (config.heartbeat_producer_ms, config.heartbeat_producer_ms)
        self.load: BusLoad = bus_load(len(config.drives), config.cycle_s, config.bus.bitrate, *hb,
                                      self.layout)
        if check_budget and self.load.fraction > config.max_bus_load:
            fits = alternatives(len(config.drives), config.cycle_s, config.bus.bitrate, config.max_bus_load,
                                *hb, config.status_refresh_ms)
            raise BusBudgetError(
                f"bus load {100 * self.load.fraction:.1f} % is over the {100 * config.max_bus_load:.0f} % "
                f"allowed: {len(config.drives)} drives every {1000 * config.cycle_s:g} ms in the "
                f"{self.layout.name} PDO layout (following error every {config.following_error_every} "
                f"SYNC) make {self.load.describe()}; "
                + (f"[canopen] settings that fit: {'; '.join(fits)}" if fits else
                   "fewer drives on this bus or a higher bitrate"))
        log.info("CANopen bus load: %s", self.load.describe())
        self._bus = bus
        self._own_bus = bus is None
        self.network: canopen.Network | None = None
        self.drives: list[_Drive] = []
        self.fault: Fault | None = None
        self.fault_log: list[Fault] = []
        self.cycles = 0
        self.streaming = False
        self._lock = threading.RLock()
        self._heartbeat_task: canopen.network.PeriodicMessageTask | None = None
        self._stream_t0 = 0.0  # first cycle with a drive streamed to: TPDO ages count from there
        self._last_sync = 0.0  # the last SYNC sent while streaming to a drive (0: none yet)
        self._fault_listeners: list[Callable[[Fault], None]] = []
        self._warning_listeners: list[Callable[[Fault], None]] = []
        self.warnings: list[Fault] = []

    # ------------------------------------------------------------------ set-up
    def open(self) -> None:
        """Connect to the bus, add the drives' nodes, start the master's heartbeat."""
        if self.network is not None:
            return
        bus = self._bus or can.Bus(**self.config.bus.bus_kwargs())
        self._bus = bus
        net = canopen.Network(bus)
        net.listeners.append(_ErrorFrameListener(self))
        net.NOTIFIER_SHUTDOWN_TIMEOUT = 2.0
        net.connect()
        self.network = net
        for cfg in self.config.drives:
            node = canopen.RemoteNode(cfg.node_id, cfg.eds_path)
            node.sdo.RESPONSE_TIMEOUT = self.config.sdo_timeout_s
            node.sdo.MAX_RETRIES = 2  # one retry (0 would retry forever)
            net.add_node(node)
            d = _Drive(cfg, node, self.layout)
            self.drives.append(d)
            node.nmt.add_heartbeat_callback(lambda state, d=d: self._on_heartbeat(d, state))
            node.emcy.add_callback(lambda entry, d=d: self._on_emcy(d, entry))
            for p in self.layout.tpdos:
                net.subscribe(p.cob_id(cfg.node_id), self._tpdo_reader(d, p))
        if self.config.heartbeat_producer_ms > 0:
            self._heartbeat_task = net.send_periodic(
                0x700 + self.config.master_node_id, [0x05], self.config.heartbeat_producer_ms / 1000.0)

    def add_warning_listener(self, callback: Callable[[Fault], None]) -> None:
        """Called with each warning (a drive without an optional object, a warning EMCY): something to
        log and show, which does not stop the machine. Any thread; keep it short."""
        self._warning_listeners.append(callback)

    def warn(self, node: int, text: str) -> None:
        """Log and publish a warning about ``node`` (0: the master)."""
        axis = next((d.cfg.axis for d in self.drives if d.cfg.node_id == node), "")
        w = Fault(node, axis, text)
        self.warnings.append(w)
        log.warning("CANopen: %s", w)
        for cb in self._warning_listeners:
            cb(w)

    def add_fault_listener(self, callback: Callable[[Fault], None]) -> None:
        """Called with the first fault after each reset, on the thread that found it (the reader
        thread, the cycle thread inside :meth:`cycle`, with the master's lock held): keep it short,
        post the fault somewhere, no SDO from it."""
        self._fault_listeners.append(callback)

    # ------------------------------------------------------------------ callbacks (reader thread)
    def _on_heartbeat(self, d: _Drive, state: int) -> None:
        d.heartbeat_at = time.monotonic()
        d.nmt_state = state
        if state == 0:
            d.booted.set()

    def _on_emcy(self, d: _Drive, entry: canopen.emcy.EmcyError) -> None:
        if entry.code & 0xFF00 == 0:
            return  # error reset
        text = f"EMCY 0x{entry.code:04X} {entry.get_desc() or 'error'}".rstrip()
        if self.config.emcy.is_warning(entry.code, entry.register):
            self.warn(d.cfg.node_id, f"{text} (error register 0x{entry.register:02X}): a warning, the "
                                     "machine goes on")
            return
        d.last_emcy, d.last_emcy_at = entry, time.monotonic()
        self.raise_fault(d.cfg.node_id, text)

    @staticmethod
    def _tpdo_reader(d: _Drive, p: Pdo) -> Callable[[int, bytearray, float], None]:
        """The reader-thread callback of one TPDO: its values into the drive's book-keeping. A TPDO
        with the position actual is the drive's cyclic sign of life (``feedback_at``)."""
        st = p.struct
        objects = p.objects

        def on_tpdo(cob_id: int, data: bytearray, timestamp: float) -> None:
            if len(data) < st.size:
                return
            for index, value in zip(objects, st.unpack_from(data), strict=True):
                if index == 0x6064:
                    d.actual = value
                    d.feedback_at = time.monotonic()
                elif index == 0x6041:
                    d.statusword = value
                elif index == 0x60F4:
                    d.following_error = value
                elif index == 0x60FD:
                    d.inputs = value
        return on_tpdo

    # ------------------------------------------------------------------ SDO helpers
    def _sdo(self, d: _Drive, what: str, index: int, sub: int, fmt: str | None = None,
             value: int | None = None, ok_aborts: tuple[int, ...] = (),
             absent: dict[int, int] | None = None) -> int:
        """One SDO read (``value`` None) or write; an abort or timeout is a :class:`CanopenError`
        naming the node, the object and ``what`` it is, except aborts in ``ok_aborts`` (then 0).
        ``absent``: an optional object, whose "does not exist" abort is recorded there (index: abort
        code; then 0)."""
        where = f"0x{index:04X}:{sub:02X} ({what})"
        try:
            if fmt is not None and value is not None:
                d.node.sdo.download(index, sub, struct.pack("<" + fmt, value))
                return value
            raw = d.node.sdo.upload(index, sub)
        except SdoAbortedError as exc:
            if exc.code in ok_aborts:
                return 0
            if absent is not None and exc.code in _NO_SUCH_OBJECT:
                absent.setdefault(index, exc.code)
                return 0
            raise CanopenError(f"{d.describe()}: SDO {'write' if value is not None else 'read'} of {where} "
                               f"aborted by the drive: 0x{exc.code:08X} {exc}") from None
        except SdoCommunicationError:
            raise CanopenError(f"{d.describe()}: SDO {'write' if value is not None else 'read'} of {where} "
                               f"timed out: no answer in {self.config.sdo_timeout_s:g} s (twice)") from None
        if fmt is None:
            fmt = {1: "B", 2: "H", 4: "I"}.get(len(raw), "I")
        return struct.unpack_from("<" + fmt, raw.ljust(struct.calcsize(fmt), b"\0"))[0]

    def _statusword(self, d: _Drive) -> int:
        return self._sdo(d, "statusword", 0x6041, 0, "H")

    # ------------------------------------------------------------------ boot
    def boot(self) -> None:
        """Reset communication, check identity, configure by SDO, start: every drive, in order."""
        self.open()
        with self._lock:
            self.streaming = False
            for d in self.drives:
                d.active = False
        for d in self.drives:
            self._boot_drive(d)

    def _boot_drive(self, d: _Drive) -> None:
        cfg, conf = d.cfg, self.config
        node = d.node
        d.booted.clear()
        node.nmt.send_command(0x82)  # reset communication
        if not d.booted.wait(conf.boot_timeout_s):
            raise CanopenError(f"{d.describe()}: no boot-up message within {conf.boot_timeout_s:g} s after "
                               "NMT reset communication (drive off, wrong node id or bitrate?)")
        # identity against the configuration (or, where it names none, against the EDS)
        od = node.object_dictionary
        for sub, name, want in ((1, "vendor id", cfg.vendor_id), (2, "product code", cfg.product_code)):
            if want is None:
                try:
                    want = od[0x1018][sub].default
                except KeyError:
                    continue
            got = self._sdo(d, f"identity {name}", 0x1018, sub, "I")
            if want is not None and got != want:
                raise CanopenError(f"{d.describe()}: identity 0x1018:{sub:02X} {name} is 0x{got:08X}, "
                                   f"the configuration expects 0x{want:08X} (wrong drive on this node id?)")
        self._check_limits(d)
        if cfg.touch_probe:
            touch_probe.check_objects(self, d)
        self._load_dcf(d)
        for index, sub, code, value, where in cfg.sdo:
            self._sdo(d, f"{where} in the machine file", index, sub, code, value)
        steps = boot_writes(conf, cfg)
        for p in self.layout.unused_pdos():
            # COB-ID bit 31; a drive without that PDO has nothing to disable
            self._sdo(d, f"{p.name} COB-ID (disable)", p.comm_index, 1, "I",
                      0x80000000 | p.cob_id(cfg.node_id), ok_aborts=_NO_SUCH_OBJECT)
        optional = optional_objects(self.layout.name)
        d.has_inputs = self._read_optional(d, "digital inputs", 0x60FD, 0, "I") is not None
        p = self.layout.carrying(DIGITAL_INPUTS, tpdo=True)
        disable = (f"{p.name} COB-ID (disable)", p.comm_index, 1, "I", 0x80000000 | p.cob_id(cfg.node_id))
        # a drive with fewer TPDOs has no room for its inputs: as a drive without 0x60FD
        self._sdo(d, *disable, absent=d.missing, ok_aborts=() if d.has_inputs else _NO_SUCH_OBJECT)
        if not d.has_inputs or p.comm_index in d.missing:
            lacks = 0x60FD if not d.has_inputs else p.comm_index
            d.has_inputs = False
            steps = [s for s in steps if s[1] not in (p.comm_index, p.mapping_index)]
            what = "digital inputs" if lacks == 0x60FD else p.name
            self.warn(cfg.node_id, f"has no object 0x{lacks:04X} ({what}"
                                   f"; SDO abort 0x{d.missing[lacks]:08X}): canon does not see its limit "
                                   "switches (0x60FD), only the drive's own reaction to them stops the axis")
        for what, index, sub, fmt, value in steps:
            before = len(d.missing)
            self._sdo(d, what, index, sub, fmt, value, absent=d.missing if index in optional else None)
            if len(d.missing) > before:
                self.warn(cfg.node_id, f"has no object 0x{index:04X} ({what}; SDO abort "
                                       f"0x{d.missing[index]:08X}): {optional[index]}")
        mode = self._sdo(d, "modes of operation display", 0x6061, 0, "b")
        if mode != cia402.MODE_CSP:
            raise CanopenError(f"{d.describe()}: modes of operation display is {mode}, not 8 (cyclic "
                               "synchronous position) after writing 0x6060 = 8")
        node.nmt.send_command(0x01)  # start
        deadline = time.monotonic() + conf.boot_timeout_s
        while d.nmt_state != 5:
            if time.monotonic() > deadline:
                raise CanopenError(f"{d.describe()}: did not report NMT Operational within "
                                   f"{conf.boot_timeout_s:g} s after NMT start (heartbeat state "
                                   f"{d.nmt_state})")
            time.sleep(0.002)
        d.heartbeat_at = time.monotonic()
        log.info("%s booted", d.describe())

    def _load_dcf(self, d: _Drive) -> None:
        """The values of the axis's DCF (its ParameterValue entries) written to the drive by canopen's
        own configuration loader (``RemoteNode.load_configuration``: PDO records first, then every
        writable object with a value). An EDS has no values: nothing is written. canon's own objects
        (the cycle, the quick stop, the PDO layout, heartbeats) are written afterwards and win."""
        od = d.node.object_dictionary
        values = [v for obj in od.values() for v in (obj.values() if hasattr(obj, "values") else [obj])
                  if getattr(v, "value", None) is not None]
        if not values:
            return
        log.info("%s: writing %d values of %s", d.describe(), len(values), d.cfg.eds_path)
        try:
            d.node.load_configuration()
        except SdoAbortedError as exc:
            raise CanopenError(f"{d.describe()}: writing the values of {d.cfg.eds_path}: SDO abort "
                               f"0x{exc.code:08X} ({exc}); the drive refused one of the file's values "
                               "(the object is in the log)") from None
        except SdoCommunicationError as exc:
            raise CanopenError(f"{d.describe()}: writing the values of {d.cfg.eds_path}: no SDO answer "
                               f"({exc})") from None

    def _read_optional(self, d: _Drive, what: str, index: int, sub: int, fmt: str) -> int | None:
        """An optional object's value, or None (remembered in ``d.missing``) when the drive lacks it."""
        before = len(d.missing)
        value = self._sdo(d, what, index, sub, fmt, absent=d.missing)
        return None if len(d.missing) > before or index in d.missing else value

    def _check_limits(self, d: _Drive) -> None:
        """The drive's capabilities and limits against the configuration, before anything is written:
        CSP among its supported modes (0x6502); max_velocity within the max motor speed (0x6080, rpm,
        with the counts per revolution from the configuration or 0x608F); max_acceleration within
        0x60C5 and 0x60C6; the soft-limit range within the software position limits (0x607D). Each
        object only where the drive has it. A configuration asking more is refused, naming the key,
        the object and both values."""
        cfg = d.cfg
        d.missing = {}
        d.limits = {}
        for index, sub, fmt, what in LIMIT_OBJECTS:
            d.limits[(index, sub)] = self._read_optional(d, what, index, sub, fmt)
        problems, notes = limit_problems(cfg, d.limits)
        if problems:
            raise CanopenError(f"{d.describe()}: {problems[0]}")
        for note in notes:
            self.warn(cfg.node_id, note)

    # ------------------------------------------------------------------ CiA 402 state machine
    def enable(self) -> None:
        """Walk every drive to Operation enabled (by SDO), holding its actual position, then stream.

        No drive is ever left without a setpoint: from the moment the enable command goes to a drive,
        the cycle sends it its target (the position it holds) every SYNC, while the others come up; a
        drive with RPDO deadline monitoring would fault otherwise. A failure part-way quick-stops the
        drives already enabled. An error names the drive's EMCY when it sent one.
        """
        with self._lock:
            if self.fault is not None:
                raise CanopenError(f"cannot enable with a fault standing ({self.fault}); "
                                   "reset_faults() first")
            self.streaming = False
            self._stream_t0 = self._last_sync = 0.0
        try:
            for d in self.drives:
                self._enable_drive(d)
                self._fault_during_enable()
        except CanopenError:
            with self._lock:
                enabled = [d for d in self.drives if d.active]
                for d in enabled:
                    d.active = False
                    d.controlword = cia402.CW_QUICK_STOP
                    with contextlib.suppress(can.CanError, OSError):
                        self._send(*d.controlword_rpdo(cia402.CW_QUICK_STOP))
            raise
        with self._lock:
            now = time.monotonic()
            for d in self.drives:
                d.heartbeat_at = max(d.heartbeat_at, now)
            self.streaming = True

    def _fault_during_enable(self, d: _Drive | None = None) -> None:
        if self.fault is not None:
            raise CanopenError(f"fault while enabling: {self.fault}")
        if d is not None and d.last_emcy is not None and d.last_emcy_at >= d.enable_started:
            e = d.last_emcy
            raise CanopenError(f"{d.describe()}: EMCY 0x{e.code:04X} {e.get_desc() or ''}".rstrip()
                               + " while enabling")

    def _wait_state(self, d: _Drive, want: State, timeout: float, doing: str,
                    resend: int | None = None, enabling: bool = False) -> int:
        """Poll the statusword until ``want``; returns it. ``resend``: write this controlword again while
        waiting, for a transition the drive takes only once it is ready (Quick stop active -> Operation
        enabled needs the stop ramp finished on many drives; the command sent during the ramp is
        ignored). ``enabling``: an EMCY of the drive (or any fault) ends the wait, named as the cause."""
        deadline = time.monotonic() + timeout
        while True:
            sw = self._statusword(d)
            state = cia402.decode(sw)
            if state == want:
                return sw
            if enabling:
                self._fault_during_enable(d)
            if time.monotonic() > deadline:
                raise CanopenError(f"{d.describe()}: stuck in '{state}' (statusword 0x{sw:04X}) "
                                   f"{timeout:g} s after {doing}, waiting for '{want}'")
            time.sleep(0.002)
            if resend is not None:
                self._sdo(d, "controlword", 0x6040, 0, "H", resend)

    def _activate(self, d: _Drive) -> None:
        """From now on the cycle sends ``d`` a target every SYNC: its actual position (read by SDO),
        held until the machine streams. Called just before the enable command reaches the drive."""
        actual = self._sdo(d, "position actual", 0x6064, 0, "i")
        inputs = self._sdo(d, "digital inputs", 0x60FD, 0, "I") if d.has_inputs else 0
        with self._lock:
            d.target = d.actual = actual
            d.inputs = inputs
            d.limits_armed = inputs & (NEGATIVE_LIMIT | POSITIVE_LIMIT)  # on a switch: it may move off
            d.controlword = cia402.CW_ENABLE_OPERATION
            d.enabled_at = math.inf
            d.active_at = d.feedback_at = time.monotonic()
            d.active = True

    def _enable_drive(self, d: _Drive) -> None:
        timeout = self.config.state_timeout_s
        d.enable_started = time.monotonic()
        if self._sdo(d, "modes of operation display", 0x6061, 0, "b") != cia402.MODE_CSP:
            self._back_to_csp(d)
        for _ in range(8):
            self._fault_during_enable(d)
            sw = self._statusword(d)
            state = cia402.decode(sw)
            if state == State.OPERATION_ENABLED:
                if not d.active:  # enabled already (by an earlier enable): hold where it stands
                    self._activate(d)
                break
            if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                code = self._sdo(d, "error code", 0x603F, 0, "H")
                raise CanopenError(f"{d.describe()}: in '{state}' (error code 0x{code:04X}): "
                                   "reset_faults() first")
            if state == State.QUICK_STOP_ACTIVE:
                if d.qs_option not in HOLDING_QUICK_STOP_OPTIONS:
                    # this quick stop option has no way back to Operation enabled: the ramp ends in
                    # Switch on disabled, from where the drive is enabled step by step
                    self._wait_state(d, State.SWITCH_ON_DISABLED, timeout, "its quick stop", enabling=True)
                    continue
                # the ramp first (bit 10 once halted): the position it holds is then final
                deadline = time.monotonic() + timeout
                while not sw & cia402.SW_TARGET_REACHED and time.monotonic() < deadline:
                    time.sleep(0.005)
                    sw = self._statusword(d)
                    if cia402.decode(sw) != State.QUICK_STOP_ACTIVE:
                        break
                if cia402.decode(sw) != State.QUICK_STOP_ACTIVE:
                    continue
            step = cia402.next_step(state)
            if step is None:
                raise CanopenError(f"{d.describe()}: stuck in '{state}' (statusword 0x{sw:04X}), "
                                   "which no controlword leads out of")
            controlword, want = step
            if want == State.OPERATION_ENABLED:
                self._activate(d)
            self._sdo(d, "controlword", 0x6040, 0, "H", controlword)
            self._wait_state(d, want, timeout, f"controlword 0x{controlword:04X}",
                             resend=controlword if state == State.QUICK_STOP_ACTIVE else None, enabling=True)
        else:
            raise CanopenError(f"{d.describe()}: did not reach Operation enabled")
        with self._lock:
            d.statusword = cia402.statusword_for(State.OPERATION_ENABLED)
            d.enabled_at = d.feedback_at = time.monotonic()

    def disable(self) -> None:
        """Stop streaming and take every drive to Switch on disabled: a drive still streamed to gets
        the quick stop first and is disabled (controlword 0, by SDO) once its ramp is over, never
        dropped at speed. No torque afterwards. A drive in Fault stays there (:meth:`reset_faults`)."""
        with self._lock:
            self.streaming = False
            self._stream_t0 = self._last_sync = 0.0
            for d in self.drives:
                if d.active:
                    d.active = False
                    d.controlword = cia402.CW_QUICK_STOP
                    self._send(*d.controlword_rpdo(cia402.CW_QUICK_STOP))
        for d in self.drives:
            self._park(d, consumer_off=False)

    def not_operational(self) -> list[str]:
        """The drives whose last heartbeat did not say NMT Operational (restarted, lost): boot again."""
        return [d.describe() for d in self.drives if d.nmt_state != 5]

    def reset_faults(self) -> None:
        """Fault-reset every drive in Fault and clear the master's fault; then :meth:`enable` again.
        Refused while a drive's heartbeat is missing (naming it): a drive not heard from is not reset."""
        conf = self.config
        if conf.heartbeat_producer_ms > 0:
            now = time.monotonic()
            for d in self.drives:
                age = now - d.heartbeat_at
                if age > conf.heartbeat_consumer_ms / 1000.0:
                    raise CanopenError(f"{d.describe()}: no heartbeat for {1000 * age:.0f} ms (consumer time "
                                       f"{conf.heartbeat_consumer_ms} ms): not reset while it is missing "
                                       "(drive off, cable, node id?)")
        with self._lock:
            self.streaming = False
        for d in self.drives:
            state = cia402.decode(self._statusword(d))
            if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                self._wait_state(d, State.FAULT, self.config.state_timeout_s, "the fault reaction")
                self._sdo(d, "controlword", 0x6040, 0, "H", 0)
                self._sdo(d, "controlword (fault reset)", 0x6040, 0, "H", cia402.CW_FAULT_RESET)
                self._wait_state(d, State.SWITCH_ON_DISABLED, self.config.state_timeout_s, "fault reset")
            d.node.emcy.active = []
            d.heartbeat_at = time.monotonic()
        with self._lock:
            self.fault = None

    # ------------------------------------------------------------------ faults
    def raise_fault(self, node: int, reason: str) -> None:
        """Record a fault (the first since the last reset is :attr:`fault`) and quick-stop every drive.

        Callable from any thread: the reader thread (EMCY), the cycle, or the daemon (a late cycle).
        """
        axis = next((d.cfg.axis for d in self.drives if d.cfg.node_id == node), "")
        f = Fault(node, axis, reason)
        with self._lock:
            self.fault_log.append(f)
            first = self.fault is None
            if first:
                self.fault = f
                log.error("CANopen fault: %s; quick stop", f)
            self._quick_stop_locked()
        if first:
            for cb in self._fault_listeners:
                cb(f)

    def quick_stop(self, reason: str = "quick stop requested") -> None:
        """Stop all axes now (CiA 402 quick stop on every drive); a fault until reset."""
        self.raise_fault(0, reason)

    def _quick_stop_locked(self) -> None:
        self.streaming = False
        self._stream_t0 = self._last_sync = 0.0
        for d in self.drives:
            d.active = False
            d.controlword = cia402.CW_QUICK_STOP
            try:
                self._send(*d.controlword_rpdo(cia402.CW_QUICK_STOP))
            except (can.CanError, OSError) as exc:
                log.error("quick stop to %s not sent: %s", d.describe(), exc)

    def _send(self, cob_id: int, data: bytes) -> None:
        assert self.network is not None
        self.network.send_message(cob_id, data)

    # ------------------------------------------------------------------ the cycle
    def cycle(self, positions: Sequence[float] | None = None) -> DriveFeedback:
        """One cycle: check the drives' feedback, send one RPDO per drive with ``positions`` (machine
        units, axis order; ``None`` holds), then one SYNC. Faulted or not enabled: SYNC only."""
        now = time.monotonic()
        with self._lock:
            if self.network is None:  # not open, or shut down: nothing to send
                return self.feedback()
            self.cycles += 1
            active = [d for d in self.drives if d.active]
            if active:
                if self._stream_t0 == 0.0:
                    self._stream_t0 = now
                self._check(now, active)
            try:
                if self.streaming and positions is not None:
                    self._set_targets(positions)
                for d in self.drives:
                    if d.active and not d.homing:
                        self._send(d.rpdo_id, d.cyclic_rpdo())
                self.network.sync.transmit()  # type: ignore[union-attr]
                if any(d.active for d in self.drives):
                    self._last_sync = time.monotonic()
            except (can.CanError, OSError) as exc:
                self.raise_fault(0, f"bus error: {exc}")
            return self.feedback()

    def _set_targets(self, positions: Sequence[float]) -> None:
        if len(positions) != len(self.drives):
            raise ValueError(f"{len(positions)} positions for {len(self.drives)} drives")
        for d, p in zip(self.drives, positions, strict=True):
            lo, hi = d.cfg.min_position, d.cfg.max_position
            if (lo is not None and p < lo) or (hi is not None and p > hi):
                self.raise_fault(d.cfg.node_id, f"commanded position {p:g} beyond the soft limits "
                                                f"[{lo}, {hi}]")
                return
            try:
                counts = d.scale.to_counts(p)
            except OverflowError as exc:
                self.raise_fault(d.cfg.node_id, str(exc))
                return
            toward = ((NEGATIVE_LIMIT if counts < d.target else 0)
                      | (POSITIVE_LIMIT if counts > d.target else 0))
            if d.inputs & toward:
                self._limit_fault(d, d.inputs & toward, "the target moves toward it")
                return
            d.target = counts

    def _check(self, now: float, active: list[_Drive]) -> None:
        """The feedback of the drives streamed to, before this cycle's RPDOs: the master's own SYNC
        gap first (a stalled cycle is the master's fault, not a node's), then per drive its heartbeat,
        its TPDOs since the last SYNC, its state, its following error."""
        conf = self.config
        if self._last_sync and now - self._last_sync > conf.feedback_timeout_s:
            gap = now - self._last_sync
            self.raise_fault(0, f"the master sent no SYNC for {1000 * gap:.0f} ms (limit "
                                f"{1000 * conf.feedback_timeout_s:g} ms): its cycle stalled, the drives got "
                                "no setpoint")
            return
        for d in active:
            hb_age = now - d.heartbeat_at
            if conf.heartbeat_producer_ms > 0 and hb_age > conf.heartbeat_consumer_ms / 1000.0:
                self.raise_fault(d.cfg.node_id, f"heartbeat missed: none for {1000 * hb_age:.0f} ms "
                                                f"(consumer time {conf.heartbeat_consumer_ms} ms)")
                return
            # how long before the latest SYNC the drive last answered one (SYNCs, not the clock: a
            # pause of the master's own is not the drive's silence)
            fb_age = self._last_sync - max(d.feedback_at, self._stream_t0, d.active_at)
            if fb_age > conf.feedback_timeout_s and not d.homing:
                self.raise_fault(d.cfg.node_id, f"no TPDO for {1000 * fb_age:.0f} ms of SYNCs "
                                                f"(limit {1000 * conf.feedback_timeout_s:g} ms): "
                                                "frames lost?")
                return
            limits = d.inputs & (NEGATIVE_LIMIT | POSITIVE_LIMIT)
            if limits & ~d.limits_armed and not d.homing:
                self._limit_fault(d, limits & ~d.limits_armed, "it became active while the axis is driven")
                return
            d.limits_armed = limits
            if d.feedback_at <= d.enabled_at:
                continue  # no TPDO yet since enabling
            state = cia402.decode(d.statusword)
            if state != State.OPERATION_ENABLED:
                self.raise_fault(d.cfg.node_id, self._stopped_itself(d, state))
                return
            if abs(d.following_error) > d.window:
                fe = d.following_error / d.scale.scale
                self.raise_fault(d.cfg.node_id, f"following error {fe:.4g} beyond its window "
                                                f"{d.cfg.following_error_window:g}")
                return
            if d.statusword & cia402.SW_BIT13 and not d.homing:
                # the drive's own check against 0x6065, seen on the statusword before (or without)
                # the following-error PDO
                self.raise_fault(d.cfg.node_id, "following error beyond its window "
                                                f"{d.cfg.following_error_window:g} (the drive reports it: "
                                                f"statusword 0x{d.statusword:04X}, bit 13)")
                return

    def _limit_fault(self, d: _Drive, bits: int, why: str) -> None:
        names = " and ".join(input_names(bits))
        self.raise_fault(d.cfg.node_id, f"{names} active (0x60FD = 0x{d.inputs:08X}): {why}; "
                                        "not re-enabled (reset, then move the axis off the switch)")

    def _stopped_itself(self, d: _Drive, state: State) -> str:
        """The fault text of a drive seen out of Operation enabled while streaming: the state and why a
        drive goes there by itself. The master never re-enables it (only reset + enable do)."""
        if state == State.QUICK_STOP_ACTIVE:
            why = ("the drive's own quick stop (its quick-stop input, a limit switch or a stop it decided "
                   "itself); it ramps down on its own quick stop deceleration")
        elif state == State.SWITCH_ON_DISABLED:
            why = ("the drive disabled itself (its enable or safe-torque-off input, or a quick stop that "
                   "ends in Switch on disabled)")
        elif state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            e = d.last_emcy
            why = (f"a drive fault, EMCY 0x{e.code:04X} {e.get_desc() or ''}".rstrip() if e is not None
                   else "a drive fault (no EMCY received)")
        else:
            why = "the drive changed state by itself"
        return (f"left Operation enabled: now '{state}' (statusword 0x{d.statusword:04X}): {why}; "
                "not re-enabled")

    def feedback(self) -> DriveFeedback:
        return DriveFeedback(
            self.cycles,
            tuple(d.scale.to_units(d.actual) for d in self.drives),
            tuple(d.following_error / d.scale.scale for d in self.drives),
            tuple(cia402.decode(d.statusword) for d in self.drives),
            self.fault,
            tuple(d.inputs for d in self.drives),
        )

    @property
    def state(self) -> list[DriveState]:
        return [DriveState(d.cfg.axis, d.cfg.node_id, cia402.decode(d.statusword), d.statusword,
                           d.scale.to_units(d.actual), d.following_error / d.scale.scale, d.actual,
                           d.scale.to_units(d.target), d.inputs) for d in self.drives]

    def positions(self) -> tuple[float, ...]:
        """The commanded (held) position of every axis, machine units: where the planner resumes."""
        return tuple(d.scale.to_units(d.target) for d in self.drives)

    # ------------------------------------------------------------------ homing
    def home(self, axis: str) -> float:
        """Home one axis as configured ("set": here is home; "cia402": homing mode 6 by SDO).

        The drive must be enabled. Returns the axis position afterwards (its ``home_offset``).
        """
        d = next((x for x in self.drives if x.cfg.axis == axis), None)
        if d is None:
            raise CanopenError(f"no drive for axis {axis!r}")
        if d.cfg.homing == "set":
            actual = self._sdo(d, "position actual", 0x6064, 0, "i")
            with self._lock:
                d.scale.set_home_here(actual)
                d.target = d.actual = actual
            return d.scale.to_units(actual)
        with self._lock:
            d.homing = True
        try:
            self._home_cia402(d)
        except CanopenError:
            # never leave the drive homing on its own while the master streams to it later
            with contextlib.suppress(CanopenError):
                self._back_to_csp(d)
            raise
        finally:
            with self._lock:
                d.homing = False
                d.feedback_at = time.monotonic()
        return d.scale.to_units(d.target)

    def _home_cia402(self, d: _Drive) -> None:
        conf = self.config
        if cia402.decode(self._statusword(d)) != State.OPERATION_ENABLED:
            raise CanopenError(f"{d.describe()}: homing needs Operation enabled; enable() first")
        self._sdo(d, "homing method", 0x6098, 0, "b", d.cfg.homing_method)
        per_unit = abs(d.scale.scale)
        cfg = d.cfg
        for what, index, sub, value in (("homing speed (search for switch)", 0x6099, 1, cfg.homing_speed),
                                        ("homing speed (search for zero)", 0x6099, 2, cfg.homing_speed_zero),
                                        ("homing acceleration", 0x609A, 0, cfg.homing_acceleration)):
            if value is not None:  # from the machine file; else the drive's own setting
                self._sdo(d, what, index, sub, "I", max(1, round(value * per_unit)))
        self._sdo(d, "home offset", 0x607C, 0, "i", 0)
        self._set_mode(d, cia402.MODE_HOMING)
        self._sdo(d, "controlword", 0x6040, 0, "H", cia402.CW_ENABLE_OPERATION)
        self._sdo(d, "controlword (homing start)", 0x6040, 0, "H",
                  cia402.CW_ENABLE_OPERATION | cia402.CW_HOMING_START)
        deadline = time.monotonic() + conf.homing_timeout_s
        while True:
            sw = self._statusword(d)
            if sw & cia402.SW_BIT13:
                raise CanopenError(f"{d.describe()}: homing error (statusword 0x{sw:04X}, method "
                                   f"{d.cfg.homing_method})")
            if cia402.decode(sw) != State.OPERATION_ENABLED:
                raise CanopenError(f"{d.describe()}: left Operation enabled while homing: "
                                   f"'{cia402.decode(sw)}'")
            if sw & cia402.SW_BIT12 and sw & cia402.SW_TARGET_REACHED:
                break
            if time.monotonic() > deadline:
                raise CanopenError(f"{d.describe()}: homing not attained within {conf.homing_timeout_s:g} s "
                                   f"(statusword 0x{sw:04X})")
            time.sleep(0.005)
        actual = self._sdo(d, "position actual", 0x6064, 0, "i")
        with self._lock:
            d.scale.drive_zero_is_home()
            d.target = d.actual = actual
        self._sdo(d, "controlword", 0x6040, 0, "H", cia402.CW_ENABLE_OPERATION)
        self._set_mode(d, cia402.MODE_CSP)

    def _back_to_csp(self, d: _Drive) -> None:
        """A drive left in another mode (a homing that failed or was cut short): stop that motion
        (homing start bit cleared), back to cyclic synchronous position, and hold where it stands."""
        if cia402.decode(self._statusword(d)) == State.OPERATION_ENABLED:
            self._sdo(d, "controlword (stop homing)", 0x6040, 0, "H", cia402.CW_ENABLE_OPERATION)
        self._set_mode(d, cia402.MODE_CSP)
        actual = self._sdo(d, "position actual", 0x6064, 0, "i")
        with self._lock:
            d.target = d.actual = actual
        log.info("%s back in cyclic synchronous position mode", d.describe())

    def _set_mode(self, d: _Drive, mode: int) -> None:
        self._sdo(d, "modes of operation", 0x6060, 0, "b", mode)
        deadline = time.monotonic() + self.config.state_timeout_s
        while (shown := self._sdo(d, "modes of operation display", 0x6061, 0, "b")) != mode:
            if time.monotonic() > deadline:
                raise CanopenError(f"{d.describe()}: modes of operation display stays {shown}, not {mode}")
            time.sleep(0.002)

    # ------------------------------------------------------------------ the end
    def shutdown(self) -> None:
        """Leave the drives in a defined state, then let go of the bus.

        Quick stop if streaming; every drive taken to Switch on disabled once its ramp is over (a
        drive in Fault stays there) and its consumer heartbeat (0x1016) cleared, all while the
        master's heartbeat still runs; then the heartbeat stops, NMT pre-operational, the bus closes.
        Otherwise every drive would fault (heartbeat consumer, EMCY 0x8130) one consumer time after
        canon exits."""
        if self.network is None:
            return
        with self._lock:
            if any(d.active for d in self.drives):
                self._quick_stop_locked()
        for d in self.drives:
            try:
                self._park(d)
            except (CanopenError, can.CanError, OSError) as exc:
                log.error("at shutdown, %s not parked: %s", d.describe(), exc)
        if self._heartbeat_task is not None:
            self._heartbeat_task.stop()
            self._heartbeat_task = None
        try:
            for d in self.drives:
                d.node.nmt.send_command(0x80)  # pre-operational: PDOs stop
        except (can.CanError, OSError):
            pass
        net, self.network = self.network, None
        if self._own_bus:
            net.disconnect()
        else:
            if net.notifier is not None:
                net.notifier.stop(2.0)

    def _park(self, d: _Drive, consumer_off: bool = True) -> None:
        """One drive to a defined state: its stop ramp waited for, Switch on disabled, and (at shutdown)
        its consumer heartbeat off."""
        for attempt in range(2):
            deadline = time.monotonic() + self.config.state_timeout_s
            while True:
                sw = self._statusword(d)
                state = cia402.decode(sw)
                ramping = (state == State.FAULT_REACTION_ACTIVE
                           or (state == State.QUICK_STOP_ACTIVE and not sw & cia402.SW_TARGET_REACHED))
                if not ramping:
                    break
                if time.monotonic() > deadline:
                    log.warning("%s still in '%s' %g s after the quick stop: disabled all the same",
                                d.describe(), state, self.config.state_timeout_s)
                    break
                time.sleep(0.005)
            if state != State.OPERATION_ENABLED or attempt:
                break
            # enabled with nothing streamed to it: its own quick stop first, never a drop of torque
            self._sdo(d, "controlword (quick stop)", 0x6040, 0, "H", cia402.CW_QUICK_STOP)
        if state not in (State.FAULT, State.FAULT_REACTION_ACTIVE, State.SWITCH_ON_DISABLED):
            self._sdo(d, "controlword (disable voltage)", 0x6040, 0, "H", cia402.CW_DISABLE_VOLTAGE)
        if consumer_off and self.config.heartbeat_producer_ms > 0:
            self._sdo(d, "consumer heartbeat time (off)", 0x1016, 1, "I", 0, ok_aborts=_NO_SUCH_OBJECT)
        with self._lock:
            d.statusword = self._statusword(d)

    def __enter__(self) -> CanopenMaster:
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()


class _ErrorFrameListener(can.Listener):
    """CAN error frames (bus errors, error passive, bus off on SocketCAN) become a master fault."""

    def __init__(self, master: CanopenMaster) -> None:
        self.master = master

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame and self.master.streaming:
            self.master.raise_fault(0, f"bus error frame (id 0x{msg.arbitration_id:X}, "
                                       f"data {msg.data.hex()})")

    def on_error(self, exc: Exception) -> None:
        self.master.raise_fault(0, f"bus error: {exc}")
