"""Cyclic and PDO handling of the simulated drive (:mod:`fieldbus.canopen.drive_sim`): the PDO mapping
read from the drive's own dictionary (what the master wrote by SDO), RPDOs applied on receipt, SYNC
driving the cycle and the SYNC TPDOs, event TPDOs on change (inhibit time) and on their event timer.
"""

from __future__ import annotations

import contextlib
import struct
from dataclasses import dataclass

import canopen

from fieldbus.canopen.drive_sim_cia402 import NMT_OPERATIONAL


@dataclass
class PdoMap:
    cob_id: int
    transmission: int
    entries: tuple[tuple[int, int, int], ...]  # (index, subindex, bytes)
    fmt: str = ""
    inhibit_s: float = 0.0
    event_timer_s: float = 0.0

    @property
    def event(self) -> bool:
        return self.transmission in (254, 255)


_FMT = {(1, True): "b", (1, False): "B", (2, True): "h", (2, False): "H", (4, True): "i", (4, False): "I"}


class CyclicMixin:
    """SYNC, RPDOs and TPDOs of :class:`~fieldbus.canopen.drive_sim.SimDrive` (its state lives there)."""

    node: canopen.LocalNode
    network: canopen.Network | None
    _rpdos: list[PdoMap]
    _tpdos: list[PdoMap]
    _event_sent: dict[int, tuple[bytes, float]]
    _subscribed: list[int]

    def _read_pdo(self, comm: int, mapping: int) -> PdoMap | None:
        if comm not in self.node.object_dictionary or mapping not in self.node.object_dictionary:
            return None  # an EDS with fewer PDOs
        cob = self._value(comm, 1)
        n = self._value(mapping, 0)
        if cob & 0x80000000 or n == 0:
            return None
        entries = []
        fmt = "<"
        for sub in range(1, n + 1):
            m = self._value(mapping, sub)
            index, subindex, bits = m >> 16, (m >> 8) & 0xFF, m & 0xFF
            obj = self.node._find_object(index, subindex)
            signed = obj.data_type in (canopen.objectdictionary.INTEGER8, canopen.objectdictionary.INTEGER16,
                                       canopen.objectdictionary.INTEGER32)
            entries.append((index, subindex, bits // 8))
            fmt += _FMT[(bits // 8, signed)]
        timing = [0.0, 0.0]
        if comm >= 0x1800:  # TPDO: inhibit time (100 us units) and event timer (ms), where the EDS has them
            for i, (sub, unit) in enumerate(((3, 1e-4), (5, 1e-3))):
                with contextlib.suppress(KeyError):
                    timing[i] = self._value(comm, sub) * unit
        return PdoMap(cob & 0x7FF, self._value(comm, 2), tuple(entries), fmt, *timing)

    def _subscribe_pdos(self) -> None:
        self._unsubscribe_pdos()
        self._rpdos = [p for p in (self._read_pdo(0x1400 + i, 0x1600 + i) for i in range(4)) if p]
        self._tpdos = [p for p in (self._read_pdo(0x1800 + i, 0x1A00 + i) for i in range(4)) if p]
        self._event_sent = {}
        for p in self._rpdos:
            self.network.subscribe(p.cob_id, self._on_rpdo)  # type: ignore[union-attr]
            self._subscribed.append(p.cob_id)

    def _unsubscribe_pdos(self) -> None:
        if self.network is not None:
            for cob in self._subscribed:
                # with the callback: never drop other nodes' subscribers on a shared network
                self.network.unsubscribe(cob, self._on_rpdo)
        self._subscribed = []

    def _on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self.lock:
            if self.nmt_state != NMT_OPERATIONAL:
                return
            for p in self._rpdos:
                if p.cob_id != can_id:
                    continue
                self.rpdos += 1
                try:
                    values = struct.unpack_from(p.fmt, data)
                except struct.error:
                    continue
                for (index, _sub, _size), value in zip(p.entries, values, strict=True):
                    if index == 0x6040:
                        self._controlword(value)
                    elif index == 0x607A:
                        self._pending_target = value
                    elif index == 0x60FF:
                        self._set_target_velocity(value)
            self._event_tpdos()

    # ------------------------------------------------------------------ the cycle
    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        now = self.clock()
        with self.lock:
            if self.nmt_state != NMT_OPERATIONAL:
                return
            self._load_params()
            period = self._period or 0.002
            if self._last_sync is not None and now - self._last_sync > 1.5 * period:
                self.late_syncs += 1
            self._last_sync = now
            self.syncs += 1
            before = self.actual
            self._step(period)
            self._probe_sample(before)
            for p in self._tpdos:
                if 1 <= p.transmission <= 240 and self.syncs % p.transmission == 0:
                    self._send(p.cob_id, self._encode(p))
            self._event_tpdos(now)

    def _event_tpdos(self, now: float | None = None) -> None:
        """Send each event TPDO whose data changed since it was last sent (once its inhibit time has
        passed), or whose event timer has run out. Called, with the lock held, after everything that
        can change the drive's state: SYNC, RPDO, SDO write, tick."""
        if self.nmt_state != NMT_OPERATIONAL or self.network is None:
            return
        now = self.clock() if now is None else now
        for p in self._tpdos:
            if not p.event:
                continue
            data = self._encode(p)
            last = self._event_sent.get(p.cob_id)
            if last is not None:
                changed = data != last[0] and now - last[1] >= p.inhibit_s
                due = p.event_timer_s > 0 and now - last[1] >= p.event_timer_s
                if not (changed or due):
                    continue
            self._send(p.cob_id, data)
            self._event_sent[p.cob_id] = (data, now)

    def _encode(self, p: PdoMap) -> bytes:
        values = []
        for index, sub, _size in p.entries:
            v = self._on_read(index, sub, None)
            values.append(self._value(index, sub) if v is None else v)
        return struct.pack(p.fmt, *values)
