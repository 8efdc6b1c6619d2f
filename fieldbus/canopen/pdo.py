"""The PDO layouts the master sets up on each drive, and what they cost on the bus.

One description serves the master (the SDO writes that configure the drive, how it packs the RPDOs and
reads the TPDOs), the bus budget (:mod:`fieldbus.canopen.busload`) and ``canon can-dump``.

Two layouts carry the same objects: target position and controlword to the drive; statusword,
position actual and following error back.

``standard``
    RPDO1 = target position + controlword, TPDO1 = statusword + position actual, both every SYNC;
    TPDO2 = following error every ``following_error_every`` SYNCs. Three frames per drive and cycle:
    the plainest mapping, and what most drive manuals show.

``compact``
    Only what changes every cycle travels every cycle: RPDO1 = target position and TPDO1 = position
    actual (4 bytes each) on every SYNC. The controlword goes in RPDO2, sent by the master only when it
    changes (transmission type 255: the drive acts on reception). The statusword comes in TPDO3,
    sent by the drive when it changes (type 255), and every ``status_refresh_ms`` besides (event
    timer). Following error in TPDO2 every ``following_error_every`` SYNCs. A drive's own following
    error check (0x6065) sets statusword bit 13, which the master sees at once, so a sparser
    following-error PDO delays only the reported value, never the fault. Six drives at 2 ms fit in
    70 % of 1 Mbit/s this way (with ``following_error_every = 4``); in ``standard`` they need 100 %.

Both layouts add TPDO4 = digital inputs (0x60FD: limit and home switches), transmission type 255 with
no event timer: the drive sends it when a switch changes (and on entering Operational), so it adds no
cyclic load. A drive without 0x60FD keeps TPDO4 disabled (a warning at boot). The drive with the
machine's touch probe also has the touch probe status (0x60B9) in TPDO4, after the inputs
(:meth:`PdoLayout.with_touch_probe`): sent when the probe latches.
"""

from __future__ import annotations

import dataclasses
import struct
from dataclasses import dataclass

TARGET_POSITION = (0x607A, 0, 32)
CONTROLWORD = (0x6040, 0, 16)
STATUSWORD = (0x6041, 0, 16)
POSITION_ACTUAL = (0x6064, 0, 32)
FOLLOWING_ERROR = (0x60F4, 0, 32)
DIGITAL_INPUTS = (0x60FD, 0, 32)
TOUCH_PROBE_STATUS = (0x60B9, 0, 16)
TARGET_VELOCITY = (0x60FF, 0, 32)  # the spindle drive's (fieldbus.canopen.master_spindle)
VELOCITY_ACTUAL = (0x606C, 0, 32)

_SIGNED = {0x607A, 0x6064, 0x60F4, 0x60FF, 0x606C}
#: transmission type 255: event-driven (device profile specific), acted on / sent on reception / change
EVENT = 255
LAYOUTS = ("standard", "compact")
#: how many RPDOs and TPDOs a CiA 402 drive has (CiA 301's default connection set): the master
#: disables every one it does not use, so a drive's factory mapping cannot add traffic
PDOS_PER_DIRECTION = 4


@dataclass(frozen=True)
class Pdo:
    """One PDO: direction, number (1-4), mapped objects ``(index, subindex, bits)``, transmission type
    (1-240: on every n-th SYNC; 255: event) and, for event TPDOs, the event timer."""

    tpdo: bool
    number: int
    entries: tuple[tuple[int, int, int], ...]
    transmission: int = 1
    event_timer_ms: int = 0

    @property
    def comm_index(self) -> int:
        return (0x1800 if self.tpdo else 0x1400) + self.number - 1

    @property
    def mapping_index(self) -> int:
        return (0x1A00 if self.tpdo else 0x1600) + self.number - 1

    def cob_id(self, node_id: int) -> int:
        return cob_base(self.tpdo, self.number) + node_id

    @property
    def name(self) -> str:
        return f"{'T' if self.tpdo else 'R'}PDO{self.number}"

    @property
    def data_bytes(self) -> int:
        return sum(bits for _, _, bits in self.entries) // 8

    @property
    def objects(self) -> tuple[int, ...]:
        return tuple(index for index, _, _ in self.entries)

    @property
    def struct(self) -> struct.Struct:
        return struct.Struct("<" + "".join(_code(index, bits) for index, _, bits in self.entries))

    @property
    def cyclic(self) -> bool:
        return 1 <= self.transmission <= 240


def cob_base(tpdo: bool, number: int) -> int:
    """CiA 301's predefined connection set: TPDOn at 0x180 + 0x100 (n-1), RPDOn at 0x200 + 0x100 (n-1)."""
    return (0x180 if tpdo else 0x200) + 0x100 * (number - 1)


def _code(index: int, bits: int) -> str:
    code = {8: "b", 16: "h", 32: "i"}[bits]
    return code if index in _SIGNED else code.upper()


@dataclass(frozen=True)
class PdoLayout:
    """The PDOs of one layout (see the module's text); ``sdo_steps`` configures a drive for it."""

    name: str
    rpdos: tuple[Pdo, ...]
    tpdos: tuple[Pdo, ...]
    following_error_every: int
    status_refresh_ms: int

    def carrying(self, obj: tuple[int, int, int], tpdo: bool) -> Pdo:
        """The PDO that carries ``obj``."""
        for p in self.tpdos if tpdo else self.rpdos:
            if obj in p.entries:
                return p
        raise KeyError(f"no {'T' if tpdo else 'R'}PDO carries 0x{obj[0]:04X} in the {self.name} layout")

    def with_touch_probe(self) -> PdoLayout:
        """This layout with the touch probe status (0x60B9) after the digital inputs in their TPDO, for
        the drive that has the machine's probe: the master reads the inputs from the PDO's first
        bytes as on every drive."""
        inputs = self.carrying(DIGITAL_INPUTS, tpdo=True)
        probe = dataclasses.replace(inputs, entries=(*inputs.entries, TOUCH_PROBE_STATUS))
        return dataclasses.replace(self, tpdos=tuple(probe if p is inputs else p for p in self.tpdos))

    def sdo_steps(self, node_id: int) -> list[tuple[str, int, int, str, int]]:
        """``(what, index, subindex, struct code, value)`` writes, in CiA 301's order: disable the PDO
        (COB-ID bit 31), set its transmission, clear its mapping, map, set the count, enable. PDOs
        the layout does not use are disabled (:func:`unused_pdos`)."""
        steps: list[tuple[str, int, int, str, int]] = []
        for p in (*self.rpdos, *self.tpdos):
            cob = p.cob_id(node_id)
            steps += [
                (f"{p.name} COB-ID (disable)", p.comm_index, 1, "I", 0x80000000 | cob),
                (f"{p.name} transmission type", p.comm_index, 2, "B", p.transmission),
            ]
            if p.tpdo and p.event_timer_ms:
                steps.append((f"{p.name} event timer", p.comm_index, 5, "H", p.event_timer_ms))
            steps.append((f"{p.name} mapping count", p.mapping_index, 0, "B", 0))
            for i, (index, sub, bits) in enumerate(p.entries, 1):
                steps.append((f"{p.name} map 0x{index:04X}", p.mapping_index, i, "I",
                              (index << 16) | (sub << 8) | bits))
            steps += [
                (f"{p.name} mapping count", p.mapping_index, 0, "B", len(p.entries)),
                (f"{p.name} COB-ID", p.comm_index, 1, "I", cob),
            ]
        return steps

    def unused_pdos(self) -> list[Pdo]:
        """The drive's other PDOs (numbers up to :data:`PDOS_PER_DIRECTION`), to be disabled."""
        used = {(p.tpdo, p.number) for p in (*self.rpdos, *self.tpdos)}
        return [Pdo(t, n, ()) for t in (False, True) for n in range(1, PDOS_PER_DIRECTION + 1)
                if (t, n) not in used]

    def frames(self) -> tuple[list[tuple[int, float]], list[tuple[int, float]]]:
        """The traffic of one drive: ``(data bytes, frames per SYNC)`` of its SYNC-driven PDOs, and
        ``(data bytes, frames per second)`` of its event PDOs at their refresh rate (changes come on
        top; they are rare: state changes). The master sends the controlword RPDO of ``compact`` only
        on a change, so it counts as no load."""
        per_sync: list[tuple[int, float]] = []
        per_second: list[tuple[int, float]] = []
        for p in (*self.rpdos, *self.tpdos):
            if p.cyclic:
                per_sync.append((p.data_bytes, 1.0 / p.transmission))
            elif p.tpdo and p.event_timer_ms:
                per_second.append((p.data_bytes, 1000.0 / p.event_timer_ms))
        return per_sync, per_second


def make_layout(name: str = "standard", following_error_every: int = 1,
                status_refresh_ms: int = 100) -> PdoLayout:
    """The layout called ``name`` (:data:`LAYOUTS`), following error every n-th SYNC."""
    if not 1 <= following_error_every <= 240:
        raise ValueError(f"following_error_every must be 1 to 240 SYNCs (a CiA 301 transmission "
                         f"type), got {following_error_every}")
    fe = Pdo(True, 2, (FOLLOWING_ERROR,), following_error_every)
    # the limit and home switches: sent by the drive when they change (and on entering Operational);
    # no event timer, so no cyclic load: a switch changes a few times per move at most
    inputs = Pdo(True, 4, (DIGITAL_INPUTS,), EVENT)
    if name == "standard":
        return PdoLayout(name, (Pdo(False, 1, (TARGET_POSITION, CONTROLWORD)),),
                         (Pdo(True, 1, (STATUSWORD, POSITION_ACTUAL)), fe, inputs), following_error_every, 0)
    if name == "compact":
        if not 1 <= status_refresh_ms <= 65535:
            raise ValueError(f"status_refresh_ms must be 1 to 65535, got {status_refresh_ms}")
        return PdoLayout(name, (Pdo(False, 1, (TARGET_POSITION,)), Pdo(False, 2, (CONTROLWORD,), EVENT)),
                         (Pdo(True, 1, (POSITION_ACTUAL,)), fe,
                          Pdo(True, 3, (STATUSWORD,), EVENT, status_refresh_ms), inputs),
                         following_error_every, status_refresh_ms)
    raise ValueError(f"unknown PDO layout {name!r} (layouts: {', '.join(LAYOUTS)})")
