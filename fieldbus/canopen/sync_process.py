"""The SYNC timed by a process of its own: ``[canopen] sync = "process"``, for buses without the kernel's.

On SocketCAN the kernel's broadcast manager sends the SYNC every period whatever Python does
(:mod:`fieldbus.canopen.sync`). ``udp_multicast`` and canon's local bus have no such timer: there the
master's cycle sends the SYNC, and whatever holds the motion process's interpreter lock when the cycle
wakes (python-can's reader decoding TPDOs, the command reader) delays the SYNC by up to the lock's
switch interval. This module gives those buses the kernel's structure: a small process that does
nothing but sleep to the next deadline and send the SYNC, with nothing else on its interpreter lock,
at SCHED_FIFO one above the cycle where the cycle has it (it stands for the bus's timer, as the
kernel's does). The master sees each SYNC on a socket of its own and sends every drive's RPDO for the
next SYNC right after it, exactly as with the kernel's SYNC.

The process is started stopped (:meth:`SyncProcess.start` begins the SYNC, as the kernel's task starts
at the first cycle) and ends with :meth:`SyncProcess.stop` and with its parent: it reads its standard
input and stops at its end, which comes when the parent closes it or dies (the kernel closes a dead
process's files), and it also stops when it finds itself re-parented. So no SYNC outlives canon, as a
BCM task ends with its socket. A deadline missed by more than a period (the process held off) is
skipped, not sent in a burst: the drives then see one long period, as after a late BCM timer.

Run as ``python -m fieldbus.canopen.sync_process``; the parent writes one JSON line (the bus, period,
COB-ID, priority, CPUs) and then ``start``; the child answers ``ready`` once its bus is open.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import select
import struct
import subprocess
import sys
import threading
import time
from typing import Any

log = logging.getLogger(__name__)

#: a SYNC's report on the child's output: its ``time.monotonic`` time, right after it was sent
STAMP = struct.Struct("<d")

#: the last part of each period spun rather than slept, as the master's cycle does
#: (:class:`~fieldbus.canopen.clock.PeriodicRunner`'s ``spin_s``)
SPIN_S = 0.0003

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
        self.started = False

    @property
    def pid(self) -> int:
        return self._proc.pid

    def start(self) -> None:
        """The child sends the SYNC from now on, every period, until :meth:`stop`."""
        if self.started:
            return
        assert self._proc.stdin is not None
        try:
            self._proc.stdin.write(b"start\n")
            self._proc.stdin.flush()
        except OSError as exc:
            raise SyncProcessError(f"the SYNC process is gone: {exc}") from None
        self.started = True

    def read(self, timeout: float) -> float | None:
        """The ``time.monotonic`` time of the next SYNC the child reports within ``timeout`` (0: one
        already reported), or None. The child reports each SYNC right after sending it (8 bytes, one
        atomic write on its output pipe; it drops reports rather than wait when this side does not read,
        as the kernel drops frames at a full socket)."""
        out = self._proc.stdout
        if out is None or out.closed:
            return None
        fd = out.fileno()
        try:
            if not select.select([fd], [], [], max(0.0, timeout))[0]:
                return None
            data = os.read(fd, STAMP.size)
        except (OSError, ValueError):  # closed meanwhile by stop()
            return None
        if len(data) != STAMP.size:  # the child's end: it stopped or died
            return None
        return STAMP.unpack(data)[0]

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
    """The child: open the bus, say ``ready``, wait for ``start``, then send the SYNC at every period's
    deadline until ``stdin`` ends or the parent is gone. Returns the number of deadlines skipped."""
    import gc

    import can

    parent = os.getppid()
    _rank(int(spec.get("priority", 0)), [int(c) for c in spec.get("cpus", [])])
    period = float(spec["period_s"])
    msg = can.Message(arbitration_id=int(spec.get("cob_id", 0x80)), data=b"", is_extended_id=False)
    bus = _open_bus(spec["bus"])
    try:
        stdout.write(b"ready\n")
        stdout.flush()
        if stdin.readline().strip() != b"start":
            return 0
        ended = threading.Event()

        def watch() -> None:  # the parent closed the pipe or died
            while stdin.readline():
                pass
            ended.set()

        threading.Thread(target=watch, name="sync-parent", daemon=True).start()
        report = stdout.fileno()
        os.set_blocking(report, False)  # a parent that does not read loses reports, never a SYNC
        gc.collect()
        gc.freeze()
        gc.disable()  # nothing here allocates for long: no collection ever stalls a SYNC
        skipped = 0
        deadline = time.monotonic()
        while not ended.is_set():
            now = time.monotonic()
            if deadline - now > SPIN_S:
                time.sleep(deadline - now - SPIN_S)
            while time.monotonic() < deadline:  # the rest spun: the kernel's wake-up is later than that
                pass
            if ended.is_set() or os.getppid() != parent:
                break
            try:
                bus.send(msg)
            except (can.CanError, OSError) as exc:
                log.error("SYNC not sent: %s", exc)
            try:
                os.write(report, STAMP.pack(time.monotonic()))
            except BlockingIOError:
                pass
            except OSError:  # the parent closed its end: it stopped
                break
            deadline += period
            late = time.monotonic() - deadline
            if late > period:  # held off past the next deadline: skip, never a burst of SYNCs
                n = int(late / period)
                deadline += n * period
                skipped += n
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
