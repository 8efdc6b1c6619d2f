"""Spindle-synchronized motion in the planner: G33, G33.1 (rigid tapping) and G76's passes.

Between :class:`~gcode_canon.commands.SpindleSync` and :class:`~gcode_canon.commands.SpindleSyncStop`
a feed move's speed is the pitch times the spindle speed (as G95 feed per revolution), and the feed
override does not apply (the spindle override does, on the spindle). The planner plans with the
commanded spindle speed: on a spindle that turns as commanded (the simulated machine, a spindle drive
in speed control) the motion keeps the pitch. Following a spindle that lags or slips needs its
position feedback in the cycle; the daemon refuses synchronized motion on a real machine without one.
A rigid tap (:class:`~gcode_canon.commands.RigidTap`) is planned as in, stop, spindle reversed, out,
spindle restored: each reversal a spindle start (a sync point). Motion comes to rest where it enters
and where it leaves synchronization (LinuxCNC waits for the spindle's index there and never blends a
synchronized move with a free one): a blend would cut across the thread's start or end. Within it (G76's
tapered entry into the full pitch) moves blend as usual.

With the spindle's measured position (a spindle drive, ``[canopen.spindle]``), the machine calls
:meth:`SpindleSyncMixin.follow_spindle` before every setpoint with the spindle's revolutions, and the
synchronized moves follow them as LinuxCNC's do its spindle index and encoder:

* G33 and G76's passes: a synchronized move that starts at rest waits for the spindle's index (the
  next whole revolution) and then runs its planned profile on the spindle's clock instead of the wall
  clock: each cycle its time advances by the revolutions the spindle turned, divided by the
  revolutions per second it was planned at. In the cruise the path position is the pitch times the
  revolutions since the index plus a constant (the acceleration's lead-in, the same on every pass), so
  every pass of a thread is cut in the same groove whatever the spindle's speed does; a slower spindle
  slows the axis with it.
* G95 (feed per revolution): a move runs on the spindle's clock as well, without the index, and
  never faster than planned (at most the commanded speed's pace: the axes' limits hold): a spindle
  slower than commanded (lagging its ramp, loaded) slows the feed with it, so each revolution
  advances F.
* G33.1 (``follow_taps``): the tap is not planned as moves but queued as a :class:`FollowedTap` sync
  point; the machine runs it, the axis position being the start plus the pitch times the revolutions
  since the spindle stood (``motiond.runtime.spindle_drive``).

Both are guarded by :func:`follow_jump`: a spindle that turned on while no setpoint went out (a stalled
cycle) would have the axes catch up in one step, a target jump the drive faults on (EMCY 0x8400)
mid-thread. Following stops there instead: G33 / G76 run on at their planned pace (the machine's fault
then stops them on their quick-stop ramp), the tap holds where it is; the fault names the line and the
jump. Both are guarded by :func:`follow_overspeed` as well: a spindle measured faster than planned
(an override on the drive, an overshoot, a spindle running away) carries the axes faster on its clock;
an axis beyond :data:`FOLLOW_SPEED_MARGIN` times its max_velocity over :data:`FOLLOW_SPEED_WINDOW_S`
stops following in the same way, the fault naming the line, the axis and the measured rpm. (The
plan-time checks, ``_synced_speed``, cover the commanded rpm: S under G97, the G96 rpm along the
move.) A stop on the path (hold, abort, quick stop) runs on the wall clock, never on the spindle's.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import gcode_canon.commands as C
from planner.machine import AxisLimits
from planner.segments import OVR_FEED, PlannerError

FOLLOW_STEP_MARGIN = 1.25
"""Following the spindle moves an axis at most this many cycles' travel at its max_velocity in one cycle;
more is a step the axis cannot follow (:func:`follow_jump`). At most the drives' own limit: canon sets
their max velocity 0x607F to max_velocity times ``CanopenConfig.velocity_margin`` (1.25), and a drive
faults on a target further than that from the last one (EMCY 0x8400). (It was 2.0, "one late cycle
ridden through": a step between 1.25 and 2 cycles' travel went out and faulted the drive.)"""


def follow_jump(axes: Sequence[AxisLimits], T: float, last: Sequence[float], pos: Sequence[float]) -> str:
    """Why the axes cannot go from ``last`` to ``pos`` in one cycle while following the spindle ("" they
    can): an axis would move more than :data:`FOLLOW_STEP_MARGIN` cycles' travel at its max_velocity."""
    for lim, a, b in zip(axes, last, pos, strict=True):
        most = FOLLOW_STEP_MARGIN * T * lim.max_velocity
        if abs(b - a) > most:
            return (f"axis {lim.name.upper()} would jump {abs(b - a):.3f} {lim.unit} in one cycle to follow "
                    f"the spindle (at most {most:.3f}, what its drive takes: the spindle turned while no "
                    "setpoint went out, a stalled cycle, or its position came late)")
    return ""


FOLLOW_SPEED_MARGIN = 1.05
"""Following the spindle an axis may go at most this many times its max_velocity, averaged over
:data:`FOLLOW_SPEED_WINDOW_S` (a spindle a little faster than planned, its speed's ripple, is ridden
through); beyond, the spindle turns too fast for the pitch (:func:`follow_overspeed`)."""

FOLLOW_SPEED_WINDOW_S = 0.02
"""The time over which a followed axis's speed is taken for :data:`FOLLOW_SPEED_MARGIN` (a cycle's
speed carries the spindle position's prediction error)."""


def follow_window(T: float) -> deque[tuple[float, Sequence[float]]]:
    """An empty window of (revolutions, axis position) for :func:`follow_overspeed`: the cycles of
    :data:`FOLLOW_SPEED_WINDOW_S` at the cycle time ``T`` (at least two)."""
    return deque(maxlen=1 + max(1, round(FOLLOW_SPEED_WINDOW_S / T)))


def follow_overspeed(axes: Sequence[AxisLimits], window: Sequence[tuple[float, Sequence[float]]],
                     T: float) -> str:
    """Why following the spindle cannot go on ("" it can): over ``window`` ((revolutions, axis position)
    of consecutive cycles) an axis went faster than :data:`FOLLOW_SPEED_MARGIN` times its
    max_velocity."""
    if len(window) < 2:
        return ""
    (r0, p0), (r1, p1) = window[0], window[-1]
    dt = (len(window) - 1) * T
    for lim, a, b in zip(axes, p0, p1, strict=True):
        v = abs(b - a) / dt
        if v > FOLLOW_SPEED_MARGIN * lim.max_velocity:
            return (f"the spindle turns at {abs(r1 - r0) * 60.0 / dt:.0f} rpm (measured), too fast for the "
                    f"pitch: axis {lim.name.upper()} would move at {v:.4g} {lim.unit}/s, beyond its "
                    f"max_velocity {lim.max_velocity:g} (x{FOLLOW_SPEED_MARGIN:g})")
    return ""


@dataclass(frozen=True, slots=True)
class FollowedTap(C.Canon):
    """G33.1 on a machine that follows the spindle's measured position: a sync point the machine
    completes. ``start`` and ``end``: machine positions (the planner's axis order); ``pitch`` per
    revolution; the spindle at ``rpm`` in ``direction`` going in, ``scale`` times as fast reversed
    coming out; the spindle is restored to ``rpm`` / ``direction`` afterwards."""

    NAME: ClassVar[str] = "RIGID_TAP_FOLLOWED"
    SYNC: ClassVar[bool] = True
    start: tuple[float, ...]
    end: tuple[float, ...]
    pitch: float
    rpm: float
    direction: C.SpindleDirection
    scale: float = 1.0


class SpindleSyncMixin:
    """Planner state used: ``_sync_pitch``, ``_spindle_rpm``, ``_spindle_dir``, ``_ovr``, ``_pose``, the
    running profile and the last setpoint."""

    _sync_pitch: float | None
    _spindle_rpm: float
    _spindle_dir: C.SpindleDirection
    _ovr: int
    _pose: list[float]
    _exact_next: bool
    _pending: list[C.Canon]
    _active: Any
    _k: int
    _last_pos: list[float]
    _css: Any  # planner.css.SurfaceSpeed
    _css_rpm: float | None = None  # G95 under G96: the rpm the line's piece being queued is planned at
    _end: list[float]
    _feed_mode: C.FeedMode
    _mode: C.MotionControlMode
    machine: Any
    T: float
    #: G33.1 queued as a :class:`FollowedTap` for the machine to run (its spindle feedback)
    follow_taps: bool = False
    # measured-position following (follow_spindle): synchronized commands' (pitch, rpm, sign, locked:
    # G33 / G76 rather than G95) by id,
    # the segment followed, its time on the spindle's clock, the last revolutions, the index awaited
    _synced_cmds: dict[int, tuple[float, float, int, bool]]
    _sp_seg: Any = None
    _sp_tau = 0.0
    _sp_last = 0.0
    _sp_index: float | None = None
    _sp_act: Any = None  # the running profile followed (a replan of the same move makes a new one)
    _sp_broken = False  # a jump was refused: no following until the planner is made again
    _sp_window: deque[tuple[float, Sequence[float]]] | None = None  # (revolutions, axes) of the last cycles

    def _spindle_sync(self, cmd: C.Canon) -> None:
        if isinstance(cmd, C.RigidTap):
            self._rigid_tap(cmd)
        elif isinstance(cmd, C.SpindleSync):
            if not (math.isfinite(cmd.pitch) and cmd.pitch > 0):
                raise PlannerError(f"spindle-synchronized motion needs a pitch > 0, got {cmd.pitch:g}",
                                   cmd.file, cmd.line)
            if self._sync_pitch is None:
                self._close_tail()  # type: ignore[attr-defined]  # a synchronized move starts at rest
            self._sync_pitch = cmd.pitch
            self._pending.append(cmd)  # passed on: the machine knows a synchronized move comes
        else:
            self._close_tail()  # type: ignore[attr-defined]  # and ends at rest: never blended out
            self._sync_pitch = None
            self._pending.append(cmd)

    def _synced_speed(self, cmd: C.Canon) -> float:
        """Path speed (units/s) of a synchronized feed move: pitch times the spindle's revolutions."""
        assert self._sync_pitch is not None
        if self._spindle_rpm <= 0:
            raise PlannerError("spindle-synchronized motion (G33, G33.1, G76) needs a turning spindle",
                               cmd.file, cmd.line)
        end = self._sync_move_end()
        top = self._pitch_rpm_cap(end)
        if self._css.in_css:
            rpm = self._css_sync_rpm(cmd, end, top)
            fastest = self._css.highest_rpm(self._end[self._css.x_index], end[self._css.x_index])
            what = f"under G96 turns the spindle at up to {fastest:.0f} rpm along this move"
            most = f"{math.floor(top):g} rpm"
            fix = "lower S or D"
        else:
            rpm = fastest = self._spindle_rpm
            what, most, fix = f"at S{rpm:g}", f"S{math.floor(top):g}", "lower S"
        if fastest > top * (1.0 + 1e-9):
            raise PlannerError(
                f"spindle-synchronized motion {what} with a pitch of {self._sync_pitch:g} needs the axes "
                f"faster than their max_velocity allows (at most {most} for this move): the thread's "
                f"pitch would not hold; {fix}", cmd.file, cmd.line)
        self._note_synced(cmd, self._sync_pitch, locked=True, rpm=rpm)
        return self._sync_pitch * rpm / 60.0

    def _sync_move_end(self) -> list[float]:
        """The end (machine, the planner's axis order) of the synchronized move being queued: where
        ``_target`` put it in ``_pose``."""
        return [self._pose[i] for i in self._pose_index]  # type: ignore[attr-defined]

    def _pitch_rpm_cap(self, end: Sequence[float]) -> float:
        """The highest rpm at which the synchronized move to ``end`` keeps its axes within their
        max_velocity at the pitch (``inf`` for a move of no length). Beyond it the axes' cap would
        shorten the pitch: on the spindle's clock the axes lag the turns, in a thread cut at the wrong
        pitch."""
        delta = [b - a for a, b in zip(self._end, end, strict=True)]
        length = math.hypot(*delta)
        tiny = 1e-12 * (1.0 + length)
        top = min((lim.max_velocity * length / abs(d) for lim, d in zip(self.machine.axes, delta, strict=True)
                   if abs(d) > tiny), default=math.inf)
        assert self._sync_pitch is not None
        return top * 60.0 / self._sync_pitch

    def _css_sync_rpm(self, cmd: C.Canon, end: Sequence[float], top: float) -> float:
        """G33 / G76 under G96 (LinuxCNC runs them: its spindle turns at the G96 rpm of the commanded X,
        the axes follow its position). Followed on the spindle's measured position (``follow_taps``),
        a move is planned at D (at most ``top``, the rpm at which its axes keep their max_velocity): on
        the spindle's clock the pitch holds at whatever rpm G96 gives, and every pass has the same
        lead-in (the same groove). Otherwise at the G96 rpm along the move (the lowest: a straight pass
        has one), as the spindle is commanded to turn."""
        mode = self._css.intake_mode
        if self.follow_taps:
            if mode.css_max >= 1e29:
                raise PlannerError("spindle-synchronized motion under constant surface speed (G96) needs "
                                   "its D word (the highest rpm): a thread followed on the spindle is "
                                   "planned at it", cmd.file, cmd.line)
            return min(float(mode.css_max), top)
        x = self._css.x_index
        return min(self._css.rpm_at(self._end[x]), self._css.rpm_at(end[x]))

    def _per_rev_speed(self, cmd: C.Canon, rate: float, piece: Any = None) -> float:
        """Path speed of a G95 move (units/s): F per revolution at the commanded speed; under G96 at the
        lowest G96 rpm along it (a line's piece: :meth:`_per_rev_css_line`; an arc ``piece``: sampled)."""
        rpm = self._spindle_rpm
        if self._css.in_css:
            if self._css_rpm is not None:
                rpm = self._css_rpm
            else:
                x = self._css.x_index
                n = 64
                rpm = min(self._css.rpm_at(piece.pos(piece.length * k / n)[x]) for k in range(n + 1))
        self._note_synced(cmd, rate, locked=False, rpm=rpm)
        return rate * rpm / 60.0

    def _per_rev_css_line(self, cmd: C.Canon) -> bool:
        """G95 under G96 (planner.css): a feed line is queued as pieces within which the G96 rpm changes
        by at most ``CSS_PIECE_RATIO``, each planned at F times its lowest rpm (at an end: the radius
        along a line is largest at one of them). False: not such a move (planned as it is)."""
        if (not self._css.in_css or self._feed_mode is not C.FeedMode.UNITS_PER_REV
                or self._css_rpm is not None or self._sync_pitch is not None
                or not isinstance(cmd, C.StraightFeed)):
            return False
        x = self._css.x_index
        assert x is not None
        start_pose, start = list(self._pose), list(self._end)
        end = self._target(cmd, cmd.end)  # type: ignore[attr-defined]  # the soft limits, once
        self._pose = start_pose
        stops = self._mode in (C.MotionControlMode.EXACT_STOP_MODAL, C.MotionControlMode.EXACT_STOP)
        cuts = [] if stops else self._css.split_line(start[x], end[x])  # (each piece would stop)
        exact = self._exact_next
        bounds = [0.0, *cuts, 1.0]
        try:
            for i, (u0, u1) in enumerate(itertools.pairwise(bounds)):
                last = i == len(bounds) - 2
                self._css_rpm = min(self._css.rpm_at(start[x] + u * (end[x] - start[x])) for u in (u0, u1))
                self._exact_next = exact and last
                self._motion(cmd if last else dataclasses.replace(  # type: ignore[attr-defined]
                    cmd, end=C.Pose(*[a + u1 * (b - a) for a, b in zip(start_pose, cmd.end, strict=True)])))
        finally:
            self._css_rpm = None
        return True

    def _note_synced(self, cmd: C.Canon, pitch: float, locked: bool, rpm: float | None = None) -> None:
        if not hasattr(self, "_synced_cmds") or len(self._synced_cmds) > 4096:
            self._synced_cmds = {}  # ids of moves long run (bounded: a move is followed while it runs)
        sign = 1 if self._spindle_dir is C.SpindleDirection.CW else -1
        self._synced_cmds[id(cmd)] = (pitch, self._spindle_rpm if rpm is None else rpm, sign, locked)

    def follow_spindle(self, revolutions: float) -> str:
        """Before :meth:`next_setpoint`, every cycle, on a machine with the spindle's position: its
        revolutions (M3 counting up) at the time the next setpoint takes effect. A synchronized move
        runs on the spindle's clock (module docstring); other motion is not touched. Returns a fault
        (``FILE:LINE: ...``) when following would jump the axes (:func:`follow_jump`): the move then
        runs on at its planned pace, and nothing is followed any more."""
        act = self._active
        info = None if act is None else getattr(self, "_synced_cmds", {}).get(id(act.seg.cmd))
        if info is None or self._sp_broken or self._stops(act.seg.ovr):  # type: ignore[attr-defined, union-attr]
            # (a stop on the path, hold or abort, runs on the wall clock: its ramp from where the axes are)
            self._sp_seg = None
            self._sp_last = revolutions
            return ""
        _pitch, rpm, sign, locked = info
        t_next = (self._k + 1) * self.T
        if act.seg is not self._sp_seg:  # a synchronized move began with the last setpoint
            self._sp_seg = act.seg
            self._sp_window = follow_window(self.T)
            from_rest = abs(act.traj.at_time(0.0)[1][0]) < 1e-12 and act.s_off <= act.seg.s0 + 1e-12
            self._sp_tau = max(0.0, t_next - self.T - act.t0)  # its time so far (one cycle's at most)
            self._sp_index = None
            if from_rest and locked:  # wait for the spindle's index: the next whole revolution
                self._sp_tau = 0.0
                self._sp_index = math.floor(revolutions) + 1.0 if sign > 0 else math.ceil(revolutions) - 1.0
        elif act is not self._sp_act:  # the move re-planned from where it is (an override): its new profile
            self._sp_tau = max(0.0, t_next - self.T - act.t0)
        self._sp_act = act
        turned = (revolutions - self._sp_last) * sign
        if self._sp_index is not None:  # still before the index: the move has not begun
            past = (revolutions - self._sp_index) * sign
            turned = max(0.0, past)
            if past >= 0.0:
                self._sp_index = None
        self._sp_last = revolutions
        step = max(0.0, turned) * 60.0 / rpm
        tau = self._sp_tau + (step if locked else min(step, self.T))
        if locked:
            p = min(act.traj.at_time(min(tau, act.traj.duration))[0][0] + act.s_off, act.s_end)
            pos = act.seg.piece.pos(p)
            why = follow_jump(self.machine.axes, self.T, self._last_pos, pos)
            if not why and self._sp_window is not None:
                self._sp_window.append((revolutions, pos))
                why = follow_overspeed(self.machine.axes, self._sp_window, self.T)
            if why:
                self._sp_broken = True  # on at the planned pace from here: act.t0 as it was
                cmd = act.seg.cmd
                return f"{cmd.file}:{cmd.line}: spindle-synchronized motion: {why}"
        self._sp_tau = tau
        act.t0 = t_next - self._sp_tau
        act.t_end = act.t0 + act.traj.duration
        return ""

    @property
    def follows_spindle(self) -> bool:
        """A move runs on the spindle's clock now (or waits for its index)."""
        act = self._active
        synced = getattr(self, "_synced_cmds", {})
        return (act is not None and not self._sp_broken and id(act.seg.cmd) in synced
                and not self._stops(act.seg.ovr))  # type: ignore[attr-defined]

    def stop_following(self) -> str:
        """The spindle's position cannot be had: the running move goes on at its planned pace (the
        machine's fault stops it on its ramp) and nothing is followed any more. Returns where the
        move is (``FILE:LINE``)."""
        self._sp_broken = True
        act = self._active
        return "" if act is None else f"{act.seg.cmd.file}:{act.seg.cmd.line}"

    def _seg_ovr(self, rapid: bool) -> int:
        """The override switches a new move obeys: a spindle-synchronized feed ignores the feed
        override (its pace is the spindle's; LinuxCNC does the same)."""
        if self._sync_pitch is not None and not rapid:
            return self._ovr & ~OVR_FEED
        return self._ovr

    def _rigid_tap(self, cmd: C.RigidTap) -> None:
        """G33.1: in to ``end`` at the pitch, stop; the spindle reversed (``scale`` times as fast);
        out to where the tap started at the pitch; the spindle as it was. Each reversal is a spindle
        start (a sync point: motion at rest, the spindle up to speed before the next move)."""
        if self._sync_pitch is None:
            raise PlannerError("RIGID_TAP outside spindle-synchronized motion", cmd.file, cmd.line)
        if self._spindle_rpm <= 0:
            raise PlannerError("rigid tapping (G33.1) needs a turning spindle", cmd.file, cmd.line)
        if not (math.isfinite(cmd.scale) and cmd.scale >= 1.0):
            raise PlannerError(f"rigid tap retract scale must be >= 1, got {cmd.scale:g}", cmd.file, cmd.line)
        where: dict[str, Any] = {"file": cmd.file, "line": cmd.line}
        back = C.Pose(*self._pose)
        rpm, forward = self._spindle_rpm, self._spindle_dir
        if self.follow_taps:
            start = tuple(self._end)  # type: ignore[attr-defined]
            end = tuple(self._target(cmd, cmd.end))  # type: ignore[attr-defined]  # checks the soft limits
            self._pose = list(back)  # the tap ends where it started
            self._sync(FollowedTap(start, end, self._sync_pitch, rpm, forward, cmd.scale,  # type: ignore[attr-defined]
                                   **where))
            return
        reverse = C.SpindleDirection.CCW if forward is C.SpindleDirection.CW else C.SpindleDirection.CW
        self._exact_next = True
        self._motion(  # type: ignore[attr-defined]
            C.StraightFeed(cmd.end, **where))
        self.feed(  # type: ignore[attr-defined]
            C.SpindleOn(reverse, rpm * cmd.scale, **where))
        self._exact_next = True
        self._motion(  # type: ignore[attr-defined]
            C.StraightFeed(back, **where))
        self.feed(  # type: ignore[attr-defined]
            C.SpindleOn(forward, rpm, **where))

