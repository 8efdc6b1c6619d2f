"""Velocity modes of the simulated drive (:mod:`fieldbus.canopen.drive_sim`): the spindle drive.

* Profile velocity (3): a target velocity (0x60FF, counts/s) takes effect on receipt; the drive ramps
  to it at its profile acceleration / deceleration (0x6083 / 0x6084, counts/s^2).
* Cyclic synchronous velocity (9): the target velocity is latched at the next SYNC (as CSP's
  target); the master ramps it, the drive follows.

In both, the motor and its load have inertia: the velocity changes by at most ``inertia_acceleration``
(counts/s^2; None: no limit beyond the mode's) per second, so a spindle with a heavy chuck lags the
commanded ramp, which spindle-synchronized motion must follow. The velocity actual (0x606C) is the
velocity reached; the position actual (0x6064) its integral (it wraps at 32 bits as a real encoder's
count does). Statusword: bit 10 target reached (the velocity is within ``at_speed_window`` counts/s of
the target), bit 12 speed zero (pv) or following the target (csv). A quick stop or a fault ramps down
at 0x6085 (the stop of :class:`~fieldbus.canopen.drive_sim_cia402.StateMachineMixin`).
"""

from __future__ import annotations

import math
from typing import Any

from fieldbus.canopen import cia402
from fieldbus.canopen.cia402 import State
from fieldbus.canopen.config import SpindleDriveConfig

MODE_PV = 3
MODE_CSV = 9
VELOCITY_MODES = (MODE_PV, MODE_CSV)


class VelocityMixin:
    """Profile and cyclic synchronous velocity of :class:`~fieldbus.canopen.drive_sim.SimDrive` (its
    state lives there)."""

    #: counts/s^2 the motor and load allow (None: no limit of their own)
    inertia_acceleration: float | None = None
    #: |velocity - target| below this is "target reached" (counts/s)
    at_speed_window: float = 1.0
    _target_velocity = 0
    _pending_velocity: int | None = None

    def _set_target_velocity(self, value: int) -> None:
        """0x60FF written (SDO or RPDO): at once in pv, at the next SYNC in csv."""
        if self.mode == MODE_CSV:
            self._pending_velocity = value
        else:
            self._target_velocity = value

    def _velocity_statusword(self) -> int:
        extra = 0
        if abs(self.velocity - self._target_velocity) <= self.at_speed_window:
            extra |= cia402.SW_TARGET_REACHED
        if self.mode == MODE_CSV:
            extra |= cia402.SW_BIT12
        elif abs(self.velocity) < self.at_speed_window:
            extra |= cia402.SW_BIT12  # pv: speed zero
        return extra

    def _velocity_step(self, dt: float) -> None:
        """One period in Operation enabled, velocity mode: toward the target within the limits."""
        if self._pending_velocity is not None:
            self._target_velocity = self._pending_velocity
            self._pending_velocity = None
        v, want = self.velocity, float(self._target_velocity)
        limit = math.inf
        if self.mode == MODE_PV:
            speeding_up = abs(want) > abs(v) and want * v >= 0
            limit = max(1, self._value(0x6083 if speeding_up else 0x6084))
        if self.inertia_acceleration is not None:
            limit = min(limit, self.inertia_acceleration)
        dv = want - v
        if abs(dv) > limit * dt:
            dv = math.copysign(limit * dt, dv)
        self._advance(v, v + dv, dt)

    def _advance(self, v0: float, v1: float, dt: float) -> None:
        self.velocity = v1
        self.actual += 0.5 * (v0 + v1) * dt
        if not -(2**31) <= self.actual < 2**31:  # the encoder count wraps (INTEGER32)
            self.actual = (self.actual + 2**31) % 2**32 - 2**31
        self.demand = self.actual
        self.target = round(self.actual)

    def _velocity_stop(self, dt: float) -> None:
        """Quick stop or fault reaction in a velocity mode: down at 0x6085 (and the inertia)."""
        v = self.velocity
        dv = self._qs_decel * dt
        if self.inertia_acceleration is not None:
            dv = min(dv, self.inertia_acceleration * dt)
        v1 = 0.0 if abs(v) <= dv else v - math.copysign(dv, v)
        self._advance(v, v1, dt)
        self._target_velocity = 0
        if v1 == 0.0:
            if self.state == State.FAULT_REACTION_ACTIVE:
                self.state = State.FAULT
            elif self.state == State.QUICK_STOP_ACTIVE and self._qs_option in (1, 2):
                self.state = State.SWITCH_ON_DISABLED

    @property
    def in_velocity_mode(self) -> bool:
        return self.mode in VELOCITY_MODES


def sim_spindle(cfg: SpindleDriveConfig, **kw: Any) -> Any:
    """The simulated spindle drive of ``[canopen.spindle]``: its inertia from ``sim_acceleration``
    (rpm/s; else ``acceleration``)."""
    from fieldbus.canopen.drive_sim import SimDrive

    rpm_s = cfg.sim_acceleration if cfg.sim_acceleration is not None else cfg.acceleration
    return SimDrive(cfg.node_id, cfg.eds_path, inertia_acceleration=rpm_s * cfg.counts_per_revolution / 60.0,
                    **kw)
