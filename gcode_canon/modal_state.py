"""M70-M73: saving and restoring the modal state, one saved state per call level, as LinuxCNC's
``save_settings`` / ``restore_settings`` / ``leave_context``. A mixin of
:class:`gcode_canon.interpreter.Interpreter` (its state is the interpreter's)."""

from __future__ import annotations

from gcode_canon.arcs import MM_PER_INCH
from gcode_canon.commands import (
    Coolant,
    FeedMode,
    SelectPlane,
    SetFeedMode,
    SetMotionControlMode,
    SetOverrides,
    SetSpindleSpeed,
    SpindleOff,
    SpindleOn,
    UseLengthUnits,
)
from gcode_canon.errors import GCodeError
from gcode_canon.lexer import Block
from gcode_canon.modal import ModalLine
from gcode_canon.offsets import N_AXES


class ModalStateMixin:
    """M70 save, M71 invalidate, M72 restore, M73 save and restore at return (module docstring)."""

    def _modal_snapshot(self) -> dict:
        return {
            "inch": self.inch, "absolute": self.absolute, "ijk_absolute": self.ijk_absolute,
            "feed_mode": self.feed_mode, "plane": self.plane, "control": self.control,
            "g5x": self.frames.g5x_index, "feed": self.feed, "speed": self.speed,
            "spindle": self.spindle, "mist": self.mist, "flood": self.flood,
            "overrides": dict(self.overrides), "retract": self.retract,
            "tool_length_mode": self.tool_length_mode, "g92_applied": self.params.numbered[5210] != 0.0,
            "comp_code": self.comp_code,
        }

    def _step_state(self, block: Block, ml: ModalLine) -> None:
        """M70-M73: LinuxCNC keeps one saved state per call level (its sub_context); M73's is restored
        when that level's subroutine returns (LinuxCNC leave_context); M73 in the main program only
        saves (LinuxCNC warns and stores it)."""
        code = ml.m.get(7)
        if code is None or code < 70:
            return
        level = len(self.flow.frames)
        if code in (70, 73):
            self.saved_states[level] = (self._modal_snapshot(), code == 73 and level > 0)
        elif code == 71:
            self.saved_states.pop(level, None)
        else:
            saved = self.saved_states.get(level)
            if saved is None:
                raise GCodeError("M72: no saved modal state to restore (M70 first)")
            self._restore(saved[0])

    def leave_call_level(self, level: int) -> None:
        """A subroutine of call level ``level`` returned: its M73 state comes back."""
        saved = self.saved_states.pop(level, None)
        if saved is not None and saved[1]:
            self._restore(saved[0])

    def _restore(self, s: dict) -> None:
        """What LinuxCNC's restore_settings puts back: units first, then F (in the restored units, to
        one decimal, as its gen_settings writes "F%.1f") and S, the modal groups that differ
        (plane, G40, distance, feed mode, G5x, G43/G49, retract mode, arc distance, G92.2/G92.3,
        path control) and the spindle, coolant and override M codes."""
        f, n = self.file, self.line
        if s["inch"] != self.inch:
            self.inch = s["inch"]
            self.scale = MM_PER_INCH if self.inch else 1.0
            self._emit(UseLengthUnits(not self.inch, file=f, line=n))
        self.absolute = s["absolute"]
        self.ijk_absolute = s["ijk_absolute"]
        self.retract = s["retract"]
        if s["feed_mode"] is not self.feed_mode:
            self.feed_mode = s["feed_mode"]
            self._emit(SetFeedMode(self.feed_mode, file=f, line=n))
        if s["plane"] is not self.plane:
            self.plane = s["plane"]
            self.xform = self.xform.with_plane(self.plane)
            self._emit(SelectPlane(self.plane, file=f, line=n))
        if s["comp_code"] == 400 and self.comp is not None:
            self._comp_off()
        if s["control"] != self.control:
            self.control = s["control"]
            self._emit(SetMotionControlMode(*self.control, file=f, line=n))
        if s["g5x"] != self.frames.g5x_index:
            self._select_system(s["g5x"])
        if s["tool_length_mode"] != self.tool_length_mode and s["tool_length_mode"] in (430, 490):
            self._apply_tool_length(s["tool_length_mode"], None)
        if s["g92_applied"] != (self.params.numbered[5210] != 0.0):
            if s["g92_applied"]:
                self.params.set_system(5210, 1.0)
                self._set_g92([self.params.numbered[5211 + k] for k in range(N_AXES)])
            else:
                self.params.set_system(5210, 0.0)
                self._set_g92([0.0] * N_AXES)
        feed = s["feed"]
        if self.feed_mode is not FeedMode.INVERSE_TIME:
            feed = float(f"{feed / self.scale:.1f}") * self.scale
        self._set_feed(feed)
        speed = float(f"{s['speed']:.0f}")
        if speed != self.speed:
            self.speed = speed
            self._emit(SetSpindleSpeed(self.speed, file=f, line=n))
        if s["spindle"] is not self.spindle:
            self.spindle = s["spindle"]
            if self.spindle is None:
                self._emit(SpindleOff(file=f, line=n))
            else:
                self._emit(SpindleOn(self.spindle, self.speed, file=f, line=n))
        if (s["mist"], s["flood"]) != (self.mist, self.flood):
            self.mist, self.flood = s["mist"], s["flood"]
            self._emit(Coolant(self.mist, self.flood, file=f, line=n))
        if s["overrides"] != self.overrides:
            self.overrides = dict(s["overrides"])
            self._emit(SetOverrides(**self.overrides, file=f, line=n))
