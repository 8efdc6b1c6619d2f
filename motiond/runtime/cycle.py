"""The motion side's cycle: what the ``canon-cycle`` thread does every period, and the state it keeps.

:class:`Cycle` is the base of :class:`motiond.runtime.motion.MotionCore` (whose docstring is the
interface): every period it sends the SYNC first (``master.sync``, at the deadline), runs the calls
posted to it, acts on a pending fault (through the task's ``fault`` hook), moves at most
:data:`FEED_PER_CYCLE` commands from the bounded command queue into the planner (keeping
:data:`LOOKAHEAD` queued there, within :data:`FEED_BUDGET` of the period), takes one setpoint, sends it
with one ``master.cycle`` (for the next SYNC) and reads the drives' feedback back, tracks velocities,
accelerations and jerks against the running job's :class:`~motiond.runtime.records.Stream`, passes the
setpoint's events on (``io.on_setpoint``, the status's spindle / coolant / tool / modal state, messages),
stops at sync points, and tells the task side when the motion comes to rest (an abort, a fault's stop, a
job's end).
Nothing here waits on a network.
"""

from __future__ import annotations

import collections
import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from gcode_canon import commands as C
from gcode_canon.errors import GCodeError
from motiond.runtime.records import ModalState, OutputSwitch, Stream

if TYPE_CHECKING:
    from motiond.runtime.motion import MotionHooks

log = logging.getLogger(__name__)

QUEUE_MAX = 2000
"""Canonical commands the interpreter may run ahead of the planner."""
LOOKAHEAD = 300
"""Items kept queued in the planner (its lookahead); more wait in the interpreter's queue."""
LOOKAHEAD_MOVES = 5000
"""... and programmed moves at most (``Planner.queued_moves``: a merged line or a smoothed chain is one
item holding many moves), as ``plan_all`` keeps; below 2 items the planner is fed regardless."""
FEED_PER_CYCLE = 40
"""At most this many commands move into the planner per cycle (bounds the cycle's work)."""
FEED_BUDGET = 0.25
"""... and, past the two items the planner needs to move on, only while the step has spent less than
this fraction of the period: one command costs the planner 0.1-0.3 ms (its blends walk the lookahead
back), up to 2 ms, so forty at a job's start took 6-8 ms of a 2 ms period. The lookahead fills over
the next cycles instead, at several commands a cycle, faster than a program's moves consume it."""
LATE_LOG = 100_000
"""The lateness of this many late cycles is kept (for the run summary's verdict)."""
END = object()
"""End of a job's commands in the queue."""


def refuse_unfollowed_sync(cmd: C.SpindleSync, followed: bool) -> None:
    """Spindle-synchronized motion (G33, G33.1, G76) without the spindle's position is planned at the
    commanded spindle speed: right for the simulated spindle, which turns exactly as commanded. A real
    spindle lags, slips and speeds up; following it needs its position in the cycle: a spindle drive
    (``[canopen.spindle]``, ``followed``). Rather than cut a thread whose pitch drifts, a real machine
    without one refuses the move."""
    if not followed:
        raise GCodeError("spindle-synchronized motion (G33, G33.1, G76) needs the spindle's position, and "
                         "this machine has no spindle feedback configured: canon would cut at the commanded "
                         "speed, not the spindle's", cmd.file, cmd.line)


class Cycle:
    """The cycle thread's state and step (module docstring). ``hooks``: the task side."""

    def __init__(self, limits: Any, canopen: Any, *, late_fault_s: float, simulated: bool,
                 hooks: MotionHooks) -> None:
        self.limits = limits
        self.names = limits.names
        self.n = len(self.names)
        self.T = limits.cycle_s
        self.canopen = canopen
        self.late_fault_s = late_fault_s
        self.simulated = simulated
        self.hooks = hooks
        self.io: Any = None
        """The IoExecutor (task side): setpoint events are handed to it, output commands checked."""
        self.master: Any = None
        self.planner: Any = None
        self.spindle_drive: Any = None
        """The spindle drive (:class:`~motiond.runtime.spindle_drive.SpindleDriveControl`), or None."""
        self.drive_probe: Any = None
        """G38.x by a drive's touch probe (:class:`~motiond.runtime.probing.DriveProbing`), or None."""
        self.runner: Any = None
        self.feed_budget_s = FEED_BUDGET * self.T
        self._feed_until = float("inf")  # set by each step; no budget when fed outside the cycle
        self._calls: queue.SimpleQueue[Callable[[], None]] = queue.SimpleQueue()
        self._cmdq: queue.Queue[Any] = queue.Queue(QUEUE_MAX)
        self.stream: Stream | None = None
        self._fault_lock = threading.Lock()
        self._pending_fault: tuple[str, str] | None = None
        self._stop_lock = threading.Lock()
        self._estopping = False
        self.hold_stream = False
        self._wait_seen: Any = None
        self._stopped_at: Any = None  # the M0/M1/M60 the planner waits at (resume releases)
        self._sync_cond = threading.Condition()
        self._sync_reached: Any = None
        self.aborting = False
        self.stop_then_disable = False
        self.jogging = False
        self.optional_stop = False
        self.cycle = 0
        self.late_cycles = 0
        self.worst_late_s = 0.0
        self.late_log: collections.deque[tuple[int, float]] = collections.deque(maxlen=LATE_LOG)
        self.commanded = tuple(0.0 for _ in range(self.n))
        self.velocity = tuple(0.0 for _ in range(self.n))
        self._acc = [0.0] * self.n
        self.actual = tuple(0.0 for _ in range(self.n))
        self.actual_t = 0.0
        self.following_error = tuple(0.0 for _ in range(self.n))
        self.drive_inputs: tuple[int, ...] = ()  # 0x60FD per axis, from the last feedback
        self.place = (0, "")  # (line, file) of the last setpoint that carried a line
        self.spindle = (0, 0.0)
        self.coolant = (False, False)
        self.tool_prepared = 0
        self.modal: ModalState | None = None  # the executing block's modal state (a job running)
        self.first_setpoint_t: float | None = None
        self._cycle_ident = 0
        #: setpoints whose events wait for their set of RPDOs to go out (the SYNC process sending them
        #: ahead, [canopen] setpoint_lead): (generation, SYNC tag, setpoint, stream)
        self._pending: collections.deque[tuple[int, int, Any, Stream | None]] = collections.deque()
        self._sp_out: tuple[int, int] | None = None  # (generation, tag) of the last setpoint sent ahead
        self._wait_mark: tuple[Any, tuple[int, int] | None] | None = None  # a sync point, its setpoint
        self.trace: list[tuple[int, float, tuple[float, ...], tuple[Any, ...]]] | None = None
        """Set to a list to record (cycle, monotonic time, positions, events) of every setpoint."""

    def post_fault(self, reason: str, source: str) -> None:
        """Any thread: a fault to be acted on at the start of the next cycle (first one wins)."""
        with self._fault_lock:
            if self._pending_fault is None:
                self._pending_fault = (reason, source)

    def _on_late(self, k: int, by: float) -> None:
        self.late_cycles += 1
        self.late_log.append((self.cycle, by))
        self.worst_late_s = max(self.worst_late_s, by)
        if by > self.late_fault_s and self.master is not None and self.master.streaming:
            self.post_fault(f"cycle {k} started {by * 1e3:.1f} ms late (limit "
                            f"{self.late_fault_s * 1e3:g} ms, period {self.T * 1e3:g} ms)", "motiond")

    def _handle_fault(self) -> None:
        with self._fault_lock:
            pending, self._pending_fault = self._pending_fault, None
        if pending is not None:
            self.hooks.fault(*pending)

    # ------------------------------------------------------------------ the cycle
    def _step(self, k: int, deadline: float) -> None:
        self._feed_until = time.perf_counter() + self.feed_budget_s
        try:
            # one setpoint per SYNC; with the SYNC process sending them ahead ([canopen] setpoint_lead),
            # as many as fill its buffer: none when full, several after a late step
            wanted = self.master.setpoints_wanted()
            self._cycle_step(wanted > 0)
            for _ in range(wanted - 1):
                self._cycle_step(True)
        except Exception as exc:  # a bug must not end the cycle thread with the drives streaming
            log.exception("cycle %d", k)
            self.post_fault(f"internal error in the cycle loop: {exc!r}", "motiond")

    def _cycle_step(self, take: bool = True) -> None:
        """One setpoint (``take``; else the checks only: the SYNC process's buffer is full) and the
        drives' feedback."""
        # the SYNC first, at the deadline: nothing below delays it; the setpoint this step sends is for
        # the next SYNC (master.sync_tick's kernel SYNC has the same structure)
        self.master.sync()
        if self._cycle_ident == 0:
            self._cycle_ident = threading.get_ident()
        self.cycle += 1
        while True:
            try:
                fn = self._calls.get_nowait()
            except queue.Empty:
                break
            fn()
        if self._pending_fault is not None:
            self._handle_fault()
        self.hooks.io_cycle(self.drive_inputs, self.velocity)  # E-stop, limits, buttons, door, waits
        master = self.master
        p = self.planner
        sp = None
        if take and p is not None and master.streaming and not self.hold_stream:
            try:
                self._feed(p)
                # with a spindle drive, synchronized motion follows its measured position
                sp = p.next_setpoint() if self.spindle_drive is None else self.spindle_drive.next_setpoint(p)
            except GCodeError as exc:  # PlannerError
                self.post_fault(str(exc), "planner")
                sp = None
        fb = master.cycle(sp.positions if sp is not None else None)
        self.actual = fb.positions
        self.actual_t = time.monotonic()
        self.following_error = fb.following_errors
        self.drive_inputs = fb.digital_inputs
        if self.spindle_drive is not None:
            self.spindle_drive.on_cycle()  # its feedback; the at-speed and M19 waits
        if self.drive_probe is not None:
            self.drive_probe.on_cycle(self.planner)  # a touch probe trip stops the probing move
        stream = self.stream
        if self.trace is not None and sp is not None:
            self.trace.append((self.cycle, time.monotonic(), sp.positions, sp.events))
        if sp is not None:
            if self.first_setpoint_t is None:
                self.first_setpoint_t = time.monotonic()
            self._track(sp, stream)
            tag = master.last_set_tag
            if tag:  # sent ahead of its SYNC: what rides on it waits until it goes out, with the motion
                self._sp_out = (master.setpoint_generation, tag)
                if sp.events:
                    self._pending.append((master.setpoint_generation, tag, sp, stream))
            elif sp.events:
                self._setpoint_events(sp, stream)
        else:
            self.velocity = tuple(0.0 for _ in range(self.n))
            self._acc = [0.0] * self.n
        if self._pending:
            self._release(master)
        if p is not None and p is self.planner:
            # the planner's stops and its end, once the setpoints before them have gone out
            w = p.waiting_for
            if w is not None and w is not self._wait_seen:
                if self._wait_mark is None or self._wait_mark[0] is not w:
                    self._wait_mark = (w, self._sp_out)  # the setpoint it stands at
                if not self._pending and self._gone_out(master, self._wait_mark[1]):
                    self._wait_mark = None
                    self._wait_seen = w
                    self._on_wait(w)
            if p.is_idle and not self._pending and self._gone_out(master, self._sp_out):
                self._at_rest()
        elif self.planner is None and (self.aborting or self.stop_then_disable):
            self._at_rest()

    @staticmethod
    def _gone_out(master: Any, mark: tuple[int, int] | None) -> bool:
        """The set of RPDOs marked (generation, SYNC tag) went out (or a stop dropped it); None: no
        set was sent ahead."""
        if mark is None:
            return True
        generation, tag = mark
        return generation != master.setpoint_generation or tag - 1 <= master.sync_number

    def _setpoint_events(self, sp: Any, stream: Stream | None) -> None:
        self._events(sp, stream)
        if self.io is not None:
            self.io.on_setpoint(sp)  # the synchronized outputs (M62-M65, M67) riding on it

    def _release(self, master: Any) -> None:
        """The events of the setpoints whose sets have gone out (a set for SYNC ``t`` goes out right
        after SYNC ``t - 1``), so that an output switched with a move, or the end of a move, is not
        acted on ``setpoint_lead - 1`` periods before the drives get there. Those of sets a stop
        dropped (an older generation) never went out: dropped too."""
        pending = self._pending
        generation = master.setpoint_generation
        while pending:
            gen, tag, sp, stream = pending[0]
            if not self._gone_out(master, (gen, tag)):
                return
            pending.popleft()
            if gen == generation:
                self._setpoint_events(sp, stream)

    def _feed(self, p: Any) -> None:
        """Commands from the queue into the planner: the two items it needs to move on whatever they
        cost, then up to its lookahead while the step is within its budget (``_feed_until``)."""
        stream = self.stream
        if stream is None:
            return
        n = 0
        until = self._feed_until
        while n < FEED_PER_CYCLE and (p.queue_length < 2 or (
                p.queue_length < LOOKAHEAD and p.queued_moves < LOOKAHEAD_MOVES
                and time.perf_counter() < until)):
            try:
                item = self._cmdq.get_nowait()
            except queue.Empty:
                return
            n += 1
            if item is END:
                p.flush()
                stream.input_done = True
                return
            if self.io is not None and isinstance(item, C.DigitalOutput | C.AnalogOutput | C.WaitInput):
                problem = self.io.check(item)
                if problem:
                    raise GCodeError(problem, item.file, item.line)
            elif self.io is None and isinstance(item, C.DigitalOutput | C.AnalogOutput):
                raise GCodeError(f"{item.NAME}: this machine has no Modbus I/O configured ([modbus])",
                                 item.file, item.line)
            elif isinstance(item, C.SpindleSync):
                refuse_unfollowed_sync(item, self.simulated or self.spindle_drive is not None)
            p.feed(item)

    def _track(self, sp: Any, stream: Stream | None) -> None:
        T = self.T
        prev = self.commanded
        pos = sp.positions
        vel = tuple((a - b) / T for a, b in zip(pos, prev, strict=True))
        acc = [(a - b) / T for a, b in zip(vel, self.velocity, strict=True)]
        if stream is not None:
            for i, pk in enumerate(stream.peaks):
                v, a = abs(vel[i]), abs(acc[i])
                j = abs(acc[i] - self._acc[i]) / T
                if v > pk.velocity:
                    pk.velocity = v
                if a > pk.acceleration:
                    pk.acceleration = a
                if j > pk.jerk:
                    pk.jerk = j
                fe = abs(self.following_error[i])
                if fe > pk.following_error:
                    pk.following_error = fe
            if sp.line:
                stream.line = sp.line
            if any(vel):
                stream.moving_cycles += 1
            if not stream.t_first:
                stream.t_first = self.actual_t
            stream.t_last = self.actual_t
        self.commanded = pos
        self.velocity = vel
        self._acc = acc
        if sp.line:
            self.place = (sp.line, sp.file)

    def _events(self, sp: Any, stream: Stream | None) -> None:
        for ev in sp.events:
            self.hooks.io_event(ev, stream)  # spindle, coolant: the I/O map's outputs
            if self.spindle_drive is not None:
                self.spindle_drive.on_event(ev)  # S, M3/M4/M5, M19 to the spindle drive
            if isinstance(ev, C.DigitalOutput | C.AnalogOutput):
                if stream is not None:
                    digital = isinstance(ev, C.DigitalOutput)
                    stream.outputs.append(OutputSwitch(
                        self.cycle, time.monotonic(), "digital" if digital else "analog", ev.index,
                        float(ev.on) if digital else ev.value, ev.synced, ev.file, ev.line))
            elif isinstance(ev, C.Message):
                self.hooks.event("DEBUG" if ev.debug else "INFO", ev.text, kind="message", source="gcode",
                                 file=ev.file, line=ev.line)
            elif isinstance(ev, C.SpindleOn):
                self.spindle = (1 if ev.direction is C.SpindleDirection.CW else -1, ev.rpm)
            elif isinstance(ev, C.SpindleOff):
                self.spindle = (0, self.spindle[1])
            elif isinstance(ev, C.SpindleOrient):
                # the planner stopped motion for it and goes on at once: the orientation is done
                # here, before the next setpoint (no spindle drive is wired, as for tool changes)
                self.spindle = (0, self.spindle[1])
                how = "simulated machine" if self.simulated else "no spindle orientation configured"
                wired = self.hooks.orient_text()  # the I/O map's orient output (and oriented input)
                self.hooks.event("INFO", f"spindle orient to {ev.angle:g} deg (P{ev.direction}): "
                                 f"{wired or f'done at once ({how})'}",
                                 kind="spindle_orient", source="motiond", file=ev.file, line=ev.line)
            elif isinstance(ev, C.SetSpindleSpeed):
                self.spindle = (self.spindle[0], ev.rpm)
            elif isinstance(ev, C.Coolant):
                self.coolant = (ev.mist, ev.flood)
            elif isinstance(ev, C.SelectTool):
                self.tool_prepared = ev.tool
            elif isinstance(ev, ModalState):
                self.modal = ev

    def _on_wait(self, w: Any) -> None:
        """Cycle thread: the planner stands at a sync point that waits for the machine."""
        p = self.planner
        if self.spindle_drive is not None and self.spindle_drive.on_wait(w):
            return  # M3/M4 at speed, M19 oriented: the spindle drive completes it
        if self.hooks.io_wait(w):
            return  # spindle at speed, oriented, a user M code: the I/O map completes it
        if isinstance(w, C.ToolChange):
            how = "simulated machine" if self.simulated else "no tool changer configured"
            self.hooks.event("INFO", f"tool change to T{w.tool}: done at once ({how})",
                             kind="tool_change", source="motiond", file=w.file, line=w.line)
            p.release()
        elif isinstance(w, C.ProgramStop | C.PalletShuttle):
            if isinstance(w, C.ProgramStop) and w.optional and not self.optional_stop:
                p.release()
                return
            self._stopped_at = w
            if isinstance(w, C.PalletShuttle):
                what = "M60 pallet shuttle"
            else:
                what = "M1" if w.optional else "M0"
            self.hooks.program_stop(what, w)
        elif self.stream is not None and self.stream.answered_ahead:
            p.release()  # MDI: the job answered this M66 or probe before it queued it: nobody waits
        else:  # M66, probe: the job thread is waiting for this
            self._sync_point_reached(w)

    def _sync_point_reached(self, w: Any) -> None:
        """Cycle thread: the planner stands at ``w`` (an M66, a probe's end or its stop): the job thread
        waiting for it wakes."""
        with self._sync_cond:
            self._sync_reached = w
            self._sync_cond.notify_all()

    def _at_rest(self) -> None:
        """Cycle thread, planner idle: finish an abort, a fault's stop, a job."""
        if self.stop_then_disable:
            self.stop_then_disable = False
            self.planner = None
            self.hooks.disable_after_fault()
            return
        if self.aborting:
            self.aborting = False
            self.hooks.aborted()
            return
        stream = self.stream
        if stream is not None and stream.input_done and self._cmdq.empty():
            self.hooks.stream_done()
        if self.jogging:
            self.jogging = False
