"""Setpoints sent ahead of their SYNC: the master's messages to the SYNC process, and its buffer.

With ``[canopen] sync = "process"`` a process of its own sends the SYNC (:mod:`fieldbus.canopen.
sync_process`). It also sends the drives' RPDOs: the master's cycle computes them up to
``setpoint_lead`` SYNCs ahead and hands each set over tagged with the SYNC that is to latch it, and the
SYNC process sends a set right after the SYNC before its own. A cycle late by less than
``setpoint_lead - 1`` periods (plus the part of a period the RPDOs leave) then costs the drives no
setpoint: they were in the buffer before it. With the RPDOs sent by the cycle itself (the kernel's
SYNC, or a lead of 1) every cycle late past one period costs each drive one.

What must not wait in a buffer goes past it:

* a stop (quick stop, disable, an enable that failed) is sent by the master at once on its own socket
  *and* through the SYNC process as ``NOW_FLUSH``, which drops every set still buffered before it
  sends the stop's frames. The SYNC process is the only sender of buffered frames and reads its
  messages in order, so its copy of the stop is the last RPDO a drive gets before the next SYNC:
  no target or controlword computed before the stop reaches a drive after it. The generation number
  a flush raises makes a set pushed before it void even if it were read after it.
* a drive that becomes active (enabled, or back from homing) gets its holding target at once and in
  every set already buffered (``NOW_MERGE``), so no SYNC finds it without a setpoint; a drive that
  starts homing is taken out of every buffered set (``DROP``): homing's controlword goes by SDO, and
  a buffered cyclic controlword must not clear its start bit.

The messages are small binary records, each written to the SYNC process's input in one write of at
most ``PIPE_BUF`` bytes (so atomic: never interleaved, never half there).
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable, Iterable, Iterator, Sequence

log = logging.getLogger(__name__)

#: kind (u8), generation (u32), tag: the SYNC number that latches the frames (i64), frame count (u16)
HEADER = struct.Struct("<BIqH")
#: COB-ID (u16), length (u8), data padded to 8 bytes
FRAME = struct.Struct("<HB8s")
#: the SYNC process's report of each SYNC, right after it was sent: its ``time.monotonic`` time, its
#: number (1 for the first), and 1 when a set of RPDOs went out for it in the period before it, else 0
REPORT = struct.Struct("<dqq")

START = 1  # the SYNC begins
PUSH = 2  # frames for SYNC ``tag``: buffered, or sent at once when that SYNC is the next one
NOW = 3  # frames sent at once (for the next SYNC)
NOW_MERGE = 4  # ... and merged into every set still buffered (a drive that became active)
NOW_FLUSH = 5  # every buffered set dropped, the generation raised, then the frames sent at once (a stop)
DROP = 6  # these COB-IDs taken out of every buffered set (a drive that started homing)

KINDS = {START, PUSH, NOW, NOW_MERGE, NOW_FLUSH, DROP}

#: the longest message written in one atomic write (Linux's PIPE_BUF)
PIPE_BUF = 4096
MAX_FRAMES = (PIPE_BUF - HEADER.size) // FRAME.size

Frame = tuple[int, bytes]


def encode(kind: int, frames: Sequence[Frame] = (), tag: int = 0, generation: int = 0) -> list[bytes]:
    """The message(s) for ``frames``: one per :data:`MAX_FRAMES` (only the first of a ``NOW_FLUSH``
    flushes; the rest are plain ``NOW``, sent after it)."""
    out = []
    for i in range(0, max(1, len(frames)), MAX_FRAMES):
        part = frames[i:i + MAX_FRAMES]
        k = NOW if (kind == NOW_FLUSH and i) else kind
        body = b"".join(FRAME.pack(cob, len(data), bytes(data)) for cob, data in part)
        out.append(HEADER.pack(k, generation & 0xFFFFFFFF, tag, len(part)) + body)
    return out


class Decoder:
    """Whole messages out of the bytes read from the pipe (a read may end inside one)."""

    def __init__(self) -> None:
        self._buf = bytearray()

    def feed(self, data: bytes) -> Iterator[tuple[int, int, int, list[Frame]]]:
        """Each whole message now in: (kind, generation, tag, frames). A message of an unknown kind
        is a broken stream: ValueError."""
        buf = self._buf
        buf += data
        pos = 0
        while len(buf) - pos >= HEADER.size:
            kind, gen, tag, n = HEADER.unpack_from(buf, pos)
            end = pos + HEADER.size + n * FRAME.size
            if kind not in KINDS or n > MAX_FRAMES:
                raise ValueError(f"a message of kind {kind} with {n} frames: the stream is broken")
            if len(buf) < end:
                break
            frames = []
            for off in range(pos + HEADER.size, end, FRAME.size):
                cob, length, raw = FRAME.unpack_from(buf, off)
                frames.append((cob, raw[:length]))
            yield kind, gen, tag, frames
            pos = end
        del buf[:pos]


class SetpointBuffer:
    """The SYNC process's side: the sets of RPDOs by the SYNC that latches them. ``send(cob_id, data)``
    puts one frame on the bus. :meth:`synced` and :meth:`send_next` after each SYNC sent;
    :meth:`on_message` for each message read."""

    #: sets further ahead than this are refused (a master that ran away, not a lead)
    MAX_AHEAD = 64

    def __init__(self, send: Callable[[int, bytes], None]) -> None:
        self._send = send
        self.number = 0  # SYNCs sent; the frames sent now are for SYNC number + 1
        self.generation = 0
        self.fed = 0  # the last SYNC a set went out for, in the period before it
        self.late = 0  # sets that came after their SYNC (dropped: the drives held)
        self.void = 0  # sets of an older generation (pushed before a stop), dropped
        self.started = False
        self._sets: dict[int, dict[int, bytes]] = {}

    @property
    def pending(self) -> list[int]:
        """The SYNC numbers with a set buffered (tests, reports)."""
        return sorted(self._sets)

    def _out(self, frames: Iterable[Frame]) -> None:
        sent = False
        for cob, data in frames:
            try:
                self._send(cob, data)
                sent = True
            except OSError as exc:  # python-can's CanError is an OSError too
                log.error("RPDO 0x%03X not sent: %s", cob, exc)
        if sent:
            self.fed = self.number + 1

    def on_message(self, kind: int, generation: int, tag: int, frames: list[Frame]) -> None:
        if kind == START:
            self.started = True
        elif kind == PUSH:
            if generation != self.generation:
                self.void += 1
            elif tag <= self.number:
                self.late += 1
            elif tag == self.number + 1:
                held = self._sets.pop(tag, {})
                held.update(frames)
                self._out(held.items())
            elif tag - self.number > self.MAX_AHEAD:
                log.error("a set for SYNC %d, %d ahead: refused", tag, tag - self.number)
            else:
                self._sets.setdefault(tag, {}).update(frames)
        elif kind == NOW_FLUSH:
            self._sets.clear()
            self.generation = generation
            self._out(frames)
        elif kind in (NOW, NOW_MERGE):
            self._out(frames)
            if kind == NOW_MERGE:
                for held in self._sets.values():
                    held.update(frames)
        elif kind == DROP:
            gone = {cob for cob, _ in frames}
            for held in self._sets.values():
                for cob in gone:
                    held.pop(cob, None)

    def synced(self) -> bool:
        """A SYNC was just sent: True when a set went out for it (in the period before it)."""
        self.number += 1
        return self.fed == self.number

    def send_next(self) -> None:
        """Right after the SYNC (and its report): the set for the next SYNC goes out."""
        for tag in [t for t in self._sets if t <= self.number]:  # none in order; never kept if any
            del self._sets[tag]
            self.late += 1
        held = self._sets.pop(self.number + 1, None)
        if held:
            self._out(held.items())
