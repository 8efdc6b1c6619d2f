"""The I/O map's per-cycle work in the task process (``[motion] process = "own"``).

In one process the cycle thread calls the I/O map's ``io_cycle`` hook at the start of every cycle
(:mod:`motiond.io_hooks`). With the motion in a process of its own, the Modbus worker and the I/O map
stay here, in the task process, and :class:`IoLoop` (the ``canon-io`` thread) does that work on
absolute deadlines one cycle period apart: :meth:`~motiond.io_hooks.IoHooks.cycle` with the drives'
digital inputs (0x60FD) and the commanded velocities of the newest state the motion process sent (the
E-stop input, the limit switches, the door, the buttons, the waits' completion and timeouts), and the
probe input while a probing move is watched (:meth:`~motiond.runtime.probing_proxy.ProbeClient.poll`).

What it finds acts as in one process, through the :class:`~motiond.runtime.motion_proxy.MotionProxy`:
an E-stop, a limit switch's quick stop and fault, an abort, a pause or resume, a wait's release and the
probe's trip go down the urgent pipe, which no command queues in front of (docs/daemon.md). The added
latency from the input seen here to the quick stop sent to the drives by the motion process is the
pipe's (docs/wiring.md states it as measured); the input is seen at most one cycle period after the
Modbus poll brought it, as in one process.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

log = logging.getLogger(__name__)


class IoLoop:
    """``canon-io``: the I/O map's cycle in the task process (module docstring). ``machine``: the
    :class:`~motiond.runtime.machine.Machine`; ``probe``: the ProbeClient of the probe input, or None."""

    def __init__(self, machine: Any, probe: Any = None) -> None:
        self.m = machine
        self.probe = probe
        self.period = machine.T
        self.loops = 0
        self.worst_late_s = 0.0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        # on the stop path (the E-stop input): ranked as the proxy's own threads (own mode only)
        self._thread = threading.Thread(target=self.m.motion.ranked(self._run), name="canon-io", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None

    def _run(self) -> None:
        m = self.m
        motion = m.motion
        hooks = m.io_hooks
        probe = self.probe
        deadline = time.monotonic()
        while not self._stop.is_set():
            try:
                if probe is not None:
                    probe.poll()
                if not hooks.empty:
                    hooks.cycle(motion.drive_inputs, motion.velocity)
            except Exception:  # the loop must outlive a bug in one pass (it holds the E-stop input)
                log.exception("the I/O loop")
            self.loops += 1
            deadline += self.period
            now = time.monotonic()
            if now > deadline:  # late (a stall of this process): start again from now
                self.worst_late_s = max(self.worst_late_s, now - deadline)
                deadline = now
            else:
                self._stop.wait(deadline - now)
