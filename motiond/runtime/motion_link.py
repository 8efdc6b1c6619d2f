"""The task side's link to the motion process (``[motion] process = "own"``): the process and its four
pipes, the requests and their answers, the urgent pipe, the threads that read the motion process's
output (states and hooks) and run the hooks in order, and the liveness watch both ways.

:class:`MotionLink` is the transport under :class:`~motiond.runtime.motion_proxy.MotionProxy`, which
turns it into the motion side's interface (what each call means, the states' values); the pipes and
what crosses them are described in :mod:`motiond.runtime.motion_proc`, the watch in
:mod:`motiond.runtime.motion_proxy`.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import itertools
import logging
import multiprocessing
import multiprocessing.connection
import queue
import signal
import threading
import time
from collections.abc import Callable
from typing import Any

from motiond.config_motion import Watch
from motiond.runtime.motion import MotionHooks
from motiond.runtime.motion_proc import FENCING_HOOKS
from motiond.states import CommandRefused

log = logging.getLogger(__name__)

REQUEST_TIMEOUT_S = 30.0
"""A request the motion process does not answer by then (a homing's SDO calls answer sooner)."""


class MotionProcessGone(CommandRefused):
    """The motion process has ended: nothing can be asked of it."""


def death_text(pid: int | None, code: int | None) -> str:
    if code is None:
        return f"the motion process (pid {pid}) is gone"
    if code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f"signal {-code}"
        return f"the motion process (pid {pid}) died: killed by {name}"
    return f"the motion process (pid {pid}) exited with code {code}"


class MotionLink:
    """The motion process, its pipes and the threads that serve them (module docstring). The subclass
    takes the states (:meth:`_take_state`), the hooks (:meth:`_hook`), a fencing hook's new generation
    (:meth:`_next_generation`) and the watch's quick stop (:meth:`quick_stop`)."""

    hooks: MotionHooks
    canopen: Any

    def __init__(self, watch: Watch | None) -> None:
        self.watch = watch or Watch()
        self._last_state = 0.0  # monotonic: when the newest state arrived (0: none yet)
        self.silent = ""  # why the watch tripped ("" it did not, or the states run again)
        self.proc: Any = None
        self._conns: dict[str, Any] = {}
        self._rid = itertools.count(1)
        self._pending: dict[int, concurrent.futures.Future[Any]] = {}
        self._req_lock = threading.Lock()
        self._urgent_lock = threading.Lock()
        self._dispatch: queue.SimpleQueue[Callable[[], None] | None] = queue.SimpleQueue()
        self._dispatch_ident = 0
        self._closing = False
        self.dead = ""  # why the motion process is gone ("" alive)
        self._rank_refused = False
        self._readers: list[threading.Thread] = []  # of the pipes from the motion process
        self._cond = threading.Condition()  # notified with each state, and when the process is gone

    # ------------------------------------------------------------------ what the subclass does
    def _take_state(self, st: dict[str, Any]) -> None:
        raise NotImplementedError

    def _hook(self, name: str, args: tuple[Any, ...], kw: dict[str, Any]) -> None:
        raise NotImplementedError

    def _next_generation(self) -> int:
        raise NotImplementedError

    def quick_stop(self, reason: str) -> None:
        raise NotImplementedError

    # ------------------------------------------------------------------ life cycle
    def _spawn(self, args: tuple[Any, ...]) -> None:
        """The motion process started (``motion_proc.main`` with the pipes' ends, then ``args``), and
        the threads that read its pipes, run its hooks and watch its end."""
        from motiond.runtime import motion_proc

        ctx = multiprocessing.get_context("spawn")
        pipes = {"cmd": ctx.Pipe(duplex=False), "urgent": ctx.Pipe(duplex=False), "req": ctx.Pipe(),
                 "out": ctx.Pipe(duplex=False)}
        child = {"cmd": pipes["cmd"][0], "urgent": pipes["urgent"][0], "req": pipes["req"][1],
                 "out": pipes["out"][1]}
        self._conns = {"cmd": pipes["cmd"][1], "urgent": pipes["urgent"][1], "req": pipes["req"][0],
                       "out": pipes["out"][0]}
        self.proc = ctx.Process(target=motion_proc.main, name="canon-motion", daemon=True,
                                args=(child, *args))
        self.proc.start()
        for c in child.values():
            c.close()
        for name, target in (("canon-hooks", self._dispatcher), ("canon-motion-out", self._receive_out),
                             ("canon-motion-req", self._receive_replies),
                             ("canon-motion-watch", self._watch)):
            thread = threading.Thread(target=self.ranked(target), name=name, daemon=True)
            thread.start()
            if name in ("canon-motion-out", "canon-motion-req"):
                self._readers.append(thread)

    def _start_ping(self) -> None:
        threading.Thread(target=self.ranked(self._ping), name="canon-motion-ping", daemon=True).start()

    def ranked(self, target: Callable[[], None]) -> Callable[[], None]:
        """``target`` run on a thread of the task's stop path (the pipes' readers, the hooks, the
        liveness ping, the I/O loop) at SCHED_FIFO two below a real-time cycle (``[canopen]
        realtime_priority``; the motion process's own threads are one below), else as it is. At normal
        priority a busy PC (two CPU hogs) kept them off a CPU past the 500 ms liveness watch, and the
        motion process stopped a healthy machine; a task thread that waits behind ordinary work also
        delays an E-stop input on its way to the drives. Only these threads: the interpreter's job
        thread, the status and the command server stay ordinary, so a long program's parse cannot take
        a CPU from the rest of the PC."""
        def run() -> None:
            from fieldbus.canopen.clock import rank_below_cycle

            if self.canopen.realtime_priority and not self._rank_refused:  # refused once: said once
                self._rank_refused = not rank_below_cycle(self.canopen.realtime_priority,
                                                          "the task's stop-path threads", log, below=2)
            target()

        return run


    def close(self) -> None:
        """The motion process stops its cycle, shuts the master down and exits."""
        if self.proc is None:
            return
        self._closing = True
        if not self.dead:
            try:
                self.request("close", timeout=10.0, dead=lambda: None)
            except Exception:
                log.exception("closing the motion process")
        self.proc.join(5.0)
        if self.proc.is_alive():  # it ignores SIGTERM while this process lives (motion_proc)
            self.proc.kill()
            self.proc.join(2.0)
        for t in self._readers:  # at the end of their pipes now: closed under them, recv would raise
            t.join(1.0)
        for c in self._conns.values():
            c.close()
        self._dispatch.put(None)

    @property
    def pid(self) -> int | None:
        return None if self.proc is None else self.proc.pid


    # ------------------------------------------------------------------ the pipes
    def request(self, name: str, *args: Any, timeout: float = REQUEST_TIMEOUT_S,
                dead: Callable[[], Any] | None = None, **kw: Any) -> Any:
        """Ask the motion process and wait for its answer; its exception is raised here. ``dead``:
        what to answer once the process is gone (default: MotionProcessGone)."""
        if self.dead or self.silent or "req" not in self._conns:  # gone, hung, or never started
            if dead is not None:
                return dead()
            raise MotionProcessGone(self.dead or self.silent or "the motion process is not running")
        rid = next(self._rid)
        fut: concurrent.futures.Future[Any] = concurrent.futures.Future()
        self._pending[rid] = fut
        try:
            with self._req_lock:
                self._conns["req"].send((rid, name, args, kw))
            return fut.result(timeout)
        except (OSError, ValueError, MotionProcessGone):
            if dead is not None:
                return dead()
            raise MotionProcessGone(self.dead or self.silent or "the motion process is gone") from None
        finally:
            self._pending.pop(rid, None)

    def request_later(self, name: str, *args: Any) -> concurrent.futures.Future[Any]:
        """Ask the motion process without waiting: the future gets its answer (or its exception, or
        MotionProcessGone when the process is gone or hung)."""
        fut: concurrent.futures.Future[Any] = concurrent.futures.Future()
        if self.dead or self.silent or "req" not in self._conns:
            why = self.dead or self.silent or "the motion process is not running"
            fut.set_exception(MotionProcessGone(why))
            return fut
        rid = next(self._rid)
        self._pending[rid] = fut
        fut.add_done_callback(lambda _f: self._pending.pop(rid, None))
        try:
            with self._req_lock:
                self._conns["req"].send((rid, name, args, {}))
        except (OSError, ValueError):
            with contextlib.suppress(concurrent.futures.InvalidStateError):
                fut.set_exception(MotionProcessGone(self.dead or "the motion process is gone"))
        return fut

    def _urgent(self, name: str, *args: Any) -> None:
        if self.dead or "urgent" not in self._conns:
            return
        with self._urgent_lock, contextlib.suppress(OSError, ValueError):
            self._conns["urgent"].send((name, args))

    def urgent(self, name: str, *args: Any) -> None:
        """Down the urgent pipe, not waited for (``probe_trip``)."""
        self._urgent(name, *args)

    def _receive_replies(self) -> None:
        conn = self._conns["req"]
        while True:
            try:
                rid, ok, value = conn.recv()
            except (EOFError, OSError):
                return
            fut = self._pending.get(rid)
            if fut is None:
                continue
            with contextlib.suppress(concurrent.futures.InvalidStateError):  # failed meanwhile (hung)
                if ok:
                    fut.set_result(value)
                else:
                    fut.set_exception(value)

    def _receive_out(self) -> None:
        conn = self._conns["out"]
        while True:
            try:
                batch = conn.recv()
            except (EOFError, OSError):
                return
            for kind, body in batch:
                if kind == "state":
                    self._take_state(body)
                else:
                    name, args, kw = body
                    if name in FENCING_HOOKS:
                        self._next_generation()
                    self._dispatch.put(lambda n=name, a=args, k=kw: self._hook(n, a, k))


    def _dispatcher(self) -> None:
        """``canon-hooks``: the hooks and run_on_cycle calls, in order."""
        self._dispatch_ident = threading.get_ident()
        while True:
            fn = self._dispatch.get()
            if fn is None:
                return
            try:
                fn()
            except Exception:
                log.exception("motion hook")

    def _watch(self) -> None:
        """The motion process's end: a fault unless the task closed it."""
        proc = self.proc
        multiprocessing.connection.wait([proc.sentinel])
        proc.join(1.0)
        if self._closing:
            self.dead = "the motion process was closed"
            return
        self.dead = death_text(proc.pid, proc.exitcode)
        log.error("%s", self.dead)
        for fut in list(self._pending.values()):
            if not fut.done():
                fut.set_exception(MotionProcessGone(self.dead))
        with self._cond:
            self._cond.notify_all()
        self._dispatch.put(lambda: self.hooks.fault(self.dead + "; the drives disable themselves by their "
                                                    "heartbeat consumer", "motiond"))

    def _ping(self) -> None:
        """``canon-motion-ping``: the liveness watch both ways (module docstring)."""
        period = self.watch.task_timeout_ms / 1e3 / 10
        limit = self.watch.motion_timeout_ms / 1e3
        self._last_state = last_look = time.monotonic()
        while not (self._closing or self.dead):
            if not self.silent:  # a hung motion process does not read: the pipe would fill
                self._urgent("ping")
            time.sleep(period)
            now = time.monotonic()
            late = now - last_look - period
            last_look = now
            if late > limit / 4:  # this process stalled: the states may wait in the pipe
                self._last_state = max(self._last_state, now - limit / 2)
                continue
            silent = now - self._last_state
            if silent >= limit and not self.silent and not (self._closing or self.dead):
                self._motion_hung(silent)
            elif silent < limit:
                self.silent = ""

    def _motion_hung(self, silent: float) -> None:
        """The requests waiting for an answer fail now, and the new ones at once, until the states
        run again (the job's cancellation must not wait REQUEST_TIMEOUT_S on each)."""
        reason = (f"the motion process (pid {self.pid}) sent no state for {silent * 1e3:.0f} ms "
                  f"(motion_timeout_ms {self.watch.motion_timeout_ms:g}) though alive: hung? The drives "
                  "are quick-stopped if it runs again, else fault by their heartbeat consumer")
        log.error("%s", reason)
        self.quick_stop(reason)
        self.silent = reason
        for fut in list(self._pending.values()):
            if not fut.done():
                fut.set_exception(MotionProcessGone(reason))
        with self._cond:
            self._cond.notify_all()
        self._dispatch.put(lambda: self.hooks.fault(reason, "motiond"))
