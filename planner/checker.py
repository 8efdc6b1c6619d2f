"""Check a setpoint stream against the machine's limits and the programmed path.

Independent of how the stream was made: it reads the program's geometry from the canonical commands
itself (lines, arcs and helices in any plane), and measures the stream as a drive would see it:

* velocity, acceleration and jerk per axis from the first, second and third differences of the
  positions divided by T, T^2, T^3, with the machine at rest before the first and after the last
  setpoint;
* the distance of every setpoint from the programmed path, against what is allowed where it is
  (1 um on exact paths, G64 P inside blends);
* whether every exact-stop point (G61.1, G9, before each sync point, the program's end) was reached:
  a setpoint equal to the point within ``stop_tolerance``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from gcode_canon import commands as C
from planner.machine import DEMO_MACHINE, MachineLimits
from planner.setpoints import Setpoint

EXACT_DEVIATION = 1e-3  # mm: 1 micrometre
LIMIT_MARGIN = 1.01  # a peak within 1 % of its limit passes


@dataclass(frozen=True, slots=True)
class Peaks:
    velocity: float
    acceleration: float
    jerk: float


@dataclass(frozen=True, slots=True)
class _Path:
    kind: str  # "line" or "arc"
    start: np.ndarray
    end: np.ndarray
    allowed: float  # deviation allowed near this piece
    allowed_start: float = 0.0  # near its start: the corner may be blended by the move before
    i0: int = 0
    i1: int = 0
    c0: float = 0.0
    c1: float = 0.0
    th0: float = 0.0
    sweep: float = 0.0
    r0: float = 0.0
    r1: float = 0.0
    length: float = 0.0
    turn: tuple[int, int, float] | None = None  # an arc's plane turned about Z: X, Y indexes, degrees


@dataclass
class CheckReport:
    """What :func:`check_stream` found. ``ok`` is the verdict the tests and ``canon plan`` use."""

    axes: tuple[str, ...]
    cycle_s: float
    duration_s: float
    cycles: int
    limits: dict[str, Peaks]
    peaks: dict[str, Peaks]
    max_deviation: float
    deviation_excess: float  # worst (deviation - allowed) over all setpoints; <= 0 is fine
    stops_total: int
    stops_missed: list[tuple[str, int, tuple[float, ...]]] = field(default_factory=list)
    final_position: tuple[float, ...] = ()
    final_error: float = 0.0

    def ratio(self, axis: str) -> Peaks:
        lim, pk = self.limits[axis], self.peaks[axis]
        return Peaks(pk.velocity / lim.velocity, pk.acceleration / lim.acceleration, pk.jerk / lim.jerk)

    @property
    def worst_ratio(self) -> float:
        return max((max(r.velocity, r.acceleration, r.jerk) for r in map(self.ratio, self.axes)), default=0.0)

    @property
    def within_limits(self) -> bool:
        return self.worst_ratio <= LIMIT_MARGIN

    @property
    def ok(self) -> bool:
        return (self.within_limits and self.deviation_excess <= 0.0 and not self.stops_missed
                and self.final_error <= 1e-9)

    def problems(self) -> list[str]:
        out = []
        for ax in self.axes:
            r = self.ratio(ax)
            for name, value in (("velocity", r.velocity), ("acceleration", r.acceleration), ("jerk", r.jerk)):
                if value > LIMIT_MARGIN:
                    out.append(f"{ax}: {name} {value * 100:.1f} % of its limit")
        if self.deviation_excess > 0:
            out.append(f"path deviation {self.max_deviation:.3g} exceeds what is allowed by "
                       f"{self.deviation_excess:.3g}")
        for file, line, point in self.stops_missed[:5]:
            out.append(f"{file}:{line}: exact stop at {point} not reached")
        if self.final_error > 1e-9:
            out.append(f"final position off by {self.final_error:.3g}")
        return out


def _program_geometry(program: Iterable[C.Canon], machine: MachineLimits, start: np.ndarray,
                      ) -> tuple[list[_Path], list[tuple[str, int, np.ndarray]], np.ndarray]:
    """Pieces of the programmed path, the exact-stop points and the final point."""
    index = machine.pose_index
    where = {p: i for i, p in enumerate(index)}
    pos = start.copy()
    paths: list[_Path] = []
    stops: list[tuple[str, int, np.ndarray]] = []
    mode, tol, exact_next = C.MotionControlMode.CONTINUOUS, 0.0, False
    last_src = ("", 0)

    def add_stop(file: str, line: int, point: np.ndarray) -> None:
        if not (stops and np.array_equal(stops[-1][2], point)):
            stops.append((file, line, point.copy()))

    for cmd in program:
        if isinstance(cmd, C.SetMotionControlMode):
            mode, tol = cmd.mode, cmd.tolerance
            continue
        if isinstance(cmd, C.ExactStopBlock):
            exact_next = True
            continue
        if cmd.SYNC and paths and not isinstance(cmd, C.Probe):
            add_stop(cmd.file, cmd.line, pos)
        if not isinstance(cmd, C.MOTION_TYPES):
            continue
        end = np.array([cmd.end[p] for p in index], dtype=float)  # type: ignore[attr-defined]
        if mode is C.MotionControlMode.CONTINUOUS:
            allowed = max(tol, EXACT_DEVIATION) if tol > 0 else math.inf
        else:
            allowed = EXACT_DEVIATION
        before = paths[-1].allowed if paths else EXACT_DEVIATION
        if isinstance(cmd, C.ArcFeed):
            p0, p1, _ = cmd.plane.value
            i0, i1 = where[p0], where[p1]
            turn = (where[0], where[1], cmd.rotation) if cmd.rotation else None
            centre = C.rotate_about_z(cmd.center, -cmd.rotation)
            c0, c1 = centre[p0], centre[p1]
            a, b = (_unturn(v, turn) for v in (pos, end))
            th0 = math.atan2(a[i1] - c1, a[i0] - c0)
            th1 = math.atan2(b[i1] - c1, b[i0] - c0)
            if cmd.turns > 0:
                sweep = (th1 - th0) % (2 * math.pi)
                sweep = (sweep if sweep > 1e-12 else sweep + 2 * math.pi) + 2 * math.pi * (cmd.turns - 1)
            else:
                sweep = -((th0 - th1) % (2 * math.pi))
                sweep = (sweep if sweep < -1e-12 else sweep - 2 * math.pi) - 2 * math.pi * (-cmd.turns - 1)
            r0 = math.hypot(a[i0] - c0, a[i1] - c1)
            r1 = math.hypot(b[i0] - c0, b[i1] - c1)
            paths.append(_Path("arc", pos.copy(), end, allowed, before, i0, i1, c0, c1, th0, sweep, r0, r1,
                               abs(sweep) * min(r0, r1), turn))  # length: a lower bound, sizes windows
        else:
            paths.append(_Path("line", pos.copy(), end, allowed, before,
                               length=float(np.linalg.norm(end - pos))))
        if exact_next or isinstance(cmd, C.Probe) or mode in (C.MotionControlMode.EXACT_STOP_MODAL,
                                                              C.MotionControlMode.EXACT_STOP):
            add_stop(cmd.file, cmd.line, end)
        exact_next = False
        pos = end
        last_src = (cmd.file, cmd.line)
    if paths:
        add_stop(*last_src, pos)
    return paths, stops, pos


def turn_points(v: np.ndarray, turn: tuple[int, int, float] | None, sign: int = 1) -> np.ndarray:
    """Points (a vector or rows) with X and Y turned about Z by ``sign`` times the degrees of
    ``turn`` (X index, Y index, an arc's ``rotation``: -1 into the frame where the arc lies in its
    axis plane, 1 back)."""
    if turn is None:
        return v
    ix, iy, degrees = turn
    c, s = math.cos(math.radians(sign * degrees)), math.sin(math.radians(sign * degrees))
    out = np.array(v, dtype=float, copy=True)
    x, y = v[..., ix], v[..., iy]
    out[..., ix], out[..., iy] = x * c - y * s, x * s + y * c
    return out


def _unturn(v: np.ndarray, turn: tuple[int, int, float] | None) -> np.ndarray:
    return turn_points(v, turn, -1)


def _distance(path: _Path, pts: np.ndarray) -> np.ndarray:
    if path.turn is not None:  # in the frame turned back, where the arc lies in its axis plane
        return _distance(replace(path, start=_unturn(path.start, path.turn), end=_unturn(path.end, path.turn),
                                 turn=None), _unturn(pts, path.turn))
    if path.kind == "line":
        d = path.end - path.start
        dd = float(d @ d)
        if dd == 0.0:
            return np.linalg.norm(pts - path.start, axis=1)
        t = np.clip((pts - path.start) @ d / dd, 0.0, 1.0)
        return np.linalg.norm(pts - path.start - t[:, None] * d, axis=1)
    i0, i1 = path.i0, path.i1
    sign = 1.0 if path.sweep > 0 else -1.0
    total = abs(path.sweep)
    delta = path.end - path.start

    def point(alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The helix at angle ``alpha`` from the start, and its derivative along ``alpha``."""
        f = alpha / total
        on = path.start[None, :] + f[:, None] * delta[None, :]
        der = np.repeat((delta / total)[None, :], len(alpha), axis=0)
        r = path.r0 + f * (path.r1 - path.r0)
        dr = (path.r1 - path.r0) / total
        th = path.th0 + sign * alpha
        c, s_ = np.cos(th), np.sin(th)
        on[:, i0] = path.c0 + r * c
        on[:, i1] = path.c1 + r * s_
        der[:, i0] = dr * c - r * sign * s_
        der[:, i1] = dr * s_ + r * sign * c
        return on, der

    phi = np.arctan2(pts[:, i1] - path.c1, pts[:, i0] - path.c0)
    base = np.mod(sign * (phi - path.th0), 2 * math.pi)
    candidates = [base + 2 * math.pi * k for k in range(int(total // (2 * math.pi)) + 2)]
    # steep helices and tiny radii: the angle says little, the height along the normal says more
    lin = np.linalg.norm(delta)
    if lin > 0:
        candidates.append((pts - path.start) @ delta / (lin * lin) * total)
    best = np.minimum(np.linalg.norm(pts - path.start, axis=1), np.linalg.norm(pts - path.end, axis=1))
    for alpha in candidates:
        alpha = np.clip(alpha, 0.0, total)
        for _ in range(4):  # Gauss-Newton towards the nearest point of the helix
            on, der = point(alpha)
            step = np.einsum("ij,ij->i", pts - on, der) / np.maximum(np.einsum("ij,ij->i", der, der), 1e-300)
            alpha = np.clip(alpha + step, 0.0, total)
        on, _ = point(alpha)
        best = np.minimum(best, np.linalg.norm(pts - on, axis=1))
    return best


def _allowed(path: _Path, pts: np.ndarray) -> np.ndarray:
    """Deviation allowed for each point near ``path``: its own mode's, or near its start the larger one
    of the move before (LinuxCNC blends a corner by the mode of the move ending there; a blend reaches
    at most 0.6 of the way into the next piece)."""
    out = np.full(len(pts), path.allowed)
    if path.allowed_start > path.allowed:
        reach = 0.6 * float(np.linalg.norm(path.end - path.start)) + 1e-9
        near = np.linalg.norm(pts - path.start, axis=1) <= reach
        out[near] = path.allowed_start
    return out


def _deviation(paths: list[_Path], pts: np.ndarray, chunk: int = 256) -> tuple[float, float]:
    """Max distance from the path and max excess over the allowed deviation (pieces in order)."""
    if not paths or len(pts) == 0:
        return 0.0, 0.0
    worst = 0.0
    excess = -math.inf
    cur = 0  # the earliest piece the last checked setpoint may be on
    ahead = 0  # the piece it is nearest to
    cum = np.cumsum([p.length for p in paths])
    for lo in range(0, len(pts), chunk):
        block = pts[lo: lo + chunk]
        travel = float(np.sum(np.linalg.norm(np.diff(block, axis=0), axis=1))) if len(block) > 1 else 0.0
        j = max(cur - 1, 0)
        k = int(np.searchsorted(cum, cum[max(cur, ahead)] + 2.0 * travel + 1e-6)) + 2
        hi = min(len(paths), max(k, j + 3))
        for _ in range(40):  # widen the window while the last point sits at its far end or off it
            dists = np.stack([_distance(paths[m], block) for m in range(j, hi)])
            allowed = np.stack([_allowed(paths[m], block) for m in range(j, hi)])
            last = dists[:, -1]
            if hi >= len(paths) or (int(np.argmin(last)) < hi - j - 1
                                    and np.min(last - np.minimum(allowed[:, -1], 1.0)) <= 1e-6):
                break
            hi = min(len(paths), j + 2 * (hi - j))
        best = np.argmin(dists, axis=0)
        dmin = dists[best, np.arange(len(block))]
        worst = max(worst, float(dmin.max()))
        # a point near two pieces (a blend) may use the larger of their tolerances
        slack = dists - allowed
        excess = max(excess, float(np.min(slack, axis=0).max()))
        # the earliest piece the last point may be on (a later piece may pass closer by)
        last = dists[:, -1]
        plausible = np.nonzero(last <= last.min() + np.minimum(allowed[:, -1], 1.0) + 1e-6)[0]
        cur = max(cur, j + int(plausible[0]))
        ahead = max(ahead, j + int(np.nonzero(last <= last.min() + 1e-9)[0][-1]))  # retraces: the later
    return worst, excess


def check_stream(setpoints: Iterable[Setpoint] | np.ndarray, program: Sequence[C.Canon],
                 machine: MachineLimits = DEMO_MACHINE, start: Sequence[float] | None = None,
                 stop_tolerance: float = 1e-9) -> CheckReport:
    """Measure a stream (Setpoints, or an array of positions, one row per cycle) against the program."""
    n = len(machine.axes)
    start_arr = np.zeros(n) if start is None else np.asarray(start, dtype=float)
    if isinstance(setpoints, np.ndarray):
        pts = setpoints.reshape(-1, n).astype(float)
    else:
        pts = np.array([sp.positions for sp in setpoints], dtype=float).reshape(-1, n)
    T = machine.cycle_s
    final = pts[-1] if len(pts) else start_arr
    padded = np.vstack([np.repeat(start_arr[None, :], 3, axis=0), pts, np.repeat(final[None, :], 3, axis=0)])
    v = np.diff(padded, 1, axis=0) / T
    a = np.diff(padded, 2, axis=0) / T**2
    j = np.diff(padded, 3, axis=0) / T**3
    names = machine.names
    peaks = {ax: Peaks(float(np.abs(v[:, i]).max()), float(np.abs(a[:, i]).max()),
                       float(np.abs(j[:, i]).max())) for i, ax in enumerate(names)}
    limits = {ax.name: Peaks(ax.max_velocity, ax.max_acceleration, ax.max_jerk) for ax in machine.axes}
    paths, stops, end = _program_geometry(program, machine, start_arr)
    worst, excess = _deviation(paths, pts)
    missed = []
    # the machine is at rest at ``start`` before the first setpoint: a stop asked for there (a
    # zero-length move under G61.1 or G9 before any motion) is met by that rest, row 0 here
    at_rest = np.vstack([start_arr[None, :], pts])
    ptr = 0
    for file, line, point in stops:
        found = -1
        size = 1024
        while ptr < len(at_rest) and found < 0:
            block = at_rest[ptr: ptr + size]
            hit = np.nonzero(np.max(np.abs(block - point), axis=1) <= stop_tolerance)[0]
            if len(hit):
                found = ptr + int(hit[0])
            else:
                ptr += len(block)
                size *= 2
        if found < 0:
            missed.append((file, line, tuple(float(x) for x in point)))
            ptr = 0
        else:
            ptr = found
    return CheckReport(
        axes=names, cycle_s=T, duration_s=len(pts) * T, cycles=len(pts), limits=limits, peaks=peaks,
        max_deviation=worst, deviation_excess=excess, stops_total=len(stops), stops_missed=missed,
        final_position=tuple(float(x) for x in final),
        final_error=float(np.max(np.abs(final - end))) if len(pts) else 0.0,
    )
