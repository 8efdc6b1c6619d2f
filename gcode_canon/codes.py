"""Code-number tables the interpreter's parts share (codes are held times ten: G59.1 -> 591)."""

from __future__ import annotations

from gcode_canon.commands import Plane
from gcode_canon.modal import gname

PLANE_BY_CODE = {170: Plane.XY, 180: Plane.XZ, 190: Plane.YZ}
CODE_BY_PLANE = {v: k for k, v in PLANE_BY_CODE.items()}
G5X_INDEX = {540: 1, 550: 2, 560: 3, 570: 4, 580: 5, 590: 6, 591: 7, 592: 8, 593: 9}
"""G54 ... G59.3 to the coordinate system's number (#5220)."""
G5X_NAMES = {v: gname(k) for k, v in G5X_INDEX.items()}
G5X_CODES = {v: k for k, v in G5X_INDEX.items()}
