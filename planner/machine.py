"""The machine as the planner sees it: axes in drive order, their kinematic limits, the cycle time.

These dataclasses are the planner's own view of the configuration; ``motiond.config`` fills them from
the TOML machine file, and :data:`DEMO_MACHINE` is what every command uses when there is no file.
Units are machine units: mm (deg for A B C) per second, per second squared, per second cubed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from gcode_canon.commands import AXES, ROTARY_AXES


class MachineError(ValueError):
    """An impossible machine description (the configuration reader names the key; this says what)."""


@dataclass(frozen=True, slots=True)
class AxisLimits:
    """One axis's limits. ``quick_stop_deceleration`` defaults to twice ``max_acceleration``."""

    name: str
    max_velocity: float
    max_acceleration: float
    max_jerk: float
    min_position: float | None = None
    max_position: float | None = None
    quick_stop_deceleration: float | None = None

    def __post_init__(self) -> None:
        if self.name not in AXES:
            raise MachineError(f"axis {self.name!r}: not one of {' '.join(AXES)}")
        for key in ("max_velocity", "max_acceleration", "max_jerk"):
            value = getattr(self, key)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise MachineError(f"axis {self.name}: {key} must be a finite number > 0, got {value!r}")
        qs = self.quick_stop_deceleration
        if qs is not None and not (math.isfinite(qs) and qs > 0):
            raise MachineError(f"axis {self.name}: quick_stop_deceleration must be > 0, got {qs!r}")
        if (self.min_position is not None and self.max_position is not None
                and self.min_position >= self.max_position):
            raise MachineError(f"axis {self.name}: min_position must be below max_position")

    @property
    def rotary(self) -> bool:
        return self.name in ROTARY_AXES

    @property
    def unit(self) -> str:
        return "deg" if self.rotary else "mm"

    @property
    def quick_stop(self) -> float:
        return self.quick_stop_deceleration or 2.0 * self.max_acceleration


@dataclass(frozen=True, slots=True)
class MachineLimits:
    """The axes in drive order and the cycle time (the CSP interpolation period)."""

    axes: tuple[AxisLimits, ...]
    cycle_s: float = 0.002
    name: str = "machine"

    def __post_init__(self) -> None:
        if not self.axes:
            raise MachineError("a machine needs at least one axis")
        names = [a.name for a in self.axes]
        if len(set(names)) != len(names):
            raise MachineError(f"axis names repeat: {' '.join(names)}")
        if not (math.isfinite(self.cycle_s) and 0.001 - 1e-12 <= self.cycle_s <= 0.010 + 1e-12):
            raise MachineError(f"cycle time must be between 1 ms and 10 ms, got {self.cycle_s * 1e3:g} ms")

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(a.name for a in self.axes)

    @property
    def pose_index(self) -> tuple[int, ...]:
        """For each configured axis, its index in a :class:`gcode_canon.commands.Pose`."""
        return tuple(AXES.index(a.name) for a in self.axes)

    def axis(self, name: str) -> AxisLimits:
        for a in self.axes:
            if a.name == name:
                return a
        raise KeyError(name)


DEMO_MACHINE = MachineLimits(
    axes=(
        AxisLimits("x", max_velocity=200.0, max_acceleration=2000.0, max_jerk=50000.0,
                   quick_stop_deceleration=5000.0),
        AxisLimits("y", max_velocity=200.0, max_acceleration=2000.0, max_jerk=50000.0,
                   quick_stop_deceleration=5000.0),
        AxisLimits("z", max_velocity=100.0, max_acceleration=1500.0, max_jerk=40000.0,
                   quick_stop_deceleration=4000.0),
    ),
    cycle_s=0.002,
    name="demo mill",
)
"""A small mill: X and Y 12 m/min, 2 m/s^2, 50 m/s^3; Z 6 m/min, 1.5 m/s^2, 40 m/s^3; 2 ms cycle."""
