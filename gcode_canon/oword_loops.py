"""The o-word loops: ``while``/``endwhile``, ``do``/``while``, ``repeat``/``endrepeat``, ``break`` and
``continue``, and the bounds that keep a program from running away in them.

A loop's body is read again from the source (its ``mark``), never held in memory. Every pass is
bounded: each loop by ``max_loop_iterations`` on its own, and the passes without a move in all loops
together (and ``M98 ... L`` repeats) by the same limit, since nested loops multiply. The rest of the
o-word flow (conditionals, subroutines, numbered programs) is :class:`gcode_canon.owords.FlowControl`,
which these keywords are part of.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from gcode_canon.errors import GCodeError

if TYPE_CHECKING:
    from gcode_canon.interpreter import Interpreter

_LOOP_END = {"while": "endwhile", "do": "while", "repeat": "endrepeat"}


@dataclass(slots=True)
class OBlock:
    """An open if / while / do / repeat block of the current call frame."""

    kind: str
    label: str
    line: int
    mark: tuple[int, int] | None = None
    cond: tuple[str, int] | None = None  # while: the folded line and where its condition starts
    count: int = 0
    remaining: int = 0



class LoopKeywords:
    """The loop keywords of :class:`gcode_canon.owords.FlowControl` (a mixin: the open blocks, the
    source marks and the skipping are FlowControl's)."""

    __slots__ = ()
    interp: Interpreter
    blocks: list[OBlock]
    idle_jumps: int
    idle_at: object

    if TYPE_CHECKING:  # supplied by FlowControl
        def _rest_empty(self, s: str, i: int, what: str) -> None: ...
        def _value(self, s: str, i: int, label: str, kw: str) -> tuple[float, int]: ...
        def _skip(self, label: str, wanted: tuple[str, ...], opener: str,
                  opener_line: int) -> tuple[str, str]: ...
        def _run_found(self, raw: str) -> None: ...
        def _top(self, label: str, kinds: tuple[str, ...], kw: str) -> OBlock: ...

    def _limit(self, b: OBlock) -> None:
        b.count += 1
        limit = self.interp.settings.max_loop_iterations
        if b.count > limit:
            raise GCodeError(f"{b.label} {b.kind} (line {b.line}) ran more than {limit} iterations "
                             "(max_loop_iterations): a runaway loop?")
        self._idle_jump(f"{b.label} {b.kind} (line {b.line})")

    def _idle_jump(self, where: str) -> None:
        """A jump back to run a loop's body again: no more than ``max_loop_iterations`` of them, in all
        loops together, without the machine moving. Each loop is bounded on its own, but nested loops
        multiply (``repeat [1e5]`` in ``repeat [1e5]``: 1e10 passes, hours of computing with nothing
        to show); a program whose loops move the machine is a long program, not a hang, and goes on."""
        pos = self.interp.pos
        if pos is not self.idle_at:
            self.idle_at = pos
            self.idle_jumps = 0
            return
        self.idle_jumps += 1
        limit = self.interp.settings.max_loop_iterations
        if self.idle_jumps > limit:
            raise GCodeError(f"{where}: more than {limit} loop passes without a move, nested loops "
                             "counted together (max_loop_iterations): a runaway loop?")

    def _kw_while(self, label: str, s: str, i: int) -> None:
        interp = self.interp
        cond, j = self._value(s, i, label, "while")
        self._rest_empty(s, j, f"{label} while")
        if self.blocks and self.blocks[-1].label == label and self.blocks[-1].kind == "do":
            b = self.blocks[-1]
            if cond != 0.0:
                self._limit(b)
                assert b.mark is not None
                interp.source.jump(b.mark)
            else:
                self.blocks.pop()
            return
        if cond != 0.0:
            self.blocks.append(OBlock("while", label, interp.line, interp.source.mark(), (s, i)))
        else:
            self._skip(label, ("endwhile",), f"{label} while", interp.line)

    def _kw_endwhile(self, label: str, s: str, i: int) -> None:
        self._rest_empty(s, i, f"{label} endwhile")
        b = self._top(label, ("while",), "endwhile")
        self._again(b)

    def _again(self, b: OBlock) -> None:
        """End of one pass of while ``b`` (endwhile or continue): test again, jump back or leave."""
        assert b.cond is not None and b.mark is not None
        cond, _ = self.interp.reader.real_value(*b.cond)
        if cond != 0.0:
            self._limit(b)
            self.interp.source.jump(b.mark)
            return
        self.blocks.pop()

    def _kw_do(self, label: str, s: str, i: int) -> None:
        self._rest_empty(s, i, f"{label} do")
        self.blocks.append(OBlock("do", label, self.interp.line, self.interp.source.mark()))

    def _kw_repeat(self, label: str, s: str, i: int) -> None:
        interp = self.interp
        value, i = self._value(s, i, label, "repeat")
        self._rest_empty(s, i, f"{label} repeat")
        count = round(value)
        limit = interp.settings.max_loop_iterations
        if count > limit:
            raise GCodeError(f"{label} repeat [{count}] is more than {limit} iterations "
                             "(max_loop_iterations)")
        if count <= 0:
            self._skip(label, ("endrepeat",), f"{label} repeat", interp.line)
            return
        self.blocks.append(OBlock("repeat", label, interp.line, interp.source.mark(), remaining=count))

    def _kw_endrepeat(self, label: str, s: str, i: int) -> None:
        self._rest_empty(s, i, f"{label} endrepeat")
        self._repeat_end(self._top(label, ("repeat",), "endrepeat"))

    def _repeat_end(self, b: OBlock) -> None:
        b.remaining -= 1
        if b.remaining > 0:
            self._idle_jump(f"{b.label} repeat (line {b.line})")
            assert b.mark is not None
            self.interp.source.jump(b.mark)
        else:
            self.blocks.pop()

    def _loop(self, label: str, kw: str) -> OBlock:
        for b in reversed(self.blocks):
            if b.kind != "if" and b.label == label:
                break
        else:
            raise GCodeError(f"{label} {kw} is not inside an {label} while, do or repeat loop")
        while self.blocks[-1] is not b:
            self.blocks.pop()
        return b

    def _kw_break(self, label: str, s: str, i: int) -> None:
        self._rest_empty(s, i, f"{label} break")
        b = self._loop(label, "break")
        self.blocks.pop()
        self._skip(label, (_LOOP_END[b.kind],), f"{label} {b.kind}", b.line)

    def _kw_continue(self, label: str, s: str, i: int) -> None:
        self._rest_empty(s, i, f"{label} continue")
        b = self._loop(label, "continue")
        if b.kind == "while":
            self._again(b)
            if self.blocks and self.blocks[-1] is b:
                return
            self._skip(label, ("endwhile",), f"{label} while", b.line)
        elif b.kind == "repeat":
            self._repeat_end(b)
            if self.blocks and self.blocks[-1] is b:
                return
            self._skip(label, ("endrepeat",), f"{label} repeat", b.line)
        else:  # do: the closing while decides
            _, raw = self._skip(label, ("while",), f"{label} do", b.line)
            self._run_found(raw)
