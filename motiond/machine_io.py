"""The machine's functions at run time: what the I/O map (``[io]``, :mod:`motiond.config_io`) binds,
acted on. See docs/wiring.md.

:class:`MachineIO` has a narrow interface, all of it called on the cycle thread (it never blocks: every
write is handed to the Modbus worker, every input read from its latest poll):

* :meth:`MachineIO.on_event`: a canonical event riding on this cycle's setpoint (M3/M4/M5, S, M7/M8/M9,
  M19) switches its outputs; returns what it switched, for the run summary;
* :meth:`MachineIO.on_wait`: the planner stands at a sync point the machine must complete (M3/M4
  with an at-speed signal, M19 with an oriented signal, a user M code): True when this object takes
  it; it then reports :data:`RELEASE` (or a fault naming the line, on timeout) from a later poll;
* :meth:`MachineIO.poll`: once per cycle with the machine's state; returns the actions the machine
  must take (:class:`Action`: E-stop, fault, release, pause, resume, abort) from the inputs (E-stop,
  limits, operator buttons, door) and the waits in progress; keeps ``machine_enable`` in step;
* :meth:`MachineIO.status`: every function's state, for the LCM status.

E-stop latency: the E-stop input is seen by the first Modbus poll after it changes (the device's
``poll_ms`` plus one request), and acted on at the start of the next cycle: at most ``poll_ms`` + the
request time + one cycle. An input that cannot be read (link lost, exception response) is an active
E-stop (fail safe).
"""

from __future__ import annotations

import concurrent.futures
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from gcode_canon import commands as C
from motiond.config_io import DIGITAL, Binding, IoMap

log = logging.getLogger(__name__)

ESTOP, FAULT, LIMIT, RELEASE, PAUSE, RESUME, ABORT, JOG_STOP = (
    "estop", "fault", "limit", "release", "pause", "resume", "abort", "jog_stop")


@dataclass(frozen=True)
class Action:
    """Something the machine must do now: ``kind`` one of ESTOP, FAULT, LIMIT (a limit switch: stop
    as a drive's does; ``axis`` set), RELEASE (the sync point is done), PAUSE, RESUME, ABORT, JOG_STOP
    (the door opened during a jog)."""

    kind: str
    reason: str = ""
    axis: str = ""


@dataclass
class Switched:
    """One function output switched (for the run summary and tests)."""

    name: str
    value: float
    file: str
    line: int


@dataclass
class _Wait:
    cmd: Any
    what: str  # "M3 S1000: spindle at speed"
    deadline: float
    futures: list[concurrent.futures.Future[float]]
    check: Any  # callable() -> bool | None (None: cannot be read)
    device: str  # whose poll must be newer than the writes ("" none)
    timeout: float = 0.0


@dataclass(frozen=True)
class MachineState:
    """What :meth:`MachineIO.poll` needs of the machine each cycle."""

    estop: bool  # in ESTOP
    enabled: bool  # drives enabled and not faulted (machine_enable on)
    running: bool  # a program runs (not paused)
    paused: bool
    velocity: tuple[float, ...] = ()  # commanded, per axis (in the machine's axis order)
    drive_inputs: tuple[int, ...] = ()  # 0x60FD per axis
    jogging: bool = False  # a jog moves an axis


class MachineIO:
    """The I/O map acted on (module docstring). ``executor``: the Modbus executor (None: a machine
    without Modbus; drive-input functions still work). ``axes``: the machine's axis names in order.
    ``drive_out``: writes a drive's 0x60FE bit (the CANopen master's ``set_output``: never blocks)."""

    def __init__(self, io: IoMap, executor: Any, axes: tuple[str, ...],
                 drive_out: Callable[[int, int, bool], concurrent.futures.Future[float]] | None = None,
                 ) -> None:
        self.io = io
        self.ex = executor
        self.drive_out = drive_out  # a drive's 0x60FE bit: (axis index, bit, on) -> future (the master's)
        self._drive_written: dict[tuple[str, int], float] = {}  # 0x60FE bits as last written
        self.axes = axes
        self.f = io.functions
        self._values: dict[str, float] = {}  # outputs as commanded
        self._inputs: dict[str, bool | None] = {}  # inputs as last read (None: unreadable)
        self._wait: _Wait | None = None
        self.door_open = False
        self._jog_stopped = False  # the door stopped the jog in progress
        self.estop_reason = ""  # why the E-stop input holds the machine in ESTOP ("" it does not)
        self.switched: list[Switched] = []
        self._spindle_rpm = 0.0
        self._spindle_dir = 0
        self._pending_futures: list[concurrent.futures.Future[float]] = []  # the last M3/M4/M19 writes
        self._drive_inputs: tuple[int, ...] = ()
        self._unwritten: dict[str, float] = {}  # outputs whose write was refused (link down), warned once
        self._read_key: tuple[Any, ...] = ()
        self._digital_inputs = [(n, b) for n, b in self.f.items()
                                if b.direction == "in" and b.kind == DIGITAL]
        for name, b in self.f.items():
            if b.direction == "out":
                self._values[name] = 0.0

    # --- what the planner must wait for -------------------------------------------------------------

    @property
    def wait_types(self) -> tuple[type[C.Canon], ...]:
        """Sync commands after which the planner must stay at rest until :meth:`poll` releases it."""
        out: list[type[C.Canon]] = [C.UserMCode]
        if "spindle_at_speed" in self.f or "spindle_speed_measured" in self.f:
            out.append(C.SpindleOn)
        if "spindle_oriented" in self.f:
            out.append(C.SpindleOrient)
        return tuple(out)

    @property
    def waiting(self) -> str:
        """What a sync point waits for now, in words ("" none)."""
        return self._wait.what if self._wait is not None else ""

    # --- outputs ------------------------------------------------------------------------------------

    def _set(self, name: str, value: float, cmd: C.Canon | None = None,
             futures: list[concurrent.futures.Future[float]] | None = None) -> None:
        """Write function output ``name`` (logical value: on/off, rpm) if bound."""
        b = self.f.get(name)
        if b is None:
            return
        self._write(b, value, cmd, futures)
        self._values[name] = float(value)

    def _write(self, b: Binding, value: float, cmd: C.Canon | None,
               futures: list[concurrent.futures.Future[float]] | None = None, force: bool = False) -> None:
        """Write ``b``'s point: its logical ``value`` at the wired level. Unless ``force`` (a user M
        code), a point already commanded to that level is not written again."""
        from fieldbus.modbus.faults import IoError

        raw = float(value) if b.kind != DIGITAL else 1.0 if bool(value) != b.active_low else 0.0
        if b.point is None:
            self._write_drive(b, raw, value, cmd, futures, force)
            return
        if self.ex is None:
            return
        if not force and self.ex.commanded_point(b.point.key) == raw:
            return
        try:
            fut = self.ex.write_point(b.point.key, raw)
        except IoError as exc:  # the link fault is reported by the executor; say what was lost, once
            if self._unwritten.get(b.point.key) != raw:
                log.warning("%s not written: %s", b.name, exc)
            self._unwritten[b.point.key] = raw
            return
        self._unwritten.pop(b.point.key, None)
        if futures is not None:
            futures.append(fut)
        self.switched.append(Switched(b.name, float(value), cmd.file if cmd else "", cmd.line if cmd else 0))

    def _write_drive(self, b: Binding, raw: float, value: float, cmd: C.Canon | None,
                     futures: list[concurrent.futures.Future[float]] | None, force: bool) -> None:
        """A drive's 0x60FE bit, through the master (its own thread writes it by SDO)."""
        key = (b.drive_axis, b.bit)
        if self.drive_out is None or (not force and self._drive_written.get(key) == raw):
            return
        fut = self.drive_out(self.axes.index(b.drive_axis), b.bit, bool(raw))
        self._drive_written[key] = raw
        fut.add_done_callback(lambda f: f.exception() is None or log.warning(
            "%s not written: %s", b.name, f.exception()))
        if futures is not None:
            futures.append(fut)
        self.switched.append(Switched(b.name, float(value), cmd.file if cmd else "", cmd.line if cmd else 0))

    def _speed(self, rpm: float, cmd: C.Canon, futures: list[concurrent.futures.Future[float]]) -> float:
        sp = self.io.spindle
        r = abs(rpm)
        clamped = min(max(r, sp.min_rpm), sp.max_rpm if sp.max_rpm is not None else r)
        if r == 0.0:
            clamped = 0.0
        self._set("spindle_speed", clamped, cmd, futures)
        return clamped

    def on_event(self, ev: C.Canon) -> list[Switched]:
        """A canonical event on this cycle's setpoint; the outputs it switched."""
        n0 = len(self.switched)
        futures: list[concurrent.futures.Future[float]] = []
        if isinstance(ev, C.SpindleOn):
            cw = ev.direction is C.SpindleDirection.CW
            self._set("spindle_orient", 0, ev)
            self._spindle_rpm = self._speed(ev.rpm, ev, futures)
            self._spindle_dir = 1 if cw else -1
            self._set("spindle_reverse", not cw, ev, futures)
            self._set("spindle_cw", cw, ev, futures)
            self._set("spindle_ccw", not cw, ev, futures)
            self._set("spindle_on", True, ev, futures)
            self._pending_futures = futures
        elif isinstance(ev, C.SpindleOff | C.SpindleOrient):
            for name in ("spindle_on", "spindle_cw", "spindle_ccw"):
                self._set(name, False, ev)
            self._spindle_dir = 0
            if isinstance(ev, C.SpindleOrient):
                self._set("spindle_orient", True, ev, futures)
                self._pending_futures = futures
            else:
                self._set("spindle_orient", False, ev)
        elif isinstance(ev, C.SetSpindleSpeed):
            self._spindle_rpm = self._speed(ev.rpm, ev, futures)
        elif isinstance(ev, C.Coolant):
            self._set("coolant_mist", ev.mist, ev)
            self._set("coolant_flood", ev.flood, ev)
        return self.switched[n0:]

    # --- sync points --------------------------------------------------------------------------------

    def on_wait(self, cmd: C.Canon, now: float | None = None) -> bool:
        """The planner stands at ``cmd``; True when this object completes it (see :meth:`poll`)."""
        now = time.monotonic() if now is None else now
        where = f"{cmd.file}:{cmd.line}: " if cmd.file else ""
        futures, self._pending_futures = list(self._pending_futures), []
        if not isinstance(cmd, self.wait_types):
            return False
        sp = self.io.spindle
        if isinstance(cmd, C.SpindleOn):
            rpm = self._spindle_rpm
            word = f"{'M3' if cmd.direction is C.SpindleDirection.CW else 'M4'} S{cmd.rpm:g}"
            if rpm == 0.0:
                self._wait = _Wait(cmd, f"{where}{word}", now, futures, lambda: True, "", 0.0)
            elif "spindle_at_speed" in self.f:
                b = self.f["spindle_at_speed"]
                self._wait = _Wait(cmd, f"{where}{word}: spindle at speed ({b.key}, {b.where})",
                                   now + sp.at_speed_timeout_s, futures, lambda: self._read(b), _dev(b),
                                   sp.at_speed_timeout_s)
            else:
                b = self.f["spindle_speed_measured"]
                tol = max(sp.at_speed_tolerance * rpm, 1e-9)
                self._wait = _Wait(cmd, f"{where}{word}: spindle at speed (measured within "
                                        f"{100 * sp.at_speed_tolerance:g} % of {rpm:g} rpm, {b.key})",
                                   now + sp.at_speed_timeout_s, futures,
                                   lambda: self._near(b, rpm, tol), _dev(b), sp.at_speed_timeout_s)
        elif isinstance(cmd, C.SpindleOrient):
            b = self.f["spindle_oriented"]
            timeout = cmd.timeout if cmd.timeout > 0 else sp.orient_timeout_s
            self._wait = _Wait(cmd, f"{where}M19 R{cmd.angle:g}: spindle oriented ({b.key}, {b.where})",
                               now + timeout, futures, lambda: self._read(b), _dev(b), timeout)
        else:
            assert isinstance(cmd, C.UserMCode)
            mc = self.io.mcodes.get(cmd.code)
            if mc is None:  # the interpreter refuses unbound codes; a program checked elsewhere?
                self._wait = None
                raise KeyError(f"{where}M{cmd.code} is not bound on this machine ([io.mcodes])")
            for b, value in mc.sets:
                self._write(b, value, cmd, futures, force=True)
            w = mc.wait
            if w is None:
                self._wait = _Wait(cmd, f"{where}M{cmd.code}", now + mc.timeout_s, futures, lambda: True, "",
                                   mc.timeout_s)
            else:
                self._wait = _Wait(cmd, f"{where}M{cmd.code}: {w.key} ({w.where})", now + mc.timeout_s,
                                   futures, lambda: self._read(w), _dev(w), mc.timeout_s)
        return True

    def cancel_wait(self) -> None:
        """The job ended (abort, fault, E-stop): the sync point waited for is gone."""
        self._wait = None
        self._pending_futures = []

    def _poll_wait(self, now: float) -> Action | None:
        w = self._wait
        if w is None:
            return None
        for fut in w.futures:
            if fut.done() and fut.exception() is not None:
                self._wait = None
                return Action(FAULT, f"{w.what}: output not written: {fut.exception()}")
        written = [fut.result() for fut in w.futures if fut.done()]
        ready = len(written) == len(w.futures)
        if ready and w.device:  # the input must come from a poll that began after the writes
            polls = self.ex.worker.snapshot.polls if self.ex is not None else {}
            ready = polls.get(w.device, (0, -1.0))[1] > max(written, default=0.0)
        if ready and w.check():
            self._wait = None
            return Action(RELEASE)
        if now > w.deadline:
            self._wait = None
            return Action(FAULT, f"{w.what}: not done within {w.timeout:g} s")
        return None

    # --- inputs -------------------------------------------------------------------------------------

    def _read(self, b: Binding, st: MachineState | None = None) -> bool | None:
        """Whether function ``b`` is active: True/False, None when it cannot be read (fail safe)."""
        if b.point is None:
            words = st.drive_inputs if st is not None else self._drive_inputs
            try:
                word = words[self.axes.index(b.drive_axis)]
            except (ValueError, IndexError):
                return None
            raw = bool(word >> b.bit & 1)
            return raw != b.active_low
        ex = self.ex
        if ex is None:
            return None
        snap = ex.worker.snapshot
        dev = b.point.device
        if (not ex.worker.link_up.get(dev, False) or dev not in snap.polls
                or ("named", b.point.key) in snap.bad):
            return None
        value = snap.named.get(b.point.key)
        if value is None:
            return None
        return bool(value) != b.active_low

    def _near(self, b: Binding, rpm: float, tol: float) -> bool:
        if self.ex is None or b.point is None:
            return False
        v = self.ex.worker.snapshot.named.get(b.point.key)
        return v is not None and abs(abs(v) - rpm) <= tol

    def _input_problem(self, name: str, what: str, active: str) -> str:
        """Why input ``name`` stands in the way ("" it does not): ``active`` when it is active, a
        sentence naming ``what`` it is when it cannot be read."""
        b = self.f.get(name)
        if b is None:
            return ""
        state = self._read(b)
        if state is None:
            return f"the {what} cannot be read ({b.where}: link down or not polled yet)"
        return f"{active} ({b.key}, {b.where})" if state else ""

    def estop_problem(self) -> str:
        """Why the machine may not leave ESTOP because of its E-stop input ("" it may)."""
        return self._input_problem("estop", "E-stop input", "the E-stop input is active")

    def jog_problem(self) -> str:
        """Why a jog may not start because of the inputs ("" it may): the door open (or unreadable)."""
        why = self._input_problem("door_open", "door switch", "the door is open")
        return f"{why}; close it first" if why.startswith("the door is open") else why

    def poll(self, st: MachineState, now: float | None = None) -> list[Action]:
        """Once per cycle: the actions the inputs and waits ask for (module docstring)."""
        now = time.monotonic() if now is None else now
        out: list[Action] = []
        prev = self._inputs
        self._drive_inputs = st.drive_inputs
        ex = self.ex
        # the inputs change with a poll (every poll_ms), a link or the drives' inputs: read them again
        # only then (most cycles fall between two polls)
        key = (st.drive_inputs, ex.worker.snapshot.seq, tuple(ex.worker.link_up.values())) \
            if ex is not None else (st.drive_inputs,)
        if key != self._read_key:
            self._read_key = key
            cur: dict[str, bool | None] = {}
            for name, b in self._digital_inputs:
                cur[name] = self._read(b, st)
            self._inputs = cur
        cur = self._inputs

        def rose(name: str) -> bool:
            return bool(cur.get(name)) and not prev.get(name)

        if "estop" in cur:
            b = self.f["estop"]
            v = cur["estop"]
            self.estop_reason = "" if v is False else (
                f"E-stop input active ({b.key}, {b.where})" if v else
                f"E-stop input unreadable ({b.where}: Modbus link lost or no answer): treated as E-stop")
            if self.estop_reason and not st.estop:
                out.append(Action(ESTOP, self.estop_reason))
        self._set_enable(st.enabled and not st.estop and not self.estop_reason)
        if out:
            return out
        for i, axis in enumerate(self.axes):
            v = st.velocity[i] if i < len(st.velocity) else 0.0
            for end, sign, word in (("min", -1.0, "negative"), ("max", 1.0, "positive")):
                name = f"limit_{axis}_{end}"
                if name not in cur or not cur[name] or not st.enabled:
                    continue
                toward = v * sign > 0.0
                if rose(name) or toward:
                    b = self.f[name]
                    why = ("it became active while the drives are enabled" if rose(name)
                           else "the axis moves toward it")
                    out.append(Action(LIMIT, f"axis {axis}: {word} limit switch {name} active ({b.where}): "
                                             f"{why}; not re-enabled (reset, then move the axis off the "
                                             "switch)", axis))
                    return out
        self.door_open = bool(cur.get("door_open"))
        if self.door_open and st.running:
            out.append(Action(PAUSE, f"door open ({self.f['door_open'].where}): motion held; close it and "
                                     "press cycle start"))
        if self.door_open and st.jogging and not self._jog_stopped:
            self._jog_stopped = True  # once per jog: the jog stops on its ramp
            out.append(Action(JOG_STOP, f"door open ({self.f['door_open'].where}): jog stopped"))
        elif not st.jogging:
            self._jog_stopped = False
        if rose("feed_hold") and st.running:
            out.append(Action(PAUSE, "feed hold button"))
        if rose("abort"):
            out.append(Action(ABORT, "abort button"))
        if rose("cycle_start") and st.paused:
            out.append(Action(RESUME, "cycle start button"))
        done = self._poll_wait(now)
        if done is not None:
            out.append(done)
        return out

    # --- the door -----------------------------------------------------------------------------------

    _HELD = ("spindle_on", "spindle_cw", "spindle_ccw", "coolant_mist", "coolant_flood")

    def hold_spindle(self) -> None:
        """The door opened on a running program: spindle and coolant off, as they were kept for
        :meth:`restore_spindle`."""
        self._held = {n: v for n in self._HELD if n in self.f and (v := self._values.get(n, 0.0))}
        for name in self._held:
            self._set(name, 0.0)

    def restore_spindle(self) -> None:
        """Door closed, cycle start: spindle and coolant as they were (the at-speed check starts)."""
        held, self._held = getattr(self, "_held", {}), {}
        futures: list[concurrent.futures.Future[float]] = []
        for name, value in held.items():
            self._set(name, value, futures=futures)
        self._restore_futures = futures

    def spindle_ready(self) -> bool | None:
        """After :meth:`restore_spindle`: the spindle at speed again (True), not yet (False), or no way
        to tell (None: no at-speed signal bound; the machine goes on at once)."""
        on = any(self._values.get(n) for n in ("spindle_on", "spindle_cw", "spindle_ccw"))
        b = self.f.get("spindle_at_speed")
        if not on or (b is None and "spindle_speed_measured" not in self.f):
            return None
        futures = getattr(self, "_restore_futures", [])
        if not all(f.done() for f in futures):
            return False
        written = max((f.result() for f in futures if f.exception() is None), default=0.0)
        if self.ex is not None:
            dev = _dev(b if b is not None else self.f["spindle_speed_measured"])
            if self.ex.worker.snapshot.polls.get(dev, (0, -1.0))[1] <= written:
                return False  # the input must come from a poll after the writes
        if b is not None:
            return bool(self._read(b))
        rpm = self._spindle_rpm
        return self._near(self.f["spindle_speed_measured"], rpm, max(self.io.spindle.at_speed_tolerance * rpm,
                                                                      1e-9))

    def _set_enable(self, on: bool) -> None:
        self._set("machine_enable", on)  # written when it changes (or was reset to safe by a recovery)

    def drop_outputs(self) -> None:
        """E-stop or fault: the spindle, coolant and machine enable off now (their safe values)."""
        for name in ("machine_enable", "spindle_on", "spindle_cw", "spindle_ccw", "spindle_orient",
                     "coolant_mist", "coolant_flood", "spindle_speed"):
            self._set(name, 0.0)
        self._spindle_dir = 0
        self.cancel_wait()

    # --- status -------------------------------------------------------------------------------------

    def status(self) -> tuple[list[str], list[float]]:
        """Every bound function and its state (inputs: 1 active, 0 not, -1 unreadable; outputs: as
        commanded; analog: the value), names sorted as in the map."""
        names: list[str] = []
        values: list[float] = []
        for name, b in self.f.items():
            names.append(name)
            if b.direction == "out":
                values.append(self._values.get(name, 0.0))
            elif b.kind == DIGITAL:
                v = self._inputs.get(name)
                values.append(-1.0 if v is None else float(v))
            else:
                snap = self.ex.worker.snapshot if self.ex is not None else None
                values.append(float(snap.named.get(name, 0.0)) if snap is not None else 0.0)
        return names, values


def _dev(b: Binding) -> str:
    return b.point.device if b.point is not None else ""
