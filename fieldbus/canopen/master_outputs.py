"""The drives' digital outputs (CiA 402 0x60FE), part of :class:`~fieldbus.canopen.master.CanopenMaster`.

:meth:`OutputsMixin.set_output` switches one bit of an axis drive's 0x60FE:01 (physical outputs) and
returns at once with a future; the master's ``canon-do`` thread writes it by SDO (0x60FE:02, the bit
mask that enables the outputs the master drives, first when a new bit joins it), so that the cycle
thread never waits on the bus. canon's PDO layouts (:mod:`fieldbus.canopen.pdo`) do not map 0x60FE:
an output switches a few times a program, and an SDO write per switch costs less bus than a PDO every
cycle. The writes of one drive go out in the order asked; the future's result is the time
(``time.monotonic``) the drive confirmed the write, its exception a :class:`CanopenError` naming node,
object and abort code (a drive without 0x60FE, a lost answer).

The master keeps the word it commanded (:meth:`OutputsMixin.outputs`), and writes it again after the
drive's boot (an NMT reset clears a drive's outputs).
"""

from __future__ import annotations

import concurrent.futures
import logging
import time

from fieldbus.canopen.master_records import CanopenError, DriveBook, MasterCore

log = logging.getLogger(__name__)

DIGITAL_OUTPUTS = 0x60FE


class OutputsMixin(MasterCore):
    """0x60FE of the axis drives, part of :class:`~fieldbus.canopen.master.CanopenMaster`."""

    _do_pool: concurrent.futures.ThreadPoolExecutor | None = None

    def set_output(self, axis: int, bit: int, on: bool) -> concurrent.futures.Future[float]:
        """Bit ``bit`` of drive ``axis``'s (index in the axis order) 0x60FE:01 on or off; the write
        happens on the ``canon-do`` thread (module docstring). Any thread; never blocks."""
        if not 0 <= bit <= 31:
            raise ValueError(f"0x60FE bit {bit}: 0 to 31")
        d = self.drives[axis]
        with self._lock:
            d.outputs = d.outputs | (1 << bit) if on else d.outputs & ~(1 << bit)
            d.outputs_mask |= 1 << bit
            if self._do_pool is None:
                self._do_pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="canon-do")
            return self._do_pool.submit(self._write_outputs, d)

    def outputs(self) -> tuple[int, ...]:
        """The 0x60FE:01 word commanded to each axis drive (axis order)."""
        return tuple(d.outputs for d in self.drives)

    def _write_outputs(self, d: DriveBook) -> float:
        if self.network is None:
            raise CanopenError(f"{d.describe()}: digital outputs 0x60FE not written: the bus is closed")
        with self._lock:
            word, mask = d.outputs, d.outputs_mask
        if mask != d.outputs_mask_written:
            self._sdo(d, "digital outputs bit mask", DIGITAL_OUTPUTS, 2, "I", mask)
            d.outputs_mask_written = mask
        self._sdo(d, "digital outputs", DIGITAL_OUTPUTS, 1, "I", word)
        return time.monotonic()

    def _restore_outputs(self, d: DriveBook) -> None:
        """After the drive's boot: the outputs as commanded (boot thread)."""
        d.outputs_mask_written = 0
        if d.outputs_mask:
            self._write_outputs(d)

    def _stop_outputs(self) -> None:
        """At shutdown: the writes asked for are done, then the thread ends."""
        pool, self._do_pool = self._do_pool, None
        if pool is not None:
            pool.shutdown(wait=True)
