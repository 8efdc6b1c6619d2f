"""The motion side: the CANopen master's cycle, planner feeding, setpoint tracking, faults, quick stop.

:class:`MotionCore` is the part of the machine that is to run in a process of its own (issue 14; the
task side is :mod:`motiond.runtime.machine` and its parts). It owns the
:class:`~fieldbus.canopen.master.CanopenMaster`, the :class:`~planner.core.Planner` (which only the
cycle thread touches: it is not thread-safe) and the ``canon-cycle`` thread (a
:class:`~fieldbus.canopen.clock.PeriodicRunner` on absolute deadlines running
:class:`~motiond.runtime.cycle.Cycle`'s step, MotionCore's base: pending calls, the pending fault,
feeding the planner from the command queue, one setpoint, one ``master.cycle``, ``io.on_setpoint``).
Nothing the cycle thread does waits on a network.

Its interface is narrow on purpose; the task side uses nothing else (tests/test_runtime_boundary.py
checks that every name it uses is one of those below):

Life: :meth:`~MotionCore.open` (master up, drives booted), :meth:`~MotionCore.start_cycle`,
:meth:`~MotionCore.stop_cycle`, :meth:`~MotionCore.close`.

In (task -> motion)
  * canonical commands through one bounded queue (:data:`QUEUE_MAX`): :meth:`MotionCore.put` (the job
    thread; blocks while full, gives up when the job is cancelled; a probing move, with a drive's
    touch probe, waits for rest and arms it first), :data:`END` after a job's last command;
    :meth:`~MotionCore.begin_stream` / :meth:`~MotionCore.end_stream` around a job (its
    :class:`~motiond.runtime.records.Stream` accounting), :meth:`~MotionCore.drop_commands`,
    :meth:`~MotionCore.wake_waiters` (a cancelled job thread waiting for a sync point looks again).
  * urgent calls, explicit methods that act within a cycle and never queue behind the commands:
    :meth:`~MotionCore.quick_stop` (any thread, at once), :meth:`~MotionCore.estop`,
    :meth:`~MotionCore.abort`, :meth:`~MotionCore.pause`, :meth:`~MotionCore.resume`,
    :meth:`~MotionCore.feed_override`, :meth:`~MotionCore.spindle_hold` (the door: the spindle drive
    stopped and back), :meth:`~MotionCore.spindle_at_speed`; and the manual ones, :meth:`~MotionCore.jog`,
    :meth:`~MotionCore.jog_stop`.
  * :meth:`~MotionCore.use_probe_input`: G38.x on the I/O map's probe input where no drive has a
    touch probe (:mod:`motiond.runtime.probing_io`; with ``[motion] process = "own"`` the input is read
    in the task process: :mod:`motiond.runtime.probing_proxy`).
  * control of the stream: ``hold_stream`` (the drives get no setpoint: a service operation talks to
    them), ``optional_stop``, :meth:`~MotionCore.new_planner`, :meth:`~MotionCore.drop_planner`,
    :meth:`~MotionCore.release_wait`, :meth:`~MotionCore.post_fault`, :meth:`~MotionCore.clear_fault`,
    :meth:`~MotionCore.fault_stop` (from the task's fault hook).
Out (motion -> task)
  * :meth:`~MotionCore.snapshot`: a :class:`MotionSnapshot` (positions, velocities, following errors,
    the line, spindle / coolant / tool as the setpoints carried them, the modal state of the block
    being cut, the feed override, every drive's state), any thread, never blocking the cycle;
    :meth:`~MotionCore.position` (where the motion stands, asked of the cycle thread),
    :meth:`~MotionCore.drained` (nothing queued, nothing left to run); the counters ``cycle``,
    ``late_cycles``, ``worst_late_s``, ``late_log``; the last setpoint's ``commanded`` position, the
    drives' ``actual`` one and its ``place`` (line, file); and the flags ``has_planner``,
    ``is_moving``, ``aborting``, ``stopping`` (an abort's or a fault's stop not yet at rest),
    ``fault_stopping``.
  * :class:`MotionHooks`, called on the cycle thread (they must not block): events, a fault to act
    on, the stream to cancel, the stream done, an abort finished, a program stop reached, the drives
    to disable after a fault's stop; and the planner's priming commands; the I/O map's (docs/wiring.md:
    ``io_cycle`` at the start of each cycle with the drives' 0x60FD inputs and the velocities,
    ``io_event`` per setpoint event, ``io_wait`` at a sync point, ``planner_waits``, ``orient_text``).
    The Modbus executor (``io``) is the motion side's too: the I/O map's outputs go out from the cycle
    thread, never waiting on the network (with ``[motion] process = "own"`` it stays in the task
    process, and these hooks cross the boundary: :mod:`motiond.runtime.io_loop`).
  * :meth:`~MotionCore.wait_sync_point`: the job thread waits until the planner stands at an M66 or
    a probe; with a drive's touch probe (``has_touch_probe``) :meth:`~MotionCore.probe` instead: the
    probing move's end or its trip, and the probed point (:class:`~motiond.runtime.probing.Probed`).

Two more things cross: :meth:`~MotionCore.run_on_cycle` (the task's job bookkeeping ordered with the
hooks) and the service operations' SDO calls on ``master`` (enable, disable, home, boot,
reset_faults, off the cycle thread). With ``[motion] process = "own"`` MotionCore runs in a process of
its own (:mod:`motiond.runtime.motion_proc`) and the task side holds a
:class:`~motiond.runtime.motion_proxy.MotionProxy` with this interface: ``run_on_cycle`` then runs on
the task's hook thread, the SDO calls are requests the motion process serves on a thread of its own.
"""

from __future__ import annotations

import concurrent.futures
import logging
import math
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from gcode_canon import commands as C
from motiond.runtime.cycle import END, FEED_PER_CYCLE, LATE_LOG, LOOKAHEAD, QUEUE_MAX, Cycle
from motiond.runtime.probing import Probed
from motiond.runtime.records import ModalState, Stream, deferred
from motiond.states import CommandRefused

log = logging.getLogger(__name__)

__all__ = ["END", "FEED_PER_CYCLE", "LATE_LOG", "LOOKAHEAD", "QUEUE_MAX", "DriveView", "MotionCore",
           "MotionHooks", "MotionSnapshot"]

NMT_NAMES = {0: "INITIALISING", 4: "STOPPED", 5: "OPERATIONAL", 127: "PRE-OPERATIONAL"}


class MotionHooks(Protocol):
    """What the motion side tells the task side; every method is called on the cycle thread and must
    return at once (post work elsewhere)."""

    def event(self, severity: str, text: str, *, kind: str = "", source: str = "motiond", file: str = "",
              line: int = 0) -> None: ...

    def fault(self, reason: str, source: str) -> None:
        """A fault to act on (the first since the last one): stop (:meth:`MotionCore.fault_stop`),
        cancel the job, FAULTED."""

    def cancel_stream(self, error: str, aborted: bool) -> None:
        """The running job is to end now (E-stop, abort): drop its commands, finish it."""

    def stream_done(self) -> None:
        """The job's commands all ran and the motion is at rest."""

    def aborted(self) -> None:
        """An abort's stop on the path is at rest (or there was nothing to stop)."""

    def program_stop(self, what: str, w: C.Canon) -> None:
        """The planner stands at an M0 / M1 / M60 (``what``) and waits for :meth:`MotionCore.resume`."""

    def disable_after_fault(self) -> None:
        """A fault's stop on the path is at rest: the drives are to be disabled (by SDO, elsewhere)."""

    def planner_prime(self) -> list[C.Canon]:
        """The modal commands a new planner starts with (feed mode, feed, path control, speed)."""

    def planner_waits(self) -> tuple[type[C.Canon], ...]:
        """Sync commands beyond the planner's own waits that the machine completes (M3 with an
        at-speed signal, M19 with an oriented one, user M codes): the planner stays at rest there."""

    def io_cycle(self, drive_inputs: tuple[int, ...], velocity: tuple[float, ...]) -> None:
        """Start of each cycle: the I/O map's inputs (E-stop, limits, buttons, door) and its waits."""

    def io_event(self, ev: C.Canon, stream: Any) -> None:
        """A setpoint event (spindle, coolant) for the I/O map's outputs."""

    def io_wait(self, w: C.Canon) -> bool:
        """The planner stands at ``w``: True when the I/O map completes it (then it releases)."""

    def orient_text(self) -> str:
        """What M19 does on this machine's wiring ("" nothing wired), for its event."""


@dataclass(frozen=True, slots=True)
class DriveView:
    """One drive as the master last saw it."""

    axis: str
    node: int
    nmt_state: str
    operational: bool
    heartbeat_ok: bool
    statusword: int
    cia402_state: str
    actual_counts: int
    following_error: int
    emcy_code: int
    error: str


@dataclass(frozen=True, slots=True)
class MotionSnapshot:
    """The motion side's state for the status (docs/telemetry.md's ``canon.status``)."""

    cycle: int
    commanded: tuple[float, ...]
    actual: tuple[float, ...]
    actual_t: float  # monotonic time of the cycle that brought ``actual``
    velocity: tuple[float, ...]
    following_error: tuple[float, ...]
    line: int  # of the last setpoint that carried one
    file: str
    modal: ModalState | None
    feed_override: float
    spindle: tuple[int, float]  # direction (1 M3, -1 M4, 0 off), speed
    coolant: tuple[bool, bool]  # mist, flood
    tool_prepared: int
    jogging: bool
    drives: tuple[DriveView, ...]
    #: the spindle drive's feedback (:class:`~fieldbus.canopen.master_spindle.SpindleFeedback`), or None
    spindle_drive: Any = None


class MotionCore(Cycle):
    """The motion side's interface (module docstring); the cycle itself is :class:`Cycle`."""

    # ------------------------------------------------------------------ life cycle
    def open(self) -> None:
        """Create the master and boot the drives (CanopenError, or python-can's errors, on failure)."""
        from fieldbus.canopen.master import CanopenMaster

        self.master = CanopenMaster(self.canopen)
        self.master.add_fault_listener(self._on_master_fault)
        self.master.add_warning_listener(self._on_master_warning)
        self.master.open()
        self.master.boot()
        from fieldbus.canopen.touch_probe import TouchProbe
        from motiond.runtime.probing import DriveProbing

        probe = TouchProbe.of(self.master)
        self.drive_probe = None if probe is None else DriveProbing(self, probe)
        if self.canopen.spindle is not None:
            from motiond.runtime.spindle_drive import SpindleDriveControl

            self.spindle_drive = SpindleDriveControl(self, self.canopen.spindle)

    def start_cycle(self) -> None:
        from fieldbus.canopen.clock import PeriodicRunner

        self.runner = PeriodicRunner(self.T, self._step, on_late=self._on_late, keep_lateness=False,
                                     name="canon-cycle",
                                     realtime_priority=self.canopen.realtime_priority,
                                     cpu_latency_us=self.canopen.cpu_latency_us,
                                     cpu_affinity=self.canopen.cpu_affinity,
                                     steer_gc=self.canopen.steer_gc, tick=self.master.sync_tick)
        self.runner.start()

    def stop_cycle(self) -> None:
        """The cycle stops for good (the machine closes), and with it the SYNC, whoever times it: no
        SYNC goes out without setpoints (:meth:`CanopenMaster.stop_sync`)."""
        if self.runner is not None:
            self.runner.stop()
            self.runner.join(2.0)
            self.runner = None
        if self.master is not None:
            self.master.stop_sync()

    def close(self) -> None:
        if self.master is not None:
            try:
                self.master.shutdown()
            except Exception:
                log.exception("shutting the CANopen master down")

    def run_on_cycle(self, fn: Callable[[], Any], *, wait: bool = True, timeout: float = 2.0) -> Any:
        """Run ``fn`` on the cycle thread (which owns the planner) and return its result; inline when
        the cycle thread is not running or is the caller."""
        runner = self.runner
        # the cycle thread itself (the I/O map's E-stop, door, buttons): inline (join would raise)
        if runner is None or threading.get_ident() == self._cycle_ident or runner.join(0):
            return fn()
        call, fut = deferred(fn)
        self._calls.put(call)
        if not wait:
            return None
        return fut.result(timeout)

    # ------------------------------------------------------------------ commands in
    def put(self, item: Any, cancel: threading.Event) -> bool:
        """Job thread: queue a canonical command (or :data:`END`), waiting while the queue is full;
        False when ``cancel`` is set first. A probing move with a drive's touch probe: first the
        motion before it comes to rest and the probe is armed (:mod:`motiond.runtime.probing`)."""
        if isinstance(item, C.Probe) and self.drive_probe is not None:
            if not self.drive_probe.before_move(item, cancel):
                return False
            if self.drive_probe.tripped_at_start:
                return True  # G38.3/G38.5 with the probe already in that state: the move is not made
        while not cancel.is_set():
            try:
                self._cmdq.put(item, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def begin_stream(self, stream: Stream, modal: ModalState) -> None:
        """A job starts: its accounting, and the modal state shown until its first line moves."""
        self.modal = modal
        self._wait_seen = None
        self._sync_reached = None
        self._stopped_at = None
        self.stream = stream

    def end_stream(self) -> None:
        self.stream = None

    def drop_commands(self) -> None:
        """The queued commands dropped; a job thread waiting for a sync point wakes (to see its cancel)."""
        while True:
            try:
                self._cmdq.get_nowait()
            except queue.Empty:
                break
        self.wake_waiters()

    def wake_waiters(self) -> None:
        with self._sync_cond:
            self._sync_cond.notify_all()

    def drained(self) -> bool:
        """The queue is empty and the planner has nothing left to run (or there is none)."""
        def idle() -> bool:
            p = self.planner
            return p is None or (p.is_idle and p.queue_length == 0)

        return self._cmdq.empty() and bool(self.run_on_cycle(idle))

    def wait_sync_point(self, cmd: Any, cancel: threading.Event) -> bool:
        """Job thread: block until the planner stands at ``cmd``; False when ``cancel`` is set first."""
        with self._sync_cond:
            while self._sync_reached is not cmd:
                if cancel.is_set():
                    return False
                self._sync_cond.wait(0.05)
        return True

    def drive_output(self, axis: int, bit: int, on: bool) -> Any:
        """Bit ``bit`` of drive ``axis``'s digital outputs (0x60FE), for the I/O map: a future, the
        master's ``canon-do`` thread writes it by SDO (never blocks the caller)."""
        if self.master is None:
            import concurrent.futures

            fut: concurrent.futures.Future[float] = concurrent.futures.Future()
            fut.set_exception(RuntimeError("the CANopen master is not open"))
            return fut
        return self.master.set_output(axis, bit, on)

    def use_probe_input(self, mio: Any) -> None:
        """G38.x on the I/O map's ``probe`` input (read by ``mio``, the task's
        :class:`~motiond.machine_io.MachineIO`) unless a drive's touch probe is the probe."""
        if self.drive_probe is None:
            from motiond.runtime.probing_io import InputProbing

            self.drive_probe = InputProbing(self, mio)

    @property
    def has_touch_probe(self) -> bool:
        """G38.x uses a drive's touch probe (``canopen.axes.<a>.touch_probe``)."""
        return self.drive_probe is not None

    def probe(self, cmd: C.Probe, cancel: threading.Event) -> Probed | None:
        """Job thread, with a drive's touch probe: wait for the probing move ``cmd`` to end (at its
        end point or stopped by the trip), let the planner go on, and return what the probe latched
        (GCodeError when the drive does not answer); None when ``cancel`` is set first."""
        assert self.drive_probe is not None
        return self.drive_probe.answer(cmd, cancel)

    def release_wait(self) -> None:
        """The sync point answered (M66 read, probe done): the planner goes on."""
        def release() -> None:
            if self.planner is not None and self.planner.waiting_for is not None:
                self.planner.release()

        self.run_on_cycle(release, wait=False)

    # ------------------------------------------------------------------ the planner
    @property
    def has_planner(self) -> bool:
        return self.planner is not None

    @property
    def is_moving(self) -> bool:
        p = self.planner
        return p is not None and not p.is_idle

    @property
    def stopping(self) -> bool:
        """An abort's or a fault's stop on the path has not come to rest yet."""
        return self.aborting or self.stop_then_disable

    @property
    def fault_stopping(self) -> bool:
        return self.planner is not None and self.stop_then_disable

    def new_planner(self, unless: Callable[[], bool] | None = None) -> None:
        """A planner at rest where the drives hold, primed with the task's modes; made on the cycle
        thread (waited for). ``unless``, asked on the cycle thread: True makes none (an E-stop came
        meanwhile and dropped the planner; one made now would outlive it)."""
        def make() -> None:
            if unless is None or not unless():
                self._new_planner()

        self.run_on_cycle(make)

    def _new_planner(self) -> None:
        from planner.core import Planner

        start = self.master.positions()
        waits = self.hooks.planner_waits()
        if self.spindle_drive is not None:
            waits = (*waits, *self.spindle_drive.wait_types)
        p = Planner(self.limits, start=start, waits=waits)
        p.follow_taps = self.spindle_drive is not None  # G33.1 follows the spindle drive's position
        for cmd in self.hooks.planner_prime():
            p.feed(cmd)
        self.planner = p
        self._wait_seen = None
        self.commanded = tuple(start)

    def drop_planner(self, *, wait: bool = True) -> None:
        """No more setpoints: the drives hold where the last one left them."""
        self.run_on_cycle(lambda: setattr(self, "planner", None), wait=wait)

    def position(self) -> tuple[float, ...]:
        """Where the motion stands (the planner's position, else the drives')."""
        def where() -> tuple[float, ...]:
            if self.planner is not None:
                return self.planner.position
            return self.master.positions() if self.master is not None else self.commanded

        return self.run_on_cycle(where)

    # ------------------------------------------------------------------ urgent calls
    def quick_stop(self, reason: str) -> None:
        """Any thread: CiA 402 quick stop on every drive now (RPDOs, no SDO), not reported as a drive
        fault."""
        if self.master is None:
            return
        with self._stop_lock:
            self._estopping = True
            try:
                self.master.quick_stop(reason)
            finally:
                self._estopping = False

    def estop(self, reason: str) -> None:
        """Quick stop now; then, on the cycle thread, the job cancelled and the planner dropped."""
        self.quick_stop(reason)

        def on_cycle() -> None:
            self.hooks.cancel_stream(reason, True)
            if self.spindle_drive is not None:
                self.spindle_drive.cancel()
            self.planner = None
            self.aborting = self.stop_then_disable = False

        self.run_on_cycle(on_cycle)

    def abort(self) -> None:
        """The job cancelled and a jerk-limited stop on the path (``hooks.aborted`` once at rest)."""
        def on_cycle() -> None:
            self.hooks.cancel_stream("aborted by the operator", True)
            if self.spindle_drive is not None:
                self.spindle_drive.cancel()
            if self.planner is not None:
                self.planner.abort()
                self.aborting = True
            else:
                self.hooks.aborted()

        self.run_on_cycle(on_cycle)

    def pause(self) -> None:
        self.run_on_cycle(lambda: self.planner.hold() if self.planner is not None else None)

    def resume(self) -> None:
        """Feed hold off; also past an M0 / M1 / M60 the planner waits at."""
        def on_cycle() -> None:
            p = self.planner
            if p is None:
                return
            if self._stopped_at is not None and p.waiting_for is self._stopped_at:
                p.release()
            self._stopped_at = None
            p.resume()

        self.run_on_cycle(on_cycle)

    def spindle_hold(self, on: bool) -> None:
        """The door: the spindle drive stopped (``on``), or back at its speed (a machine without one:
        nothing)."""
        if self.spindle_drive is not None:
            self.run_on_cycle(lambda: self.spindle_drive.hold(on), wait=False)

    def spindle_at_speed(self) -> bool:
        """The spindle drive turns at the speed it is to (True without one)."""
        return self.spindle_drive is None or self.spindle_drive.at_speed()

    def feed_override(self, factor: float) -> None:
        self.run_on_cycle(lambda: self.planner.set_feed_override(factor) if self.planner is not None
                          else None)

    def jog(self, i: int, velocity: float, distance: float, base: C.Pose, feed: float) -> None:
        """A jerk-limited move of axis ``i`` by ``distance`` (0: to the soft limit, or 1000 units) at
        ``|velocity|``. ``base``: the full pose the other (non-machine) axes keep; ``feed``: the feed
        rate restored after it. CommandRefused when not enabled or moving."""
        lim = self.limits.axes[i]

        def on_cycle() -> None:
            p = self.planner
            if p is None:
                raise CommandRefused("drives not enabled")
            if not p.is_idle:
                raise CommandRefused("cannot jog while the axes move")
            pos = list(p.position)
            if distance:
                target = pos[i] + math.copysign(abs(distance), velocity)
            else:  # until a jog with velocity 0, at most to the soft limit (or 1000 units)
                bound = lim.max_position if velocity > 0 else lim.min_position
                target = bound if bound is not None else pos[i] + math.copysign(1000.0, velocity)
            if lim.min_position is not None and target < lim.min_position:
                target = lim.min_position
            if lim.max_position is not None and target > lim.max_position:
                target = lim.max_position
            pose = list(base)
            for j, k in enumerate(self.limits.pose_index):
                pose[k] = pos[j]
            pose[self.limits.pose_index[i]] = target
            p.feed(C.SetFeedRate(abs(velocity) * 60.0))  # a one-axis move runs at the feed
            p.feed(C.StraightFeed(C.Pose(*pose), file="<jog>"))
            p.feed(C.SetFeedRate(feed))
            p.flush()
            self.jogging = True

        self.run_on_cycle(on_cycle)

    def jog_stop(self) -> None:
        self.run_on_cycle(lambda: self.planner.abort() if self.planner is not None and self.jogging
                          else None)

    # ------------------------------------------------------------------ faults
    def clear_fault(self) -> None:
        with self._fault_lock:
            self._pending_fault = None

    def fault_stop(self) -> None:
        """Cycle thread (the fault hook): the master quick-stopped the drives on its own fault (the
        planner is dropped, to be made again later); otherwise the planner stops on the path with the
        quick-stop limits and the drives are disabled once at rest (``hooks.disable_after_fault``)."""
        master_faulted = self.master is not None and self.master.fault is not None
        if self.planner is not None:
            if master_faulted:
                self.planner = None
            else:
                self.planner.quick_stop()
                self.stop_then_disable = True

    def _on_master_fault(self, fault: Any) -> None:
        if self._estopping:
            return
        self.post_fault(str(fault), "canopen")

    def _on_master_warning(self, warning: Any) -> None:
        """A drive without an optional object, a warning EMCY: logged and published, motion goes on."""
        self.hooks.event("WARNING", str(warning), kind="drive_warning", source="canopen")

    # ------------------------------------------------------------------ state out
    def snapshot(self) -> MotionSnapshot:
        """The motion's state now (any thread; reads what the cycle thread last wrote, no lock)."""
        line, file = self.place
        p = self.planner
        return MotionSnapshot(
            cycle=self.cycle, commanded=tuple(self.commanded), actual=tuple(self.actual),
            actual_t=self.actual_t, velocity=tuple(self.velocity),
            following_error=tuple(self.following_error), line=line, file=file, modal=self.modal,
            feed_override=float(p.feed_override) if p is not None else 1.0, spindle=self.spindle,
            coolant=self.coolant, tool_prepared=int(self.tool_prepared), jogging=self.jogging,
            drives=self._drives(),
            spindle_drive=self.spindle_drive.feedback if self.spindle_drive is not None else None)

    def _drives(self) -> tuple[DriveView, ...]:
        master = self.master
        if master is None:
            return ()
        now = time.monotonic()
        hb_limit = self.canopen.heartbeat_consumer_ms / 1000.0
        fault = master.fault
        views = []
        for d, st in zip(master.drives, master.state, strict=False):
            active = getattr(d.node.emcy, "active", [])
            views.append(DriveView(
                axis=st.axis, node=st.node, nmt_state=NMT_NAMES.get(d.nmt_state, ""),
                operational=d.nmt_state == 5,
                heartbeat_ok=(not self.canopen.heartbeat_producer_ms) or now - d.heartbeat_at <= hb_limit,
                statusword=int(st.statusword) & 0xFFFF, cia402_state=st.state.name.lower(),
                actual_counts=int(st.actual_counts), following_error=int(d.following_error),
                emcy_code=int(active[-1].code) if active else 0,
                error=str(fault.reason) if fault is not None and fault.node == st.node else ""))
        return tuple(views)

