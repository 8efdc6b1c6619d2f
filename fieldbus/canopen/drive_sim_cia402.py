"""The CiA 402 side of the simulated drive (:mod:`fieldbus.canopen.drive_sim`): statusword, digital
inputs, the controlword's transitions, faults, and the cyclic synchronous position motion of one SYNC
period (servo lag, following error, the quick stop and fault reaction ramps).
"""

from __future__ import annotations

import logging
import math

from fieldbus.canopen import cia402
from fieldbus.canopen.cia402 import Command, State

log = logging.getLogger("fieldbus.canopen.drive_sim")

NMT_INITIALISING, NMT_STOPPED, NMT_OPERATIONAL, NMT_PRE_OPERATIONAL = 0, 4, 5, 127

EMCY_VELOCITY = 0x8400  # setpoint jump beyond the maximum velocity
EMCY_FOLLOWING_ERROR = 0x8611
EMCY_HEARTBEAT = 0x8130  # life guard / heartbeat consumer timeout
EMCY_GENERIC = 0x1000
EMCY_RPDO_TIMEOUT = 0x8250  # RPDO deadline monitoring (CiA 301: "RPDO timeout")

#: 0x60FD bits (CiA 402)
DI_NEGATIVE_LIMIT, DI_POSITIVE_LIMIT, DI_HOME, DI_INTERLOCK = 0x1, 0x2, 0x4, 0x8


class StateMachineMixin:
    """The drive's CiA 402 state machine and CSP motion (its state lives in
    :class:`~fieldbus.canopen.drive_sim.SimDrive`)."""

    def statusword(self) -> int:
        extra = 0
        if self.state == State.OPERATION_ENABLED:
            if self.mode == cia402.MODE_CSP:
                extra |= cia402.SW_BIT12
                if self._window != 0xFFFFFFFF and abs(self.demand - self.actual) > self._window:
                    extra |= cia402.SW_BIT13
            elif self.mode == cia402.MODE_HOMING and not self._homing:
                # bits 13, 12, 10 as CiA 402 says for a homing that is over (this drive stops at once):
                # 0 1 1 attained, 1 0 1 error at standstill, 0 0 1 interrupted or not started;
                # 0 0 0 while it runs
                extra |= cia402.SW_TARGET_REACHED
                if self._homing_attained:
                    extra |= cia402.SW_BIT12
                if self._homing_error:
                    extra |= cia402.SW_BIT13
            elif self.in_velocity_mode:
                extra |= self._velocity_statusword()
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

    def digital_outputs(self) -> int:
        """0x60FE:01 as the master last wrote it (the physical outputs; 0 before any write), masked by
        0x60FE:02 (a bit outside the mask is not driven, as CiA 402 has it)."""
        store = self.node.data_store.get(0x60FE, {})
        word, mask = (int.from_bytes(store.get(sub, b"\0"), "little") for sub in (1, 2))
        return word & mask

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
            elif self.mode == cia402.MODE_HOMING and previous & cia402.CW_HOMING_START \
                    and not cw & cia402.CW_HOMING_START and self._homing:
                # start bit 1 -> 0: the homing is interrupted; the drive ramps down at the homing
                # acceleration (0x609A), as drives do, and shows it stopped (bit 10) at standstill
                self._homing_interrupted = True
        elif (s == State.QUICK_STOP_ACTIVE and cmd == Command.ENABLE_OPERATION
              and (self.velocity == 0 or self.reenable_during_quick_stop_ramp)
              and self._qs_option in (5, 6, 7, 8)):
            self._enable()

    def _enable(self) -> None:
        # As drives do: the demand starts where the motor is, so enabling never jumps. A target received
        # since the last SYNC stays for the next one: a drive's 0x607A keeps the last RPDO's value, and
        # a master that sends its RPDOs right after a SYNC (for the next one) may enable the drive
        # after them, before that SYNC (that SYNC did not go without a setpoint).
        if self.quick_stop_input:
            return  # the input holds the drive in its stop
        self.enables += 1
        self._syncs_without_target = 0
        self.state = State.OPERATION_ENABLED
        self.demand = self.actual
        self.target = round(self.actual)
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

    def _step(self, dt: float) -> None:
        s = self.state
        new = self._pending_target
        self._pending_target = None
        if s == State.OPERATION_ENABLED and self.in_velocity_mode:
            self._velocity_step(dt)
        elif s == State.OPERATION_ENABLED and self.mode == cia402.MODE_CSP:
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
        if self.in_velocity_mode:
            self._velocity_stop(dt)
            return
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
