"""The RS274/NGC interpreter: lines in, canonical commands out, lazily.

Each line goes through :func:`~gcode_canon.lexer.parse_line` (values evaluated as read), the modal
checks of :mod:`gcode_canon.modal`, then the parameter settings of the line, then ``self.steps``: one
method per item of LinuxCNC's order of execution. A later module (canned cycles, cutter compensation,
o-words) adds or replaces a step instead of rewriting the loop.

The class here holds the set-up, the public API and the order of execution; the rest is split by
concern, as LinuxCNC's rs274ngc is, into mixins whose state is the interpreter's:

* :mod:`gcode_canon.program_loop`: reading lines, the fast path, executing one line;
* :mod:`gcode_canon.block_checks`: the per-line word checks (``interp_check.cc``);
* :mod:`gcode_canon.mode_steps`: the modal steps other than motion and tools, the stops and program end;
* :mod:`gcode_canon.tool_steps`: S, T, M6/M61, spindle and coolant;
* :mod:`gcode_canon.comp_steps`: G40/G41/G42 and the compensated output;
* :mod:`gcode_canon.motion_steps`: moves, arcs, probes, canned cycles, G12/G13;
* :mod:`gcode_canon.group0`: G10, G28/G30, G52/G92; :mod:`gcode_canon.modal_state`: M70-M73;
* :mod:`gcode_canon.param_glue`: predefined parameters and the parameter file;
* :mod:`gcode_canon.status`: ``active_gcodes()``, ``active_mcodes()``, ``modal_key()``.

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
import itertools
import logging
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

from gcode_canon import cycles, transforms
from gcode_canon.block_checks import BlockChecksMixin
from gcode_canon.commands import Canon, FeedMode, MotionControlMode, Plane, Pose, SpindleDirection
from gcode_canon.comp_steps import CutterCompMixin
from gcode_canon.compiled import LineCache
from gcode_canon.dialect import Dialect
from gcode_canon.errors import GCodeError
from gcode_canon.expressions import ExpressionReader, near_int
from gcode_canon.group0 import Group0Mixin
from gcode_canon.lathe_cycles import LatheCycleMixin
from gcode_canon.lexer import AXIS_LETTERS, Block
from gcode_canon.machine import DryRunMachine, MachineCallbacks, Resume
from gcode_canon.messages import LogFiles
from gcode_canon.modal import ModalLine
from gcode_canon.modal_state import ModalStateMixin
from gcode_canon.mode_steps import ModeStepsMixin
from gcode_canon.motion_steps import MotionMixin
from gcode_canon.offsets import N_AXES, Frames
from gcode_canon.owords import FlowControl
from gcode_canon.param_glue import ParamGlueMixin
from gcode_canon.parameters import Parameters
from gcode_canon.program_loop import ProgramLoopMixin
from gcode_canon.settings import InterpreterSettings
from gcode_canon.source import LineSource
from gcode_canon.spindle_sync import SpindleSyncMixin
from gcode_canon.spline_steps import SplineMixin
from gcode_canon.status import StatusMixin
from gcode_canon.tool_steps import ToolSpindleMixin

if TYPE_CHECKING:
    from gcode_canon import cutter_comp

log = logging.getLogger(__name__)


class Interpreter(ProgramLoopMixin, BlockChecksMixin, ModeStepsMixin, ToolSpindleMixin, CutterCompMixin,
                  MotionMixin, SpindleSyncMixin, SplineMixin, LatheCycleMixin, ModalStateMixin, Group0Mixin,
                  ParamGlueMixin, StatusMixin):
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
        self._out: list[Canon | Resume] = []
        self.dialect = Dialect.parse(self.settings.dialect) if isinstance(self.settings.dialect, str) \
            else self.settings.dialect
        # LinuxCNC (and Grbl, which has no expressions) compare GT/GE/LT/LE strictly
        self.reader.tolerant_order = self.dialect is Dialect.GCODE_CANON
        self._lines = LineCache(self.reader, fast_for=self._fast_runner)
        self._modal_lines: dict[tuple, ModalLine] = {}  # (G codes, M codes) -> sort_codes' answer
        self._checks_passed: set[tuple] = set()  # see _check_block
        self._shape_ids: dict[tuple, int] = {}  # see _shape
        self._shape_count = itertools.count()
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
            self._step_spindle_mode,
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
            self._step_user_mcode,
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
        self._builtin_steps = len(self.steps)  # another count: a module's step, which runs on every line


    # What each built-in step acts on: G groups, M groups, words, comments; a step not listed (one a
    # module added) runs on every line. Lines with the same groups and words share one step list.
    _STEP_TRIGGERS: ClassVar[dict[str, tuple[tuple[int, ...], tuple[int, ...], str, bool]]] = {
        "_step_comment": ((), (), "", True),
        "_step_spindle_mode": ((14,), (), "", False),
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
        "_step_user_mcode": ((), (10,), "", False),
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
        self.css_max = 0.0  # G97; G96: the highest rpm (1e30 without D)
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
        self._spline_reset()
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
        self.diameter_mode = False  # G7 (lathe diameter mode) / G8; M2 does not reset it, as LinuxCNC

    def _load_tool_table(self) -> None:
        self.tool_table = None
        self._implicit_table = False  # no file: every tool exists with zero offsets (G10 may set some)
        if self.settings.tool_table is not None:
            from gcode_canon import tooltable

            self.tool_table = tooltable.read_tool_table(self.settings.tool_table)

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
                if isinstance(item, Resume):
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

    def shutdown(self) -> None:
        """Write the parameter file (unless dry run) and close LOG files."""
        self.logs.close()
        self.probe_log.close()
        self._write_var_file()

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
        if self.css_max:  # G96: the spindle's centre line moved with the X offsets
            self._emit(self._css_mode())

    def _resync(self) -> None:
        where = self.machine.current_position()
        if where is not None:
            self.pos = Pose(*where)
            self.prog = self._from_machine(self.pos)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.logs.close()
            self.probe_log.close()

