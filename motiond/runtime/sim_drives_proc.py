"""Simulated drives in a process of their own, for ``[motion] process = "own"`` with ``simulate = true``.

With the motion side in its own process the drives it streams to must be reachable from there and must
not share an interpreter lock with it; nor with the task side, whose interpreter would stall their
answers (a drive that misses a SYNC sees a setpoint jump: EMCY 0x8400). So the task process starts
them here, as ``canon sim drives`` would, on the same bus (canon_local, udp_multicast or socketcan), and
stops them when it shuts down; they end too when the task process dies (their pipe closes).
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import signal
from typing import Any

READY_TIMEOUT_S = 60.0


def _main(conn: Any, canopen: Any, lag_s: float, log_level: int) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the task's
    logging.basicConfig(level=log_level, format="sim-drives[%(process)d] %(levelname)s %(name)s: %(message)s")
    from fieldbus.canopen.sim_process import SimBus, machine_sim_drives

    _rank_like_hardware(canopen.realtime_priority)
    bus = SimBus(machine_sim_drives(canopen, lag_s), canopen.bus)
    conn.send("ready")
    with contextlib.suppress(EOFError, OSError):
        conn.recv()  # "stop", or EOF when the task process is gone
    bus.close()


def _rank_like_hardware(cycle_priority: int) -> None:
    """With a SCHED_FIFO cycle (``[canopen] realtime_priority``), this process and every thread it
    starts run at SCHED_FIFO one above the cycle: the drives stand in for hardware, which answers
    every SYNC whatever the PC runs, the motion process included. At ordinary priority a busy PC
    stalled them past their own heartbeat watch (EMCY 0x8130 at enable with the demo in "own" mode and
    two CPU hogs beside it), a fault real drives would not have. One below the cycle, level with the
    motion process's other threads (its main thread took half a CPU, and a SCHED_FIFO thread is not
    preempted by one of its own level), they missed TPDOs for just over 100 ms ("no TPDO for 101 ms",
    a real drive's limit) in 3 of 7 runs of the example programs in "own" mode on the loaded
    2-core test PC. Refused (not root): logged, they run as they are."""
    from fieldbus.canopen.clock import rank_below_cycle

    rank_below_cycle(cycle_priority, "the simulated drives", logging.getLogger(__name__), below=-1)


class SimDrivesProcess:
    """The simulated drives of ``canopen`` in a child process, up when the constructor returns."""

    def __init__(self, canopen: Any, lag_s: float) -> None:
        ctx = multiprocessing.get_context("spawn")
        self.conn, child = ctx.Pipe()
        level = logging.getLogger().getEffectiveLevel()
        self.proc = ctx.Process(target=_main, args=(child, canopen, lag_s, level), name="canon-sim-drives",
                                daemon=True)
        self.proc.start()
        child.close()
        if not self.conn.poll(READY_TIMEOUT_S):
            self.close()
            raise RuntimeError("the simulated drives' process did not start")
        self.conn.recv()

    def close(self) -> None:
        with contextlib.suppress(OSError, ValueError):
            self.conn.send("stop")
        self.proc.join(5.0)
        if self.proc.is_alive():
            self.proc.terminate()
            self.proc.join(2.0)
        self.conn.close()
