"""The machine at run time: interpreter, planner, CANopen master, Modbus I/O and telemetry, wired.

:class:`Machine` is the core that ``canon run`` and ``canon daemon`` share. It owns

* the :class:`~fieldbus.canopen.master.CanopenMaster` (and, with ``[canopen] simulate = true``, the
  simulated drives in this process on their own bus object and reader thread),
* the :class:`~fieldbus.modbus.executor.IoExecutor` (and, for ``simulate = true`` devices, the
  simulated I/O module on loopback),
* the :class:`~planner.core.Planner`, which only the cycle thread touches (it is not thread-safe:
  every other thread posts a function to :meth:`Machine._on_cycle` instead),
* the :class:`~gcode_canon.interpreter.Interpreter`, run on a job thread that interprets ahead into a
  bounded queue (:data:`QUEUE_MAX` commands),
* the :class:`~motiond.states.MachineStates` (the transition rules, used as they are), the event
  publisher and the status thread.

Threads: ``canon-cycle`` (a :class:`~fieldbus.canopen.clock.PeriodicRunner` on absolute deadlines:
feeds the planner from the queue, one setpoint, one ``master.cycle``, ``io.on_setpoint``); the job
thread (interpretation; blocks in the machine callbacks for M66 and probes); ``canon-status``
(builds and publishes ``canon.status`` at ``status_hz``: never on the cycle thread); ``canon-service``
(the slow operations the command channel asked for, one at a time: see below); the CANopen and
Modbus libraries' own threads; the caller's (commands). Nothing the cycle thread does waits on a
network: LCM publishing, Modbus traffic and SDO transfers all happen elsewhere.

Slow operations (``enable``, ``disable``, ``estop_reset``, ``reset``, ``home``: SDO conversations of
tens of milliseconds to tens of seconds) block their caller when called as methods (``canon run``,
tests, :meth:`Machine.bring_up`). From the command channel, :meth:`Machine.handle_command` checks them
against the state at once, hands them to the ``canon-service`` thread and returns: the LCM thread
that answers commands must never wait behind a 30 s homing, or an operator's ``estop``, ``abort`` or
``pause`` would wait with it. While one runs, another is refused (``busy: homing axis x``); its result
is an event (``motiond.control_client.result_text``). ``estop`` interrupts a running one: the drives
are quick-stopped at once (no SDO), and the operation ends failed with the machine left in ESTOP.

Faults (a drive's EMCY or heartbeat, a late cycle beyond ``late_fault_s``, an I/O link, an
interpreter or planner error) all end in :meth:`Machine._fault`: motion stops (the master quick-stops
the drives on its own faults; otherwise the planner stops on the path with the quick-stop limits
and the drives are then disabled), the job is cancelled, the state becomes FAULTED with the reason
and an event goes out. ``reset`` returns to IDLE with the drives disabled.
"""

from __future__ import annotations

import collections
import concurrent.futures
import contextlib
import dataclasses
import itertools
import linecache
import logging
import math
import os
import queue
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from gcode_canon import commands as C
from gcode_canon.errors import GCodeError
from motiond.programs import resolve_program
from motiond.states import CommandRefused, MachineStates, Mode, State

log = logging.getLogger(__name__)

QUEUE_MAX = 2000
"""Canonical commands the interpreter may run ahead of the planner."""
LOOKAHEAD = 300
"""Items kept queued in the planner (its lookahead); more wait in the interpreter's queue."""
FEED_PER_CYCLE = 40
"""At most this many commands move into the planner per cycle (bounds the cycle's work)."""
SIM_LATE_FAULT_S = 1.0
"""Default late-cycle fault limit with simulated drives (nothing physical to protect; a loaded PC)."""
SIM_FEEDBACK_TIMEOUT_S = 0.5
SIM_HEARTBEAT_CONSUMER_MS = 1500
"""And a heartbeat this late (both ways): on a loaded PC the process can stall for a few 100 ms."""
"""With drives simulated in this process, a TPDO may be this late before it is a fault (real: 0.1 s)."""
LATE_LOG = 100_000
"""The lateness of this many late cycles is kept (for the run summary's verdict)."""
SERVICE_JOIN_S = 5.0
"""Shutdown waits this long for the service thread to end an interrupted operation."""
_END = object()  # end of a job's commands in the queue

_instance = itertools.count(1)


class MachineError(Exception):
    """The machine could not be brought up (boot, I/O, telemetry); the message says what and where."""


@dataclass
class AxisPeaks:
    velocity: float = 0.0
    acceleration: float = 0.0
    jerk: float = 0.0
    following_error: float = 0.0


@dataclass
class OutputSwitch:
    """A Modbus output the program switched, in the cycle it was handed to the I/O side."""

    cycle: int
    t: float  # monotonic time of that cycle
    kind: str  # "digital" or "analog"
    index: int
    value: float
    synced: bool
    file: str
    line: int


@dataclass
class JobResult:
    """What a finished program (or MDI line) did: ``error`` is empty when it ended normally."""

    program: str
    ok: bool
    error: str = ""
    aborted: bool = False
    duration_s: float = 0.0
    cycles: int = 0
    cycle_s: float = 0.0
    late_cycles: int = 0
    peaks: dict[str, AxisPeaks] = field(default_factory=dict)
    outputs: list[OutputSwitch] = field(default_factory=list)
    final_commanded: tuple[float, ...] = ()
    final_actual: tuple[float, ...] = ()
    expected_final: tuple[float, ...] = ()
    first_cycle: int = 0
    # where the time went (the run summary explains a run longer than its motion with these)
    moving_cycles: int = 0  # cycles in which some axis moved
    first_setpoint_s: float = 0.0  # from the start of the job to its first setpoint
    last_setpoint_s: float = 0.0  # ... to its last
    late_s: list[float] = field(default_factory=list)  # how late each late cycle of the job started


@dataclass(frozen=True, slots=True)
class ModalState(C.Canon):
    """The interpreter's modal state after a line, travelling with the commands to the status.

    Not a machining command. The interpreter reads up to :data:`QUEUE_MAX` commands ahead of the
    motion, so its own state describes text not yet cut. The job thread puts one of these in front of
    the first command of a line whose modal state differs from the previous line's; the planner passes
    it on as an event riding on the first setpoint of the next motion (or sync point), exactly as it
    does a synchronized output (M62), and the cycle thread shows it in the status from that setpoint
    on: the state of the block being executed.
    """

    NAME: ClassVar[str] = "MODAL_STATE"
    gcodes: tuple[str, ...] = ()
    mcodes: tuple[str, ...] = ()
    feed: float = 0.0
    tool: int = 0
    tool_length_offset: float = 0.0


@dataclass
class _StartState:
    """Run from line: what the lines before the start line left active, read from the interpreter
    just before it executes the start line (so the start line's own words are not in it)."""

    target: C.Pose  # where the skipped part left the tool: the start of the first move (machine)
    tool: int
    selected: int
    spindle: int  # 1 M3, -1 M4, 0 M5
    speed: float
    mist: bool
    flood: bool
    overrides: dict[str, bool]
    feed_mode: C.FeedMode
    feed: float
    control: tuple[Any, float, float]
    modal: ModalState
    key: object


class _RunFrom:
    """Run from line: the job thread's bookkeeping while the lines before the start line are
    interpreted with their commands withheld from the planner (:meth:`Machine._job_main`)."""

    def __init__(self, line: int, tool: int) -> None:
        self.line = line
        self.tool0 = tool  # the tool in the spindle when the job started
        self.main: Any = None  # the main program's LineSource (the first one the hook sees)
        self.reached = False  # the interpreter is about to execute the start line (state captured)
        self.started = False  # the restore and the approach are queued: commands go to the planner
        self.skipped = 0
        self.outputs: list[C.DigitalOutput | C.AnalogOutput] = []
        self.tool_cmd: C.ToolChange | C.SetToolNumber | None = None
        self.end_line = 0  # where a skipped M2/M30 ended the program
        self.state: _StartState | None = None

    def note(self, cmd: C.Canon) -> None:
        """A command of the skipped part: nothing is sent, but what must be reported is kept."""
        self.skipped += 1
        if isinstance(cmd, C.DigitalOutput | C.AnalogOutput):
            self.outputs.append(cmd)
        elif isinstance(cmd, C.ToolChange | C.SetToolNumber):
            self.tool_cmd = cmd
        elif isinstance(cmd, C.ProgramEnd):
            self.end_line = cmd.line


class _Job:
    def __init__(self, program: str, mode: Mode, n_axes: int) -> None:
        self.program = program
        self.mode = mode
        self.cancel = threading.Event()
        self.done = threading.Event()
        self.input_done = False
        self.thread: threading.Thread | None = None
        self.error = ""
        self.aborted = False
        self.t0 = time.monotonic()
        self.cycle0 = 0
        self.late0 = 0
        self.queued = 0
        self.peaks = [AxisPeaks() for _ in range(n_axes)]
        self.outputs: list[OutputSwitch] = []
        self.result: JobResult | None = None
        self.line = 0
        self.lines_total = 0
        self.run_from: _RunFrom | None = None
        self.moving_cycles = 0
        self.t_first = 0.0
        self.t_last = 0.0

    @property
    def skipping(self) -> bool:
        """Run from line, before the start: commands are withheld and nothing may wait for motion."""
        return self.run_from is not None and not self.run_from.started


@dataclass(eq=False)
class _ServiceOp:
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


class _Aborted(Exception):
    """The job was cancelled while the interpreter waited in a machine callback."""


class _Callbacks:
    """The interpreter's machine callbacks (``gcode_canon.machine.MachineCallbacks``).

    They run on the job thread. The interpreter asks them right after yielding the sync command, long
    before the cycle thread has run the motion before it; so M66 and probes wait here until the
    planner stands at that sync point, then answer, then let the planner go on (``release``).
    """

    def __init__(self, machine: Machine) -> None:
        self.m = machine

    def _job(self) -> _Job:
        job = self.m._job
        if job is None:
            raise _Aborted()
        return job

    def wait_input(self, cmd: C.WaitInput) -> float:
        job = self._job()
        io = self.m.io
        if io is None:
            raise GCodeError("M66: this machine has no Modbus I/O configured ([modbus])", cmd.file, cmd.line)
        # before the start line of a run from line nothing moves: the input is read (waited for) now
        synced = job.mode is Mode.AUTO and not job.skipping
        if synced:
            self.m._wait_sync_point(cmd, job)
        from fieldbus.modbus.faults import IoError, WaitAborted

        try:
            value = io.wait_input(cmd, cancel=job.cancel)
        except WaitAborted:
            raise _Aborted() from None
        except IoError as exc:
            raise GCodeError(str(exc), cmd.file, cmd.line) from None
        if synced:
            self.m._on_cycle(self.m._release_wait, wait=False)
        return value

    def probe(self, cmd: C.Probe) -> tuple[C.Pose, bool]:
        job = self._job()
        if job.skipping:
            assert job.run_from is not None
            raise GCodeError(f"cannot start at line {job.run_from.line}: the probe at line {cmd.line} comes "
                             "before it, and its result (#5061-#5070) needs the probing move; start at or "
                             "before the probe", cmd.file, cmd.line)
        if not self.m.simulated:
            raise GCodeError("probing (G38.x) needs a probe input, and this machine has none configured",
                             cmd.file, cmd.line)
        if job.mode is Mode.AUTO:
            self.m._wait_sync_point(cmd, job)
            self.m._on_cycle(self.m._release_wait, wait=False)
        self.m.event("INFO", "probe: simulated machine, contact at the end point of the move",
                     kind="probe", source="motiond", file=cmd.file, line=cmd.line)
        return cmd.end, True

    def current_position(self) -> C.Pose | None:
        """At the start of a program or MDI line: where the machine is (it may have been jogged, homed
        or stopped by an abort since the interpreter last commanded it). Later (after M0, M6): None,
        the machine went exactly where the interpreter sent it; also after an M6 before the start line
        of a run from line (nothing moved: the interpreter's own position is the program's)."""
        job = self.m._job
        if job is None or job.queued or (job.run_from is not None and job.run_from.skipped):
            return None
        return self.m._machine_pose()

    def print_text(self, text: str) -> None:
        self.m.event("INFO", text, kind="print", source="gcode")


class Machine:
    """A whole machine from a :class:`motiond.config.MachineConfig` (module docstring).

    ``lc``: an LCM instance for events and status (None: no telemetry). ``interp_settings``: the
    interpreter's settings (:mod:`motiond.interp_settings`); without them they are built from the
    machine file's ``[interpreter]`` with ``var_file`` / ``tool_table`` (the parameter file and tool
    table) taking precedence. ``late_fault_s``: a cycle that
    starts later than this after its deadline is a fault (default: ten cycles, at least 50 ms;
    1 s with simulated drives).
    ``modbus_port``: put the simulated I/O module on this port instead of the configured one (0: a
    free port; the demo machine uses a free port so that runs do not collide). ``feedback_timeout_s``:
    how long a drive may send no TPDO before it is a fault (CanopenConfig's 0.1 s; 0.5 s simulated).
    """

    def __init__(self, config: Any, *, lc: Any = None, telemetry: Any = None,
                 var_file: str | os.PathLike[str] | None = None, tool_table: str | None = None,
                 late_fault_s: float | None = None, modbus_port: int | None = None,
                 sim_lag_s: float = 0.002, feedback_timeout_s: float | None = None,
                 interp_settings: Any = None) -> None:
        from fieldbus.canopen.config import CanopenConfig
        from motiond.config_canopen import canopen_for_machine
        from motiond.config_modbus import modbus_for
        from telemetry.config import TelemetryConfig
        from telemetry.publisher import EventPublisher, StatusPublisher

        self.config = config
        self.limits = config.limits
        self.names = self.limits.names
        self.n = len(self.names)
        self.T = self.limits.cycle_s
        self.telemetry = telemetry if telemetry is not None else TelemetryConfig.from_table(config.telemetry)
        canopen: CanopenConfig = canopen_for_machine(config)
        if canopen.simulate and canopen.bus.interface == "virtual":
            # python-can's virtual channels are global to the process: one of our own per machine
            canopen = dataclasses.replace(canopen, bus=dataclasses.replace(
                canopen.bus, channel=f"{canopen.bus.channel}-{os.getpid()}-{next(_instance)}"))
        if canopen.simulate:
            # the simulated drives share this process (and its interpreter lock) with the master: a stall
            # of the process delays their answers as much as the cycle, so allow for it
            canopen = dataclasses.replace(
                canopen, feedback_timeout_s=max(canopen.feedback_timeout_s, SIM_FEEDBACK_TIMEOUT_S),
                heartbeat_consumer_ms=max(canopen.heartbeat_consumer_ms, SIM_HEARTBEAT_CONSUMER_MS)
                if canopen.heartbeat_producer_ms else canopen.heartbeat_consumer_ms)
        if feedback_timeout_s is not None:
            canopen = dataclasses.replace(canopen, feedback_timeout_s=feedback_timeout_s)
        self.canopen = canopen
        modbus = modbus_for(config)
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
            late_fault_s = SIM_LATE_FAULT_S if canopen.simulate else max(10 * self.T, 0.050)
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

        from gcode_canon.interpreter import Interpreter
        self.interp = Interpreter(interp_settings, _Callbacks(self))
        self.master: Any = None
        self.sim_bus: Any = None
        self.sim_drives: list[Any] = []
        self.io: Any = None
        self.sim_io: dict[str, Any] = {}
        self.planner: Any = None
        self.runner: Any = None
        self._calls: queue.SimpleQueue[Callable[[], None]] = queue.SimpleQueue()
        self._cmdq: queue.Queue[Any] = queue.Queue(QUEUE_MAX)
        self._job: _Job | None = None
        self._last_job: _Job | None = None
        self._ops = threading.RLock()  # one slow operation (enable, home, reset ...) at a time
        self._activity = ""  # the slow operation holding _ops, in words ("" none)
        self._service_q: queue.SimpleQueue[_ServiceOp | None] = queue.SimpleQueue()
        self._service_ops: list[_ServiceOp] = []  # accepted and not finished, in order
        self._service_lock = threading.Lock()
        self._service_thread: threading.Thread | None = None
        self._service_closed = False
        self._tls = threading.local()  # .since: the running service op's interruption count
        self._stop_lock = threading.Lock()
        self._interrupts = 0  # E-stops (and a shutdown) so far: a slow operation compares
        self._interrupt_reason = ""
        self._aborts = 0  # 'abort' commands so far: a homing stops before its next axis
        self._fault_lock = threading.Lock()
        self._pending_fault: tuple[str, str] | None = None
        self._estopping = False
        self._hold_stream = False
        self._wait_seen: Any = None
        self._stopped_at: Any = None  # the M0/M1/M60 the planner waits at (resume releases)
        self._sync_cond = threading.Condition()
        self._sync_reached: Any = None
        self._aborting = False
        self._stop_then_disable = False
        self.single_block = False
        self.optional_stop = False
        self._homing = ""
        self._jogging = False
        self.homed = [False] * self.n
        self.cycle = 0
        self.late_cycles = 0
        self.worst_late_s = 0.0
        self.late_log: collections.deque[tuple[int, float]] = collections.deque(maxlen=LATE_LOG)
        self.last_error = ""
        self.last_error_utime = 0
        self._commanded = tuple(0.0 for _ in range(self.n))
        self._velocity = tuple(0.0 for _ in range(self.n))
        self._acc = [0.0] * self.n
        self._actual = tuple(0.0 for _ in range(self.n))
        self._actual_t = 0.0
        self.status_data_t: collections.OrderedDict[int, float] = collections.OrderedDict()
        """seq of a published status -> monotonic time of the cycle whose drive feedback it carries."""
        self._fe = tuple(0.0 for _ in range(self.n))
        self._line = (0, "")
        self._spindle = (0, 0.0)
        self._coolant = (False, False)
        self._tool_prepared = 0
        self._modal: ModalState | None = None  # the executing block's modal state (a job running)
        self.first_setpoint_t: float | None = None
        self.status_seq = 0
        self._status_stop = threading.Event()
        self._status_thread: threading.Thread | None = None
        self.started = False
        self._cycle_ident = 0
        self.trace: list[tuple[int, float, tuple[float, ...], tuple[Any, ...]]] | None = None
        """Set to a list to record (cycle, monotonic time, positions, events) of every setpoint."""

    # ------------------------------------------------------------------ bring-up and shutdown
    def start(self) -> Machine:
        """Start the simulators (if configured), boot the drives, start the I/O, the cycle thread and
        telemetry. The machine is then in ESTOP: nothing moves before ``estop_reset`` and ``enable``.
        Raises :class:`MachineError` naming what could not be brought up."""
        from fieldbus.canopen.clock import PeriodicRunner
        from fieldbus.canopen.master import CanopenError, CanopenMaster

        # a short GIL switch interval: the cycle thread gets the interpreter within 0.5 ms of waking
        # even while the job thread interprets (the default 5 ms would make cycles late)
        sys.setswitchinterval(min(sys.getswitchinterval(), 0.0005))
        import planner.core  # noqa: F401  (ruckig and numpy: imported here, not on the cycle thread)
        import telemetry.lcmtypes.canon.status  # noqa: F401
        self.events.start()
        try:
            if self.simulated:
                from fieldbus.canopen.drive_sim import SimDrive, motor_for
                from fieldbus.canopen.sim_process import SimBus

                self.sim_drives = [SimDrive(d.node_id, d.eds_path, lag_s=self.sim_lag_s,
                                            parameters=motor_for(d, d.eds_path))
                                   for d in self.canopen.drives]
                self.sim_bus = SimBus(self.sim_drives, self.canopen.bus)
            try:
                self.master = CanopenMaster(self.canopen)
                self.master.add_fault_listener(self._on_master_fault)
                self.master.add_warning_listener(self._on_master_warning)
                self.master.open()
                self.master.boot()
            except CanopenError as exc:
                raise MachineError(f"CANopen: {exc}") from None
            except Exception as exc:  # python-can: no such interface or channel
                raise MachineError(f"CANopen: cannot open the {self.canopen.bus.interface} bus "
                                   f"{self.canopen.bus.channel!r}: {exc}") from None
            if self.modbus is not None:
                self._start_io()
            self.runner = PeriodicRunner(self.T, self._step, on_late=self._on_late, keep_lateness=False,
                                         name="canon-cycle",
                                         realtime_priority=self.canopen.realtime_priority,
                                         cpu_latency_us=self.canopen.cpu_latency_us,
                                         cpu_affinity=self.canopen.cpu_affinity,
                                         steer_gc=self.canopen.steer_gc, tick=self.master.sync_tick)
            self.runner.start()
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
        self.event("INFO", f"machine {self.limits.name!r} up: {self.n} drives, cycle {self.T * 1e3:g} ms, "
                           f"{'simulated' if self.simulated else self.canopen.bus.interface} bus",
                   kind="startup", source="motiond")
        return self

    def _start_io(self) -> None:
        from fieldbus.modbus.executor import IoExecutor
        from fieldbus.modbus.faults import IoError
        from fieldbus.modbus.sim import SimIoModule

        assert self.modbus is not None
        for dev in self.modbus.devices:
            if dev.simulate:
                mod = SimIoModule(host="127.0.0.1", port=dev.port, unit=dev.unit)
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

    def shutdown(self) -> None:
        """Stop everything safely: the job cancelled, drives quick-stopped then disabled, outputs to
        their safe values, parameters saved, telemetry stopped. Safe to call twice."""
        interrupted = self._stop_service()
        job = self._job
        if job is not None:
            job.cancel.set()
            with self._sync_cond:
                self._sync_cond.notify_all()
            if job.thread is not None:
                job.thread.join(2.0)
        if self.master is not None and (self.master.streaming or interrupted):
            self._hold_stream = True
            try:
                self._disable_drives()
            except Exception:
                log.exception("disabling the drives at shutdown")
        if self.runner is not None:
            self.runner.stop()
            self.runner.join(2.0)
            self.runner = None
        if self.io is not None:
            try:
                self.io.stop(safe=True)
            except Exception:
                log.exception("stopping the Modbus I/O")
            self.io = None
        if self.master is not None:
            try:
                self.master.shutdown()
            except Exception:
                log.exception("shutting the CANopen master down")
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

    # ------------------------------------------------------------------ helpers
    def event(self, severity: str, text: str, *, kind: str = "", source: str = "motiond", file: str = "",
              line: int = 0) -> None:
        from telemetry.lcmtypes.canon import event as ev

        level = {"DEBUG": logging.DEBUG, "INFO": logging.INFO, "WARNING": logging.WARNING,
                 "ERROR": logging.ERROR, "FATAL": logging.CRITICAL}[severity]
        log.log(level, "%s%s", (f"{file}:{line}: " if line else f"{file}: ") if file else "", text)
        self.events.emit(getattr(ev, severity), text, kind=kind, source=source, file=file, line=line)

    def _on_cycle(self, fn: Callable[[], Any], *, wait: bool = True, timeout: float = 2.0) -> Any:
        """Run ``fn`` on the cycle thread (which owns the planner) and return its result."""
        runner = self.runner
        if runner is None or runner.join(0) or threading.get_ident() == self._cycle_ident:
            return fn()
        fut: concurrent.futures.Future[Any] = concurrent.futures.Future()

        def call() -> None:
            try:
                fut.set_result(fn())
            except BaseException as exc:
                fut.set_exception(exc)

        self._calls.put(call)
        if not wait:
            return None
        return fut.result(timeout)

    # ------------------------------------------------------------------ slow operations
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
        count it runs against (:class:`_ServiceOp`'s ``since`` on the service thread, now otherwise).

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
        with self._stop_lock:
            self._interrupt_reason = reason
            self._interrupts += 1

    def _quick_stop(self, reason: str) -> None:
        """CiA 402 quick stop on every drive now (RPDOs, no SDO), not reported as a drive fault."""
        if self.master is None:
            return
        with self._stop_lock:
            self._estopping = True
            try:
                self.master.quick_stop(reason)
            finally:
                self._estopping = False

    def _stop_after_interrupt(self) -> None:
        self._quick_stop(self._interrupt_reason or "E-stop")
        self.states.estop()
        self._on_cycle(lambda: setattr(self, "planner", None), wait=False)

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
            if self.planner is not None and not self.planner.is_idle:
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
        op = _ServiceOp(verb, what, fn, int(cmd.request_id), str(cmd.sender), self._interrupts)
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

    def _run_op(self, op: _ServiceOp) -> str | None:
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
            self._quick_stop("shutdown")
        if thread is None:
            return False
        self._service_q.put(None)
        thread.join(SERVICE_JOIN_S)
        if thread.is_alive():
            log.warning("the service thread is still in %r %g s after shutdown began; carrying on",
                        self.busy(), SERVICE_JOIN_S)
            return False
        return running

    def _on_state_change(self, before: Any, after: Any) -> None:
        if before.state != after.state:
            self.event("INFO", f"state {before.state.value} -> {after.state.value}", kind="state",
                       source="motiond")

    # ------------------------------------------------------------------ faults
    def _on_master_fault(self, fault: Any) -> None:
        if self._estopping:
            return
        self._post_fault(str(fault), "canopen")

    def _on_master_warning(self, warning: Any) -> None:
        """A drive without an optional object, a warning EMCY: logged and published, motion goes on."""
        self.event("WARNING", str(warning), kind="drive_warning", source="canopen")

    def _on_io_fault(self, fault: Any) -> None:
        self._post_fault(str(fault), "modbus")

    def _on_io_recover(self, device: str) -> None:
        self.event("INFO", f"Modbus device {device!r} answers again; outputs written to their safe values",
                   kind="io_recovered", source="modbus")

    def _on_late(self, k: int, by: float) -> None:
        self.late_cycles += 1
        self.late_log.append((self.cycle, by))
        self.worst_late_s = max(self.worst_late_s, by)
        if by > self.late_fault_s and self.master is not None and self.master.streaming:
            self._post_fault(f"cycle {k} started {by * 1e3:.1f} ms late (limit "
                             f"{self.late_fault_s * 1e3:g} ms, period {self.T * 1e3:g} ms)", "motiond")

    def _post_fault(self, reason: str, source: str) -> None:
        """Any thread: a fault to be acted on at the start of the next cycle (first one wins)."""
        with self._fault_lock:
            if self._pending_fault is None:
                self._pending_fault = (reason, source)

    def _handle_fault(self) -> None:
        """Cycle thread: stop motion, cancel the job, FAULTED with the reason."""
        with self._fault_lock:
            pending, self._pending_fault = self._pending_fault, None
        if pending is None:
            return
        reason, source = pending
        if self.states.state is State.FAULTED:
            log.warning("further fault while faulted: %s", reason)
            return
        self.last_error = reason
        self.last_error_utime = time.time_ns() // 1000
        self._cancel_job(reason)
        master_faulted = self.master is not None and self.master.fault is not None
        if self.planner is not None:
            if master_faulted:
                self.planner = None  # the drives stop on their own ramps; the planner restarts later
            else:
                self.planner.quick_stop()
                self._stop_then_disable = True
        self.states.fault(reason)
        kind = {"canopen": "drive_fault", "modbus": "io_fault"}.get(source, "fault")
        self.event("ERROR", reason, kind=kind, source=source)

    def _cancel_job(self, error: str = "", aborted: bool = False) -> None:
        job = self._job
        if job is None:
            return
        job.cancel.set()
        if error and not job.error:
            job.error = error
        job.aborted = job.aborted or aborted
        while True:
            try:
                self._cmdq.get_nowait()
            except queue.Empty:
                break
        with self._sync_cond:
            self._sync_cond.notify_all()
        self._finish_job()

    # ------------------------------------------------------------------ the cycle
    def _step(self, k: int, deadline: float) -> None:
        try:
            self._cycle_step()
        except Exception as exc:  # a bug must not end the cycle thread with the drives streaming
            log.exception("cycle %d", k)
            self._post_fault(f"internal error in the cycle loop: {exc!r}", "motiond")

    def _cycle_step(self) -> None:
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
        master = self.master
        p = self.planner
        sp = None
        if p is not None and master.streaming and not self._hold_stream:
            try:
                self._feed(p)
                sp = p.next_setpoint()
            except GCodeError as exc:  # PlannerError
                self._post_fault(str(exc), "planner")
                sp = None
        fb = master.cycle(sp.positions if sp is not None else None)
        self._actual = fb.positions
        self._actual_t = time.monotonic()
        self._fe = fb.following_errors
        job = self._job
        if self.trace is not None and sp is not None:
            self.trace.append((self.cycle, time.monotonic(), sp.positions, sp.events))
        if sp is not None:
            if self.first_setpoint_t is None:
                self.first_setpoint_t = time.monotonic()
            self._track(sp, job)
            if sp.events:
                self._events(sp, job)
                if self.io is not None:
                    self.io.on_setpoint(sp)
        else:
            self._velocity = tuple(0.0 for _ in range(self.n))
            self._acc = [0.0] * self.n
        if p is not None and p is self.planner:
            w = p.waiting_for
            if w is not None and w is not self._wait_seen:
                self._wait_seen = w
                self._on_wait(w)
            if p.is_idle:
                self._at_rest()
        elif self.planner is None and (self._aborting or self._stop_then_disable):
            self._at_rest()

    def _feed(self, p: Any) -> None:
        job = self._job
        if job is None:
            return
        n = 0
        while p.queue_length < LOOKAHEAD and n < FEED_PER_CYCLE:
            try:
                item = self._cmdq.get_nowait()
            except queue.Empty:
                return
            n += 1
            if item is _END:
                p.flush()
                job.input_done = True
                return
            if self.io is not None and isinstance(item, C.DigitalOutput | C.AnalogOutput | C.WaitInput):
                problem = self.io.check(item)
                if problem:
                    raise GCodeError(problem, item.file, item.line)
            elif self.io is None and isinstance(item, C.DigitalOutput | C.AnalogOutput):
                raise GCodeError(f"{item.NAME}: this machine has no Modbus I/O configured ([modbus])",
                                 item.file, item.line)
            p.feed(item)

    def _track(self, sp: Any, job: _Job | None) -> None:
        T = self.T
        prev = self._commanded
        pos = sp.positions
        vel = tuple((a - b) / T for a, b in zip(pos, prev, strict=True))
        acc = [(a - b) / T for a, b in zip(vel, self._velocity, strict=True)]
        if job is not None:
            for i, pk in enumerate(job.peaks):
                v, a = abs(vel[i]), abs(acc[i])
                j = abs(acc[i] - self._acc[i]) / T
                if v > pk.velocity:
                    pk.velocity = v
                if a > pk.acceleration:
                    pk.acceleration = a
                if j > pk.jerk:
                    pk.jerk = j
                fe = abs(self._fe[i])
                if fe > pk.following_error:
                    pk.following_error = fe
            if sp.line:
                job.line = sp.line
            if any(vel):
                job.moving_cycles += 1
            if not job.t_first:
                job.t_first = self._actual_t
            job.t_last = self._actual_t
        self._commanded = pos
        self._velocity = vel
        self._acc = acc
        if sp.line:
            self._line = (sp.line, sp.file)

    def _events(self, sp: Any, job: _Job | None) -> None:
        for ev in sp.events:
            if isinstance(ev, C.DigitalOutput | C.AnalogOutput):
                if job is not None:
                    digital = isinstance(ev, C.DigitalOutput)
                    job.outputs.append(OutputSwitch(
                        self.cycle, time.monotonic(), "digital" if digital else "analog", ev.index,
                        float(ev.on) if digital else ev.value, ev.synced, ev.file, ev.line))
            elif isinstance(ev, C.Message):
                self.event("DEBUG" if ev.debug else "INFO", ev.text, kind="message", source="gcode",
                           file=ev.file, line=ev.line)
            elif isinstance(ev, C.SpindleOn):
                self._spindle = (1 if ev.direction is C.SpindleDirection.CW else -1, ev.rpm)
            elif isinstance(ev, C.SpindleOff):
                self._spindle = (0, self._spindle[1])
            elif isinstance(ev, C.SpindleOrient):
                # the planner stopped motion for it and goes on at once: the orientation is done
                # here, before the next setpoint (no spindle drive is wired, as for tool changes)
                self._spindle = (0, self._spindle[1])
                how = "simulated machine" if self.simulated else "no spindle orientation configured"
                self.event("INFO", f"spindle orient to {ev.angle:g} deg (P{ev.direction}): done at once "
                           f"({how})",
                           kind="spindle_orient", source="motiond", file=ev.file, line=ev.line)
            elif isinstance(ev, C.SetSpindleSpeed):
                self._spindle = (self._spindle[0], ev.rpm)
            elif isinstance(ev, C.Coolant):
                self._coolant = (ev.mist, ev.flood)
            elif isinstance(ev, C.SelectTool):
                self._tool_prepared = ev.tool
            elif isinstance(ev, ModalState):
                self._modal = ev

    def _on_wait(self, w: Any) -> None:
        """Cycle thread: the planner stands at a sync point that waits for the machine."""
        p = self.planner
        if isinstance(w, C.ToolChange):
            how = "simulated machine" if self.simulated else "no tool changer configured"
            self.event("INFO", f"tool change to T{w.tool}: done at once ({how})",
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
            with contextlib.suppress(CommandRefused):
                self.states.pause()
            self.event("INFO", f"{what}: program paused; 'resume' continues", kind="program_stop",
                       source="gcode", file=w.file, line=w.line)
        else:  # M66, probe: the job thread is waiting for this
            with self._sync_cond:
                self._sync_reached = w
                self._sync_cond.notify_all()

    def _wait_sync_point(self, cmd: Any, job: _Job) -> None:
        """Job thread: block until the planner stands at ``cmd`` (or the job is cancelled)."""
        with self._sync_cond:
            while self._sync_reached is not cmd:
                if job.cancel.is_set():
                    raise _Aborted()
                self._sync_cond.wait(0.05)

    def _release_wait(self) -> None:
        if self.planner is not None and self.planner.waiting_for is not None:
            self.planner.release()

    def _at_rest(self) -> None:
        """Cycle thread, planner idle: finish an abort, a fault's stop, a job."""
        if self._stop_then_disable:
            self._stop_then_disable = False
            self.planner = None
            threading.Thread(target=self._disable_quietly, name="canon-disable", daemon=True).start()
            return
        if self._aborting:
            self._aborting = False
            if self.states.state in (State.RUNNING, State.PAUSED):
                self.states.abort()
            return
        job = self._job
        if job is not None and job.input_done and self._cmdq.empty():
            self._finish_job()
            if self.states.state in (State.RUNNING, State.PAUSED):
                self.states.finished()
        if self._jogging:
            self._jogging = False

    def _finish_job(self) -> None:
        job = self._job
        if job is None:
            return
        self._job = None
        self._last_job = job
        ok = not job.error and not job.aborted
        res = JobResult(
            program=job.program, ok=ok, error=job.error, aborted=job.aborted,
            duration_s=time.monotonic() - job.t0, cycles=self.cycle - job.cycle0,
            cycle_s=(self.cycle - job.cycle0) * self.T, late_cycles=self.late_cycles - job.late0,
            peaks={name: job.peaks[i] for i, name in enumerate(self.names)}, outputs=job.outputs,
            final_commanded=tuple(self._commanded), final_actual=tuple(self._actual),
            expected_final=tuple(self.interp.position[i] for i in self.limits.pose_index),
            first_cycle=job.cycle0, moving_cycles=job.moving_cycles,
            first_setpoint_s=job.t_first - job.t0 if job.t_first else 0.0,
            last_setpoint_s=job.t_last - job.t0 if job.t_last else 0.0,
            late_s=[by for c, by in self.late_log if c >= job.cycle0])
        job.result = res
        job.done.set()
        if ok:
            self.event("INFO", f"{job.mode.value} {job.program} done in {res.duration_s:.2f} s",
                       kind="program_end", source="motiond",
                       file=job.program if job.mode is Mode.AUTO else "")
        elif job.aborted:
            self.event("WARNING", f"{job.program} aborted", kind="program_abort", source="motiond")

    def _machine_pose(self, base: C.Pose | None = None) -> C.Pose:
        """Where the machine stands, as a full pose (axes the machine lacks: ``base``'s, by default the
        interpreter's)."""
        def where() -> tuple[float, ...]:
            if self.planner is not None:
                return self.planner.position
            return self.master.positions() if self.master is not None else self._commanded

        pos = self._on_cycle(where)
        pose = list(self.interp.position if base is None else base)
        for i, k in enumerate(self.limits.pose_index):
            pose[k] = pos[i]
        return C.Pose(*pose)

    def _new_planner_unless_interrupted(self, since: int) -> None:
        """Cycle thread: :meth:`_new_planner`, unless an E-stop came since ``since`` (it dropped the
        planner; one made now would outlive it). Deciding on the cycle thread orders this against the
        E-stop's own drop of the planner, which it posts after counting the interruption."""
        if self._interrupts == since:
            self._new_planner()

    def _new_planner(self) -> None:
        """Cycle thread: a planner at rest where the drives hold, primed with the interpreter's modes."""
        from planner.core import Planner

        start = self.master.positions()
        p = Planner(self.limits, start=start)
        interp = self.interp
        p.feed(C.SetFeedMode(interp.feed_mode))
        p.feed(C.SetFeedRate(interp.feed))
        mode, tol, cam = interp.control
        p.feed(C.SetMotionControlMode(mode, tol, cam))
        if interp.speed:
            p.feed(C.SetSpindleSpeed(interp.speed))
        self.planner = p
        self._wait_seen = None
        self._commanded = tuple(start)

    # ------------------------------------------------------------------ status
    def _status_loop(self) -> None:
        period = 1.0 / self.telemetry.status_hz
        deadline = time.monotonic()
        while not self._status_stop.is_set():
            try:
                snap = self.status()
                self.status_pub.update(snap)
                self.status_pub.publish_now()
            except Exception:
                log.exception("building the status")
            deadline += period
            late = time.monotonic() - deadline
            if late > 0:
                deadline += (int(late / period) + 1) * period
            self._status_stop.wait(max(0.0, deadline - time.monotonic()))

    def status(self) -> Any:
        """A ``canon.status`` snapshot of the machine now (any thread)."""
        from telemetry.lcmtypes.canon import drive_status, status

        s = status()
        self.status_seq += 1
        s.utime = time.time_ns() // 1000
        s.seq = self.status_seq
        s.machine = self.limits.name
        snap = self.states.snapshot()
        state = {State.ESTOP: "estop", State.IDLE: "idle", State.RUNNING: "running", State.PAUSED: "paused",
                 State.FAULTED: "fault"}[snap.state]
        if state == "idle" and self._homing:
            state = "homing"
        elif state == "idle" and self._jogging:
            state = "jogging"
        s.state = state
        s.mode = snap.mode.value
        s.estop = snap.state is State.ESTOP
        s.enabled = snap.enabled
        job = self._job
        line = self._line[0]
        s.program = job.program if job is not None and job.mode is Mode.AUTO else ""
        s.line = int(line) if job is not None else 0
        s.block = ""
        if job is not None and line:
            if job.mode is Mode.MDI:
                s.block = job.program
            else:
                s.block = linecache.getline(job.program, int(line)).strip()[:200]
        s.single_block = self.single_block
        s.optional_stop = self.optional_stop
        s.block_delete = bool(self.interp.settings.block_delete)
        s.num_axes = self.n
        s.axis_names = list(self.names)
        s.homed = list(self.homed)
        cmd = self._commanded
        act = self._actual
        self.status_data_t[s.seq] = self._actual_t
        if len(self.status_data_t) > 2000:
            self.status_data_t.popitem(last=False)
        s.commanded = [float(v) for v in cmd]
        s.actual = [float(v) for v in act]
        s.velocity = [float(v) for v in self._velocity]
        s.following_error = [float(v) for v in self._fe]
        lin = [self._velocity[i] for i, a in enumerate(self.limits.axes) if not a.rotary]
        s.path_velocity = math.sqrt(sum(v * v for v in lin))
        modal = self._modal if job is not None else None
        if modal is None:  # no job: the interpreter's state is the machine's
            modal = self._modal_state("", 0)
        s.feed_rate = modal.feed
        p = self.planner
        s.feed_override = float(p.feed_override) if p is not None else 1.0
        s.rapid_override = 1.0
        s.spindle_override = 1.0
        drives = []
        master = self.master
        if master is not None:
            now = time.monotonic()
            nmt_names = {0: "INITIALISING", 4: "STOPPED", 5: "OPERATIONAL", 127: "PRE-OPERATIONAL"}
            hb_limit = self.canopen.heartbeat_consumer_ms / 1000.0
            fault = master.fault
            for d, st in zip(master.drives, master.state, strict=False):
                ds = drive_status()
                ds.axis = st.axis
                ds.node_id = st.node
                ds.nmt_state = nmt_names.get(d.nmt_state, "")
                ds.heartbeat_ok = (not self.canopen.heartbeat_producer_ms) or now - d.heartbeat_at <= hb_limit
                ds.statusword = int(st.statusword) & 0xFFFF
                ds.cia402_state = st.state.name.lower()
                ds.mode_display = 8 if d.nmt_state == 5 else 0
                ds.position_actual = int(st.actual_counts)
                ds.following_error = int(d.following_error)
                active = getattr(d.node.emcy, "active", [])
                ds.emcy_code = int(active[-1].code) if active else 0
                ds.error = str(fault.reason) if fault is not None and fault.node == st.node else ""
                drives.append(ds)
        s.num_drives = len(drives)
        s.drives = drives
        g, m = list(modal.gcodes), list(modal.mcodes)
        s.num_gcodes, s.gcodes = len(g), g
        s.num_mcodes, s.mcodes = len(m), m
        s.tool = modal.tool
        s.tool_prepared = int(self._tool_prepared)
        s.tool_length_offset = modal.tool_length_offset
        s.spindle_direction, s.spindle_speed = self._spindle[0], float(self._spindle[1])
        s.mist, s.flood = self._coolant
        if self.io is not None:
            io = self.io.state()
            di, do, ai, ao = io.arrays()
            s.io_ok = io.io_ok
        else:
            di, do, ai, ao = [], [], [], []
            s.io_ok = self.modbus is None
        s.num_digital_inputs, s.digital_inputs = len(di), [bool(v) for v in di]
        s.num_digital_outputs, s.digital_outputs = len(do), [bool(v) for v in do]
        s.num_analog_inputs, s.analog_inputs = len(ai), [float(v) for v in ai]
        s.num_analog_outputs, s.analog_outputs = len(ao), [float(v) for v in ao]
        s.last_error = self.last_error
        s.last_error_utime = self.last_error_utime
        s.events_dropped = self.events.dropped
        return s

    # ------------------------------------------------------------------ commands
    def estop(self) -> None:
        """Always accepted: quick stop on every drive now, the job cancelled, ESTOP. A slow operation
        running meanwhile (homing, enabling ...) fails (:meth:`_operation`)."""
        self._interrupt("E-stop")
        self.states.estop()
        self._quick_stop("E-stop")

        def on_cycle() -> None:
            self._cancel_job("E-stop", aborted=True)
            self.planner = None
            self._aborting = self._stop_then_disable = False

        self._on_cycle(on_cycle)
        self.event("WARNING", "E-stop", kind="estop", source="motiond")

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
        self._on_cycle(lambda: setattr(self, "planner", None))
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
            self._hold_stream = False
            self._on_cycle(lambda: self._new_planner_unless_interrupted(since))
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
            while self.planner is not None and self._stop_then_disable and time.monotonic() < deadline:
                time.sleep(0.01)  # the fault's stop on the path is still running
            self._reset_drives()
            with self._fault_lock:
                self._pending_fault = None
            self.states.reset()
            self.last_error = ""
            self.event("INFO", "fault reset", kind="reset", source="motiond")

    def _start_job(self, mode: Mode, program: str, source: Callable[[], Any], lines_total: int = 0,
                   start_line: int = 0) -> _Job:
        # bounded: the command thread must not wait behind a slow operation called from elsewhere
        if not self._ops.acquire(timeout=1.0):
            raise CommandRefused(f"busy: {self.busy() or 'another operation'}")
        with contextlib.ExitStack() as held:
            held.callback(self._ops.release)
            if self.states.state is not State.IDLE:
                self.states.start(mode)  # raises the refusal that names the state
            if self._job is not None or self._aborting or self._stop_then_disable:
                raise CommandRefused("busy: the previous program is still stopping")
            if self.planner is None and self.states.snapshot().enabled:
                self._on_cycle(self._new_planner)
            self.states.start(mode)  # raises the refusal
            job = _Job(program, mode, self.n)
            job.lines_total = lines_total
            if start_line > 1:
                job.run_from = _RunFrom(start_line, int(self.interp.current_tool))
            self._modal = self._modal_state("", 0)  # until the motion reaches the job's first line
            job.cycle0 = self.cycle
            job.late0 = self.late_cycles
            self._wait_seen = None
            self._sync_reached = None
            self._stopped_at = None
            self._job = job
            job.thread = threading.Thread(target=self._job_main, args=(job, source), name="canon-interp",
                                          daemon=True)
            job.thread.start()
            self.event("INFO", f"{mode.value} {program} started", kind="program_start", source="motiond",
                       file=program if mode is Mode.AUTO else "")
            return job

    def run(self, path: str | os.PathLike[str], start_line: int = 0) -> _Job:
        """Start a program file (IDLE, enabled). Returns the job (``job.done``, ``job.result``).

        ``start_line`` above 1: run from that line. The lines before it are interpreted as in a full
        run (modal state, parameters, offsets, tool, o-word flow) with their commands withheld, then
        the machine restores what they left active and approaches the start point in a safe order
        (:meth:`_start_from`); refusals end the job with the reason, nothing moved (docs/daemon.md).
        A start line beyond the end of the file is refused here, before anything starts.
        """
        if start_line < 0:
            raise CommandRefused(f"start line must be 1 or more, got {start_line}")
        p = Path(path)
        if not p.is_file():
            raise CommandRefused(f"{path}: no such file")
        try:
            with p.open("rb") as fh:
                total = sum(1 for _ in fh)
        except OSError as exc:
            raise CommandRefused(f"{path}: cannot read: {exc.strerror}") from None
        if start_line > total:
            raise CommandRefused(f"{path}:{start_line}: cannot start at line {start_line}: the program has "
                                 f"only {total} lines")
        linecache.checkcache(str(path))  # the file may have changed since it last ran
        return self._start_job(Mode.AUTO, str(path), lambda: self.interp.run_file(p), total, start_line)

    def mdi(self, line: str) -> _Job:
        limit = self.interp.settings.max_line_length
        if len(line) > limit:  # refused at once, as the interpreter would refuse it
            raise CommandRefused(f"<mdi>:1: Line too long (more than {limit} characters)")
        return self._start_job(Mode.MDI, line, lambda: iter(self.interp.execute_mdi(line)))

    def _modal_state(self, file: str, line: int) -> ModalState:
        """The interpreter's modal state now, for the status (job thread, or before it starts)."""
        from motiond.status_view import status_gcodes  # the codes as the dialect shows them

        interp = self.interp
        return ModalState(status_gcodes(interp.active_gcodes(), interp.dialect),
                          tuple(interp.active_mcodes()), float(interp.feed), int(interp.current_tool),
                          float(interp.parameter(5403)), file=file, line=line)

    def _job_main(self, job: _Job, source: Callable[[], Any]) -> None:
        interp = self.interp
        run_from = job.run_from
        hook: Callable[[], None] | None = None
        if run_from is not None:
            def before_line() -> None:
                self._before_line(job, run_from)
            hook = interp.before_line = before_line
        last_line = 0
        place: tuple[str, int] = ("", -1)
        key: object = None
        try:
            for cmd in source():
                if run_from is not None and not run_from.started:
                    if job.cancel.is_set():
                        return
                    if not run_from.reached:
                        run_from.note(cmd)
                        continue
                    if not self._start_from(job, run_from):
                        return
                    assert run_from.state is not None
                    key = run_from.state.key
                if (self.single_block and job.mode is Mode.AUTO and last_line and cmd.line != last_line
                        and not self._single_block_stop(job, last_line)):
                    return
                last_line = cmd.line
                if cmd.line != place[1] or cmd.file != place[0]:
                    # a new line: its modal state travels with it to the status (ModalState); the cheap
                    # key is compared on every line, the codes built only when it changed
                    place = (cmd.file, cmd.line)
                    k = interp.modal_key()
                    if k != key:
                        key = k
                        if not self._put(self._modal_state(cmd.file, cmd.line), job):
                            return
                if not self._put(cmd, job):
                    return
            if run_from is not None and not run_from.started:
                if not run_from.reached:
                    raise GCodeError(self._never_reached(job, run_from), job.program, run_from.line)
                if not self._start_from(job, run_from):
                    return
            self._report_unsaved()
            self._put(_END, job)
        except _Aborted:
            return
        except GCodeError as exc:
            if not job.cancel.is_set():
                if job.skipping:  # nothing was sent to the machine: a refusal, not a fault
                    self._refuse_start(job, exc)
                else:
                    self._post_fault(str(exc), "gcode")
        except Exception as exc:  # never silently: an interpreter bug faults the machine
            log.exception("interpreter thread")
            if not job.cancel.is_set():
                self._post_fault(f"internal error in the interpreter: {exc!r}", "gcode")
        finally:
            if hook is not None and interp.before_line is hook:
                interp.before_line = None

    def _report_unsaved(self) -> None:
        """Job thread, at the program's end: an ERROR event when its parameter save failed (M2)."""
        exc = self.interp.save_error
        if exc is not None and exc is not self._save_reported:  # each failed save once
            self._save_reported = exc
            self.event("ERROR", f"parameters not saved: {exc.message}; the values are kept in memory and "
                       "saved at the next program end or at shutdown", kind="save_failed", file=exc.file)

    # ------------------------------------------------------------------ run from line
    def _before_line(self, job: _Job, run_from: _RunFrom) -> None:
        """Job thread, the interpreter's ``before_line`` hook: is it about to execute the start line?

        Only the main program's own line counts, reached by the program's flow. Inside a subroutine
        (LinuxCNC refuses that too) or a loop body (which pass would be meant?), or with cutter
        compensation on (its path depends on the moves before), the start is refused naming the place.
        Otherwise the state the skipped part left is captured here, before the start line's own words
        change it, and the hook removes itself (no cost on the remaining lines).
        """
        interp = self.interp
        if run_from.main is None:
            run_from.main = interp.source  # the first line read is the main program's
        if interp.line != run_from.line or interp.source is not run_from.main:
            return
        n = run_from.line
        flow = interp.flow
        if flow.frames:
            inner, outer = flow.frames[-1], flow.frames[0]
            raise GCodeError(f"cannot start at line {n}: it is inside subroutine {inner.label} (sub at line "
                             f"{inner.sub_line}), here called from {outer.caller_file}:{outer.call_line}; "
                             "start at or before the call, or after it", interp.file, n)
        loops = [b for b in flow.blocks if b.kind in ("while", "do", "repeat")]
        if loops:
            b = loops[0]
            raise GCodeError(f"cannot start at line {n}: it is inside the body of loop {b.label} {b.kind} "
                             f"(line {b.line}), and which pass is meant is not defined; start at line "
                             f"{b.line} or after the loop", interp.file, n)
        if interp.active_gcodes(extensions=False)[6] != "G40":
            raise GCodeError(f"cannot start at line {n}: cutter radius compensation "
                             f"({interp.active_gcodes(extensions=False)[6]}) is on there, and its path "
                             "depends on the moves before; start before its G41/G42 or after its G40",
                             interp.file, n)
        run_from.state = _StartState(
            target=interp.position, tool=int(interp.current_tool), selected=int(interp.selected_tool),
            spindle=(1 if interp.parameter("_spindle_cw") else -1) if interp.parameter("_spindle_on") else 0,
            speed=float(interp.speed), mist=bool(interp.parameter("_mist")),
            flood=bool(interp.parameter("_flood")),
            overrides={"feed": bool(interp.parameter("_feed_override")),
                       "spindle": bool(interp.parameter("_speed_override")),
                       "adaptive_feed": bool(interp.parameter("_adaptive_feed")),
                       "feed_hold": bool(interp.parameter("_feed_hold"))},
            feed_mode=interp.feed_mode, feed=float(interp.feed), control=interp.control,
            modal=self._modal_state(interp.file, n), key=interp.modal_key())
        run_from.reached = True
        interp.before_line = None

    def _never_reached(self, job: _Job, run_from: _RunFrom) -> str:
        """Why the program's flow never executed the start line, in words (the error's message)."""
        from gcode_canon.owords import o_head

        n = run_from.line
        open_sub: tuple[str, int] | None = None
        with contextlib.suppress(OSError), open(job.program, encoding="utf-8-sig",
                                               errors="surrogateescape") as fh:
            for k, raw in enumerate(fh, 1):
                head = o_head(raw)
                if head is not None and head[1] == "sub" and open_sub is None:
                    open_sub = (head[0], k)
                elif head is not None and head[1] == "endsub" and open_sub and head[0] == open_sub[0]:
                    if open_sub[1] < n < k:
                        return (f"cannot start at line {n}: it is inside the definition of subroutine "
                                f"{open_sub[0]} (lines {open_sub[1]}-{k}), and the program never ran it "
                                "(and a start inside a subroutine is refused anyway); start at or before "
                                "a call, or outside the subroutine")
                    open_sub = None
                if k >= n and open_sub is None:
                    break
        if run_from.end_line and run_from.end_line < n:
            return (f"cannot start at line {n}: the program ends at line {run_from.end_line} (M2/M30) "
                    "before its flow reaches it")
        return (f"cannot start at line {n}: the program's flow never executes it (a branch not taken, a "
                "loop that does not run, or after the end of the program); nothing was moved")

    def _refuse_start(self, job: _Job, exc: GCodeError) -> None:
        """Job thread: a run from line refused, or a G-code error, before anything was queued. Nothing
        was sent to the drives, so there is nothing to stop and no fault: the job ends with the reason
        (``last_error``, an ERROR event), the machine back to IDLE with the drives still enabled."""
        reason = str(exc)

        def on_cycle() -> None:
            if self._job is not job:
                return
            job.error = job.error or reason
            self.last_error = reason
            self.last_error_utime = time.time_ns() // 1000
            self._finish_job()
            if self.states.state in (State.RUNNING, State.PAUSED):
                self.states.finished()
            self.event("ERROR", reason, kind="run_from_line", source="gcode", file=exc.file, line=exc.line)

        self._on_cycle(on_cycle, wait=False)

    def _start_from(self, job: _Job, run_from: _RunFrom) -> bool:
        """Job thread, run from line: queue what restores the skipped part's state, then the approach.

        In this order, each at rest (G61.1 for the approach, the operator's feed override and feed hold
        on for it):

        1. feed mode and rate (state only);
        2. the tool: a tool change (M6, an event and a sync point as any) to the tool the skipped part
           left in the spindle, when it differs from the one there at the start (M61 when the skipped
           part declared it with M61); then the prepared tool (T);
        3. Z up, alone, to the higher of where it stands and the start point's Z;
        4. spindle speed, spindle on (M3/M4) or off (M5), coolant (mist, flood);
        5. the other axes (X Y and any rotary) to the start point, at that Z;
        6. Z down to the start point;
        7. the skipped part's path control mode (G61/G64 P) and override switches (M48-M53).

        Machine coordinates; Z is the tool axis whatever G17/G18/G19 selects (those choose the arc
        plane, not the spindle's direction; the tool length offset is along Z too), and up is +Z. A
        machine without a Z axis moves all axes together. Outputs (M62-M65, M67, M68), dwells, stops
        and messages of the skipped part are not replayed: a WARNING lists the outputs.
        False when the job was cancelled meanwhile.
        """
        run_from.started = True
        st = run_from.state
        assert st is not None
        f, n = job.program, run_from.line
        seq: list[C.Canon] = [st.modal, C.SetFeedMode(st.feed_mode, file=f, line=n),
                              C.SetFeedRate(st.feed, file=f, line=n),
                              C.SetMotionControlMode(C.MotionControlMode.EXACT_STOP_MODAL, file=f, line=n),
                              C.SetOverrides(feed=True, spindle=True, adaptive_feed=False, feed_hold=True,
                                             file=f, line=n)]
        did: list[str] = []
        if st.tool != run_from.tool0:
            if isinstance(run_from.tool_cmd, C.SetToolNumber):
                seq.append(C.SetToolNumber(st.tool, file=f, line=n))
                did.append(f"M61 Q{st.tool}")
            else:
                seq += [C.SelectTool(st.tool, file=f, line=n), C.ToolChange(st.tool, file=f, line=n)]
                did.append(f"T{st.tool} M6")
        if st.selected >= 0 and st.selected != st.tool:
            seq.append(C.SelectTool(st.selected, file=f, line=n))
            did.append(f"T{st.selected}")
        target = st.target
        current = self._machine_pose(target)
        zi = self.names.index("z") if "z" in self.names else None
        if zi is None:
            moves = [target]
        else:
            k = self.limits.pose_index[zi]
            z_safe = max(current[k], target[k])
            moves = [current._replace(**{C.AXES[k]: z_safe}), target._replace(**{C.AXES[k]: z_safe}), target]
        restore: list[C.Canon] = [C.SetSpindleSpeed(st.speed, file=f, line=n)]
        if st.spindle:
            restore.append(C.SpindleOn(C.SpindleDirection.CW if st.spindle > 0 else C.SpindleDirection.CCW,
                                       st.speed, file=f, line=n))
            did.append(f"{'M3' if st.spindle > 0 else 'M4'} S{st.speed:g}")
        else:
            restore.append(C.SpindleOff(file=f, line=n))
            did.append("M5")
        restore.append(C.Coolant(st.mist, st.flood, file=f, line=n))
        did.append(" ".join(c for c, on in (("M7", st.mist), ("M8", st.flood)) if on) or "M9")
        where = current
        for i, pose in enumerate(moves):
            if i == 1 or len(moves) == 1:
                seq += restore
            if any(abs(a - b) > 1e-9 for a, b in zip(pose, where, strict=True)):
                seq.append(C.StraightTraverse(pose, file=f, line=n))
                where = pose
        seq += [C.SetMotionControlMode(*st.control, file=f, line=n),
                C.SetOverrides(**st.overrides, file=f, line=n)]
        ovr = st.overrides
        did.append("M48" if ovr["feed"] and ovr["spindle"] else "M49")
        axes = " ".join(f"{a.upper()}{target[k]:.4f}" for a, k in zip(self.names, self.limits.pose_index,
                                                                      strict=True))
        self.event("INFO", f"run from line {n}: {run_from.skipped} commands of the lines before it not "
                           f"sent (nothing moved); restoring {', '.join(did)}; approach to {axes} "
                           "(Z up first, then the other axes, then Z down)",
                   kind="run_from_line", source="motiond", file=f, line=n)
        if run_from.outputs:
            words = [f"{'D' if isinstance(o, C.DigitalOutput) else 'A'}{o.index}="
                     f"{(int(o.on) if isinstance(o, C.DigitalOutput) else o.value):g} (line {o.line})"
                     for o in run_from.outputs[:10]]
            more = f" and {len(run_from.outputs) - 10} more" if len(run_from.outputs) > 10 else ""
            self.event("WARNING", f"run from line {n}: outputs switched before it are not replayed: "
                                  f"{', '.join(words)}{more}",
                       kind="run_from_line", source="motiond", file=f, line=n)
        return all(self._put(cmd, job) for cmd in seq)

    def _single_block_stop(self, job: _Job, line: int) -> bool:
        """Job thread, single block on: let the machine finish the block (``line``), pause, and wait for
        ``resume``. False when the job was cancelled meanwhile."""
        def idle() -> bool:
            p = self.planner
            return p is None or (p.is_idle and p.queue_length == 0)

        while not job.cancel.is_set():
            if self._cmdq.empty() and self._on_cycle(idle):
                break
            time.sleep(self.T)
        else:
            return False
        with contextlib.suppress(CommandRefused):
            self.states.pause()
        self.event("INFO", f"single block: stopped after line {line}; 'resume' runs the next block",
                   kind="single_block", source="motiond", file=job.program, line=line)
        while self.states.state is State.PAUSED and not job.cancel.is_set():
            time.sleep(0.01)
        return not job.cancel.is_set() and self.states.state is State.RUNNING

    def _put(self, item: Any, job: _Job) -> bool:
        while not job.cancel.is_set():
            try:
                self._cmdq.put(item, timeout=0.05)
                job.queued += 1
                return True
            except queue.Full:
                continue
        return False

    def pause(self) -> None:
        self.states.pause()
        self._on_cycle(lambda: self.planner.hold() if self.planner is not None else None)

    def resume(self) -> None:
        self.states.resume()

        def on_cycle() -> None:
            p = self.planner
            if p is None:
                return
            if self._stopped_at is not None and p.waiting_for is self._stopped_at:
                p.release()
            self._stopped_at = None
            p.resume()

        self._on_cycle(on_cycle)

    def abort(self) -> None:
        """Stop the program on the path (module docstring); a homing stops before its next axis."""
        snap = self.states.snapshot()
        if snap.state not in (State.RUNNING, State.PAUSED, State.IDLE):
            self.states.abort()  # raises
        self._aborts += 1

        def on_cycle() -> None:
            self._cancel_job("aborted by the operator", aborted=True)
            if self.planner is not None:
                self.planner.abort()
                self._aborting = True
            elif self.states.state in (State.RUNNING, State.PAUSED):
                self.states.abort()

        self._on_cycle(on_cycle)

    def feed_override(self, factor: float) -> None:
        if not (math.isfinite(factor) and 0.0 <= factor <= 2.0):
            raise CommandRefused(f"feed override must be between 0 and 2 (0 to 200 %), got {factor:g}")
        self._on_cycle(lambda: self.planner.set_feed_override(factor) if self.planner is not None else None)

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
            if self.planner is not None and not self.planner.is_idle:
                raise CommandRefused("cannot home while the axes move")
            aborts = self._aborts
            self._hold_stream = True
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
                    self.homed[self.names.index(a)] = True
                    self.event("INFO", f"axis {a} homed", kind="homed", source="canopen")
            except CanopenError as exc:
                raise CommandRefused(f"homing failed: {exc}") from None
            finally:
                self._homing = ""
                self._on_cycle(lambda: self._new_planner_unless_interrupted(since))
                self._hold_stream = False

    def jog(self, axis: str, velocity: float, distance: float = 0.0) -> None:
        a = axis.lower()
        if a not in self.names:
            raise CommandRefused(f"no axis {a!r} (axes: {' '.join(self.names)})")
        i = self.names.index(a)
        lim = self.limits.axes[i]
        if velocity == 0.0:
            self._on_cycle(lambda: self.planner.abort() if self.planner is not None and self._jogging
                           else None)
            return
        if abs(velocity) > lim.max_velocity:
            raise CommandRefused(f"jog velocity {abs(velocity):g} beyond axis {a}'s max_velocity "
                                 f"{lim.max_velocity:g}")
        self.states.manual("jog")

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
            pose = list(self.interp.position)
            for j, k in enumerate(self.limits.pose_index):
                pose[k] = pos[j]
            pose[self.limits.pose_index[i]] = target
            p.feed(C.SetFeedRate(abs(velocity) * 60.0))  # a one-axis move runs at the feed
            p.feed(C.StraightFeed(C.Pose(*pose), file="<jog>"))
            p.feed(C.SetFeedRate(self.interp.feed))
            p.flush()
            self._jogging = True

        self._on_cycle(on_cycle)

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

    def wait_job(self, job: _Job, timeout: float | None = None) -> JobResult | None:
        if not job.done.wait(timeout):
            return None
        return job.result

    @property
    def job(self) -> _Job | None:
        return self._job

    def stop_on_path(self, timeout: float) -> bool:
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
            if (self._job is None and not self._aborting
                    and self.states.state not in (State.RUNNING, State.PAUSED)):
                return True
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.01)

    @property
    def motion_place(self) -> tuple[str, int]:
        """The file and line of the last setpoint sent to the drives (line 0 before any motion)."""
        line, file = self._line
        return file, line
