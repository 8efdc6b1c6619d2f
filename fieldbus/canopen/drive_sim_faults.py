"""Fault injection into the simulated drive (:mod:`fieldbus.canopen.drive_sim`), from tests in the same
process or by SDO to the simulation-only object 0x2F00 from another one (``canon sim inject``)."""

from __future__ import annotations

import logging

from fieldbus.canopen.cia402 import State
from fieldbus.canopen.drive_sim_cia402 import EMCY_GENERIC

log = logging.getLogger("fieldbus.canopen.drive_sim")

# Manufacturer-specific, simulation only (not on a real drive): an SDO write of a non-zero code to
# sub 1 faults the drive with that EMCY code, after the delay in ms held in sub 2 (write it first);
# writing 0 to sub 1 cancels faults still waiting for their delay.
SIM_INJECT = 0x2F00
SIM_INJECT_CODE, SIM_INJECT_DELAY_MS = 1, 2
#: sub 3: the drive's local quick-stop input (1 active, 0 released), as a wired button or limit switch
SIM_QUICK_STOP_INPUT = 3
#: sub 4: send a warning EMCY with this code (error register 0); the drive goes on as it is
SIM_WARNING = 4


class FaultInjectionMixin:
    """Faults a test injects into :class:`~fieldbus.canopen.drive_sim.SimDrive` (its state lives there)."""

    def inject_fault(self, code: int = EMCY_GENERIC, at: float | None = None) -> None:
        """Fault now, or at clock time ``at`` (sends EMCY ``code``)."""
        with self.lock:
            if at is None:
                self._fault(code, "injected")
            else:
                self._scheduled.append((at, code))

    def _injected_by_sdo(self, code: int) -> None:
        """0x2F00:01 written (from another process): fault with ``code`` after 0x2F00:02 ms; 0 cancels."""
        if code == 0:
            self._scheduled.clear()
            return
        delay_ms = self._value(SIM_INJECT, SIM_INJECT_DELAY_MS)
        log.info("drive %d: EMCY 0x%04X injected by SDO, in %d ms", self.id, code, delay_ms)
        if delay_ms:
            self._scheduled.append((self.clock() + delay_ms / 1000.0, code))
        else:
            self._fault(code, "injected by SDO")

    def send_warning(self, code: int, register: int = 0) -> None:
        """Send an EMCY that is a warning (error register 0 by default): the drive stays as it is."""
        with self.lock:
            self.emcys.append(code)
            if self.network is not None:
                self.node.emcy.send(code, register)

    def drop_heartbeat(self, seconds: float) -> None:
        """Send no heartbeat for ``seconds``."""
        self._hb_dropped_until = self.clock() + seconds

    def abort_sdo(self, index: int, subindex: int = 0, code: int = 0x08000020) -> None:
        """Answer SDO access to ``index:subindex`` with abort ``code`` (0 removes it)."""
        if code:
            self._sdo_aborts[(index, subindex)] = code
        else:
            self._sdo_aborts.pop((index, subindex), None)

    def set_quick_stop_input(self, active: bool) -> None:
        """The drive's local quick-stop input (a wired stop button, a limit switch on the drive): on
        activation in Operation enabled the drive goes to Quick stop active and ramps down at 0x6085,
        ending as its quick stop option (0x605A) says; while it is active the drive does not enable."""
        with self.lock:
            self.quick_stop_input = active
            if active and self.state == State.OPERATION_ENABLED:
                log.info("drive %d: local quick stop input", self.id)
                self._homing = False
                self.state = State.QUICK_STOP_ACTIVE
            self._event_tpdos()

    def inject_disable(self) -> None:
        """Drop to Switch on disabled, as a drive does when its safe-torque-off input opens."""
        with self.lock:
            self.state = State.SWITCH_ON_DISABLED
            self.velocity = 0.0

    def stall(self, stalled: bool = True) -> None:
        """The motor stops following (a jammed axis): the following error grows."""
        self._stalled = stalled
