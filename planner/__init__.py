"""planner: canonical commands in, timed jerk-limited setpoints out (ruckig). No I/O.

Usage, in a cycle loop::

    p = Planner(machine_limits)           # at rest at machine zero (or start=...)
    p.feed(cmd) / p.feed_many(cmds)       # canonical commands, as the interpreter yields them
    sp = p.next_setpoint()                # once per cycle: a Setpoint, or None when idle at rest
    p.set_feed_override(0.5); p.hold(); p.resume(); p.abort(); p.quick_stop()
    p.waiting_for                         # the sync command the stream is stopped at; p.release()

and faster than real time: ``plan_all(commands, machine)`` yields the whole stream.

Where events ride (``Setpoint.events``), exactly:

* Synchronized outputs (M62/M63 ``DigitalOutput(synced=True)``, M67 ``AnalogOutput(synced=True)``)
  and the other non-motion commands passed on (coolant, spindle speed, tool select, messages,
  override switches) ride on the first setpoint of the next motion, the one sampled where its profile
  starts (from rest: the cycle at rest on its start point, as it begins). When a corner blend starts
  that motion, that is the first setpoint of the blend. If a sync point comes first, they ride on the sync
  point's rest setpoint; if the input ends first (``flush()``, the end of ``plan_all``), on one last
  rest setpoint.
* Immediate outputs (M64/M65, M68: ``synced=False``) ride on the next setpoint emitted after they are
  fed, whatever motion is queued before them.
* Sync commands (``SYNC`` True: dwell, spindle start/stop, M66, tool change, M0/M1, M60, program end)
  run the queue dry: motion stops exactly on the last point, and the command rides on the first
  setpoint at rest there. A dwell then holds that position for its time (rounded up to whole
  cycles). Waits (M66, tool change, M0/M1, M60) then hold with ``waiting_for`` set until
  ``release()``; previews (``plan_all``) release them at once. Spindle start/stop and program end
  continue at once.
* A probe (G38.x) stops first, rides on the first setpoint of its move, ends at rest on its end point
  and waits there (``waiting_for``) for the daemon, which may ``abort()`` the move when the probe
  trips.
* State commands (feed, feed mode, G61/G64, G9, plane, units, offsets, comments) are consumed.
"""

from __future__ import annotations

import importlib
from typing import Any

# Exported lazily: ``planner.setpoints`` (imported by the fieldbus) must not pull in ruckig and numpy.
_EXPORTS = {
    "CheckReport": "planner.checker", "Peaks": "planner.checker", "check_stream": "planner.checker",
    "Planner": "planner.core", "PlannerError": "planner.segments", "plan_all": "planner.core",
    "DEMO_MACHINE": "planner.machine", "AxisLimits": "planner.machine", "MachineError": "planner.machine",
    "MachineLimits": "planner.machine", "Setpoint": "planner.setpoints",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'planner' has no attribute {name!r}")
