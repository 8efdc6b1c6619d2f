"""The machine's probe input as a drive's CiA 402 touch probe (0x60B8-0x60BD), for G38.x.

One axis's drive carries the probe input (``[canopen.axes.<a>] touch_probe = 1`` or 2: which of the
drive's two touch probes). The drive latches its position count in hardware on the input's edge, so
the probed position is exact to the encoder count, not the position of the cycle in which the master
saw the trip (one cycle's travel: 10 µm at 300 mm/min and 2 ms).

* Boot (:func:`check_objects`, from the master before anything is written): the drive must have the
  touch probe function, status and the probe's two latched positions; a drive without them is refused
  naming node, axis, key and object.
* Boot (:func:`~fieldbus.canopen.commissioning.boot_writes`): the status 0x60B9 is mapped into TPDO4
  after the digital inputs (:meth:`~fieldbus.canopen.pdo.PdoLayout.with_touch_probe`), an event PDO:
  the drive sends it when the probe latches, and :attr:`TouchProbe.tripped` sees it on the next cycle.
* Each probing move (:class:`TouchProbe`): :meth:`~TouchProbe.arm` by SDO before the move starts
  (first event only; the positive edge, contact made, for G38.2/G38.3, the negative edge, contact
  lost, for G38.4/G38.5); the caller stops the motion when :attr:`~TouchProbe.tripped`; then
  :meth:`~TouchProbe.result` reads the status and the latched position by SDO and disarms.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

from fieldbus.canopen.pdo import TOUCH_PROBE_STATUS

if TYPE_CHECKING:
    from fieldbus.canopen.master import CanopenMaster
    from fieldbus.canopen.master_records import DriveBook

log = logging.getLogger(__name__)

FUNCTION, STATUS = 0x60B8, 0x60B9
#: probe number: (positive edge, negative edge) latched position objects
POSITIONS = {1: (0x60BA, 0x60BB), 2: (0x60BC, 0x60BD)}
#: 0x60B8 bits of probe 1 (probe 2: shifted by 8): enable, sample the positive / negative edge
ENABLE, POSITIVE, NEGATIVE = 0x01, 0x10, 0x20
#: 0x60B9 bits of probe 1 (probe 2: shifted by 8): enabled, positive / negative edge position stored
ENABLED, POSITIVE_STORED, NEGATIVE_STORED = 0x01, 0x02, 0x04


def objects(probe: int) -> list[tuple[int, str]]:
    """The objects touch probe ``probe`` (1 or 2) needs, and their names."""
    pos, neg = POSITIONS[probe]
    return [(FUNCTION, "touch probe function"), (STATUS, "touch probe status"),
            (pos, f"touch probe {probe} position, positive edge"),
            (neg, f"touch probe {probe} position, negative edge")]


def check_objects(master: CanopenMaster, d: DriveBook) -> None:
    """Boot, before anything is written: the drive has every object of its configured touch probe
    (else a :class:`~fieldbus.canopen.master.CanopenError` naming node, axis, key and object)."""
    from fieldbus.canopen.master import CanopenError

    missing: dict[int, int] = {}
    for index, what in objects(d.cfg.touch_probe):
        master._sdo(d, what, index, 0, absent=missing)
        if index in missing:
            raise CanopenError(
                f"{d.describe()}: canopen.axes.{d.cfg.axis}.touch_probe = {d.cfg.touch_probe}, but the drive "
                f"has no object 0x{index:04X} ({what}; SDO abort 0x{missing[index]:08X}): it has no CiA 402 "
                "touch probe; remove the key (G38.x then has no probe input on this machine)")


@dataclass(frozen=True)
class ProbeResult:
    """After a probing move: whether the probe latched, and where (counts and machine units)."""

    tripped: bool
    counts: int = 0
    position: float = 0.0


class TouchProbe:
    """The configured drive's touch probe, on a booted master (see the module's text)."""

    def __init__(self, master: CanopenMaster, d: DriveBook) -> None:
        from fieldbus.canopen.master import CanopenError

        if not d.has_inputs:
            raise CanopenError(f"{d.describe()}: canopen.axes.{d.cfg.axis}.touch_probe: the touch probe "
                               "status travels in TPDO4 with the digital inputs (0x60FD), which this drive "
                               "lacks (see the warning at boot)")
        self.master = master
        self.drive = d
        self.axis = d.cfg.axis
        self.shift = 8 * (d.cfg.touch_probe - 1)
        self._edge = POSITIVE_STORED
        self.status = 0  # 0x60B9, from TPDO4 (reader thread) or the last SDO read
        pdo = master.layout.with_touch_probe().carrying(TOUCH_PROBE_STATUS, tpdo=True)
        self._struct = pdo.struct
        self._at = pdo.objects.index(STATUS)
        assert master.network is not None
        # beside the master's own reader of that TPDO (which takes the inputs from its first bytes);
        # the network's subscription ends with the master's
        master.network.subscribe(pdo.cob_id(d.cfg.node_id), self._on_tpdo)

    @classmethod
    def of(cls, master: CanopenMaster) -> TouchProbe | None:
        """The touch probe of the drive configured with one, or None."""
        d = next((x for x in master.drives if x.cfg.touch_probe), None)
        return None if d is None else cls(master, d)

    def _on_tpdo(self, cob_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) >= self._struct.size:
            self.status = self._struct.unpack_from(data)[self._at]

    def arm(self, toward: bool) -> bool | None:
        """Arm for one probing move (job thread, SDO): the first positive edge (``toward``: contact
        made, G38.2/G38.3) or negative edge (contact lost, G38.4/G38.5) latches. Disabled first, so
        that the edge's stored bit and position of an earlier probing are cleared. Returns the probe
        input's level now (True: in contact), where the drive shows it in the status
        (``touch_probe_level_bit``), else None: a probe already in contact makes no edge."""
        d = self.drive
        self._edge = POSITIVE_STORED if toward else NEGATIVE_STORED
        function = (ENABLE | (POSITIVE if toward else NEGATIVE)) << self.shift
        self.master._sdo(d, "touch probe function (off)", FUNCTION, 0, "H", 0)
        self.master._sdo(d, "touch probe function (arm)", FUNCTION, 0, "H", function)
        self.status = self.master._sdo(d, "touch probe status", STATUS, 0, "H")
        bit = d.cfg.touch_probe_level_bit
        return None if bit is None else bool(self.status >> bit & 1)

    @property
    def tripped(self) -> bool:
        """The armed edge latched (as the drive last reported: TPDO4 or SDO)."""
        return bool(self.status >> self.shift & self._edge)

    def result(self) -> ProbeResult:
        """After the probing move stopped (job thread, SDO): whether the armed edge latched and its
        position; the probe is disarmed."""
        d = self.drive
        self.status = self.master._sdo(d, "touch probe status", STATUS, 0, "H")
        out = ProbeResult(False)
        if self.tripped:
            index = POSITIONS[d.cfg.touch_probe][0 if self._edge == POSITIVE_STORED else 1]
            counts = self.master._sdo(d, "touch probe position", index, 0, "i")
            out = ProbeResult(True, counts, d.scale.to_units(counts))
        self.disarm()
        return out

    def disarm(self) -> None:
        self.master._sdo(self.drive, "touch probe function (off)", FUNCTION, 0, "H", 0)
