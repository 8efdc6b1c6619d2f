"""Task side: the slow operations (enable, disable, estop_reset, reset, home) and their service thread.

:class:`ServiceMixin` is the part of :class:`motiond.runtime.machine.Machine` that carries out the
operations that talk SDO to the drives (tens of milliseconds to tens of seconds): one at a time
(:meth:`ServiceMixin._operation`), failed by an E-stop that comes meanwhile (the drives quick-stopped
again, the machine left in ESTOP). Called as methods they block their caller (``canon run``, tests,
``bring_up``); from the command channel :meth:`ServiceMixin._accept` checks them against the state at
once and hands them to the ``canon-service`` thread, whose result is an event
(``motiond.control_client.result_text``): the thread that answers commands never waits for a homing.

What crosses to the motion side: ``hold_stream`` (no setpoints while a drive homes), a new planner
or none (:meth:`~motiond.runtime.motion.MotionCore.new_planner`,
:meth:`~motiond.runtime.motion.MotionCore.drop_planner`), the quick stop, clearing a handled fault;
and, in this process, the master's SDO calls (``enable``, ``disable``, ``home``, ``boot``,
``reset_faults``), which across processes become requests the motion process serves off its cycle.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from motiond.runtime.parts import MachinePart
from motiond.states import CommandRefused, State

log = logging.getLogger(__name__)

SERVICE_JOIN_S = 5.0
"""Shutdown waits this long for the service thread to end an interrupted operation."""


@dataclass(eq=False)
class ServiceOp:
    """A slow operation the command channel accepted, for the service thread.

    ``since``: the machine's interruption count when it was accepted, so that an E-stop that comes
    after the command but before the thread starts it still makes it fail (an ``estop_reset`` must
    not undo a later ``estop``).
    """

    verb: str
    what: str  # "homing axis x": what a refused command is told is busy
    fn: Callable[[], None]
    request_id: int
    sender: str
    since: int


class ServiceMixin(MachinePart):
    """The slow operations of :class:`~motiond.runtime.machine.Machine` (module docstring)."""

    if TYPE_CHECKING:  # provided by Machine
        master: Any
        homed: list[bool]
        _ops: threading.RLock
        _activity: str
        _homing: str
        _service_q: Any
        _service_ops: list[ServiceOp]
        _service_lock: threading.Lock
        _service_thread: threading.Thread | None
        _service_closed: bool
        _tls: threading.local
        _interrupt_lock: threading.Lock
        _interrupts: int
        _interrupt_reason: str
        _aborts: int

    def busy(self) -> str:
        """The slow operation running or accepted now, in words ("homing axis x"); "" when none.

        The command channel refuses another slow operation, and anything that would move, meanwhile.
        """
        what = self._activity
        if what:
            return what
        with self._service_lock:
            return self._service_ops[0].what if self._service_ops else ""

    @contextlib.contextmanager
    def _operation(self, what: str) -> Iterator[int]:
        """One slow operation at a time (``_ops``), named for :meth:`busy`; yields the interruption
        count it runs against (:class:`ServiceOp`'s ``since`` on the service thread, now otherwise).

        An E-stop (or shutdown) during the operation makes it fail, whatever it got to: the drives are
        quick-stopped again (it may have enabled some after the E-stop's own quick stop) and the state
        put back to ESTOP (it may have left ESTOP or enabled), then :class:`CommandRefused` says so.
        """
        since = getattr(self._tls, "since", None)
        with self._ops:
            if since is None:
                since = self._interrupts
            outer, self._activity = self._activity, what
            try:
                try:
                    yield since
                except Exception as exc:
                    if self._interrupts == since:
                        raise
                    doing = self._activity
                    self._stop_after_interrupt()
                    if isinstance(exc, CommandRefused):
                        raise CommandRefused(f"{doing} interrupted by {self._interrupt_reason} ({exc})") \
                            from None
                    raise
                if self._interrupts != since:
                    doing = self._activity
                    self._stop_after_interrupt()
                    raise CommandRefused(f"{doing} interrupted by {self._interrupt_reason}")
            finally:
                self._activity = outer

    def _interrupt(self, reason: str) -> None:
        """Any thread: every slow operation running or accepted now is to fail (E-stop, shutdown)."""
        with self._interrupt_lock:
            self._interrupt_reason = reason
            self._interrupts += 1

    def _stop_after_interrupt(self) -> None:
        self.motion.quick_stop(self._interrupt_reason or "E-stop")
        self.states.estop()
        self.motion.drop_planner(wait=False)

    def _service_request(self, verb: str, strings: list[str]) -> tuple[Callable[[], None], str]:
        """Check a slow verb against the state now (its refusal in the state rules' words, as the
        method itself would give it) and return the method call for the service thread and what it
        is doing. Nothing here talks to the drives."""
        snap = self.states.snapshot()
        if verb == "enable":
            self._refuse_unless(snap.state is State.IDLE, self.states.enable)
            return self.enable, "enabling the drives"
        if verb == "disable":
            self._refuse_unless(snap.state in (State.IDLE, State.FAULTED), self.states.disable)
            return self.disable, "disabling the drives"
        if verb == "estop_reset":
            self._refuse_unless(snap.state is State.ESTOP, self.states.estop_reset)
            if self.io is not None and self.io.fault is not None and not self.io.link_up:
                raise CommandRefused(f"cannot reset the estop: a Modbus link is down ({self.io.fault})")
            return self.estop_reset, "leaving E-stop (resetting the drives)"
        if verb == "reset":
            self._refuse_unless(snap.state is State.FAULTED, self.states.reset)
            if self.io is not None and self.io.fault is not None and not self.io.link_up:
                raise CommandRefused(f"cannot reset: a Modbus link is still down ({self.io.fault})")
            return self.reset, "resetting the fault"
        if verb == "home":
            names = self._home_axes(strings)
            self.states.manual("home")
            if self.motion.is_moving:
                raise CommandRefused("cannot home while the axes move")
            return (lambda: self.home(names)), f"homing axis {names[0]}"
        raise ValueError(f"{verb!r} is not a slow operation")

    def _refuse_unless(self, allowed: bool, transition: Callable[[], Any]) -> None:
        """``transition`` is the state rule's method, which raises its refusal when not ``allowed``; the
        states' lock keeps the state from changing between the snapshot and the call (the call would
        then perform the transition)."""
        with self.states._lock:
            if not allowed:
                transition()  # raises the refusal

    def _accept(self, cmd: Any) -> str | None:
        """Command thread: check a slow verb now, queue it for the service thread, return at once."""
        verb = cmd.verb
        busy = self.busy()
        if busy:
            return f"busy: {busy}"
        try:
            fn, what = self._service_request(verb, list(cmd.strings))
        except CommandRefused as exc:
            return str(exc)
        op = ServiceOp(verb, what, fn, int(cmd.request_id), str(cmd.sender), self._interrupts)
        with self._service_lock:
            if self._service_thread is None or self._service_closed or not self._service_thread.is_alive():
                return "the machine is not running (shutting down?)"
            if self._service_ops:
                return f"busy: {self._service_ops[0].what}"
            self._service_ops.append(op)
        self._service_q.put(op)
        self.event("DEBUG", f"command {verb} from {cmd.sender or '?'} accepted: {what}", kind="command",
                   source="telemetry")
        return None

    def _service_main(self) -> None:
        """The ``canon-service`` thread: accepted slow operations, in order; each one's result an event."""
        from motiond.control_client import RESULT_KIND, result_text

        while True:
            op = self._service_q.get()
            if op is None:
                return
            error: str | None = "internal error: the operation did not report"
            try:
                error = "not run: the machine is shutting down" if self._service_closed else self._run_op(op)
            finally:  # whatever happened, not busy any more, and before anyone hears the result
                with self._service_lock:
                    if op in self._service_ops:
                        self._service_ops.remove(op)
                self.event("INFO" if error is None else "ERROR",
                           result_text(op.verb, op.request_id, op.sender, error),
                           kind=RESULT_KIND, source="motiond")

    def _run_op(self, op: ServiceOp) -> str | None:
        """Run one operation on the service thread: None, or why it failed."""
        self._tls.since = op.since
        try:
            op.fn()
        except CommandRefused as exc:
            return str(exc)
        except concurrent.futures.TimeoutError:
            return f"{op.what}: the cycle thread did not answer (machine stopping?)"
        except Exception as exc:  # a bug: reported as the result, never silently
            log.exception("%s", op.what)
            return f"internal error while {op.what}: {type(exc).__name__}: {exc}"
        finally:
            self._tls.since = None
        return None

    def _stop_service(self) -> bool:
        """Shutdown: interrupt the running operation (quick stop), drop those not started, end the
        thread (waiting at most :data:`SERVICE_JOIN_S`). True when an operation was interrupted and the
        thread has ended, so that the drives may be disabled by SDO without crossing it."""
        with self._service_lock:
            self._service_closed = True
            running = bool(self._service_ops)
        thread, self._service_thread = self._service_thread, None
        if running:
            self._interrupt("shutdown")
            self.motion.quick_stop("shutdown")
        if thread is None:
            return False
        self._service_q.put(None)
        thread.join(SERVICE_JOIN_S)
        if thread.is_alive():
            log.warning("the service thread is still in %r %g s after shutdown began; carrying on",
                        self.busy(), SERVICE_JOIN_S)
            return False
        return running

    def estop_reset(self) -> None:
        with self._operation("leaving E-stop (resetting the drives)"):
            if self.states.state is not State.ESTOP:
                self.states.estop_reset()  # raises the refusal
            if self.io is not None and self.io.fault is not None and not self.io.acknowledge():
                raise CommandRefused(f"cannot reset the estop: a Modbus link is down ({self.io.fault})")
            self._reset_drives()
            self.states.estop_reset()
            self.last_error = ""

    def _reset_drives(self) -> None:
        """Fault-reset the drives, then take them to Switch on disabled (disabled, as the states say)."""
        from fieldbus.canopen.master import CanopenError

        try:
            lost = self.master.not_operational()
            if lost:  # a drive restarted (power cycle, process restarted): boot the bus again
                self.event("INFO", f"booting the drives again ({', '.join(lost)} not operational)",
                           kind="reboot", source="canopen")
                self.master.boot()
            self.master.reset_faults()
            self._disable_drives()
        except CanopenError as exc:
            raise CommandRefused(f"the drives did not reset: {exc}") from None

    def _disable_drives(self) -> None:
        """Stop streaming and take every drive to Switch on disabled (controlword 0 by SDO)."""
        self.motion.drop_planner()
        self.master.disable()

    def _disable_quietly(self) -> None:
        with self._ops:
            if self.states.state is not State.FAULTED:
                return  # reset (or estop) came first and has taken care of the drives
            try:
                self._disable_drives()
            except Exception as exc:
                log.error("disabling the drives after a fault: %s", exc)

    def enable(self) -> None:
        from fieldbus.canopen.master import CanopenError

        with self._operation("enabling the drives") as since:
            snap = self.states.snapshot()
            if snap.state is not State.IDLE:
                self.states.enable()  # raises the refusal
            if snap.enabled and self.master.streaming:
                return
            try:
                self.master.enable()
            except CanopenError as exc:
                raise CommandRefused(f"enable failed: {exc}") from None
            self.motion.hold_stream = False
            self.motion.new_planner(unless=lambda: self._interrupts != since)
            if self._interrupts != since:
                return  # _operation: failed, and the machine left in ESTOP
            self.states.enable()

    def disable(self) -> None:
        from fieldbus.canopen.master import CanopenError

        with self._operation("disabling the drives"):
            snap = self.states.snapshot()
            if snap.state not in (State.IDLE, State.FAULTED):
                self.states.disable()  # raises
            try:
                self._disable_drives()
            except CanopenError as exc:
                raise CommandRefused(f"disable failed: {exc}") from None
            self.states.disable()

    def reset(self) -> None:
        with self._operation("resetting the fault"):
            if self.states.state is not State.FAULTED:
                self.states.reset()  # raises the refusal
            if self.io is not None and self.io.fault is not None and not self.io.acknowledge():
                raise CommandRefused("cannot reset: a Modbus link is still down "
                                     f"({self.io.fault})")
            deadline = time.monotonic() + 3.0
            while self.motion.fault_stopping and time.monotonic() < deadline:
                time.sleep(0.01)  # the fault's stop on the path is still running
            self._reset_drives()
            self.motion.clear_fault()
            self.states.reset()
            self.last_error = ""
            self.event("INFO", "fault reset", kind="reset", source="motiond")

    def _home_axes(self, axes: list[str] | tuple[str, ...]) -> list[str]:
        names = [a.lower() for a in axes] or list(self.names)
        for a in names:
            if a not in self.names:
                raise CommandRefused(f"no axis {a!r} (axes: {' '.join(self.names)})")
        return names

    def home(self, axes: list[str] | tuple[str, ...] = ()) -> None:
        """Home ``axes`` (all: none given) one after the other. An E-stop fails it at once (the drive
        homing is quick-stopped); an ``abort`` before the next axis."""
        from fieldbus.canopen.master import CanopenError

        names = self._home_axes(axes)
        with self._operation(f"homing axis {names[0]}") as since:
            self.states.manual("home")
            if self.motion.is_moving:
                raise CommandRefused("cannot home while the axes move")
            aborts = self._aborts
            self.motion.hold_stream = True
            try:
                time.sleep(2 * self.T)  # let the cycle thread see the hold
                for a in names:
                    if self._aborts != aborts:
                        raise CommandRefused(f"homing aborted by the operator before axis {a}")
                    self._homing = a
                    self._activity = f"homing axis {a}"
                    self.master.home(a)
                    if self._interrupts != since:
                        return  # _operation: failed, the axis not marked homed
                    # the commanded position rebased to the homed drive before the status says homed,
                    # so no status shows the axis homed at its old coordinate
                    self.motion.new_planner(unless=lambda: self._interrupts != since)
                    self.homed[self.names.index(a)] = True
                    self.event("INFO", f"axis {a} homed", kind="homed", source="canopen")
            except CanopenError as exc:
                raise CommandRefused(f"homing failed: {exc}") from None
            finally:
                self._homing = ""
                self.motion.new_planner(unless=lambda: self._interrupts != since)
                self.motion.hold_stream = False
