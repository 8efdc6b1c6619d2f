"""The steps of a line that set modes, in LinuxCNC's order of execution (``execute_block`` in
``interp_execute.cc``, each as its ``convert_*`` in ``interp_convert.cc``): comments and messages, feed
mode and F, M62-M68 I/O, overrides, G4, plane, units, tool length offset, coordinate system, path
control, distance modes, retract mode, the gcode-canon transforms, and the stops and program end
(``convert_stop``). Tools and spindle are in :mod:`gcode_canon.tool_steps`, motion in
:mod:`gcode_canon.motion_steps`. A mixin of :class:`gcode_canon.interpreter.Interpreter`."""

from __future__ import annotations

import logging

from gcode_canon import transforms
from gcode_canon.codes import G5X_INDEX, PLANE_BY_CODE
from gcode_canon.commands import (
    AnalogOutput,
    Comment,
    Coolant,
    DigitalOutput,
    Dwell,
    FeedMode,
    InputKind,
    Message,
    MotionControlMode,
    PalletShuttle,
    Plane,
    Pose,
    ProgramEnd,
    ProgramStop,
    SelectPlane,
    SetFeedMode,
    SetFeedRate,
    SetG5xOffset,
    SetMotionControlMode,
    SetOverrides,
    SetSpindleMode,
    SpindleOff,
    UseLengthUnits,
    UserMCode,
    UseToolLengthOffset,
    WaitInput,
    WaitMode,
)
from gcode_canon.errors import GCodeError
from gcode_canon.lexer import AXIS_LETTERS, Block
from gcode_canon.machine import Resume
from gcode_canon.messages import classify, expand
from gcode_canon.modal import ModalLine
from gcode_canon.offsets import N_AXES, ROTARY_INDEXES

log = logging.getLogger(__name__)

_FEED_MODES = {930: FeedMode.INVERSE_TIME, 940: FeedMode.UNITS_PER_MINUTE, 950: FeedMode.UNITS_PER_REV}

class ModeStepsMixin:
    """Modal groups other than motion, tools and spindle (module docstring)."""

    def _set_feed(self, rate: float) -> None:
        if rate != self.feed:
            self.feed = rate
            self._emit(SetFeedRate(rate, file=self.file, line=self.line))

    # --- steps, in LinuxCNC's order of execution --------------------------------------------------

    def _step_comment(self, block: Block, ml: ModalLine) -> None:
        if not block.comments:
            return
        keyword, text = classify(block.comments[-1])
        f, n = self.file, self.line
        if keyword == "":
            self._emit(Comment(text, file=f, line=n))
        elif keyword == "msg":
            self._emit(Message(text, file=f, line=n))
        elif keyword == "debug":
            if self.params.numbered[5599] != 0.0:
                self._emit(Message(expand(text, self.params), debug=True, file=f, line=n))
        elif keyword == "print":
            self.machine.print_text(expand(text, self.params))
        elif keyword == "logopen":
            self.logs.open(text, append=False)
        elif keyword == "logappend":
            self.logs.open(text, append=True)
        elif keyword == "logclose":
            self.logs.close()
        elif keyword == "log":
            self.logs.write(expand(text, self.params))
        elif keyword == "probeopen":
            self.probe_log.open(text, append=False)
        elif keyword == "probeclose":
            self.probe_log.close()
        elif keyword == "abort":  # LinuxCNC: the program stops with the (expanded) text as its error
            raise GCodeError(expand(text, self.params).strip() or "(ABORT) in the program")

    def _step_feed_mode(self, block: Block, ml: ModalLine) -> None:
        code = ml.g.get(5)
        if code is None:
            return
        mode = _FEED_MODES[code]
        if mode is not self.feed_mode:
            was_inverse = self.feed_mode is FeedMode.INVERSE_TIME
            self.feed_mode = mode
            self._emit(SetFeedMode(mode, file=self.file, line=self.line))
            if was_inverse or mode is FeedMode.INVERSE_TIME:
                self._set_feed(0.0)  # a rate in the other meaning must not carry over

    def _step_feed(self, block: Block, ml: ModalLine) -> None:
        value = block.take("f")
        if value is None:
            return
        if value < 0.0:
            raise GCodeError(f"Negative F word used: F{value:g}")
        if self.feed_mode is FeedMode.INVERSE_TIME:
            self.feed = value  # every inverse-time move states its own rate: always emitted
            self._emit(SetFeedRate(value, file=self.file, line=self.line))
        else:
            self._set_feed(value * self.scale)

    def _step_io(self, block: Block, ml: ModalLine) -> None:
        code = ml.m.get(5)
        if code is None:
            return
        f, n = self.file, self.line
        if code in (62, 63, 64, 65):
            index = self._int_word(block, "p", f"M{code}")
            if index is None:
                raise GCodeError(f"M{code} needs a P word (the output number)")
            self._emit(DigitalOutput(index, code in (62, 64), code in (62, 63), file=f, line=n))
        elif code in (67, 68):
            index = self._int_word(block, "e", f"M{code}")
            value = block.take("q")
            if index is None or value is None:
                raise GCodeError(f"M{code} needs an E word (output number) and a Q word (value)")
            self._emit(AnalogOutput(index, value, code == 67, file=f, line=n))
        else:
            self._m66(block)

    def _m66(self, block: Block) -> None:
        p = self._int_word(block, "p", "M66")
        e = self._int_word(block, "e", "M66")
        if (p is None) == (e is None):
            raise GCodeError("M66 needs exactly one of P (digital input) or E (analog input)")
        mode_n = self._int_word(block, "l", "M66") or 0
        if mode_n > 4:
            raise GCodeError(f"M66 L{mode_n}: wait modes are L0 to L4")
        timeout = block.take("q")
        if e is not None and mode_n != 0:
            raise GCodeError("M66 with an analog input (E) allows only L0 (immediate)")
        if mode_n != 0 and timeout is None:
            raise GCodeError(f"M66 L{mode_n} needs a Q word (timeout in seconds)")
        if timeout is not None and timeout < 0:
            raise GCodeError("M66 Q (timeout) must not be negative")
        cmd = WaitInput(InputKind.DIGITAL if p is not None else InputKind.ANALOG,
                        p if p is not None else e, WaitMode(mode_n), timeout or 0.0,
                        file=self.file, line=self.line)
        self._emit(cmd)

        def answer() -> None:
            value = float(self.machine.wait_input(cmd))
            self.params.set_system(5399, value)

        self._emit(Resume(answer))

    def _step_overrides(self, block: Block, ml: ModalLine) -> None:
        code = ml.m.get(9)
        if code is None:
            return
        if code in (48, 49):
            on = code == 48
            self.overrides["feed"] = self.overrides["spindle"] = on
            self._emit(SetOverrides(feed=on, spindle=on, file=self.file, line=self.line))
            return
        p = block.take("p")
        on = True if p is None else p != 0.0
        key = {50: "feed", 51: "spindle", 52: "adaptive_feed", 53: "feed_hold"}[code]
        self.overrides[key] = on
        self._emit(SetOverrides(**{key: on}, file=self.file, line=self.line))

    def _step_user_mcode(self, block: Block, ml: ModalLine) -> None:
        """M100-M199 the machine binds (sort_codes refused the others): a sync point with P and Q."""
        code = ml.m.get(10)
        if code is not None:
            self._emit(UserMCode(code, block.take("p"), block.take("q"), file=self.file, line=self.line))

    def _step_dwell(self, block: Block, ml: ModalLine) -> None:
        if ml.g.get(0) != 40:
            return
        p = block.take("p")
        if p is None:
            raise GCodeError("Dwell time P word missing with G4")
        if p < 0:
            raise GCodeError(f"Negative dwell time with G4: P{p:g}")
        self._emit(Dwell(p, file=self.file, line=self.line))

    def _step_plane(self, block: Block, ml: ModalLine) -> None:
        code = ml.g.get(2)
        if code is None:
            return
        plane = PLANE_BY_CODE[code]
        if plane is not self.plane:
            self.plane = plane
            self.xform = self.xform.with_plane(plane)
            self._emit(SelectPlane(plane, file=self.file, line=self.line))

    def _step_units(self, block: Block, ml: ModalLine) -> None:
        code = ml.g.get(6)
        if code is None:
            return
        inch = code == 200
        if inch != self.inch:
            self.inch = inch
            self._emit(UseLengthUnits(not inch, file=self.file, line=self.line))

    def _step_tool_length(self, block: Block, ml: ModalLine) -> None:
        code = ml.g.get(8)
        if code is None:
            return
        self._apply_tool_length(code, block)

    def _apply_tool_length(self, code: int, block: Block | None) -> None:
        offset = [0.0] * N_AXES
        if code == 430:
            h = self._int_word(block, "h", "G43") if block is not None else None
            number = self.current_tool if h is None else h
            tool = self._tool(number)
            if tool is not None:
                offset = [float(v) for v in tool.offset]
        elif code == 431:
            # LinuxCNC convert_tool_length_offset: axes not given keep their current offset
            assert block is not None
            offset = list(self.frames.tool)
            for k, letter in enumerate(AXIS_LETTERS):
                value = block.take(letter)
                if value is not None:
                    offset[k] = value if k in ROTARY_INDEXES else value * self.scale
        elif code == 432:
            # G43.2: adds tool H's offsets, or the axis words, to the offsets in force
            assert block is not None
            offset = list(self.frames.tool)
            given = [k for k, letter in enumerate(AXIS_LETTERS) if letter in block.words]
            h = self._int_word(block, "h", "G43.2")
            if h is not None and given:
                raise GCodeError("G43.2: Can not have both H and axis words")
            if h is None and not given:
                raise GCodeError("G43.2: No axes specified and H word missing")
            if h is not None:
                tool = self._tool(h)
                if tool is not None:
                    offset = [a + float(b) for a, b in zip(offset, tool.offset, strict=True)]
            for k in given:
                value = block.take(AXIS_LETTERS[k])
                assert value is not None
                offset[k] += value if k in ROTARY_INDEXES else value * self.scale
        self.tool_length_mode = code
        self.frames.tool = offset
        self._offsets_changed()
        self._emit(UseToolLengthOffset(Pose(*offset), file=self.file, line=self.line))

    def _select_system(self, index: int) -> None:
        self.params.set_system(5220, float(index))
        self.frames.load_system(self.params, index)
        self._offsets_changed()
        self._emit(SetG5xOffset(index, Pose(*self.frames.g5x), self.frames.rotation,
                                file=self.file, line=self.line))

    def _step_coord_system(self, block: Block, ml: ModalLine) -> None:
        code = ml.g.get(12)
        if code is None:
            return
        index = G5X_INDEX[code]
        if index != self.frames.g5x_index:
            self._select_system(index)

    def _step_path_control(self, block: Block, ml: ModalLine) -> None:
        code = ml.g.get(13)
        if code is None:
            return
        if code == 640:
            p = block.take("p")
            q = block.take("q")
            if q is not None and p is None:
                raise GCodeError("G64 Q (naive CAM tolerance) needs a P word too")
            if (p is not None and p < 0) or (q is not None and q < 0):
                raise GCodeError("G64 P and Q must not be negative")
            control = (MotionControlMode.CONTINUOUS, (p or 0.0) * self.scale, (q or 0.0) * self.scale)
            r = block.take("r")
            if r is not None:
                # LinuxCNC master (convert_control_mode, G64_R_PLANNER): R <= 0 trapezoidal, else the
                # smooth planner with its peak scale clamped to 0.1..1; the path tolerances as P/Q
                planner, peak = (0, -1.0) if r <= 0.0 else (1, min(1.0, max(0.1, r)))
                self.control = control
                self._emit(SetMotionControlMode(*control, planner, peak, file=self.file, line=self.line))
                return
        elif code == 610:
            control = (MotionControlMode.EXACT_PATH, 0.0, 0.0)
        else:
            control = (MotionControlMode.EXACT_STOP_MODAL, 0.0, 0.0)
        if control != self.control:
            self.control = control
            self._emit(SetMotionControlMode(*control, file=self.file, line=self.line))

    def _step_distance(self, block: Block, ml: ModalLine) -> None:
        code = ml.g.get(3)
        if code is not None:
            self.absolute = code == 900
        code = ml.g.get(4)
        if code is not None:
            self.ijk_absolute = code == 901

    def _step_retract(self, block: Block, ml: ModalLine) -> None:
        code = ml.g.get(10)
        if code is not None:
            self.retract = code

    def _step_transforms(self, block: Block, ml: ModalLine) -> None:
        """:mod:`gcode_canon.transforms` holds the geometry; :mod:`gcode_canon.dialect` the meaning."""
        g = ml.g
        code = g.get(16)
        if code is not None:
            if code == 150:
                self.polar_on = False
            else:
                from gcode_canon.dialect import Action, resolve

                self.polar_on = True
                self.polar = transforms.PolarState()
                action = resolve("G16", self.dialect).action
                self.polar_origin = (transforms.PolarOrigin.CURRENT if action is Action.POLAR_ON_CURRENT
                                     else transforms.PolarOrigin.FANUC)
        mirror, scale, rotate = g.get(19), g.get(17), g.get(18)
        if mirror is None and scale is None and rotate is None:
            return
        if self.comp is not None:
            raise GCodeError("Cannot change G22/G51/G68 transforms with cutter radius compensation on")
        old = self.xform
        new = old
        w = block.words
        centre = self._target(block, polar=False)  # words resolved like a move's target (G90/G91)
        if mirror == 220:
            given = {AXIS_LETTERS[k]: centre[k] for k in range(N_AXES) if AXIS_LETTERS[k] in w}
            if not given:
                raise GCodeError("G22 needs the axis words of the mirror lines (e.g. G22 X10)")
            new = new.with_mirror(given)
        elif mirror == 230:
            letters = [a for a in AXIS_LETTERS if a in w]
            new = new.cancel_mirror(letters or None)
        if scale == 510:
            if "p" in w:
                factors: float | dict[str, float] = w["p"]
            else:
                factors = {a: w[i] for a, i in (("x", "i"), ("y", "j"), ("z", "k")) if i in w}
                if not factors:
                    raise GCodeError("G51 needs P (one factor) or I J K (factors for X Y Z)")
            new = new.with_scale(centre, factors)
        elif scale == 500:
            new = new.cancel_scale()
        if rotate == 680:
            first, second, _ = self.plane.value
            new = new.with_rotation((centre[first], centre[second]), w.get("r", 0.0))
        elif rotate == 690:
            new = new.cancel_rotation()
        machine_prog = old.apply_position(self.prog)
        self.xform = new
        self.xform_on = not new.identity
        self.prog = list(new.invert_position(machine_prog))
        if scale is not None:
            self.scale_code = scale
        if rotate is not None:
            self.rotation_code = rotate

    def _step_stop(self, block: Block, ml: ModalLine) -> None:
        code = ml.m.get(4)
        if code is None:
            return
        f, n = self.file, self.line
        if code in (0, 1):
            self._emit(ProgramStop(code == 1, file=f, line=n))
            self._emit(Resume(self._resync))
        elif code == 60:
            self._emit(PalletShuttle(file=f, line=n))
            self._emit(Resume(self._resync))
        elif code == 98:
            p = self._int_word(block, "p", "M98")
            if p is None:
                raise GCodeError("M98 needs a P word (the program number to call)")
            repeats = self._int_word(block, "l", "M98")
            self.flow.m98(p, 1 if repeats is None else repeats)
        elif code == 99:
            if not self.flow.m99():
                self._end_program(2)  # M99 in the main program ends it (stand-alone interpreter)
        else:
            self._end_program(code)

    def _end_program(self, code: int | None) -> None:
        """M2/M30 (code) or a closing % (None): LinuxCNC's resets (G54, G17, G90, G94 with feed 0,
        overrides on, spindle and coolant off, motion mode G1; G92 offsets persist), then PROGRAM_END,
        then the parameter file is written."""
        f, n = self.file, self.line
        self._comp_off()
        self._after_comp = False
        if code is not None:
            if self.frames.g5x_index != 1:
                self._select_system(1)
            if self.plane is not Plane.XY:
                self.plane = Plane.XY
                self._emit(SelectPlane(Plane.XY, file=f, line=n))
            self.absolute = True
            if self.feed_mode is not FeedMode.UNITS_PER_MINUTE:
                self.feed_mode = FeedMode.UNITS_PER_MINUTE
                self._emit(SetFeedMode(self.feed_mode, file=f, line=n))
            self._set_feed(0.0)
            if not (self.overrides["feed"] and self.overrides["spindle"]):
                self.overrides["feed"] = self.overrides["spindle"] = True
                self._emit(SetOverrides(feed=True, spindle=True, file=f, line=n))
            if self.spindle is not None:
                self.spindle = None
                self._emit(SpindleOff(file=f, line=n))
            if self.mist or self.flood:
                self.mist = self.flood = False
                self._emit(Coolant(False, False, file=f, line=n))
            if self.settings.disable_g92_persistence:  # LinuxCNC convert_stop step 10
                for k in range(5210, 5220):
                    self.params.set_system(k, 0.0)
                if any(self.frames.g92):
                    self._set_g92([0.0] * N_AXES)
            self.motion = 10
            self._spline_reset()  # LinuxCNC convert_stop: nurbs_reset_global_variables
            if self.css_max:  # LinuxCNC convert_stop: SET_SPINDLE_MODE(s, 0)
                self.css_max = 0.0
                self._emit(SetSpindleMode(0.0, file=f, line=n))
            self.scale_code, self.rotation_code = 500, 690
            if self.xform_on or self.polar_on:  # Fanuc cancels these on reset
                self.xform = self.xform.cancel_all()
                self.xform_on = False
                self.polar_on = False
                self.prog = self.frames.machine_to_program(self.pos)
        self._emit(ProgramEnd(code == 30, file=f, line=n))
        self.ended = True
        self._fast_ok = False
        self.logs.close()
        self.probe_log.close()
        try:
            self._write_var_file()
        except GCodeError as exc:
            # the program itself ran: a full disk is no error at the M2 line. The values stay in memory,
            # the next program end and shutdown() try again; the caller reports save_error.
            log.error("%s (the values are kept in memory and saved at the next program end)", exc)

