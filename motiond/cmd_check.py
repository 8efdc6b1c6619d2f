"""``canon check``: interpret a program without a machine and print its canonical commands.

A check is a dry run: the machine starts at zero with every offset zero (or as a ``--var`` parameter
file says), inputs read 0, probes trip at their end point, and no parameter file is ever written.
Text output names each command as LinuxCNC's canonical function (``STRAIGHT_FEED(...)``) with its
source line, so it can be set beside ``rs274`` output (a line of a subroutine file as ``FILE:LINE``);
``--json`` prints one object per command.
``--dialect`` picks the meaning of the codes LinuxCNC and gcode-canon disagree on; ``--subroutine-path``
(repeatable) lists the directories ``o<name> call`` looks in (then the program's own directory). The
machine file's ``[interpreter]`` table gives the defaults of these (:mod:`motiond.interp_settings`).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from motiond.cli import add_common, program_file


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from motiond.interp_settings import add_arguments as add_interp_arguments

    add_common(parser)
    add_interp_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from gcode_canon.interpreter import Interpreter
    from gcode_canon.machine import DryRunMachine
    from motiond.config_check import load_checked
    from motiond.interp_settings import settings_from_args
    from motiond.progress import line_progress

    program_file(args.file)
    # the demo machine without --config: then any of the nine axes may be named
    settings = settings_from_args(load_checked(args.config), args, dry_run=True)
    interp = Interpreter(settings, DryRunMachine())
    out = sys.stdout
    write = out.write
    # progress on a terminal while the commands go to a file or a pipe (on the same terminal the
    # commands themselves show the progress)
    show = sys.stderr.isatty() and not out.isatty() and not args.json
    with line_progress(f"checking {Path(args.file).name}", args.file, enabled=show) as advance:
        _write(interp, args, write, advance if show else None)
    out.flush()
    return 0


def _write(interp: Any, args: argparse.Namespace, write: Callable[[str], Any],
           advance: Callable[[int], None] | None) -> None:
    from itertools import islice

    from motiond.progress import tracked

    commands = interp.run_file(args.file)
    if advance is not None:
        commands = tracked(commands, args.file, advance)
    if args.json:
        import json

        dumps = json.dumps
        for cmd in commands:
            write(dumps(to_json(cmd)) + "\n")
    else:
        block: list[Any] = []
        fill = block.extend
        text = _TextBlock(args.file)
        try:
            # the commands are gathered a block at a time and then written out: interpreting a block of
            # lines and then formatting it takes less CPU time than taking turns at each command
            # (9 % less on bench/interpreter.py's mixed program, as measured with
            # bench/interpreter_ab.py); the text is the same. list.extend gathers them without a
            # Python step per command, and keeps those it got when the interpreter raises.
            while True:
                fill(islice(commands, _BLOCK))
                if len(block) < _BLOCK:  # the program's end
                    break
                write(text(block))
                block.clear()
        finally:  # the commands before an error are printed before it
            write(text(block))


_BLOCK = 256
"""Commands formatted and written at a time: one write call per block of lines (a write call per line
costs more), and the block's commands kept no longer than that."""


class _TextBlock:
    """``canon check``'s text of a block of commands (as :func:`format_text` with the line number in
    front, ``FILE:LINE`` for a subroutine file's lines), one of two ways that give the same text.

    A number is written by looking its text up (:class:`_NumberTexts`, :meth:`cached`) where a
    program's numbers come back (loops, parameters, a part's grid of coordinates): a dict lookup in C
    instead of ``%.4f``'s exact decimal conversion, about 0.25 µs a number. A number seen for the first
    time costs more that way (about 0.6 µs more: the Python ``__missing__`` call and the insertion), so
    a block whose numbers are mostly new (more new numbers than commands: a CAM program's path, where
    hardly any point comes back) sends the next blocks the direct way (:meth:`direct`, ``%`` over the
    whole block), and the lookup is tried again after 16 blocks, then 32, 64 ... while it does not pay
    (the tries cost a program of new numbers about 2 % of its text). bench/interpreter.py's mixed
    program: the text of its 100,000 commands in 0.82-0.87 of the time; the plain one: the same."""

    def __init__(self, main: str) -> None:
        from gcode_canon.commands import ArcFeed, Comment, StraightFeed, StraightTraverse

        self.main = main
        self.arc = ArcFeed
        self.comment = Comment
        self.straight = {
            StraightFeed: "%6d STRAIGHT_FEED(%.4f, %.4f, %.4f, 0.0000, 0.0000, 0.0000)\n",
            StraightTraverse: "%6d STRAIGHT_TRAVERSE(%.4f, %.4f, %.4f, 0.0000, 0.0000, 0.0000)\n",
        }
        self.heads = {StraightFeed: "%6d STRAIGHT_FEED(", StraightTraverse: "%6d STRAIGHT_TRAVERSE("}
        self.texts = _NumberTexts()
        self.wait = 0  # blocks still to be written the direct way
        self.interval = _RETRY_FIRST  # the wait after a block whose numbers were mostly new

    def __call__(self, commands: list[Any]) -> str:
        if self.wait:
            self.wait -= 1
            return self.direct(commands)
        texts = self.texts
        known = len(texts)
        text = self.cached(commands)
        if len(texts) - known > len(commands):  # mostly new numbers: the lookup did not pay
            self.wait = self.interval
            self.interval = min(2 * self.interval, _RETRY_MAX)
        else:
            self.interval = _RETRY_FIRST
        if len(texts) > _TEXTS_MAX:
            texts.clear()
        return text

    def cached(self, commands: list[Any]) -> str:
        """The block's text, each number of the bulk (straight moves with A-W at zero, arcs with U V W
        at zero) looked up in :attr:`texts` with its ", " after it, the pieces joined; any other line as
        :meth:`direct` writes it (``format_text``)."""
        main, arc_class, comment_class = self.main, self.arc, self.comment
        head_of = self.heads.get
        num = self.texts.__getitem__  # in C where the number is known
        zeros = (0.0,) * 6
        parts: list[str] = []
        put = parts.append
        for cmd in commands:
            file = cmd.file
            if file and file != main:  # a subroutine's file: FILE:LINE where the number stands
                put(f"{file}:{cmd.line} {format_text(cmd)}\n")
                continue
            cls = cmd.__class__
            head = head_of(cls)
            if head is not None:
                e = cmd.end
                if e[3:] == zeros:  # the bulk
                    parts += (head % cmd.line, num(e[0]), num(e[1]), num(e[2]), "0.0000, 0.0000, 0.0000)\n")
                    continue
            elif cls is arc_class:
                e = cmd.end
                if not (e[6] or e[7] or e[8]):
                    f, s, n = cmd.plane._value_
                    c = cmd.center
                    if e[3] or e[4] or e[5]:
                        parts += (f"{cmd.line:6d} ARC_FEED(", num(e[f]), num(e[s]), num(c[f]), num(c[s]),
                                  f"{cmd.turns}, ", num(e[n]), num(e[3]), num(e[4]), num(e[5])[:-2], ")\n")
                    else:  # A B C at 0 (the bulk): written as _num writes them, not looked up
                        parts += (f"{cmd.line:6d} ARC_FEED(", num(e[f]), num(e[s]), num(c[f]), num(c[s]),
                                  f"{cmd.turns}, ", num(e[n]), "0.0000, 0.0000, 0.0000)\n")
                    continue
            # any other command, and a move the branches above leave (A-W not all at zero)
            put(f'{cmd.line:>6} COMMENT("{cmd.text}")\n' if cls is comment_class
                else f"{cmd.line:>6} {format_text(cmd)}\n")
        return "".join(parts)

    def direct(self, commands: list[Any]) -> str:
        """The block's text with its straight moves and arcs (A-W at zero) formatted with one ``%`` (their
        formats joined, their values in one tuple: one call instead of one per line), and then
        ``_num``'s "0.0000" for "-0.0000" over the block's text (a value that prints so is below
        0.00005; any other starts "-0.000" and goes on with a digit that is not 0 on its 4th decimal, or
        has another digit before the point). Other lines are formatted on their own and go in as ``%s``
        values; one whose text holds "-0.0000" itself (a comment may) ends the formatting there and is
        put after it as it is, so that nothing of it is replaced."""
        main, arc_class, comment_class = self.main, self.arc, self.comment
        straight = self.straight.get
        zeros = (0.0,) * 6
        done: list[str] = []  # the text of the block so far, in pieces
        forms: list[str] = []  # since then: a format per line, and the values of them all
        form = forms.append
        values: list[Any] = []
        put = values.append
        for cmd in commands:
            file = cmd.file
            if file and file != main:  # a subroutine's file: FILE:LINE where the number stands
                text = f"{file}:{cmd.line} {format_text(cmd)}\n"
            else:
                cls = cmd.__class__
                line_form = straight(cls)
                if line_form is not None:
                    e = cmd.end
                    if e[3:] == zeros:  # the bulk
                        form(line_form)
                        values += (cmd.line, e[0], e[1], e[2])
                        continue
                elif cls is arc_class:
                    e = cmd.end
                    if not (e[6] or e[7] or e[8]):
                        f, s, n = cmd.plane._value_
                        c = cmd.center
                        if e[3] or e[4] or e[5]:
                            form(_ARC_LINE)
                            values += (cmd.line, e[f], e[s], c[f], c[s], cmd.turns, e[n], e[3], e[4], e[5])
                        else:  # A B C at 0 (the bulk): written as _num writes them, not formatted
                            form(_ARC_LINE_ABC0)
                            values += (cmd.line, e[f], e[s], c[f], c[s], cmd.turns, e[n])
                        continue
                # any other command, and a move the branches above leave (A-W not all at zero)
                text = (f'{cmd.line:>6} COMMENT("{cmd.text}")\n' if cls is comment_class
                        else f"{cmd.line:>6} {format_text(cmd)}\n")
            if "-0.0000" in text:  # not to be replaced: the formatting so far ends here
                done.append(_formatted(forms, values))
                done.append(text)
                forms.clear()
                values.clear()
            else:
                form("%s")
                put(text)
        done.append(_formatted(forms, values))
        return "".join(done)


_RETRY_FIRST = 16
"""Blocks written the direct way after one whose numbers were mostly new, doubled at each such block
after it (up to ``_RETRY_MAX``), back to this after a block where the lookup paid."""
_RETRY_MAX = 256
_TEXTS_MAX = 1 << 15
"""Numbers :class:`_NumberTexts` keeps (about 4 MB) before it is emptied and fills again."""


class _NumberTexts(dict):
    """A number's text as ``canon check`` writes it in a move or an arc, ", " after it: ``%.4f`` with
    "0.0000" for "-0.0000" (as :meth:`_TextBlock.direct`'s replacement and :func:`_num` write it), made
    once per number and kept. Equal keys give the same text (0.0 and -0.0 both "0.0000"; 1 and 1.0);
    a NaN is not equal to itself and is formatted each time ("nan", as ``%.4f`` writes it)."""

    __slots__ = ()

    def __missing__(self, value: float) -> str:
        text = f"{value:.4f}, "
        if text == "-0.0000, ":
            text = "0.0000, "
        self[value] = text
        return text


def _formatted(forms: list[str], values: list[Any]) -> str:
    """``forms`` joined, formatted with ``values``, with "0.0000" for "-0.0000" (:class:`_TextBlock`)."""
    text = "".join(forms) % tuple(values)
    return text.replace("-0.0000", "0.0000") if "-0.0000" in text else text


def _num(v: float) -> str:
    """Four decimals as rs274 prints, without "-0.0000" for rounding noise around zero."""
    return f"{v:.4f}" if abs(v) >= 0.00005 else "0.0000"


def _pose_text(p) -> str:
    values = list(p[:6])
    if any(p[6:]):
        values += list(p[6:])
    return ", ".join(_num(v) for v in values)


def _value_text(v: object) -> str:
    import enum

    from gcode_canon.commands import Pose

    if isinstance(v, Pose):
        return _pose_text(v)
    if isinstance(v, bool):
        return str(v).upper()
    if isinstance(v, float):
        return _num(v)
    if isinstance(v, enum.Enum):
        return v.name
    if isinstance(v, str):
        return repr(v)
    return str(v)


def format_text(cmd) -> str:
    """``NAME(args)``: moves give x, y, z, a, b, c (u, v, w when used); ARC_FEED as LinuxCNC orders
    its arguments (first end, second end, first centre, second centre, rotation, normal end, a, b, c:
    the plane is the last SELECT_PLANE's); units, planes, path modes and texts as rs274 writes them."""
    name = cmd.NAME
    if name == "STRAIGHT_FEED" or name == "STRAIGHT_TRAVERSE":  # the bulk: no introspection
        e = cmd.end
        if e[6] or e[7] or e[8]:
            return f"{name}({_pose_text(e)})"
        a, b, c = e[3], e[4], e[5]  # A B C are mostly 0: no float formatting for them then
        tail = ", 0.0000, 0.0000, 0.0000)" if not (a or b or c) else f", {_num(a)}, {_num(b)}, {_num(c)})"
        text = f"{name}({e[0]:.4f}, {e[1]:.4f}, {e[2]:.4f}"
        # as _num: no "-0.0000" (a value that prints so is below 0.00005; any other starts "-0.000" and
        # goes on with a digit that is not 0 on its 4th decimal, or has another digit before the point)
        if "-0.0000" in text:
            text = text.replace("-0.0000", "0.0000")
        return text + tail
    if name == "ARC_FEED":  # (no import statement here: it costs a microsecond per call)
        f, s, n = cmd.plane._value_  # Enum's value property is Python code: read per arc
        e, c = cmd.end, cmd.center
        # one formatting, then _num's "0.0000" for "-0.0000" (see the straight moves above)
        text = _ARC_TEXT % (e[f], e[s], c[f], c[s], cmd.turns, e[n], e[3], e[4], e[5])
        if "-0.0000" in text:
            text = text.replace("-0.0000", "0.0000")
        if e[6] or e[7] or e[8]:
            text += ", " + ", ".join(_num(v) for v in e[6:])
        return f"{cmd.NAME}({text})"
    special = _LINUXCNC_STYLE.get(cmd.NAME)
    if special is not None:
        return f"{cmd.NAME}({special(cmd)})"
    import dataclasses

    fields = [fl.name for fl in dataclasses.fields(cmd) if fl.name not in ("file", "line")]
    return f"{cmd.NAME}({', '.join(_value_text(getattr(cmd, name)) for name in fields)})"


_ARC_TEXT = "%.4f, %.4f, %.4f, %.4f, %s, %.4f, %.4f, %.4f, %.4f"
_ARC_LINE = f"%6d ARC_FEED({_ARC_TEXT})\n"
_ARC_LINE_ABC0 = "%6d ARC_FEED(%.4f, %.4f, %.4f, %.4f, %s, %.4f, 0.0000, 0.0000, 0.0000)\n"

# Arguments written as LinuxCNC's rs274 writes them, where canon's command carries the same thing.
_LINUXCNC_STYLE = {
    "USE_LENGTH_UNITS": lambda c: "CANON_UNITS_MM" if c.metric else "CANON_UNITS_INCHES",
    "SELECT_PLANE": lambda c: f"CANON_PLANE_{c.plane.name}",
    "MESSAGE": lambda c: f'"{c.text}"',
    "COMMENT": lambda c: f'"{c.text}"',
    "SET_MOTION_CONTROL_MODE": lambda c: (
        {"EXACT_PATH": "CANON_EXACT_PATH", "EXACT_STOP_MODAL": "CANON_EXACT_STOP"}.get(
            c.mode.name, "CANON_CONTINUOUS") + f", {c.tolerance:.6f}, {c.naive_cam_tolerance:.6f}"
    ),
}


def to_json(cmd) -> dict:
    """``line``, ``file``, ``command`` (NAME), the end point as x..w for moves, then the fields."""
    import dataclasses
    import enum

    from gcode_canon.commands import AXES, Pose

    obj: dict = {"line": cmd.line, "file": cmd.file, "command": cmd.NAME}
    end = getattr(cmd, "end", None)
    if cmd.MOVES and end is not None:
        obj.update(zip(AXES, end, strict=True))
    for fl in dataclasses.fields(cmd):
        if fl.name in ("file", "line", "end"):
            continue
        v = getattr(cmd, fl.name)
        if isinstance(v, Pose):
            v = dict(zip(AXES, v, strict=True))
        elif isinstance(v, enum.Enum):
            v = v.name
        obj[fl.name] = v
    return obj
