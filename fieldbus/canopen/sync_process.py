"""The SYNC timed by a process of its own: ``[canopen] sync = "process"``, for buses without the kernel's.

On SocketCAN the kernel's broadcast manager sends the SYNC every period whatever Python does
(:mod:`fieldbus.canopen.sync`). ``udp_multicast`` and canon's local bus have no such timer: there the
master's cycle sends the SYNC, and whatever holds the motion process's interpreter lock when the cycle
wakes (python-can's reader decoding TPDOs, the command reader) delays the SYNC by up to the lock's
switch interval. This module gives those buses the kernel's structure, and one thing more: a small
process that does nothing but sleep to the next deadline, send the SYNC and then the drives' RPDOs for
the next one, with nothing else on its interpreter lock, at SCHED_FIFO one above the cycle where the
cycle has it (it stands for the bus's timer, as the kernel's does). The master's cycle, paced by the
SYNCs the process reports, computes the RPDOs up to ``[canopen] setpoint_lead`` SYNCs ahead and hands
them over tagged with the SYNC that is to latch them (:mod:`fieldbus.canopen.setpoint_buffer`), so a
late cycle costs no setpoint while the buffer lasts; stops pass the buffer and empty it.

The process is started stopped (:meth:`SyncProcess.start` begins the SYNC, as the kernel's task starts
at the first cycle) and ends with :meth:`SyncProcess.stop` and with its parent: it reads its standard
input (the master's messages) and stops at its end, which comes when the parent closes it or dies (the
kernel closes a dead process's files), and it also stops when it finds itself re-parented. So no SYNC
outlives canon, as a BCM task ends with its socket. A deadline missed by more than a period (the
process held off) is skipped, not sent in a burst: the drives then see one long period, as after a
late BCM timer.

Run as ``python -m fieldbus.canopen.sync_process``; the parent writes one JSON line (the bus, period,
COB-ID, priority, CPUs), the child answers ``ready`` once its bus is open, and from then on the parent
writes binary messages (``START``, the setpoints) and the child reports each SYNC.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import select
import subprocess
import sys
import time
from array import array
from typing import Any

from fieldbus.canopen import setpoint_buffer as sb

log = logging.getLogger(__name__)

#: the last part of each period spun rather than slept, as the master's cycle does
#: (:class:`~fieldbus.canopen.clock.PeriodicRunner`'s ``spin_s``)
SPIN_S = 0.0003

#: an environment variable naming a folder: the SYNC process records the ``time.monotonic`` time right
#: after each SYNC it sends and writes them there at its end (``sync-PID.f64``, native doubles), so a
#: bench can tell the SYNC's jitter at its sender from what the bus and the receivers add
TRACE_ENV = "CANON_SYNC_TRACE"

#: how long the parent waits for the child's bus to be open (Python's start-up and python-can's
#: import, several seconds on a loaded PC)
READY_TIMEOUT_S = 20.0


class SyncProcessError(Exception):
    """The SYNC process could not be started."""


class SyncProcess:
    """The parent's handle: the child started and its bus open (:class:`SyncProcessError` if not),
    the SYNC not yet sent. ``bus``: the :class:`~fieldbus.canopen.config.CanBusConfig`'s fields
    (interface, channel, bitrate, options); ``priority``: the cycle's SCHED_FIFO priority (0: none; the
    child takes one above it); ``cpus``: the CPUs it may run on (empty: any)."""

    def __init__(self, bus: dict[str, Any], period_s: float, cob_id: int = 0x80, priority: int = 0,
                 cpus: tuple[int, ...] = ()) -> None:
        spec = {"bus": bus, "period_s": period_s, "cob_id": cob_id, "priority": priority,
                "cpus": list(cpus)}
        try:
            self._proc = subprocess.Popen([sys.executable, "-m", __name__], stdin=subprocess.PIPE,
                                          stdout=subprocess.PIPE, close_fds=True)
        except OSError as exc:
            raise SyncProcessError(f"cannot start the SYNC process: {exc}") from None
        assert self._proc.stdin is not None and self._proc.stdout is not None
        try:
            self._proc.stdin.write(json.dumps(spec).encode() + b"\n")
            self._proc.stdin.flush()
            answer = _read_line(self._proc.stdout, READY_TIMEOUT_S)
        except OSError as exc:
            answer = f"its pipe broke: {exc}"
        if answer != "ready":
            self.stop()
            raise SyncProcessError(f"the SYNC process did not open the bus: {answer or 'no answer'}")
        # from here on one atomic write per message that never blocks: a SYNC process that does not
        # read (stalled, stopped) is an error of the write, not a stalled cycle
        os.set_blocking(self._proc.stdin.fileno(), False)
        self.started = False
        #: the number of the last SYNC reported (0: none yet)
        self.number = 0
        #: reported SYNCs that found no set of RPDOs sent for them, numbered from :attr:`expect_from`
        #: on (the master sets it to the first SYNC it pushed a set for, and back to never at a stop)
        self.unfed = 0
        self.expect_from = sys.maxsize

    @property
    def pid(self) -> int:
        return self._proc.pid

    def start(self) -> None:
        """The child sends the SYNC from now on, every period, until :meth:`stop`."""
        if self.started:
            return
        self._write(sb.encode(sb.START))
        self.started = True

    def _write(self, messages: list[bytes]) -> None:
        stdin = self._proc.stdin
        if stdin is None or stdin.closed:
            raise SyncProcessError("the SYNC process is stopped")
        fd = stdin.fileno()
        for m in messages:
            try:
                os.write(fd, m)
            except BlockingIOError:
                raise SyncProcessError("the SYNC process takes no setpoints (its input is full: it is "
                                       "stalled)") from None
            except OSError as exc:
                # its input closed: the child is dead, and with it the SYNC (as the timeout would say)
                raise SyncProcessError(f"no SYNC on the bus: the SYNC process stopped (killed?), its input "
                                       f"is gone ({exc})") from None

    def push(self, tag: int, frames: list[sb.Frame], generation: int) -> None:
        """RPDOs for SYNC number ``tag``: sent right after the SYNC before it (at once if that one is
        already out; dropped if ``tag`` is). :class:`SyncProcessError` when the child is gone or
        stalled."""
        self._write(sb.encode(sb.PUSH, frames, tag, generation))

    def now(self, frames: list[sb.Frame], *, merge: bool = False, flush: bool = False,
            generation: int = 0) -> None:
        """Frames sent at once (for the next SYNC). ``merge``: and into every buffered set (a drive
        that became active). ``flush``: every buffered set dropped first and ``generation`` the
        current one (a stop)."""
        kind = sb.NOW_FLUSH if flush else sb.NOW_MERGE if merge else sb.NOW
        self._write(sb.encode(kind, frames, 0, generation))

    def drop(self, cob_ids: list[int]) -> None:
        """These COB-IDs out of every buffered set (a drive that starts homing)."""
        self._write(sb.encode(sb.DROP, [(c, b"") for c in cob_ids]))

    def read(self, timeout: float) -> float | None:
        """The ``time.monotonic`` time of the next SYNC the child reports within ``timeout`` (0: one
        already reported), or None; :attr:`number` becomes its number. The child reports each SYNC right
        after sending it (one atomic write on its output pipe; it drops reports rather than wait when
        this side does not read, as the kernel drops frames at a full socket)."""
        out = self._proc.stdout
        if out is None or out.closed:
            return None
        fd = out.fileno()
        try:
            if not select.select([fd], [], [], max(0.0, timeout))[0]:
                return None
            data = os.read(fd, sb.REPORT.size)
        except (OSError, ValueError):  # closed meanwhile by stop()
            return None
        if len(data) != sb.REPORT.size:  # the child's end: it stopped or died
            return None
        t, number, fed = sb.REPORT.unpack(data)
        self.number = number
        if not fed and number >= self.expect_from:
            self.unfed += 1
        return t

    def end(self) -> None:
        """Close the child's input: it sends no SYNC after this (it looks before each)."""
        stdin = self._proc.stdin
        if stdin is not None:
            with contextlib.suppress(OSError):
                stdin.close()

    def stop(self, timeout: float = 2.0) -> None:
        """Close the child's input (it stops before its next SYNC) and output, and reap it; killed if it
        lingers."""
        proc = self._proc
        self.end()
        if proc.stdout is not None:
            with contextlib.suppress(OSError):
                proc.stdout.close()
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout)


def _read_line(pipe: Any, timeout: float) -> str:
    """One line from ``pipe`` within ``timeout`` ("" at its end or when none came)."""
    deadline = time.monotonic() + timeout
    buf = b""
    fd = pipe.fileno()
    while not buf.endswith(b"\n"):
        left = deadline - time.monotonic()
        if left <= 0 or not select.select([fd], [], [], left)[0]:
            return buf.decode(errors="replace").strip()
        chunk = os.read(fd, 256)
        if not chunk:
            break
        buf += chunk
    return buf.decode(errors="replace").strip()


# ---------------------------------------------------------------------------------------- the child
def _open_bus(bus: dict[str, Any]) -> Any:
    from fieldbus.canopen.busopen import open_bus
    from fieldbus.canopen.config import LOCAL_INTERFACE, CanBusConfig

    config = CanBusConfig(bus["interface"], bus["channel"], int(bus.get("bitrate", 1_000_000)),
                          dict(bus.get("options", {})))
    if config.interface == LOCAL_INTERFACE:  # it never reads: no peer should queue frames for it
        return open_bus(config, send_only=True)
    return open_bus(config)


def _rank(priority: int, cpus: list[int]) -> None:
    """SCHED_FIFO one above the cycle (it stands for the bus's timer), else normal priority even
    when started from a real-time thread; pinned to ``cpus`` where given."""
    from fieldbus.canopen.clock import rank_below_cycle

    if priority > 0:
        rank_below_cycle(priority, "the SYNC process", log, below=-1)
    elif hasattr(os, "sched_setscheduler"):
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    if cpus and hasattr(os, "sched_setaffinity"):
        try:
            os.sched_setaffinity(0, cpus)
        except OSError as exc:
            log.warning("the SYNC process is not pinned to CPUs %s: %s", cpus, exc)


def run(spec: dict[str, Any], stdin: Any, stdout: Any) -> int:
    """The child: open the bus, say ``ready``, then read the parent's messages; from ``START`` on send
    the SYNC at every period's deadline, each followed by its report and the RPDOs buffered for the
    next SYNC, until ``stdin`` ends or the parent is gone. Returns the number of deadlines skipped."""
    import gc

    import can

    parent = os.getppid()
    _rank(int(spec.get("priority", 0)), [int(c) for c in spec.get("cpus", [])])
    period = float(spec["period_s"])
    msg = can.Message(arbitration_id=int(spec.get("cob_id", 0x80)), data=b"", is_extended_id=False)
    bus = _open_bus(spec["bus"])
    try:
        def send(cob_id: int, data: bytes) -> None:
            bus.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))

        buffer = sb.SetpointBuffer(send)
        decoder = sb.Decoder()
        fd = stdin.fileno()
        stdout.write(b"ready\n")
        stdout.flush()
        report = stdout.fileno()
        os.set_blocking(report, False)  # a parent that does not read loses reports, never a SYNC
        gc.collect()
        gc.freeze()
        gc.disable()  # nothing here allocates for long: no collection ever stalls a SYNC

        def take(timeout: float | None) -> bool:
            """The parent's messages within ``timeout``, acted on; False at the input's end."""
            if not select.select([fd], [], [], timeout)[0]:
                return True
            data = os.read(fd, 65536)
            if not data:  # the parent closed its end, or died
                return False
            for m in decoder.feed(data):
                buffer.on_message(*m)
            return True

        trace = array("d") if os.environ.get(TRACE_ENV) else None
        skipped = 0
        deadline: float | None = None
        while True:
            if deadline is None:  # not started: only messages
                if not take(None):
                    break
                if buffer.started:
                    deadline = time.monotonic()
                continue
            left = deadline - time.monotonic() - SPIN_S
            if left > 0:
                if not take(left):
                    break
                continue
            while time.monotonic() < deadline:  # the rest spun: the kernel's wake-up is later than that
                pass
            # a message that came while spinning (a stop, the end) is acted on before the SYNC
            if not take(0.0) or os.getppid() != parent:
                break
            try:
                bus.send(msg)
            except (can.CanError, OSError) as exc:
                log.error("SYNC not sent: %s", exc)
            fed = buffer.synced()
            sent_at = time.monotonic()
            if trace is not None:
                trace.append(sent_at)
            try:
                os.write(report, sb.REPORT.pack(sent_at, buffer.number, int(fed)))
            except BlockingIOError:
                pass
            except OSError:  # the parent closed its end: it stopped
                break
            buffer.send_next()
            deadline += period
            late = time.monotonic() - deadline
            if late > period:  # held off past the next deadline: skip, never a burst of SYNCs
                n = int(late / period)
                deadline += n * period
                skipped += n
        if buffer.late or buffer.void:
            log.warning("%d sets of RPDOs came after their SYNC, %d were void (pushed before a stop)",
                        buffer.late, buffer.void)
        if trace is not None:
            from fieldbus.canopen.clock import write_trace

            write_trace(TRACE_ENV, f"sync-{os.getpid()}.f64", trace)
        return skipped
    finally:
        bus.shutdown()


def main() -> int:
    logging.basicConfig(level=logging.WARNING, format="canon sync process: %(message)s")
    stdin, stdout = sys.stdin.buffer, sys.stdout.buffer
    line = stdin.readline()
    try:
        spec = json.loads(line)
    except ValueError:
        return 2
    import can

    try:
        skipped = run(spec, stdin, stdout)
    except (OSError, ValueError, KeyError, can.CanError) as exc:  # the bus did not open: said to the parent
        try:
            stdout.write(f"{type(exc).__name__}: {exc}\n".encode())
            stdout.flush()
        except OSError:
            pass
        return 1
    if skipped:
        log.warning("%d SYNC deadlines skipped (the process was held off past a period)", skipped)
    return 0


if __name__ == "__main__":
    sys.exit(main())
