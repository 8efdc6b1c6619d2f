"""Spindle-synchronized motion: G33 (synchronized move), G33.1 (rigid tapping), G76 (threading cycle).

LinuxCNC's semantics (interp_convert.cc ``convert_straight`` and ``convert_threading_cycle``): each is
a feed whose speed follows the spindle, ``K`` (G33, G33.1) or ``P`` (G76) units of travel per
revolution, bracketed by ``START_SPEED_FEED_SYNCH`` / ``STOP_SPEED_FEED_SYNCH``
(:class:`~gcode_canon.commands.SpindleSync`, :class:`~gcode_canon.commands.SpindleSyncStop`); the
spindle must be turning. G33.1 is one :class:`~gcode_canon.commands.RigidTap` (in, reverse, out to
where it started); G76 expands into passes (:mod:`gcode_canon.threading_cycle`), the feed override off
while each cuts. The pitch is handed on in machine units (mm).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from gcode_canon.commands import (
    Canon,
    RigidTap,
    SetOverrides,
    SpindleSync,
    SpindleSyncStop,
    StraightFeed,
    StraightTraverse,
)
from gcode_canon.errors import GCodeError
from gcode_canon.offsets import ROTARY_INDEXES

if TYPE_CHECKING:
    from gcode_canon.lexer import Block

SYNC_MOTIONS = (330, 331, 760)
"""G33, G33.1, G76 (motion codes times ten)."""

SYNC_WORDS: dict[int, str] = {330: "ke", 331: "ike", 760: "ijkpqrlhe"}
"""The words each synchronized motion uses (the block checks take them as used)."""


def check_sync_block(motion: int, words: dict[str, float]) -> None:
    """LinuxCNC's word checks for G33/G33.1 (check_other_codes), before anything on the line runs."""
    if motion in (330, 331):
        if "k" not in words:
            raise GCodeError("K word missing with G33")
        if "f" in words:
            raise GCodeError("F word used with G33")


class SpindleSyncMixin:
    """G33, G33.1 and G76 for :class:`~gcode_canon.interpreter.Interpreter` (its state is used)."""

    def _sync_motion(self, motion: int, block: Block) -> None:
        name = {330: "G33", 331: "G33.1", 760: "G76"}[motion]
        if self.spindle is None:  # type: ignore[attr-defined]
            raise GCodeError(f"Spindle not turning in {name}" if motion != 760
                             else "Chosen spindle (0) not turning in G76")
        if motion == 760:
            self._threading_cycle(block)
            return
        if self.comp is not None:  # type: ignore[attr-defined]
            raise GCodeError(f"Cannot use {name} with cutter radius compensation on")
        k = block.take("k")
        i = block.take("i")
        block.take("e")
        assert k is not None  # check_sync_block
        target = self._target(block)  # type: ignore[attr-defined]
        end = self._to_machine(target)  # type: ignore[attr-defined]
        if not math.isfinite(sum(end)):
            raise GCodeError("Coordinate out of range")
        f, n = self.file, self.line  # type: ignore[attr-defined]
        self._emit(SpindleSync(k * self.scale, file=f, line=n))  # type: ignore[attr-defined]
        if motion == 330:
            self._emit(StraightFeed(end, file=f, line=n))  # type: ignore[attr-defined]
            self.prog = target  # type: ignore[attr-defined]
            self.pos = end  # type: ignore[attr-defined]
        else:  # the tap comes back to where it started: the position does not change
            self._emit(RigidTap(end, max(i, 1.0) if i is not None else 1.0,  # type: ignore[attr-defined]
                                file=f, line=n))
        self._emit(SpindleSyncStop(file=f, line=n))  # type: ignore[attr-defined]

    def _threading_cycle(self, block: Block) -> None:
        # imported here, for G76 only: not every program's start-up (2.5 ms of canon check's 0.1 s)
        from gcode_canon import threading_cycle as tc

        if self.comp is not None:  # type: ignore[attr-defined]
            raise GCodeError("Cannot use G76 threading cycle with cutter radius compensation on")
        scale = self.scale  # type: ignore[attr-defined]

        def length(letter: str) -> float | None:
            v = block.take(letter)
            return None if v is None else v * scale

        words = tc.ThreadWords(p=length("p"), i=length("i"), j=length("j"), k=length("k"),
                               r=block.take("r"), q=block.take("q"), h=block.take("h"), e=length("e"),
                               l=block.take("l"))
        tc.check_words(words)
        target = self._target(block)  # type: ignore[attr-defined]
        here = list(self.prog)  # type: ignore[attr-defined]
        if any(abs(target[k] - here[k]) > 1e-12 for k in ROTARY_INDEXES) or \
                any(abs(target[k] - here[k]) > 1e-12 for k in range(6, len(here))):
            raise GCodeError("Cannot move rotary axes with G76")  # LinuxCNC: also U, V, W
        ops = tc.expand(words, here[0], here[2], target[0], target[2],
                        diameter_mode=self.diameter_mode)  # type: ignore[attr-defined]
        f, n = self.file, self.line  # type: ignore[attr-defined]
        for op in ops:
            cmd: Canon
            if op.kind is tc.OpKind.SYNC:
                cmd = SpindleSync(op.value, file=f, line=n)
            elif op.kind is tc.OpKind.SYNC_STOP:
                cmd = SpindleSyncStop(file=f, line=n)
            elif op.kind is tc.OpKind.FEED_OVERRIDE:
                cmd = SetOverrides(feed=op.value > 0, file=f, line=n)
            else:
                prog = list(here)
                prog[0], prog[2] = op.x, op.z
                if op is ops[-1]:  # to the block's end point, Y and the rest as programmed
                    prog = list(target)
                pose = self._to_machine(prog)  # type: ignore[attr-defined]
                move = StraightTraverse if op.kind is tc.OpKind.TRAVERSE else StraightFeed
                cmd = move(pose, file=f, line=n)
                self.prog = prog  # type: ignore[attr-defined]
                self.pos = pose  # type: ignore[attr-defined]
            self._emit(cmd)  # type: ignore[attr-defined]
