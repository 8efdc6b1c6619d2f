"""Task side: a program (or MDI line) as a job: the interpreter on its job thread, feeding the motion.

:class:`JobsMixin` is the part of :class:`motiond.runtime.machine.Machine` that starts a job, runs
the :class:`~gcode_canon.interpreter.Interpreter` on a ``canon-interp`` thread that interprets ahead
into the motion side's bounded command queue (:meth:`motiond.runtime.motion.MotionCore.put`), answers
the interpreter's machine callbacks (:class:`Callbacks`: M66 and probes wait for their sync point),
stops after each block in single block, and turns the motion side's accounting of the job
(:class:`~motiond.runtime.records.Stream`) into a :class:`~motiond.runtime.records.JobResult` when it
ends. Run from line (the lines before the start withheld) is :mod:`motiond.runtime.run_from_line`.

What crosses to the motion side: canonical commands (and a :class:`ModalState` in front of each line
whose modal state changed) through the queue, the end marker, and the stream's begin and end.
"""

from __future__ import annotations

import contextlib
import linecache
import logging
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from gcode_canon import commands as C
from gcode_canon.errors import GCodeError
from motiond.runtime.motion import END
from motiond.runtime.parts import MachinePart
from motiond.runtime.records import JobResult, ModalState, Stream
from motiond.states import CommandRefused, Mode, State

if TYPE_CHECKING:
    from motiond.runtime.machine import Machine
    from motiond.runtime.run_from_line import RunFrom

log = logging.getLogger(__name__)


class Job:
    """One program or MDI line: its thread, its cancel flag, and (``stream``) what its motion did."""

    def __init__(self, program: str, mode: Mode, n_axes: int) -> None:
        self.program = program
        self.mode = mode
        self.cancel = threading.Event()
        self.done = threading.Event()
        self.thread: threading.Thread | None = None
        self.error = ""
        self.aborted = False
        self.t0 = time.monotonic()
        self.cycle0 = 0
        self.late0 = 0
        self.queued = 0
        self.stream = Stream(n_axes)
        self.stream.answered_ahead = mode is not Mode.AUTO
        self.result: JobResult | None = None
        self.lines_total = 0
        self.run_from: RunFrom | None = None

    @property
    def line(self) -> int:
        """The line of the last setpoint sent to the drives."""
        return self.stream.line

    @property
    def skipping(self) -> bool:
        """Run from line, before the start: commands are withheld and nothing may wait for motion."""
        return self.run_from is not None and not self.run_from.started


class Aborted(Exception):
    """The job was cancelled while the interpreter waited in a machine callback."""


class Callbacks:
    """The interpreter's machine callbacks (``gcode_canon.machine.MachineCallbacks``).

    They run on the job thread. The interpreter asks them right after yielding the sync command, long
    before the cycle thread has run the motion before it; so M66 and probes wait here until the
    planner stands at that sync point, then answer, then let the planner go on (``release_wait``).
    """

    def __init__(self, machine: Machine) -> None:
        self.m = machine
        self._probed = False  # a drive's touch probe stopped the last probing move

    def _job(self) -> Job:
        job = self.m._job
        if job is None:
            raise Aborted()
        return job

    def wait_input(self, cmd: C.WaitInput) -> float:
        job = self._job()
        io = self.m.io
        if io is None:
            raise GCodeError("M66: this machine has no Modbus I/O configured ([modbus])", cmd.file, cmd.line)
        # before the start line of a run from line nothing moves: the input is read (waited for) now
        synced = job.mode is Mode.AUTO and not job.skipping
        if synced and not self.m.motion.wait_sync_point(cmd, job.cancel):
            raise Aborted()
        from fieldbus.modbus.faults import IoError, WaitAborted

        try:
            value = io.wait_input(cmd, cancel=job.cancel)
        except WaitAborted:
            raise Aborted() from None
        except IoError as exc:
            raise GCodeError(str(exc), cmd.file, cmd.line) from None
        if synced:
            self.m.motion.release_wait()
        return value

    def probe(self, cmd: C.Probe) -> tuple[C.Pose, bool]:
        job = self._job()
        if job.skipping:
            assert job.run_from is not None
            raise GCodeError(f"cannot start at line {job.run_from.line}: the probe at line {cmd.line} comes "
                             "before it, and its result (#5061-#5070) needs the probing move; start at or "
                             "before the probe", cmd.file, cmd.line)
        if self.m.motion.has_touch_probe:
            return self._touch_probe(cmd, job)
        if not self.m.simulated:
            raise GCodeError("probing (G38.x) needs a probe input, and this machine has none configured",
                             cmd.file, cmd.line)
        if job.mode is Mode.AUTO:
            if not self.m.motion.wait_sync_point(cmd, job.cancel):
                raise Aborted()
            self.m.motion.release_wait()
        self.m.event("INFO", "probe: simulated machine, contact at the end point of the move",
                     kind="probe", source="motiond", file=cmd.file, line=cmd.line)
        return cmd.end, True

    def _touch_probe(self, cmd: C.Probe, job: Job) -> tuple[C.Pose, bool]:
        """The probe is a drive's touch probe (docs/canopen.md; the probed point is its latch) or the I/O
        map's probe input (docs/wiring.md; the commanded position of the cycle that saw it)."""
        if job.mode is not Mode.AUTO:
            # an MDI line's probe callback runs before the line's commands are queued: the move
            # could not have run yet
            raise GCodeError(f"G{cmd.mode.value} in MDI: probing with the probe input needs the "
                             "move to run first; put the probing move in a program", cmd.file, cmd.line)
        probed = self.m.motion.probe(cmd, job.cancel)
        if probed is None:
            raise Aborted()
        pose = list(cmd.end)  # axes the machine lacks: as programmed
        for i, k in enumerate(self.m.limits.pose_index):
            pose[k] = probed.positions[i]
        if probed.tripped:
            self._probed = True  # the machine stopped past the point: the next move starts there
            what = (f"the probe input tripped at {', '.join(f'{v:.6g}' for v in probed.positions)}"
                    if probed.axis == "probe input" else  # motiond.runtime.probing_io
                    f"the touch probe of axis {probed.axis} latched at {probed.latched:.6g} "
                    f"({probed.counts} counts)")
            self.m.event("INFO", f"probe: {what}", kind="probe", source="motiond", file=cmd.file,
                         line=cmd.line)
        return C.Pose(*pose), probed.tripped

    def current_position(self) -> C.Pose | None:
        """At the start of a program or MDI line: where the machine is (it may have been jogged, homed
        or stopped by an abort since the interpreter last commanded it). Later (after M0, M6): None,
        the machine went exactly where the interpreter sent it; also after an M6 before the start line
        of a run from line (nothing moved: the interpreter's own position is the program's)."""
        job = self.m._job
        probed, self._probed = self._probed, False  # stopped past the trip point: go on from there
        if job is None or (job.queued and not probed) or (job.run_from is not None and job.run_from.skipped):
            return None
        return self.m._machine_pose()

    def print_text(self, text: str) -> None:
        self.m.event("INFO", text, kind="print", source="gcode")


class JobsMixin(MachinePart):
    """Jobs of :class:`~motiond.runtime.machine.Machine` (module docstring)."""

    if TYPE_CHECKING:  # provided by Machine
        single_block: bool
        _last_job: Job | None
        _ops: threading.RLock
        _save_reported: Exception | None
        def busy(self) -> str: ...
        def _before_line(self, job: Job, run_from: RunFrom) -> None: ...
        def _start_from(self, job: Job, run_from: RunFrom) -> bool: ...
        def _never_reached(self, job: Job, run_from: RunFrom) -> str: ...
        def _refuse_start(self, job: Job, exc: GCodeError, kind: str = ...) -> None: ...
        def _post_fault(self, reason: str, source: str) -> None: ...

    def run(self, path: str | os.PathLike[str], start_line: int = 0) -> Job:
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

    def mdi(self, line: str) -> Job:
        limit = self.interp.settings.max_line_length
        if len(line) > limit:  # refused at once, as the interpreter would refuse it
            raise CommandRefused(f"<mdi>:1: Line too long (more than {limit} characters)")
        return self._start_job(Mode.MDI, line, lambda: iter(self.interp.execute_mdi(line)))

    def wait_job(self, job: Job, timeout: float | None = None) -> JobResult | None:
        if not job.done.wait(timeout):
            return None
        return job.result

    @property
    def job(self) -> Job | None:
        return self._job

    def _start_job(self, mode: Mode, program: str, source: Callable[[], Any], lines_total: int = 0,
                   start_line: int = 0) -> Job:
        from motiond.runtime.run_from_line import RunFrom

        # bounded: the command thread must not wait behind a slow operation called from elsewhere
        if not self._ops.acquire(timeout=1.0):
            raise CommandRefused(f"busy: {self.busy() or 'another operation'}")
        motion = self.motion
        with contextlib.ExitStack() as held:
            held.callback(self._ops.release)
            if self.states.state is not State.IDLE:
                self.states.start(mode)  # raises the refusal that names the state
            if self._job is not None or motion.stopping:
                raise CommandRefused("busy: the previous program is still stopping")
            if not motion.has_planner and self.states.snapshot().enabled:
                motion.new_planner()
            self.states.start(mode)  # raises the refusal
            job = Job(program, mode, self.n)
            job.lines_total = lines_total
            if start_line > 1:
                job.run_from = RunFrom(start_line, int(self.interp.current_tool))
            job.cycle0 = motion.cycle
            job.late0 = motion.late_cycles
            # the modal state shown until the motion reaches the job's first line
            motion.begin_stream(job.stream, self._modal_state("", 0))
            self._job = job
            job.thread = threading.Thread(target=self._job_main, args=(job, source), name="canon-interp",
                                          daemon=True)
            job.thread.start()
            self.event("INFO", f"{mode.value} {program} started", kind="program_start", source="motiond",
                       file=program if mode is Mode.AUTO else "")
            return job

    def _modal_state(self, file: str, line: int) -> ModalState:
        """The interpreter's modal state now, for the status (job thread, or before it starts)."""
        from motiond.status_view import status_gcodes  # the codes as the dialect shows them

        interp = self.interp
        return ModalState(status_gcodes(interp.active_gcodes(), interp.dialect),
                          tuple(interp.active_mcodes()), float(interp.feed), int(interp.current_tool),
                          float(interp.parameter(5403)), file=file, line=line)

    def _planner_prime(self) -> list[C.Canon]:
        """Cycle thread (a new planner): the interpreter's feed mode, feed, path control and speed."""
        interp = self.interp
        mode, tol, cam = interp.control
        prime: list[C.Canon] = [C.SetFeedMode(interp.feed_mode), C.SetFeedRate(interp.feed),
                                C.SetMotionControlMode(mode, tol, cam)]
        if interp.speed:
            prime.append(C.SetSpindleSpeed(interp.speed))
        return prime

    def _machine_pose(self, base: C.Pose | None = None) -> C.Pose:
        """Where the machine stands, as a full pose (axes the machine lacks: ``base``'s, by default the
        interpreter's)."""
        pos = self.motion.position()
        pose = list(self.interp.position if base is None else base)
        for i, k in enumerate(self.limits.pose_index):
            pose[k] = pos[i]
        return C.Pose(*pose)

    def _job_main(self, job: Job, source: Callable[[], Any]) -> None:
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
            self._put(END, job)
        except Aborted:
            return
        except GCodeError as exc:
            if not job.cancel.is_set():
                if job.skipping:  # nothing was sent to the machine: a refusal, not a fault
                    self._refuse_start(job, exc)
                elif job.mode is Mode.MDI:  # an MDI line is interpreted whole before any of it is
                    self._refuse_start(job, exc, kind="gcode")  # queued: nothing moved, no fault
                else:
                    self._post_fault(str(exc), "gcode")
        except Exception as exc:  # never silently: an interpreter bug faults the machine
            log.exception("interpreter thread")
            if not job.cancel.is_set():
                self._post_fault(f"internal error in the interpreter: {exc!r}", "gcode")
        finally:
            if hook is not None and interp.before_line is hook:
                interp.before_line = None

    def _put(self, item: Any, job: Job) -> bool:
        if not self.motion.put(item, job.cancel):
            return False
        job.queued += 1
        return True

    def _report_unsaved(self) -> None:
        """Job thread, at the program's end: an ERROR event when its parameter save failed (M2)."""
        exc = self.interp.save_error
        if exc is not None and exc is not self._save_reported:  # each failed save once
            self._save_reported = exc
            self.event("ERROR", f"parameters not saved: {exc.message}; the values are kept in memory and "
                       "saved at the next program end or at shutdown", kind="save_failed", file=exc.file)

    def _single_block_stop(self, job: Job, line: int) -> bool:
        """Job thread, single block on: let the machine finish the block (``line``), pause, and wait for
        ``resume``. False when the job was cancelled meanwhile."""
        while not job.cancel.is_set():
            if self.motion.drained():
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

    def _cancel_job(self, error: str = "", aborted: bool = False,
                    then: Callable[[], None] | None = None) -> None:
        """Cycle thread (or inline): the job ends now, its queued commands dropped. ``then``: as for
        :meth:`_finish_job` (called also when there is no job)."""
        job = self._job
        if job is None:
            if then is not None:
                then()
            return
        job.cancel.set()
        if error and not job.error:
            job.error = error
        job.aborted = job.aborted or aborted
        self.motion.drop_commands()
        self.io_hooks.stopped(outputs_off=False)
        self._finish_job(then)

    def _finish_job(self, then: Callable[[], None] | None = None) -> None:
        """The job's result. ``then`` (the machine's state change that the job's end brings: IDLE,
        FAULTED) runs before the job is marked done, so that whoever waited for the job (``wait_job``,
        a client sending the next MDI line) finds the machine in its new state, not still RUNNING."""
        job = self._job
        if job is None:
            if then is not None:
                then()
            return
        motion = self.motion
        self._job = None
        motion.end_stream()
        self._last_job = job
        ok = not job.error and not job.aborted
        st = job.stream
        res = JobResult(
            program=job.program, ok=ok, error=job.error, aborted=job.aborted,
            duration_s=time.monotonic() - job.t0, cycles=motion.cycle - job.cycle0,
            cycle_s=(motion.cycle - job.cycle0) * self.T, late_cycles=motion.late_cycles - job.late0,
            peaks={name: st.peaks[i] for i, name in enumerate(self.names)}, outputs=st.outputs,
            final_commanded=tuple(motion.commanded), final_actual=tuple(motion.actual),
            expected_final=tuple(self.interp.position[i] for i in self.limits.pose_index),
            first_cycle=job.cycle0, moving_cycles=st.moving_cycles,
            first_setpoint_s=st.t_first - job.t0 if st.t_first else 0.0,
            last_setpoint_s=st.t_last - job.t0 if st.t_last else 0.0,
            late_s=[by for c, by in motion.late_log if c >= job.cycle0])
        job.result = res
        if then is not None:
            then()
        job.done.set()
        if ok:
            self.event("INFO", f"{job.mode.value} {job.program} done in {res.duration_s:.2f} s",
                       kind="program_end", source="motiond",
                       file=job.program if job.mode is Mode.AUTO else "")
        elif job.aborted:
            self.event("WARNING", f"{job.program} aborted", kind="program_abort", source="motiond")
