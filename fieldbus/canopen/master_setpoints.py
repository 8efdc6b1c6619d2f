"""The master's RPDOs handed to the SYNC process ahead of their SYNC (``[canopen] sync = "process"``).

Part of :class:`~fieldbus.canopen.master.CanopenMaster`. The cycle gathers its RPDOs into one set and
pushes it tagged with the SYNC that is to latch it, up to :attr:`setpoint_lead` SYNCs ahead of the last
one the SYNC process reported; the SYNC process sends each set right after the SYNC before its own
(:mod:`fieldbus.canopen.setpoint_buffer`, which also says how stops, enables and homing pass the
buffer). Without the SYNC process every method here sends at once on the master's socket, as before.
"""

from __future__ import annotations

import logging
import sys

import can

from fieldbus.canopen.master_records import MasterCore
from fieldbus.canopen.sync_process import SyncProcess, SyncProcessError

log = logging.getLogger(__name__)


class SetpointsMixin(MasterCore):
    """The cycle's RPDOs, now or ahead (module docstring)."""

    setpoint_lead: int
    _setpoints: SyncProcess | None  # the SYNC process, while it sends the RPDOs
    _next_tag: int  # the SYNC the next set is for (0: from the one after the last seen)
    _generation: int  # raised at each stop: a set pushed before it is void
    _frames: list[tuple[int, bytes]] | None  # the cycle's RPDOs, while it gathers them
    #: the SYNC the last :meth:`cycle` pushed its set for (0: it pushed none: sent at once, or nothing)
    last_set_tag: int

    def _send(self, cob_id: int, data: bytes) -> None:
        assert self.network is not None
        self.network.send_message(cob_id, data)

    def _cyclic(self, cob_id: int, data: bytes) -> None:
        """A cycle's RPDO: sent now (for the next SYNC), or gathered for the SYNC process."""
        if self._frames is not None:
            self._frames.append((cob_id, data))
        else:
            self._send(cob_id, data)

    def setpoints_wanted(self) -> int:
        """How many cycles the caller should run now, each with its setpoint: 1, except with the SYNC
        process sending the RPDOs (:attr:`setpoint_lead` > 1), where it is what fills the buffer up to
        the lead (0 when full; up to the lead after a stop or a stall). Callers that run one cycle
        per SYNC regardless get a lead of 1."""
        timer = self._setpoints
        if timer is None:
            return 1
        seen = timer.number
        return max(0, seen + self.setpoint_lead - max(self._next_tag, seen + 1) + 1)

    def _push(self, frames: list[tuple[int, bytes]]) -> None:
        """With ``_lock`` held: a cycle's RPDOs to the SYNC process, for the next SYNC not yet given
        a set (SYNCs already past are skipped: the drives held there)."""
        timer = self._setpoints
        assert timer is not None
        tag = max(self._next_tag, timer.number + 1)
        if self._next_tag == 0:
            timer.expect_from = tag
        timer.push(tag, frames, self._generation)
        self._next_tag = tag + 1
        self.last_set_tag = tag

    @property
    def sync_number(self) -> int:
        """With the SYNC process: the number of the last SYNC it reported. A set tagged ``t`` has gone
        out once this is ``t - 1`` or more (or was dropped by a stop: :attr:`setpoint_generation`)."""
        timer = self._setpoints
        return timer.number if timer is not None else 0

    @property
    def setpoint_generation(self) -> int:
        """Raised at each stop: the sets pushed before it never go out."""
        return self._generation

    def _stopped(self, frames: list[tuple[int, bytes]]) -> None:
        """With ``_lock`` held, after a stop's frames went out on the master's own socket: through the
        SYNC process too, which drops every set it still holds first (the stop is then the last RPDO
        before the next SYNC: :mod:`fieldbus.canopen.setpoint_buffer`)."""
        timer = self._setpoints
        if timer is None:
            return
        self._generation += 1
        self._next_tag = 0
        timer.expect_from = sys.maxsize
        try:
            timer.now(frames, flush=True, generation=self._generation)
        except SyncProcessError as exc:  # sent on the master's socket already; its SYNC stops with it
            log.error("the stop's frames not passed to the SYNC process: %s", exc)

    def _hold_now(self, frames: list[tuple[int, bytes]]) -> None:
        """With ``_lock`` held: a drive that became active gets ``frames`` (its holding target) at once,
        and in every set already buffered. Else they go out on the master's socket."""
        timer = self._setpoints
        if timer is None:
            for cob_id, data in frames:
                self._send(cob_id, data)
            return
        try:
            timer.now(frames, merge=True)
            if self._next_tag == 0:
                self._fill_with_holds(timer)
        except SyncProcessError as exc:
            raise can.CanError(str(exc)) from None

    def _fill_with_holds(self, timer: SyncProcess) -> None:
        """With ``_lock`` held, nothing buffered yet (the first drive enabled, or the first since a
        stop): the active drives' holding targets fill the lead at once. Else the buffer would fill
        only at the next cycle, and a cycle late past one period then cost the SYNCs just after the
        enable their setpoints (seen beside two CPU hogs: one missed by each drive)."""
        held = [(d.rpdo_id, d.cyclic_rpdo()) for d in self.drives if d.active and not d.homing]
        first = timer.number + 1
        timer.expect_from = first
        for tag in range(first, first + self.setpoint_lead):
            timer.push(tag, held, self._generation)
        self._next_tag = first + self.setpoint_lead

    def _unbuffer(self, cob_ids: list[int]) -> None:
        """With ``_lock`` held: these frames out of every buffered set (a drive that starts homing)."""
        timer = self._setpoints
        if timer is not None:
            try:
                timer.drop(cob_ids)
            except SyncProcessError as exc:
                raise can.CanError(str(exc)) from None

