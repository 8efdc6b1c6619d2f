"""O-word flow control (LinuxCNC): subroutines, conditionals and loops, on lazily read sources.

Why its own module: as LinuxCNC's ``interp_o_word.cc``, flow control is a separate concern from the
execution of a line. :class:`FlowControl` holds the state (open blocks, call frames, known
subroutines) and moves the interpreter's current :class:`~gcode_canon.source.LineSource`; the
interpreter hands it each line that starts with an O word.

How it works without holding a program in memory:

* A loop remembers :meth:`LineSource.mark` just after its opening line and jumps back there; a
  ``while`` condition is kept as text and evaluated again at ``endwhile`` (so no mark before a line
  is ever needed: the plain-G1 path pays nothing for o-words).
* A false ``if``, a ``break``, or a ``sub`` met in the flow of the program skips forward line by line
  looking only at o-word heads (skipped lines are not parsed, as LinuxCNC does not execute them).
* ``sub`` met in the flow remembers where its body starts and skips it; ``call`` jumps there and
  ``return``/``endsub`` jumps back. A subroutine not defined (yet) in the program is looked for as
  ``NAME.ngc`` in :attr:`InterpreterSettings.subroutine_path`, then in the main program's directory;
  the file is opened for the call and closed after it.
* Each call saves #1-#30 (the arguments, the rest 0) and opens a scope for named locals;
  ``#<_value>`` / ``#<_value_returned>`` carry the returned value.
* Guards: ``max_call_depth`` (nested calls, recursion included) and ``max_loop_iterations`` (per
  loop, per run of it, an ``M98 ... L`` repeat count, and passes without a move in all loops
  together); beyond them a GCodeError names the limit. The loop keywords are
  :mod:`gcode_canon.oword_loops`. Blocks left open at the end of a file, or closed by the wrong
  keyword or label, are errors naming both lines.

Fanuc-style numbered programs (``O1000`` alone on a line, ``M98 P1000 L2``, ``M99``) are handled
here too, with the meaning :mod:`gcode_canon.dialect` selects.
"""

from __future__ import annotations

import io
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from gcode_canon.errors import GCodeError
from gcode_canon.lexer import split_comments
from gcode_canon.oword_loops import LoopKeywords, OBlock
from gcode_canon.source import LineSource, Mark

if TYPE_CHECKING:
    from gcode_canon.interpreter import Interpreter

N_ARGS = 30
KEYWORDS = frozenset((
    "sub", "endsub", "call", "return", "if", "elseif", "else", "endif", "while", "endwhile", "do",
    "repeat", "endrepeat", "break", "continue",
))
_FOLD = str.maketrans("", "", " \t\r")
_HEAD = re.compile(r"/?(?:n[0-9]+(?:\.[0-9]*)?)?o(<[^>]*>|[0-9]+)([a-z]*)")
_LABEL_NUMBER = re.compile(r"[0-9]+")
_KEYWORD = re.compile(r"[a-z]+")
_NAME_OK = re.compile(r"[a-z0-9_.\-]+")


def o_head(raw: str) -> tuple[str, str] | None:
    """``(label, keyword)`` of a raw line that starts with an O word, else None; cheap, no evaluation.
    The label is printable: ``o<name>`` or ``o100``."""
    if "o" not in raw and "O" not in raw:
        return None
    s = raw.translate(_FOLD)
    if "(" in s or ";" in s:
        try:
            s, _ = split_comments(s)
        except GCodeError:
            return None
    m = _HEAD.match(s.lower())
    if m is None:
        return None
    return _label(m.group(1)), m.group(2)


def _label(text: str) -> str:
    if text.startswith("<"):
        return f"o{text}"
    return f"o{int(text)}"


@dataclass(slots=True)
class Frame:
    """One active call: where to come back to and what to restore."""

    label: str
    source: LineSource
    own_source: bool  # opened for this call (closed on return)
    restore: Mark | None  # the source's place before the jump, when it was already open
    caller: LineSource
    caller_file: str
    call_line: int
    saved: list[float]
    blocks: list[OBlock]
    sub_line: int
    fanuc: bool = False
    repeats: int = 0  # M98 L: further runs still to do
    start: Mark | None = None


@dataclass(slots=True)
class SubDef:
    source: LineSource
    mark: Mark
    line: int
    fanuc: bool = False


@dataclass(slots=True)
class FlowControl(LoopKeywords):
    interp: Interpreter
    frames: list[Frame] = field(default_factory=list)
    blocks: list[OBlock] = field(default_factory=list)
    subs: dict[str, SubDef] = field(default_factory=dict)
    file_marks: dict[str, tuple[Mark, int]] = field(default_factory=dict)
    value: float = 0.0
    value_returned: bool = False
    main_dir: Path | None = None
    main_source: LineSource | None = None
    #: jumps back (a loop's next pass, an ``M98 ... L`` repeat) since the machine last moved, in all
    #: loops together, and where it stood then (:meth:`_idle_jump`)
    idle_jumps: int = 0
    idle_at: object = None

    # --- program start / end --------------------------------------------------------------------

    def reset(self, main: LineSource) -> None:
        self.close_all()
        self.frames = []
        self.blocks = []
        self.subs = {}
        self.file_marks = {}
        self.value = 0.0
        self.value_returned = False
        self.idle_jumps = 0
        self.idle_at = None
        self.main_source = main
        is_file = not isinstance(main.stream, io.StringIO)
        self.main_dir = Path(main.name).parent if is_file else None

    def close_all(self) -> None:
        for frame in self.frames:
            if frame.own_source:
                frame.source.close()
        self.frames = []

    def at_end_of_source(self, source: LineSource) -> None:
        """End of file of the current source: open blocks or an unfinished call are errors."""
        interp = self.interp
        last = max(source.line, 1)
        if self.frames and self.frames[-1].source is source:
            frame = self.frames[-1]
            if frame.fanuc:  # a numbered subprogram may simply run to the end of its file
                self._return(0.0, False, "M99")
                return
            raise GCodeError(f"File ended inside subroutine {frame.label} (sub at line {frame.sub_line}, "
                             f"called from {frame.caller_file}:{frame.call_line}) with no endsub",
                             interp.file, last)
        if self.blocks:
            b = self.blocks[-1]
            raise GCodeError(f"{b.label} {b.kind} at line {b.line} is not closed: file ended at line {last}",
                             interp.file, last)

    # --- the o-word line ----------------------------------------------------------------------------

    def execute(self, text: str) -> None:
        """Execute one folded line starting with ``o`` (comments left as ``(`` markers)."""
        s = text
        if s.startswith("o<"):
            end = s.find(">")
            if end < 0:
                raise GCodeError("Named o-word label is missing its closing '>'")
            name = s[2:end]
            if not name:
                raise GCodeError("Empty o-word label o<>")
            label = f"o<{name}>"
            i = end + 1
        elif s[1:2] in ("#", "["):  # o#<sub> call: a numbered label from a parameter or expression
            from gcode_canon.expressions import near_int

            value, i = self.interp.reader.real_value(s, 1)
            number = near_int(value, "O word label")
            if number < 0:
                raise GCodeError(f"O word label must not be negative: {number}")
            label = f"o{number}"
        else:
            m = _LABEL_NUMBER.match(s, 1)
            if m is None:
                raise GCodeError("O word needs a number or a <name> label")
            label = f"o{int(m.group())}"
            i = m.end()
        m = _KEYWORD.match(s, i)
        keyword = m.group() if m else ""
        if keyword == "":
            self._program_number(label, s[i:])
            return
        if keyword not in KEYWORDS:
            raise GCodeError(f"Unknown o-word keyword {keyword!r} after {label}")
        i = m.end()
        getattr(self, f"_kw_{keyword}")(label, s, i)

    def _rest_empty(self, s: str, i: int, what: str) -> None:
        if s[i:].strip("(") != "":
            raise GCodeError(f"Unexpected text after {what}: {s[i:].replace('(', '')!r}")

    def _value(self, s: str, i: int, label: str, kw: str) -> tuple[float, int]:
        if i >= len(s) or s[i] == "(":
            raise GCodeError(f"{label} {kw} needs a condition or value, e.g. [#1 GT 0]")
        return self.interp.reader.real_value(s, i)

    def _optional_value(self, s: str, i: int, label: str, kw: str) -> tuple[float | None, int]:
        if i >= len(s) or s[i] == "(":
            return None, i
        value, i = self.interp.reader.real_value(s, i)
        self._rest_empty(s, i, f"{label} {kw}")
        return value, i

    # --- skipping -----------------------------------------------------------------------------------

    def _skip(self, label: str, wanted: tuple[str, ...], opener: str, opener_line: int) -> tuple[str, str]:
        """Read lines of the current source until ``label`` with one of ``wanted``; return
        (keyword, raw line). The interpreter's line number follows."""
        interp = self.interp
        source = interp.source
        for raw in source:
            interp.line = source.line
            head = o_head(raw)
            if head is not None and head[0] == label and head[1] in wanted:
                return head[1], raw
        want = " or ".join(f"{label} {w}" for w in wanted)
        last = max(source.line, 1)
        raise GCodeError(f"{opener} at line {opener_line} has no matching {want}: file ended at line {last}",
                         interp.file, last)

    def _run_found(self, raw: str) -> None:
        """Execute an o-word line found by a skip (elseif, the while closing a do)."""
        from gcode_canon.lexer import parse_line

        block = parse_line(raw, self.interp.reader)
        assert block.o_text is not None
        self.execute(block.o_text)

    # --- conditionals -------------------------------------------------------------------------------

    def _kw_if(self, label: str, s: str, i: int) -> None:
        cond, i = self._value(s, i, label, "if")
        self._rest_empty(s, i, f"{label} if")
        self._branch(label, cond != 0.0, self.interp.line)

    def _branch(self, label: str, taken: bool, if_line: int) -> None:
        """Enter the branch if taken; else skip to the next elseif / else / endif of ``label``."""
        interp = self.interp
        while not taken:
            kw, raw = self._skip(label, ("elseif", "else", "endif"), f"{label} if", if_line)
            if kw == "endif":
                return
            if kw == "else":
                break
            block_text = self._folded(raw)
            j = block_text.find("elseif") + len("elseif")
            cond, j = self._value(block_text, j, label, "elseif")
            self._rest_empty(block_text, j, f"{label} elseif")
            taken = cond != 0.0
        self.blocks.append(OBlock("if", label, interp.line if taken else if_line))

    def _folded(self, raw: str) -> str:
        from gcode_canon.lexer import parse_line

        block = parse_line(raw, self.interp.reader)
        assert block.o_text is not None
        return block.o_text

    def _top(self, label: str, kinds: tuple[str, ...], kw: str) -> OBlock:
        if not self.blocks:
            raise GCodeError(f"{label} {kw} with no open {label} {' or '.join(kinds)}")
        top = self.blocks[-1]
        if top.label != label or top.kind not in kinds:
            raise GCodeError(f"{label} {kw} does not match the open {top.label} {top.kind} "
                             f"(line {top.line}); close that first")
        return top

    def _kw_elseif(self, label: str, s: str, i: int) -> None:
        top = self._top(label, ("if",), "elseif")
        self.blocks.pop()
        self._skip(label, ("endif",), f"{label} if", top.line)

    def _kw_else(self, label: str, s: str, i: int) -> None:
        self._rest_empty(s, i, f"{label} else")
        top = self._top(label, ("if",), "else")
        self.blocks.pop()
        self._skip(label, ("endif",), f"{label} if", top.line)

    def _kw_endif(self, label: str, s: str, i: int) -> None:
        self._rest_empty(s, i, f"{label} endif")
        self._top(label, ("if",), "endif")
        self.blocks.pop()

    # --- subroutines --------------------------------------------------------------------------------

    def _kw_sub(self, label: str, s: str, i: int) -> None:
        interp = self.interp
        self._rest_empty(s, i, f"{label} sub")
        if self.blocks:
            b = self.blocks[-1]
            raise GCodeError(f"{label} sub inside the open {b.label} {b.kind} (line {b.line}): "
                             "subroutines cannot be defined inside a block")
        if self.frames and not self.frames[-1].fanuc:
            raise GCodeError(f"Nested subroutine definition: '{label} sub' found inside called "
                             f"subroutine '{self.frames[-1].label}'")
        line = interp.line
        self.subs[label] = SubDef(interp.source, interp.source.mark(), line)
        self._skip(label, ("endsub",), f"{label} sub", line)

    def _kw_call(self, label: str, s: str, i: int) -> None:
        interp = self.interp
        args: list[float] = []
        n = len(s)
        while i < n and s[i] in "[(":
            if s[i] == "(":  # a comment between the arguments (LinuxCNC reads past it)
                i += 1
                continue
            value, i = interp.reader.real_value(s, i)
            args.append(value)
        self._rest_empty(s, i, f"{label} call (arguments go in [brackets])")
        if len(args) > N_ARGS:
            raise GCodeError(f"{label} call with {len(args)} arguments: at most {N_ARGS}")
        self._check_depth(label)
        source, own, restore, sub_line = self._locate(label)
        self._enter(label, source, own, restore, sub_line, args, fanuc=False)

    def _check_depth(self, label: str) -> None:
        limit = self.interp.settings.max_call_depth
        if len(self.frames) >= limit:
            raise GCodeError(f"{label} call: more than {limit} nested calls (max_call_depth): "
                             "runaway recursion?")

    def _locate(self, label: str) -> tuple[LineSource, bool, Mark | None, int]:
        """The source to run ``label`` from (positioned at its body), whether it was opened for the
        call, the place to restore in it afterwards, and the line of its ``sub``."""
        interp = self.interp
        d = self.subs.get(label)
        if d is not None and not d.source.stream.closed:
            restore = d.source.mark()
            d.source.jump(d.mark)
            return d.source, False, restore, d.line
        try:
            path = self._find_file(label)
        except GCodeError:
            found = self._scan_sub(label)
            if found is None:
                raise
            return found
        source = LineSource.from_file(path, interp.settings.max_line_length)
        try:
            key = str(path)
            cached = self.file_marks.get(key)
            if cached is not None:
                source.jump(cached[0])
                return source, True, None, cached[1]
            for raw in source:
                head = o_head(raw)
                if head is not None and head[0] == label and head[1] == "sub":
                    self.file_marks[key] = (source.mark(), source.line)
                    return source, True, None, source.line
            raise GCodeError(f"{label} call: {path} does not define {label} sub")
        except BaseException:
            source.close()
            raise

    def _scan_sub(self, label: str) -> tuple[LineSource, bool, Mark, int] | None:
        """LinuxCNC's forward seek (control_back_to): a sub not defined yet and not on the path may
        follow later in the main program's file; the subs passed on the way are recorded."""
        interp = self.interp
        src = interp.source
        if src is not self.main_source:
            return None
        back = src.mark()
        line = interp.line
        for raw in src:
            if raw.strip() == "%":  # nothing after the closing percent is read
                break
            head = o_head(raw)
            if head is not None and head[1] == "sub":
                self.subs.setdefault(head[0], SubDef(src, src.mark(), src.line))
                if head[0] == label:
                    return src, False, back, src.line
        src.jump(back)
        interp.line = line
        return None

    def search_dirs(self) -> list[Path]:
        dirs = [Path(p) for p in self.interp.settings.subroutine_path]
        if self.main_dir is not None:
            dirs.append(self.main_dir)
        return dirs

    def _find_file(self, label: str) -> Path:
        name = label[2:-1] if label.startswith("o<") else label[1:]
        if ".." in name or name.startswith(".") or not _NAME_OK.fullmatch(name):
            raise GCodeError(f"{label} call: the name {name!r} may not contain '/', '\\' or '..' nor start "
                             "with '.' (subroutine files must be on the subroutine path)")
        dirs = self.search_dirs()
        for d in dirs:
            candidate = d / f"{name}.ngc"
            try:
                found = candidate.is_file()
            except OSError as exc:  # ENAMETOOLONG and the like: the name cannot be a file's
                raise GCodeError(f"{label} call: cannot look for {name[:40]}....ngc in {d}: "
                                 f"{exc.strerror or exc}") from None
            if found:
                return candidate
        where = ", ".join(str(d) for d in dirs) or "(no subroutine path set)"
        raise GCodeError(f"{label} call: no subroutine {label} defined before the call and no file "
                         f"{name}.ngc on the subroutine path: {where}")

    def _enter(self, label: str, source: LineSource, own: bool, restore: Mark | None,
               sub_line: int, args: list[float], *, fanuc: bool, repeats: int = 0) -> None:
        interp = self.interp
        params = interp.params
        nums = params.numbered
        saved: list[float] = []
        if not fanuc:
            saved = nums[1:N_ARGS + 1]
            nums[1:N_ARGS + 1] = args + [0.0] * (N_ARGS - len(args))
            params.push_scope()
        frame = Frame(label, source, own, restore, interp.source, interp.file, interp.line, saved,
                      self.blocks, sub_line, fanuc, repeats, source.mark() if fanuc else None)
        self.frames.append(frame)
        self.blocks = []
        self.value_returned = False
        interp.switch_source(source)

    def _kw_return(self, label: str, s: str, i: int) -> None:
        # LinuxCNC returns from the running subroutine whatever label the return carries
        value, _ = self._optional_value(s, i, label, "return")
        if not self.frames or self.frames[-1].fanuc:
            raise GCodeError(f"{label} return outside a subroutine call")
        self._return(value or 0.0, value is not None, "return", self.frames[-1])

    def _kw_endsub(self, label: str, s: str, i: int) -> None:
        value, _ = self._optional_value(s, i, label, "endsub")
        frame = self._frame_for(label, "endsub")
        if self.blocks:
            b = self.blocks[-1]
            raise GCodeError(f"{label} endsub with {b.label} {b.kind} (line {b.line}) still open")
        self._return(value or 0.0, value is not None, "endsub", frame)

    def _frame_for(self, label: str, kw: str) -> Frame:
        if not self.frames or self.frames[-1].fanuc:
            raise GCodeError(f"{label} {kw} outside a subroutine call")
        frame = self.frames[-1]
        if frame.label != label:
            raise GCodeError(f"{label} {kw} inside {frame.label} (sub at line {frame.sub_line}): "
                             "labels do not match")
        return frame

    def _return(self, value: float, returned: bool, what: str, frame: Frame | None = None) -> None:
        interp = self.interp
        frame = frame or self.frames[-1]
        if frame.fanuc and frame.repeats > 0:
            self._idle_jump(f"M98 {frame.label.upper()} repeat")
            frame.repeats -= 1
            self.blocks = []
            assert frame.start is not None
            frame.source.jump(frame.start)
            return
        level = len(self.frames)
        self.frames.pop()
        self.blocks = frame.blocks
        if not frame.fanuc:
            interp.params.numbered[1:N_ARGS + 1] = frame.saved
            interp.params.pop_scope()
            self.value = value
            self.value_returned = returned
        if frame.own_source:
            frame.source.close()
        elif frame.restore is not None:
            frame.source.jump(frame.restore)
        interp.switch_source(frame.caller, frame.caller_file)
        interp.leave_call_level(level)

    # --- Fanuc-style numbered programs ----------------------------------------------------------------

    def _program_number(self, label: str, rest: str) -> None:
        from gcode_canon.dialect import Action, resolve

        self._rest_empty(rest, 0, f"program number {label.upper()}")
        interp = self.interp
        if interp.settings.disable_fanuc_style_sub:
            raise GCodeError(f"DISABLE_FANUC_STYLE_SUB is set, but found bare O-word {label.upper()}")
        meaning = resolve("O", interp.dialect)
        src = interp.source
        self.subs[label] = SubDef(src, src.mark(), interp.line, fanuc=True)
        if meaning.action is Action.PROGRAM_NUMBER:
            # LinuxCNC: a numbered program after the main one is reached only by M98
            if self.frames and self.frames[-1].fanuc:
                return
            if interp.seen_code:
                raise GCodeError(f"Program {label.upper()} reached in the flow of the program: the "
                                 "main program must end with M2/M30 before its subprograms")

    def m98(self, p: int, repeats: int) -> None:
        """M98 P<p> L<repeats>: run numbered program ``p`` (defined by a bare ``O<p>`` line)."""
        label = f"o{p}"
        if repeats <= 0:
            return
        limit = self.interp.settings.max_loop_iterations
        if repeats > limit:  # its runs are a loop: bounded as a repeat count is
            raise GCodeError(f"M98 P{p} L{repeats} is more than {limit} iterations (max_loop_iterations)")
        self._check_depth(label)
        d = self.subs.get(label)
        if d is None or d.source.stream.closed or not d.fanuc:
            d = self._scan_program(label)
        restore = d.source.mark()
        d.source.jump(d.mark)
        self._enter(label, d.source, False, restore, d.line, [], fanuc=True, repeats=repeats - 1)

    def _scan_program(self, label: str) -> SubDef:
        """Find ``O<n>`` later in the current source (LinuxCNC: subprograms follow the main one)."""
        from gcode_canon.dialect import Action, resolve

        interp = self.interp
        if resolve("M98", interp.dialect).action is Action.CALL_LABEL:
            raise GCodeError(f"M98 P{label[1:]}: no program number {label.upper()} read before the call")
        src = interp.source
        back = src.mark()
        line = interp.line
        try:
            for raw in src:
                head = o_head(raw)
                if head is not None and head[0] == label and head[1] == "":
                    d = SubDef(src, src.mark(), src.line, fanuc=True)
                    self.subs[label] = d
                    return d
        finally:
            src.jump(back)
            interp.line = line
        raise GCodeError(f"M98 P{label[1:]}: no program {label.upper()} in {interp.file}")

    def m99(self) -> bool:
        """M99: back after the calling M98; False in the main program (the caller ends it)."""
        if not self.frames:
            return False
        frame = self.frames[-1]
        if not frame.fanuc:
            raise GCodeError(f"M99 inside o-word subroutine {frame.label}: use {frame.label} endsub "
                             "or return")
        self._return(0.0, False, "M99", frame)
        return True
