"""The modal state as status displays read it: LinuxCNC's ``write_g_codes`` / ``write_m_codes``
(``interp_write.cc``) as ``active_gcodes()`` / ``active_mcodes()``, the cheap ``modal_key()`` that
says when they may have changed, and the program-frame position. A mixin of
:class:`gcode_canon.interpreter.Interpreter`."""

from __future__ import annotations

from gcode_canon.codes import CODE_BY_PLANE, G5X_NAMES
from gcode_canon.commands import MotionControlMode, Pose, SpindleDirection
from gcode_canon.modal import gname
from gcode_canon.offsets import ROTARY_INDEXES


class StatusMixin:
    """What the status display reads (module docstring)."""

    def program_position(self) -> Pose:
        """The same point in the active program frame and units (what #5420-#5428 read)."""
        return Pose(*(v if k in ROTARY_INDEXES else v / self.scale for k, v in enumerate(self.prog)))

    def active_gcodes(self, *, extensions: bool = True) -> tuple[str, ...]:
        """The modal G codes in force, as strings, for status displays.

        First LinuxCNC's groups, always 13 entries in this order: motion, plane, units, distance,
        arc distance, feed mode, cutter compensation, tool length, canned-cycle return, coordinate
        system, path control, spindle speed mode, lathe diameter mode (LinuxCNC's ``write_g_codes``
        reports these modal groups; its group-0 entry, sequence number and G92.3 flag have no
        place here). Then, with ``extensions`` (default), the state of the gcode-canon transform
        groups in :mod:`gcode_canon.modal` order, each only when the interpreter's dialect accepts
        the code (:func:`gcode_canon.dialect.resolve`): G15/G16 polar, G50/G51 scaling, G68/G69
        rotation, G22/G23 mirroring. LinuxCNC has none of them (``Unknown g code used``), so
        ``extensions=False`` gives exactly LinuxCNC's list.
        """
        codes = [
            gname(self.motion), gname(CODE_BY_PLANE[self.plane]), "G20" if self.inch else "G21",
            "G90" if self.absolute else "G91", "G90.1" if self.ijk_absolute else "G91.1",
            f"G{self.feed_mode.value}", gname(self.comp_code), gname(self.tool_length_mode),
            gname(self.retract), G5X_NAMES[self.frames.g5x_index],
            {MotionControlMode.EXACT_PATH: "G61", MotionControlMode.EXACT_STOP_MODAL: "G61.1"}.get(
                self.control[0], "G64"),
            "G96" if self.css_max else "G97", "G7" if self.diameter_mode else "G8",
        ]
        if extensions:
            codes.extend(self._active_extension_gcodes())
        return tuple(codes)

    def _active_extension_gcodes(self) -> list[str]:
        from gcode_canon.dialect import resolve

        state = (
            ("G16" if self.polar_on else "G15"),
            gname(self.scale_code),
            gname(self.rotation_code),
            ("G22" if self.xform.mirrored else "G23"),  # G23 X cancels only X: G22 while others stay
        )
        return [code for code in state if resolve(code, self.dialect).accepted]

    def active_mcodes(self) -> tuple[str, ...]:
        spindle = {SpindleDirection.CW: "M3", SpindleDirection.CCW: "M4", None: "M5"}[self.spindle]
        coolant = ["M7"] if self.mist else []
        if self.flood:
            coolant.append("M8")
        return (spindle, *(coolant or ["M9"]), "M48" if self.overrides["feed"] and
                self.overrides["spindle"] else "M49")

    def modal_key(self) -> tuple[object, ...]:
        """A cheap value (about a microsecond; ``active_gcodes()`` costs tens) that changes whenever
        ``active_gcodes()``, ``active_mcodes()``, ``feed``, ``speed``, ``current_tool`` or the tool length
        offset may: a consumer that follows the modal state line by line (the daemon's status, which
        shows the state of the block being executed) compares it and rebuilds the codes only then."""
        return (self.motion, self.plane, self.inch, self.absolute, self.ijk_absolute, self.feed_mode,
                self.comp_code, self.tool_length_mode, self.retract, self.frames.g5x_index, self.control[0],
                self.polar_on, self.scale_code, self.rotation_code,
                self.xform.mirrored if self.xform_on else (), self.spindle, self.mist, self.flood,
                self.overrides["feed"], self.overrides["spindle"], self.feed, self.speed, self.current_tool,
                self.params.numbered[5403], self.diameter_mode)

