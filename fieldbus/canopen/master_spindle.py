"""The spindle as a CiA 402 drive on the master's bus (``[canopen.spindle]``), part of
:class:`~fieldbus.canopen.master.CanopenMaster`.

The spindle drive runs in profile velocity (3) or cyclic synchronous velocity (9) mode. Its PDOs:

* RPDO1 = controlword + target velocity (0x60FF, counts/s), sent every cycle (for the next SYNC)
  while it is enabled. In ``csv`` the master ramps the target at ``acceleration`` (the drive follows
  each SYNC's); in ``pv`` the target is the commanded speed and the drive ramps at 0x6083 / 0x6084.
* TPDO1 = statusword + velocity actual (0x606C), TPDO2 = position actual (0x6064), both every SYNC: the
  measured speed and the spindle's revolutions, counted across the 32-bit wrap of the encoder count
  (what spindle-synchronized motion follows).

Boot, enable, quick stop, fault reset, disable and shutdown treat it as the axes' drives are treated
(NMT reset, identity, supported mode 0x6502, canon's own objects, heartbeats, NMT start; enable by SDO
with the cyclic RPDO from the enable command on; quick stop option 2). It is supervised every cycle:
heartbeat, TPDO age, state (a spindle drive that leaves Operation enabled stops the machine), EMCY.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import can
import canopen

from fieldbus.canopen import cia402
from fieldbus.canopen.cia402 import State
from fieldbus.canopen.config import SpindleDriveConfig
from fieldbus.canopen.master_records import NO_SUCH_OBJECT, CanopenError, MasterCore
from fieldbus.canopen.pdo import (
    CONTROLWORD,
    POSITION_ACTUAL,
    STATUSWORD,
    TARGET_VELOCITY,
    VELOCITY_ACTUAL,
    Pdo,
    PdoLayout,
)

log = logging.getLogger(__name__)

#: the spindle drive's PDOs (module docstring)
SPINDLE_LAYOUT = PdoLayout("spindle", (Pdo(False, 1, (CONTROLWORD, TARGET_VELOCITY)),),
                           (Pdo(True, 1, (STATUSWORD, VELOCITY_ACTUAL)), Pdo(True, 2, (POSITION_ACTUAL,))),
                           1, 0)
#: a lost position TPDO is told from the position's advance only when the spindle turns at least this
#: many counts per SYNC (below, a count of quantization is too large a part of the advance)
LOSS_MIN_COUNTS = 4.0
#: at most this many SYNCs are counted between two position TPDOs (lost frames told by the advance)
LOSS_MAX_SYNCS = 50
#: quick stop option of the spindle drive: ramp down, then Switch on disabled (the cyclic controlword
#: 0x0F cannot re-enable it, as for the axes in the standard layout)
SPINDLE_QUICK_STOP_OPTION = 2


@dataclass(frozen=True)
class SpindleFeedback:
    """What the spindle drive last reported: measured speed (rpm, M3 positive), revolutions since boot
    (M3 counts up), its state, the speed commanded to it (rpm; in csv, the ramped target), when its
    position came (monotonic) and which SYNC it answered.

    The SYNC: the drive sends one position TPDO per SYNC from NMT start on, so the n-th one after the
    NMT start answers the n-th SYNC the master sent after it: a TPDO the bus reader hands on late (a
    loaded PC) is still dated right. A TPDO lost on the bus (CAN retransmits a frame that was not
    acknowledged: an overrun controller or a bus error loses one) is told by the position's advance
    against the measured speed (:meth:`SpindleBook.syncs_between`), so the later ones keep their
    SYNC; at a speed too low to tell, a lost one dates the later ones a SYNC early until one is told."""

    rpm: float
    revolutions: float
    state: State
    commanded_rpm: float
    at: float
    #: the master's SYNC (its cycle count) the position and speed were measured at
    sync: int = 0
    #: the change of the measured speed from the SYNC before (rpm/s)
    acceleration: float = 0.0


class SpindleBook:
    """The master's book-keeping of the spindle drive (the axes' :class:`DriveBook` counterpart; the
    boot, enable and park code that takes a drive takes this too)."""

    def __init__(self, cfg: SpindleDriveConfig, node: canopen.RemoteNode,
                 syncs: Callable[[], int] = lambda: 0) -> None:
        self.cfg = cfg
        self.node = node
        self.syncs = syncs  # the master's SYNCs sent so far
        self.sync_base: int | None = None  # SYNCs sent at its NMT start (None: not started)
        self.cycle_s = 0.002  # the SYNC period (the master's cycle)
        self._vel = (0, 0.0)  # velocity actual 0x606C (counts/s), its change from the SYNC before (/s)
        rpdo = SPINDLE_LAYOUT.rpdos[0]
        self.rpdo_id = rpdo.cob_id(cfg.node_id)
        self.rpdo_struct = rpdo.struct
        self.controlword = cia402.CW_ENABLE_OPERATION
        self.commanded_rpm = 0.0  # what the machine asks (signed, M3 positive)
        self.ramp_rpm = 0.0  # csv: the target sent this cycle, ramped toward commanded_rpm
        self.statusword = 0
        self.position: int | None = None  # counts, 0x6064 as last received
        self._pos = (0, 0, 0.0)  # counts since boot (unwrapped), the SYNC they answer, when they came
        self._restarted = False
        self.feedback_at = 0.0
        self.heartbeat_at = 0.0
        self.nmt_state = -1
        self.enabled_at = math.inf
        self.active_at = 0.0
        self.active = False
        self.homing = False
        self.enable_started = 0.0
        self.last_emcy_at = 0.0
        self.last_emcy: canopen.emcy.EmcyError | None = None
        self.booted = threading.Event()
        self.missing: dict[int, int] = {}
        self.qs_option = SPINDLE_QUICK_STOP_OPTION
        self.has_inputs = False
        self.sdo_lock = threading.Lock()  # one SDO transfer at a time (as DriveBook's)

    def describe(self) -> str:
        return f"node {self.cfg.node_id} (spindle)"

    def target_counts(self) -> int:
        return round(self.cfg.counts_per_s(self.ramp_rpm))

    def rpdo(self, controlword: int | None = None) -> bytes:
        return self.rpdo_struct.pack(self.controlword if controlword is None else controlword,
                                     self.target_counts())

    def on_tpdo(self, cob_id: int, data: bytearray, timestamp: float) -> None:
        """Reader thread: TPDO1 (statusword, velocity) or TPDO2 (position, unwrapped). Each frame's
        values are replaced as one tuple: the cycle thread never reads a position with another
        SYNC's date."""
        base = cob_id - self.cfg.node_id
        if base == 0x180 and len(data) >= 6:
            sw, velocity = SPINDLE_LAYOUT.tpdos[0].struct.unpack_from(data)
            self.statusword = sw
            self._vel = (velocity, (velocity - self._vel[0]) / self.cycle_s)
        elif base == 0x280 and len(data) >= 4:
            (pos,) = SPINDLE_LAYOUT.tpdos[1].struct.unpack_from(data)
            counts, sync, _at = self._pos
            step = 0 if self.position is None else (pos - self.position + 2**31) % 2**32 - 2**31
            counts = pos if self.position is None else counts + step
            first, self._restarted = self.position is None or self._restarted, False
            self.position = pos
            if self.sync_base is None:
                sync = self.syncs()
            else:  # never a SYNC not sent yet (the kernel's SYNC may be one ahead of the count)
                sync = min(max(sync, self.sync_base) + (1 if first else self.syncs_between(step)),
                           self.syncs() + 1)
            now = time.monotonic()
            self._pos = (counts, sync, now)
            self.feedback_at = now

    def syncs_between(self, step: int) -> int:
        """SYNCs between the last position TPDO and this one, whose position advanced ``step`` counts:
        one, or more when TPDOs were lost between (the advance a multiple of the measured speed's per
        SYNC; told when that is :data:`LOSS_MIN_COUNTS` or more)."""
        per_sync = self._vel[0] * self.cycle_s
        if abs(per_sync) < LOSS_MIN_COUNTS:
            return 1
        return max(1, min(LOSS_MAX_SYNCS, round(step / per_sync)))

    @property
    def velocity(self) -> int:
        return self._vel[0]

    @property
    def counts(self) -> int:
        return self._pos[0]

    @property
    def sync(self) -> int:
        return self._pos[1]

    def restart_count(self, base: int | None) -> None:
        """The SYNCs its TPDOs answer count from ``base`` (its NMT start; None: not started)."""
        self.sync_base = base
        self._pos = (self._pos[0], 0, self._pos[2])
        self._restarted = True  # its next position answers the first SYNC after base

    def feedback(self) -> SpindleFeedback:
        cfg = self.cfg
        counts, sync, at = self._pos
        velocity, accel = self._vel
        return SpindleFeedback(cfg.rpm(velocity), counts * cfg.direction / cfg.counts_per_revolution,
                               cia402.decode(self.statusword), self.ramp_rpm, at, sync, cfg.rpm(accel))


class SpindleMixin(MasterCore):
    """The spindle drive's part of the master (module docstring)."""

    spindle: SpindleBook | None

    # ------------------------------------------------------------------ set-up and boot
    def _open_spindle(self, net: canopen.Network) -> None:
        cfg = self.config.spindle
        if cfg is None:
            return
        node = canopen.RemoteNode(cfg.node_id, cfg.eds_path)
        node.sdo.RESPONSE_TIMEOUT = self.config.sdo_timeout_s
        node.sdo.MAX_RETRIES = 2
        net.add_node(node)
        sb = SpindleBook(cfg, node, lambda: self.cycles)
        sb.cycle_s = self.config.cycle_s
        self.spindle = sb
        node.nmt.add_heartbeat_callback(lambda state: self._on_heartbeat(sb, state))
        node.emcy.add_callback(lambda entry: self._on_emcy(sb, entry))
        for p in SPINDLE_LAYOUT.tpdos:
            net.subscribe(p.cob_id(cfg.node_id), sb.on_tpdo)

    def _boot_spindle(self) -> None:
        sb = self.spindle
        if sb is None:
            return
        cfg, conf = sb.cfg, self.config
        sb.booted.clear()
        sb.restart_count(None)
        sb.node.nmt.send_command(0x82)
        if not sb.booted.wait(conf.boot_timeout_s):
            raise CanopenError(f"{sb.describe()}: no boot-up message within {conf.boot_timeout_s:g} s after "
                               "NMT reset communication (drive off, wrong node id or bitrate?)")
        sdo = self._sdo
        for sub, name, want in ((1, "vendor id", cfg.vendor_id), (2, "product code", cfg.product_code)):
            if want is not None and (got := sdo(sb, f"identity {name}", 0x1018, sub, "I")) != want:
                raise CanopenError(f"{sb.describe()}: identity 0x1018:{sub:02X} {name} is 0x{got:08X}, "
                                   f"canopen.spindle expects 0x{want:08X} (wrong drive on this node id?)")
        modes = self._read_optional(sb, "supported drive modes", 0x6502, 0, "I")
        mode = cfg.mode_number
        if modes is not None and not modes & (1 << (mode - 1)):
            raise CanopenError(f"{sb.describe()}: canopen.spindle.mode = \"{cfg.mode}\" (mode {mode}), but "
                               f"the drive's 0x6502 supported drive modes is 0x{modes:08X}, "
                               f"bit {mode - 1} clear")
        cpr = cfg.counts_per_revolution
        cycle_us = round(conf.cycle_s * 1e6)
        steps: list[tuple[str, int, int, str, int]] = [
            ("modes of operation", 0x6060, 0, "b", mode),
            ("communication cycle period", 0x1006, 0, "I", cycle_us),
            ("quick stop option", 0x605A, 0, "h", SPINDLE_QUICK_STOP_OPTION),
            ("quick stop deceleration", 0x6085, 0, "I", math.ceil(cfg.quick_stop_deceleration * cpr / 60.0)),
        ]
        if cfg.mode == "pv":
            acc = math.ceil(cfg.acceleration * cpr / 60.0)
            steps += [("profile acceleration", 0x6083, 0, "I", acc),
                      ("profile deceleration", 0x6084, 0, "I", acc)]
        steps += SPINDLE_LAYOUT.sdo_steps(cfg.node_id)
        steps += [("producer heartbeat time", 0x1017, 0, "H", conf.heartbeat_producer_ms),
                  ("consumer heartbeat time", 0x1016, 1, "I", (conf.master_node_id << 16)
                   | (conf.heartbeat_consumer_ms if conf.heartbeat_producer_ms else 0))]
        for p in SPINDLE_LAYOUT.unused_pdos():
            sdo(sb, f"{p.name} COB-ID (disable)", p.comm_index, 1, "I", 0x80000000 | p.cob_id(cfg.node_id),
                ok_aborts=NO_SUCH_OBJECT)
        for what, index, sub, fmt, value in steps:
            sdo(sb, what, index, sub, fmt, value)
        shown = sdo(sb, "modes of operation display", 0x6061, 0, "b")
        if shown != mode:
            raise CanopenError(f"{sb.describe()}: modes of operation display is {shown}, not {mode} "
                               f"({cfg.mode}) after writing 0x6060 = {mode}")
        with self._lock:  # the SYNCs its TPDOs answer count from here (no SYNC goes out in between)
            sb.restart_count(self.cycles)
            sb.node.nmt.send_command(0x01)
        deadline = time.monotonic() + conf.boot_timeout_s
        while sb.nmt_state != 5:
            if time.monotonic() > deadline:
                raise CanopenError(f"{sb.describe()}: did not report NMT Operational within "
                                   f"{conf.boot_timeout_s:g} s after NMT start")
            time.sleep(0.002)
        sb.heartbeat_at = time.monotonic()

    # ------------------------------------------------------------------ enable
    def _enable_spindle(self) -> None:
        """Walk the spindle drive to Operation enabled at speed 0 (by SDO; the cyclic RPDO from the
        enable command on)."""
        sb = self.spindle
        if sb is None:
            return
        timeout = self.config.state_timeout_s
        sdo = self._sdo
        sb.enable_started = time.monotonic()
        if sdo(sb, "modes of operation display", 0x6061, 0, "b") != sb.cfg.mode_number:
            sdo(sb, "modes of operation", 0x6060, 0, "b", sb.cfg.mode_number)
        for _ in range(8):
            self._fault_during_enable(sb)
            state = cia402.decode(self._statusword(sb))
            if state == State.OPERATION_ENABLED:
                self._activate_spindle(sb)
                break
            if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                raise CanopenError(f"{sb.describe()}: in '{state}': reset_faults() first")
            if state == State.QUICK_STOP_ACTIVE:
                self._wait_state(sb, State.SWITCH_ON_DISABLED, timeout, "its quick stop",
                                 enabling=True)
                continue
            step = cia402.next_step(state)
            if step is None:
                raise CanopenError(f"{sb.describe()}: stuck in '{state}', which no controlword leads out of")
            controlword, want = step
            if want == State.OPERATION_ENABLED:
                self._activate_spindle(sb)
            sdo(sb, "controlword", 0x6040, 0, "H", controlword)
            self._wait_state(sb, want, timeout, f"controlword 0x{controlword:04X}",
                             enabling=True)
        else:
            raise CanopenError(f"{sb.describe()}: did not reach Operation enabled")
        with self._lock:
            sb.statusword = cia402.statusword_for(State.OPERATION_ENABLED)
            sb.enabled_at = sb.feedback_at = time.monotonic()

    def _activate_spindle(self, sb: SpindleBook) -> None:
        with self._lock:
            if sb.active:
                return
            sb.commanded_rpm = sb.ramp_rpm = 0.0
            sb.controlword = cia402.CW_ENABLE_OPERATION
            sb.enabled_at = math.inf
            sb.active_at = sb.feedback_at = time.monotonic()
            sb.active = True

    # ------------------------------------------------------------------ the cycle
    def set_spindle_speed(self, rpm: float) -> float:
        """The speed the spindle drive is to turn at (rpm, M3 positive, 0 stops), clamped to
        ``max_rpm``; returns what is commanded. Any thread; acted on from the next cycle."""
        sb = self.spindle
        if sb is None:
            return 0.0
        limit = sb.cfg.max_rpm
        sb.commanded_rpm = max(-limit, min(limit, rpm))
        return sb.commanded_rpm

    def spindle_feedback(self) -> SpindleFeedback | None:
        return self.spindle.feedback() if self.spindle is not None else None

    def _spindle_cycle(self, now: float, send: bool = True) -> None:
        """With ``_lock`` held, after the SYNC: supervise the spindle drive, ramp its target (csv),
        send its RPDO."""
        sb = self.spindle
        if sb is None or not sb.active:
            return
        conf = self.config
        hb_age = now - sb.heartbeat_at
        if conf.heartbeat_producer_ms > 0 and hb_age > conf.heartbeat_consumer_ms / 1000.0:
            self.raise_fault(sb.cfg.node_id, f"spindle drive heartbeat missed: none for {1000 * hb_age:.0f} "
                                             f"ms (consumer time {conf.heartbeat_consumer_ms} ms)")
            return
        fb_age = now - max(sb.feedback_at, sb.active_at)
        if fb_age > conf.feedback_timeout_s + conf.cycle_s:
            self.raise_fault(sb.cfg.node_id, f"spindle drive: no TPDO for {1000 * fb_age:.0f} ms "
                                             f"(limit {1000 * conf.feedback_timeout_s:g} ms): frames lost?")
            return
        if sb.feedback_at > sb.enabled_at:
            state = cia402.decode(sb.statusword)
            if state != State.OPERATION_ENABLED:
                self.raise_fault(sb.cfg.node_id, f"spindle drive left Operation enabled: in '{state}' "
                                                 f"(statusword 0x{sb.statusword:04X})")
                return
        if not send:  # the SYNC process's buffer is full: no set this cycle, so no ramp step either
            return
        want = sb.commanded_rpm
        if sb.cfg.mode == "csv":
            step = sb.cfg.acceleration * conf.cycle_s
            sb.ramp_rpm += max(-step, min(step, want - sb.ramp_rpm))
        else:
            sb.ramp_rpm = want
        self._cyclic(sb.rpdo_id, sb.rpdo())

    def _spindle_quick_stop(self) -> tuple[int, bytes] | None:
        """With ``_lock`` held: the spindle drive's quick stop (its own 0x6085 ramp), sent at once on the
        master's socket (an error logged); its frame, for the SYNC process's flush
        (:meth:`~fieldbus.canopen.master_supervision.SupervisionMixin._quick_stop_drives`), or None."""
        sb = self.spindle
        if sb is None:
            return None
        sb.commanded_rpm = sb.ramp_rpm = 0.0
        if not sb.active:
            return None
        sb.active = False
        sb.controlword = cia402.CW_QUICK_STOP
        frame = (sb.rpdo_id, sb.rpdo(cia402.CW_QUICK_STOP))
        try:
            self._send(*frame)
        except (can.CanError, OSError) as exc:
            log.error("quick stop to %s not sent: %s", sb.describe(), exc)
        return frame

    def _spindle_books(self) -> list[SpindleBook]:
        return [self.spindle] if self.spindle is not None else []
