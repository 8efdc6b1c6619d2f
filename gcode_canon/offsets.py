"""Coordinate frames: program coordinates to machine coordinates, and the data behind them.

Three frames, all held in mm/deg (program values are converted at the word):

* program: what the program's axis words mean (the active G5x system, shifted by G92);
* absolute: ``rotate(program + G92, R) + G5x`` (LinuxCNC's canonical position, no tool offset);
* machine: ``absolute + tool length offset``: what every output command carries.

The rotation R of the active coordinate system turns X/Y about the system's origin. The data lives
in the numbered parameters (#5211-#5219 G92, #5220 active system, #5221... the nine systems), which are
the persistent truth, as in LinuxCNC; :class:`Frames` caches what the active system needs.
"""

from __future__ import annotations

import math
from operator import add as _add

from gcode_canon.commands import Plane, Pose
from gcode_canon.parameters import Parameters

N_AXES = 9
ROTARY_INDEXES = frozenset((3, 4, 5))
"""A B C: angles, never scaled by G20/G21."""


def system_base(index: int) -> int:
    """First parameter (X) of coordinate system ``index`` 1..9 (G54 = 1 -> 5221)."""
    return 5201 + 20 * index


_new_pose = tuple.__new__


class Frames:
    """Active offsets and the transforms between frames (lists of nine floats)."""

    __slots__ = ("cos_r", "g5x", "g5x_index", "g92", "rotation", "sin_r", "sum", "tool")

    def __init__(self) -> None:
        self.g5x_index = 1
        self.g5x = [0.0] * N_AXES
        self.rotation = 0.0
        self.cos_r = 1.0
        self.sin_r = 0.0
        self.g92 = [0.0] * N_AXES
        self.tool = [0.0] * N_AXES
        self.sum = [0.0] * N_AXES  # g5x + g92 + tool, for the no-rotation fast path

    def refresh(self) -> None:
        self.sum = [a + b + c for a, b, c in zip(self.g5x, self.g92, self.tool, strict=True)]
        r = math.radians(self.rotation)
        self.cos_r = math.cos(r)
        self.sin_r = math.sin(r)
        if self.rotation == 0.0:
            self.cos_r, self.sin_r = 1.0, 0.0

    def load_system(self, params: Parameters, index: int) -> None:
        base = system_base(index)
        self.g5x_index = index
        self.g5x = [params.numbered[base + k] for k in range(N_AXES)]
        self.rotation = params.numbered[base + 9]
        self.refresh()

    def arc_rotation(self, plane: Plane) -> float:
        """An arc's ``rotation`` (ArcFeed): the system's rotation turns the XZ and YZ planes about Z
        (LinuxCNC's ARC_FEED); the XY plane and the UVW ones stay."""
        return self.rotation if plane is Plane.XZ or plane is Plane.YZ else 0.0

    # --- transforms -------------------------------------------------------------------------------

    def to_absolute(self, prog: list[float]) -> list[float]:
        g92 = self.g92
        out = [p + o for p, o in zip(prog, g92, strict=True)]
        if self.rotation != 0.0:
            x, y = out[0], out[1]
            out[0] = x * self.cos_r - y * self.sin_r
            out[1] = x * self.sin_r + y * self.cos_r
        g5x = self.g5x
        return [p + o for p, o in zip(out, g5x, strict=True)]

    def from_absolute(self, absolute: list[float]) -> list[float]:
        out = [p - o for p, o in zip(absolute, self.g5x, strict=True)]
        if self.rotation != 0.0:
            x, y = out[0], out[1]
            out[0] = x * self.cos_r + y * self.sin_r
            out[1] = -x * self.sin_r + y * self.cos_r
        return [p - o for p, o in zip(out, self.g92, strict=True)]

    def to_machine(self, prog: list[float]) -> Pose:
        if self.rotation == 0.0:
            s = self.sum
            # prog[k] + s[k] for the nine axes, added in C; NamedTuple's own __new__ is Python: slower
            return _new_pose(Pose, map(_add, prog, s))
        a = self.to_absolute(prog)
        return Pose(*(p + t for p, t in zip(a, self.tool, strict=True)))

    def machine_to_program(self, machine: Pose | list[float]) -> list[float]:
        return self.from_absolute([m - t for m, t in zip(machine, self.tool, strict=True)])
