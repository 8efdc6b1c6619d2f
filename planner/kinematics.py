"""Closed forms for jerk-limited speed changes along the path (no solver in the lookahead).

A speed change from v0 to v1 that starts and ends with zero acceleration, with acceleration limit a
and jerk limit j, is point-symmetric in time, so the distance it needs is the mean speed times its
duration. The lookahead uses these instead of calling ruckig for every segment of the window:
ruckig is called once per segment, when that segment starts.
"""

from __future__ import annotations

import math


def change_time(dv: float, a: float, j: float) -> float:
    """Shortest time for a speed change of ``dv`` (>= 0) with zero acceleration at both ends."""
    if dv <= a * a / j:
        return 2.0 * math.sqrt(dv / j)
    return dv / a + a / j


def change_distance(v0: float, v1: float, a: float, j: float) -> float:
    """Distance travelled while changing speed from ``v0`` to ``v1`` as fast as the limits allow."""
    return 0.5 * (v0 + v1) * change_time(abs(v1 - v0), a, j)


def max_reach(w: float, length: float, a: float, j: float) -> float:
    """Largest speed v >= w such that changing between v and w fits in ``length``.

    Backward pass: the fastest a segment may be entered and still leave it at ``w``. Forward pass: the
    fastest it can be left when entered at ``w``. Both are this function, the profile being symmetric.
    """
    if length <= 0.0:
        return w
    # Short change (no constant-acceleration phase): with x = sqrt(dv / j), j x^3 + 2 w x - L = 0.
    p = 2.0 * w / j
    q = -length / j
    if p <= 1e-12 * (-q) ** (2.0 / 3.0):
        x = (-q) ** (1.0 / 3.0)
    else:
        m = 2.0 * math.sqrt(p / 3.0)
        x = m * math.sinh(math.asinh(-1.5 * q / p * math.sqrt(3.0 / p)) / 3.0)
    for _ in range(2):  # Newton polishes the rounding of the closed form
        f = x * (x * x + p) + q
        x -= f / (3.0 * x * x + p) if x > 0.0 else 0.0
    dv = j * x * x
    if dv > a * a / j:
        # With a constant-acceleration phase: dv^2 + dv (a^2/j + 2w) + 2 w a^2/j - 2 L a = 0.
        b = a * a / j + 2.0 * w
        c = 2.0 * w * a * a / j - 2.0 * length * a
        dv = (-b + math.sqrt(b * b - 4.0 * c)) / 2.0
    return w + max(dv, 0.0)


def min_reach(v0: float, length: float, a: float, j: float) -> float:
    """Smallest speed that ``length`` allows braking to from ``v0`` (0 when a stop fits)."""
    if change_distance(v0, 0.0, a, j) <= length:
        return 0.0
    lo, hi = 0.0, v0  # change_distance(v0, v) decreases from > length (v = 0) to 0 (v = v0)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if change_distance(v0, mid, a, j) > length:
            lo = mid
        else:
            hi = mid
    return hi


def stop_distance(v: float, a: float, j: float) -> float:
    return change_distance(v, 0.0, a, j)
