"""Where the machine's I/O map meets :class:`motiond.runtime.Machine`: the few calls the runtime makes
into :class:`motiond.machine_io.MachineIO`, and what it does with the actions that come back.

Kept apart from the runtime so that the runtime's part is a handful of one-line hooks (the motion
side calls them through its ``MotionHooks``: ``io_cycle``, ``io_event``, ``io_wait``,
``planner_waits``, ``orient_text``; all on the cycle thread):

* :meth:`IoHooks.cycle` (cycle thread, at the start of each cycle, before the planner is stepped):
  polls the functions and acts: an E-stop input (or an unreadable one) is :meth:`Machine.estop` now,
  so the quick stop goes out before this cycle's setpoint; a Modbus limit switch stops the machine as
  a drive's own limit switch does (CiA 402 quick stop on every drive at once, then FAULTED with the
  axis and switch named); a timed-out wait is a fault naming the line; the door and the operator
  buttons pause, resume and abort as the commands of the same names do;
* :meth:`IoHooks.on_event` (cycle thread, each event on the setpoint): spindle, coolant outputs;
* :meth:`IoHooks.on_wait` (cycle thread, the planner stands at a sync point): True when the I/O map
  completes it (M3/M4 with at-speed, M19 with oriented, a user M code);
* :meth:`IoHooks.refuse_estop_reset`, :meth:`IoHooks.refuse_resume`, :meth:`IoHooks.refuse_jog`: the
  input-side refusals (a jog while the door is open; a jog in progress stops when it opens);
* :meth:`IoHooks.stopped`: E-stop, fault or abort: the wait is gone; on E-stop and fault the spindle,
  coolant and machine enable are switched off.

With the motion in its own process (``[motion] process = "own"``) these run in the task process all
the same: :meth:`IoHooks.cycle` on the ``canon-io`` thread (:mod:`motiond.runtime.io_loop`) from the
motion process's states, :meth:`IoHooks.on_event` and :meth:`IoHooks.on_wait` on the ``canon-hooks``
thread as the motion process posts them; what they do to the motion goes down the urgent pipe.

The door (``door_open``) opened on a running program holds the motion (feed hold, as the command) and
stops the spindle and the coolant (their outputs off; a spindle drive to speed 0), as a machine
builder's door interlock does. Once it is closed, cycle start restores them as they were and the
motion resumes when the spindle is at speed again (the at-speed input or the measured speed; the
spindle drive's measured speed), at most ``at_speed_timeout_s`` (else a fault); with no at-speed signal
at once.
"""

from __future__ import annotations

import contextlib
import logging
import time
from typing import Any

from gcode_canon import commands as C
from motiond.config_io import IoMap
from motiond.machine_io import (
    ABORT,
    ESTOP,
    FAULT,
    JOG_STOP,
    LIMIT,
    PAUSE,
    RELEASE,
    RESUME,
    MachineIO,
    MachineState,
)
from motiond.states import CommandRefused, State

log = logging.getLogger(__name__)


class IoHooks:
    """The I/O map's run-time side for one :class:`~motiond.runtime.Machine` (module docstring)."""

    def __init__(self, machine: Any, io: IoMap) -> None:
        self.m = machine
        self.map = io
        self.empty = io.empty  # no map: the hooks cost nothing per cycle
        self.mio = MachineIO(io, None, tuple(machine.names), self._drive_out)
        self._door_held = False  # the door stopped the spindle and coolant (restored on cycle start)
        self._resume_at: float | None = None  # cycle start after the door: resume once at speed, by then
        self.stop_seen: tuple[str, float] | None = None
        """The last E-stop or limit switch acted on: its kind and when (monotonic), for the latency."""

    def start(self, executor: Any) -> None:
        """The Modbus executor is up: the functions on Modbus points can be read and written."""
        self.mio = MachineIO(self.map, executor, tuple(self.m.names), self._drive_out)

    def _drive_out(self, axis: int, bit: int, on: bool) -> Any:
        """A drive's 0x60FE bit, written by the CANopen master (the motion side's)."""
        return self.m.motion.drive_output(axis, bit, on)

    @property
    def wait_types(self) -> tuple[type[C.Canon], ...]:
        return self.mio.wait_types

    # --- cycle thread -------------------------------------------------------------------------------

    def cycle(self, drive_inputs: tuple[int, ...], velocity: tuple[float, ...]) -> None:
        """Poll the functions and act on what they ask (module docstring). ``drive_inputs``: 0x60FD
        per axis from the last feedback; ``velocity``: the commanded one per axis."""
        if self.empty:
            return
        snap = self.m.states.snapshot()
        st = MachineState(
            estop=snap.state is State.ESTOP,
            enabled=snap.enabled and snap.state in (State.IDLE, State.RUNNING, State.PAUSED),
            running=snap.state is State.RUNNING, paused=snap.state is State.PAUSED,
            velocity=velocity, drive_inputs=drive_inputs,
            jogging=bool(getattr(self.m.motion, "jogging", False)))
        for act in self.mio.poll(st):
            self._act(act)
        if self._resume_at is not None:
            self._resume_when_at_speed()

    def _resume_when_at_speed(self) -> None:
        m = self.m
        ready = self.mio.spindle_ready()
        if ready is not False and m.motion.spindle_at_speed():
            self._resume_at = None
            try:
                m.resume()
            except CommandRefused as exc:
                m.event("WARNING", f"cycle start: {exc}", kind="io_refused", source="modbus")
        elif time.monotonic() > self._resume_at:
            self._resume_at = None
            m._post_fault(f"cycle start after the door: the spindle not at speed again within "
                          f"{self.map.spindle.at_speed_timeout_s:g} s ([io.spindle] at_speed_timeout_s)",
                          "modbus")

    def _act(self, act: Any) -> None:
        m = self.m
        if act.kind in (ESTOP, LIMIT):
            self.stop_seen = (act.kind, time.monotonic())
        if act.kind == ESTOP:
            m.estop(act.reason)
        elif act.kind == LIMIT:  # as a drive's limit switch: every drive quick-stopped now, then FAULTED
            m.motion.quick_stop(act.reason)
            m._post_fault(act.reason, "modbus")
        elif act.kind == FAULT:
            m._post_fault(act.reason, "modbus")
        elif act.kind == RELEASE:
            m.motion.release_wait()
        elif act.kind == PAUSE:
            with contextlib.suppress(CommandRefused):
                m.pause()
                m.event("INFO", f"paused: {act.reason}", kind="io_pause", source="modbus")
                if act.reason.startswith("door open") and not self._door_held:
                    self._door_held = True  # the spindle and coolant stop with the motion
                    self.mio.hold_spindle()
                    m.motion.spindle_hold(True)
        elif act.kind == RESUME:
            if self._door_held and not self.mio.door_open:
                self._door_held = False  # spindle and coolant back; the motion once at speed
                self.mio.restore_spindle()
                m.motion.spindle_hold(False)
                self._resume_at = time.monotonic() + self.map.spindle.at_speed_timeout_s
                m.event("INFO", f"{act.reason}: spindle and coolant restored, resuming once at speed",
                        kind="io_resume", source="modbus")
                return
            try:
                m.resume()
            except CommandRefused as exc:
                m.event("WARNING", f"{act.reason}: {exc}", kind="io_refused", source="modbus")
        elif act.kind == JOG_STOP:
            m.motion.jog_stop()
            m.event("WARNING", act.reason, kind="io_jog_stop", source="modbus")
        elif act.kind == ABORT:
            with contextlib.suppress(CommandRefused):
                m.abort()
                m.event("WARNING", f"aborted: {act.reason}", kind="io_abort", source="modbus")

    def on_event(self, ev: C.Canon, job: Any) -> None:
        """A setpoint event: switch the outputs it asks for; note them for the run summary."""
        if self.empty or not isinstance(ev, C.SpindleOn | C.SpindleOff | C.SpindleOrient
                                            | C.SetSpindleSpeed | C.Coolant):
            return
        switched = self.mio.on_event(ev)
        self._note(switched, job)
        if isinstance(ev, C.SpindleOn | C.SetSpindleSpeed):
            sp = self.map.spindle
            rpm = abs(ev.rpm)
            if "spindle_speed" in self.map.functions and rpm and (
                    rpm < sp.min_rpm or (sp.max_rpm is not None and rpm > sp.max_rpm)):
                got = next((s.value for s in switched if s.name == "spindle_speed"), rpm)
                self.m.event("WARNING", f"S{rpm:g} clamped to {got:g} rpm ([io.spindle] min_rpm "
                             f"{sp.min_rpm:g}, max_rpm {sp.max_rpm if sp.max_rpm is not None else '-'})",
                             kind="spindle_clamp", source="modbus", file=ev.file, line=ev.line)

    def _note(self, switched: list[Any], stream: Any) -> None:
        """The outputs switched, into the job's record (``stream.outputs``: the run summary)."""
        if stream is None:
            return
        from motiond.runtime.records import OutputSwitch

        now = time.monotonic()
        for s in switched:
            stream.outputs.append(OutputSwitch(self.m.cycle, now, "function", -1, s.value, True, s.file,
                                               s.line, name=s.name))

    def on_wait(self, w: C.Canon) -> bool:
        """The planner stands at ``w``: True when the I/O map completes it."""
        n0 = len(self.mio.switched)
        try:
            taken = self.mio.on_wait(w)
        except KeyError as exc:
            self.m._post_fault(str(exc.args[0]), "modbus")
            return True
        if taken:
            self._note(self.mio.switched[n0:], self.m.motion.stream)
        return taken

    def orient_text(self) -> str:
        """What M19 does on this machine's wiring, for its event ("" nothing wired: done at once)."""
        f = self.map.functions
        if "spindle_orient" not in f:
            return ""
        return "spindle_orient on" + (", waiting for spindle_oriented" if "spindle_oriented" in f else "")

    def stopped(self, *, outputs_off: bool) -> None:
        """The job ended early (E-stop, fault, abort): forget the wait; on E-stop and fault switch the
        spindle, coolant and machine enable off."""
        self._door_held = False
        self._resume_at = None
        if outputs_off:
            self.mio.drop_outputs()
        else:
            self.mio.cancel_wait()

    # --- other threads ------------------------------------------------------------------------------

    def refuse_estop_reset(self, wait: bool = True) -> None:
        """Raise :class:`CommandRefused` while the E-stop input is active or cannot be read. Right
        after start the first poll may not have come: ``wait`` gives it up to 2 s; without ``wait``
        (the command thread, which never waits) that case passes, for the operation to decide."""
        why = self.mio.estop_problem()
        if not wait and "not polled yet" in why:
            return
        if why and "not polled yet" in why:
            deadline = time.monotonic() + 2.0
            while why and time.monotonic() < deadline:
                time.sleep(0.01)
                why = self.mio.estop_problem()
        if why:
            raise CommandRefused(f"cannot reset the estop: {why}")

    def refuse_jog(self) -> None:
        """Raise :class:`CommandRefused` while the door is open (or its switch cannot be read)."""
        why = self.mio.jog_problem()
        if why:
            raise CommandRefused(f"cannot jog: {why}")

    def refuse_resume(self) -> None:
        if self.mio.door_open:
            raise CommandRefused("cannot resume: the door is open (door_open); close it, then cycle start")
        if self._door_held:
            raise CommandRefused("cannot resume: the door stopped the spindle; press cycle start (it "
                                 "restarts the spindle and resumes once it is at speed)")

    def status(self, s: Any) -> None:
        names, values = self.mio.status()
        s.num_io_functions, s.io_function_names, s.io_function_values = len(names), names, values
        s.io_waiting = self.mio.waiting
