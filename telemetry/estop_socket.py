"""The E-stop's own socket: the kernel hands it E-stop commands and nothing else.

Why: every other command shares one socket and one receiving thread. Under a flood of valid commands
(1,000 a second, issue #14) on a PC whose CPUs are busy, that thread fell behind the arrivals, the
socket's queue grew, and an E-stop published in the middle waited behind every command queued before
it: 223 ms in the stressed suite, against a 50 ms bound. However fast each command is checked, a
queue in front of the E-stop is the structural fault.

So the command server also opens, for a ``udpm`` URL, a second socket on the same group and port
with a classic BPF socket filter attached (``SO_ATTACH_FILTER``) that accepts only an LCM short
message on the command channel whose payload is a ``canon.command`` (its fingerprint) with the verb
``estop``. Filtered in the kernel, a flood of other commands never reaches this socket's queue, and
its thread (on the task's stop path, ranked as those threads are) wakes only for an E-stop. What
arrives still goes through the server's checks (MAC, time, sequence): the filter selects, it does not
trust. The same E-stop also arrives on the ordinary socket; whichever of the server's readers has it
first decides it and the other skips it, so it is decided once.

Where the filter cannot be attached (not Linux, another LCM provider) :func:`open_estop_socket` says
why and the server takes E-stops from its ordinary socket, as before.
"""

from __future__ import annotations

import ctypes
import logging
import os
import socket
import struct
import sys
import threading
import time
from collections.abc import Callable

from telemetry.url import LcmUrl

log = logging.getLogger(__name__)

LCM_SHORT_MAGIC = 0x4C433032
"""``LC02``: an LCM message sent in one datagram (an E-stop always is; fragments are ``LC03``)."""
UDP_HEADER = 8
"""A UDP socket's filter sees the datagram from its UDP header (measured: the LCM magic at offset 8)."""
SO_ATTACH_FILTER = 26
MAX_SENDER = 65507
"""The largest sender length the filter reads past: a UDP datagram's largest payload. Longer is no
datagram (the check only keeps the index register's sum from wrapping around)."""

# classic BPF opcodes (linux/filter.h)
_LD_W_ABS, _LD_B_ABS = 0x20, 0x30
_LD_W_IND, _LD_B_IND = 0x40, 0x50
_JEQ_K, _JGT_K, _TAX, _RET_K = 0x15, 0x25, 0x07, 0x06
_ACCEPT = 0xFFFF


_GO_ON, _DROP_IF_FALSE, _DROP_IF_TRUE = 0, 1, 2


def _assemble(steps: list[tuple[int, int, int]]) -> list[tuple[int, int, int, int]]:
    """BPF instructions ``(code, jt, jf, k)`` from steps ``(code, k, how)``: a comparison step drops the
    datagram when it is false (``_DROP_IF_FALSE``) or true (``_DROP_IF_TRUE``), else goes on; the
    program ends with accept, then drop."""
    drop = len(steps) + 1
    out = []
    for i, (code, k, how) in enumerate(steps):
        skip = drop - i - 1  # a jump's offset counts from the next instruction
        jt, jf = {_GO_ON: (0, 0), _DROP_IF_FALSE: (0, skip), _DROP_IF_TRUE: (skip, 0)}[how]
        out.append((code, jt, jf, k))
    if drop > 255:  # a jump's offset is one byte
        raise ValueError(f"socket filter too long ({drop} steps): a channel name this long is not supported")
    return [*out, (_RET_K, 0, 0, _ACCEPT), (_RET_K, 0, 0, 0)]


def _bytes_equal(at: int, expected: bytes, indexed: bool) -> list[tuple[int, int, int]]:
    """Steps that compare the packet's bytes at ``at`` (plus the index register if ``indexed``) with
    ``expected``: words while four bytes are left, then single bytes."""
    steps = []
    i = 0
    while i < len(expected):
        if len(expected) - i >= 4:
            (word,) = struct.unpack(">I", expected[i:i + 4])
            steps += [(_LD_W_IND if indexed else _LD_W_ABS, at + i, _GO_ON), (_JEQ_K, word, _DROP_IF_FALSE)]
            i += 4
        else:
            steps += [(_LD_B_IND if indexed else _LD_B_ABS, at + i, _GO_ON),
                      (_JEQ_K, expected[i], _DROP_IF_FALSE)]
            i += 1
    return steps


def estop_filter(channel: str, fingerprint: bytes) -> list[tuple[int, int, int, int]]:
    """The BPF program (``(code, jt, jf, k)`` instructions) that accepts a datagram only if it is an LCM
    short message on ``channel`` carrying a ``canon.command`` (``fingerprint``) whose verb is ``estop``.
    A load past the datagram's end drops it (BPF's rule).

    The command's layout (telemetry/canon_command.lcm): fingerprint, utime, request_id (8 bytes each),
    sender (int32 length with its NUL, then the bytes), seq (8), verb (int32 length, bytes). The
    sender's length is variable, so the verb is read relative to it (BPF's index register)."""
    name = channel.encode() + b"\0"
    payload = UDP_HEADER + 8 + len(name)
    verb_at = payload + 28 + 8  # after the sender (its length in the index register) and seq
    steps = [(_LD_W_ABS, UDP_HEADER, _GO_ON), (_JEQ_K, LCM_SHORT_MAGIC, _DROP_IF_FALSE)]
    steps += _bytes_equal(UDP_HEADER + 8, name, indexed=False)
    steps += _bytes_equal(payload, fingerprint, indexed=False)
    steps += [(_LD_W_ABS, payload + 24, _GO_ON), (_JGT_K, MAX_SENDER, _DROP_IF_TRUE), (_TAX, 0, _GO_ON),
              (_LD_W_IND, verb_at, _GO_ON), (_JEQ_K, len(b"estop\0"), _DROP_IF_FALSE)]
    steps += _bytes_equal(verb_at + 4, b"estop\0", indexed=True)
    return _assemble(steps)


def _attach(sock: socket.socket, program: list[tuple[int, int, int, int]]) -> None:
    code = b"".join(struct.pack("HBBI", *ins) for ins in program)
    buf = ctypes.create_string_buffer(code, len(code))
    fprog = struct.pack("HL", len(program), ctypes.addressof(buf))
    sock.setsockopt(socket.SOL_SOCKET, SO_ATTACH_FILTER, fprog)  # the kernel copies the program


def open_estop_socket(url: LcmUrl, channel: str, fingerprint: bytes) -> tuple[socket.socket | None, str]:
    """A UDP socket joined to ``url``'s group and port that receives only E-stop commands on ``channel``;
    (None, why) where it cannot be had."""
    if url.provider != "udpm":
        return None, f"LCM provider {url.provider!r} (the E-stop's own socket needs udpm)"
    if not sys.platform.startswith("linux"):
        return None, "not Linux (no socket filter)"
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        # as LCM binds its own socket on Linux: the group's port shared by every LCM instance on this
        # host, each getting its own copy of a multicast datagram (no SO_REUSEPORT, which would put the
        # sockets in a group that shares out unicast datagrams instead)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        _attach(sock, estop_filter(channel, fingerprint))  # before bind: nothing unfiltered queues
        sock.bind(("", url.port))
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
                        socket.inet_aton(url.group) + socket.inet_aton("0.0.0.0"))
    except OSError as exc:
        sock.close()
        return None, f"{exc.strerror or exc}"
    return sock, ""


def lcm_payload(datagram: bytes, channel: str) -> bytes | None:
    """The message inside an LCM short datagram on ``channel`` (None if it is not one)."""
    if len(datagram) < 8 or struct.unpack_from(">I", datagram)[0] != LCM_SHORT_MAGIC:
        return None
    end = datagram.find(b"\0", 8)
    if end < 0 or datagram[8:end] != channel.encode():
        return None
    return datagram[end + 1:]


CPU_BUDGET = 0.3
"""CPU seconds a second beyond which the E-stop thread reads at ordinary priority (a flood). A real
E-stop costs microseconds and a client may repeat one; a flood of forged ones costs a decode and a MAC
check each (16 us of the thread's CPU measured on the 2-core development PC): a thousand a second is
under 2 % of a CPU, read at real-time priority, so an E-stop among them is still decided at once. Only
a flood that would take more than this share of a CPU at real-time priority (about twenty thousand a
second there, from the LAN) gives up the rank, to keep the rest of the PC (and the task's other
threads, on the interpreter lock) running; at that rate the socket's queue overflows and drops
datagrams whatever the thread's priority."""


class _FloodBudget:
    """The E-stop thread's CPU budget: when it used more than ``cpu_s`` of CPU time (``time.thread_time``)
    in a second, it drops from the real-time rank it was given to SCHED_OTHER, and takes the rank back
    after a whole second under the budget. It still reads and decides every datagram meanwhile (an
    E-stop in a flood is still decided, at ordinary priority, as on the ordinary socket); the drives'
    own stop paths (the motion process, the E-stop input, the drives) do not depend on this thread. A
    thread that was not ranked (no ``realtime_priority``, or not allowed) has nothing to give up; it
    only counts and warns."""

    def __init__(self, cpu_s: float) -> None:
        self.cpu_s = cpu_s
        self.rank = _own_rank()
        self.window = time.monotonic()
        self.cpu_at = time.thread_time()
        self.demoted = False
        self.floods = 0
        self.read = 0  # datagrams read in this window

    def count(self, now: float) -> None:
        """A datagram was read (and decided) at ``now``."""
        self.read += 1
        if now - self.window >= 1.0:
            self._next_window(now)
        elif not self.demoted and time.thread_time() - self.cpu_at > self.cpu_s:
            self._demote()

    def quiet(self, now: float) -> None:
        """No datagram for a while (the socket's timeout): a flood that ended ends here too."""
        if now - self.window >= 1.0:
            self._next_window(now)

    def _next_window(self, now: float) -> None:
        cpu = time.thread_time()
        if self.demoted and cpu - self.cpu_at <= self.cpu_s * (now - self.window):
            self._restore()
        self.window, self.cpu_at, self.read = now, cpu, 0

    def _demote(self) -> None:
        self.demoted = True
        self.floods += 1
        took = time.monotonic() - self.window
        why = (f"E-stop socket: a flood ({self.read} E-stop datagrams in {took:.2f} s took more than "
               f"{self.cpu_s:g} s of CPU; likely forged)")
        if self.rank is None:
            log.warning("%s; each is still checked", why)
            return
        try:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        except OSError as exc:
            log.warning("%s, and the thread could not leave its real-time rank: %s", why, exc)
            return
        log.warning("%s: read at ordinary priority until it ends; each is still checked", why)

    def _restore(self) -> None:
        self.demoted = False
        if self.rank is None:
            return
        policy, priority = self.rank
        try:
            os.sched_setscheduler(0, policy, os.sched_param(priority))
        except OSError as exc:
            log.warning("E-stop socket: the flood ended but the real-time rank was refused: %s", exc)
            return
        log.warning("E-stop socket: the flood ended; real-time rank back")


def _own_rank() -> tuple[int, int] | None:
    """The calling thread's real-time policy and priority, or None when it runs ordinary."""
    try:
        policy = os.sched_getscheduler(0)
        priority = os.sched_getparam(0).sched_priority
    except (AttributeError, OSError):
        return None
    if policy not in (os.SCHED_FIFO, os.SCHED_RR):
        return None
    return policy, priority


class EstopListener:
    """A thread that reads the E-stop socket and calls ``on_estop(payload)`` for each E-stop datagram.

    ``thread_wrapper`` wraps the thread's body (the daemon ranks it with the task's stop-path threads).
    More than ``cpu_budget`` seconds of CPU in a second is a flood (:class:`_FloodBudget`): the thread gives
    up its real-time rank until a second passes under it."""

    def __init__(self, sock: socket.socket, channel: str, on_estop: Callable[[bytes], None],
                 thread_wrapper: Callable[[Callable[[], None]], Callable[[], None]] | None = None,
                 cpu_budget: float = CPU_BUDGET) -> None:
        self.sock = sock
        self.channel = channel
        self.on_estop = on_estop
        self.cpu_budget = cpu_budget
        self.budget: _FloodBudget | None = None
        self._stop = threading.Event()
        body = self._run if thread_wrapper is None else thread_wrapper(self._run)
        self._thread = threading.Thread(target=body, name="canon-command-estop", daemon=True)

    def start(self) -> EstopListener:
        self.sock.settimeout(0.1)  # the thread looks at its stop flag between waits
        self._thread.start()
        return self

    def _run(self) -> None:
        budget = self.budget = _FloodBudget(self.cpu_budget)  # after thread_wrapper ranked the thread
        while not self._stop.is_set():
            try:
                datagram = self.sock.recv(65536)
            except TimeoutError:
                budget.quiet(time.monotonic())
                continue
            except OSError:
                if self._stop.is_set():
                    return
                log.exception("the E-stop socket failed; E-stops still arrive on the command socket")
                return
            budget.count(time.monotonic())
            payload = lcm_payload(datagram, self.channel)
            if payload is None:
                continue
            try:
                self.on_estop(payload)
            except Exception:
                log.exception("an E-stop from the E-stop socket could not be handled")

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        self._thread.join(timeout)
        self.sock.close()

