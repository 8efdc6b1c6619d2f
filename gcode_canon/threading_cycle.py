"""G76, the lathe threading cycle, as a pure expansion into passes (LinuxCNC's semantics).

The cycle works in the XZ plane from where the tool stands (the *drive line*: its X, at its Z) to the
Z word. Each pass retracts to the drive line, goes in to the pass's depth, cuts along Z synchronized
to the spindle (``P`` per revolution), and comes out again; the depth of pass ``n`` follows the
degression ``R`` (``I + J * n ** (1 / R)``, so R 1 gives equal depths, R 2 equal chip areas) until
the full thread depth ``K`` is reached, which is then cut ``H`` more times (spring passes). ``Q``
moves each pass's start along Z by the compound slide angle; ``E`` and ``L`` add tapered entries and
exits. A negative ``I`` cuts an outside thread (peaks inside the drive line), a positive one an inside
(boring) thread. After the passes the tool goes to the block's end point.

Distances are program-unit radii (in lathe diameter mode the interpreter halves I, J and K before,
as LinuxCNC does). The result is a list of :class:`ThreadOp`: the interpreter turns each into a
canonical command at the current Y and the other axes.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

from gcode_canon.errors import GCodeError


class OpKind(enum.Enum):
    TRAVERSE = "traverse"
    FEED = "feed"
    SYNC = "sync"  # spindle-synchronized feed from here on, ``value`` per revolution
    SYNC_STOP = "sync_stop"
    FEED_OVERRIDE = "feed_override"  # ``value`` 1.0: allowed again, 0.0: off for the cut


@dataclass(frozen=True, slots=True)
class ThreadOp:
    kind: OpKind
    x: float = 0.0
    z: float = 0.0
    value: float = 0.0


@dataclass(frozen=True, slots=True)
class ThreadWords:
    """The G76 block's words (program units; None: not on the line)."""

    p: float | None
    i: float | None
    j: float | None
    k: float | None
    r: float | None = None
    q: float | None = None
    h: float | None = None
    e: float | None = None
    l: float | None = None  # noqa: E741 (the G-code letter)


def check_words(w: ThreadWords) -> None:
    """LinuxCNC's checks on a G76 block, in its order and words."""
    if w.p is None:
        raise GCodeError("P word missing with G76")
    if w.i is None or w.j is None or w.k is None:
        raise GCodeError("I, J or K words missing with G76")
    if w.i == 0:
        raise GCodeError("In G76, I must not be 0")
    if w.j <= 0:
        raise GCodeError("In G76, J must be greater than 0")
    if w.k <= w.j:
        raise GCodeError("In G76, K must be greater than J")


def expand(w: ThreadWords, start_x: float, start_z: float, end_x: float, end_z: float,
           diameter_mode: bool = False) -> list[ThreadOp]:
    """The passes of one G76 block from the drive line (``start_x``, ``start_z``) to ``end_z``, then
    to (``end_x``, ``end_z``). Call :func:`check_words` first."""
    assert w.p is not None and w.i is not None and w.j is not None and w.k is not None
    i, j, k = w.i, w.j, w.k
    if diameter_mode:
        i, j, k = i / 2, j / 2, k / 2
    boring = i > 0
    peaks = abs(i)  # drive line to the thread's peaks
    first_depth = abs(i) + abs(j)
    step = abs(j)
    height = abs(k)
    full_depth = abs(k) + abs(i)
    pitch = w.p
    angle = 0.0 if w.q is None or w.q == -1 else w.q
    angle = math.radians(angle)
    taper = max(w.e, 0.0) if w.e is not None else 0.0
    taper_pitch = pitch * math.hypot(taper, height) / taper if taper > 0 else pitch
    if end_z > start_z:  # cutting toward +Z: the compound angle and the tapers point the other way
        angle, taper = -angle, -taper
    flags = int(w.l) if w.l is not None and w.l >= 0 else 0
    entry, exit_ = bool(flags & 1), bool(flags & 2)
    degression = w.r if w.r is not None and w.r >= 1.0 else 1.0
    springs = int(w.h) if w.h is not None else 0
    target_z = end_z + height * math.tan(angle)
    sign = 1.0 if boring else -1.0

    def radius(depth: float) -> float:
        return start_x + sign * depth

    ops: list[ThreadOp] = []

    def one_pass(depth: float) -> None:
        zoff = (depth - peaks) * math.tan(angle)
        z0, z1 = start_z - zoff, target_z - zoff
        clear = radius(depth) - sign * full_depth  # the drive line's side, clear of the thread
        shallow = radius(depth) - sign * height  # the taper's start: the peaks' depth
        ops.append(ThreadOp(OpKind.TRAVERSE, clear, z0))
        if taper and entry:
            ops.append(ThreadOp(OpKind.FEED_OVERRIDE, value=0.0))
            ops.append(ThreadOp(OpKind.SYNC, value=taper_pitch))
            ops.append(ThreadOp(OpKind.FEED, shallow, z0))
            ops.append(ThreadOp(OpKind.FEED, radius(depth), z0 - taper))
            ops.append(ThreadOp(OpKind.SYNC, value=pitch))
        else:
            ops.append(ThreadOp(OpKind.TRAVERSE, radius(depth), z0))
            ops.append(ThreadOp(OpKind.FEED_OVERRIDE, value=0.0))
            ops.append(ThreadOp(OpKind.SYNC, value=pitch))
        if taper and exit_:
            ops.append(ThreadOp(OpKind.FEED, radius(depth), z1 + taper))
            ops.append(ThreadOp(OpKind.SYNC, value=taper_pitch))
            ops.append(ThreadOp(OpKind.FEED, shallow, z1))
        else:
            ops.append(ThreadOp(OpKind.FEED, radius(depth), z1))
        ops.append(ThreadOp(OpKind.SYNC_STOP))
        ops.append(ThreadOp(OpKind.TRAVERSE, clear, z1))
        ops.append(ThreadOp(OpKind.FEED_OVERRIDE, value=1.0))

    n = 1
    depth = first_depth
    while depth < full_depth:
        one_pass(depth)
        n += 1
        depth = peaks + step * n ** (1.0 / degression)
    for _ in range(springs + 1):  # the full depth at least once, then the spring passes
        one_pass(full_depth)
    ops.append(ThreadOp(OpKind.TRAVERSE, end_x, end_z))
    return ops
