"""The machine at run time: the task side's facade over the motion side, wired to the layers.

:class:`Machine` is the core that ``canon run`` and ``canon daemon`` share, and the one object the
rest of the code and the tests use. It owns

* the motion side, :class:`~motiond.runtime.motion.MotionCore` (``self.motion``): the CANopen master,
  the planner and the ``canon-cycle`` thread, reached only through its interface (that module's
  docstring): commands in through a bounded queue, urgent calls as methods, a snapshot out, hooks
  called back on the cycle thread (:class:`_TaskHooks` here);
* the task side, in parts by concern, each readable alone: jobs and the interpreter's job thread
  (:mod:`motiond.runtime.jobs`), run from line (:mod:`motiond.runtime.run_from_line`), the slow
  operations and their ``canon-service`` thread (:mod:`motiond.runtime.service`), the status and its
  ``canon-status`` thread (:mod:`motiond.runtime.status`); here: bring-up and shutdown, the command
  verbs (:meth:`Machine.handle_command`), faults as the task side handles them, events;
* with ``[canopen] simulate = true``, the simulated drives: in "thread" mode here (their own bus
  object and reader thread, outside the motion side), in "own" mode in a process of their own
  (:class:`~motiond.runtime.sim_drives_proc.SimDrivesProcess`); the
  :class:`~fieldbus.modbus.executor.IoExecutor` (and simulated I/O modules on loopback), the
  :class:`~gcode_canon.interpreter.Interpreter`, the :class:`~motiond.states.MachineStates` (the
  transition rules, used as they are), the event publisher.

Faults (a drive's EMCY or heartbeat, a late cycle beyond ``late_fault_s``, an I/O link, an
interpreter or planner error) are posted to the motion side (:meth:`MotionCore.post_fault`), which
acts on the first at the start of the next cycle through :meth:`_TaskHooks.fault`: motion stops (the
master quick-stops the drives on its own faults; otherwise the planner stops on the path with the
quick-stop limits and the drives are then disabled), the job is cancelled, the state becomes FAULTED
with the reason and an event goes out. ``reset`` returns to IDLE with the drives disabled.
"""

from __future__ import annotations

import collections
import concurrent.futures
import contextlib
import dataclasses
import itertools
import logging
import math
import os
import queue
import sys
import threading
import time
from pathlib import Path
from typing import Any

from fieldbus.canopen.config import LOCAL_INTERFACE
from gcode_canon import commands as C
from gcode_canon.errors import GCodeError
from motiond.programs import resolve_program
from motiond.runtime.jobs import Callbacks, Job, JobsMixin
from motiond.runtime.motion import MotionCore
from motiond.runtime.records import MachineError
from motiond.runtime.run_from_line import RunFromLineMixin
from motiond.runtime.service import ServiceMixin, ServiceOp
from motiond.runtime.status import StatusMixin
from motiond.states import CommandRefused, MachineStates, State

log = logging.getLogger(__name__)

SIM_LATE_FAULT_S = 1.0
"""Default late-cycle fault limit with simulated drives in the motion side's process ("thread" mode:
nothing physical to protect; a loaded PC stalls the drives with the cycle)."""
SIM_FEEDBACK_TIMEOUT_S = 0.5
"""With drives simulated in the motion side's process, a TPDO may be this late before it is a fault
(real: 0.1 s)."""
SIM_HEARTBEAT_CONSUMER_MS = 1500
"""And a heartbeat this late (both ways): on a loaded PC the process can stall for a few 100 ms. In
"own" mode the simulated drives run in a process of their own and none of the three applies."""
PRIVATE_SIM_BUSES = ("virtual", LOCAL_INTERFACE)
"""Buses on which a machine's simulated drives get a channel of the machine's own (``<channel>-<pid>-<n>``):
no other machine reaches them there."""

STOP_TIMEOUT_S = 10.0
"""Ctrl-C (``canon run``) or SIGTERM (the daemon): the jerk-limited stop on the path
(:meth:`Machine.stop_on_path`) must be at rest by then (it takes a few 100 ms at most); after it the
drives are disabled whatever the motion."""

_instance = itertools.count(1)


class _MotionAttr:
    """A :class:`Machine` attribute that is the motion side's own (``machine.motion.<name>``), for the
    code and tests that read it on the machine."""

    def __init__(self, *, settable: bool = False) -> None:
        self.settable = settable
        self.name = ""

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    def __get__(self, obj: Any, objtype: type | None = None) -> Any:
        return self if obj is None else getattr(obj.motion, self.name)

    def __set__(self, obj: Any, value: Any) -> None:
        if not self.settable:
            raise AttributeError(f"{self.name} is the motion side's: read only")
        setattr(obj.motion, self.name, value)


class _TaskHooks:
    """What the motion side calls back on the cycle thread (:class:`motiond.runtime.motion.MotionHooks`);
    each returns at once."""

    def __init__(self, machine: Machine) -> None:
        self.m = machine

    def event(self, severity: str, text: str, *, kind: str = "", source: str = "motiond", file: str = "",
              line: int = 0) -> None:
        self.m.event(severity, text, kind=kind, source=source, file=file, line=line)

    def fault(self, reason: str, source: str) -> None:
        """Stop motion, cancel the job, FAULTED with the reason."""
        m = self.m
        if m.states.state is State.FAULTED:
            log.warning("further fault while faulted: %s", reason)
            return
        m.last_error = reason
        m.last_error_utime = time.time_ns() // 1000

        def stop() -> None:
            m.io_hooks.stopped(outputs_off=True)
            m.motion.fault_stop()
            m.states.fault(reason)

        m._cancel_job(reason, then=stop)
        kind = {"canopen": "drive_fault", "modbus": "io_fault"}.get(source, "fault")
        m.event("ERROR", reason, kind=kind, source=source)

    def cancel_stream(self, error: str, aborted: bool) -> None:
        self.m._cancel_job(error, aborted=aborted)

    def stream_done(self) -> None:
        m = self.m

        def finished() -> None:
            if m.states.state in (State.RUNNING, State.PAUSED):
                m.states.finished()

        m._finish_job(finished)

    def aborted(self) -> None:
        if self.m.states.state in (State.RUNNING, State.PAUSED):
            self.m.states.abort()

    def program_stop(self, what: str, w: C.Canon) -> None:
        with contextlib.suppress(CommandRefused):
            self.m.states.pause()
        self.m.event("INFO", f"{what}: program paused; 'resume' continues", kind="program_stop",
                     source="gcode", file=w.file, line=w.line)

    def disable_after_fault(self) -> None:
        threading.Thread(target=self.m._disable_quietly, name="canon-disable", daemon=True).start()

    def planner_prime(self) -> list[C.Canon]:
        return self.m._planner_prime()

    def planner_waits(self) -> tuple[type[C.Canon], ...]:
        return self.m.io_hooks.wait_types

    def io_cycle(self, drive_inputs: tuple[int, ...], velocity: tuple[float, ...]) -> None:
        self.m.io_hooks.cycle(drive_inputs, velocity)

    def io_event(self, ev: C.Canon, stream: Any) -> None:
        self.m.io_hooks.on_event(ev, stream)

    def io_wait(self, w: C.Canon) -> bool:
        return self.m.io_hooks.on_wait(w)

    def orient_text(self) -> str:
        return self.m.io_hooks.orient_text()


class Machine(JobsMixin, RunFromLineMixin, ServiceMixin, StatusMixin):
    """A whole machine from a :class:`motiond.config.MachineConfig` (module docstring).

    ``lc``: an LCM instance for events and status (None: no telemetry). ``interp_settings``: the
    interpreter's settings (:mod:`motiond.interp_settings`); without them they are built from the
    machine file's ``[interpreter]`` with ``var_file`` / ``tool_table`` (the parameter file and tool
    table) taking precedence. ``late_fault_s``: a cycle that
    starts later than this after its deadline is a fault (default: ten cycles, at least 50 ms;
    1 s with simulated drives in this process, "thread" mode).
    ``modbus_port``: put the simulated I/O module on this port instead of the configured one (0: a
    free port; the demo machine uses a free port so that runs do not collide). ``feedback_timeout_s``:
    how long a drive may send no TPDO before it is a fault (CanopenConfig's 0.1 s; 0.5 s with simulated
    drives in this process).
    """

    def __init__(self, config: Any, *, lc: Any = None, telemetry: Any = None,
                 var_file: str | os.PathLike[str] | None = None, tool_table: str | None = None,
                 late_fault_s: float | None = None, modbus_port: int | None = None,
                 sim_lag_s: float = 0.002, feedback_timeout_s: float | None = None,
                 interp_settings: Any = None) -> None:
        from fieldbus.canopen.config import CanopenConfig
        from motiond.config_canopen import canopen_for_machine
        from motiond.config_io import machine_io
        from motiond.io_hooks import IoHooks
        from telemetry.config import TelemetryConfig
        from telemetry.publisher import EventPublisher, StatusPublisher

        self.config = config
        self.limits = config.limits
        self.names = self.limits.names
        self.n = len(self.names)
        self.T = self.limits.cycle_s
        self.telemetry = telemetry if telemetry is not None else TelemetryConfig.from_table(config.telemetry)
        canopen: CanopenConfig = canopen_for_machine(config)
        from motiond.config_motion import motion_settings

        self.motion_mode, watch = motion_settings(config, canopen)  # [motion] process: "thread" or "own"
        if canopen.simulate and canopen.bus.interface in PRIVATE_SIM_BUSES:
            # the drives simulated for this machine are its own: a channel of their own per machine
            # (python-can's virtual channels are global to the process; canon_local's to the user)
            canopen = dataclasses.replace(canopen, bus=dataclasses.replace(
                canopen.bus, channel=f"{canopen.bus.channel}-{os.getpid()}-{next(_instance)}"))
        self.sim_shares_motion = canopen.simulate and self.motion_mode == "thread"
        """The simulated drives run in the motion side's process (and on its interpreter lock)."""
        if self.sim_shares_motion and canopen.bus.interface == LOCAL_INTERFACE:
            # master and drives in this one process: python-can's virtual bus carries their frames
            # without sockets (the demo's pocket.ngc on canon_local here had 2,451-4,078 late cycles
            # against 621-866 on virtual, same load); canon_local is for drives in another process
            canopen = dataclasses.replace(canopen, bus=dataclasses.replace(canopen.bus, interface="virtual"))
        if self.sim_shares_motion:
            # a stall of the process delays the drives' answers as much as the cycle, so allow for it;
            # in "own" mode they are in a process of their own and the configured limits hold
            canopen = dataclasses.replace(
                canopen, feedback_timeout_s=max(canopen.feedback_timeout_s, SIM_FEEDBACK_TIMEOUT_S),
                heartbeat_consumer_ms=max(canopen.heartbeat_consumer_ms, SIM_HEARTBEAT_CONSUMER_MS)
                if canopen.heartbeat_producer_ms else canopen.heartbeat_consumer_ms)
        if feedback_timeout_s is not None:
            canopen = dataclasses.replace(canopen, feedback_timeout_s=feedback_timeout_s)
        self.canopen = canopen
        modbus, io_map = machine_io(config)  # [modbus] with the I/O map's points (motiond.config_io)
        if modbus is not None:
            port = modbus_port
            if port is None and config.path is None:
                port = 0
            if port is not None:
                devices = tuple(dataclasses.replace(d, port=port) if d.simulate else d
                                for d in modbus.devices)
                modbus = dataclasses.replace(modbus, devices=devices)
        self.modbus = modbus
        self.simulated = canopen.simulate
        self.sim_lag_s = sim_lag_s
        if late_fault_s is None:
            late_fault_s = SIM_LATE_FAULT_S if self.sim_shares_motion else max(10 * self.T, 0.050)
        self.late_fault_s = late_fault_s
        if interp_settings is None:  # [interpreter] of the machine file, var_file / tool_table winning
            from motiond.interp_settings import build_settings

            interp_settings = build_settings(config, var=None if var_file is None else str(var_file),
                                             tool_table=tool_table)
        self.save_error = ""
        """Why the parameters could not be saved at shutdown ("" saved): ``canon daemon`` exits 1."""
        self._save_reported: Exception | None = None
        self.program_dirs: list[Path] = list(config.interpreter.program_path)
        """Where the ``run`` command finds programs (``canon daemon`` sets it); none: ``run`` refused."""
        self.var_file = str(interp_settings.var_file) if interp_settings.var_file is not None else None
        self.tool_table = str(interp_settings.tool_table) if interp_settings.tool_table is not None else None
        self.lc = lc
        self.events = EventPublisher(lc, maxsize=self.telemetry.event_queue)
        self.status_pub = StatusPublisher(lc, self.telemetry.status_hz)
        self.states = MachineStates()
        self.states.subscribe(self._on_state_change)
        self.io_hooks = IoHooks(self, io_map)  # the I/O map at run time (docs/wiring.md)

        from gcode_canon.interpreter import Interpreter
        self.interp = Interpreter(interp_settings, Callbacks(self))
        if self.motion_mode == "own":
            from motiond.runtime.motion_proxy import MotionProxy

            # the I/O map stays here: what the motion process must know of it
            io_setup = {"map": not self.io_hooks.empty, "modbus": self.modbus is not None,
                        "orient_text": self.io_hooks.orient_text()}
            self.motion: Any = MotionProxy(self.limits, canopen, late_fault_s=late_fault_s,
                                           simulated=self.simulated, hooks=_TaskHooks(self), watch=watch,
                                           io_setup=io_setup)
        else:
            self.motion = MotionCore(self.limits, canopen, late_fault_s=late_fault_s,
                                     simulated=self.simulated, hooks=_TaskHooks(self))
        self.sim_bus: Any = None
        self.sim_drives: list[Any] = []
        self.io_loop: Any = None  # "own": the I/O map's cycle in this process (motiond.runtime.io_loop)
        self.io = None
        self.sim_io: dict[str, Any] = {}
        self._job: Job | None = None
        self._last_job: Job | None = None
        self._ops = threading.RLock()  # one slow operation (enable, home, reset ...) at a time
        self._activity = ""  # the slow operation holding _ops, in words ("" none)
        self._service_q: queue.SimpleQueue[ServiceOp | None] = queue.SimpleQueue()
        self._service_ops: list[ServiceOp] = []  # accepted and not finished, in order
        self._service_lock = threading.Lock()
        self._service_thread: threading.Thread | None = None
        self._service_closed = False
        self._tls = threading.local()  # .since: the running service op's interruption count
        self._interrupt_lock = threading.Lock()
        self._interrupts = 0  # E-stops (and a shutdown) so far: a slow operation compares
        self._interrupt_reason = ""
        self._aborts = 0  # 'abort' commands so far: a homing stops before its next axis
        self.single_block = False
        self._homing = ""
        self.homed = [False] * self.n
        self.last_error = ""
        self.last_error_utime = 0
        self.status_data_t: collections.OrderedDict[int, float] = collections.OrderedDict()
        """seq of a published status -> monotonic time of the cycle whose drive feedback it carries."""
        self.status_seq = 0
        self._status_stop = threading.Event()
        self._status_thread: threading.Thread | None = None
        self.started = False

    # ------------------------------------------------------------------ bring-up and shutdown
    def start(self) -> Machine:
        """Start the simulators (if configured), boot the drives, start the I/O, the cycle thread and
        telemetry. The machine is then in ESTOP: nothing moves before ``estop_reset`` and ``enable``.
        Raises :class:`MachineError` naming what could not be brought up."""
        from fieldbus.canopen.master import CanopenError

        # a short GIL switch interval: the cycle thread gets the interpreter within 0.5 ms of waking
        # even while the job thread interprets (the default 5 ms would make cycles late)
        sys.setswitchinterval(min(sys.getswitchinterval(), 0.0005))
        import planner.core  # noqa: F401  (ruckig and numpy: imported here, not on the cycle thread)
        import telemetry.lcmtypes.canon.status  # noqa: F401
        self.events.start()
        try:
            if self.simulated and self.motion_mode == "own":  # out of both processes
                from motiond.runtime.sim_drives_proc import SimDrivesProcess

                self.sim_bus = SimDrivesProcess(self.canopen, self.sim_lag_s)
            elif self.simulated:
                from fieldbus.canopen.sim_process import SimBus, machine_sim_drives

                self.sim_drives = machine_sim_drives(self.canopen, self.sim_lag_s)
                self.sim_bus = SimBus(self.sim_drives, self.canopen.bus)
            try:
                self.motion.open()
            except CanopenError as exc:
                raise MachineError(f"CANopen: {exc}") from None
            except Exception as exc:  # python-can: no such interface or channel
                raise MachineError(f"CANopen: cannot open the {self.canopen.bus.interface} bus "
                                   f"{self.canopen.bus.channel!r}: {exc}") from None
            if self.modbus is not None:
                self._start_io()
            if "probe" in self.io_hooks.map.functions:
                self.motion.use_probe_input(self.io_hooks.mio)  # G38.x on the I/O map's probe input
            self.motion.start_cycle()
            probe = getattr(self.motion, "probe_client", None)
            probe = probe if probe is not None and probe.mio is not None else None
            if self.motion_mode == "own" and (not self.io_hooks.empty or probe is not None):
                from motiond.runtime.io_loop import IoLoop

                self.io_loop = IoLoop(self, probe)
                self.io_loop.start()
            self._service_closed = False
            self._service_thread = threading.Thread(target=self._service_main, name="canon-service",
                                                    daemon=True)
            self._service_thread.start()
            self._status_thread = threading.Thread(target=self._status_loop, name="canon-status", daemon=True)
            self._status_thread.start()
        except BaseException:
            self.shutdown()
            raise
        self.started = True
        bus = f"{self.canopen.bus.interface} bus {self.canopen.bus.channel}"
        self.event("INFO", f"machine {self.limits.name!r} up: {self.n} drives, cycle {self.T * 1e3:g} ms, "
                           f"{'simulated drives on ' if self.simulated else ''}{bus}, motion side "
                           f"{self.motion_mode}", kind="startup", source="motiond")
        return self

    def _start_io(self) -> None:
        from fieldbus.modbus.executor import IoExecutor
        from fieldbus.modbus.faults import IoError
        from fieldbus.modbus.sim import SimIoModule, size_for
        from motiond.sim_wiring import apply, wiring_for

        assert self.modbus is not None
        wiring = wiring_for(self.io_hooks.map)
        for dev in self.modbus.devices:
            if dev.simulate:
                mod = SimIoModule(host="127.0.0.1", port=dev.port, unit=dev.unit,
                                  size=size_for(self.modbus, dev.name))
                apply(mod, wiring.get(dev.name), self._sim_z,
                      lambda a: self.motion.commanded[self.names.index(a)])  # [io.sim] limits
                try:
                    mod.start()
                except OSError as exc:
                    raise MachineError(f"simulated Modbus module {dev.name!r}: cannot listen on "
                                       f"127.0.0.1:{dev.port}: {exc}") from None
                self.sim_io[dev.name] = mod
        if any(dev.simulate and dev.port == 0 for dev in self.modbus.devices):
            devices = tuple(dataclasses.replace(d, port=self.sim_io[d.name].port) if d.simulate else d
                            for d in self.modbus.devices)
            self.modbus = dataclasses.replace(self.modbus, devices=devices)
        self.io = IoExecutor(self.modbus, on_fault=self._on_io_fault, on_recover=self._on_io_recover)
        try:
            self.io.start()
        except IoError as exc:
            self.io = None
            raise MachineError(f"Modbus: {exc}") from None
        self.io_hooks.start(self.io)

    def _sim_z(self) -> float:
        """The commanded machine Z (the simulated I/O module's probe, ``[io.sim] probe_z``)."""
        return self.motion.commanded[self.names.index("z")] if "z" in self.names else 0.0

    def shutdown(self) -> None:
        """Stop everything safely: the job cancelled, drives quick-stopped then disabled, outputs to
        their safe values, parameters saved, telemetry stopped. Safe to call twice."""
        interrupted = self._stop_service()
        job = self._job
        if job is not None:
            job.cancel.set()
            self.motion.wake_waiters()
            if job.thread is not None:
                job.thread.join(2.0)
        if self.master is not None and (self.master.streaming or interrupted):
            self.motion.hold_stream = True
            try:
                self._disable_drives()
            except Exception:
                log.exception("disabling the drives at shutdown")
        if self.io_loop is not None:
            self.io_loop.stop()
            self.io_loop = None
        self.motion.stop_cycle()
        if self.io is not None:
            try:
                self.io.stop(safe=True)
            except Exception:
                log.exception("stopping the Modbus I/O")
            self.io = None
        self.motion.close()
        if self.sim_bus is not None:
            self.sim_bus.close()
            self.sim_bus = None
        for mod in self.sim_io.values():
            mod.stop()
        self.sim_io = {}
        try:
            self.interp.shutdown()  # the parameter file
        except Exception as exc:
            where = f"{exc.file}: {exc.message}" if isinstance(exc, GCodeError) and not exc.line else exc
            self.save_error = f"parameters NOT saved at shutdown: {where}"
            self.event("ERROR", self.save_error, kind="save_failed")
        self._status_stop.set()
        if self._status_thread is not None:
            self._status_thread.join(2.0)
            self._status_thread = None
        if self.started:
            self.event("INFO", "machine shut down", kind="shutdown", source="motiond")
        self.started = False
        self.events.stop()

    def __enter__(self) -> Machine:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    # ------------------------------------------------------------------ the motion side, as attributes
    io = _MotionAttr(settable=True)  # the IoExecutor (None: no Modbus); the cycle hands it setpoint events
    master = _MotionAttr()
    planner = _MotionAttr()
    runner = _MotionAttr()
    cycle = _MotionAttr()
    late_cycles = _MotionAttr()
    worst_late_s = _MotionAttr()
    late_log = _MotionAttr()
    first_setpoint_t = _MotionAttr()
    trace = _MotionAttr(settable=True)  # a list: (cycle, monotonic time, positions, events) per setpoint
    optional_stop = _MotionAttr(settable=True)

    def _on_cycle(self, fn: Any, *, wait: bool = True, timeout: float = 2.0) -> Any:
        """Run ``fn`` on the cycle thread (tests stall it with this)."""
        return self.motion.run_on_cycle(fn, wait=wait, timeout=timeout)

    # ------------------------------------------------------------------ helpers
    def event(self, severity: str, text: str, *, kind: str = "", source: str = "motiond", file: str = "",
              line: int = 0) -> None:
        from telemetry.lcmtypes.canon import event as ev

        level = {"DEBUG": logging.DEBUG, "INFO": logging.INFO, "WARNING": logging.WARNING,
                 "ERROR": logging.ERROR, "FATAL": logging.CRITICAL}[severity]
        log.log(level, "%s%s", (f"{file}:{line}: " if line else f"{file}: ") if file else "", text)
        self.events.emit(getattr(ev, severity), text, kind=kind, source=source, file=file, line=line)

    def _on_state_change(self, before: Any, after: Any) -> None:
        if before.state != after.state:
            self.event("INFO", f"state {before.state.value} -> {after.state.value}", kind="state",
                       source="motiond")

    # ------------------------------------------------------------------ faults
    def _post_fault(self, reason: str, source: str) -> None:
        """Any thread: a fault to be acted on at the start of the next cycle (first one wins)."""
        self.motion.post_fault(reason, source)

    def _on_io_fault(self, fault: Any) -> None:
        self._post_fault(str(fault), "modbus")

    def _on_io_recover(self, device: str) -> None:
        self.event("INFO", f"Modbus device {device!r} answers again; outputs written to their safe values",
                   kind="io_recovered", source="modbus")

    # ------------------------------------------------------------------ commands
    def estop(self, reason: str = "") -> None:
        """Always accepted: quick stop on every drive now, the job cancelled, ESTOP. A slow operation
        running meanwhile (homing, enabling ...) fails (:meth:`_operation`). ``reason``: what pressed
        it (the E-stop input, motiond.io_hooks), for the event; none: the operator's command."""
        text = f"E-stop: {reason}" if reason else "E-stop"
        self._interrupt("E-stop")
        self.states.estop()
        self.motion.estop(text)
        self.io_hooks.stopped(outputs_off=True)
        self.event("WARNING", text, kind="estop", source="modbus" if reason else "motiond")

    def pause(self) -> None:
        self.states.pause()
        self.motion.pause()

    def resume(self) -> None:
        self.io_hooks.refuse_resume()
        self.states.resume()
        self.motion.resume()

    def abort(self) -> None:
        """Stop the program on the path (module docstring); a homing stops before its next axis."""
        snap = self.states.snapshot()
        if snap.state not in (State.RUNNING, State.PAUSED, State.IDLE):
            self.states.abort()  # raises
        self._aborts += 1
        self.motion.abort()

    def feed_override(self, factor: float) -> None:
        if not (math.isfinite(factor) and 0.0 <= factor <= 2.0):
            raise CommandRefused(f"feed override must be between 0 and 2 (0 to 200 %), got {factor:g}")
        self.motion.feed_override(factor)

    def jog(self, axis: str, velocity: float, distance: float = 0.0) -> None:
        a = axis.lower()
        if a not in self.names:
            raise CommandRefused(f"no axis {a!r} (axes: {' '.join(self.names)})")
        i = self.names.index(a)
        lim = self.limits.axes[i]
        if velocity == 0.0:
            self.motion.jog_stop()
            return
        if abs(velocity) > lim.max_velocity:
            raise CommandRefused(f"jog velocity {abs(velocity):g} beyond axis {a}'s max_velocity "
                                 f"{lim.max_velocity:g}")
        self.io_hooks.refuse_jog()  # the door interlock
        self.states.manual("jog")
        self.motion.jog(i, velocity, distance, self.interp.position, self.interp.feed)

    def set_single_block(self, on: bool) -> None:
        self.single_block = on

    def set_optional_stop(self, on: bool) -> None:
        self.optional_stop = on

    def set_block_delete(self, on: bool) -> None:
        self.interp.settings.block_delete = on

    # ------------------------------------------------------------------ LCM commands
    def security_event(self, text: str) -> None:
        """A command refused by its authentication (telemetry.commands.CommandServer): an event."""
        self.event("WARNING", text, kind="security", source="telemetry")

    def handle_command(self, cmd: Any) -> str | None:
        """``telemetry.commands.CommandServer``'s handler: None (done / accepted) or the refusal.

        It runs on the LCM thread and never waits for the drives: the slow verbs
        (``control_client.SERVICE_VERBS``) are checked here and carried out on the service thread,
        their result an event (``control_client.result_text``)."""
        from motiond.control_client import SERVICE_VERBS

        verb = cmd.verb
        s = list(cmd.strings)
        v = list(cmd.values)
        if verb in SERVICE_VERBS:
            return self._accept(cmd)  # the result follows as an event
        if verb in ("run", "mdi") or (verb == "jog" and v and v[0] != 0.0):
            busy = self.busy()
            if busy:
                return f"busy: {busy}"
        try:
            if verb == "run":  # only from the program directories (motiond.programs)
                self.run(resolve_program(s[0], self.program_dirs), int(v[0]) if v else 0)
            elif verb == "mdi":
                self.mdi(s[0])
            elif verb == "pause":
                self.pause()
            elif verb == "resume":
                self.resume()
            elif verb == "feed_override":
                self.feed_override(v[0])
            elif verb == "abort":
                self.abort()
            elif verb == "estop":
                self.estop()
            elif verb == "jog":
                self.jog(s[0], v[0], v[1] if len(v) > 1 else 0.0)
            elif verb == "single_block":
                self.set_single_block(bool(v[0]))
            elif verb == "optional_stop":
                self.set_optional_stop(bool(v[0]))
            elif verb == "block_delete":
                self.set_block_delete(bool(v[0]))
            else:
                return f"unknown verb {verb!r}"
        except CommandRefused as exc:
            return str(exc)
        except concurrent.futures.TimeoutError:
            return f"{verb}: the cycle thread did not answer (machine stopping?)"
        self.event("DEBUG", f"command {verb} from {cmd.sender or '?'} done", kind="command",
                   source="telemetry")
        return None

    # ------------------------------------------------------------------ for canon run and tests
    def bring_up(self) -> None:
        """ESTOP -> IDLE -> enabled: what an operator does before running a program."""
        self.estop_reset()
        self.enable()

    def stop_on_path(self, timeout: float = STOP_TIMEOUT_S) -> bool:
        """The jerk-limited stop on the path (:meth:`abort`: the drives keep streaming until the motion is
        at rest), waited for at most ``timeout`` seconds; True at rest. What Ctrl-C and SIGTERM do before
        :meth:`shutdown`, which alone would stop the stream with the axes at speed. A refused abort (a
        fault or E-stop is already stopping the machine) is not an error here."""
        with contextlib.suppress(CommandRefused):
            self.abort()
        return self.wait_at_rest(timeout)

    def wait_at_rest(self, timeout: float) -> bool:
        """After :meth:`abort`: True once the program has ended and its jerk-limited stop on the path
        has brought the motion to rest (or a fault ended it); False after ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        while True:
            if (self._job is None and not self.motion.aborting
                    and self.states.state not in (State.RUNNING, State.PAUSED)):
                return True
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.01)

    @property
    def motion_place(self) -> tuple[str, int]:
        """The file and line of the last setpoint sent to the drives (line 0 before any motion)."""
        line, file = self.motion.place
        return file, line
