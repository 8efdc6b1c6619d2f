"""The master's supervision: EMCY, heartbeats and TPDOs from the reader thread, the per-cycle checks of
the drives streamed to, faults (the first one stops every drive by quick stop) and warnings."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import can
import canopen

from fieldbus.canopen import cia402
from fieldbus.canopen.cia402 import State
from fieldbus.canopen.master_records import (
    NEGATIVE_LIMIT,
    POSITIVE_LIMIT,
    DriveBook,
    Fault,
    MasterCore,
    input_names,
)
from fieldbus.canopen.pdo import Pdo

log = logging.getLogger(__name__)


class SupervisionMixin(MasterCore):
    """Faults, warnings and the checks of the feedback, part of
    :class:`~fieldbus.canopen.master.CanopenMaster`."""

    def add_warning_listener(self, callback: Callable[[Fault], None]) -> None:
        """Called with each warning (a drive without an optional object, a warning EMCY): something to
        log and show, which does not stop the machine. Any thread; keep it short."""
        self._warning_listeners.append(callback)

    def warn(self, node: int, text: str) -> None:
        """Log and publish a warning about ``node`` (0: the master)."""
        axis = next((d.cfg.axis for d in self.drives if d.cfg.node_id == node), "")
        spindle = getattr(self, "spindle", None)
        if not axis and spindle is not None and spindle.cfg.node_id == node:
            axis = "spindle"
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
    def _on_heartbeat(self, d: DriveBook, state: int) -> None:
        d.heartbeat_at = time.monotonic()
        d.nmt_state = state
        if state == 0:
            d.booted.set()

    def _on_emcy(self, d: DriveBook, entry: canopen.emcy.EmcyError) -> None:
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
    def _tpdo_reader(d: DriveBook, p: Pdo) -> Callable[[int, bytearray, float], None]:
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


    # ------------------------------------------------------------------ faults
    def raise_fault(self, node: int, reason: str) -> None:
        """Record a fault (the first since the last reset is :attr:`fault`) and quick-stop every drive.

        Callable from any thread: the reader thread (EMCY), the cycle, or the daemon (a late cycle).
        """
        axis = next((d.cfg.axis for d in self.drives if d.cfg.node_id == node), "")
        spindle = getattr(self, "spindle", None)
        if not axis and spindle is not None and spindle.cfg.node_id == node:
            axis = "spindle"
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
        self._streaming_off()
        self._quick_stop_drives(self.drives)

    def _quick_stop_drives(self, drives: list[DriveBook]) -> None:
        """With ``_lock`` held: quick stop to the spindle drive and to ``drives``, no longer streamed to.
        Each frame goes out at once on the master's own socket; one that cannot be sent is logged and
        the others still go (a bus error on the first drive must not leave the next one driven). Then
        all of them pass through the SYNC process in one flush, its buffered sets dropped first."""
        frames = []
        spindle = self._spindle_quick_stop()
        if spindle is not None:
            frames.append(spindle)
        for d in drives:
            d.active = False
            d.controlword = cia402.CW_QUICK_STOP
            frames.append(d.controlword_rpdo(cia402.CW_QUICK_STOP))
            try:
                self._send(*frames[-1])
            except (can.CanError, OSError) as exc:
                log.error("quick stop to %s not sent: %s", d.describe(), exc)
        self._stopped(frames)  # and through the SYNC process, its buffered sets dropped

    def _check(self, now: float, active: list[DriveBook]) -> None:
        """The feedback of the drives streamed to, before this cycle's RPDOs: the SYNC first (a stalled
        cycle, or a SYNC that stopped, is the master's fault, not a node's), then per drive its
        heartbeat, its TPDOs since the last SYNC, its state, its following error."""
        conf = self.config
        if self._sync_stalled(now):
            return
        # TPDO ages count to the latest SYNC: the one the master sent, or (kernel SYNC) the last one its
        # bus reader saw, which has read every TPDO sent before it
        last_sync = self._last_sent if self._kernel_sync is None else self._reader_sync_at
        for d in active:
            hb_age = now - d.heartbeat_at
            if conf.heartbeat_producer_ms > 0 and hb_age > conf.heartbeat_consumer_ms / 1000.0:
                self.raise_fault(d.cfg.node_id, f"heartbeat missed: none for {1000 * hb_age:.0f} ms "
                                                f"(consumer time {conf.heartbeat_consumer_ms} ms)")
                return
            # how long before the latest SYNC the drive last answered one (SYNCs, not the clock: a
            # pause of the master's own is not the drive's silence)
            fb_age = last_sync - max(d.feedback_at, self._stream_t0, d.active_at)
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

    def _sync_stalled(self, now: float) -> bool:
        """A fault (True) when the SYNC or the setpoints stopped for ``feedback_timeout_s``: the
        master's SYNC when its cycle stalled; with the kernel's SYNC, the SYNC itself (its task stopped,
        the interface down) or the RPDOs (the cycle stalled while SYNCs were still seen)."""
        limit = self.config.feedback_timeout_s
        gap = now - self._last_sent if self._last_sent else 0.0
        ks = self._kernel_sync
        if ks is None:
            if gap > limit:
                self.raise_fault(0, f"the master sent no SYNC for {1000 * gap:.0f} ms (limit "
                                    f"{1000 * limit:g} ms): its cycle stalled, the drives got no setpoint")
                return True
            return False
        quiet = now - max(self._reader_sync_at, self._stream_t0)
        process = getattr(ks, "timer", None) is not None
        if quiet > limit:
            why = ("the SYNC process stopped (killed?)" if process else
                   "the kernel's periodic SYNC stopped (its task removed, the interface down?)")
            self.raise_fault(0, f"no SYNC on the bus for {1000 * quiet:.0f} ms (limit {1000 * limit:g} ms): "
                                f"{why} or the master's bus reader stalled")
            return True
        # the SYNC went on: one was seen more than the limit after the last setpoints, not merely the
        # clock past it (the bus reader can read the last SYNC before a kill just after the cycle's
        # push: the silence since then is the SYNC's, and the check above names it once it is due)
        if self._last_sent and self._reader_sync_at - self._last_sent > limit:
            self.raise_fault(0, f"the master sent no setpoint for {1000 * gap:.0f} ms (limit "
                                f"{1000 * limit:g} ms) while the {'SYNC process' if process else 'kernel'}'s "
                                "SYNC went on: its cycle stalled, the drives held their last target")
            return True
        return False

    def _limit_fault(self, d: DriveBook, bits: int, why: str) -> None:
        names = " and ".join(input_names(bits))
        self.raise_fault(d.cfg.node_id, f"{names} active (0x60FD = 0x{d.inputs:08X}): {why}; "
                                        "not re-enabled (reset, then move the axis off the switch)")

    def _stopped_itself(self, d: DriveBook, state: State) -> str:
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



class ErrorFrameListener(can.Listener):
    """CAN error frames (bus errors, error passive, bus off on SocketCAN) become a master fault."""

    def __init__(self, master: SupervisionMixin) -> None:
        self.master = master

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame and self.master.streaming:
            self.master.raise_fault(0, f"bus error frame (id 0x{msg.arbitration_id:X}, "
                                       f"data {msg.data.hex()})")

    def on_error(self, exc: Exception) -> None:
        self.master.raise_fault(0, f"bus error: {exc}")
