"""``[motion]`` of the machine file: where the motion side runs (docs/daemon.md, issue 14).

``process = "thread"`` (the default) runs :class:`~motiond.runtime.motion.MotionCore` as a thread of
the one canon process. ``process = "own"`` runs it in a child process of its own
(:mod:`motiond.runtime.motion_proc`), so that nothing else shares its interpreter lock; the task side
talks to it through :class:`~motiond.runtime.motion_proxy.MotionProxy`.

"own" needs a bus that reaches across processes (socketcan, or udp_multicast for simulated drives in
another process): python-can's ``virtual`` channels exist only inside one process, so the drives
simulated there could not be reached from the motion process. The Modbus I/O (``[modbus]``, the
``[io]`` map) stays in the task process (:mod:`motiond.runtime.io_loop`); a drive's touch probe and
the probe input cross as requests and urgent messages (docs/daemon.md).

The liveness watch of the two processes (``task_timeout_ms``, ``motion_timeout_ms``, "own" only):
:class:`Watch`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from motiond.configkit import Table, in_range, one_of

if TYPE_CHECKING:
    from motiond.config import MachineConfig

MODES = ("thread", "own")
TIMEOUT_RANGE_MS = (100.0, 10000.0)


@dataclass(frozen=True)
class Watch:
    """How long each process of "own" may fall silent before the other stops the machine.

    ``task_timeout_ms`` (default 500): the motion process quick-stops the drives when no ping of the
    task process arrived for this long. ``motion_timeout_ms`` (default 500): the task process faults
    when no state of the motion process arrived for this long while it is alive. 500 ms is ten ping
    periods (the task pings every tenth of the timeout) and about five times the longest stall measured
    on the loaded 2-core test PC (a SYNC gap of 103 ms, issue 14), so a busy PC does not trip it; and a
    real hang stops the machine within half a second, about a human's reaction time, and at least
    twice as fast as the drives' usual heartbeat consumer (1000 ms) would react to a hung motion process.
    """

    task_timeout_ms: float = 500.0
    motion_timeout_ms: float = 500.0


def motion_settings(config: MachineConfig, canopen: Any = None) -> tuple[str, Watch]:
    """``[motion]``: the process mode, checked against the rest of the file (ConfigError naming the
    key), and the liveness watch. ``canopen``: the CanopenConfig already read (read here when None)."""
    root = config.root
    if root is None or "motion" not in root.data:
        return "thread", Watch()
    t = Table(root.data, root.file).table("motion")
    mode = t.get("process", str, default="thread", check=one_of(*MODES))
    limits = in_range(*TIMEOUT_RANGE_MS)
    watch = Watch(t.get("task_timeout_ms", float, default=Watch.task_timeout_ms, check=limits),
                  t.get("motion_timeout_ms", float, default=Watch.motion_timeout_ms, check=limits))
    t.check_unknown()
    if mode == "thread":
        return mode, watch
    if canopen is None:
        from motiond.config_canopen import canopen_for_machine

        canopen = canopen_for_machine(config)
    if canopen.bus.interface == "virtual":
        raise t.error("process", '"own" needs a bus that crosses processes ([canopen] interface = '
                      '"socketcan", or "udp_multicast" for simulated drives): python-can\'s virtual '
                      'bus exists inside one process only')
    return mode, watch


def motion_process(config: MachineConfig, canopen: Any = None) -> str:
    """The ``[motion] process`` mode (:func:`motion_settings`)."""
    return motion_settings(config, canopen)[0]
