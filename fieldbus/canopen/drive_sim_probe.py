"""The touch probe of the simulated drive (:mod:`fieldbus.canopen.drive_sim`): CiA 402 0x60B8-0x60BD.

The drive has one probe input, switched by the axis's own position: active at or below
``probe_trip_counts`` (``probe_active_below``, a probe touching a surface from above), or at or above
it. Touch probes 1 and 2 both sample that input. 0x60B8 (touch probe function) per probe, bits
shifted by 8 for probe 2: bit 0 enable, bit 1 continuous (else the first event only), bits 2-3
trigger source (0: the probe input; other sources never trigger here), bit 4/5 sample the positive
(inactive -> active) / negative edge. Enabling a probe or an edge (a 0 -> 1 of its bit) arms it and
clears what it had stored. 0x60B9 (status): bit 0 enabled, bit 1/2 positive/negative edge position
stored; 0x60BA/0x60BB (probe 1) and 0x60BC/0x60BD (probe 2) the latched positions. Bits 7 and 15
(manufacturer-specific) show the probe input's level, as many drives do (the master reads it with
``touch_probe_level_bit = 7`` or 15).

The latch is exact, as a drive latches its encoder count in hardware on the input's edge: the edge
falls between two position samples of a SYNC period (or of the drive's own clock), and the position
latched is the one at the edge, interpolated inside the period; never a sample's.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from fieldbus.canopen.config import DriveConfig

log = logging.getLogger("fieldbus.canopen.drive_sim")

TOUCH_PROBE_FUNCTION, TOUCH_PROBE_STATUS = 0x60B8, 0x60B9
#: (positive edge, negative edge) latched position objects of probes 1 and 2
TOUCH_PROBE_POSITIONS = {1: (0x60BA, 0x60BB), 2: (0x60BC, 0x60BD)}
TP_ENABLE, TP_CONTINUOUS, TP_SOURCE, TP_POSITIVE, TP_NEGATIVE = 0x01, 0x02, 0x0C, 0x10, 0x20
TP_STATUS_ENABLED, TP_STATUS_POSITIVE, TP_STATUS_NEGATIVE = 0x01, 0x02, 0x04
#: 0x60B9 bits of this drive's (manufacturer-specific): the probe input is active
TP_STATUS_LEVEL = 0x8080
PROBE_OBJECTS = frozenset({TOUCH_PROBE_STATUS, *(i for pair in TOUCH_PROBE_POSITIONS.values() for i in pair)})


def sim_probe(cfg: DriveConfig, position: float | None = None) -> dict[str, int | bool]:
    """``SimDrive`` keyword arguments for a probe input active at and below machine ``position``
    (default the axis's ``sim_probe_position``; none: no arguments). Below in machine units is the
    drive's positive side when the axis counts the other way (a negative scale)."""
    from fieldbus.canopen.config import AxisScale

    position = cfg.sim_probe_position if position is None else position
    if position is None:
        return {}
    scale = AxisScale(cfg)
    return {"probe_trip_counts": scale.to_counts(position), "probe_active_below": scale.scale > 0}


class TouchProbeMixin:
    """Touch probe of :class:`~fieldbus.canopen.drive_sim.SimDrive` (its position lives there)."""

    actual: float
    id: int
    #: the probe input's switching position in counts (None: no probe wired)
    probe_trip_counts: int | None = None
    probe_active_below: bool = True

    def _probe_reset(self) -> None:
        self._tp_function = 0
        self._tp_status = 0
        self._tp_latched: dict[int, int] = {}  # object index: latched counts

    def probe_input(self, position: float | None = None) -> bool:
        """The probe input at ``position`` (counts; default the actual position)."""
        trip = self.probe_trip_counts
        if trip is None:
            return False
        pos = self.actual if position is None else position
        return pos <= trip if self.probe_active_below else pos >= trip

    def _probe_function(self, value: int) -> None:
        """0x60B8 written: (re-)arm the probes and edges whose enable bit went 0 -> 1."""
        before, self._tp_function = self._tp_function, value
        for n in TOUCH_PROBE_POSITIONS:
            shift = 8 * (n - 1)
            f, old = value >> shift & 0xFF, before >> shift & 0xFF
            if not f & TP_ENABLE:
                self._tp_status &= ~(0xFF << shift)
                continue
            cleared = 0
            if not old & TP_ENABLE:
                cleared = TP_STATUS_POSITIVE | TP_STATUS_NEGATIVE
            else:
                cleared |= TP_STATUS_POSITIVE if f & TP_POSITIVE and not old & TP_POSITIVE else 0
                cleared |= TP_STATUS_NEGATIVE if f & TP_NEGATIVE and not old & TP_NEGATIVE else 0
            self._tp_status = (self._tp_status & ~(cleared << shift)) | (TP_STATUS_ENABLED << shift)

    def _probe_read(self, index: int) -> int:
        if index == TOUCH_PROBE_STATUS:
            return self._tp_status | (TP_STATUS_LEVEL if self.probe_input() else 0)
        return self._tp_latched.get(index, 0)

    def _probe_sample(self, before: float) -> None:
        """After the position moved from ``before`` to ``actual``: latch the edge the input made, if
        an armed probe samples it."""
        was, now = self.probe_input(before), self.probe_input()
        if was == now or not self._tp_function:
            return
        trip = self.probe_trip_counts
        assert trip is not None
        # where inside the period the input switched (the motion taken as straight between the two
        # samples): the position there, as the drive's hardware latches its count at the edge
        moved = self.actual - before
        at = round(before + (trip - before) / moved * moved) if moved else round(self.actual)
        stored, edge = (TP_STATUS_POSITIVE, TP_POSITIVE) if now else (TP_STATUS_NEGATIVE, TP_NEGATIVE)
        for n, objects in TOUCH_PROBE_POSITIONS.items():
            shift = 8 * (n - 1)
            f = self._tp_function >> shift & 0xFF
            if not f & TP_ENABLE or not f & edge or f & TP_SOURCE:
                continue
            if self._tp_status >> shift & stored and not f & TP_CONTINUOUS:
                continue  # first event only: already latched
            self._tp_latched[objects[0] if now else objects[1]] = at
            self._tp_status |= stored << shift
            log.info("drive %d: touch probe %d latched %s edge at %d counts", self.id, n,
                     "positive" if now else "negative", at)
