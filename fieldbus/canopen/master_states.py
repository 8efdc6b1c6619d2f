"""The master driving the CiA 402 state machine of its drives by SDO: enable (a setpoint every SYNC from
the enable command on), disable, fault reset, homing, and the parking of every drive at shutdown."""

from __future__ import annotations

import contextlib
import logging
import math
import time

import can

from fieldbus.canopen import cia402
from fieldbus.canopen.cia402 import State
from fieldbus.canopen.config import HOLDING_QUICK_STOP_OPTIONS
from fieldbus.canopen.master_records import (
    NEGATIVE_LIMIT,
    NO_SUCH_OBJECT,
    POSITIVE_LIMIT,
    CanopenError,
    DriveBook,
    MasterCore,
)

log = logging.getLogger(__name__)


class StateMachineMixin(MasterCore):
    """Enable, disable, reset, homing and shutdown, part of
    :class:`~fieldbus.canopen.master.CanopenMaster`."""

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
            self._streaming_off()
        try:
            for d in self.drives:
                self._enable_drive(d)
                self._fault_during_enable()
            self._enable_spindle()
            self._fault_during_enable()
        except CanopenError:
            with self._lock:
                self._quick_stop_drives([d for d in self.drives if d.active])
            raise
        with self._lock:
            now = time.monotonic()
            for d in self.drives:
                d.heartbeat_at = max(d.heartbeat_at, now)
            self.streaming = True

    def _fault_during_enable(self, d: DriveBook | None = None) -> None:
        if self.fault is not None:
            raise CanopenError(f"fault while enabling: {self.fault}")
        if d is not None and d.last_emcy is not None and d.last_emcy_at >= d.enable_started:
            e = d.last_emcy
            raise CanopenError(f"{d.describe()}: EMCY 0x{e.code:04X} {e.get_desc() or ''}".rstrip()
                               + " while enabling")

    def _wait_state(self, d: DriveBook, want: State, timeout: float, doing: str,
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

    def _activate(self, d: DriveBook) -> None:
        """From now on the cycle sends ``d`` a target every SYNC: its actual position (read by SDO),
        held until the machine streams. Called just before the enable command reaches the drive.

        The first target goes out here, at once: the cycle sends its RPDOs right after a SYNC, for the
        next one, so the SYNC after the enable command would otherwise find none (the cycle's RPDOs of
        that period went out before the drive was active)."""
        actual = self._sdo(d, "position actual", 0x6064, 0, "i")
        self._arm_limits(d)  # on a switch: it may move off
        with self._lock:
            d.target = d.actual = actual
            d.controlword = cia402.CW_ENABLE_OPERATION
            d.enabled_at = math.inf
            d.active_at = d.feedback_at = time.monotonic()
            d.active = True
            if self.network is not None and not d.homing:
                try:
                    self._hold_now([(d.rpdo_id, d.cyclic_rpdo())])  # and into every buffered set
                except (can.CanError, OSError) as exc:
                    raise CanopenError(f"{d.describe()}: its first target not sent: {exc}") from None

    def _enable_drive(self, d: DriveBook) -> None:
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
                self._fault_during_enable(d)  # its EMCY, when one came since the enable began
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
            self._streaming_off()
            self._quick_stop_drives([d for d in self.drives if d.active])
        for d in [*self.drives, *self._spindle_books()]:
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
            for d in [*self.drives, *self._spindle_books()]:
                age = now - d.heartbeat_at
                if age > conf.heartbeat_consumer_ms / 1000.0:
                    raise CanopenError(f"{d.describe()}: no heartbeat for {1000 * age:.0f} ms (consumer time "
                                       f"{conf.heartbeat_consumer_ms} ms): not reset while it is missing "
                                       "(drive off, cable, node id?)")
        with self._lock:
            self.streaming = False
        for d in [*self.drives, *self._spindle_books()]:
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
            # homing's controlword goes by SDO: no buffered cyclic one may clear its start bit
            self._unbuffer([d.rpdo_id])
        try:
            self._home_cia402(d)
        except CanopenError:
            # never leave the drive homing on its own while the master streams to it later
            with contextlib.suppress(CanopenError):
                self._back_to_csp(d)
            raise
        finally:
            with self._lock:
                d.homing = False  # streamed to again already (_stream_again), unless that failed
                d.feedback_at = time.monotonic()
        return d.scale.to_units(d.target)

    def _home_cia402(self, d: DriveBook) -> None:
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
        self._arm_limits(d)
        with self._lock:
            d.scale.drive_zero_is_home()
        self._sdo(d, "controlword", 0x6040, 0, "H", cia402.CW_ENABLE_OPERATION)
        self._stream_again(d, actual)
        self._set_mode(d, cia402.MODE_CSP)
        self._stream_again(d, actual)  # again in CSP: a drive that drops a target on the mode change

    def _arm_limits(self, d: DriveBook) -> None:
        """At enable and after homing: the limit switches active where the drive stands (read by SDO)
        count as armed (it may move off them), since homing on a limit switch (methods 17/18) ends on
        its edge with it active. The cycle's check arms them from the TPDOs while homing too, but only
        if it ran between the drive's arrival and the homing's end: a cycle held off that long (a busy
        PC) would take the switch the drive homed on for one that became active while driven."""
        inputs = self._sdo(d, "digital inputs", 0x60FD, 0, "I") if d.has_inputs else 0
        with self._lock:
            d.inputs = inputs
            d.limits_armed = inputs & (NEGATIVE_LIMIT | POSITIVE_LIMIT)

    def _stream_again(self, d: DriveBook, actual: int) -> None:
        """Before a drive goes back to cyclic synchronous position: the cycle sends it ``actual`` as its
        target from now on (and, with the SYNC process, in every set already buffered), so the first
        SYNC it sees in CSP finds a target (switched first, a SYNC while the mode's SDOs go back and
        forth would find none). The target in an RPDO is ignored in homing mode, and its controlword
        is the 0x000F just written. Called again once the drive shows CSP: a drive that drops its
        pending target on the mode change (as the simulated one does, starting from where the motor
        is) gets it again; a SYNC between the mode's write and that still finds none, and the drive
        holds where it stands, as CiA 402 drives do on entering CSP."""
        with self._lock:
            d.target = d.actual = actual
            d.homing = False
            d.feedback_at = time.monotonic()
            if d.active and self.network is not None:
                with contextlib.suppress(can.CanError, OSError):
                    self._hold_now([(d.rpdo_id, d.cyclic_rpdo())])

    def _back_to_csp(self, d: DriveBook) -> None:
        """A drive left in another mode (a homing that failed or was cut short): stop that motion
        (homing start bit cleared), hold where it stands, back to cyclic synchronous position."""
        if cia402.decode(self._statusword(d)) == State.OPERATION_ENABLED:
            self._sdo(d, "controlword (stop homing)", 0x6040, 0, "H", cia402.CW_ENABLE_OPERATION)
            self._wait_homing_stopped(d)
        actual = self._sdo(d, "position actual", 0x6064, 0, "i")
        self._arm_limits(d)
        self._stream_again(d, actual)
        self._set_mode(d, cia402.MODE_CSP)
        self._stream_again(d, actual)
        log.info("%s back in cyclic synchronous position mode", d.describe())

    def _wait_homing_stopped(self, d: DriveBook) -> None:
        """After the homing start bit went 1 -> 0: until the drive shows the homing interrupted and
        at standstill (statusword bit 10, CiA 402's "interrupted" or "error, velocity 0"), so the
        position read next is where it holds; a drive still decelerating would otherwise be streamed a
        target behind it and jump back on entering CSP. Not seen within ``state_timeout_s``: a
        warning, and the position read as it is."""
        deadline = time.monotonic() + self.config.state_timeout_s
        while True:
            sw = self._statusword(d)
            if sw & cia402.SW_TARGET_REACHED or cia402.decode(sw) != State.OPERATION_ENABLED:
                return
            if time.monotonic() > deadline:
                log.warning("%s: homing stopped but no standstill shown within %g s (statusword "
                            "0x%04X)", d.describe(), self.config.state_timeout_s, sw)
                return
            time.sleep(0.002)

    def _set_mode(self, d: DriveBook, mode: int) -> None:
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
        canon exits.

        The kernel's SYNC (if it times the SYNC) stops first, as the master's own stops with its cycle:
        the drives are parked by SDO in either case, and no SYNC outlives the master."""
        if self.network is None:
            return
        self._stop_kernel_sync()
        self._stop_outputs()  # type: ignore[attr-defined]  (OutputsMixin)
        with self._lock:
            if any(d.active for d in [*self.drives, *self._spindle_books()]):
                self._quick_stop_locked()
        for d in [*self.drives, *self._spindle_books()]:
            try:
                self._park(d)
            except (CanopenError, can.CanError, OSError) as exc:
                log.error("at shutdown, %s not parked: %s", d.describe(), exc)
        if self._heartbeat_task is not None:
            self._heartbeat_task.stop()
            self._heartbeat_task = None
        try:
            for d in [*self.drives, *self._spindle_books()]:
                d.node.nmt.send_command(0x80)  # pre-operational: PDOs stop
        except (can.CanError, OSError):
            pass
        net, self.network = self.network, None
        self._release(net)

    def _park(self, d: DriveBook, consumer_off: bool = True) -> None:
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
            self._sdo(d, "consumer heartbeat time (off)", 0x1016, 1, "I", 0, ok_aborts=NO_SUCH_OBJECT)
        with self._lock:
            d.statusword = self._statusword(d)

