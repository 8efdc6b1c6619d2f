"""``[motion]`` of the machine file: where the motion side runs (docs/daemon.md, issue 14).

``process = "thread"`` runs :class:`~motiond.runtime.motion.MotionCore` as a thread of the one canon
process. ``process = "own"`` runs it in a child process of its own (:mod:`motiond.runtime.motion_proc`),
so that nothing else shares its interpreter lock; the task side talks to it through
:class:`~motiond.runtime.motion_proxy.MotionProxy`. ``process = "auto"`` (the default) is "own" where
the machine allows it and "thread" otherwise (:func:`motion_choice` says which and why).

"own" needs a bus that reaches across processes (:data:`~fieldbus.canopen.config.CROSS_PROCESS_INTERFACES`:
canon's local bus ``canon_local`` or ``udp_multicast`` for simulated drives in another process,
``socketcan``): python-can's ``virtual`` channels exist only inside one process, so the drives
simulated there could not be reached from the motion process. The Modbus I/O (``[modbus]``, the
``[io]`` map) stays in the task process (:mod:`motiond.runtime.io_loop`); a drive's touch probe and
the probe input cross as requests and urgent messages (docs/daemon.md). An explicit "own" takes them;
"auto" keeps a machine with them in "thread" for now and says why: carrying them across is new, and
the one-process path is the one long proven with the I/O map (the measured extra latency of an E-stop
input through the task: docs/wiring.md).

The liveness watch of the two processes (``task_timeout_ms``, ``motion_timeout_ms``, "own" only):
:class:`Watch`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from motiond.configkit import Table, in_range, one_of

if TYPE_CHECKING:
    from motiond.config import MachineConfig

log = logging.getLogger(__name__)

MODES = ("auto", "thread", "own")
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


@dataclass(frozen=True)
class MotionChoice:
    """``[motion]`` as read: the mode that runs ("thread" or "own"), what the file asked for ("auto",
    "thread" or "own"), why (for "auto": the reason "own" was or was not taken), the watch."""

    mode: str
    asked: str
    reason: str
    watch: Watch

    def describe(self) -> str:
        where = "its own process" if self.mode == "own" else "a thread of the canon process"
        why = f": {self.reason}" if self.reason else ""
        return f'motion side in {where} (process = "{self.asked}"{why})'


def motion_choice(config: MachineConfig, canopen: Any = None) -> MotionChoice:
    """``[motion]``: the process mode, checked against the rest of the file (ConfigError naming the
    key for an explicit "own" this machine cannot have), and the liveness watch. ``canopen``: the
    CanopenConfig already read (read here when None)."""
    root = config.root
    data = root.data if root is not None else {}
    t = Table(data, root.file if root is not None else "").table("motion")
    asked = t.get("process", str, default="auto", check=one_of(*MODES))
    limits = in_range(*TIMEOUT_RANGE_MS)
    watch = Watch(t.get("task_timeout_ms", float, default=Watch.task_timeout_ms, check=limits),
                  t.get("motion_timeout_ms", float, default=Watch.motion_timeout_ms, check=limits))
    t.check_unknown()
    if asked == "thread":
        return MotionChoice("thread", asked, "", watch)
    if canopen is None:
        from motiond.config_canopen import canopen_for_machine

        canopen = canopen_for_machine(config)
    bus = _bus_refusal(canopen)
    if bus is not None:
        if asked == "own":
            raise t.error("process", f'"own" {bus[1]}')
        log.debug("[motion] process = \"auto\": thread, as %s", bus[0])
        return MotionChoice("thread", asked, bus[0], watch)
    if asked == "own":
        return MotionChoice("own", asked, "", watch)
    beside = _kept_beside(config, canopen)
    if beside is not None:
        log.debug("[motion] process = \"auto\": thread, as %s", beside)
        return MotionChoice("thread", asked, beside, watch)
    return MotionChoice("own", asked, f"the {canopen.bus.interface} bus crosses processes", watch)


def _bus_refusal(canopen: Any) -> tuple[str, str] | None:
    """Why this bus cannot carry an own motion process: (the reason in a phrase, the refusal of an
    explicit "own"); None: it can."""
    from fieldbus.canopen.config import CROSS_PROCESS_INTERFACES

    interface = canopen.bus.interface
    if interface in CROSS_PROCESS_INTERFACES:
        return None
    if interface == "virtual":
        refusal = ('needs a bus that crosses processes ([canopen] interface = "canon_local" or '
                   '"udp_multicast" for simulated drives, "socketcan"): python-can\'s virtual bus exists '
                   'inside one process only')
    else:
        refusal = (f'needs a bus that crosses processes ([canopen] interface = "canon_local", '
                   f'"udp_multicast" or "socketcan"), not {interface!r}')
    return f"the {interface} bus does not cross processes", refusal


def _kept_beside(config: MachineConfig, canopen: Any) -> str | None:
    """Why "auto" keeps the motion a thread on a bus that would allow "own" (an explicit "own"
    takes these along): the Modbus I/O or a drive's touch probe, whose stops are quickest beside
    the motion (docs/daemon.md). None: nothing keeps it."""
    data = config.root.data if config.root is not None else {}
    from motiond.config_modbus import modbus_for

    for key in ("modbus", "io"):
        if key in data or (key == "modbus" and modbus_for(config) is not None):
            return f"the Modbus I/O ([{key}]) runs beside the motion (\"own\" takes it when asked)"
    probes = [d.axis for d in canopen.drives if getattr(d, "touch_probe", 0)]
    if probes:
        return (f"a drive's touch probe (axis {probes[0]}) runs beside the motion (\"own\" takes it "
                "when asked)")
    return None


def motion_settings(config: MachineConfig, canopen: Any = None) -> tuple[str, Watch]:
    """The process mode that runs ("thread" or "own") and the watch (:func:`motion_choice`)."""
    choice = motion_choice(config, canopen)
    return choice.mode, choice.watch


def motion_process(config: MachineConfig, canopen: Any = None) -> str:
    """The ``[motion] process`` mode that runs (:func:`motion_choice`)."""
    return motion_choice(config, canopen).mode
