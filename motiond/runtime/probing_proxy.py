"""G38.x from the task process (``[motion] process = "own"``): the job thread's side of a probing move,
whose motion side is :mod:`motiond.runtime.probing_child` (its docstring tells what crosses).

:class:`ProbeClient` offers what :class:`~motiond.runtime.motion.MotionCore` does for probing
(``before_move`` from ``put``, ``answer`` from ``probe``), over the
:class:`~motiond.runtime.motion_proxy.MotionProxy`:

* before the probing move is sent: the task waits until every command before it ran and the motion
  is at rest (``drained``); with the I/O map's probe input it reads the input (already in the sought
  state: an error or a trip at once, as in one process), then asks the motion process to arm (a drive's
  touch probe: armed there by SDO);
* with the probe input, :meth:`ProbeClient.poll` (the task's I/O loop, :mod:`motiond.runtime.io_loop`,
  every cycle period) reads the input while the move runs and sends the time it saw the trip on the
  urgent pipe, once;
* once the planner stands at the move's end or its stop (the sync point, by its sequence number), the
  probed point is asked for.

Latency of the probe input (docs/wiring.md): the input is seen by the first Modbus poll after it
changes (``poll_ms`` plus the request) and by the I/O loop's next read (at most one cycle period);
the probed point is the commanded position of the cycle running at that read (as in one process: the
cycle that saw it), and the move stops in the cycle the urgent message arrives in (a pipe's latency,
well under a cycle: docs/daemon.md).
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

from gcode_canon import commands as C
from motiond.runtime.probing import IDLE_POLL_S, Probed
from motiond.runtime.probing_io import at_start

if TYPE_CHECKING:
    import threading


class ProbeClient:
    """The task's side of the probing moves (module docstring). ``proxy``: the MotionProxy; ``mio``:
    the :class:`~motiond.machine_io.MachineIO` that reads the probe input (None: a drive's touch probe)."""

    def __init__(self, proxy: Any, mio: Any = None) -> None:
        self.proxy = proxy
        self.mio = mio
        self.binding = None if mio is None else mio.f["probe"]
        self._watch: bool | None = None  # the level the running probing move seeks (None: not watching)
        self._start: tuple[float, ...] | None = None
        self.tripped_at_start = False
        self.seen_at = 0.0  # when the last trip was seen (monotonic), for the tests and the docs

    @property
    def where(self) -> str:
        b = self.binding
        return "" if b is None else f"{b.key}, {b.where}"

    def before_move(self, cmd: C.Probe, cancel: threading.Event) -> bool:
        """Job thread: wait for rest, check the input, arm. False when ``cancel`` is set meanwhile."""
        p = self.proxy
        while not p.drained():
            if cancel.is_set():
                return False
            time.sleep(IDLE_POLL_S)
        if self.mio is None:
            self.tripped_at_start = p.request("probe_arm", cmd)
            return True
        self._start = p.position()
        self.tripped_at_start = at_start(cmd, self.mio._read(self.binding), self.where)
        if not self.tripped_at_start:
            p.request("probe_arm", cmd)
            self._watch = cmd.mode.toward
        return True

    def poll(self) -> None:
        """The task's I/O loop: the input read while a move is watched; its trip goes out at once."""
        toward = self._watch
        if toward is None or self.mio is None:
            return
        level = self.mio._read(self.binding)
        if level is None or level == toward:
            self._watch = None
            self.seen_at = time.monotonic()
            self.proxy.urgent("probe_trip", self.seen_at, level is None)

    def answer(self, cmd: C.Probe, cancel: threading.Event) -> Probed | None:
        """Job thread: wait for the move's end or its stop; the probed point (None: ``cancel`` set)."""
        p = self.proxy
        if self.tripped_at_start:
            self.tripped_at_start = False
            if self.mio is None:
                return p.request("probe_at_start", cmd)
            assert self._start is not None
            return Probed(True, self._start, "probe input")
        try:
            reached = p.wait_sync_point(cmd, cancel)
        finally:
            self._watch = None
        if not reached:
            p.request("probe_unwatch", dead=lambda: None)
            return None
        return p.request("probe_latched", cmd)
