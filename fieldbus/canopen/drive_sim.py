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
* Homing mode 6 by the method's direction and end (``drive_sim_homing``): limit switches (17/18), the
  home switch (19-30, reversed by the limit switch in 23-30), the next index pulse (33/34), here
  (35/37); travel at 0x6099:1, at 0x6099:2 on the home switch (its 0x60FD bit 2, with
  ``home_switch_window_counts``); the position then reads 0x607C.
* Digital inputs 0x60FD from the actual position: bit 0 negative limit switch (at or below
  ``negative_limit_counts``), bit 1 positive limit switch (at or above ``positive_limit_counts``), bit 2
  home switch (within ``home_switch_window_counts`` of ``home_switch_counts``; 0: no home input).
  The drive itself does not react to them (as a drive whose limit switch reaction is "report"): the
  master must.
* A touch probe (0x60B8-0x60BD) on a probe input switched at ``probe_trip_counts``: the position is
  latched where the motion crossed it inside the period (``drive_sim_probe``).
* Optional objects absent (``absent_objects``): SDO access aborts 0x06020000 and the drive keeps its
  own defaults for them.
* Profile velocity (3) and cyclic synchronous velocity (9), for a spindle drive
  (``drive_sim_velocity``): target velocity 0x60FF, velocity actual 0x606C, the motor's inertia
  (``inertia_acceleration``) making the spindle lag its commanded ramp.
* A small motor's limits, from the EDS (0x6080 3000 rpm, 0x608F 50000 counts/rev, 0x60C5/0x60C6,
  0x607D, 0x6502 with CSP) or ``parameters``.
* RPDO deadline monitoring (``rpdo_timeout_syncs``): in Operation enabled, that many SYNCs in a row
  without a target fault the drive with EMCY 0x8250.
* EMCY on every fault, and the reset EMCY (code 0) on fault reset.

Faults are injected from tests: :meth:`inject_fault`, :meth:`drop_heartbeat`, :meth:`abort_sdo`,
``boot_delay_s``, :meth:`stall`, the local quick-stop input :meth:`set_quick_stop_input` (also by SDO:
0x2F00:03 = 1/0, ``canon sim inject --quick-stop on|off``), a warning EMCY :meth:`send_warning` (also
by SDO: 0x2F00:04 = the code). From another process, as a test bench
does on a real bus, by SDO to the simulation-only object 0x2F00 (:data:`SIM_INJECT`): sub 2 a delay in
ms, then sub 1 an EMCY code; the drive faults with that code exactly as :meth:`inject_fault` does
(``canon sim inject``).

The drive is one class, :class:`SimDrive`, written by concern: this module holds its wiring, NMT,
heartbeat and dictionary; ``drive_sim_cia402`` the state machine and the CSP motion of a SYNC
period; ``drive_sim_pdo`` the SYNC and the PDOs; ``drive_sim_homing`` homing mode;
``drive_sim_probe`` the touch probe; ``drive_sim_velocity`` the velocity modes (a spindle);
``drive_sim_faults`` fault injection.
"""

from __future__ import annotations

import logging
import math
import struct
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path

import canopen
from canopen.sdo import SdoAbortedError

from fieldbus.canopen import SHIPPED_EDS, cia402
from fieldbus.canopen.cia402 import State
from fieldbus.canopen.config import DriveConfig
from fieldbus.canopen.drive_sim_cia402 import (
    DI_HOME,
    DI_INTERLOCK,
    DI_NEGATIVE_LIMIT,
    DI_POSITIVE_LIMIT,
    EMCY_FOLLOWING_ERROR,
    EMCY_GENERIC,
    EMCY_HEARTBEAT,
    EMCY_RPDO_TIMEOUT,
    EMCY_VELOCITY,
    NMT_INITIALISING,
    NMT_OPERATIONAL,
    NMT_PRE_OPERATIONAL,
    NMT_STOPPED,
    StateMachineMixin,
)
from fieldbus.canopen.drive_sim_faults import (
    SIM_INJECT,
    SIM_INJECT_CODE,
    SIM_INJECT_DELAY_MS,
    SIM_QUICK_STOP_INPUT,
    SIM_WARNING,
    FaultInjectionMixin,
)
from fieldbus.canopen.drive_sim_homing import HomingMixin
from fieldbus.canopen.drive_sim_pdo import CyclicMixin, PdoMap
from fieldbus.canopen.drive_sim_probe import PROBE_OBJECTS, TOUCH_PROBE_FUNCTION, TouchProbeMixin
from fieldbus.canopen.drive_sim_velocity import VELOCITY_MODES, VelocityMixin

__all__ = [
    "DI_HOME", "DI_INTERLOCK", "DI_NEGATIVE_LIMIT", "DI_POSITIVE_LIMIT", "EMCY_FOLLOWING_ERROR",
    "EMCY_GENERIC", "EMCY_HEARTBEAT", "EMCY_RPDO_TIMEOUT", "EMCY_VELOCITY", "NMT_INITIALISING",
    "NMT_OPERATIONAL", "NMT_PRE_OPERATIONAL", "NMT_STOPPED", "NO_SUCH_OBJECT", "SIM_INJECT",
    "SIM_INJECT_CODE", "SIM_INJECT_DELAY_MS", "SIM_QUICK_STOP_INPUT", "PdoMap", "SimDrive", "motor_for",
]

log = logging.getLogger(__name__)

NO_SUCH_OBJECT = 0x06020000  # SDO abort: object does not exist in the object dictionary

_LIVE = {0x6041, 0x6061, 0x6062, 0x6064, 0x606C, 0x60F4, 0x603F, 0x1001, 0x60FD, *PROBE_OBJECTS}


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


class SimDrive(StateMachineMixin, CyclicMixin, HomingMixin, TouchProbeMixin, VelocityMixin,
               FaultInjectionMixin):
    """One simulated drive. Attach it to a ``canopen.Network``; call :meth:`tick` every few ms."""

    def __init__(self, node_id: int, eds: str | Path = SHIPPED_EDS, *, lag_s: float = 0.002,
                 order: int = 1, damping: float = 0.8, boot_delay_s: float = 0.0,
                 home_switch_counts: int = 0, rpdo_timeout_syncs: int = 0,
                 negative_limit_counts: int | None = None, positive_limit_counts: int | None = None,
                 home_switch_window_counts: int = 0, probe_trip_counts: int | None = None,
                 probe_active_below: bool = True, inertia_acceleration: float | None = None,
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
        # the touch probe input (0x60B8-0x60BD), by the actual position in counts; None: not wired
        self.probe_trip_counts = probe_trip_counts
        self.probe_active_below = probe_active_below
        self._probe_reset()
        # velocity modes (a spindle): the acceleration the motor's load allows, counts/s^2 (None: any)
        self.inertia_acceleration = inertia_acceleration
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
        self._homing_interrupted = False
        self._homing_v = 0.0  # counts/s of the last homing step (an interrupt ramps down from it)
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
            self._probe_reset()
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
            before = self.actual
            if self._last_tick is not None and self.state == State.OPERATION_ENABLED \
                    and self.mode == cia402.MODE_HOMING:
                self._homing_step(now - self._last_tick)  # homing runs on the drive's own clock
            elif (self._last_tick is not None
                  and self.state in (State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE)
                  and (self._last_sync is None or now - self._last_sync > 3 * (self._period or 0.01))):
                self._decelerate(now - self._last_tick)  # no SYNC: the stop ramp runs on its own clock
            self._probe_sample(before)
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
            if index == 0x606C:
                return round(self.velocity) if self.in_velocity_mode else 0
            if index == 0x60F4:
                return round(self.demand - self.actual)
            if index == 0x603F:
                return self.error_code
            if index == 0x60FD:
                return self.digital_inputs()
            if index in PROBE_OBJECTS:
                return self._probe_read(index)
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
            elif index == TOUCH_PROBE_FUNCTION:
                self._probe_function(struct.unpack_from("<H", data)[0])
            elif index == 0x607A:
                self._pending_target = struct.unpack_from("<i", data)[0]
            elif index == 0x60FF:
                self._set_target_velocity(struct.unpack_from("<i", data)[0])
            elif index == 0x6060:
                mode = struct.unpack_from("<b", data)[0]
                if mode not in (cia402.MODE_CSP, cia402.MODE_HOMING, *VELOCITY_MODES):
                    raise SdoAbortedError(0x06090030)  # value range exceeded
                if mode != self.mode:
                    # as drives do on a mode change: the demand starts where the motor is (no jump,
                    # and a homing travel cut short stops where it is)
                    self.demand = self.actual
                    self.target = round(self.actual)
                    self._pending_target = None
                    self._pending_velocity = None
                    self._target_velocity = 0
                    self.velocity = 0.0
                self.mode = mode
                self._homing = False
            elif index == SIM_INJECT and subindex == SIM_INJECT_CODE:
                self._injected_by_sdo(struct.unpack_from("<H", data)[0])
            elif index == SIM_INJECT and subindex == SIM_QUICK_STOP_INPUT:
                self.set_quick_stop_input(bool(data[0]))
            elif index == SIM_INJECT and subindex == SIM_WARNING:
                self.send_warning(struct.unpack_from("<H", data)[0])
            else:
                self._params_dirty = True
            self._event_tpdos()
