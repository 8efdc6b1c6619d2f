"""Profiles: the 1-D ruckig solves of a segment when it starts, stops, and the re-solve of the running
segment from its current state (override, hold, resume, abort, quick stop).
"""

from __future__ import annotations

import logging

from ruckig import ControlInterface, InputParameter, Result, RuckigError, Trajectory

from planner.kinematics import change_distance, max_reach, min_reach
from planner.segments import (
    OVR_ADAPTIVE,
    OVR_FEED,
    OVR_FEED_STOP,
    SLACK,
    PlannerError,
    Seg,
    _Active,
)

log = logging.getLogger(__name__)


class ProfilesMixin:
    """Part of :class:`planner.core.Planner`: solving and re-solving profiles."""

    def _solve(self, v0: float, a0: float, length: float, v1: float, vmax: float, a: float, j: float,
               ) -> Trajectory | None:
        """1-D profile from (0, v0, a0) to (length, v1, 0); None if it fails or leaves [0, length]."""
        inp = self._inp
        inp.control_interface = ControlInterface.Position
        inp.current_position = [0.0]
        inp.current_velocity = [v0]
        inp.current_acceleration = [a0]
        inp.target_position = [length]
        inp.target_velocity = [v1]
        inp.target_acceleration = [0.0]
        inp.max_velocity = [max(vmax, v1, 1e-9)]
        inp.max_acceleration = [a]
        inp.max_jerk = [j]
        traj = self._calculate(inp)
        if traj is None:
            return None
        ext = traj.position_extrema[0]
        slack = 1e-9 + 1e-9 * length
        if ext.max > length + slack or ext.min < -slack:
            return None
        if v0 > inp.max_velocity[0] * (1.0 + 1e-9):
            # Starting above the velocity limit, ruckig brakes first, and its position_extrema do not
            # cover that phase (seen: a profile that passes its target and comes back, extrema saying
            # otherwise). Check what the cycle loop will sample.
            h = 0.5 * self.T
            steps = min(int(traj.duration / h) + 2, 100_000)
            for k in range(steps):
                pos = traj.at_time(min(k * h, traj.duration))[0][0]
                if pos > length + slack or pos < -slack:
                    return None
        return traj

    def _solve_stop(self, v0: float, a0: float, a: float, j: float) -> Trajectory | None:
        inp = self._inp
        inp.control_interface = ControlInterface.Velocity
        inp.current_position = [0.0]
        inp.current_velocity = [v0]
        inp.current_acceleration = [a0]
        inp.target_velocity = [0.0]
        inp.target_acceleration = [0.0]
        inp.max_velocity = [max(abs(v0), 1e-9)]
        inp.max_acceleration = [a]
        inp.max_jerk = [j]
        try:
            return self._calculate(inp)
        finally:
            inp.control_interface = ControlInterface.Position

    def _calculate(self, inp: InputParameter) -> Trajectory | None:
        """One ruckig solve; None when ruckig refuses or fails (callers then lower their target)."""
        traj = Trajectory(1)
        self.stats["solves"] += 1
        try:
            result = self._otg.calculate(inp, traj)
        except (RuntimeError, RuckigError):  # RuckigError is no RuntimeError: both mean "no profile"
            return None
        if result not in (Result.Working, Result.Finished):
            return None
        return traj

    def _stop_limits(self, seg: Seg) -> tuple[float, float]:
        return (seg.qs_a, seg.qs_j) if self._quick else (seg.a, seg.j)

    def _stops(self, ovr: int) -> bool:
        """Whether a move with switches ``ovr`` must stop now: hold, abort and quick stop always; the
        feed override at 0, the adaptive feed at 0 and the feed stop input only where switched on."""
        return (self._hold or self._abort or self._quick
                or (ovr & OVR_FEED != 0 and self._override <= 0.0)
                or (ovr & OVR_ADAPTIVE != 0 and self._adaptive <= 0.0)
                or (ovr & OVR_FEED_STOP != 0 and self._feed_stop))

    def _ovr_now(self) -> int:
        """The switches of the running move, or at rest those of the next queued move (else the next
        fed one)."""
        if self._active is not None:
            return self._active.seg.ovr
        for i in range(self._h, len(self._q)):
            item = self._q[i]
            if isinstance(item, Seg):
                return item.ovr
        return self._ovr

    @property
    def _stopping(self) -> bool:
        return self._stops(self._ovr_now())

    def _start(self, seg: Seg, t0: float) -> None:
        """Commit ``seg``: solve its profile from the current end speed."""
        self._start_profile(seg, t0)
        if seg.last > self._started:
            self._started = seg.last
        assert self._active is not None
        self._v_end = self._active.v1

    def _start_profile(self, seg: Seg, t0: float) -> None:
        v0 = self._v_end
        length = seg.length
        a, j = seg.a, seg.j
        if self._stops(seg.ovr):
            a, j = self._stop_limits(seg)
            if change_distance(v0, 0.0, a, j) <= length:
                traj = self._solve_stop(v0, 0.0, a, j)
                if traj is not None:
                    stop = min(traj.at_time(traj.duration)[0][0], length)
                    self._active = _Active(seg, t0, traj, seg.s0, seg.s0 + stop, 0.0, True)
                    return
            target = lo = min_reach(v0, length, a, j)
        else:
            target = min(seg.vb, max_reach(v0, length * SLACK, a, j))
            lo = target
            if target < v0 and change_distance(v0, target, a, j) > length:
                if target <= 0.0 and self._tight_stop(seg, t0, v0, length, a, j):
                    return
                lo = target = min_reach(v0, length, a, j)  # after an override cut: brake all the way
        for _attempt in range(60):
            traj = self._solve(v0, 0.0, length, target, seg.cap, a, j)
            if traj is None:
                traj = self._solve(v0, 0.0, length, target, max(seg.cap, v0), a, j)
            if traj is not None:
                self._active = _Active(seg, t0, traj, seg.s0, seg.piece.length, target, True)
                return
            if self.stats["retries"] < 20:
                log.debug("%s:%d: profile %g -> %g over %g (cap %g) failed; lowering", seg.cmd.file,
                          seg.cmd.line, v0, target, length, seg.cap)
            self.stats["retries"] += 1
            if _attempt == 0:
                lo = min(lo, min_reach(v0, length, a, j))
            if target <= lo * (1 + 1e-12):
                break
            target = lo + 0.5 * (target - lo) if target - lo > 1e-9 else lo
        if seg.vb <= 0.0 and self._tight_stop(seg, t0, v0, length, a, j):
            return
        for eps in (1e-9, 1e-7, 1e-5, 1e-3):  # at the very edge of feasibility: a hair faster
            target = min(lo + eps * (v0 + lo + 1e-9), max(v0, lo))
            traj = self._solve(v0, 0.0, length, target, max(seg.cap, v0), a, j)
            if traj is not None:
                self._active = _Active(seg, t0, traj, seg.s0, seg.piece.length, target, True)
                return
        raise PlannerError(f"no feasible profile for this move (length {length:g}, from speed {v0:g} to "
                           f"{target:g})", seg.cmd.file, seg.cmd.line)

    def _tight_stop(self, seg: Seg, t0: float, v0: float, length: float, a: float, j: float) -> bool:
        """Start ``seg`` as a stop at its end when that stop is at the very edge of what its length
        allows (rounding): with a hair more acceleration and jerk (at most 1e-4), never with an end
        speed above 0. ``seg`` must end at rest (a stop, the end of the queue), and braking to a low
        speed needs more room than stopping (the mean speed is higher), so the lowest speed reachable
        short of a stop may be far above 0: taking it would end the stream while moving."""
        for eps in (0.0, 1e-9, 1e-7, 1e-6, 1e-5, 1e-4):
            traj = self._solve(v0, 0.0, length, 0.0, max(seg.cap, v0), a * (1 + eps), j * (1 + eps))
            if traj is not None:
                self._active = _Active(seg, t0, traj, seg.s0, seg.piece.length, 0.0, True)
                return True
        log.warning("%s:%d: cannot stop at the end of this move from %g (length %g)", seg.cmd.file,
                    seg.cmd.line, v0, length)
        return False

    def _replan(self) -> None:
        """Re-solve the running profile from the current state (override, hold, resume, stops)."""
        act = self._active
        if act is None:
            return
        t_now = self._k * self.T
        tau = min(max(t_now - act.t0, 0.0), act.traj.duration)
        p, v, acc = (x[0] for x in act.traj.at_time(tau))
        s_cur = min(act.s_off + p, act.seg.piece.length)
        seg = act.seg
        remaining = seg.piece.length - s_cur
        self._set_cap(seg)
        head = self._q[self._h] if self._h < len(self._q) else None
        if isinstance(head, Seg) and not seg.stop:
            # as the backward pass plans it (length * SLACK): a hair more and the head could not keep
            # its own end speed (at the end of the queue: stop) within its length
            vb = min(seg.jgeom, seg.cap, head.cap, max_reach(head.vb, head.length * SLACK, head.a, head.j))
        else:
            vb = 0.0
        stopping = self._stops(seg.ovr)
        if stopping:
            a, j = self._stop_limits(seg)
            traj = self._solve_stop(v, acc, a, j)
            if traj is not None:
                dist = traj.at_time(traj.duration)[0][0]
                if dist <= remaining + 1e-12:
                    self._active = _Active(seg, t_now, traj, s_cur, s_cur + dist, 0.0, act.first)
                    self._v_end = 0.0
                    return
            candidates = [min_reach(max(v, 0.0), remaining, a, j) + k * 0.1 * act.v1 for k in range(11)]
        else:
            a, j = seg.a, seg.j
            top = min(vb, max_reach(max(v, 0.0), remaining, a, j))
            candidates = [top * (1.0 - 0.1 * k) for k in range(11)]
        for target in candidates:
            if target < 0.0 or (stopping and target > act.v1):
                continue
            traj = self._solve(v, acc, remaining, target, seg.cap, a, j)
            if traj is not None:
                self._active = _Active(seg, t_now, traj, s_cur, seg.piece.length, target, act.first)
                self._v_end = target
                return
        log.debug("replan found nothing better; the running profile continues")
