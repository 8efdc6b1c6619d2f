"""``[motion]`` of the machine file: where the motion side runs (docs/daemon.md, issue 14).

``process = "thread"`` (the default) runs :class:`~motiond.runtime.motion.MotionCore` as a thread of
the one canon process. ``process = "own"`` runs it in a child process of its own
(:mod:`motiond.runtime.motion_proc`), so that nothing else shares its interpreter lock; the task side
talks to it through :class:`~motiond.runtime.motion_proxy.MotionProxy`.

"own" needs a bus that reaches across processes (socketcan, or udp_multicast for simulated drives in
another process): python-can's ``virtual`` channels exist only inside one process, so the drives
simulated there could not be reached from the motion process. The Modbus I/O (``[modbus]``, the
``[io]`` map) and a drive's touch probe are not carried across the boundary yet: they are refused with
"own" rather than half working.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from motiond.configkit import Table, one_of

if TYPE_CHECKING:
    from motiond.config import MachineConfig

MODES = ("thread", "own")


def motion_process(config: MachineConfig, canopen: Any = None) -> str:
    """The ``[motion] process`` mode, checked against the rest of the file (ConfigError naming the
    key). ``canopen``: the CanopenConfig already read (read here when None)."""
    root = config.root
    if root is None or "motion" not in root.data:
        return "thread"
    t = Table(root.data, root.file).table("motion")
    mode = t.get("process", str, default="thread", check=one_of(*MODES))
    t.check_unknown()
    if mode == "thread":
        return mode
    if canopen is None:
        from motiond.config_canopen import canopen_for_machine

        canopen = canopen_for_machine(config)
    if canopen.bus.interface == "virtual":
        raise t.error("process", '"own" needs a bus that crosses processes ([canopen] interface = '
                      '"socketcan", or "udp_multicast" for simulated drives): python-can\'s virtual '
                      'bus exists inside one process only')
    for key in ("modbus", "io"):
        if key in root.data:
            raise t.error("process", f'"own" does not carry the Modbus I/O ([{key}]) across the process '
                          'boundary yet: use process = "thread" on this machine')
    probes = [d.axis for d in canopen.drives if getattr(d, "touch_probe", 0)]
    if probes:
        raise t.error("process", f'"own" does not carry a drive\'s touch probe (axis {probes[0]}) across '
                      'the process boundary yet: use process = "thread" on this machine')
    return mode
