"""Tool and spindle steps of a line: S, T, M6/M61 (with the tool parameters #5400-#5413), M3/M4/M5,
M19 and coolant M7/M8/M9, as LinuxCNC's ``convert_speed``, ``convert_tool_select``,
``convert_tool_change``, ``convert_spindle_mode`` and ``convert_coolant`` do. A mixin of
:class:`gcode_canon.interpreter.Interpreter`."""

from __future__ import annotations

from gcode_canon.commands import (
    Coolant,
    Pose,
    SelectTool,
    SetSpindleMode,
    SetSpindleSpeed,
    SetToolNumber,
    SpindleDirection,
    SpindleOff,
    SpindleOn,
    SpindleOrient,
    ToolChange,
)
from gcode_canon.errors import GCodeError
from gcode_canon.expressions import near_int
from gcode_canon.lexer import Block
from gcode_canon.machine import Resume
from gcode_canon.modal import ModalLine
from gcode_canon.offsets import N_AXES


class ToolSpindleMixin:
    """S T M6 M61 M3 M4 M5 M19 M7 M8 M9 (module docstring)."""

    def _step_spindle_mode(self, block: Block, ml: ModalLine) -> None:
        """G96 D (constant surface speed, D the highest rpm) and G97: LinuxCNC's
        ``convert_spindle_mode``, the first step of a line after its comment."""
        code = ml.g.get(14)
        if code == 970:
            self.css_max = 0.0
            self._emit(SetSpindleMode(0.0, file=self.file, line=self.line))
        elif code == 960:
            if "s" not in block.words:
                raise GCodeError("S word missing with G96")
            d = block.take("d")
            self.css_max = abs(d) if d is not None else 1e30
            # the line's S word comes next (_step_speed): it issues the mode with its surface speed

    def _css_mode(self) -> SetSpindleMode:
        """The G96 state as a command: the surface speed in mm/min, the X where the radius is 0."""
        f = self.frames
        surface = self.speed * (304.8 if self.inch else 1000.0)
        return SetSpindleMode(self.css_max, surface, f.g5x[0] + f.g92[0] + f.tool[0], file=self.file,
                              line=self.line)

    def _step_speed(self, block: Block, ml: ModalLine) -> None:
        value = block.take("s")
        if value is None:
            return
        if value < 0.0:
            raise GCodeError(f"Negative spindle speed used: S{value:g}")
        self.speed = value
        if self.css_max:
            self._emit(self._css_mode())
        self._emit(SetSpindleSpeed(value, file=self.file, line=self.line))

    def _tool(self, number: int):
        if number == 0 or self.tool_table is None:
            return None
        tool = self.tool_table.get(number)
        if tool is None and self._implicit_table:
            return None
        if tool is None:
            raise GCodeError(f"Tool {number} is not in the tool table")
        return tool

    def _step_select_tool(self, block: Block, ml: ModalLine) -> None:
        number = self._int_word(block, "t", "a tool selection")
        if number is None:
            return
        tool = self._tool(number)
        self.selected_tool = number
        self.selected_pocket = tool.pocket if tool is not None else number
        self._emit(SelectTool(number, file=self.file, line=self.line))

    def _set_tool_parameters(self, number: int) -> None:
        tool = self._tool(number) if number else None
        self.params.set_system(5400, float(number))
        offset = list(tool.offset) if tool is not None else [0.0] * N_AXES
        for k in range(N_AXES):
            self.params.set_system(5401 + k, offset[k])
        values = (0, 0, 0, 0)
        if tool is not None:
            values = (tool.diameter, tool.front_angle, tool.back_angle, tool.orientation)
        for k, v in enumerate(values):
            self.params.set_system(5410 + k, float(v))
        self.current_pocket = tool.pocket if tool is not None else number

    def _step_tool_change(self, block: Block, ml: ModalLine) -> None:
        code = ml.m.get(6)
        if code is None:
            return
        if code == 6:
            if self.selected_tool < 0:
                raise GCodeError("M6 with no tool selected (give a T word first)")
            number = self.selected_tool
            if not self.settings.tool_change_with_spindle_on and self.spindle is not None:
                # LinuxCNC convert_tool_change: STOP_SPINDLE_TURNING first (a later G84 must not tap
                # with a spindle it believes is turning)
                self.spindle = None
                self._emit(SpindleOff(file=self.file, line=self.line))
            self._emit(ToolChange(number, file=self.file, line=self.line))
            self._emit(Resume(self._refresh_position))
        else:
            q = block.take("q")
            if q is None:
                raise GCodeError("M61 needs a Q word (the tool number)")
            number = near_int(q, "Q word of M61")
            if number < 0:
                raise GCodeError(f"M61 Q{number}: negative tool number")
            self._tool(number)
            self._emit(SetToolNumber(number, file=self.file, line=self.line))
            self._emit(Resume(self._refresh_position))
        self.current_tool = number
        self._set_tool_parameters(number)

    def _refresh_position(self) -> None:
        """After M6 / M61 (LinuxCNC's toolchange_flag, refresh_actual_position): the program position
        is read back from where the machine is, or was last sent, even when it is not the programmed
        point (after G40 the tool stays on the compensated path until the next move)."""
        where = self.machine.current_position()
        if where is not None:
            self.pos = Pose(*where)
        self.prog = self._from_machine(self.pos)

    def _step_spindle(self, block: Block, ml: ModalLine) -> None:
        code = ml.m.get(7)
        if code is None or code >= 70:
            return
        if code == 5:
            self.spindle = None
            self._emit(SpindleOff(file=self.file, line=self.line))
            return
        if code == 19:
            # M19 R Q P: the spindle stops at R degrees (the words were checked in _check_words).
            # *canon*: a bare M19 orients to 0 degrees, as the manual's defaults read; LinuxCNC master
            # emits no ORIENT_SPINDLE without R or P (only marks the spindle stopped). M19 takes no
            # ORIENT_OFFSET: canon has no such setting.
            w = block.words
            self.spindle = None
            self._emit(SpindleOrient(w.get("r", 0.0), round(w.get("p", 0.0)), w.get("q", 0.0),
                                     file=self.file, line=self.line))
            return
        self.spindle = SpindleDirection.CW if code == 3 else SpindleDirection.CCW
        self._emit(SpindleOn(self.spindle, self.speed, file=self.file, line=self.line))

    def _step_coolant(self, block: Block, ml: ModalLine) -> None:
        codes = [c for c in block.m if c in (7, 8, 9)]
        if not codes:
            return
        for code in codes:
            if code == 7:
                self.mist = True
            elif code == 8:
                self.flood = True
            else:
                self.mist = self.flood = False
        self._emit(Coolant(self.mist, self.flood, file=self.file, line=self.line))

