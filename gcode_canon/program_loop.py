"""The interpreter's loop: lines read from a lazily read source, the fast path for plain G0/G1 lines,
and the execution of one line (parse, checks, parameter settings, then the steps its codes concern).
A mixin of :class:`gcode_canon.interpreter.Interpreter` (module docstring there)."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterator
from functools import partial

from gcode_canon.arcs import MM_PER_INCH
from gcode_canon.commands import (
    Canon,
    FeedMode,
    MotionControlMode,
    Pose,
    SetFeedRate,
    SetMotionControlMode,
    StraightFeed,
    StraightTraverse,
    new_comment,
    slot_setters,
)
from gcode_canon.compiled import FAST_SEEN, CompiledLine
from gcode_canon.dialect import GRBL_JUNCTION_DEVIATION_MM, Dialect
from gcode_canon.errors import GCodeError
from gcode_canon.fast_lines import EXPRESSION_ERRORS, straight_function
from gcode_canon.lexer import FAST_LINE, Block
from gcode_canon.machine import Resume
from gcode_canon.modal import ModalLine, sort_codes
from gcode_canon.source import LineSource

log = logging.getLogger(__name__)

_isfinite = math.isfinite
_new_pose = tuple.__new__
_new_object = object.__new__
_feed_end, _set_file, _set_line = slot_setters(StraightFeed)
_traverse_end = slot_setters(StraightTraverse)[0]

class ProgramLoopMixin:
    """Reading and executing lines (module docstring)."""

    def _run_source(self, open_source: Callable[[], LineSource]) -> Iterator[Canon]:
        source = open_source()  # open errors surface at the call, not at first next()
        return self._run(source)

    def _run(self, source: LineSource) -> Iterator[Canon]:
        """The program's commands, lazily: :meth:`_loop` sets up and reads from the start of ``source``.
        One generator between the source and the caller: a generator that hands on another's
        commands (``yield from``) costs a resumption of both for each command."""
        return self._loop(source)

    def _start(self, source: LineSource) -> Canon | None:
        """The interpreter at the start of a program read from ``source``; the command to yield first
        (Grbl's blending), or None."""
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
            return SetMotionControlMode(*self.control, file=source.name, line=1)
        return None

    def switch_source(self, source: LineSource, file: str | None = None) -> None:
        """Continue reading from ``source`` (an o-word call or return); the loop picks it up."""
        self.source = source
        self.file = file if file is not None else source.name
        self._fast_ok = False  # re-evaluated after the line

    def _loop(self, main: LineSource | None, depth: int = 0) -> Iterator[Canon]:
        """Read and execute lines from ``self.source`` until the program ends (``main``: the program's
        source, set up here by :meth:`_start` and closed at the end) or, for an MDI call, until the
        call stack is back to ``depth`` frames.

        The lines are read here as :meth:`LineSource.__iter__` reads them (its chunk of lines, the same
        line count, limit and errors), not through it: a generator between the source and this loop costs its
        resumption at every line."""
        if main is not None:
            first = self._start(main)
            if first is not None:
                yield first
        fast_match = FAST_LINE.match
        fast = self._fast_values
        fast_block = self._fast_block
        parse = self._lines.parse
        known = self._lines.known
        entries, cache_size = self._lines.entries, self._lines.size
        # lines run by the pattern are noted in the line cache (FAST_SEEN) while some are read again:
        # after as many lines as it holds and none read again (CAM output, every line its own), no more
        # are, until one noted before comes back (a note costs 3 % of the instructions of such a line)
        noting = cache_size
        flow = self.flow
        self._tail = None
        settings = self.settings
        percent_open = False
        seen_content = seen_fast = False
        try:
            while True:
                source = self.source
                in_main = source is main
                max_length = source.max_line_length
                switched = False
                while True:
                    # the source's chunk, index and count read afresh at each line (a jump, a scan for
                    # a subroutine, may have moved them)
                    i = source.next
                    lines = source.lines
                    if i >= len(lines):
                        if not source.fill():
                            break  # the end of the source: below
                        i = 0
                        lines = source.lines
                    raw = lines[i]
                    source.next = i + 1
                    self.line = source.line = source.line + 1
                    if len(raw) > max_length:
                        raise source.too_long()
                    if self.before_line is not None:
                        self.before_line()
                    if self._fast_ok:
                        entry = known(raw)
                        if entry is not None:  # a line read before: its Block or compiled line, no parsing
                            run = entry.fast  # type: ignore[attr-defined]
                            if run is not None:
                                try:
                                    cmds = run()
                                except Exception as exc:
                                    err, cause = self._line_error(exc)
                                    raise err from cause
                                if cmds is not None:
                                    seen_content = True
                                    self.seen_code = True
                                    if len(cmds) == 1:  # most lines: one command, no iterator over them
                                        yield cmds[0]
                                    else:
                                        yield from cmds
                                    continue
                            elif entry is FAST_SEEN:  # a line noted below, read again
                                noting = cache_size
                        elif (m := fast_match(raw)) is not None:
                            g, xs, ys, zs, fs = m.groups()
                            cmds = fast(None if g is None else 0 if g == "0" else 10,
                                        None if xs is None else float(xs), None if ys is None else float(ys),
                                        None if zs is None else float(zs), None if fs is None else float(fs))
                            if cmds is not None:
                                seen_content = seen_fast = True
                                if noting:  # noted: read again, it is parsed and kept with its fast path
                                    noting -= 1
                                    if len(entries) >= cache_size:
                                        entries.clear()
                                    entries[raw] = FAST_SEEN
                                if len(cmds) == 1:
                                    yield cmds[0]
                                else:
                                    yield from cmds
                                continue
                    self._tail = None
                    stripped = raw.strip()
                    if not stripped:
                        continue
                    if stripped[0] == "$" and self.dialect is Dialect.GRBL:
                        log.warning("%s:%d: Grbl system command %r skipped (not G-code)", self.file,
                                    self.line, stripped)
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
                        block = parse(raw)
                        cmds = fast_block(block) if block.plain is not None and self._fast_ok else None
                        if cmds is None:
                            out = self._execute_block(block)
                    except Exception as exc:
                        err, cause = self._line_error(exc)
                        raise err from cause
                    if cmds is not None:
                        self.seen_code = True
                        yield from cmds
                        continue
                    for item in out:
                        if type(item) is Resume:
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
                        switched = True
                        break
                if switched:
                    continue
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
        finally:
            if main is not None:
                self.flow.close_all()
                main.close()

    def _drain(self) -> Iterator[Canon]:
        out, self._out = self._out, []
        for item in out:
            if isinstance(item, Resume):
                item.fn()
            else:
                yield item

    def _fast_runner(self, line: Block | CompiledLine) -> Callable[[], tuple[Canon, ...] | None] | None:
        """The fast path of a line the line cache keeps (its ``fast``, called by the loop where the fast
        path is allowed): the line's commands (``()`` when there are none), or None for the general
        way with nothing changed. A parsed Block of the fast path's shape runs :meth:`_fast_values` or
        ``_fast_arc`` on its words' values, bound once; a compiled straight line computes its X Y Z F
        values (``CompiledLine.quick``) and gives them to :meth:`_fast_values`, no Block built; a
        compiled line of parameter settings alone sets them as :meth:`_execute_block` would. An
        expression that fails here fails again the general way, which says it in its place. The fast
        path's A-W tail (``_tail``) stays: none of these lines moves those axes or changes an offset.
        None: the line has no fast path."""
        if line.__class__ is Block:
            motion, comment = line.plain  # type: ignore[misc]
            w = line.words  # type: ignore[union-attr]
            if motion is not None and motion >= 20:
                run = partial(self._fast_arc, motion, w.get("x"), w.get("y"), w.get("z"),  # type: ignore[attr-defined]
                              w.get("i"), w.get("j"), w.get("k"), w.get("r"), w.get("f"))
            elif line.axes:  # type: ignore[union-attr]
                return straight_function(self, motion, w, comment)
            else:
                run = partial(self._fast_values, motion, None, None, None, w.get("f"))
            return run if comment is None else self._commented(run, comment)
        quick = line.quick  # type: ignore[union-attr]
        if quick is None:
            return None
        if line.plain is None:  # parameter settings alone
            return self._settings_runner(quick)
        motion, comment = line.plain
        if line.axes:  # type: ignore[union-attr]
            return straight_function(self, motion, dict(line.values), comment)  # type: ignore[union-attr]
        fast = self._fast_values

        def straight() -> tuple[Canon, ...] | None:
            try:
                values = quick()
            except EXPRESSION_ERRORS:
                return None
            return fast(motion, *values)  # type: ignore[misc]

        return straight if comment is None else self._commented(straight, comment)

    def _commented(self, run: Callable[[], tuple[Canon, ...] | None],
                   text: str) -> Callable[[], tuple[Canon, ...] | None]:
        """``run`` on a line with a comment: the comment first (``_step_comment`` runs first)."""

        def commented() -> tuple[Canon, ...] | None:
            cmds = run()
            if cmds is None:
                return None
            return (new_comment(text, self.file, self.line), *cmds)

        return commented

    def _settings_runner(self, quick: Callable[[], object]) -> Callable[[], tuple[Canon, ...] | None]:
        """The fast path of a compiled line of parameter settings alone (:meth:`_fast_runner`)."""

        def settings() -> tuple[Canon, ...] | None:
            if self.cycle_state.initial_level is not None or len(self.steps) != self._builtin_steps:
                return None
            try:
                values = quick()
            except EXPRESSION_ERRORS:
                return None
            self._tail = None  # as the general path: computed again at the next fast line
            self._assign(values)  # type: ignore[arg-type]
            return ()

        return settings

    def _line_error(self, exc: Exception) -> tuple[GCodeError, Exception | None]:
        """The error to raise for ``exc`` raised by the current line, located, and its cause."""
        if isinstance(exc, GCodeError):
            return exc.located(self.file, self.line), None
        if isinstance(exc, RecursionError):
            return GCodeError("Expression nested too deeply", self.file, self.line), None
        log.exception("internal error")
        return GCodeError(f"internal error: {exc!r}", self.file, self.line), exc

    def _fast_block(self, block: Block) -> tuple[Canon, ...] | None:
        """The fast path for a parsed line of the same shape (:attr:`Block.plain`: an optional G0/G1,
        X Y Z F words whatever their values are written as, a comment that is not active; or G2/G3
        with X Y Z I J K R F words, ``_fast_arc``): the general path's commands, or None to send it
        there."""
        motion, comment = block.plain  # type: ignore[misc]
        w = block.words
        if motion is not None and motion >= 20:
            cmds = self._fast_arc(motion, w.get("x"), w.get("y"), w.get("z"),  # type: ignore[attr-defined]
                                  w.get("i"), w.get("j"), w.get("k"), w.get("r"), w.get("f"))
        else:
            cmds = self._fast_values(motion, w.get("x"), w.get("y"), w.get("z"), w.get("f"))
        if cmds is None or comment is None:
            return cmds
        return (new_comment(comment, self.file, self.line), *cmds)  # _step_comment runs first

    def _fast_values(self, g: int | None, xv: float | None, yv: float | None, zv: float | None,
                     fv: float | None) -> tuple[Canon, ...] | None:
        """The fast path (FAST_LINE's lines, and :meth:`_fast_block`): motion code (None, 0, 10) and the
        words' values; None sends the line the general way."""
        has_axes = xv is not None or yv is not None or zv is not None
        if g is None:
            if not has_axes and fv is None:
                return None
            motion = self.motion
        else:
            motion = g
        scale = self.scale
        feed = self.feed
        if fv is not None:
            feed = fv * scale
            if feed < 0.0 or not _isfinite(feed):
                return None
        if has_axes and ((motion == 10 and feed == 0.0) or motion not in (0, 10)):
            return None
        file, line = self.file, self.line
        end = None
        if has_axes:
            prog = self.prog
            x, y, z = prog[0], prog[1], prog[2]
            if self.absolute:
                if xv is not None:
                    x = xv * scale
                if yv is not None:
                    y = yv * scale
                if zv is not None:
                    z = zv * scale
            else:
                if xv is not None:
                    x += xv * scale
                if yv is not None:
                    y += yv * scale
                if zv is not None:
                    z += zv * scale
            s = self.frames.sum
            mx, my, mz = x + s[0], y + s[1], z + s[2]
            if not _isfinite(mx + my + mz):  # any of them not finite (or a sum too large to add)
                return None  # the general path reports it (or takes it)
            prog[0], prog[1], prog[2] = x, y, z
            tail = self._tail
            if tail is None:  # A B C U V W do not change on fast lines: computed once per run of them
                tail = self._tail = (prog[3] + s[3], prog[4] + s[4], prog[5] + s[5], prog[6] + s[6],
                                     prog[7] + s[7], prog[8] + s[8])
            end = _new_pose(Pose, (mx, my, mz, *tail))
            self.pos = end
            if motion:  # new_straight_feed's object, without the call (slot_setters)
                cmd = _new_object(StraightFeed)
                _feed_end(cmd, end)
            else:
                cmd = _new_object(StraightTraverse)
                _traverse_end(cmd, end)
            _set_file(cmd, file)
            _set_line(cmd, line)
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

    def _emit(self, cmd: Canon | Resume) -> None:
        comp = self.comp
        if comp is not None and comp.pending:  # keep order behind the move compensation holds back
            self._out.extend(comp.hold(cmd))  # type: ignore[arg-type]
            return
        self._out.append(cmd)

    def _execute_line(self, raw: str) -> list[Canon | Resume]:
        return self._execute_block(self._lines.parse(raw))

    def _execute_block(self, block: Block) -> list[Canon | Resume]:
        self._out = []
        if block.deleted and self.settings.block_delete:
            return []
        if block.o_text is not None:
            self._o_word(block)
            return self._drain_list()
        if block.g or block.m or block.words or block.assigns:
            self.seen_code = True
            if (not block.words and not block.g and not block.m and not block.comments and self._fast_ok
                    and self.cycle_state.initial_level is None and len(self.steps) == self._builtin_steps):
                # parameter settings alone: no check and no built-in step has anything to do (the
                # motion step would only cancel a canned cycle's level), nor does the fast path's state
                # change; a step a module added runs on every line: the general way then
                self._assign(block.assigns)
                return []
        shape = block.shape
        if shape is None:
            shape = self._shape(block)
        ml = shape[0]
        capture = self._g7x is not None  # reading a G70-G72 profile: no checks, nothing executed
        if not capture:
            self._check_block(block, ml, shape[1])
        if block.assigns:
            self._assign(block.assigns)
        units = ml.g.get(6)
        if units is not None:
            self.scale = MM_PER_INCH if units == 200 else 1.0
        lathe = ml.g.get(15)
        if lathe is not None:
            self.diameter_mode = lathe == 70
        if self.diameter_mode and "x" in block.words:
            block = _radius_x(block)
        if capture:
            self._profile_line(block, ml)
            return self._drain_list()
        steps = self._step_cache.get(shape)
        if steps is None or len(self.steps) != self._step_cache_len:
            steps = self._steps_for(shape, block, ml)
        for step in steps:
            step(block, ml)
        self._fast_ok = self.fast_path_allowed()
        return self._drain_list()

    def _assign(self, assigns: list[tuple[int | str, float]]) -> None:
        """A line's parameter settings: all refused if one is, else made in their order."""
        params = self.params
        for key, _ in assigns:
            params.check_assignable(key)
        for key, value in assigns:
            params.assign(key, value)

    def _shape(self, block: Block) -> tuple[ModalLine, int]:
        """What the line's execution depends on besides its values, computed once per line text
        (:attr:`Block.shape`): its codes sorted by group (``sort_codes``, remembered per codes) and a
        number for its codes, word letters and comments, which keys the checks passed and the step
        lists. A line in error is not kept."""
        codes = (tuple(block.g), tuple(block.m))
        ml = self._modal_lines.get(codes)
        if ml is None:  # sort_codes depends on the codes only
            ml = sort_codes(block, self.settings.user_mcodes)
            if len(self._modal_lines) >= 4096:
                self._modal_lines.clear()
            self._modal_lines[codes] = ml
        key = (codes, tuple(block.words), bool(block.comments))
        ids = self._shape_ids
        number = ids.get(key)
        if number is None:
            if len(ids) >= 4096:
                ids.clear()  # numbers are never given twice (the count goes on): old keys stay apart
            number = ids[key] = next(self._shape_count)
        shape = (ml, number)
        block.keep_shape(shape)
        return shape

    def _steps_for(self, shape: tuple, block: Block,
                   ml: ModalLine) -> list[Callable[[Block, ModalLine], None]]:
        if self._step_cache_for != self.steps:  # a module inserted or removed steps: start again
            self._step_cache = {}
            self._step_cache_for = list(self.steps)
            self._step_cache_len = len(self.steps)
        words = block.words
        comments = bool(block.comments)
        g_groups, m_groups = ml.g, ml.m
        present = {"f": "f" in words, "s": "s" in words, "t": "t" in words}
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
        if len(self._step_cache) >= 4096:
            self._step_cache.clear()
        self._step_cache[shape] = chosen
        return chosen

    def fast_path_allowed(self) -> bool:
        """Whether plain G0/G1 lines may skip the general machinery in the current modal state.

        Asked after every general line. A module that changes what a straight move produces (cutter
        compensation, scaling, mirroring ...) must extend this to return False while it is active.
        """
        return (self.feed_mode is not FeedMode.INVERSE_TIME and self.frames.rotation == 0.0
                and not self._missing_axes & {"x", "y", "z"} and self.cycle_state.motion is None
                and self.comp is None and not self._after_comp and not self.polar_on
                and not self.xform_on and not self.diameter_mode and self._g7x is None)

    def _drain_list(self) -> list[Canon | Resume]:
        out, self._out = self._out, []
        return out

    def _o_word(self, block: Block) -> None:
        """Flow control: :mod:`gcode_canon.owords`."""
        assert block.o_text is not None
        self.flow.execute(block.o_text)


def _radius_x(block: Block) -> Block:
    """G7 (lathe diameter mode): the X word is a diameter, so the X axis moves by half of it; every use
    of X on the line (moves, G92, G10, cycles ...), as LinuxCNC halves ``x_number`` (``read_x``,
    ``convert_lathe_diameter_mode``: a G7 or G8 on the line counts for its own X word). A copy: a
    Block may be shared by every reading of its line."""
    copy = Block()
    copy.g, copy.m, copy.assigns, copy.comments = block.g, block.m, block.assigns, block.comments
    copy.line_number, copy.deleted, copy.o_text, copy.axes = (block.line_number, block.deleted, block.o_text,
                                                              block.axes)
    copy.words = dict(block.words)
    copy.words["x"] /= 2.0
    return copy
