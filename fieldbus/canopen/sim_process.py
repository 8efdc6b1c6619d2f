"""Several simulated drives on one python-can bus: one bus object, one reader thread, one ticker.

On ``udp_multicast`` one socket per drive falls behind at 1-2 ms cycles (peers measured 14-17 % of
SYNCs lost); all drives of a process sharing one bus object and one reader thread lost none. So a
:class:`SimBus` owns one ``can.Bus``, one ``canopen.Network`` (whose notifier is the reader thread)
and one housekeeping thread that ticks every drive (boot-up, heartbeat, scheduled faults).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterable

import can
import canopen

from fieldbus.canopen.busopen import open_bus
from fieldbus.canopen.config import CanBusConfig, CanopenConfig
from fieldbus.canopen.drive_sim import SimDrive, motor_for

log = logging.getLogger(__name__)


class SimBus:
    """Run ``drives`` on ``bus`` (or a new bus from ``bus_config``) until :meth:`close`."""

    def __init__(self, drives: Iterable[SimDrive], bus_config: CanBusConfig | None = None,
                 bus: can.BusABC | None = None, tick_s: float = 0.002) -> None:
        self.drives = {d.id: d for d in drives}
        if bus is None:
            bus = open_bus(bus_config or CanBusConfig())
        self.bus = bus
        self.network = canopen.Network(bus)
        self.network.NOTIFIER_SHUTDOWN_TIMEOUT = 2.0
        self.network.connect()
        self._stop = threading.Event()
        self.tick_s = tick_s
        for d in self.drives.values():
            d.attach(self.network)
        self._thread = threading.Thread(target=self._run, name="sim-drives-tick", daemon=True)
        self._thread.start()

    def __getitem__(self, node_id: int) -> SimDrive:
        return self.drives[node_id]

    def _run(self) -> None:
        while not self._stop.wait(self.tick_s):
            for d in self.drives.values():
                try:
                    d.tick()
                except Exception:  # a drive's bug must not stop the others' heartbeats
                    log.exception("simulated drive %d", d.id)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        for d in self.drives.values():
            d.detach()
        try:
            self.network.disconnect()
        except Exception:  # already shut down
            log.debug("closing the simulated drives' bus", exc_info=True)

    def __enter__(self) -> SimBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def machine_sim_drives(canopen: CanopenConfig, lag_s: float) -> list[SimDrive]:
    """The simulated drives of a machine's ``[canopen]``: one per axis (with its motor, and its touch
    probe where configured), and the spindle's (``[canopen.spindle]``)."""
    from fieldbus.canopen.drive_sim_probe import sim_probe

    drives = [SimDrive(d.node_id, d.eds_path, lag_s=lag_s, parameters=motor_for(d, d.eds_path),
                       **sim_probe(d)) for d in canopen.drives]
    if canopen.spindle is not None:
        from fieldbus.canopen.drive_sim_velocity import sim_spindle

        drives.append(sim_spindle(canopen.spindle))
    return drives
