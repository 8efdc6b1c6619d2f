"""The motion step of a line: straight moves, G53, arcs, probes, canned cycles and the gcode-canon
full circles G12/G13, from the axis words to canonical commands in machine coordinates (LinuxCNC's
``convert_motion``, ``convert_straight``, ``convert_arc``, ``convert_probe``, ``convert_cycle`` and
``find_ends``). A mixin of :class:`gcode_canon.interpreter.Interpreter`."""

from __future__ import annotations

import math

from gcode_canon import cycles, transforms
from gcode_canon.arcs import centre_ijk, centre_r
from gcode_canon.commands import (
    ArcFeed,
    Canon,
    Dwell,
    FeedMode,
    MotionControlMode,
    Pose,
    Probe,
    ProbeMode,
    ProgramStop,
    SetFeedRate,
    SetMotionControlMode,
    SetOverrides,
    SpindleDirection,
    SpindleOff,
    SpindleOn,
    SpindleOrient,
    StraightFeed,
    StraightTraverse,
    new_arc_feed,
    new_straight_feed,
    new_straight_traverse,
    slot_setters,
)
from gcode_canon.errors import GCodeError
from gcode_canon.lathe_cycles import LATHE_CYCLES
from gcode_canon.lexer import AXIS_LETTERS, Block
from gcode_canon.machine import Resume
from gcode_canon.modal import ModalLine, gname
from gcode_canon.offsets import N_AXES, ROTARY_INDEXES
from gcode_canon.spindle_sync import SYNC_MOTIONS
from gcode_canon.spline_steps import SPLINE_MOTIONS

_PROBE_MODES = {382: ProbeMode.TOWARD_ERROR, 383: ProbeMode.TOWARD, 384: ProbeMode.AWAY_ERROR,
                385: ProbeMode.AWAY}
_IJK = "ijk"
UVW_ARC = "Cannot do an arc in planes G17.1, G18.1, or G19.1"
"""LinuxCNC's refusal of an arc (G2/G3, and G12/G13 here) in a UVW plane."""
_PLAIN_MOTIONS = frozenset((0, 10, 20, 30))
_isfinite = math.isfinite
_AXIS_INDEX = {letter: k for k, letter in enumerate(AXIS_LETTERS)}
_new_pose = tuple.__new__
_new_object = object.__new__
_arc_end, _arc_center, _arc_plane, _arc_turns, _arc_rotation, _arc_file, _arc_line = slot_setters(ArcFeed)

class MotionMixin:
    """Group 1 (motion) and G12/G13 (module docstring)."""

    def _target(self, block: Block, prog: list[float] | None = None, polar: bool = True) -> list[float]:
        """End point in the program frame (mm) from the line's axis words and polar words."""
        target = list(self.prog if prog is None else prog)
        scale = self.scale
        absolute = self.absolute
        words = block.words
        if polar and self.polar_on:
            first, second, _ = self.plane._value_
            r_letter, a_letter = AXIS_LETTERS[first], AXIS_LETTERS[second]
            radius = words.get(r_letter)
            angle = words.get(a_letter)
            if radius is not None or angle is not None:
                point, self.polar = transforms.polar_target(
                    (target[first], target[second]), None if radius is None else radius * scale, angle,
                    incremental=not absolute, origin=self.polar_origin, state=self.polar)
                rest = {k: v for k, v in words.items() if k not in (r_letter, a_letter)}
                tmp = Block()
                tmp.words = rest
                target = self._target(tmp, target, polar=False)
                target[first], target[second] = point
                return target
        for letter, value in words.items():
            k = _AXIS_INDEX.get(letter)
            if k is not None:
                if k < 3 or k > 5:
                    value *= scale
                target[k] = value if absolute else target[k] + value
        r_word = words.get("@")
        a_word = words.get("^")
        if r_word is not None or a_word is not None:
            cur_r = math.hypot(target[0], target[1])
            cur_a = math.degrees(math.atan2(target[1], target[0]))
            if absolute:
                if a_word is None and cur_r == 0.0:
                    raise GCodeError("Must specify angle in polar coordinate if at the origin")
                radius = r_word * scale if r_word is not None else cur_r
                angle = a_word if a_word is not None else cur_a
            else:
                if cur_r < 1e-9:
                    raise GCodeError("Incremental polar move (G91 @ ^) from the origin is indeterminate")
                radius = cur_r + (r_word * scale if r_word is not None else 0.0)
                angle = cur_a + (a_word if a_word is not None else 0.0)
            target[0] = radius * math.cos(math.radians(angle))
            target[1] = radius * math.sin(math.radians(angle))
        return target

    def _full_circle(self, code: int, block: Block) -> None:
        """G12/G13 (gcode-canon): a full circle of radius I around the current point."""
        name = gname(code)
        if self.comp is not None:
            raise GCodeError(f"{name} with cutter radius compensation on is not supported")
        first, second, normal = self.plane._value_
        if normal > 2:
            raise GCodeError(UVW_ARC)
        self._require_feed(block, name)
        i = block.take("i")
        tool_radius = 0.0
        d = self._int_word(block, "d", name)
        if d is not None:
            tool = self._tool(d)
            tool_radius = float(tool.diameter) / 2.0 if tool is not None else 0.0
        start = list(self.prog)
        moves = transforms.full_circle((start[first], start[second]), None if i is None else i * self.scale,
                                       code == 120, tool_radius=tool_radius, code=name)
        f, n = self.file, self.line
        xform = self.xform
        for mv in moves:
            target = list(self.prog)
            target[first], target[second] = mv.end
            end_pose = self._to_machine(target)
            if mv.kind == "feed":
                self._emit(StraightFeed(end_pose, file=f, line=n))
            else:
                assert mv.centre is not None
                centre = list(target)
                centre[first], centre[second] = mv.centre
                clockwise = mv.clockwise
                if self.xform_on:
                    clockwise = xform.arc_clockwise(clockwise, self.plane)
                centre_pose = self._to_machine(centre)
                self._emit(ArcFeed(end_pose, centre_pose, self.plane, -1 if clockwise else 1,
                                   self.frames.arc_rotation(self.plane), file=f, line=n))
            self.prog = target
            self.pos = end_pose
        _ = normal

    def _step_motion(self, block: Block, ml: ModalLine) -> None:
        g0 = ml.g.get(0)
        explicit = ml.g.get(1)
        if ml.axis_user:
            if explicit is not None:
                self.motion = explicit
            return
        previous = self.motion
        motion = previous if explicit is None else explicit
        self.motion = motion
        w = block.words
        has_axes = block.axes
        if motion not in _PLAIN_MOTIONS:  # the common case (G0 G1 G2 G3) skips these tests
            if motion in LATHE_CYCLES:
                if has_axes or explicit == motion:
                    self._lathe_cycle(motion, block)
                return
            if motion in SPLINE_MOTIONS:
                if has_axes or explicit in (52, 62):
                    self._spline(motion, block, previous)
                elif explicit is not None:
                    raise GCodeError(f"All axes missing with motion code {gname(motion)}")
                return
            if motion in cycles.CYCLE_CODES:
                if has_axes:
                    self._cycle(motion, block)
                return
        if self.cycle_state.motion is not None or self.cycle_state.initial_level is not None:
            self.cycle_state = cycles.cancel(self.cycle_state)
        if motion in SYNC_MOTIONS:
            if has_axes:
                self._sync_motion(motion, block)
            return
        if motion == 20 or motion == 30:
            # a G2/G3 written on the line is an arc even with no other word (LinuxCNC then refuses it:
            # "R, I, J or K words missing"); a line in G2/G3 mode with none of them moves nothing
            if has_axes or "i" in w or "j" in w or "k" in w or "r" in w or explicit in (20, 30):
                self._arc(block, motion == 20)
            return
        if not has_axes:
            return
        f, n = self.file, self.line
        if g0 == 530:
            # LinuxCNC (find_ends): machine coordinates, the tool length offset not added (G53 G0 Z0
            # goes to machine Z0 whatever G43 is in force), except on (unwrapped) rotary axes
            tool = self.frames.tool
            end = list(self.pos)
            for k, letter in enumerate(AXIS_LETTERS):
                value = block.take(letter)
                if value is not None:
                    if k in ROTARY_INDEXES:
                        value += tool[k]
                    else:
                        value *= self.scale
                    end[k] = value
            target = self._from_machine(end)
        else:
            target = self._target(block)
        end_pose = self._to_machine(target)
        if not _isfinite(sum(end_pose)):  # also refuses sums beyond 1e308: no machine is that big
            raise GCodeError("Coordinate out of range")
        if self.comp is not None and motion in (0, 10):
            if motion == 10:
                self._require_feed(block, "G1")
            first, second, normal = self.plane._value_
            t = list(self.xform.apply_position(target)) if self.xform_on else target
            others = tuple(t[k] for k in range(N_AXES) if k not in (first, second, normal))
            from gcode_canon import cutter_comp  # with compensation only: not at every start-up

            self._comp_move(cutter_comp.Line2(self.comp.programmed, (t[first], t[second]),
                                              t[normal], others, n, motion == 0))
            self.prog = target
            return
        self._after_comp = False
        if motion == 0:
            cmd: Canon = new_straight_traverse(end_pose, f, n)
        elif motion == 10:
            self._require_feed(block, "G1")
            cmd = new_straight_feed(end_pose, f, n)
        elif motion in _PROBE_MODES:
            if self.comp is not None:
                raise GCodeError("Cannot probe with cutter radius compensation on")
            if self.feed_mode is FeedMode.INVERSE_TIME:
                raise GCodeError("Cannot probe in inverse time feed mode")
            if self.feed_mode is FeedMode.UNITS_PER_REV:
                raise GCodeError("Cannot probe with feed per rev mode")
            if any(end_pose[k] != self.pos[k] for k in ROTARY_INDEXES):
                raise GCodeError("Cannot move rotary axes during probing")
            self._require_feed(block, gname(motion))
            if math.dist(end_pose, self.pos) < 1e-9 and _PROBE_MODES[motion].error_on_miss:
                # LinuxCNC refuses it for G38.2/G38.4 only: G38.3/G38.5 may start where they end
                raise GCodeError(f"{gname(motion)}: probe move has zero length")
            self._probe(Probe(end_pose, _PROBE_MODES[motion], file=f, line=n))
            return
        else:  # pragma: no cover (other motion codes are refused by modal.sort_codes)
            raise GCodeError(f"{gname(motion)} is not supported yet")
        self.prog = target
        self.pos = end_pose
        self._emit(cmd)

    def _cycle(self, code: int, block: Block) -> None:
        """A canned cycle block: :mod:`gcode_canon.cycles` expands it in plane-local program units;
        each op becomes canonical commands in machine coordinates here."""
        self._after_comp = False
        plane = self.plane
        scale = self.scale
        words = cycles.CycleWords.from_letters(plane, block.words)
        ctx = cycles.CycleContext(
            plane=plane, incremental=not self.absolute, retract_mode=self.retract // 10,
            feed_rate=self.feed, inverse_time=self.feed_mode is FeedMode.INVERSE_TIME,
            cutter_comp=self.comp is not None, spindle=self.spindle, metric=not self.inch,
        )
        unit = [1.0 if k in ROTARY_INDEXES else scale for k in range(N_AXES)]
        here = [v / u for v, u in zip(self.prog, unit, strict=True)]
        result = cycles.expand_cycle(code, words, self.cycle_state, ctx, cycles.to_local(plane, here))
        self.cycle_state = result.state
        f, n = self.file, self.line
        first, second, normal = plane.value
        control = self.control
        prog = list(self.prog)
        for op in result.ops:
            kind = op.kind
            if kind == "traverse" or kind == "feed":
                assert op.point is not None
                prog[first] = op.point[0] * unit[first]
                prog[second] = op.point[1] * unit[second]
                prog[normal] = op.point[2] * unit[normal]
                end = self._to_machine(prog)
                if not _isfinite(sum(end)):
                    raise GCodeError("Coordinate out of range")
                self.prog = list(prog)
                self.pos = end
                cls = StraightTraverse if kind == "traverse" else StraightFeed
                self._emit(cls(end, file=f, line=n))
            elif kind == "dwell":
                self._emit(Dwell(op.seconds, file=f, line=n))
            elif kind == "spindle_stop":
                self._emit(SpindleOff(file=f, line=n))
            elif kind == "spindle_on":
                assert op.direction is not None
                self._emit(SpindleOn(op.direction, self.speed, file=f, line=n))
            elif kind == "program_stop":
                self._emit(ProgramStop(False, file=f, line=n))
            elif kind == "overrides_off":
                self._emit(SetOverrides(feed=False, spindle=False, file=f, line=n))
            elif kind == "overrides_restore":
                self._emit(SetOverrides(feed=self.overrides["feed"], spindle=self.overrides["spindle"],
                                        file=f, line=n))
            elif kind == "exact_path_begin":
                if control[0] is not MotionControlMode.EXACT_PATH:
                    self._emit(SetMotionControlMode(MotionControlMode.EXACT_PATH, 0.0, 0.0, file=f, line=n))
            elif kind == "exact_path_end":
                if control[0] is not MotionControlMode.EXACT_PATH:
                    self._emit(SetMotionControlMode(*control, file=f, line=n))
            elif kind == "orient":
                # G87 stops the spindle at 0 degrees turning the way it was going: M19 P1 for M3, P2
                # for M4. *canon*: LinuxCNC passes its CANON_DIRECTION (2 or 3) as the orient mode,
                # which reads as "counter-clockwise" or out of range; its G87 waits for nothing
                # (timeout 0), as here.
                direction = 1 if op.direction is SpindleDirection.CW else 2
                self._emit(SpindleOrient(0.0, direction, 0.0, file=f, line=n))
            else:  # pragma: no cover (cycles.OpKind is closed)
                raise GCodeError(f"{gname(code)}: unknown cycle operation {kind}")
        prog[first] = result.end[0] * unit[first]
        prog[second] = result.end[1] * unit[second]
        prog[normal] = result.end[2] * unit[normal]
        self.prog = prog
        self.pos = self._to_machine(prog)

    def _require_feed(self, block: Block, what: str) -> None:
        if self.feed_mode is FeedMode.INVERSE_TIME:
            if "f" not in block.words:
                raise GCodeError(f"F word missing with inverse time {what} move")
        elif self.feed == 0.0:
            raise GCodeError(f"Cannot do {what} with zero feed rate")

    def _probe(self, cmd: Probe) -> None:
        self._emit(cmd)

        def answer() -> None:
            where, tripped = self.machine.probe(cmd)
            where = Pose(*where) if tripped else cmd.end
            self.pos = where
            self.prog = self._from_machine(where)
            for k in range(N_AXES):
                scale = 1.0 if k in ROTARY_INDEXES else self.scale
                self.params.set_system(5061 + k, self.prog[k] / scale)
            self.params.set_system(5070, 1.0 if tripped else 0.0)
            if tripped and self.probe_log.stream is not None:
                self.probe_log.write(" ".join(f"{self.params.numbered[5061 + k]:.6f}" for k in range(N_AXES)))
            if not tripped and cmd.mode.error_on_miss:
                raise GCodeError(f"G{cmd.mode.value} move finished without making contact")
            # LinuxCNC set_probe_data: #5061-#5069 are where the probe tripped, the position the next
            # move starts from is where the machine stopped (past the trip point, or backed off)
            now = self.machine.current_position()
            if now is not None:
                self.pos = Pose(*now)
                self.prog = self._from_machine(self.pos)

        self._emit(Resume(answer))

    def _arc(self, block: Block, clockwise: bool) -> None:
        name = "G2" if clockwise else "G3"
        first, second, normal = self.plane._value_
        if normal > 2:
            raise GCodeError(UVW_ARC)
        words = block.words
        first_letter, second_letter, normal_letter = _IJK[first], _IJK[second], _IJK[normal]
        if normal_letter in words:
            raise GCodeError(f"{normal_letter.upper()} word given for arc in {self.plane.gcode} plane")
        turns = self._int_word(block, "p", name, minimum=1) if "p" in words else None
        turns = 1 if turns is None else turns
        self._require_feed(block, name)
        start = self.prog
        radius = words.get("r")
        has_ijk = first_letter in words or second_letter in words
        if radius is not None and has_ijk:
            raise GCodeError("Mixed radius-ijk format for arc")
        target = self._target(block)
        s2 = (start[first], start[second])
        e2 = (target[first], target[second])
        if radius is None and not has_ijk:
            raise GCodeError(f"R, I, J or K words missing for arc ({name})")
        cx, cy, rot = self._arc_centre(words, clockwise, s2, e2, turns)
        if self._after_comp:
            raise GCodeError("The move just after exiting cutter compensation mode must be straight, "
                             "not an arc")
        if self.comp is not None:
            normal = self.plane._value_[2]
            t, t_start = target, start
            end2, centre2, ccw = e2, (cx, cy), rot > 0
            if self.xform_on:
                res = self.xform.apply_arc((target[first], target[second], target[normal]), (cx, cy),
                                           clockwise, self.plane)
                t = list(self.xform.apply_position(target))
                t_start = list(self.xform.apply_position(start))
                end2, centre2, ccw = (t[first], t[second]), res.centre, not res.clockwise
            others = tuple(t[k] for k in range(N_AXES) if k not in (first, second, normal))
            self._comp_normal = t_start[normal]
            from gcode_canon import cutter_comp  # with compensation only: not at every start-up

            self._comp_move(cutter_comp.Arc2(self.comp.programmed, end2, centre2, ccw, t[normal],
                                             others, self.line, abs(rot)))
            self.prog = target
            return
        self._arc_out(start, target, cx, cy, clockwise, rot)

    def _arc_centre(self, words: dict[str, float], clockwise: bool, s2: tuple[float, float],
                    e2: tuple[float, float], turns: int) -> tuple[float, float, int]:
        """Centre and LinuxCNC's rotation of an arc from (start ``s2``) to ``e2`` in the plane, from its
        R word or, without one, its I J K words (one of them given)."""
        radius = words.get("r")
        if radius is not None:
            return centre_r(clockwise, s2, e2, radius * self.scale, turns)
        first, second, _ = self.plane._value_
        off1 = (words.get(_IJK[first]) or 0.0) * self.scale
        off2 = (words.get(_IJK[second]) or 0.0) * self.scale
        centre = (off1, off2) if self.ijk_absolute else (s2[0] + off1, s2[1] + off2)
        return centre_ijk(clockwise, s2, e2, centre, turns, self.inch)

    def _arc_out(self, start: list[float], target: list[float], cx: float, cy: float, clockwise: bool,
                 rot: int) -> None:
        """Emit the arc from ``start`` to ``target`` (program frame, mm) around (cx, cy) in the plane,
        ``rot`` LinuxCNC's rotation (its sign the sense, as ``clockwise``)."""
        cmd = self._arc_command(start, target, cx, cy, clockwise, rot)
        self.prog = target
        self.pos = cmd.end
        self._emit(cmd)

    def _arc_command(self, start: list[float], target: list[float], cx: float, cy: float, clockwise: bool,
                     rot: int) -> ArcFeed:
        """:meth:`_arc_out`'s command, nothing changed."""
        first, second, _ = self.plane._value_
        centre_prog = list(start)
        centre_prog[first] = cx
        centre_prog[second] = cy
        xform = self.xform
        if self.xform_on:
            normal = self.plane._value_[2]
            res = xform.apply_arc((target[first], target[second], target[normal]), (cx, cy), clockwise,
                                  self.plane)
            end_t = list(xform.apply_position(target))
            centre_t = list(end_t)
            centre_t[first], centre_t[second] = res.centre
            centre_t[normal] = xform.apply_position(start)[normal]
            rot = abs(rot) * (-1 if res.clockwise else 1)
            end_pose = self.frames.to_machine(end_t)
            centre_pose = self.frames.to_machine(centre_t)
        else:
            end_pose = self.frames.to_machine(target)
            centre_pose = self.frames.to_machine(centre_prog)
        if not (_isfinite(sum(end_pose)) and _isfinite(sum(centre_pose))):
            raise GCodeError("Coordinate out of range")
        return new_arc_feed(end_pose, centre_pose, self.plane, rot, self.frames.arc_rotation(self.plane),
                            self.file, self.line)

    def _fast_arc(self, motion: int, xv: float | None, yv: float | None, zv: float | None, iv: float | None,
                  jv: float | None, kv: float | None, rv: float | None,
                  fv: float | None) -> tuple[Canon, ...] | None:
        """The fast path of a G2/G3 line read again (:attr:`Block.plain`: X Y Z I J K R F words, their
        values here, None where absent; taken where :meth:`fast_path_allowed` holds): the commands of
        the general path (its F step, then :meth:`_step_motion`'s arc), or None to send the line there,
        with nothing changed (every error is the general path's, said in its place).

        :meth:`_target`, :meth:`_arc_centre` and :meth:`_arc_command` written out for what
        :meth:`fast_path_allowed` leaves: no polar words, no rotation, scaling or mirroring (the frames'
        sum is the whole transform, the arc's ``rotation`` 0). A-W do not move: their machine
        coordinates are the straight fast path's ``_tail``, kept across the lines it runs."""
        plane = self.plane
        first, second, normal = plane._value_
        if normal > 2:
            return None
        offsets = (iv, jv, kv)
        if offsets[normal] is not None:
            return None
        o1, o2 = offsets[first], offsets[second]
        has_ijk = o1 is not None or o2 is not None
        scale = self.scale
        feed = self.feed if fv is None else fv * scale
        if ((rv is not None) == has_ijk or not (feed > 0.0 and _isfinite(feed))
                or self.cycle_state.initial_level is not None):
            return None
        prog = self.prog
        target = [prog[0], prog[1], prog[2]]  # X Y Z: A-W do not move (no such words here)
        if self.absolute:
            if xv is not None:
                target[0] = xv * scale
            if yv is not None:
                target[1] = yv * scale
            if zv is not None:
                target[2] = zv * scale
        else:
            if xv is not None:
                target[0] += xv * scale
            if yv is not None:
                target[1] += yv * scale
            if zv is not None:
                target[2] += zv * scale
        clockwise = motion == 20
        s2 = (prog[first], prog[second])
        e2 = (target[first], target[second])
        try:
            if rv is not None:
                cx, cy, rot = centre_r(clockwise, s2, e2, rv * scale, 1)
            else:
                off1 = (o1 or 0.0) * scale
                off2 = (o2 or 0.0) * scale
                centre = (off1, off2) if self.ijk_absolute else (s2[0] + off1, s2[1] + off2)
                cx, cy, rot = centre_ijk(clockwise, s2, e2, centre, 1, self.inch)
        except GCodeError:
            return None
        centre_xyz = [prog[0], prog[1], prog[2]]
        centre_xyz[first] = cx
        centre_xyz[second] = cy
        sums = self.frames.sum
        tail = self._tail  # A-W in machine coordinates, as the straight fast path keeps them
        if tail is None:
            tail = self._tail = (prog[3] + sums[3], prog[4] + sums[4], prog[5] + sums[5], prog[6] + sums[6],
                                 prog[7] + sums[7], prog[8] + sums[8])
        s0, s1, s2_ = sums[0], sums[1], sums[2]
        end = _new_pose(Pose, (target[0] + s0, target[1] + s1, target[2] + s2_, *tail))
        centre_pose = _new_pose(Pose, (centre_xyz[0] + s0, centre_xyz[1] + s1, centre_xyz[2] + s2_, *tail))
        if not (_isfinite(sum(end)) and _isfinite(sum(centre_pose))):
            return None
        file, line = self.file, self.line
        cmd = _new_object(ArcFeed)  # new_arc_feed's object, without the call (slot_setters)
        _arc_end(cmd, end)
        _arc_center(cmd, centre_pose)
        _arc_plane(cmd, plane)
        _arc_turns(cmd, rot)
        _arc_rotation(cmd, 0.0)
        _arc_file(cmd, file)
        _arc_line(cmd, line)
        self.motion = motion
        prog[0], prog[1], prog[2] = target
        self.pos = end
        if feed != self.feed:
            self.feed = feed
            return (SetFeedRate(feed, file=file, line=line), cmd)
        return (cmd,)
