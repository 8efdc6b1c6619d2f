"""The motion process (``[motion] process = "own"``): :class:`MotionCore` alone on an interpreter lock.

The task process (:class:`~motiond.runtime.motion_proxy.MotionProxy`) starts :func:`main` in a child
process (multiprocessing, spawn) and talks to it through four one-purpose pipes, each served by a
thread of its own here so that none waits behind another:

* ``cmd`` (task -> motion): the canonical commands, as ``(generation, seq, item)``. The task sends no
  more than :data:`~motiond.runtime.cycle.QUEUE_MAX` ahead of what the cycle took (``consumed`` in the
  state), so the reader never blocks; items of a generation the task has since dropped are discarded.
* ``urgent`` (task -> motion): estop, quick_stop, abort, pause, resume, feed_override, jog_stop,
  post_fault, release_wait, spindle_hold, probe_trip (:mod:`motiond.runtime.probing_child`). The quick
  stop of an E-stop or a quick_stop is sent from the reader thread the moment it arrives; the rest is
  posted to the cycle thread and runs at the start of the next cycle.
* ``req`` (both ways): everything else, a reply per request (the value or the exception): the stream
  and planner calls, ``position``, ``drained``, and the master's SDO calls of the service operations
  (enable, disable, home, boot, reset_faults), which run on a worker thread so that a homing does not
  hold up a ``position``.
* ``out`` (motion -> task): every few ms (at once when a hook fires) the newest state (the
  :class:`MotionSnapshot`, counters, flags, the stream's accounting) and then the hooks since the last
  one, in order. The cycle thread only appends to a queue and sets an event: it never waits on a pipe.

The task process pings on the urgent pipe (``("ping", ())``, every tenth of ``[motion]
task_timeout_ms``, from a thread of its own: see :class:`~motiond.runtime.motion_proxy.MotionProxy`).
The urgent pipe carries it because its reader is the thread that acts on an E-stop: a ping that gets
through proves that path is served. The ``motion-watch`` thread here (:meth:`MotionServer._watch`)
quick-stops the drives as on the task's death when no ping came for ``task_timeout_ms`` (a task
stopped by SIGSTOP or deadlocked: alive, its pipes open, nobody to press its E-stop), and posts a fault
naming the silence, which the task receives when it runs again. The watch starts at the first ping
(the task's start-up is not counted), ends at the task's ``close`` request, and allows for its own
lateness (a stall of this whole process is not the task's silence). A task still silent
:data:`ORPHAN_HOLD_S` after that gets the drives disabled, as a dead one does (the process stays, with
its pipes open: a task that runs again finds its machine FAULTED with the drives off, and a reset
and an enable bring it back).

When the task process dies (its pipes reach end of file) the drives are quick-stopped at once and held
(the master keeps the cycle and its heartbeat running) for :data:`ORPHAN_HOLD_S`; then they are
disabled and the process exits. SIGINT and SIGTERM are ignored while the task lives: the task process
stops the motion on the path and closes this process itself.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import logging
import os
import queue
import signal
import sys
import threading
import time
from typing import Any

from gcode_canon import commands as C
from motiond.runtime.cycle import END
from motiond.runtime.motion import MotionCore
from motiond.runtime.probing_child import ProbeServer
from motiond.runtime.records import Stream

log = logging.getLogger(__name__)

ORPHAN_HOLD_S = 30.0
"""After the task process died: the drives held in quick stop this long, then disabled."""
WATCH_PERIOD_S = 0.01
"""How often the motion process looks at the time since the task's last ping."""
STATE_PERIOD_S = 0.005
"""The state goes to the task at least this often."""
END_MARK = "__canon_end__"
""":data:`END` on the command pipe (an ``object()`` does not survive pickling as itself)."""
SYNC_TYPES = (C.WaitInput, C.Probe)
"""Commands the job thread waits at (``wait_sync_point``): their sequence number is reported back."""
FENCING_HOOKS = frozenset({"fault", "cancel_stream"})
"""Hooks posted after this process fenced its commands by itself (:meth:`MotionServer.fence`: it
accepts only a newer generation from then on): the task starts one as it reads them."""
MASTER_METHODS = frozenset({"enable", "disable", "home", "boot", "reset_faults", "not_operational",
                            "positions"})
MASTER_ATTRS = frozenset({"streaming", "fault", "sync_mode"})


class _CountingQueue(queue.Queue):  # type: ignore[type-arg]
    """The cycle's command queue, counting what was taken out (the task's send credit)."""

    def __init__(self) -> None:
        super().__init__()
        self.taken = 0

    def _get(self) -> Any:
        self.taken += 1
        return super()._get()


IO_EVENTS = (C.SpindleOn, C.SpindleOff, C.SpindleOrient, C.SetSpindleSpeed, C.Coolant)
"""The setpoint events the task's I/O map switches outputs for (``io_event``)."""


class ChildHooks:
    """:class:`~motiond.runtime.motion.MotionHooks` in the motion process: posted to the task; the
    ones with a value answer from what the task pushed ahead (``prime``, ``waits``, ``io_map``)."""

    def __init__(self, server: MotionServer) -> None:
        self.s = server
        self.prime: list[C.Canon] = []
        self.waits: tuple[type[C.Canon], ...] = ()
        self.io_map = False  # the task has an I/O map: the spindle and coolant events go to it
        self.done_for = -1  # the stream whose stream_done was posted

    def _post(self, name: str, *args: Any, **kw: Any) -> None:
        core = self.s.core
        on_cycle = threading.get_ident() == core._cycle_ident
        self.s.hook_q.put((core.cycle if on_cycle else -1, (name, args, kw)))
        self.s.wake.set()

    def event(self, severity: str, text: str, **kw: Any) -> None:
        self._post("event", severity, text, **kw)

    def fault(self, reason: str, source: str) -> None:
        self.s.core.fault_stop()  # on the cycle thread now, as the in-process hook does
        self.s.fence()
        self._post("fault", reason, source)

    def cancel_stream(self, error: str, aborted: bool) -> None:
        self.s.fence()  # no command of the cancelled job reaches the planner meanwhile
        self._post("cancel_stream", error, aborted)

    def stream_done(self) -> None:
        """Posted once per stream, with its id: the cycle calls it every cycle until the task's
        ``end_stream`` arrives, and a late one must not end the task's next job."""
        sid = self.s.stream_id
        if self.done_for != sid:
            self.done_for = sid
            self._post("stream_done", sid)

    def aborted(self) -> None:
        self._post("aborted")

    def program_stop(self, what: str, w: C.Canon) -> None:
        self._post("program_stop", what, w)

    def disable_after_fault(self) -> None:
        self._post("disable_after_fault")

    def planner_prime(self) -> list[C.Canon]:
        return list(self.prime)

    def planner_waits(self) -> tuple[type[C.Canon], ...]:
        return self.waits

    def io_cycle(self, drive_inputs: tuple[int, ...], velocity: tuple[float, ...]) -> None:
        pass  # the task's I/O loop does it (motiond.runtime.io_loop), from the states sent there

    def io_event(self, ev: C.Canon, stream: Any) -> None:
        if self.io_map and isinstance(ev, IO_EVENTS):
            self._post("io_event", ev)  # in order with the state of its cycle (MotionServer._out)

    def io_wait(self, w: C.Canon) -> bool:
        """The task's I/O map completes the sync points of the types it gave (``waits``): it is told,
        the planner stays at rest until its release comes down the urgent pipe."""
        if isinstance(w, self.waits):
            self._post("io_wait", w)
            return True
        return False

    def orient_text(self) -> str:
        return self.s.orient_text


class TaskIo:
    """``core.io`` in the motion process when the task holds the Modbus I/O: the synchronized outputs
    (M62-M63, M67) riding on a setpoint go to the task as a hook, in order with its state (the task
    checked them before sending them: ``check`` has nothing to add)."""

    def __init__(self, hooks: ChildHooks) -> None:
        self.hooks = hooks

    def check(self, cmd: C.Canon) -> str | None:
        return None

    def on_setpoint(self, sp: Any) -> None:
        events = [ev for ev in sp.events if isinstance(ev, C.DigitalOutput | C.AnalogOutput)]
        if events:
            self.hooks._post("io_setpoint", events)


class ChildCore(MotionCore):
    """MotionCore that reports the sync point it stands at by the task's sequence number."""

    sync_seq = 0
    seq_of: dict[int, tuple[Any, int]]

    def _sync_point_reached(self, w: Any) -> None:
        super()._sync_point_reached(w)
        entry = self.seq_of.pop(id(w), None)
        if entry is not None:
            self.sync_seq = entry[1]
            self.server.wake.set()


class MotionServer:
    """The threads of the motion process around one :class:`ChildCore` (module docstring)."""

    def __init__(self, conns: dict[str, Any], limits: Any, canopen: Any, late_fault_s: float,
                 simulated: bool, task_timeout_s: float = 0.5) -> None:
        self.conns = conns
        self.task_timeout_s = task_timeout_s
        self.last_ping = 0.0  # monotonic; 0: no ping yet (the watch not started)
        self.task_silent = False  # the watch tripped: the drives quick-stopped, a fault posted
        self.silent_disabled = False  # and the silence went on ORPHAN_HOLD_S more: the drives disabled
        self.closing = False  # the task asked this process to close: the watch ends
        self.hook_q: queue.SimpleQueue[tuple[int, tuple[str, tuple[Any, ...], dict[str, Any]]]] = \
            queue.SimpleQueue()
        """(the cycle that posted it, -1 another thread; the hook): see :meth:`_out`."""
        self.wake = threading.Event()
        self.hooks = ChildHooks(self)
        core = ChildCore(limits, canopen, late_fault_s=late_fault_s, simulated=simulated, hooks=self.hooks)
        core.seq_of = {}
        self.orient_text = ""  # the task's I/O map's words for M19 (ChildHooks.orient_text)
        self.probes = ProbeServer(core)
        self.trace_on = False
        core.server = self  # type: ignore[attr-defined]
        core._cmdq = _CountingQueue()  # bounded by the task's credit, never blocks the reader
        self.core = core
        self.gen = 0  # the newest command generation seen
        self.accept_from = 0  # commands of an older generation are discarded
        self.discarded = 0
        self.estops = 0  # E-stops (and quick stops) received: a new_planner asked before one is void
        self.late_sent = 0
        self.stream_id = 0
        self.last_estop: tuple[float, float, int, int] | None = None
        """The last E-stop: when it arrived, when its quick stop was sent (monotonic), the cycle then."""
        self.last_quick_stop: tuple[float, float, int, int] | None = None
        """The same for the last quick stop (a limit switch of the task's I/O map, the task's watch)."""
        self.alive = True
        self.send_lock = threading.Lock()
        self.fence_lock = threading.Lock()
        self.sdo = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="motion-sdo")
        self.orphaned = threading.Event()
        self.done = threading.Event()

    # ------------------------------------------------------------------ commands
    def fence(self, gen: int = 0) -> None:
        """The running job is cancelled: its queued commands and those still on the pipe go (those
        older than ``gen``, the task's new generation, when it asks)."""
        with self.fence_lock:
            self.accept_from = max(self.accept_from, self.gen + 1, gen)
            core = self.core
            while True:
                try:
                    core._cmdq.get_nowait()
                except queue.Empty:
                    break
            core.seq_of.clear()

    def _commands(self) -> None:
        conn = self.conns["cmd"]
        core = self.core
        while True:
            try:
                batch = conn.recv()
            except (EOFError, OSError):
                return self._task_gone("its command pipe closed")
            for gen, seq, item in batch:
                with self.fence_lock:
                    self.gen = max(self.gen, gen)
                    if gen < self.accept_from:
                        self.discarded += 1
                        continue
                    if isinstance(item, str) and item == END_MARK:
                        item = END
                    elif isinstance(item, SYNC_TYPES):
                        core.seq_of[id(item)] = (item, seq)
                        if isinstance(item, C.Probe):
                            self.probes.adopt(item)
                    core._cmdq.put(item)

    # ------------------------------------------------------------------ urgent calls
    def _urgent(self) -> None:
        conn = self.conns["urgent"]
        core = self.core
        while True:
            try:
                name, args = conn.recv()
            except (EOFError, OSError):
                return self._task_gone("its urgent pipe closed")
            if name == "ping":
                self.last_ping = time.monotonic()
                continue
            try:
                if name in ("estop", "quick_stop"):
                    self.estops += 1
                if name == "estop":
                    arrived, cycle = time.monotonic(), core.cycle
                    core.quick_stop(args[0])  # the drives now, from this thread
                    self.last_estop = (arrived, time.monotonic(), cycle, core.cycle)
                    core.run_on_cycle(lambda r=args[0]: self._estop_on_cycle(r), wait=False)
                elif name == "post_fault":
                    core.post_fault(*args)
                elif name == "quick_stop":
                    arrived, cycle = time.monotonic(), core.cycle
                    core.quick_stop(*args)
                    self.last_quick_stop = (arrived, time.monotonic(), cycle, core.cycle)
                elif name == "probe_trip":
                    self.probes.trip(*args)
                else:  # abort, pause, resume, feed_override, jog_stop, release_wait, spindle_hold: on
                    # the next cycle, not waited for
                    method = getattr(MotionCore, name)
                    core.run_on_cycle(lambda m=method, a=args: _call_on_cycle(core, m, a), wait=False)
            except Exception:
                log.exception("urgent %s", name)

    def _estop_on_cycle(self, reason: str) -> None:
        core = self.core
        core.hooks.cancel_stream(reason, True)
        core.planner = None
        core.aborting = core.stop_then_disable = False

    # ------------------------------------------------------------------ requests
    def _requests(self) -> None:
        conn = self.conns["req"]
        while True:
            try:
                rid, name, args, kw = conn.recv()
            except (EOFError, OSError):
                return self._task_gone("its request pipe closed")
            if name.startswith("master.") and name[7:] in MASTER_METHODS:
                self.sdo.submit(self._answer, rid, name, args, kw)
            elif name == "drive_output":  # the master's own thread writes it: answered when written
                self._answer_when_done(rid, args)
            else:
                self._answer(rid, name, args, kw)
            if name == "close":
                return

    def _answer_when_done(self, rid: int, args: tuple[Any, ...]) -> None:
        """``drive_output``: the master's future (its ``canon-do`` thread writes 0x60FE by SDO, in the
        order asked), answered when it is done; this thread never waits for the SDO."""

        def reply(fut: concurrent.futures.Future[Any]) -> None:
            exc = fut.exception()
            answer = (rid, True, fut.result()) if exc is None else (rid, False, _picklable(exc))
            with self.send_lock, contextlib.suppress(OSError, ValueError):
                self.conns["req"].send(answer)

        try:
            self.core.drive_output(*args).add_done_callback(reply)
        except Exception as exc:  # a bit out of range: refused at once
            with self.send_lock, contextlib.suppress(OSError, ValueError):
                self.conns["req"].send((rid, False, _picklable(exc)))

    def _answer(self, rid: int, name: str, args: tuple[Any, ...], kw: dict[str, Any]) -> None:
        try:
            value, ok = self._call(name, args, kw), True
        except BaseException as exc:
            value, ok = _picklable(exc), False
        if rid:
            with self.send_lock, contextlib.suppress(OSError, ValueError):
                self.conns["req"].send((rid, ok, value))

    def _call(self, name: str, args: tuple[Any, ...], kw: dict[str, Any]) -> Any:
        core = self.core
        if name.startswith("master."):
            attr = name[7:]
            if attr in MASTER_METHODS:
                return getattr(core.master, attr)(*args, **kw)
            if attr in MASTER_ATTRS:
                value = getattr(core.master, attr, None)
                return value if attr != "fault" or value is None else str(value)
            raise AttributeError(f"the motion process does not serve master.{attr}")
        if name == "set":
            attr, value = args
            if attr == "trace":  # a list to record the setpoints in, sent with the states
                self.trace_on = bool(value)
                core.trace = [] if value else None
                return None
            if attr not in ("hold_stream", "optional_stop"):
                raise AttributeError(attr)
            setattr(core, attr, value)
            return None
        if name.startswith("probe_"):
            return self.probes.call(name, args)
        if name == "new_planner":
            prime, waits, estops = args
            self.hooks.prime, self.hooks.waits = prime, waits
            deadline = time.monotonic() + 1.0  # the urgent pipe may lag this one: let it catch up
            while self.estops < estops and time.monotonic() < deadline:
                time.sleep(0.001)
            return core.new_planner(unless=lambda: estops != self.estops)
        if name == "begin_stream":
            stream, modal, self.stream_id = args
            return core.begin_stream(stream, modal)
        if name == "fence":
            return core.run_on_cycle(lambda: self.fence(args[0]))
        if name == "drained":
            # counted before the planner is looked at: a command taken meanwhile is then in the planner
            # (taken and fed in one step), not counted as consumed while the planner still looks idle
            consumed = core._cmdq.taken + self.discarded
            idle = core.run_on_cycle(lambda: core.planner is None or (
                core.planner.is_idle and core.planner.queue_length == 0))
            return consumed, bool(idle)
        if name == "open":
            io = args[0] if args else {}
            self.hooks.io_map = bool(io.get("map"))
            self.orient_text = io.get("orient_text", "")
            if io.get("modbus"):
                core.io = TaskIo(self.hooks)
            core.open()
            return core.drive_probe is not None
        if name == "close":
            self.closing = True  # the task stops pinging now: not a silence to act on
            core.stop_cycle()
            core.close()
            self.done.set()
            return None
        if name in ("start_cycle", "stop_cycle", "end_stream", "drop_planner", "position", "jog",
                    "release_wait", "clear_fault", "wake_waiters"):
            return getattr(core, name)(*args, **kw)
        raise AttributeError(f"the motion process does not serve {name!r}")

    # ------------------------------------------------------------------ state out
    def state(self) -> dict[str, Any]:
        core = self.core
        log_ = core.late_log
        k = min(core.late_cycles - self.late_sent, len(log_))
        late = [log_[-i] for i in range(k, 0, -1)]
        self.late_sent = core.late_cycles
        st = core.stream
        return {
            "at": time.monotonic(),  # begun: all below is of this time or later (MotionProxy.new_planner)
            "snapshot": core.snapshot(), "cycle": core.cycle, "late_cycles": core.late_cycles,
            "worst_late_s": core.worst_late_s, "late_new": late, "first_setpoint_t": core.first_setpoint_t,
            "commanded": tuple(core.commanded), "actual": tuple(core.actual), "place": core.place,
            "has_planner": core.has_planner, "is_moving": core.is_moving, "aborting": core.aborting,
            "stopping": core.stopping, "fault_stopping": core.fault_stopping, "jogging": core.jogging,
            "consumed": core._cmdq.taken + self.discarded, "sync_seq": core.sync_seq,
            "stream": None if st is None else vars(st).copy(), "stream_id": self.stream_id,
            "last_estop": self.last_estop, "last_quick_stop": self.last_quick_stop,
            "drive_inputs": core.drive_inputs, "spindle_at_speed": core.spindle_at_speed(),
            "trace_new": self._trace_new(),
        }

    def _trace_new(self) -> list[Any]:
        """The setpoints recorded since the last state (``set trace``), taken out of the record."""
        tr = self.core.trace
        if not self.trace_on or tr is None:
            return []
        n = len(tr)  # the cycle thread appends meanwhile: only what is there now goes
        new = tr[:n]
        del tr[:n]
        return new

    def _out(self) -> None:
        """The state, then the hooks. A hook posted by the cycle thread goes once that cycle's step has
        ended (the next one began), so that the state sent with it shows all that step did: the abort's
        ``aborting`` with its ``cancel_stream``, the planner gone with the E-stop's."""
        conn = self.conns["out"]
        held: list[tuple[int, Any]] = []
        while not self.done.is_set():
            self.wake.wait(STATE_PERIOD_S)
            self.wake.clear()
            while True:
                try:
                    held.append(self.hook_q.get_nowait())
                except queue.Empty:
                    break
            now = self.core.cycle
            running = self.core.runner is not None
            n = 0
            while n < len(held) and (held[n][0] < now or not running):  # in order: stop at the first held
                n += 1
            hooks = [h for _, h in held[:n]]
            del held[:n]
            try:
                state = self.state()
                conn.send([("state", state), *(("hook", h) for h in hooks)])
            except (OSError, ValueError, BrokenPipeError):
                return self._task_gone("its state pipe closed")
            except Exception:
                log.exception("sending the motion state")

    # ------------------------------------------------------------------ the task's death
    def _task_gone(self, why: str) -> None:
        if self.done.is_set() or self.orphaned.is_set():
            return
        self.orphaned.set()
        core = self.core
        log.error("task process gone (%s): quick stop, drives held %g s", why, ORPHAN_HOLD_S)
        core.quick_stop("task process gone")
        core.run_on_cycle(lambda: self._estop_on_cycle("task process gone"), wait=False)

    # ------------------------------------------------------------------ the task's silence
    def _watch(self) -> None:
        """``motion-watch``: the task's pings (module docstring)."""
        last_look = time.monotonic()
        while not self.done.wait(WATCH_PERIOD_S):
            now = time.monotonic()
            late = now - last_look - WATCH_PERIOD_S
            last_look = now
            if self.last_ping == 0.0 or self.orphaned.is_set():
                continue
            if self.closing:
                return
            if late > self.task_timeout_s / 4:  # this process stalled: the pings may wait in the pipe
                self.last_ping = max(self.last_ping, now - self.task_timeout_s / 2)
                continue
            silent = now - self.last_ping
            if silent >= self.task_timeout_s and not self.task_silent:
                try:
                    self._task_hung(silent)
                except Exception:  # the watch must outlive a failing quick stop
                    log.exception("stopping the drives for the task's silence")
            elif silent >= self.task_timeout_s + ORPHAN_HOLD_S and not self.silent_disabled:
                self.silent_disabled = True
                self._disable_held(silent)
            elif silent < self.task_timeout_s and self.task_silent:
                self.task_silent = False  # it runs again (the fault posted is its to clear)
                self.silent_disabled = False

    def _task_hung(self, silent: float) -> None:
        self.task_silent = True
        reason = (f"the task process (pid {os.getppid()}) sent no ping for {silent * 1e3:.0f} ms "
                  f"(task_timeout_ms {self.task_timeout_s * 1e3:g}): the motion process quick-stopped "
                  "the drives")
        log.error("%s", reason)
        core = self.core
        core.quick_stop("task process silent")
        core.run_on_cycle(lambda: self._estop_on_cycle(reason), wait=False)
        core.post_fault(reason, "motiond")

    def _disable_held(self, silent: float) -> None:
        """The task silent :data:`ORPHAN_HOLD_S` past its timeout: the held drives are disabled, as
        for a dead task (the cycle and the heartbeat go on: the task may run again)."""
        log.error("task process silent for %.0f s: drives disabled", silent)
        self._disable_drives("the task's silence")

    def _disable_drives(self, why: str) -> None:
        """Hold the stream and disable every drive; a failing disable is logged, never raised (the
        watch and the orphan's close must outlive it)."""
        core = self.core
        core.hold_stream = True
        try:
            if core.master is not None:
                core.master.disable()
        except Exception:
            log.exception("disabling the drives for %s", why)

    def run(self) -> None:
        for name, target in (("motion-cmd", self._commands), ("motion-urgent", self._urgent),
                             ("motion-req", self._requests), ("motion-out", self._out),
                             ("motion-watch", self._watch)):
            threading.Thread(target=target, name=name, daemon=True).start()
        while not self.done.wait(0.1):
            if self.orphaned.is_set():
                signal.signal(signal.SIGTERM, signal.SIG_DFL)
                if not self.done.wait(ORPHAN_HOLD_S):
                    self._disable_and_close()
                return

    def _disable_and_close(self) -> None:
        self._disable_drives("the task process's death")
        self.core.stop_cycle()
        self.core.close()


def _call_on_cycle(core: MotionCore, method: Any, args: tuple[Any, ...]) -> None:
    """An urgent call on the cycle thread (run_on_cycle runs it inline there)."""
    method(core, *args)


def _picklable(exc: BaseException) -> BaseException:
    """The exception as the task side can unpickle it (else its text in a RuntimeError)."""
    import pickle

    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:
        return RuntimeError(f"{type(exc).__name__}: {exc}")


def rank_threads(cycle_priority: int) -> None:
    """With a SCHED_FIFO cycle (``[canopen] realtime_priority``): the calling thread, and so every
    thread it starts afterwards, at SCHED_FIFO just below the cycle thread (python-can's reader, the
    heartbeat, the pipes' threads): none of them, holding the interpreter lock, waits behind an ordinary
    process while the cycle waits for the lock (:func:`~fieldbus.canopen.clock.set_fifo`)."""
    from fieldbus.canopen.clock import rank_below_cycle

    rank_below_cycle(cycle_priority, "the motion process's threads", log)


def main(conns: dict[str, Any], limits: Any, canopen: Any, late_fault_s: float, simulated: bool,
         log_level: int, task_timeout_s: float = 0.5) -> None:
    """The motion process's entry point (spawned by MotionProxy.open)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the task's: it stops on the path
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    logging.basicConfig(level=log_level, format="motion[%(process)d] %(levelname)s %(name)s: %(message)s")
    sys.setswitchinterval(min(sys.getswitchinterval(), 0.0005))
    rank_threads(canopen.realtime_priority)  # before any thread starts: they all inherit it
    import planner.core  # noqa: F401  (ruckig, numpy: not on the cycle thread)

    server = MotionServer(conns, limits, canopen, late_fault_s, simulated, task_timeout_s)
    server.run()
    time.sleep(0.05)
    leave()


def leave(code: int = 0) -> None:
    """End the motion process now that its master is closed: logs and streams flushed, then
    ``os._exit``. A normal interpreter exit joins every non-daemon thread (the SDO and output pools'
    workers); one stuck there kept an orphaned motion process alive long after its drives were off
    (seen once, 15 min after its task died)."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)


__all__ = ["END_MARK", "MotionServer", "Stream", "main"]
