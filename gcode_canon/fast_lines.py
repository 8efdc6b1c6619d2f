"""A straight line read again, compiled into one function: its values, the fast path and its commands.

The program loop runs a line the line cache keeps through the line's ``fast`` function
(``ProgramLoopMixin._fast_runner``). For a straight move with axis words (an optional G0/G1, X Y Z F
words, a comment that is not active: :attr:`~gcode_canon.lexer.Block.plain`) that function is made
here, as Python source for the line's shape (which words, which of them computed, the motion code
if the line has one, the comment), compiled once per shape and bound to the line's own values or
expression nodes. It is :meth:`ProgramLoopMixin._fast_values` written out for that shape: the tests
a constant word makes needless left out (no G code: the motion mode in force is tested; G0: no zero
feed to refuse), the values computed in the line's order, no call between them and the move.

What it reads of the interpreter it reads at each run (the modal state, the position, the offsets),
as ``_fast_values`` does; what it declines (a negative or zero feed, a motion mode other than G0/G1,
a position that is not finite, an expression that fails) it leaves unchanged and returns None, and
the line goes the general way, which says any error in its place.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from gcode_canon.commands import (
    Canon,
    Pose,
    SetFeedRate,
    StraightFeed,
    StraightTraverse,
    new_comment,
    slot_setters,
)
from gcode_canon.errors import GCodeError

EXPRESSION_ERRORS = (GCodeError, RecursionError, ArithmeticError, ValueError)
"""What an expression may raise: on the fast path, the line goes the general way, which says it."""

_FACTORIES: dict[str, Callable[..., Callable[[], tuple[Canon, ...] | None]]] = {}
"""Generated factories by their source: one ``compile`` per shape of line."""

_FEED_END, _FILE, _LINE = slot_setters(StraightFeed)
_TRAVERSE_END = slot_setters(StraightTraverse)[0]
_GLOBALS = {"isfinite": math.isfinite, "new_pose": tuple.__new__, "Pose": Pose, "SetFeedRate": SetFeedRate,
            "new_object": object.__new__, "Feed": StraightFeed, "Traverse": StraightTraverse,
            "feed_end": _FEED_END, "traverse_end": _TRAVERSE_END, "set_file": _FILE, "set_line": _LINE,
            "new_comment": new_comment, "ERRORS": EXPRESSION_ERRORS}
"""The generated code's names. A move is made as ``new_straight_feed`` makes it (``slot_setters``),
without the call to it."""


def straight_function(interp: Any, motion: int | None, values: dict[str, object],
                      comment: str | None) -> Callable[[], tuple[Canon, ...] | None]:
    """The fast path of one straight line with at least one of X Y Z (module docstring): ``motion``
    its G0/G1 (0, 10) or None, ``values`` its words in the line's order (letter to a constant or a
    function computing the value now), ``comment`` its comment's text or None. The function returns
    the line's commands, or None with nothing changed. The factory is found by the line's shape (its
    motion, its letters in order and which of them are computed, a comment or not), which decides its
    source: writing the source out for each line to find it took about 17 µs a line."""
    shape = (motion, tuple((letter, callable(node)) for letter, node in values.items()), comment is not None)
    make = _BY_SHAPE.get(shape)
    if make is None:
        make = _BY_SHAPE[shape] = _factory(motion, values, comment)
    return make(interp, comment, *values.values())


_BY_SHAPE: dict[tuple[object, ...], Callable[..., Callable[[], tuple[Canon, ...] | None]]] = {}
"""The factories by the shape of line (:func:`straight_function`)."""


def _factory(motion: int | None, values: dict[str, object],
             comment: str | None) -> Callable[..., Callable[[], tuple[Canon, ...] | None]]:
    """The factory of :func:`straight_function`'s functions for the shape of this line: ``make(interp,
    text, *values)`` binds a line's comment and values (or expression functions)."""
    names: list[str] = []
    lines: list[str] = []
    computed = [letter for letter, node in values.items() if callable(node)]
    for letter in values:
        names.append(f"n_{letter}")
    if computed:  # evaluated in the line's order; a failure sends the line the general way
        lines.append("try:")
        lines += [f" v_{letter} = n_{letter}()" for letter in computed]
        lines += ["except ERRORS:", " return None"]
    value = {letter: (f"v_{letter}" if callable(node) else f"n_{letter}") for letter, node in values.items()}
    lines.append("self = interp")
    if motion is None:
        lines += ["motion = self.motion", "if motion != 0 and motion != 10:", " return None"]
    else:
        lines.append(f"motion = {motion}")
    lines.append("scale = self.scale")
    if "f" in values:
        lines += [f"feed = {value['f']} * scale", "if feed < 0.0 or not isfinite(feed):", " return None"]
    else:
        lines.append("feed = self.feed")
    if motion is None:
        lines += ["if motion == 10 and feed == 0.0:", " return None"]
    elif motion == 10:
        lines += ["if feed == 0.0:", " return None"]
    lines.append("prog = self.prog")
    axes = [(k, letter) for k, letter in enumerate("xyz") if letter in values]
    lines += [f"{letter} = prog[{k}]" for k, letter in enumerate("xyz") if letter not in values]
    lines.append("if self.absolute:")
    lines += [f" {letter} = {value[letter]} * scale" for _, letter in axes]
    lines.append("else:")
    lines += [f" {letter} = prog[{k}] + {value[letter]} * scale" for k, letter in axes]
    lines += ["s = self.frames.sum", "mx = x + s[0]", "my = y + s[1]", "mz = z + s[2]",
              "if not isfinite(mx + my + mz):",  # any of them not finite (or a sum too large to add)
              " return None",
              "prog[0] = x", "prog[1] = y", "prog[2] = z",
              "tail = self._tail",
              "if tail is None:",  # A-W do not change on fast lines: computed once per run of them
              " tail = self._tail = (prog[3] + s[3], prog[4] + s[4], prog[5] + s[5], prog[6] + s[6],"
              " prog[7] + s[7], prog[8] + s[8])",
              "end = new_pose(Pose, (mx, my, mz, *tail))",
              "self.pos = end",
              "file = self.file",
              "line = self.line"]
    if motion is None:
        lines += ["if motion:", " cmd = new_object(Feed)", " feed_end(cmd, end)",
                  "else:", " cmd = new_object(Traverse)", " traverse_end(cmd, end)"]
    elif motion:
        lines += ["cmd = new_object(Feed)", "feed_end(cmd, end)"]
    else:
        lines += ["cmd = new_object(Traverse)", "traverse_end(cmd, end)"]
    lines += ["set_file(cmd, file)", "set_line(cmd, line)"]
    first = "new_comment(text, file, line), " if comment is not None else ""  # _step_comment runs first
    lines += ["self.motion = motion",
              "if feed != self.feed:",
              " self.feed = feed",
              f" return ({first}SetFeedRate(feed, file=file, line=line), cmd)",
              f"return ({first}cmd,)"]
    body = "".join(f"  {line}\n" for line in lines)
    source = f"def make(interp, text, {', '.join(names)}):\n def run():\n{body} return run\n"
    make = _FACTORIES.get(source)
    if make is None:
        namespace = dict(_GLOBALS)
        exec(compile(source, "<fast line>", "exec"), namespace)
        make = _FACTORIES[source] = namespace["make"]  # type: ignore[assignment]
    return make
