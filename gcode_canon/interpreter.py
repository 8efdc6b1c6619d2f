"""The RS274/NGC interpreter: lines in, canonical commands out, lazily.

Each line goes through :func:`~gcode_canon.lexer.parse_line` (values evaluated as read), the modal
checks of :mod:`gcode_canon.modal`, then the parameter settings of the line, then ``self.steps``: one
method per item of LinuxCNC's order of execution. A later module (canned cycles, cutter compensation,
o-words) adds or replaces a step instead of rewriting the loop. Group 0 (G10, G28/G30, G52/G92) lives
in :mod:`gcode_canon.group0`, M70-M73 in :mod:`gcode_canon.modal_state` (mixins of the class here).

Plain ``G0``/``G1`` lines of literal X/Y/Z/F words take a fast path (one regular expression, no
Block) while the modal state allows it (G94/G95, no rotation): the bulk of CAM output.

Sync points: a :class:`~gcode_canon.commands.WaitInput`, :class:`~gcode_canon.commands.Probe`, stop
or tool change is yielded first; the machine callback is asked for the answer when the consumer
resumes the generator, before the next line is read. The machine position is also asked for at the
start of every program and MDI line (the machine may have been jogged), so the first move starts from
where the machine really is.

Public API (for the planner, the daemon and ``canon check``):

* ``Interpreter(settings, machine)``; ``run_file(path)`` / ``run_string(text, name)`` return lazy
  iterators of :class:`~gcode_canon.commands.Canon`; ``execute_mdi(line)`` returns a list (its sync
  callbacks are called before it returns); ``shutdown()`` writes the parameter file.
* State, read-only by convention: ``position`` (machine Pose), ``program_position()``,
  ``active_gcodes()``, ``active_mcodes()``, ``file``/``line``, ``current_tool``, ``selected_tool``,
  ``parameter(5221)`` / ``parameter("_x")``, ``params`` (the store), ``frames`` (offsets).
* Errors: only :class:`~gcode_canon.errors.GCodeError`, always with file and line.
* ``before_line``: None, or a function called with no arguments before each line the program's flow
  reads (``file``/``line``/``source``/``flow`` say which; lines passed over by a false ``if``, a
  ``sub`` definition or a ``break`` are not reported); it may raise GCodeError. The daemon's "run
  from line" uses it to find the start line as the program's own control flow reaches it.
* ``modal_key()``: a cheap value that changes whenever the modal state shown by ``active_gcodes()``,
  ``active_mcodes()``, the feed, the speed or the tool does (for following the state line by line).

Decisions a machine builder should know:

* Output positions include every offset, the tool length offset too (machine = rotate(program + G92)
  + G5x + tool); G28/G30/G53 positions are machine positions: the tool offset is not added (G53 G0 Z0
  goes to machine Z0 with G43 in force), and G28.1/G30.1 store the machine position, as LinuxCNC.
* Offsets in the numbered parameters (#5161-#5390) and the tool table are in mm/deg whatever G20/G21
  says (LinuxCNC's "user units" on a millimetre machine); #5061-#5069, #5420-#5428 and the machine
  position #5021-#5029 (``#<_abs_x>`` ...) are in program units.
* Parameter settings on a line take effect after the whole line is read and before it is executed
  (LinuxCNC copies them just before ``execute_block``).
* F is read in the units in force after the line's G20/G21 and kept physically (mm/min): a later
  G20/G21 does not change the feed. SET_FEED_RATE is emitted when the rate changes (LinuxCNC repeats it
  for every F word); in G93 it is emitted for every F.
* Mode commands (SELECT_PLANE, USE_LENGTH_UNITS, SET_G5X_OFFSET ...) are emitted on change only; no
  preamble at start: the planner starts from G17 G21 G90 G94 G54 G64 (P0), motion mode G80.
* O-words (:mod:`gcode_canon.owords`) move the interpreter between places of a lazily read source
  (``LineSource.mark``/``jump``) and between files; the output's ``file``/``line`` is where each
  command really comes from (a subroutine file's own line numbers). Canned cycles
  (:mod:`gcode_canon.cycles`) come out as plain moves and dwells, each block in exact path mode.
* M6 stops the spindle first (setting ``tool_change_with_spindle_on`` keeps it turning); after M6,
  M61 and a probe move the position is read back from the machine (after a probe: where it stopped,
  while #5061-#5069 hold where it tripped). Canned cycles start in G99, as LinuxCNC.
* M2/M30 reset what LinuxCNC's convert_stop resets (G54, G17, G90, G94 with F0, feed/spindle
  overrides on, spindle and coolant off, motion mode G1); G92 offsets and G20/G21 persist.
"""

from __future__ import annotations

import contextlib
import logging
import math
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import ClassVar

from gcode_canon import cutter_comp, cycles, transforms
from gcode_canon.arcs import MM_PER_INCH, centre_ijk, centre_r
from gcode_canon.commands import (
    AXES,
    AnalogOutput,
    ArcFeed,
    Canon,
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
    Probe,
    ProbeMode,
    ProgramEnd,
    ProgramStop,
    SelectPlane,
    SelectTool,
    SetFeedMode,
    SetFeedRate,
    SetG5xOffset,
    SetMotionControlMode,
    SetOverrides,
    SetSpindleSpeed,
    SetToolNumber,
    SpindleDirection,
    SpindleOff,
    SpindleOn,
    SpindleOrient,
    StraightFeed,
    StraightTraverse,
    ToolChange,
    UseLengthUnits,
    UseToolLengthOffset,
    WaitInput,
    WaitMode,
)
from gcode_canon.dialect import GRBL_JUNCTION_DEVIATION_MM, Dialect
from gcode_canon.errors import GCodeError
from gcode_canon.expressions import ExpressionReader, near_int
from gcode_canon.group0 import Group0Mixin
from gcode_canon.lexer import AXIS_LETTERS, FAST_LINE, Block, parse_line
from gcode_canon.machine import DryRunMachine, MachineCallbacks
from gcode_canon.messages import LogFiles, classify, expand
from gcode_canon.modal import G_AXIS_USERS_GROUP0, ModalLine, gname, sort_codes
from gcode_canon.modal_state import ModalStateMixin
from gcode_canon.offsets import N_AXES, ROTARY_INDEXES, Frames
from gcode_canon.owords import FlowControl
from gcode_canon.parameters import Parameters
from gcode_canon.settings import InterpreterSettings
from gcode_canon.source import LineSource
from gcode_canon.spindle_sync import SYNC_MOTIONS, SYNC_WORDS, SpindleSyncMixin, check_sync_block

log = logging.getLogger(__name__)

_PLANE_BY_CODE = {170: Plane.XY, 180: Plane.XZ, 190: Plane.YZ}
_CODE_BY_PLANE = {v: k for k, v in _PLANE_BY_CODE.items()}
_FEED_MODES = {930: FeedMode.INVERSE_TIME, 940: FeedMode.UNITS_PER_MINUTE, 950: FeedMode.UNITS_PER_REV}
_PROBE_MODES = {382: ProbeMode.TOWARD_ERROR, 383: ProbeMode.TOWARD, 384: ProbeMode.AWAY_ERROR,
                385: ProbeMode.AWAY}
_IJK = "ijk"
_PERSISTENT_FALLBACK = range(5161, 5391)
_isfinite = math.isfinite
_new_pose = tuple.__new__
_AXIS_INDEX = {letter: k for k, letter in enumerate(AXIS_LETTERS)}


class _Resume:
    """Placeholder in the output of a line: run ``fn`` when the consumer asks for what follows."""

    __slots__ = ("fn",)

    def __init__(self, fn: Callable[[], None]) -> None:
        self.fn = fn


class Interpreter(ModalStateMixin, Group0Mixin, SpindleSyncMixin):
    """One interpreter, one machine state; run programs one after another (state carries over)."""

    def __init__(self, settings: InterpreterSettings | None = None,
                 machine: MachineCallbacks | None = None) -> None:
        self.settings = settings or InterpreterSettings()
        self.machine: MachineCallbacks = machine if machine is not None else DryRunMachine()
        self.params = Parameters()
        self.params.ini = dict(self.settings.ini_values)
        self.reader = ExpressionReader(self.params, self.settings.max_expression_depth)
        self.frames = Frames()
        self.logs = LogFiles(self.settings.log_dir)
        self.probe_log = LogFiles(self.settings.log_dir)
        self.file = ""
        self.line = 0
        self._out: list[Canon | _Resume] = []
        self.dialect = Dialect.parse(self.settings.dialect) if isinstance(self.settings.dialect, str) \
            else self.settings.dialect
        # LinuxCNC (and Grbl, which has no expressions) compare GT/GE/LT/LE strictly
        self.reader.tolerant_order = self.dialect is Dialect.GCODE_CANON
        self.flow = FlowControl(self)
        self.source: LineSource = LineSource.from_string("", "<none>")
        self.seen_code = False
        self.before_line: Callable[[], None] | None = None
        """Called before each line the flow reads (module docstring); None: nothing."""
        self._persist_keys: set[int] = set()
        self._missing_axes = frozenset(AXIS_LETTERS) - frozenset((self.settings.axes or AXIS_LETTERS).lower())
        self._reset_modes()
        self.save_error: GCodeError | None = None
        """Why the last parameter-file save failed (None: saved, or not tried yet)."""
        self._load_var_file()
        self._load_tool_table()
        self._install_predefined()
        self.steps: list[Callable[[Block, ModalLine], None]] = [
            self._step_comment,
            self._step_feed_mode,
            self._step_feed,
            self._step_speed,
            self._step_select_tool,
            self._step_io,
            self._step_tool_change,
            self._step_spindle,
            self._step_state,
            self._step_coolant,
            self._step_overrides,
            self._step_dwell,
            self._step_plane,
            self._step_units,
            self._step_cutter_comp,
            self._step_tool_length,
            self._step_coord_system,
            self._step_path_control,
            self._step_distance,
            self._step_retract,
            self._step_transforms,
            self._step_group0,
            self._step_motion,
            self._step_stop,
        ]
        """The order of execution (LinuxCNC's list); later modules insert (or remove) their own steps;
        each line runs only the steps its codes and words concern (``_STEP_TRIGGERS``)."""
        self._step_cache: dict[tuple, list[Callable[[Block, ModalLine], None]]] = {}
        self._step_cache_for: list[Callable[[Block, ModalLine], None]] = []
        self._step_cache_len = -1

    # --- set-up -----------------------------------------------------------------------------------

    def _reset_modes(self) -> None:
        self.prog = [0.0] * N_AXES
        self.pos = Pose()
        self.motion: int = 800  # G80: no motion mode until a program sets one
        self.plane = Plane.XY
        self.inch = False
        self.scale = 1.0
        self.absolute = True
        self.ijk_absolute = False
        self.feed_mode = FeedMode.UNITS_PER_MINUTE
        self.feed = 0.0  # mm/min (G94), mm/rev (G95), 1/min (G93)
        self.speed = 0.0
        self.spindle: SpindleDirection | None = None
        self.mist = False
        self.flood = False
        self.overrides = {"feed": True, "spindle": True, "adaptive_feed": False, "feed_hold": True}
        self.control = (MotionControlMode.CONTINUOUS, 0.0, 0.0)
        self.tool_length_mode = 490
        self.retract = 990  # LinuxCNC starts in G99 (interp_setup.cc: RETRACT_MODE::R_PLANE)
        self.current_tool = 0
        self.current_pocket = 0
        self.selected_tool = -1
        self.selected_pocket = -1
        self.saved_states: dict[int, tuple[dict, bool]] = {}  # M70/M73 per call level: (state, M73)
        self.ended = False
        self._fast_ok = True
        self._tail: tuple[float, ...] | None = None
        self.cycle_state = cycles.CycleState()
        self.comp: cutter_comp.CutterCompensator | None = None
        self.xform = transforms.ProgramTransform()
        self.xform_on = False  # not xform.identity, cached: the property is costly on every move
        self.polar_on = False
        self.polar = transforms.PolarState()
        self.polar_origin = transforms.PolarOrigin.FANUC
        self.scale_code = 500  # G50/G51 as programmed (G51 P1 is G51 though it changes nothing)
        self.rotation_code = 690  # G68/G69 as programmed (G68 R0 likewise)
        self.comp_code = 400
        self._after_comp = False  # the first move after G40 must be straight
        self._comp_normal = 0.0

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

    def _load_tool_table(self) -> None:
        self.tool_table = None
        self._implicit_table = False  # no file: every tool exists with zero offsets (G10 may set some)
        if self.settings.tool_table is not None:
            from gcode_canon import tooltable

            self.tool_table = tooltable.read_tool_table(self.settings.tool_table)

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
            "_plane": lambda: b(_CODE_BY_PLANE[self.plane]),
            "_ccomp": lambda: b(self.comp_code),
            "_metric": lambda: b(not self.inch),
            "_imperial": lambda: b(self.inch),
            "_absolute": lambda: b(self.absolute),
            "_incremental": lambda: b(not self.absolute),
            "_inverse_time": lambda: b(self.feed_mode is FeedMode.INVERSE_TIME),
            "_units_per_minute": lambda: b(self.feed_mode is FeedMode.UNITS_PER_MINUTE),
            "_units_per_rev": lambda: b(self.feed_mode is FeedMode.UNITS_PER_REV),
            "_coord_system": lambda: b(_G5X_CODES[self.frames.g5x_index]),  # 540 ... 593
            # LinuxCNC's lookup_named_param: 1 when the applied tool offset is not zero (G43 of a
            # zero-length tool reads 0), and R_PLANE is G99, OLD_Z G98 (its manual has these two
            # the other way round; the code is what programs see).
            "_tool_offset": lambda: b(any(v != 0.0 for v in self.frames.tool)),
            "_retract_r_plane": lambda: b(self.retract == 990),
            "_retract_old_z": lambda: b(self.retract == 980),
            "_spindle_rpm_mode": lambda: 1.0,
            "_spindle_css_mode": lambda: 0.0,
            "_ijk_absolute_mode": lambda: b(self.ijk_absolute),
            "_lathe_diameter_mode": lambda: 0.0,
            "_lathe_radius_mode": lambda: 0.0,
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

    # --- public API ---------------------------------------------------------------------------------

    def run_file(self, path: Path | str) -> Iterator[Canon]:
        """Interpret a program file lazily (the file is read one line at a time)."""
        return self._run_source(lambda: LineSource.from_file(path, self.settings.max_line_length))

    def run_string(self, text: str, name: str = "<string>") -> Iterator[Canon]:
        return self._run_source(lambda: LineSource.from_string(text, name, self.settings.max_line_length))

    def execute_mdi(self, line: str) -> list[Canon]:
        """Execute one MDI line and return its commands. Sync callbacks (M66, probe) are called before
        this returns, i.e. the caller must have executed earlier commands already."""
        self.file, self.line = "<mdi>", 1
        self.ended = False
        self._tail = None
        if len(line) > self.settings.max_line_length:  # as for a program's lines (LineSource)
            raise GCodeError(f"Line too long (more than {self.settings.max_line_length} characters)",
                             "<mdi>", 1)
        mdi = LineSource.from_string(line, "<mdi>", self.settings.max_line_length)
        self.source = mdi
        self.flow.reset(mdi)
        try:
            self._resync()
            out = self._execute_line(line)
            result: list[Canon] = []
            for item in out:
                if isinstance(item, _Resume):
                    item.fn()
                else:
                    result.append(item)
            if self.flow.frames and not self.ended:  # an o-word call: run the subroutine through
                result.extend(self._loop(None, 0))
            if self.flow.blocks:
                b = self.flow.blocks[-1]
                raise GCodeError(f"{b.label} {b.kind}: loops and conditionals need a program, not MDI")
            return result
        except GCodeError as exc:
            self.flow.close_all()
            raise exc.located(self.file, self.line) from None
        except Exception as exc:  # a bug must not take the daemon down without a place
            log.exception("internal error in MDI line")
            raise GCodeError(f"internal error: {exc!r}", self.file, self.line) from exc

    @property
    def position(self) -> Pose:
        """Where the last command leaves the machine (machine coordinates, mm/deg)."""
        return self.pos

    def program_position(self) -> Pose:
        """The same point in the active program frame and units (what #5420-#5428 read)."""
        return Pose(*(v if k in ROTARY_INDEXES else v / self.scale for k, v in enumerate(self.prog)))

    def parameter(self, key: int | str) -> float:
        """Read a parameter as a program would: ``parameter(5221)`` or ``parameter("_x")``."""
        if isinstance(key, str):
            return self.params.get_named("".join(key.split()).lower().lstrip("#<").rstrip(">"))
        return self.params.get_numbered(key)

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
            gname(self.motion), gname(_CODE_BY_PLANE[self.plane]), "G20" if self.inch else "G21",
            "G90" if self.absolute else "G91", "G90.1" if self.ijk_absolute else "G91.1",
            f"G{self.feed_mode.value}", gname(self.comp_code), gname(self.tool_length_mode),
            gname(self.retract), _G5X_NAMES[self.frames.g5x_index],
            {MotionControlMode.EXACT_PATH: "G61", MotionControlMode.EXACT_STOP_MODAL: "G61.1"}.get(
                self.control[0], "G64"),
            "G97", "G8",
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
                self.params.numbered[5403])

    def shutdown(self) -> None:
        """Write the parameter file (unless dry run) and close LOG files."""
        self.logs.close()
        self.probe_log.close()
        self._write_var_file()

    # --- the loop -----------------------------------------------------------------------------------

    def _run_source(self, open_source: Callable[[], LineSource]) -> Iterator[Canon]:
        source = open_source()  # open errors surface at the call, not at first next()
        return self._run(source)

    def _run(self, source: LineSource) -> Iterator[Canon]:
        self.file = source.name
        self.line = 0
        self.ended = False
        self.source = source
        self.flow.reset(source)
        self.seen_code = False
        self._resync()  # the machine may have been jogged or homed since the last program
        self._fast_ok = self.fast_path_allowed()
        if self.dialect is Dialect.GRBL and self.control == (MotionControlMode.CONTINUOUS, 0.0, 0.0):
            # Grbl blends every corner within its junction deviation ($11); a G64 P in the program wins
            self.control = (MotionControlMode.CONTINUOUS, GRBL_JUNCTION_DEVIATION_MM, 0.0)
            yield SetMotionControlMode(*self.control, file=source.name, line=1)
        try:
            yield from self._loop(main=source)
        finally:
            self.flow.close_all()
            source.close()

    def switch_source(self, source: LineSource, file: str | None = None) -> None:
        """Continue reading from ``source`` (an o-word call or return); the loop picks it up."""
        self.source = source
        self.file = file if file is not None else source.name
        self._fast_ok = False  # re-evaluated after the line

    def _loop(self, main: LineSource | None, depth: int = 0) -> Iterator[Canon]:
        """Read and execute lines from ``self.source`` until the program ends (``main``) or, for an
        MDI call, until the call stack is back to ``depth`` frames."""
        fast_match = FAST_LINE.match
        fast = self._fast
        flow = self.flow
        self._tail = None
        settings = self.settings
        percent_open = False
        seen_content = seen_fast = False
        while True:
            source = self.source
            in_main = source is main
            for raw in source:
                self.line = source.line
                if self.before_line is not None:
                    self.before_line()
                if self._fast_ok:
                    m = fast_match(raw)
                    if m is not None:
                        cmds = fast(m)
                        if cmds is not None:
                            seen_content = seen_fast = True
                            yield from cmds
                            continue
                self._tail = None
                stripped = raw.strip()
                if not stripped:
                    continue
                if stripped[0] == "$" and self.dialect is Dialect.GRBL:
                    log.warning("%s:%d: Grbl system command %r skipped (not G-code)", self.file, self.line,
                                stripped)
                    continue
                if stripped == "%":
                    if not in_main:
                        continue
                    if not seen_content:
                        seen_content = True
                        percent_open = True
                        continue
                    self._end_program(None)
                    yield from self._drain()
                    return
                seen_content = True
                if seen_fast:
                    self.seen_code = True
                try:
                    out = self._execute_line(raw)
                except GCodeError as exc:
                    raise exc.located(self.file, self.line) from None
                except RecursionError:
                    raise GCodeError("Expression nested too deeply", self.file, self.line) from None
                except Exception as exc:
                    log.exception("internal error")
                    raise GCodeError(f"internal error: {exc!r}", self.file, self.line) from exc
                for item in out:
                    if type(item) is _Resume:
                        try:
                            item.fn()
                        except GCodeError as exc:
                            raise exc.located(self.file, self.line) from None
                    else:
                        yield item
                if self.ended:
                    return
                if self.source is not source:
                    if main is None and len(flow.frames) <= depth:
                        return
                    break
            else:
                try:
                    flow.at_end_of_source(source)
                except GCodeError as exc:
                    raise exc.located(self.file, max(source.line, 1)) from None
                if self.source is not source:
                    if main is None and len(flow.frames) <= depth:
                        return
                    continue
                if main is None:
                    return
                if self.dialect is Dialect.GRBL:
                    # Grbl has no program end: the end of the file ends the program (modes stay, as
                    # after a closing %)
                    self._end_program(None)
                    yield from self._drain()
                    return
                if settings.require_program_end:
                    last = max(source.line, 1)
                    if percent_open:
                        raise GCodeError("File ended with no closing percent sign", self.file, last)
                    raise GCodeError("File ended with no percent sign or program end (M2, M30)",
                                     self.file, last)
                return

    def _drain(self) -> Iterator[Canon]:
        out, self._out = self._out, []
        for item in out:
            if isinstance(item, _Resume):
                item.fn()
            else:
                yield item

    def _fast(self, m) -> tuple[Canon, ...] | None:
        """A plain G0/G1 line of literal X Y Z F words; None sends the line the general way."""
        g, xs, ys, zs, fs = m.groups()
        has_axes = xs is not None or ys is not None or zs is not None
        if g is None:
            if not has_axes and fs is None:
                return None
            motion = self.motion
        else:
            motion = 0 if g == "0" else 10
        scale = self.scale
        feed = self.feed
        if fs is not None:
            feed = float(fs) * scale
            if feed < 0.0 or not math.isfinite(feed):
                return None
        if has_axes and ((motion == 10 and feed == 0.0) or motion not in (0, 10)):
            return None
        file, line = self.file, self.line
        end = None
        if has_axes:
            prog = self.prog
            x, y, z = prog[0], prog[1], prog[2]
            if self.absolute:
                if xs is not None:
                    x = float(xs) * scale
                if ys is not None:
                    y = float(ys) * scale
                if zs is not None:
                    z = float(zs) * scale
            else:
                if xs is not None:
                    x += float(xs) * scale
                if ys is not None:
                    y += float(ys) * scale
                if zs is not None:
                    z += float(zs) * scale
            s = self.frames.sum
            mx, my, mz = x + s[0], y + s[1], z + s[2]
            if not (_isfinite(mx) and _isfinite(my) and _isfinite(mz)):
                return None  # the general path reports it
            prog[0], prog[1], prog[2] = x, y, z
            tail = self._tail
            if tail is None:  # A B C U V W do not change on fast lines: computed once per run of them
                tail = self._tail = (prog[3] + s[3], prog[4] + s[4], prog[5] + s[5], prog[6] + s[6],
                                     prog[7] + s[7], prog[8] + s[8])
            end = _new_pose(Pose, (mx, my, mz, *tail))
            self.pos = end
            if motion:
                cmd: Canon = StraightFeed(end, file=file, line=line)
            else:
                cmd = StraightTraverse(end, file=file, line=line)
            self.motion = motion
            if feed != self.feed:
                self.feed = feed
                return (SetFeedRate(feed, file=file, line=line), cmd)
            return (cmd,)
        self.motion = motion
        if feed != self.feed:
            self.feed = feed
            return (SetFeedRate(feed, file=file, line=line),)
        return ()

    def _emit(self, cmd: Canon | _Resume) -> None:
        comp = self.comp
        if comp is not None and comp.pending:  # keep order behind the move compensation holds back
            self._out.extend(comp.hold(cmd))  # type: ignore[arg-type]
            return
        self._out.append(cmd)

    def _execute_line(self, raw: str) -> list[Canon | _Resume]:
        self._out = []
        block = parse_line(raw, self.reader)
        if block.deleted and self.settings.block_delete:
            return []
        if block.o_text is not None:
            self._o_word(block)
            return self._drain_list()
        if block.g or block.m or block.words or block.assigns:
            self.seen_code = True
        ml = sort_codes(block)
        self._check_words(block, ml)
        for key, _ in block.assigns:
            self.params.check_assignable(key)
        for key, value in block.assigns:
            self.params.assign(key, value)
        units = ml.g.get(6)
        if units is not None:
            self.scale = MM_PER_INCH if units == 200 else 1.0
        words = block.words
        key = (tuple(ml.g), tuple(ml.m), "f" in words, "s" in words, "t" in words, bool(block.comments))
        steps = self._step_cache.get(key)
        if steps is None or len(self.steps) != self._step_cache_len:
            steps = self._steps_for(key)
        for step in steps:
            step(block, ml)
        self._fast_ok = self.fast_path_allowed()
        return self._drain_list()

    # What each built-in step acts on: G groups, M groups, words, comments; a step not listed (one a
    # module added) runs on every line. Lines with the same groups and words share one step list.
    _STEP_TRIGGERS: ClassVar[dict[str, tuple[tuple[int, ...], tuple[int, ...], str, bool]]] = {
        "_step_comment": ((), (), "", True),
        "_step_feed_mode": ((5,), (), "", False),
        "_step_feed": ((), (), "f", False),
        "_step_speed": ((), (), "s", False),
        "_step_select_tool": ((), (), "t", False),
        "_step_io": ((), (5,), "", False),
        "_step_tool_change": ((), (6,), "", False),
        "_step_spindle": ((), (7,), "", False),
        "_step_state": ((), (7,), "", False),
        "_step_coolant": ((), (8,), "", False),
        "_step_overrides": ((), (9,), "", False),
        "_step_dwell": ((0,), (), "", False),
        "_step_plane": ((2,), (), "", False),
        "_step_units": ((6,), (), "", False),
        "_step_cutter_comp": ((7,), (), "", False),
        "_step_tool_length": ((8,), (), "", False),
        "_step_coord_system": ((12,), (), "", False),
        "_step_path_control": ((13,), (), "", False),
        "_step_distance": ((3, 4), (), "", False),
        "_step_retract": ((10,), (), "", False),
        "_step_transforms": ((16, 17, 18, 19), (), "", False),
        "_step_group0": ((0,), (), "", False),
        "_step_stop": ((), (4,), "", False),
    }

    def _steps_for(self, key: tuple) -> list[Callable[[Block, ModalLine], None]]:
        if self._step_cache_for != self.steps:  # a module inserted or removed steps: start again
            self._step_cache = {}
            self._step_cache_for = list(self.steps)
            self._step_cache_len = len(self.steps)
        g_groups, m_groups, f, s, t, comments = key
        present = {"f": f, "s": s, "t": t}
        chosen = []
        for step in self.steps:
            trigger = self._STEP_TRIGGERS.get(getattr(step, "__name__", ""))
            if trigger is None or getattr(step, "__self__", None) is not self:
                chosen.append(step)
                continue
            gs, ms, letters, wants_comments = trigger
            if (any(g in g_groups for g in gs) or any(m in m_groups for m in ms)
                    or any(present[c] for c in letters) or (wants_comments and comments)):
                chosen.append(step)
        self._step_cache[key] = chosen
        return chosen

    def fast_path_allowed(self) -> bool:
        """Whether plain G0/G1 lines may skip the general machinery in the current modal state.

        Asked after every general line. A module that changes what a straight move produces (cutter
        compensation, scaling, mirroring ...) must extend this to return False while it is active.
        """
        return (self.feed_mode is not FeedMode.INVERSE_TIME and self.frames.rotation == 0.0
                and not self._missing_axes & {"x", "y", "z"} and self.cycle_state.motion is None
                and self.comp is None and not self._after_comp and not self.polar_on
                and not self.xform_on)

    def _drain_list(self) -> list[Canon | _Resume]:
        out, self._out = self._out, []
        return out

    def _o_word(self, block: Block) -> None:
        """Flow control: :mod:`gcode_canon.owords`."""
        assert block.o_text is not None
        self.flow.execute(block.o_text)

    # --- checks ---------------------------------------------------------------------------------------

    def _effective_motion(self, ml: ModalLine) -> int | None:
        """The motion code that uses this line's axis words, or None when something else takes them."""
        if ml.axis_user:
            return None
        motion = ml.g.get(1)
        return self.motion if motion is None else motion

    def _check_words(self, block: Block, ml: ModalLine) -> None:
        w = block.words
        g0 = ml.g.get(0)
        g1 = ml.g.get(1)
        has_axes = block.has_axes()
        if has_axes and self._missing_axes:
            for letter in w:
                if letter in self._missing_axes or (letter in "@^" and self._missing_axes & {"x", "y"}):
                    axis = letter.upper() if letter not in "@^" else "X or Y"
                    raise GCodeError(f"{letter.upper()} word used, but the machine has no {axis} axis")
        axis_user0 = ml.axis_user
        if has_axes:
            if axis_user0 and g1 is not None and g1 != 800:
                raise GCodeError("Cannot use two G codes that both use axis values: "
                                 f"{_axis_user_name(ml)} and {gname(g1)}")
            if not axis_user0:
                motion = self.motion if g1 is None else g1
                if motion == 800:
                    if g1 == 800:
                        raise GCodeError("Cannot use axis values with G80")
                    raise GCodeError("Cannot use axis values without a G code that uses them")
        if g0 == 530:
            motion = self.motion if g1 is None else g1
            if motion not in (0, 10):
                raise GCodeError("Must use G0 or G1 with G53")
            if (not self.absolute and ml.g.get(3) != 900) or ml.g.get(3) == 910:
                raise GCodeError("Cannot use G53 incremental (G91)")
        motion = self._effective_motion(ml)
        if motion in SYNC_MOTIONS and (has_axes or g1 == motion):  # their own checks; their words used
            check_sync_block(motion, w)
            w = {k: v for k, v in w.items() if k not in SYNC_WORDS[motion]}
        arc = motion in (20, 30)
        if "@" in w or "^" in w:
            if self.plane is not Plane.XY:  # LinuxCNC enhance_block
                raise GCodeError("Cannot use polar coordinate except in G17 plane")
            if "x" in w or "y" in w:
                raise GCodeError("Cannot mix polar coordinates (@ ^) with X or Y words")
            if axis_user0 or g0 == 530:
                raise GCodeError(f"Polar coordinates (@ ^) cannot be used with {_axis_user_name(ml)}")
        ms = set(block.m)
        if self.settings.disable_fanuc_style_sub and ms & {98, 99}:  # LinuxCNC: when the line is read
            raise GCodeError(f"DISABLE_FANUC_STYLE_SUB is set, but found M{min(ms & {98, 99})}")
        takes_ijk = g0 in (100, 120, 130) or ml.g.get(17) == 510
        for letter in "ijk":
            if letter in w and not arc and motion != 870 and not takes_ijk:
                raise GCodeError(f"{letter.upper()} word with no G2 or G3 to use it")
        cycle = motion in cycles.CYCLE_CODES
        orient = ml.m.get(7) == 19
        if "r" in w and not (arc or cycle or orient) and g0 != 100 and ml.g.get(18) != 680 and \
                ml.g.get(13) != 640:
            raise GCodeError("R word with no G code that uses it")
        if "p" in w and not (arc or g0 in (40, 100) or ml.g.get(17) == 510 or ml.g.get(13) == 640
                             or motion in (740, 820, 840, 860, 880, 890) or orient
                             or ms & {50, 51, 52, 53, 62, 63, 64, 65, 66, 98}):
            raise GCodeError("P word with no G or M code that uses it")
        if "q" in w and not (ml.g.get(13) == 640 or ms & {61, 66, 67, 68} or motion in (730, 830)
                             or g0 == 100 or orient):
            raise GCodeError("Q word with no G or M code that uses it")
        if orient:
            self._check_orient_words(w, ml)
        if "l" in w and not (g0 == 100 or 66 in ms or 98 in ms or cycle
                             or ml.g.get(7) in (410, 420, 411, 421)):
            # LinuxCNC (check_other_codes) takes L with G41/G42 too, and ignores it there
            raise GCodeError("L word with no G10, cutter compensation, canned cycle, M66 or M98 to use it")
        if "e" in w and not ms & {66, 67, 68}:
            raise GCodeError("E word with no M66, M67 or M68 to use it")
        if "h" in w and ml.g.get(8) not in (430, 432) and g0 != 100:
            raise GCodeError("H word with no G43 to use it")
        if "d" in w and motion not in (730, 830) and ml.g.get(7) not in (410, 420, 411, 421) and \
                g0 not in (100, 120, 130):
            raise GCodeError("D word with no G code that uses it (G41, G42, G41.1, G42.1, G73, G83)")
        if self.comp is not None:
            self._check_comp(ml)
        if g0 == 100 and "l" not in w:
            raise GCodeError("Line with G10 does not have an L word")

    @staticmethod
    def _check_orient_words(w: dict[str, float], ml: ModalLine) -> None:
        """M19's own checks, LinuxCNC's (interp_check.cc), before anything on the line runs."""
        if "p" in w:
            p = w["p"]
            whole = round(p)
            if abs(whole - p) > 0.001:
                raise GCodeError("P value not an integer with M19")
            if not 0 <= whole <= 2:
                raise GCodeError("P value must be 0, 1 or 2 with M19")
        if "r" in w:
            if ml.g.get(13) == 640:
                raise GCodeError("R word is ambiguous on a line with both G64 and M19: use separate lines")
            if not 0.0 <= w["r"] <= 360.0:
                raise GCodeError("R value must be within 0..360 with M19")
        if "q" in w and not w["q"] > 0.0:
            raise GCodeError("Q word with M19 requires a value > 0")

    def _check_comp(self, ml: ModalLine) -> None:
        """What LinuxCNC refuses while cutter radius compensation is on."""
        plane = ml.g.get(2)
        if plane is not None and _PLANE_BY_CODE.get(plane) is not self.plane:
            raise GCodeError("Cannot change planes with cutter radius compensation on")
        if ml.g.get(7) == 400:
            return
        g0 = ml.g.get(0)
        if g0 in (280, 300):
            raise GCodeError(f"Cannot use {gname(g0)} with cutter radius compensation on")
        if g0 == 530:
            raise GCodeError("Cannot use G53 with cutter radius compensation on")
        if g0 in (920, 921, 922, 923, 520):
            raise GCodeError("Cannot change axis offsets (G52, G92) with cutter radius compensation on")
        if ml.g.get(12) is not None:
            raise GCodeError("Cannot change coordinate systems with cutter radius compensation on")
        if ml.m.get(6) == 6:
            raise GCodeError("Cannot change tools with cutter radius compensation on")

    # --- helpers ------------------------------------------------------------------------------------

    def _length(self, value: float) -> float:
        return value * self.scale

    def _int_word(self, block: Block, letter: str, what: str, minimum: int = 0) -> int | None:
        value = block.take(letter)
        if value is None:
            return None
        n = near_int(value, f"{letter.upper()} word of {what}")
        if n < minimum:
            raise GCodeError(f"{letter.upper()} word of {what} must be at least {minimum}, not {n}")
        return n

    def _to_machine(self, prog: list[float]) -> Pose:
        """Program frame (untransformed, mm) to machine: G22/G51/G68, then the offsets."""
        if self.xform_on:
            return self.frames.to_machine(list(self.xform.apply_position(prog)))
        return self.frames.to_machine(prog)

    def _from_machine(self, pos) -> list[float]:
        prog = self.frames.machine_to_program(pos)
        if self.xform_on:
            return list(self.xform.invert_position(prog))
        return prog

    def _offsets_changed(self) -> None:
        """Keep the machine where it is: its program coordinates change instead."""
        self.frames.refresh()
        self.prog = self._from_machine(self.pos)

    def _target(self, block: Block, prog: list[float] | None = None, polar: bool = True) -> list[float]:
        """End point in the program frame (mm) from the line's axis words and polar words."""
        target = list(self.prog if prog is None else prog)
        scale = self.scale
        absolute = self.absolute
        words = block.words
        if polar and self.polar_on:
            first, second, _ = self.plane.value
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

    def _step_speed(self, block: Block, ml: ModalLine) -> None:
        value = block.take("s")
        if value is None:
            return
        if value < 0.0:
            raise GCodeError(f"Negative spindle speed used: S{value:g}")
        self.speed = value
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

        self._emit(_Resume(answer))

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
            self._emit(_Resume(self._refresh_position))
        else:
            q = block.take("q")
            if q is None:
                raise GCodeError("M61 needs a Q word (the tool number)")
            number = near_int(q, "Q word of M61")
            if number < 0:
                raise GCodeError(f"M61 Q{number}: negative tool number")
            self._tool(number)
            self._emit(SetToolNumber(number, file=self.file, line=self.line))
            self._emit(_Resume(self._refresh_position))
        self.current_tool = number
        self._set_tool_parameters(number)

    def _resync(self) -> None:
        where = self.machine.current_position()
        if where is not None:
            self.pos = Pose(*where)
            self.prog = self._from_machine(self.pos)

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
        plane = _PLANE_BY_CODE[code]
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

    def _step_cutter_comp(self, block: Block, ml: ModalLine) -> None:
        """G40 / G41 / G42 / G41.1 / G42.1: :mod:`gcode_canon.cutter_comp` does the geometry; the
        modal state, the radius, the lathe tool orientation and the block checks are here.

        The orientation (tool table Q for G41/G42, L for G41.1/G42.1, 0 without L) and its checks are
        LinuxCNC's ``convert_cutter_compensation_on`` (``interp_convert.cc``): a lathe orientation
        (1-8) is only meaningful in G18, so L in any other plane, or a tool with orientation 1-8 there,
        is an error; a G41/G42 L word is accepted and ignored, as there."""
        code = ml.g.get(7)
        if code is None:
            return
        if code == 400:
            self._comp_off()
            return
        name = gname(code)
        if self.comp is not None:
            raise GCodeError("Cannot turn cutter radius comp on when already on")
        if self.plane is Plane.YZ or self.plane.value[0] > 2:
            raise GCodeError(f"{name}: cutter radius compensation works in G17 or G18 only, not "
                             f"{self.plane.gcode}")
        d = block.take("d")
        orientation = 0
        if code in (411, 421):
            if d is None:
                raise GCodeError(f"{name} needs a D word (the tool diameter)")
            diameter = d * self.scale
            lword = self._int_word(block, "l", name)
            if lword is not None:
                if self.plane is not Plane.XZ:
                    raise GCodeError(f"{name} with L word, but plane is not G18")
                if lword > 9:
                    # *canon*: LinuxCNC's manual makes this an error, its source takes any L >= 0 (and
                    # an L above 9 then moves nothing but the lathe entry-arc pre-move)
                    raise GCodeError(f"{name} L{lword}: invalid tool orientation (0 to 9)")
                orientation = lword
        else:
            number = self.current_tool
            if d is not None:
                number = near_int(d, f"D word of {name}")
                if number < 0:
                    raise GCodeError(f"{name} D{number}: negative tool number")
            tool = self._tool(number)
            diameter = float(tool.diameter) if tool is not None else 0.0
            orientation = tool.orientation if tool is not None else 0
            if self.plane is not Plane.XZ and orientation not in (0, 9):
                raise GCodeError(f"{name} with lathe tool, but plane is not G18 (T{number} has "
                                 f"orientation Q{orientation})")
        first, second, normal = self.plane.value
        side = "left" if code in (410, 411) else "right"
        here = self.prog
        if self.xform_on:  # compensation works on the transformed path; a mirror swaps the side
            here = list(self.xform.apply_position(here))
            side = self.xform.comp_side(side, self.plane)
        self.comp = cutter_comp.CutterCompensator(side, diameter / 2.0, (here[first], here[second]),
                                                  orientation, here[normal])
        self._comp_normal = here[normal]
        self.comp_code = code
        self._after_comp = False

    def _comp_off(self) -> None:
        """G40 or the end of the program: the held move goes out at its offset end."""
        comp = self.comp
        if comp is None:
            return
        self.comp = None
        self.comp_code = 400
        self._comp_output(comp.finish())
        self._after_comp = True

    def _comp_move(self, seg: cutter_comp.Segment) -> None:
        assert self.comp is not None
        self._comp_output(self.comp.add(seg))

    def _comp_output(self, items: list) -> None:
        """Compensated segments to canonical commands (machine coordinates); held commands as they are."""
        first, second, normal = self.plane.value
        others = [k for k in range(N_AXES) if k not in (first, second, normal)]
        f = self.file
        for item in items:
            if isinstance(item, (cutter_comp.Line2, cutter_comp.Arc2)):
                prog = [0.0] * N_AXES
                prog[first], prog[second] = item.end
                prog[normal] = item.normal
                for k, v in zip(others, item.extra, strict=True):
                    prog[k] = v
                end = self.frames.to_machine(prog)
                if not _isfinite(sum(end)):
                    raise GCodeError("Coordinate out of range")
                n = item.line or self.line
                if isinstance(item, cutter_comp.Line2):
                    cls = StraightTraverse if item.rapid else StraightFeed
                    self._out.append(cls(end, file=f, line=n))
                else:
                    centre = list(prog)
                    centre[first], centre[second] = item.center
                    centre[normal] = self._comp_normal
                    centre_pose = self.frames.to_machine(centre)
                    turns = item.turns if item.ccw else -item.turns
                    self._out.append(ArcFeed(end, centre_pose, self.plane, turns, file=f, line=n))
                self._comp_normal = item.normal
                self.pos = end
            else:
                self._out.append(item)

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
        index = _G5X_INDEX[code]
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

    # --- gcode-canon / Fanuc transforms: G15/G16, G22/G23, G50/G51, G68/G69 -----------------------

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

    def _full_circle(self, code: int, block: Block) -> None:
        """G12/G13 (gcode-canon): a full circle of radius I around the current point."""
        name = gname(code)
        if self.comp is not None:
            raise GCodeError(f"{name} with cutter radius compensation on is not supported")
        self._require_feed(block, name)
        first, second, normal = self.plane.value
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
                self._emit(ArcFeed(end_pose, centre_pose, self.plane, -1 if clockwise else 1, file=f, line=n))
            self.prog = target
            self.pos = end_pose
        _ = normal

    # --- motion -------------------------------------------------------------------------------------

    def _step_motion(self, block: Block, ml: ModalLine) -> None:
        g0 = ml.g.get(0)
        explicit = ml.g.get(1)
        if ml.axis_user:
            if explicit is not None:
                self.motion = explicit
            return
        motion = self.motion if explicit is None else explicit
        self.motion = motion
        w = block.words
        has_axes = block.has_axes()
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
        if motion in (20, 30):
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
            first, second, normal = self.plane.value
            t = list(self.xform.apply_position(target)) if self.xform_on else target
            others = tuple(t[k] for k in range(N_AXES) if k not in (first, second, normal))
            self._comp_move(cutter_comp.Line2(self.comp.programmed, (t[first], t[second]),
                                              t[normal], others, n, motion == 0))
            self.prog = target
            return
        self._after_comp = False
        if motion == 0:
            cmd: Canon = StraightTraverse(end_pose, file=f, line=n)
        elif motion == 10:
            self._require_feed(block, "G1")
            cmd = StraightFeed(end_pose, file=f, line=n)
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

        self._emit(_Resume(answer))

    def _arc(self, block: Block, clockwise: bool) -> None:
        name = "G2" if clockwise else "G3"
        first, second, normal = self.plane.value
        if self.frames.rotation != 0.0 and self.plane is not Plane.XY:
            raise GCodeError(f"{name} in {self.plane.gcode}: arcs out of the XY plane with a rotated "
                             "coordinate system are not supported")
        letters = {first: _IJK[first], second: _IJK[second]}
        normal_letter = _IJK[normal]
        if normal_letter in block.words:
            raise GCodeError(f"{normal_letter.upper()} word given for arc in {self.plane.gcode} plane")
        turns = self._int_word(block, "p", name, minimum=1)
        turns = 1 if turns is None else turns
        self._require_feed(block, name)
        start = self.prog
        radius = block.take("r")
        has_ijk = any(letter in block.words for letter in letters.values())
        if radius is not None and has_ijk:
            raise GCodeError("Mixed radius-ijk format for arc")
        target = self._target(block)
        s2 = (start[first], start[second])
        e2 = (target[first], target[second])
        inch = self.inch
        if radius is not None:
            cx, cy, rot = centre_r(clockwise, s2, e2, radius * self.scale, turns)
        elif has_ijk:
            off1 = (block.take(letters[first]) or 0.0) * self.scale
            off2 = (block.take(letters[second]) or 0.0) * self.scale
            if self.ijk_absolute:
                centre = (off1, off2)
            else:
                centre = (s2[0] + off1, s2[1] + off2)
            cx, cy, rot = centre_ijk(clockwise, s2, e2, centre, turns, inch)
        else:
            raise GCodeError(f"R, I, J or K words missing for arc ({name})")
        if self._after_comp:
            raise GCodeError("The move just after exiting cutter compensation mode must be straight, "
                             "not an arc")
        if self.comp is not None:
            normal = self.plane.value[2]
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
            self._comp_move(cutter_comp.Arc2(self.comp.programmed, end2, centre2, ccw, t[normal],
                                             others, self.line, abs(rot)))
            self.prog = target
            return
        centre_prog = list(start)
        centre_prog[first] = cx
        centre_prog[second] = cy
        xform = self.xform
        if self.xform_on:
            normal = self.plane.value[2]
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
        self.prog = target
        self.pos = end_pose
        self._emit(ArcFeed(end_pose, centre_pose, self.plane, rot, file=self.file, line=self.line))

    # --- stops and the end ------------------------------------------------------------------------

    def _step_stop(self, block: Block, ml: ModalLine) -> None:
        code = ml.m.get(4)
        if code is None:
            return
        f, n = self.file, self.line
        if code in (0, 1):
            self._emit(ProgramStop(code == 1, file=f, line=n))
            self._emit(_Resume(self._resync))
        elif code == 60:
            self._emit(PalletShuttle(file=f, line=n))
            self._emit(_Resume(self._resync))
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

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.logs.close()
            self.probe_log.close()


def _axis_user_name(ml: ModalLine) -> str:
    g = ml.g
    if g.get(0) in G_AXIS_USERS_GROUP0:
        return gname(g[0])
    if g.get(0) == 530:
        return "G53"
    for group in (8, 19, 17, 18):
        if group in g:
            return gname(g[group])
    return "G43.1"


_G5X_INDEX = {540: 1, 550: 2, 560: 3, 570: 4, 580: 5, 590: 6, 591: 7, 592: 8, 593: 9}
_G5X_NAMES = {v: gname(k) for k, v in _G5X_INDEX.items()}
_G5X_CODES = {v: k for k, v in _G5X_INDEX.items()}
