"""The spindle drive (``[canopen.spindle]``) on the motion side: S, M3/M4/M5 and M19 acted on, the M3/M4
wait for the measured speed, M19's orientation, and the drive's feedback for the status.

All of it runs on the cycle thread (:class:`~motiond.runtime.cycle.Cycle` calls :meth:`on_event` for
each setpoint event, :meth:`on_wait` at a sync point, :meth:`on_cycle` after each ``master.cycle``);
nothing waits on the network: the speed goes to the master, which sends it with the next RPDO.

* M3/M4 S: the speed (M4 negative) to the drive; the planner stands at the M3/M4 until the measured
  speed is within ``at_speed_tolerance`` of the commanded one (at most ``max_rpm``), else a fault
  naming the line after ``at_speed_timeout_s``. S alone changes the speed of a turning spindle.
* M5: speed 0 (no wait: the next move may start while the spindle runs down, as with LinuxCNC).
* G33, G76 (:meth:`next_setpoint`): before every setpoint the planner gets the spindle's revolutions
  predicted for the SYNC the setpoint is latched at (measured at the last SYNC, smoothed by
  :class:`PositionSmoother`, plus its measured speed times one cycle), and runs its synchronized moves
  on them (``planner.spindle_sync``). A position
  missing for more than ``max_missed_positions`` SYNCs in a row (bridged from the speed until then)
  stops the following with a fault naming the spindle drive's node.
* G33.1 (a :class:`~planner.spindle_sync.FollowedTap` sync point): the spindle stops; the tap starts
  with it standing, and the axes' setpoint is the tap's start plus the pitch times the revolutions
  turned (predicted as above) along the tap, every cycle: in with the spindle at S in its direction;
  at the depth the spindle is reversed (I times as fast) and the axes follow it through its stop
  (the tap goes as deep as the spindle overshoots, as with LinuxCNC) and back out; at the start the
  axes stand and the spindle is restored to S in its direction. The tap is refused (a fault naming the
  line) when the pitch times the spindle's speed or acceleration exceeds an axis's limits. Mid-tap a
  step the axes cannot make (``follow_jump``: a stalled cycle) or an axis beyond 1.05 x its max_velocity
  over 20 ms (``follow_overspeed``: the spindle running away) holds the tap where it is, the spindle
  stopped, a fault naming the line and the cause.
* M19 R P Q: the spindle stops, then turns at up to ``orient_rpm`` (P1 clockwise, P2
  counter-clockwise, P0 the shorter way) toward R degrees of its position since boot, slowing in
  proportion to the angle left; done when within ``orient_tolerance_deg`` and still (three positions
  in a row), within Q seconds
  (``orient_timeout_s`` without Q), else a fault. The drive then holds speed 0 (velocity control: the
  angle is held by the drive's own velocity loop, not locked in position).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections import deque
from collections.abc import Sequence
from typing import Any

from gcode_canon import commands as C
from planner.setpoints import Setpoint
from planner.spindle_sync import FollowedTap, follow_jump, follow_overspeed, follow_window

#: orientation's position loop: speed (rev/s) per revolution left, i.e. 1 / time constant (s)
ORIENT_GAIN = 4.0
#: the spindle counts as stopped below this speed (rpm)
STILL_RPM = 0.5


class SpindleDriveControl:
    """The spindle drive on the motion side (module docstring). ``cycle``: the :class:`Cycle` (its
    ``master``, ``post_fault``, ``planner``); ``cfg``: the spindle drive's configuration."""

    wait_types: tuple[type[C.Canon], ...] = (C.SpindleOn, C.SpindleOrient, FollowedTap)

    def __init__(self, cycle: Any, cfg: Any) -> None:
        self.c = cycle
        self.cfg = cfg
        self.feedback: Any = None  # the master's SpindleFeedback after the last cycle
        self._rpm = 0.0  # S, unsigned
        self._dir = 0  # 1 M3, -1 M4, 0 stopped
        self._wait: tuple[C.Canon, str, float, float] | None = None  # (command, what, deadline, timeout)
        self._orient: tuple[float, int] | None = None  # (target angle in revolutions, direction P)
        self._orienting = False  # M19: stopped, now turning to the angle
        self._settled = 0  # M19: positions in a row found oriented
        self._settled_sync = -1
        self._tap: _Tap | None = None  # G33.1 in progress
        self.smoother = PositionSmoother()  # the encoder's counts smoothed for following

    # --- setpoints ----------------------------------------------------------------------------------
    def _predicted(self) -> Any:
        """(revolutions, feedback): the revolutions predicted for the SYNC the next setpoint is latched
        at, from the last position, speed and change of speed measured (as many SYNCs ahead as that
        position is old: the setpoint goes out after SYNC ``master.cycles``, for the one after it, and
        the last position answers the SYNC before: two, or more when its TPDO came late)."""
        master = self.c.master
        fb = master.spindle_feedback()
        tau = self.c.T * max(1, master.cycles + 1 - fb.sync)
        revs = self.smoother.update(fb.sync, fb.revolutions, fb.rpm, self.c.T)
        return revs + (fb.rpm + 0.5 * fb.acceleration * tau) / 60.0 * tau, fb

    def next_setpoint(self, p: Any) -> Any:
        """The planner's next setpoint, its synchronized moves run on the spindle's revolutions; during
        a rigid tap, the tap's position instead."""
        revs, fb = self._predicted()
        if self._tap is not None and p is not self._tap.planner:
            self._tap = None  # a new planner: it starts where the axes stand
        # SYNCs since, whose position did not come (the one just sent cannot have answered yet)
        missed = self.c.master.cycles - 1 - fb.sync
        if missed > self.cfg.max_missed_positions:
            self._feedback_lost(p, missed)
        if self._tap is None:
            why = p.follow_spindle(revs)
            if why:  # the axes run on at the planned pace until the fault's stop ramps them down
                self.c.post_fault(f"{why}: the axes stop on their quick-stop ramp", "spindle")
            return p.next_setpoint()
        sp = p.next_setpoint()  # at rest at the tap's sync point (its clock goes on)
        pos = self._tap_step(revs)
        if pos is None:
            return sp
        if sp is None:
            return Setpoint(p._k * self.c.T, pos, self._tap.cmd.file, self._tap.cmd.line)
        return dataclasses.replace(sp, positions=pos)

    def _feedback_lost(self, p: Any, missed: int) -> None:
        """No spindle position for ``missed`` SYNCs: motion following it stops (a fault)."""
        why = (f"node {self.cfg.node_id} (spindle): no position for {missed} SYNCs while motion follows "
               f"it (at most {self.cfg.max_missed_positions} are bridged from its speed, "
               "canopen.spindle.max_missed_positions; TPDOs lost?)")
        t = self._tap
        if t is not None and t.phase in ("in", "out"):
            self._hold_tap(t, f"rigid tap: {why}")
        elif p.follows_spindle:
            where = p.stop_following()
            self.c.post_fault(f"{where}: {why}: the axes stop on their quick-stop ramp", "spindle")

    def _hold_tap(self, t: _Tap, why: str) -> None:
        """Stop a tap in the work as an interrupted one: the spindle stopped, the axes held where they
        are, a fault naming the line and ``why``."""
        t.phase = "held"
        self._command(0.0)
        self._dir = 0
        self.c.post_fault(f"{t.cmd.file}:{t.cmd.line}: {why}: spindle stopped, axes held where they are "
                          "(back it out by hand)", "spindle")

    # --- G33.1 --------------------------------------------------------------------------------------
    def _tap_begin(self, w: FollowedTap) -> str:
        """Start a followed tap; a reason it cannot be done ("" it can)."""
        travel = [e - s for s, e in zip(w.start, w.end, strict=True)]
        length = math.sqrt(sum(d * d for d in travel))
        if length <= 0.0:
            return ""
        top = max(w.rpm, w.rpm * w.scale, 0.0)
        for i, d in enumerate(travel):
            lim = self.c.limits.axes[i]
            share = abs(d) / length
            v = w.pitch * share * min(top, self.cfg.max_rpm) / 60.0
            a = w.pitch * share * self.cfg.acceleration / 60.0
            if v > lim.max_velocity * (1 + 1e-9):
                return (f"rigid tap: pitch {w.pitch:g} at {top:g} rpm moves axis {lim.name.upper()} at "
                        f"{v:g}/s, beyond its max_velocity {lim.max_velocity:g}")
            if a > lim.max_acceleration * (1 + 1e-9):
                return (f"rigid tap: pitch {w.pitch:g} with the spindle's acceleration "
                        f"{self.cfg.acceleration:g} rpm/s moves axis {lim.name.upper()} at {a:g}/s², "
                        f"beyond its max_acceleration {lim.max_acceleration:g}")
        turns = length / w.pitch
        self._tap = _Tap(w, [t / length for t in travel], length,
                         1 if w.direction is C.SpindleDirection.CW else -1, self.c.planner, self.c.T)
        self._tap.deadline = time.monotonic() + 2 * self.cfg.at_speed_timeout_s + 4.0 * turns * 60.0 / max(
            1e-9, min(w.rpm, w.rpm * w.scale))
        self._command(0.0)
        return ""

    def _tap_step(self, revs: float) -> tuple[float, ...] | None:
        """One cycle of the tap: the axes' position (None: not moving yet)."""
        t = self._tap
        assert t is not None
        w = t.cmd
        fb = self.c.master.spindle_feedback()
        if t.phase == "held":
            return t.last
        if t.phase == "stop":
            if abs(fb.rpm) >= STILL_RPM:
                return None
            t.r0 = revs
            t.phase = "in"
            self._command(t.sign * w.rpm)
        d = (revs - t.r0) * t.sign * w.pitch
        if t.phase == "in" and d >= t.length:
            t.phase = "out"
            self._command(-t.sign * w.rpm * w.scale)
        elif t.phase == "out" and d <= 0.0:
            self._tap = None
            self._command(t.sign * w.rpm)
            p = self.c.planner
            if p is not None and p.waiting_for is w:
                p.release()
            return tuple(w.start)
        d = max(0.0, d)
        pos = tuple(s + u * d for s, u in zip(w.start, t.unit, strict=True))
        why = follow_jump(self.c.limits.axes, self.c.T, t.last, pos)
        if not why:  # a spindle running away (faster than the pitch allows the axes) is not followed
            t.window.append((revs, pos))
            why = follow_overspeed(self.c.limits.axes, t.window, self.c.T)
        if why:
            # following it now is a jump no axis can make (a drive faults on it, 0x8400, mid-thread), or
            # beyond the axes' max_velocity: stop here as on an interrupted tap, naming the cause
            self._hold_tap(t, f"rigid tap: {why}")
            return t.last
        t.last = pos
        return t.last

    # --- events -------------------------------------------------------------------------------------
    def _command(self, rpm: float) -> float:
        return self.c.master.set_spindle_speed(rpm)

    def on_event(self, ev: C.Canon) -> None:
        if isinstance(ev, C.SpindleOn):
            self._orient = None
            self._rpm = abs(ev.rpm)
            self._dir = 1 if ev.direction is C.SpindleDirection.CW else -1
            self._command(self._dir * self._rpm)
        elif isinstance(ev, C.SpindleOff):
            self._orient = None
            self._dir = 0
            self._command(0.0)
        elif isinstance(ev, C.SetSpindleSpeed):
            self._rpm = abs(ev.rpm)
            if self._dir:
                self._command(self._dir * self._rpm)
        elif isinstance(ev, C.SpindleOrient):
            self._dir = 0
            self._command(0.0)

    def hold(self, on: bool) -> None:
        """The door: speed 0 (``on``), or back to the speed S and M3/M4 asked for."""
        self._command(0.0 if on else self._dir * self._rpm)

    def at_speed(self) -> bool:
        fb = self.feedback
        if fb is None:
            return False
        want = max(-self.cfg.max_rpm, min(self.cfg.max_rpm, self._dir * self._rpm))
        return abs(fb.rpm - want) <= max(self.cfg.at_speed_tolerance * abs(want), STILL_RPM)

    # --- sync points --------------------------------------------------------------------------------
    def on_wait(self, w: C.Canon, now: float | None = None) -> bool:
        """The planner stands at ``w``: True when the spindle drive completes it (:meth:`on_cycle`
        releases the planner, or posts a fault)."""
        now = time.monotonic() if now is None else now
        where = f"{w.file}:{w.line}: " if w.file else ""
        if isinstance(w, C.SpindleOn):
            word = f"{'M3' if w.direction is C.SpindleDirection.CW else 'M4'} S{w.rpm:g}"
            timeout = self.cfg.at_speed_timeout_s
            self._wait = (w, f"{where}{word}: spindle drive at speed (within "
                             f"{100 * self.cfg.at_speed_tolerance:g} %)", now + timeout, timeout)
            return True
        if isinstance(w, FollowedTap):
            why = self._tap_begin(w)
            if why:
                self.c.post_fault(f"{where}{why}", "spindle")
            elif self._tap is None:  # no travel: nothing to tap
                self.c.planner.release()
            return True
        if isinstance(w, C.SpindleOrient):
            timeout = w.timeout if w.timeout > 0 else self.cfg.orient_timeout_s
            self._orient = ((w.angle / 360.0) % 1.0, w.direction)
            self._orienting = False
            self._settled = 0
            self._wait = (w, f"{where}M19 R{w.angle:g}: spindle drive oriented (within "
                             f"{self.cfg.orient_tolerance_deg:g} deg)", now + timeout, timeout)
            return True
        return False

    def cancel(self) -> None:
        """The job ended (E-stop, abort): no wait. A rigid tap in the work cannot just end (the planner
        would take the axes back to the tap's start at once): the spindle is stopped, the axes hold
        where the tap left them, and it is a fault (the drives are disabled and the next planner starts
        where they stand; back the tap out by hand)."""
        self._wait = None
        self._orient = None
        t = self._tap
        if t is not None and t.phase in ("in", "out"):
            self._hold_tap(t, "rigid tap interrupted with the tap in the work")
        else:
            self._tap = None

    def on_cycle(self, now: float | None = None) -> None:
        self.feedback = fb = self.c.master.spindle_feedback()
        if fb is None:
            return
        if self._orient is not None:
            self._orient_step(fb)
        t = self._tap
        if t is not None and t.phase != "held" and time.monotonic() > t.deadline:
            self._hold_tap(t, f"rigid tap not done in time (spindle at {fb.rpm:.1f} rpm)")
        w = self._wait
        if w is None:
            return
        cmd, what, deadline, timeout = w
        if self._done(cmd, fb):
            self._wait = None
            p = self.c.planner
            if p is not None and p.waiting_for is cmd:
                p.release()
            return
        now = time.monotonic() if now is None else now
        if now > deadline:
            self._wait = None
            self._orient = None
            self._command(0.0)
            self.c.post_fault(f"{what}: not done within {timeout:g} s (measured {fb.rpm:.1f} rpm)", "spindle")

    def _done(self, cmd: C.Canon, fb: Any) -> bool:
        if isinstance(cmd, C.SpindleOn):
            return self.at_speed()
        if self._orient is None:
            return False
        # oriented on three positions in a row (a late TPDO repeats an old one)
        self._settled = self._settled + 1 if self._oriented(fb) and fb.sync != self._settled_sync else (
            self._settled if self._oriented(fb) else 0)
        self._settled_sync = fb.sync
        return self._settled >= 3

    # --- M19 ----------------------------------------------------------------------------------------
    def _left(self, fb: Any) -> float:
        """Revolutions from the spindle's angle to the target, in M19 P's direction (-0.5..0.5 for P0)."""
        assert self._orient is not None
        target, direction = self._orient
        left = (target - fb.revolutions) % 1.0  # 0..1, clockwise (M3: revolutions count up)
        if direction == 2 or (direction == 0 and left > 0.5):
            left -= 1.0
        return left

    def _oriented(self, fb: Any) -> bool:
        left = self._left(fb)
        left = min(abs(left), 1.0 - abs(left))
        return left * 360.0 <= self.cfg.orient_tolerance_deg and abs(fb.rpm) < STILL_RPM

    def _orient_step(self, fb: Any) -> None:
        """Stop first; then toward the angle at a speed in proportion to what is left (position loop
        around the drive's velocity control)."""
        if self._wait is None or not isinstance(self._wait[0], C.SpindleOrient):
            return
        if not self._orienting and abs(fb.rpm) >= STILL_RPM:
            return  # still running down (the M19's own stop)
        self._orienting = True
        left = self._left(fb)
        if abs(left) > 0.5:  # P1/P2: the long way round is taken at full orientation speed
            left = math.copysign(0.5, left)
        rpm = max(-self.cfg.orient_rpm, min(self.cfg.orient_rpm, 60.0 * ORIENT_GAIN * left))
        self._command(rpm)
        if self._oriented(fb):
            self._command(0.0)


class PositionSmoother:
    """The spindle's position as motion follows it: the encoder's counts smoothed without lag.

    Each SYNC's position is predicted from the last one by the measured speed (the mean of the two
    SYNCs' speeds over the SYNCs between: exact for a constant acceleration), then corrected by
    :attr:`GAIN` of the difference to the measured position. The measured counts step by whole counts
    (a pitch / counts_per_revolution of axis travel each), which a third difference over a cycle turns
    into jerk peaks of the followed axis; the drive's speed does not step so. While that speed is right
    the estimate does not lag; a speed off by a fraction e leaves it e x one SYNC's turn / GAIN behind.
    A difference of more than :attr:`RESET_REVS` (a restart, a jump of the count) starts it afresh."""

    #: the share of the measured position taken each SYNC
    GAIN = 0.2
    RESET_REVS = 0.05
    #: SYNCs without a position beyond which the estimate starts afresh
    RESET_SYNCS = 20

    def __init__(self) -> None:
        self._sync: int | None = None
        self._revs = 0.0
        self._rpm = 0.0

    def update(self, sync: int, revolutions: float, rpm: float, T: float) -> float:
        """The smoothed revolutions at SYNC ``sync``, measured ``revolutions`` at ``rpm`` then."""
        last = self._sync
        if last is not None and sync == last:
            return self._revs
        if last is None or not 0 < sync - last <= self.RESET_SYNCS:
            self._sync, self._revs, self._rpm = sync, revolutions, rpm
            return revolutions
        guess = self._revs + (self._rpm + rpm) / 120.0 * T * (sync - last)
        error = revolutions - guess
        self._revs = revolutions if abs(error) > self.RESET_REVS else guess + self.GAIN * error
        self._sync, self._rpm = sync, rpm
        return self._revs


class _Tap:
    """A followed rigid tap in progress: ``phase`` "stop" (the spindle comes to a stand), "in", "out",
    "held" (interrupted: the axes stay at ``last``)."""

    def __init__(self, cmd: FollowedTap, unit: list[float], length: float, sign: int, planner: Any,
                 T: float) -> None:
        self.cmd = cmd
        self.planner = planner
        self.last = tuple(cmd.start)
        self.unit = unit
        self.length = length
        self.sign = sign
        self.phase = "stop"
        self.r0 = 0.0
        self.deadline = math.inf
        #: (revolutions, axes) of the last cycles followed, for :func:`~planner.spindle_sync.follow_overspeed`
        self.window: deque[tuple[float, Sequence[float]]] = follow_window(T)
