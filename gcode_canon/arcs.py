"""Arc centres from IJK offsets or an R radius, with LinuxCNC's checks and tolerances.

All values are in the plane's (first, second) coordinates in mm. ``turns`` follows LinuxCNC's
rotation: +P counter-clockwise (G3), -P clockwise (G2).
"""

from __future__ import annotations

import math

from gcode_canon.errors import GCodeError

MM_PER_INCH = 25.4
SPIRAL_ABS_TOLERANCE_MM = 2 * 0.01 * math.sqrt(2)
SPIRAL_ABS_TOLERANCE_INCH = 2 * 0.001 * math.sqrt(2)
SPIRAL_REL_TOLERANCE = 0.001
RADIUS_TOLERANCE_INCH = 0.00005
RADIUS_TOLERANCE_MM = RADIUS_TOLERANCE_INCH * MM_PER_INCH


def _fmt(*values: float) -> str:
    return ", ".join(f"{v:.4f}" for v in values)


def centre_ijk(
    clockwise: bool,
    start: tuple[float, float],
    end: tuple[float, float],
    centre: tuple[float, float],
    turns: int,
    inch: bool,
) -> tuple[float, float, int]:
    """Centre (already absolute in the program frame) checked against both ends."""
    r1 = math.hypot(start[0] - centre[0], start[1] - centre[1])
    r2 = math.hypot(end[0] - centre[0], end[1] - centre[1])
    radius_tol = RADIUS_TOLERANCE_MM
    if r1 < radius_tol or r2 < radius_tol:
        raise GCodeError("Zero-radius arc: the centre is on the start or end point")
    spiral_abs = SPIRAL_ABS_TOLERANCE_INCH * MM_PER_INCH if inch else SPIRAL_ABS_TOLERANCE_MM
    abs_err = abs(r1 - r2)
    rel_err = abs_err / max(r1, r2)
    if abs_err > spiral_abs * 100.0 or (abs_err > spiral_abs and rel_err > SPIRAL_REL_TOLERANCE):
        scale = 1 / MM_PER_INCH if inch else 1.0
        raise GCodeError(
            "Radius to end of arc differs from radius to start: "
            f"start=({_fmt(start[0] * scale, start[1] * scale)}) "
            f"center=({_fmt(centre[0] * scale, centre[1] * scale)}) "
            f"end=({_fmt(end[0] * scale, end[1] * scale)}) "
            f"r1={r1 * scale:.4f} r2={r2 * scale:.4f} abs_err={abs_err * scale:.4g} rel_err={rel_err:.4%}"
        )
    return centre[0], centre[1], (-turns if clockwise else turns)


def centre_r(
    clockwise: bool,
    start: tuple[float, float],
    end: tuple[float, float],
    radius: float,
    turns: int,
) -> tuple[float, float, int]:
    """Centre of the arc of radius ``|radius|`` from start to end; negative R takes the long way."""
    if math.hypot(end[0] - start[0], end[1] - start[1]) < RADIUS_TOLERANCE_MM:
        raise GCodeError("Current point same as end point of arc (R format cannot make a full circle)")
    abs_r = abs(radius)
    if abs_r < RADIUS_TOLERANCE_MM:
        raise GCodeError("Zero-radius arc (R word 0)")
    mid_x = (start[0] + end[0]) / 2.0
    mid_y = (start[1] + end[1]) / 2.0
    half = math.hypot(end[0] - mid_x, end[1] - mid_y)
    if half - abs_r > RADIUS_TOLERANCE_MM:
        raise GCodeError(
            f"Arc radius too small to reach end point: R={abs_r:.4f} mm, half the chord is {half:.4f} mm"
        )
    if half > abs_r:
        half = abs_r
    direction = math.atan2(end[1] - start[1], end[0] - start[0])
    # The centre lies to the right of the chord for a short clockwise arc, to the left for a short
    # counter-clockwise one; a negative R (more than half a circle) flips the side.
    left = (not clockwise) == (radius > 0)
    theta = direction + (math.pi / 2 if left else -math.pi / 2)
    dist = math.sqrt(max(abs_r * abs_r - half * half, 0.0))
    return mid_x + dist * math.cos(theta), mid_y + dist * math.sin(theta), (-turns if clockwise else turns)
