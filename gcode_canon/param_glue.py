"""The interpreter's parameters as programs see them: the predefined named parameters (``#<_x>``,
``#<_metric>`` ... LinuxCNC's ``interp_namedparams.cc``), the position parameters #5021-#5029 and
#5420-#5428, reading one from outside (``Interpreter.parameter``), and the parameter file's load at
start and save at program end. A mixin of :class:`gcode_canon.interpreter.Interpreter`."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from gcode_canon.codes import CODE_BY_PLANE, G5X_CODES
from gcode_canon.commands import AXES, FeedMode, SpindleDirection
from gcode_canon.errors import GCodeError
from gcode_canon.machine import DryRunMachine
from gcode_canon.offsets import N_AXES, ROTARY_INDEXES

_PERSISTENT_FALLBACK = range(5161, 5391)

class ParamGlueMixin:
    """Predefined parameters and the parameter file (module docstring)."""

    def _load_var_file(self) -> None:
        path = self.settings.var_file
        if path is not None and Path(path).exists():
            from gcode_canon import paramfile

            values = paramfile.read_parameter_file(path)
            if self.settings.disable_g92_persistence:  # LinuxCNC init: those read are cleared
                values = {k: (0.0 if 5210 <= k <= 5219 else v) for k, v in values.items()}
            self.params.load(values)
            self._persist_keys.update(values)
        index = round(self.params.numbered[5220])
        if not 1 <= index <= 9:
            index = 1
        self.params.set_system(5220, float(index))
        self.frames.load_system(self.params, index)
        if self.params.numbered[5210] == 1.0:
            self.frames.g92 = [self.params.numbered[5211 + k] for k in range(N_AXES)]
            self.frames.refresh()
        self.pos = self.frames.to_machine(self.prog)
        self.prog = self.frames.machine_to_program(self.pos)


    def _install_predefined(self) -> None:
        p = self.params.predefined
        b = float

        def axis_getter(k: int) -> Callable[[], float]:
            return lambda: self.prog[k] / (1.0 if k in ROTARY_INDEXES else self.scale)

        def numbered_axis_getter(k: int) -> Callable[[], float]:
            def get() -> float:
                if self.comp is not None:  # LinuxCNC read_parameter (interp_read.cc); not #<_x>
                    raise GCodeError("Cannot read current position with cutter radius compensation on")
                return self.prog[k] / (1.0 if k in ROTARY_INDEXES else self.scale)
            return get

        def abs_getter(k: int) -> Callable[[], float]:
            # LinuxCNC get_abs_position (interp_convert.cc): the machine (G53) position, tool length
            # offset included, in program units; here after the G22/G51/G68 transforms too.
            return lambda: self.pos[k] / (1.0 if k in ROTARY_INDEXES else self.scale)

        for k, name in enumerate(AXES):
            p[f"_{name}"] = axis_getter(k)
            self.params.dynamic_numbered[5420 + k] = numbered_axis_getter(k)
            p[f"_abs_{name}"] = abs_getter(k)
            self.params.dynamic_numbered[5021 + k] = abs_getter(k)
        p.update({
            "_vmajor": lambda: 2.9,
            "_vminor": lambda: 0.0,
            "_metric_machine": lambda: 1.0,  # lengths are kept in mm: a metric machine
            "_line": lambda: b(self.line),
            "_motion_mode": lambda: b(self.motion),
            "_plane": lambda: b(CODE_BY_PLANE[self.plane]),
            "_ccomp": lambda: b(self.comp_code),
            "_metric": lambda: b(not self.inch),
            "_imperial": lambda: b(self.inch),
            "_absolute": lambda: b(self.absolute),
            "_incremental": lambda: b(not self.absolute),
            "_inverse_time": lambda: b(self.feed_mode is FeedMode.INVERSE_TIME),
            "_units_per_minute": lambda: b(self.feed_mode is FeedMode.UNITS_PER_MINUTE),
            "_units_per_rev": lambda: b(self.feed_mode is FeedMode.UNITS_PER_REV),
            "_coord_system": lambda: b(G5X_CODES[self.frames.g5x_index]),  # 540 ... 593
            # LinuxCNC's lookup_named_param: 1 when the applied tool offset is not zero (G43 of a
            # zero-length tool reads 0), and R_PLANE is G99, OLD_Z G98 (its manual has these two
            # the other way round; the code is what programs see).
            "_tool_offset": lambda: b(any(v != 0.0 for v in self.frames.tool)),
            "_retract_r_plane": lambda: b(self.retract == 990),
            "_retract_old_z": lambda: b(self.retract == 980),
            "_spindle_rpm_mode": lambda: b(not self.css_max),
            "_spindle_css_mode": lambda: b(bool(self.css_max)),
            "_ijk_absolute_mode": lambda: b(self.ijk_absolute),
            "_lathe_diameter_mode": lambda: b(self.diameter_mode),
            "_lathe_radius_mode": lambda: b(not self.diameter_mode),  # LinuxCNC: 1 in G8
            "_spindle_on": lambda: b(self.spindle is not None),
            "_spindle_cw": lambda: b(self.spindle is SpindleDirection.CW),
            "_mist": lambda: b(self.mist),
            "_flood": lambda: b(self.flood),
            "_speed_override": lambda: b(self.overrides["spindle"]),
            "_feed_override": lambda: b(self.overrides["feed"]),
            "_adaptive_feed": lambda: b(self.overrides["adaptive_feed"]),
            "_feed_hold": lambda: b(self.overrides["feed_hold"]),
            "_feed": lambda: self._feed_in_program_units(),
            "_rpm": lambda: self.speed,
            "_current_tool": lambda: b(self.current_tool),
            "_current_pocket": lambda: b(self.current_pocket),
            "_selected_tool": lambda: b(self.selected_tool),
            "_selected_pocket": lambda: b(self.selected_pocket),
            "_value": lambda: self.flow.value,
            "_value_returned": lambda: b(self.flow.value_returned),
            "_task": lambda: b(not isinstance(self.machine, DryRunMachine)),
            "_call_level": lambda: b(self.params.call_level),
            "_remap_level": lambda: 0.0,
        })

    def _feed_in_program_units(self) -> float:
        if self.feed_mode is FeedMode.INVERSE_TIME:
            return self.feed
        return self.feed / self.scale

    def parameter(self, key: int | str) -> float:
        """Read a parameter as a program would: ``parameter(5221)`` or ``parameter("_x")``."""
        if isinstance(key, str):
            return self.params.get_named("".join(key.split()).lower().lstrip("#<").rstrip(">"))
        return self.params.get_numbered(key)

    def _write_var_file(self) -> None:
        """Save the parameter file; on failure keep ``save_error`` (naming the file, line 0) and raise it."""
        path = self.settings.var_file
        if path is None or self.settings.dry_run:
            return
        from gcode_canon import paramfile

        keys = set(getattr(paramfile, "PERSISTENT", _PERSISTENT_FALLBACK)) | self._persist_keys
        keys.update(i for i in range(31, 5001) if self.params.numbered[i] != 0.0)
        try:
            paramfile.write_parameter_file(path, self.params.snapshot(keys))
        except GCodeError as exc:
            self.save_error = exc
            raise
        self.save_error = None

