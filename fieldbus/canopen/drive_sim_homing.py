"""Homing mode (6) of the simulated drive (:mod:`fieldbus.canopen.drive_sim`), run on the drive's own
clock from :meth:`~fieldbus.canopen.drive_sim.SimDrive.tick`.

The homing method (0x6098) decides the direction and where the drive stops, as CiA 402 says, with
the switches the drive has (in counts, at its positions before homing):

* 17 / 18: negative / positive limit switch: travel negative / positive to its edge.
* 19, 20 (home switch on the positive side) and 21, 22 (on the negative side): the first direction
  is the one toward ``home_switch_counts`` as the switch's state tells it; stop at the switch's edge.
* 23-26 / 27-30: home switch with the positive / negative limit switch: first direction positive /
  negative; the limit switch, met first, reverses the travel; stop at the home switch's edge.
* 1-14: as 17-30 (method + 16): this drive's encoder gives no index pulse after a switch.
* 33 / 34: the next index pulse in the negative / positive direction (one per motor revolution,
  0x608F counts); 35 and 37: the current position.
* Others (15, 16, 31, 32, 36, manufacturer-specific): a homing error (statusword bit 13).

A switch that is needed but not fitted means endless travel, as on a machine: the master's
``homing_timeout_s`` ends it. Travel is at 0x6099:1, at 0x6099:2 on the home switch (within
``home_switch_window_counts``). At the home point the position reads the home offset (0x607C) and the
switches (and the probe's trip point) move with the new count, as physical switches stay where they are.
"""

from __future__ import annotations

import math

from fieldbus.canopen.drive_sim_cia402 import DI_HOME

_CURRENT = (35, 37)


class HomingMixin:
    """Homing of :class:`~fieldbus.canopen.drive_sim.SimDrive` (its state lives there)."""

    def _start_homing(self) -> None:
        self._homing = True
        self._homing_attained = False
        self._homing_error = False
        self._homing_interrupted = False
        self._homing_v = 0.0
        method = self._homing_method
        if 1 <= method <= 14:
            method += 16
        home = self.home_switch_counts
        # (first direction, what ends the search: "home", "negative", "positive", "index")
        if method == 17:
            plan = (-1, "negative")
        elif method == 18:
            plan = (1, "positive")
        elif method in (19, 20):
            plan = (1 if self.actual < home else -1, "home")
        elif method in (21, 22):
            plan = (-1 if self.actual > home else 1, "home")
        elif 23 <= method <= 26:
            plan = (1, "home")
        elif 27 <= method <= 30:
            plan = (-1, "home")
        elif method in (33, 34):
            plan = (-1 if method == 33 else 1, "index")
        elif method in _CURRENT:
            plan = (0, "here")
        else:
            self._homing = False
            self._homing_error = True
            return
        self._homing_dir, self._homing_goal = plan

    def _homing_goal_counts(self) -> float | None:
        """Where the search ends, in the current direction (None: a switch that is not fitted)."""
        goal, direction = self._homing_goal, self._homing_dir
        if goal == "here":
            return self.actual
        if goal == "home":
            return float(self.home_switch_counts)
        if goal == "negative":
            return None if self.negative_limit_counts is None else float(self.negative_limit_counts)
        if goal == "positive":
            return None if self.positive_limit_counts is None else float(self.positive_limit_counts)
        cpr = self._value(0x608F, 1) / max(1, self._value(0x608F, 2))
        k = self.actual / cpr
        return cpr * (math.floor(k - 1e-9) if direction < 0 else math.ceil(k + 1e-9))

    def _homing_step(self, dt: float) -> None:
        if not self._homing:
            return
        if self._homing_interrupted:
            self._homing_ramp_down(dt)
            return
        speed = self._homing_speed
        if self.home_switch_window_counts and self.digital_inputs() & DI_HOME:
            speed = self._homing_speed_zero  # on the home switch: the slow search for its zero
        self._homing_v = speed
        step = speed * dt
        goal = self._homing_goal_counts()
        direction = self._homing_dir
        ahead = None if goal is None else (goal - self.actual) * direction
        if ahead is not None and ahead < 0 and self._homing_goal == "home":
            ahead = None  # the home switch is behind: on toward the limit switch, which reverses
        if goal is None or ahead is None or ahead > step:
            limit = self.positive_limit_counts if direction > 0 else self.negative_limit_counts
            self.actual += direction * step
            if self._homing_goal == "home" and limit is not None and (self.actual - limit) * direction >= 0:
                self.actual = float(limit)
                self._homing_dir = -direction  # the limit switch reverses the search
            self.demand = self.actual
            return
        # home found: the position now reads the home offset; the switches stay where they are, so
        # their counts move with the drive's
        shift = self._home_offset - round(goal)
        self.actual = float(self._home_offset)
        self.demand = self.actual
        self.target = round(self.actual)
        self.home_switch_counts += shift
        for name in ("negative_limit_counts", "positive_limit_counts", "probe_trip_counts"):
            value = getattr(self, name)
            if value is not None:
                setattr(self, name, value + shift)
        self._homing = False
        self._homing_attained = True

    def _homing_ramp_down(self, dt: float) -> None:
        """An interrupted homing (start bit 1 -> 0): on in its direction, slower each period at 0x609A,
        until it stands; then the homing is over (statusword bit 10: interrupted)."""
        v = max(0.0, self._homing_v - max(1, self._value(0x609A)) * dt)
        self.actual += self._homing_dir * 0.5 * (self._homing_v + v) * dt
        self.demand = self.actual
        self._homing_v = v
        if v == 0.0:
            self._homing = False
            self._homing_interrupted = False
