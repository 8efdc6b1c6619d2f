"""A simulated CiA 402 servo drive on a canopen ``LocalNode``, behaving as a real drive on the bus.

python canopen 2.4's ``LocalNode`` gives the object dictionary and the SDO server; its PDO and NMT
parts are master-side or incomplete (no RPDO written into the dictionary, no TPDO on SYNC, no boot-up
after a remote reset), so this drive does NMT, heartbeat and PDO framing itself from its own
dictionary: the PDO mapping the master writes by SDO (0x1400/0x1600, 0x1800/0x1A00) is what it uses.

Behaviour a real drive has and the tests rely on:

* NMT: boot-up message after power-on and after reset (optionally late: ``boot_delay_s``); PDOs only
  in Operational; heartbeat producer (0x1017) and consumer of the master's heartbeat (0x1016).
* The CiA 402 state machine (``cia402``), controlword applied on receipt (by SDO or RPDO).
* PDOs 1-4 each way as mapped: SYNC-driven TPDOs (type 1-240) on every n-th SYNC; event TPDOs (type
  254/255) when their data change (no sooner than the inhibit time, sub 3) and on the event timer
  (sub 5); every RPDO's values applied on receipt, a target latched at the next SYNC.
* Cyclic synchronous position: the target received by RPDO is latched at the next SYNC; position
  actual follows the demand with first- or second-order dynamics (the servo lag); following error is
  demand minus actual and faults the drive beyond 0x6065. A target that jumps further than 0x607F
  (max velocity) allows in one period faults it. A SYNC period without a new target, or a SYNC
  arriving late, is counted (``missed_setpoints``, ``late_syncs``).
* Quick stop and fault reaction decelerate at 0x6085; quick stop option 0x605A 5/6 stays in Quick
  stop active holding the position, 1/2 ends in Switch on disabled.
* Homing mode 6: methods 35/37 take the current position as home; others travel at 0x6099:1 to a
  simulated home switch, at 0x6099:2 once on it (its 0x60FD bit 2, with ``home_switch_window_counts``);
  either way the position then reads 0x607C.
* Digital inputs 0x60FD from the actual position: bit 0 negative limit switch (at or below
  ``negative_limit_counts``), bit 1 positive limit switch (at or above ``positive_limit_counts``), bit 2
  home switch (within ``home_switch_window_counts`` of ``home_switch_counts``; 0: no home input).
  The drive itself does not react to them (as a drive whose limit switch reaction is "report"): the
  master must.
* Optional objects absent (``absent_objects``): SDO access aborts 0x06020000 and the drive keeps its
  own defaults for them.
* A small motor's limits, from the EDS (0x6080 3000 rpm, 0x608F 50000 counts/rev, 0x60C5/0x60C6,
  0x607D, 0x6502 with CSP) or ``parameters``.
* RPDO deadline monitoring (``rpdo_timeout_syncs``): in Operation enabled, that many SYNCs in a row
  without a target fault the drive with EMCY 0x8250.
* EMCY on every fault, and the reset EMCY (code 0) on fault reset.

Faults are injected from tests: :meth:`inject_fault`, :meth:`drop_heartbeat`, :meth:`abort_sdo`,
``boot_delay_s``, :meth:`stall`, the local quick-stop input :meth:`set_quick_stop_input` (also by SDO:
0x2F00:03 = 1/0, ``canon sim inject --quick-stop on|off``). From another process, as a test bench
does on a real bus, by SDO to the simulation-only object 0x2F00 (:data:`SIM_INJECT`): sub 2 a delay in
ms, then sub 1 an EMCY code; the drive faults with that code exactly as :meth:`inject_fault` does
(``canon sim inject``).
"""

from __future__ import annotations

import contextlib
import logging
import math
import struct
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import canopen
from canopen.sdo import SdoAbortedError

from fieldbus.canopen import SHIPPED_EDS, cia402
from fieldbus.canopen.cia402 import Command, State
from fieldbus.canopen.config import DriveConfig

log = logging.getLogger(__name__)

NMT_INITIALISING, NMT_STOPPED, NMT_OPERATIONAL, NMT_PRE_OPERATIONAL = 0, 4, 5, 127

EMCY_VELOCITY = 0x8400  # setpoint jump beyond the maximum velocity
EMCY_FOLLOWING_ERROR = 0x8611
EMCY_HEARTBEAT = 0x8130  # life guard / heartbeat consumer timeout
EMCY_GENERIC = 0x1000
EMCY_RPDO_TIMEOUT = 0x8250  # RPDO deadline monitoring (CiA 301: "RPDO timeout")

# Manufacturer-specific, simulation only (not on a real drive): an SDO write of a non-zero code to
# sub 1 faults the drive with that EMCY code, after the delay in ms held in sub 2 (write it first);
# writing 0 to sub 1 cancels faults still waiting for their delay.
SIM_INJECT = 0x2F00
SIM_INJECT_CODE, SIM_INJECT_DELAY_MS = 1, 2
#: sub 3: the drive's local quick-stop input (1 active, 0 released), as a wired button or limit switch
SIM_QUICK_STOP_INPUT = 3

NO_SUCH_OBJECT = 0x06020000  # SDO abort: object does not exist in the object dictionary

_LIVE = {0x6041, 0x6061, 0x6062, 0x6064, 0x60F4, 0x603F, 0x1001, 0x60FD}

#: 0x60FD bits (CiA 402)
DI_NEGATIVE_LIMIT, DI_POSITIVE_LIMIT, DI_HOME, DI_INTERLOCK = 0x1, 0x2, 0x4, 0x8


@dataclass
class PdoMap:
    cob_id: int
    transmission: int
    entries: tuple[tuple[int, int, int], ...]  # (index, subindex, bytes)
    fmt: str = ""
    inhibit_s: float = 0.0
    event_timer_s: float = 0.0

    @property
    def event(self) -> bool:
        return self.transmission in (254, 255)


_FMT = {(1, True): "b", (1, False): "B", (2, True): "h", (2, False): "H", (4, True): "i", (4, False): "I"}


def motor_for(cfg: DriveConfig, eds: str | Path = SHIPPED_EDS) -> dict[tuple[int, int], int]:
    """``parameters`` for a simulated motor big enough for the axis ``cfg``: the EDS's small motor where
    it fits, else 0x6080 (rpm, at the EDS's 0x608F counts per revolution) and 0x60C5/0x60C6 raised to
    what the configuration asks (velocity with the 0x607F margin). The simulated machine (``canon run``,
    the daemon, ``canon sim drives``) stands in for drives sized for it; tests that want a motor too
    small for the configuration build their SimDrive without it."""
    od = canopen.import_od(str(eds), cfg.node_id)
    out: dict[tuple[int, int], int] = {}
    try:
        cpr = od[0x608F][1].default / max(1, od[0x608F][2].default)
        rpm = od[0x6080].default
    except KeyError:
        return out
    per_unit = abs(cfg.counts_per_unit)
    need_rpm = math.ceil(cfg.max_velocity * 1.25 * per_unit * 60.0 / cpr)
    if need_rpm > rpm:
        out[(0x6080, 0)] = need_rpm
    if cfg.max_acceleration is not None:
        need = math.ceil(max(cfg.max_acceleration, cfg.quick_stop_deceleration) * per_unit)
        for index in (0x60C5, 0x60C6):
            if index in od and need > od[index].default:
                out[(index, 0)] = need
    return out


class SimDrive:
    """One simulated drive. Attach it to a ``canopen.Network``; call :meth:`tick` every few ms."""

    def __init__(self, node_id: int, eds: str | Path = SHIPPED_EDS, *, lag_s: float = 0.002,
                 order: int = 1, damping: float = 0.8, boot_delay_s: float = 0.0,
                 home_switch_counts: int = 0, rpdo_timeout_syncs: int = 0,
                 negative_limit_counts: int | None = None, positive_limit_counts: int | None = None,
                 home_switch_window_counts: int = 0,
                 absent_objects: Iterable[int] = (), parameters: Mapping[tuple[int, int], int] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if order not in (1, 2):
            raise ValueError("order must be 1 (first-order lag) or 2 (second-order dynamics)")
        self.id = node_id
        self.node = canopen.LocalNode(node_id, str(eds))
        # canopen's NmtSlave starts its own heartbeat task when 0x1017 is written; this drive sends its
        # heartbeat itself (so that a test can drop it), so that callback is removed.
        self.node._write_callbacks.remove(self.node.nmt.on_write)
        self.node.add_write_callback(self._on_write)
        self.node.add_read_callback(self._on_read)
        self.lag_s = lag_s
        self.order = order
        self.damping = damping
        self.boot_delay_s = boot_delay_s
        self.home_switch_counts = home_switch_counts
        # limit and home switches (0x60FD), by the actual position in counts; None / 0: not fitted
        self.negative_limit_counts = negative_limit_counts
        self.positive_limit_counts = positive_limit_counts
        self.home_switch_window_counts = home_switch_window_counts
        # RPDO deadline monitoring, as EPOS4-style drives have: in Operation enabled (CSP), this many
        # SYNCs in a row without a target fault the drive with EMCY 0x8250 (0: off)
        self.rpdo_timeout_syncs = rpdo_timeout_syncs
        # objects this drive does not have, though its EDS lists them: SDO access aborts 0x06020000
        # (a drive without optional objects, as many are); it then uses its defaults for them
        self.absent_objects = frozenset(absent_objects)
        # (index, subindex): value the drive has instead of its EDS default, after every power-on (a
        # motor of its own: 0x6080 max motor speed, 0x608F encoder, 0x60C5/0x60C6, 0x607D, 0x6502)
        self.parameters = dict(parameters or {})
        self._syncs_without_target = 0
        self.clock = clock
        self.lock = threading.RLock()
        self.network: canopen.Network | None = None

        self.nmt_state = NMT_INITIALISING
        self._boot_at: float | None = None
        self.state = State.NOT_READY_TO_SWITCH_ON
        self.controlword = 0
        self.mode = 0
        self.error_code = 0
        # positions in counts (floats inside the dynamics; reported rounded)
        self.actual = 0.0
        self.velocity = 0.0
        self.demand = 0.0
        self.target = 0
        self._pending_target: int | None = None
        self._homing: bool = False
        self._homing_attained = False
        self._homing_error = False
        # counters a test reads
        self.syncs = 0
        self.rpdos = 0
        self.missed_setpoints = 0
        self.late_syncs = 0
        self.heartbeats_sent = 0
        self.enables = 0  # times the drive entered Operation enabled
        self.emcys: list[int] = []
        self.latched: list[tuple[int, int]] = []  # (sync number, target) when record_targets is on
        self.record_targets = False
        # fault injection
        self._scheduled: list[tuple[float, int]] = []
        self._hb_dropped_until = 0.0
        self._sdo_aborts: dict[tuple[int, int], int] = {}
        self._stalled = False
        self.sdo_silent: set[int] = set()  # SDO requests to these indexes get no answer
        self.ignore_controlword = False  # a drive stuck in its state
        # the drive's local quick-stop input (:meth:`set_quick_stop_input`): while it is active the
        # drive does not enable
        self.quick_stop_input = False
        # CiA 402 allows transition 16 (Quick stop active -> Operation enabled, options 5-8) at any
        # time; many drives take it only once the ramp has ended (False), strict ones at once (True)
        self.reenable_during_quick_stop_ramp = False
        # beyond 0x6065 the drive faults (EMCY 0x8611); False: it only sets statusword bit 13, as
        # drives whose following-error reaction is "report" do
        self.fault_on_following_error = True
        self._last_tick: float | None = None
        # communication set-up, read from the dictionary on entering Operational
        self._rpdos: list[PdoMap] = []
        self._tpdos: list[PdoMap] = []
        self._event_sent: dict[int, tuple[bytes, float]] = {}  # event TPDO COB-ID: (data, time sent)
        self._subscribed: list[int] = []
        self._last_sync: float | None = None
        self._next_hb = 0.0
        self._master_id = 0
        self._master_hb_seen: float | None = None
        self._params_dirty = True
        self._period = 0.0

    # ------------------------------------------------------------------ wiring
    def attach(self, network: canopen.Network) -> None:
        self.network = network
        network.add_node(self.node)
        # SDO requests pass through this drive first, so that a test can make it fall silent
        network.unsubscribe(self.node.sdo.rx_cobid, self.node.sdo.on_request)
        network.subscribe(self.node.sdo.rx_cobid, self._on_sdo)
        network.subscribe(0, self._on_nmt)
        network.subscribe(0x80, self._on_sync)
        self.power_on()

    def detach(self) -> None:
        if self.network is None:
            return
        with self.lock:
            self._unsubscribe_pdos()
            self.network.unsubscribe(self.node.sdo.rx_cobid, self._on_sdo)
            self.network.subscribe(self.node.sdo.rx_cobid, self.node.sdo.on_request)
            if self._master_id:
                self.network.unsubscribe(0x700 + self._master_id, self._on_master_heartbeat)
                self._master_id = 0
            self.network.unsubscribe(0, self._on_nmt)
            self.network.unsubscribe(0x80, self._on_sync)
            self.node.remove_network()
            self.network = None

    def power_on(self) -> None:
        """Start as after switching the drive on (again): dictionary back to its defaults, CiA 402
        state machine from the start, boot-up after ``boot_delay_s``."""
        with self.lock:
            self._reset(application=True)
            self.velocity = 0.0
        self.tick()

    def _on_sdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self.sdo_silent and len(data) >= 3 and int.from_bytes(data[1:3], "little") in self.sdo_silent:
            return
        if self.nmt_state == NMT_INITIALISING:
            return  # not booted: no SDO server yet
        self.node.sdo.on_request(can_id, data, timestamp)

    def _send(self, cob_id: int, data: bytes | bytearray | list[int]) -> None:
        if self.network is not None:
            self.network.send_message(cob_id, bytes(data))

    # ------------------------------------------------------------------ NMT
    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) < 2:
            return
        cmd, target = data[0], data[1]
        if target not in (0, self.id):
            return
        with self.lock:
            if cmd == 0x01:
                self._enter_nmt(NMT_OPERATIONAL)
            elif cmd == 0x02:
                self._enter_nmt(NMT_STOPPED)
            elif cmd == 0x80:
                self._enter_nmt(NMT_PRE_OPERATIONAL)
            elif cmd in (0x81, 0x82):
                self._reset(application=cmd == 0x81)

    def _reset(self, application: bool) -> None:
        self._unsubscribe_pdos()
        store = self.node.data_store
        for index in list(store):
            if application or index < 0x2000:
                del store[index]
        for (index, sub), value in self.parameters.items():
            if application or index < 0x2000:
                obj = self.node._find_object(index, sub)
                store.setdefault(index, {})[sub] = obj.encode_raw(value)
        if application:
            self.state = State.NOT_READY_TO_SWITCH_ON
            self.mode = 0
            self.controlword = 0
        self.nmt_state = NMT_INITIALISING
        self._master_hb_seen = None
        self._params_dirty = True
        self._boot_at = self.clock() + self.boot_delay_s

    def _enter_nmt(self, new: int) -> None:
        if self.nmt_state == NMT_INITIALISING:
            return
        if new == NMT_OPERATIONAL and self.nmt_state != NMT_OPERATIONAL:
            self._load_params()
            self._subscribe_pdos()
            self._last_sync = None
        elif new != NMT_OPERATIONAL:
            self._unsubscribe_pdos()
        self.nmt_state = new
        self._send_heartbeat()
        self._event_tpdos()  # event TPDOs go out on entering Operational

    def _send_heartbeat(self) -> None:
        if self.clock() < self._hb_dropped_until:
            return
        self._send(0x700 + self.id, [self.nmt_state])
        self.heartbeats_sent += 1

    def _on_master_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self._master_hb_seen = self.clock()

    def tick(self, now: float | None = None) -> None:
        """Time-driven work: boot-up, heartbeat, master heartbeat watch, scheduled faults."""
        now = self.clock() if now is None else now
        with self.lock:
            if self.nmt_state == NMT_INITIALISING:
                if self._boot_at is not None and now >= self._boot_at and self.network is not None:
                    self._boot_at = None
                    self._send(0x700 + self.id, [0])  # boot-up
                    self.nmt_state = NMT_PRE_OPERATIONAL
                    if self.state == State.NOT_READY_TO_SWITCH_ON:
                        self.state = State.SWITCH_ON_DISABLED
                    self._params_dirty = True
                    self._load_params()
                    self._next_hb = now + self._hb_ms / 1000.0
                return
            self._load_params()
            if self._last_tick is not None and self.state == State.OPERATION_ENABLED \
                    and self.mode == cia402.MODE_HOMING:
                self._homing_step(now - self._last_tick)  # homing runs on the drive's own clock
            elif (self._last_tick is not None
                  and self.state in (State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE)
                  and (self._last_sync is None or now - self._last_sync > 3 * (self._period or 0.01))):
                self._decelerate(now - self._last_tick)  # no SYNC: the stop ramp runs on its own clock
            self._last_tick = now
            if self._hb_ms > 0 and now >= self._next_hb:
                self._send_heartbeat()
                self._next_hb = max(self._next_hb + self._hb_ms / 1000.0, now)
            if (self._consumer_ms > 0 and self._master_hb_seen is not None
                    and now - self._master_hb_seen > self._consumer_ms / 1000.0):
                self._master_hb_seen = None
                if self.state not in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                    self._fault(EMCY_HEARTBEAT, "master heartbeat lost")
            for item in [s for s in self._scheduled if s[0] <= now]:
                self._scheduled.remove(item)
                self._fault(item[1], "injected")
            self._event_tpdos(now)

    # ------------------------------------------------------------------ parameters from the dictionary
    def _value(self, index: int, subindex: int = 0) -> int:
        obj = self.node._find_object(index, subindex)
        store = self.node.data_store.get(index, {})
        if subindex in store:
            return obj.decode_raw(store[subindex])
        return obj.value if obj.value is not None else (obj.default or 0)

    _hb_ms = 0
    _consumer_ms = 0

    def _load_params(self) -> None:
        if not self._params_dirty:
            return
        self._params_dirty = False
        self._hb_ms = self._value(0x1017)
        consumer = self._value(0x1016, 1)
        self._consumer_ms = consumer & 0xFFFF
        master_id = (consumer >> 16) & 0x7F
        if master_id != self._master_id and self.network is not None:
            if self._master_id:
                self.network.unsubscribe(0x700 + self._master_id, self._on_master_heartbeat)
            if master_id:
                self.network.subscribe(0x700 + master_id, self._on_master_heartbeat)
            self._master_id = master_id
        period_us = self._value(0x1006)
        if period_us:
            self._period = period_us / 1e6
        else:
            self._period = self._value(0x60C2, 1) * 10.0 ** self._value(0x60C2, 2)
        self._window = self._value(0x6065)
        self._max_velocity = self._value(0x607F)
        self._qs_decel = max(1, self._value(0x6085))
        self._qs_option = self._value(0x605A)
        self._home_offset = self._value(0x607C)
        self._homing_method = self._value(0x6098)
        self._homing_speed = max(1, self._value(0x6099, 1))
        self._homing_speed_zero = max(1, self._value(0x6099, 2))

    def _read_pdo(self, comm: int, mapping: int) -> PdoMap | None:
        if comm not in self.node.object_dictionary or mapping not in self.node.object_dictionary:
            return None  # an EDS with fewer PDOs
        cob = self._value(comm, 1)
        n = self._value(mapping, 0)
        if cob & 0x80000000 or n == 0:
            return None
        entries = []
        fmt = "<"
        for sub in range(1, n + 1):
            m = self._value(mapping, sub)
            index, subindex, bits = m >> 16, (m >> 8) & 0xFF, m & 0xFF
            obj = self.node._find_object(index, subindex)
            signed = obj.data_type in (canopen.objectdictionary.INTEGER8, canopen.objectdictionary.INTEGER16,
                                       canopen.objectdictionary.INTEGER32)
            entries.append((index, subindex, bits // 8))
            fmt += _FMT[(bits // 8, signed)]
        timing = [0.0, 0.0]
        if comm >= 0x1800:  # TPDO: inhibit time (100 us units) and event timer (ms), where the EDS has them
            for i, (sub, unit) in enumerate(((3, 1e-4), (5, 1e-3))):
                with contextlib.suppress(KeyError):
                    timing[i] = self._value(comm, sub) * unit
        return PdoMap(cob & 0x7FF, self._value(comm, 2), tuple(entries), fmt, *timing)

    def _subscribe_pdos(self) -> None:
        self._unsubscribe_pdos()
        self._rpdos = [p for p in (self._read_pdo(0x1400 + i, 0x1600 + i) for i in range(4)) if p]
        self._tpdos = [p for p in (self._read_pdo(0x1800 + i, 0x1A00 + i) for i in range(4)) if p]
        self._event_sent = {}
        for p in self._rpdos:
            self.network.subscribe(p.cob_id, self._on_rpdo)  # type: ignore[union-attr]
            self._subscribed.append(p.cob_id)

    def _unsubscribe_pdos(self) -> None:
        if self.network is not None:
            for cob in self._subscribed:
                # with the callback: never drop other nodes' subscribers on a shared network
                self.network.unsubscribe(cob, self._on_rpdo)
        self._subscribed = []

    # ------------------------------------------------------------------ dictionary callbacks
    def _on_read(self, index: int, subindex: int, od: object) -> int | None:
        if index in self.absent_objects and od is not None:
            raise SdoAbortedError(NO_SUCH_OBJECT)
        abort = self._sdo_aborts.get((index, subindex))
        if abort:
            raise SdoAbortedError(abort)
        if index not in _LIVE:
            return None
        with self.lock:
            if index == 0x6041:
                return self.statusword()
            if index == 0x6061:
                return self.mode
            if index == 0x6062:
                return round(self.demand)
            if index == 0x6064:
                return round(self.actual)
            if index == 0x60F4:
                return round(self.demand - self.actual)
            if index == 0x603F:
                return self.error_code
            if index == 0x60FD:
                return self.digital_inputs()
            return 1 if self.state in (State.FAULT, State.FAULT_REACTION_ACTIVE) else 0

    def _on_write(self, index: int, subindex: int, od: object, data: bytes) -> None:
        if index in self.absent_objects:
            raise SdoAbortedError(NO_SUCH_OBJECT)
        abort = self._sdo_aborts.get((index, subindex))
        if abort:
            raise SdoAbortedError(abort)
        with self.lock:
            if index == 0x6040:
                self._controlword(struct.unpack_from("<H", data)[0])
            elif index == 0x607A:
                self._pending_target = struct.unpack_from("<i", data)[0]
            elif index == 0x6060:
                mode = struct.unpack_from("<b", data)[0]
                if mode not in (cia402.MODE_CSP, cia402.MODE_HOMING):
                    raise SdoAbortedError(0x06090030)  # value range exceeded
                if mode != self.mode:
                    # as drives do on a mode change: the demand starts where the motor is (no jump,
                    # and a homing travel cut short stops where it is)
                    self.demand = self.actual
                    self.target = round(self.actual)
                    self._pending_target = None
                    self.velocity = 0.0
                self.mode = mode
                self._homing = False
            elif index == SIM_INJECT and subindex == SIM_INJECT_CODE:
                self._injected_by_sdo(struct.unpack_from("<H", data)[0])
            elif index == SIM_INJECT and subindex == SIM_QUICK_STOP_INPUT:
                self.set_quick_stop_input(bool(data[0]))
            else:
                self._params_dirty = True
            self._event_tpdos()

    def _on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self.lock:
            if self.nmt_state != NMT_OPERATIONAL:
                return
            for p in self._rpdos:
                if p.cob_id != can_id:
                    continue
                self.rpdos += 1
                try:
                    values = struct.unpack_from(p.fmt, data)
                except struct.error:
                    continue
                for (index, _sub, _size), value in zip(p.entries, values, strict=True):
                    if index == 0x6040:
                        self._controlword(value)
                    elif index == 0x607A:
                        self._pending_target = value
            self._event_tpdos()

    # ------------------------------------------------------------------ CiA 402
    def statusword(self) -> int:
        extra = 0
        if self.state == State.OPERATION_ENABLED:
            if self.mode == cia402.MODE_CSP:
                extra |= cia402.SW_BIT12
                if self._window != 0xFFFFFFFF and abs(self.demand - self.actual) > self._window:
                    extra |= cia402.SW_BIT13
            elif self.mode == cia402.MODE_HOMING:
                if self._homing_attained:
                    extra |= cia402.SW_BIT12 | cia402.SW_TARGET_REACHED
                if self._homing_error:
                    extra |= cia402.SW_BIT13
        elif self.state == State.QUICK_STOP_ACTIVE and self.velocity == 0:
            extra |= cia402.SW_TARGET_REACHED  # halted at the end of the quick stop ramp
        return cia402.statusword_for(self.state, extra)

    _window = 0xFFFFFFFF

    def digital_inputs(self) -> int:
        """0x60FD from the actual position: the limit and home switches this drive has."""
        bits = 0
        pos = round(self.actual)
        if self.negative_limit_counts is not None and pos <= self.negative_limit_counts:
            bits |= DI_NEGATIVE_LIMIT
        if self.positive_limit_counts is not None and pos >= self.positive_limit_counts:
            bits |= DI_POSITIVE_LIMIT
        window = self.home_switch_window_counts
        if window and abs(pos - self.home_switch_counts) <= window:
            bits |= DI_HOME
        return bits

    def _controlword(self, cw: int) -> None:
        if self.ignore_controlword:
            return
        self._load_params()
        previous, self.controlword = self.controlword, cw
        cmd = cia402.command_of(cw, previous)
        s = self.state
        if s == State.FAULT:
            if cmd == Command.FAULT_RESET:
                self.state = State.SWITCH_ON_DISABLED
                self.error_code = 0
                if self.network is not None:
                    self.node.emcy.reset()
            return
        if s in (State.FAULT_REACTION_ACTIVE, State.NOT_READY_TO_SWITCH_ON):
            return
        if cmd == Command.DISABLE_VOLTAGE:
            self.state = State.SWITCH_ON_DISABLED
        elif s == State.SWITCH_ON_DISABLED:
            if cmd == Command.SHUTDOWN:
                self.state = State.READY_TO_SWITCH_ON
        elif s == State.READY_TO_SWITCH_ON:
            if cmd == Command.SWITCH_ON:
                self.state = State.SWITCHED_ON
            elif cmd == Command.QUICK_STOP:
                self.state = State.SWITCH_ON_DISABLED
        elif s == State.SWITCHED_ON:
            if cmd == Command.ENABLE_OPERATION:
                self._enable()
            elif cmd == Command.SHUTDOWN:
                self.state = State.READY_TO_SWITCH_ON
            elif cmd == Command.QUICK_STOP:
                self.state = State.SWITCH_ON_DISABLED
        elif s == State.OPERATION_ENABLED:
            if cmd == Command.QUICK_STOP:
                self.state = State.QUICK_STOP_ACTIVE
            elif cmd == Command.SWITCH_ON:
                self.state = State.SWITCHED_ON
            elif cmd == Command.SHUTDOWN:
                self.state = State.READY_TO_SWITCH_ON
            elif self.mode == cia402.MODE_HOMING and cw & cia402.CW_HOMING_START \
                    and not previous & cia402.CW_HOMING_START:
                self._start_homing()
        elif (s == State.QUICK_STOP_ACTIVE and cmd == Command.ENABLE_OPERATION
              and (self.velocity == 0 or self.reenable_during_quick_stop_ramp)
              and self._qs_option in (5, 6, 7, 8)):
            self._enable()

    def _enable(self) -> None:
        # As drives do: the demand starts where the motor is, so enabling never jumps.
        if self.quick_stop_input:
            return  # the input holds the drive in its stop
        self.enables += 1
        self._syncs_without_target = 0
        self.state = State.OPERATION_ENABLED
        self.demand = self.actual
        self.target = round(self.actual)
        self._pending_target = None
        self.velocity = 0.0

    def _fault(self, code: int, why: str) -> None:
        log.info("drive %d: fault 0x%04X (%s) in %s", self.id, code, why, self.state)
        self.error_code = code
        self.emcys.append(code)
        self._homing = False
        if self.network is not None:
            self.node.emcy.send(code, 0x01)
        if self.state in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE):
            self.state = State.FAULT_REACTION_ACTIVE
        else:
            self.state = State.FAULT
            self.velocity = 0.0

    # ------------------------------------------------------------------ the cycle
    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        now = self.clock()
        with self.lock:
            if self.nmt_state != NMT_OPERATIONAL:
                return
            self._load_params()
            period = self._period or 0.002
            if self._last_sync is not None and now - self._last_sync > 1.5 * period:
                self.late_syncs += 1
            self._last_sync = now
            self.syncs += 1
            self._step(period)
            for p in self._tpdos:
                if 1 <= p.transmission <= 240 and self.syncs % p.transmission == 0:
                    self._send(p.cob_id, self._encode(p))
            self._event_tpdos(now)

    def _event_tpdos(self, now: float | None = None) -> None:
        """Send each event TPDO whose data changed since it was last sent (once its inhibit time has
        passed), or whose event timer has run out. Called, with the lock held, after everything that
        can change the drive's state: SYNC, RPDO, SDO write, tick."""
        if self.nmt_state != NMT_OPERATIONAL or self.network is None:
            return
        now = self.clock() if now is None else now
        for p in self._tpdos:
            if not p.event:
                continue
            data = self._encode(p)
            last = self._event_sent.get(p.cob_id)
            if last is not None:
                changed = data != last[0] and now - last[1] >= p.inhibit_s
                due = p.event_timer_s > 0 and now - last[1] >= p.event_timer_s
                if not (changed or due):
                    continue
            self._send(p.cob_id, data)
            self._event_sent[p.cob_id] = (data, now)

    def _encode(self, p: PdoMap) -> bytes:
        values = []
        for index, sub, _size in p.entries:
            v = self._on_read(index, sub, None)
            values.append(self._value(index, sub) if v is None else v)
        return struct.pack(p.fmt, *values)

    def _step(self, dt: float) -> None:
        s = self.state
        new = self._pending_target
        self._pending_target = None
        if s == State.OPERATION_ENABLED and self.mode == cia402.MODE_CSP:
            if new is None:
                self.missed_setpoints += 1
                self._syncs_without_target += 1
                if self.rpdo_timeout_syncs and self._syncs_without_target >= self.rpdo_timeout_syncs:
                    self._fault(EMCY_RPDO_TIMEOUT, f"{self._syncs_without_target} SYNCs without a target")
                    self._decelerate(dt)
                    return
            else:
                self._syncs_without_target = 0
                if abs(new - self.target) > self._max_velocity * dt * 1.0001 + 1:
                    self._fault(EMCY_VELOCITY, f"target jump {new - self.target} counts in {dt} s")
                    self._decelerate(dt)
                    return
                self.target = new
                if self.record_targets:
                    self.latched.append((self.syncs, new))
            previous = self.demand
            self.demand = float(self.target)
            self.velocity = (self.demand - previous) / dt
            self._follow(dt)
            if (self.fault_on_following_error and self._window != 0xFFFFFFFF
                    and abs(self.demand - self.actual) > self._window):
                self._fault(EMCY_FOLLOWING_ERROR, f"following error {self.demand - self.actual:.0f} counts")
        elif s in (State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE):
            self._decelerate(dt)
        else:
            self.velocity = 0.0
            self.demand = self.actual
            self.target = round(self.actual)

    def _follow(self, dt: float) -> None:
        if self._stalled:
            return
        tau = max(self.lag_s, 1e-6)
        if self.order == 1:
            self.actual += (self.demand - self.actual) * (1.0 - math.exp(-dt / tau))
            return
        wn = 1.0 / tau
        n = 8
        h = dt / n
        v = getattr(self, "_actual_velocity", 0.0)
        for _ in range(n):
            acc = wn * wn * (self.demand - self.actual) - 2.0 * self.damping * wn * v
            v += acc * h
            self.actual += v * h
        self._actual_velocity = v

    def _decelerate(self, dt: float) -> None:
        v = self.velocity
        dv = self._qs_decel * dt
        v = 0.0 if abs(v) <= dv else v - math.copysign(dv, v)
        self.velocity = v
        self.demand += v * dt
        self.target = round(self.demand)
        self._follow(dt)
        if v == 0.0:
            if self.state == State.FAULT_REACTION_ACTIVE:
                self.state = State.FAULT
            elif self.state == State.QUICK_STOP_ACTIVE and self._qs_option in (1, 2):
                self.state = State.SWITCH_ON_DISABLED

    def _start_homing(self) -> None:
        self._homing = True
        self._homing_attained = False
        self._homing_error = False

    def _homing_step(self, dt: float) -> None:
        if not self._homing:
            return
        if self._homing_method in (35, 37):
            goal = self.actual
        else:
            goal = float(self.home_switch_counts)
        speed = self._homing_speed
        if self.home_switch_window_counts and self.digital_inputs() & DI_HOME:
            speed = self._homing_speed_zero  # on the home switch: the slow search for its zero
        step = speed * dt
        d = goal - self.actual
        if abs(d) > step:
            self.actual += math.copysign(step, d)
            self.demand = self.actual
            return
        # home found: the position now reads the home offset
        self.actual = float(self._home_offset)
        self.demand = self.actual
        self.target = round(self.actual)
        self.home_switch_counts = round(self.actual) if self._homing_method not in (35, 37) else \
            self.home_switch_counts
        self._homing = False
        self._homing_attained = True

    # ------------------------------------------------------------------ fault injection
    def inject_fault(self, code: int = EMCY_GENERIC, at: float | None = None) -> None:
        """Fault now, or at clock time ``at`` (sends EMCY ``code``)."""
        with self.lock:
            if at is None:
                self._fault(code, "injected")
            else:
                self._scheduled.append((at, code))

    def _injected_by_sdo(self, code: int) -> None:
        """0x2F00:01 written (from another process): fault with ``code`` after 0x2F00:02 ms; 0 cancels."""
        if code == 0:
            self._scheduled.clear()
            return
        delay_ms = self._value(SIM_INJECT, SIM_INJECT_DELAY_MS)
        log.info("drive %d: EMCY 0x%04X injected by SDO, in %d ms", self.id, code, delay_ms)
        if delay_ms:
            self._scheduled.append((self.clock() + delay_ms / 1000.0, code))
        else:
            self._fault(code, "injected by SDO")

    def send_warning(self, code: int, register: int = 0) -> None:
        """Send an EMCY that is a warning (error register 0 by default): the drive stays as it is."""
        with self.lock:
            self.emcys.append(code)
            if self.network is not None:
                self.node.emcy.send(code, register)

    def drop_heartbeat(self, seconds: float) -> None:
        """Send no heartbeat for ``seconds``."""
        self._hb_dropped_until = self.clock() + seconds

    def abort_sdo(self, index: int, subindex: int = 0, code: int = 0x08000020) -> None:
        """Answer SDO access to ``index:subindex`` with abort ``code`` (0 removes it)."""
        if code:
            self._sdo_aborts[(index, subindex)] = code
        else:
            self._sdo_aborts.pop((index, subindex), None)

    def set_quick_stop_input(self, active: bool) -> None:
        """The drive's local quick-stop input (a wired stop button, a limit switch on the drive): on
        activation in Operation enabled the drive goes to Quick stop active and ramps down at 0x6085,
        ending as its quick stop option (0x605A) says; while it is active the drive does not enable."""
        with self.lock:
            self.quick_stop_input = active
            if active and self.state == State.OPERATION_ENABLED:
                log.info("drive %d: local quick stop input", self.id)
                self._homing = False
                self.state = State.QUICK_STOP_ACTIVE
            self._event_tpdos()

    def inject_disable(self) -> None:
        """Drop to Switch on disabled, as a drive does when its safe-torque-off input opens."""
        with self.lock:
            self.state = State.SWITCH_ON_DISABLED
            self.velocity = 0.0

    def stall(self, stalled: bool = True) -> None:
        """The motor stops following (a jammed axis): the following error grows."""
        self._stalled = stalled
