"""The task side's stand-in for a :class:`MotionCore` in its own process (``[motion] process = "own"``).

:class:`MotionProxy` offers the interface :mod:`motiond.runtime.motion`'s docstring lists, so that
:class:`~motiond.runtime.machine.Machine` is the same in both modes; behind it the calls cross to the
motion process (:mod:`motiond.runtime.motion_proc`, which describes the pipes):

* ``put`` sends each command with the job's generation and a sequence number, never more than
  :data:`QUEUE_MAX` ahead of what the motion process reports consumed (the bounded queue, end to end);
  ``drop_commands`` starts a new generation, so that nothing of the cancelled job still on the pipe runs.
* the urgent calls go down their own pipe without waiting for an answer (they act within a cycle of
  arriving); the rest are requests answered by the motion process (an exception there is raised here).
* the values (``cycle``, ``actual``, ``aborting`` ...) and :meth:`snapshot` come from the newest state
  the motion process sent; the hooks arrive after the state they followed and run in order on the
  ``canon-hooks`` thread, which also runs :meth:`run_on_cycle` (so the task's job bookkeeping stays
  ordered with them, as on the cycle thread in one process).
* the hooks that answer with a value are pushed ahead: the planner's priming commands and wait types
  go with each ``new_planner``; whether the task has an I/O map and Modbus outputs, and M19's words,
  at ``open`` (``io_setup``).
* the I/O map stays here (the Modbus worker is the task's): its per-cycle work runs on the task's
  ``canon-io`` thread (:mod:`motiond.runtime.io_loop`) from the states' drive inputs and velocities;
  the spindle and coolant events and the synchronized outputs come as hooks (``io_event``,
  ``io_setpoint``) in order with their cycle's state; a sync point the I/O map completes comes as the
  ``io_wait`` hook and its release goes down the urgent pipe (``release_wait``), as do the door's
  ``spindle_hold`` and the probe input's trip. G38.x: :mod:`motiond.runtime.probing_proxy`.

The liveness watch, both ways (``[motion] task_timeout_ms``, ``motion_timeout_ms``:
:class:`~motiond.config_motion.Watch`): the ``canon-motion-ping`` thread sends a ping down the urgent
pipe every tenth of ``task_timeout_ms`` (the motion process quick-stops the drives when they stop:
:mod:`~motiond.runtime.motion_proc`), and looks at the time since the last state arrived: when the
motion process, still alive, sent none for ``motion_timeout_ms`` (stopped by SIGSTOP, deadlocked), the
task faults naming it and how long it was silent, and sends a quick stop down the urgent pipe (acted on
if the motion process runs again). A ping thread that was itself late (this process stalled) does not
count the time it was away. The states run again: the watch re-arms (the fault stays, for the
operator to reset).

When the motion process dies (its sentinel fires without :meth:`close`), the task gets one fault naming
it and how it ended (exit code or signal): the job is cancelled, FAULTED. The drives, without the
master's heartbeat, disable themselves by their heartbeat consumer.
"""

from __future__ import annotations

import collections
import concurrent.futures
import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

from gcode_canon import commands as C
from gcode_canon.errors import GCodeError
from motiond.config_motion import Watch
from motiond.runtime.cycle import END, LATE_LOG, QUEUE_MAX
from motiond.runtime.motion import MotionHooks, MotionSnapshot
from motiond.runtime.motion_link import MotionLink, MotionProcessGone
from motiond.runtime.motion_proc import END_MARK, SYNC_TYPES
from motiond.runtime.records import Stream, deferred

log = logging.getLogger(__name__)

STATE_WAIT_S = 0.5
"""How long a call that needs the motion process's state of after it (:meth:`MotionProxy.new_planner`)
waits for one: a hundred state periods, the motion watch's default."""

OPEN_TIMEOUT_S = 60.0
"""The motion process's start: spawn, imports, the drives booted."""


def _value(key: str, default: Any = None) -> Any:
    """A MotionProxy property: ``key`` of the newest state the motion process sent."""
    return property(lambda self: self._get(key, default), doc=f"``{key}`` of the newest state")


class MasterProxy:
    """``machine.master`` in "own" mode: the service operations' SDO calls, served in the motion
    process; a few attributes read there."""

    _methods = ("enable", "disable", "home", "boot", "reset_faults", "not_operational", "positions")

    def __init__(self, proxy: MotionProxy) -> None:
        self._p = proxy

    def __getattr__(self, name: str) -> Any:
        if name in self._methods:
            return lambda *a, **kw: self._p.request(f"master.{name}", *a, dead=_raise_canopen, **kw)
        if name in ("streaming", "fault", "sync_mode"):
            return self._p.request(f"master.{name}", dead=lambda: None)
        raise AttributeError(f"master.{name} is not served across the process boundary")


def _raise_canopen() -> Any:
    from fieldbus.canopen.master import CanopenError

    raise CanopenError("the motion process is gone")


class MotionProxy(MotionLink):
    """The motion side's interface over the process boundary (module docstring), on its
    :class:`~motiond.runtime.motion_link.MotionLink`."""

    def __init__(self, limits: Any, canopen: Any, *, late_fault_s: float, simulated: bool,
                 hooks: MotionHooks, watch: Watch | None = None,
                 io_setup: dict[str, Any] | None = None) -> None:
        super().__init__(watch)
        self.limits = limits
        self.canopen = canopen
        self.late_fault_s = late_fault_s
        self.simulated = simulated
        self.hooks = hooks
        self.n = len(limits.names)
        self.master: Any = None
        self.io: Any = None  # the task's IoExecutor (Machine sets it), None without Modbus
        self.io_setup: dict[str, Any] = io_setup or {}
        """For the motion process at open: ``map`` (an I/O map), ``modbus`` (Modbus outputs),
        ``orient_text`` (:meth:`~motiond.io_hooks.IoHooks.orient_text`)."""
        self.probe_client: Any = None  # G38.x (motiond.runtime.probing_proxy), None: no probe
        self._trace: list[Any] | None = None
        self.planner = None  # the motion process's own
        self.runner = None
        self.stream: Stream | None = None
        self._state: dict[str, Any] = {}
        self.late_log: collections.deque[tuple[int, float]] = collections.deque(maxlen=LATE_LOG)
        self._gen = 1
        self._seq = 0
        self._sent = 0
        self._seq_of: dict[int, tuple[Any, int]] = {}
        self._estops = 0
        self._cmd_lock = threading.Lock()
        self._stream_id = 0
        self._hold_stream = False
        self._optional_stop = False

    # ------------------------------------------------------------------ life cycle
    def open(self) -> None:
        self._spawn((self.limits, self.canopen, self.late_fault_s, self.simulated,
                     logging.getLogger().getEffectiveLevel(), self.watch.task_timeout_ms / 1e3))
        self.master = MasterProxy(self)
        try:
            if self.request("open", self.io_setup, timeout=OPEN_TIMEOUT_S):  # a drive's touch probe
                from motiond.runtime.probing_proxy import ProbeClient

                self.probe_client = ProbeClient(self)
        except BaseException:
            self.close()
            raise
        self._start_ping()

    def start_cycle(self) -> None:
        self.request("start_cycle")

    def stop_cycle(self) -> None:
        if not self.dead:
            self.request("stop_cycle", dead=lambda: None)

    # ------------------------------------------------------------------ what crosses back
    def _hook(self, name: str, args: tuple[Any, ...], kw: dict[str, Any]) -> None:
        """``canon-hooks``: one hook of the motion process."""
        if name == "io_event":  # the job's record here (its outputs: the run summary)
            self.hooks.io_event(args[0], self.stream)
        elif name == "stream_done":  # of the stream it names: a late one does not end the next job
            if args[0] == self._stream_id and self.stream is not None:
                self.hooks.stream_done()
        elif name == "io_setpoint":
            if self.io is not None:
                self.io.on_setpoint(_Events(tuple(args[0])))
        else:
            getattr(self.hooks, name)(*args, **kw)

    def _take_state(self, st: dict[str, Any]) -> None:
        self.late_log.extend(st.pop("late_new"))
        trace = st.pop("trace_new", None)
        if trace and self._trace is not None:
            self._trace.extend(trace)
        stream = st.pop("stream")
        if stream is not None and self.stream is not None and st.get("stream_id") == self._stream_id:
            here = [o for o in self.stream.outputs if o.kind == "function"]  # the I/O map's, noted here
            for k, v in stream.items():
                if k != "answered_ahead":
                    setattr(self.stream, k, v)
            if here:
                self.stream.outputs = sorted([*self.stream.outputs, *here], key=lambda o: o.t)
        self._last_state = time.monotonic()
        with self._cond:
            self._state = st
            self._cond.notify_all()

    def _get(self, key: str, default: Any) -> Any:
        return self._state.get(key, default)

    # ------------------------------------------------------------------ commands in
    def put(self, item: Any, cancel: threading.Event) -> bool:
        """Job thread: send a canonical command (or END), waiting while QUEUE_MAX are not consumed yet;
        False when ``cancel`` is set first (or the motion process is gone)."""
        with self._cond:
            while self._sent - self._get("consumed", 0) >= QUEUE_MAX:
                if cancel.is_set() or self.dead:
                    return False
                self._cond.wait(0.05)
        if isinstance(item, C.DigitalOutput | C.AnalogOutput | C.WaitInput) and self.io is not None:
            problem = self.io.check(item)  # checked here: the Modbus I/O is this process's
            if problem:
                self.post_fault(str(GCodeError(problem, item.file, item.line)), "planner")
                return False
        if isinstance(item, C.Probe) and self.probe_client is not None:
            if not self.probe_client.before_move(item, cancel):
                return False
            if self.probe_client.tripped_at_start:
                return True  # G38.3/G38.5 with the probe already in that state: the move is not made
        with self._cmd_lock:
            if cancel.is_set() or self.dead:
                return False
            self._seq += 1
            self._sent += 1
            if isinstance(item, SYNC_TYPES):
                self._seq_of[id(item)] = (item, self._seq)
            try:
                self._conns["cmd"].send([(self._gen, self._seq, END_MARK if item is END else item)])
            except (OSError, ValueError):
                return False
        return True

    def begin_stream(self, stream: Stream, modal: Any) -> None:
        self.stream = stream
        self._stream_id += 1
        self.request("begin_stream", stream, modal, self._stream_id)

    def end_stream(self) -> None:
        self.stream = None
        self.request("end_stream", dead=lambda: None)

    def drop_commands(self) -> None:
        """A new generation: what is still on the pipe is discarded over there."""
        gen = self._next_generation()
        self.request("fence", gen, dead=lambda: None)
        self.wake_waiters()

    def _next_generation(self) -> int:
        """Commands sent from now on are of a new generation. Also taken when the motion process
        fenced by itself (:data:`FENCING_HOOKS`): it then accepts only a generation newer than any it
        has seen, and a task that went on sending the old one, with no job to cancel (a fault while
        idle), had every later command discarded there: an MDI line after the reset stayed "running"
        for ever (found with the I/O module killed while idle)."""
        with self._cmd_lock:
            self._gen += 1
            self._seq_of.clear()
            return self._gen

    def wake_waiters(self) -> None:
        with self._cond:
            self._cond.notify_all()

    def drained(self) -> bool:
        consumed, idle = self.request("drained")
        return idle and consumed >= self._sent

    def wait_sync_point(self, cmd: Any, cancel: threading.Event) -> bool:
        entry = self._seq_of.get(id(cmd))
        if entry is None or entry[0] is not cmd:
            return False
        seq = entry[1]
        with self._cond:
            while self._get("sync_seq", 0) < seq:
                if cancel.is_set() or self.dead:
                    return False
                self._cond.wait(0.05)
        self._seq_of.pop(id(cmd), None)
        return True

    def drive_output(self, axis: int, bit: int, on: bool) -> concurrent.futures.Future[Any]:
        """:meth:`MotionCore.drive_output` in the motion process: never waits (the I/O loop calls it)."""
        return self.request_later("drive_output", axis, bit, on)

    def use_probe_input(self, mio: Any) -> None:
        """G38.x on the I/O map's probe input, read here (unless a drive's touch probe is the probe)."""
        if self.probe_client is None:
            from motiond.runtime.probing_proxy import ProbeClient

            client = ProbeClient(self, mio)
            self.request("probe_input", client.where)
            self.probe_client = client

    @property
    def has_touch_probe(self) -> bool:
        return self.probe_client is not None

    def probe(self, cmd: Any, cancel: threading.Event) -> Any:
        assert self.probe_client is not None
        return self.probe_client.answer(cmd, cancel)

    def release_wait(self) -> None:
        """Urgent: the I/O loop releases a wait with it (it must not queue behind requests)."""
        self._urgent("release_wait")

    # ------------------------------------------------------------------ the planner
    def new_planner(self, unless: Callable[[], bool] | None = None) -> None:
        if unless is not None and unless():
            return
        self.request("new_planner", self.hooks.planner_prime(), self.hooks.planner_waits(), self._estops)
        self._state_since(time.monotonic(), STATE_WAIT_S)

    def _state_since(self, since: float, timeout: float) -> None:
        """Wait, at most ``timeout``, for a state the motion process began building at ``since`` or
        later. After a new planner (a homed axis rebased, a reset) the newest state here was built before
        it: a status taken from it showed the axis homed at its old coordinate (X -2.52 right after
        "x homed"), which one process never showed. The state comes every 5 ms; a hung motion process
        is the watch's to report, not this wait's."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._state.get("at", math.inf) < since and not (self.dead or self.silent):
                left = deadline - time.monotonic()
                if left <= 0:
                    return
                self._cond.wait(left)

    def drop_planner(self, *, wait: bool = True) -> None:
        self.request("drop_planner", wait=wait, dead=lambda: None)

    def position(self) -> tuple[float, ...]:
        return self.request("position")

    @property
    def hold_stream(self) -> bool:
        return self._hold_stream

    @hold_stream.setter
    def hold_stream(self, on: bool) -> None:
        self._hold_stream = on
        self.request("set", "hold_stream", on, dead=lambda: None)

    @property
    def optional_stop(self) -> bool:
        return self._optional_stop

    @optional_stop.setter
    def optional_stop(self, on: bool) -> None:
        self._optional_stop = on
        self.request("set", "optional_stop", on, dead=lambda: None)

    # ------------------------------------------------------------------ urgent calls
    def quick_stop(self, reason: str) -> None:
        self._estops += 1
        self._urgent("quick_stop", reason)

    def estop(self, reason: str) -> None:
        self._estops += 1
        self._urgent("estop", reason)

    def abort(self) -> None:
        self._urgent("abort")

    def pause(self) -> None:
        self._urgent("pause")

    def resume(self) -> None:
        self._urgent("resume")

    def feed_override(self, factor: float) -> None:
        self._urgent("feed_override", factor)

    def spindle_hold(self, on: bool) -> None:
        self._urgent("spindle_hold", on)

    def spindle_at_speed(self) -> bool:
        return bool(self._get("spindle_at_speed", True))

    def jog(self, i: int, velocity: float, distance: float, base: Any, feed: float) -> None:
        self.request("jog", i, velocity, distance, base, feed)

    def jog_stop(self) -> None:
        self._urgent("jog_stop")

    def post_fault(self, reason: str, source: str) -> None:
        self._urgent("post_fault", reason, source)

    def clear_fault(self) -> None:
        self.request("clear_fault", dead=lambda: None)

    def fault_stop(self) -> None:
        """Done in the motion process as its fault hook fires (nothing to do here)."""

    def run_on_cycle(self, fn: Callable[[], Any], *, wait: bool = True, timeout: float = 2.0) -> Any:
        """Run ``fn`` on the ``canon-hooks`` thread, ordered with the hooks (inline there)."""
        if threading.get_ident() == self._dispatch_ident:
            return fn()
        call, fut = deferred(fn)
        self._dispatch.put(call)
        return fut.result(timeout) if wait else None

    # ------------------------------------------------------------------ state out
    def snapshot(self) -> MotionSnapshot:
        snap = self._get("snapshot", None)
        if snap is None:
            zero = tuple(0.0 for _ in range(self.n))
            return MotionSnapshot(0, zero, zero, 0.0, zero, zero, 0, "", None, 1.0, (0, 0.0), (False, False),
                                  0, False, ())
        return snap

    cycle = _value("cycle", 0)
    late_cycles = _value("late_cycles", 0)
    worst_late_s = _value("worst_late_s", 0.0)
    first_setpoint_t = _value("first_setpoint_t")
    place = _value("place", (0, ""))
    has_planner = _value("has_planner", False)
    is_moving = _value("is_moving", False)
    aborting = _value("aborting", False)
    stopping = _value("stopping", False)
    fault_stopping = _value("fault_stopping", False)
    jogging = _value("jogging", False)
    last_estop = _value("last_estop")
    """(arrived, quick stop sent, cycle then, cycle after): monotonic times, this host's clock."""
    last_quick_stop = _value("last_quick_stop")
    """The same for the last quick stop (an I/O map's limit switch)."""
    drive_inputs = _value("drive_inputs", ())

    @property
    def velocity(self) -> tuple[float, ...]:
        return self.snapshot().velocity

    @property
    def trace(self) -> list[Any] | None:
        """A list: the motion process records (cycle, monotonic time, positions, events) of every
        setpoint into it, sent with the states (tests)."""
        return self._trace

    @trace.setter
    def trace(self, value: list[Any] | None) -> None:
        self._trace = value
        self.request("set", "trace", value is not None, dead=lambda: None)

    @property
    def commanded(self) -> tuple[float, ...]:
        return self._get("commanded", tuple(0.0 for _ in range(self.n)))

    @property
    def actual(self) -> tuple[float, ...]:
        return self._get("actual", tuple(0.0 for _ in range(self.n)))


class _Events:
    """A setpoint as the IoExecutor reads it (its events only)."""

    def __init__(self, events: tuple[Any, ...]) -> None:
        self.events = events


__all__ = ["MasterProxy", "MotionProcessGone", "MotionProxy"]
