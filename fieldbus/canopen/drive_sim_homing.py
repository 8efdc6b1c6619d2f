"""Homing mode (6) of the simulated drive (:mod:`fieldbus.canopen.drive_sim`), run on the drive's own
clock from :meth:`~fieldbus.canopen.drive_sim.SimDrive.tick`."""

from __future__ import annotations

import math

from fieldbus.canopen.drive_sim_cia402 import DI_HOME


class HomingMixin:
    """Homing of :class:`~fieldbus.canopen.drive_sim.SimDrive` (its state lives there)."""

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
