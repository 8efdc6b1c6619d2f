"""Task side: run from line: the lines before the start line interpreted with their commands withheld.

:class:`RunFromLineMixin` is the part of :class:`motiond.runtime.machine.Machine` that decides where a
run from line may start (the interpreter's ``before_line`` hook), why the start line was never reached,
and what is queued before the start line's own commands: the restored state and the approach
(:meth:`RunFromLineMixin._start_from`; docs/daemon.md, "Run from line"). It runs on the job thread
(:mod:`motiond.runtime.jobs`) and talks to the motion side only through the command queue (and the
machine's position, asked once for the approach).
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from gcode_canon import commands as C
from gcode_canon.errors import GCodeError
from motiond.runtime.parts import MachinePart
from motiond.runtime.records import ModalState
from motiond.states import State

if TYPE_CHECKING:
    from motiond.runtime.jobs import Job


@dataclass
class StartState:
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
    css: C.SetSpindleMode | None = None  # G96 in force there: the mode, re-sent before the speed


class RunFrom:
    """Run from line: the job thread's bookkeeping while the lines before the start line are
    interpreted with their commands withheld from the planner (:mod:`motiond.runtime.jobs`)."""

    def __init__(self, line: int, tool: int) -> None:
        self.line = line
        self.tool0 = tool  # the tool in the spindle when the job started
        self.main: Any = None  # the main program's LineSource (the first one the hook sees)
        self.reached = False  # the interpreter is about to execute the start line (state captured)
        self.started = False  # the restore and the approach are queued: commands go to the planner
        self.skipped = 0
        self.outputs: list[C.DigitalOutput | C.AnalogOutput] = []
        self.mcodes: dict[int, C.UserMCode] = {}  # user M codes (M100-M199): the last one of each code
        self.tool_cmd: C.ToolChange | C.SetToolNumber | None = None
        self.end_line = 0  # where a skipped M2/M30 ended the program
        self.state: StartState | None = None

    def note(self, cmd: C.Canon) -> None:
        """A command of the skipped part: nothing is sent, but what must be reported is kept."""
        self.skipped += 1
        if isinstance(cmd, C.DigitalOutput | C.AnalogOutput):
            self.outputs.append(cmd)
        elif isinstance(cmd, C.UserMCode):
            self.mcodes.pop(cmd.code, None)  # kept in the order of their last occurrence
            self.mcodes[cmd.code] = cmd
        elif isinstance(cmd, C.ToolChange | C.SetToolNumber):
            self.tool_cmd = cmd
        elif isinstance(cmd, C.ProgramEnd):
            self.end_line = cmd.line


class RunFromLineMixin(MachinePart):
    """Run from line for :class:`~motiond.runtime.machine.Machine` (module docstring)."""

    if TYPE_CHECKING:  # provided by Machine and JobsMixin
        def _modal_state(self, file: str, line: int) -> ModalState: ...
        def _machine_pose(self, base: C.Pose | None = None) -> C.Pose: ...
        def _finish_job(self, then: Callable[[], None] | None = None) -> None: ...
        def _put(self, item: Any, job: Job) -> bool: ...

    def _before_line(self, job: Job, run_from: RunFrom) -> None:
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
        run_from.state = StartState(
            target=interp.position, tool=int(interp.current_tool), selected=int(interp.selected_tool),
            spindle=(1 if interp.parameter("_spindle_cw") else -1) if interp.parameter("_spindle_on") else 0,
            speed=float(interp.speed), mist=bool(interp.parameter("_mist")),
            flood=bool(interp.parameter("_flood")),
            overrides={"feed": bool(interp.parameter("_feed_override")),
                       "spindle": bool(interp.parameter("_speed_override")),
                       "adaptive_feed": bool(interp.parameter("_adaptive_feed")),
                       "feed_hold": bool(interp.parameter("_feed_hold"))},
            feed_mode=interp.feed_mode, feed=float(interp.feed), control=interp.control,
            modal=self._modal_state(interp.file, n), key=interp.modal_key(),
            css=interp._css_mode() if interp.css_max else None)
        run_from.reached = True
        interp.before_line = None

    def _never_reached(self, job: Job, run_from: RunFrom) -> str:
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

    def _refuse_start(self, job: Job, exc: GCodeError, kind: str = "run_from_line") -> None:
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

            def finished() -> None:
                if self.states.state in (State.RUNNING, State.PAUSED):
                    self.states.finished()

            self._finish_job(finished)
            self.event("ERROR", reason, kind=kind, source="gcode", file=exc.file, line=exc.line)

        self.motion.run_on_cycle(on_cycle, wait=False)

    def _user_mcodes(self, run_from: RunFrom, f: str, n: int, did: list[str]) -> list[C.Canon]:
        """The skipped user M codes to replay (docs/daemon.md, "Run from line"): of those bound to set
        outputs (``[io.mcodes]``), the last occurrence of each code, in the order of those occurrences.
        For every output the M code that last wrote it comes last, so each ends as the skipped part
        left it; each runs with its wait (a clamp closed is confirmed again). An M code that only waits
        changes nothing and is not replayed."""
        mcodes = self.io_hooks.map.mcodes  # type: ignore[attr-defined]
        out: list[C.Canon] = []
        for code, cmd in run_from.mcodes.items():
            mc = mcodes.get(code)
            if mc is None or not mc.sets:
                continue
            out.append(dataclasses.replace(cmd, file=f, line=n))
            did.append(f"M{code} (as line {cmd.line})")
        return out

    def _start_from(self, job: Job, run_from: RunFrom) -> bool:
        """Job thread, run from line: queue what restores the skipped part's state, then the approach.

        In this order, each at rest (G61.1 for the approach, the operator's feed override and feed hold
        on for it):

        1. feed mode and rate (state only);
        2. the tool: a tool change (M6, an event and a sync point as any) to the tool the skipped part
           left in the spindle, when it differs from the one there at the start (M61 when the skipped
           part declared it with M61); then the prepared tool (T);
        3. Z up, alone, to the higher of where it stands and the start point's Z;
        4. the user M codes (M100-M199) that set outputs: the last occurrence of each, in the order of
           those (so every output ends as the skipped part left it), each with its wait; then spindle
           speed, spindle on (M3/M4) or off (M5), coolant (mist, flood);
        5. the other axes (X Y and any rotary) to the start point, at that Z;
        6. Z down to the start point;
        7. the skipped part's path control mode (G61/G64 P) and override switches (M48-M53).

        Machine coordinates; Z is the tool axis whatever G17/G18/G19 selects (those choose the arc
        plane, not the spindle's direction; the tool length offset is along Z too), and up is +Z. A
        machine without a Z axis moves all axes together. Outputs (M62-M65, M67, M68), dwells, stops
        and messages of the skipped part are not replayed: a WARNING lists the outputs (the user M
        codes are, step 4).
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
        restore: list[C.Canon] = self._user_mcodes(run_from, f, n, did)
        # under G96 the speed is a surface speed: its mode first, so that the planner makes rpm of it
        if st.css is not None:
            restore.append(dataclasses.replace(st.css, file=f, line=n))
        restore.append(C.SetSpindleSpeed(st.speed, file=f, line=n))
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
