"""Names and meanings of CANopen frames by COB-ID, for watching the bus (``canon can-dump``).

Decodes the predefined connection set (NMT, SYNC, EMCY, PDOs, SDO, heartbeat) and, for the PDO layout
the master sets up (:mod:`fieldbus.canopen.pdo`), the values: target and controlword, statusword (with
the CiA 402 state), position actual, following error.
"""

from __future__ import annotations

import struct

from fieldbus.canopen import cia402
from fieldbus.canopen.nmt_names import NMT_COMMANDS, NMT_STATES
from fieldbus.canopen.pdo import PdoLayout, make_layout

_OBJECT_NAMES = {0x607A: "target", 0x6040: "controlword", 0x6041: "statusword", 0x6064: "position",
                 0x60F4: "following error", 0x60FD: "digital inputs"}


def _pdo_values(layout: PdoLayout, fn: int, data: bytes) -> str:
    for p in (*layout.rpdos, *layout.tpdos):
        if p.cob_id(0) != fn or p.data_bytes != len(data):
            continue
        parts = []
        for index, value in zip(p.objects, p.struct.unpack_from(data), strict=True):
            if index == 0x6041:
                parts.append(f"statusword 0x{value:04X} ({cia402.decode(value)})")
            elif index == 0x6040:
                parts.append(f"controlword 0x{value:04X}")
            else:
                parts.append(f"{_OBJECT_NAMES.get(index, f'0x{index:04X}')} {value}")
        return ", ".join(parts)
    return ""


def name_of(cob_id: int) -> str:
    """``SYNC``, ``TPDO1 node 3``, ``SDO request node 5`` ..."""
    if cob_id == 0x000:
        return "NMT"
    if cob_id == 0x080:
        return "SYNC"
    if cob_id == 0x100:
        return "TIME"
    fn, node = cob_id & 0x780, cob_id & 0x7F
    names = {0x080: "EMCY", 0x180: "TPDO1", 0x200: "RPDO1", 0x280: "TPDO2", 0x300: "RPDO2",
             0x380: "TPDO3", 0x400: "RPDO3", 0x480: "TPDO4", 0x500: "RPDO4", 0x580: "SDO response",
             0x600: "SDO request", 0x700: "heartbeat"}
    if fn in names and node:
        return f"{names[fn]} node {node}"
    return f"0x{cob_id:03X}"


def describe(cob_id: int, data: bytes, layout: PdoLayout | None = None) -> str:
    """One line: the frame's name and what its data means (as far as it is known); PDOs decoded as
    ``layout`` maps them (default: the standard layout)."""
    name = name_of(cob_id)
    fn = cob_id & 0x780
    meaning = ""
    try:
        if cob_id == 0 and len(data) >= 2:
            target = f"node {data[1]}" if data[1] else "all nodes"
            meaning = f"{NMT_COMMANDS.get(data[0], f'command 0x{data[0]:02X}')} -> {target}"
        elif fn == 0x700 and cob_id != 0x700 and data:
            meaning = "boot-up" if data[0] == 0 else NMT_STATES.get(data[0] & 0x7F, f"state {data[0]}")
        elif fn == 0x080 and cob_id != 0x80 and len(data) >= 3:
            code, reg = struct.unpack_from("<HB", data)
            meaning = "error reset" if code == 0 else f"error 0x{code:04X}, register 0x{reg:02X}"
        elif 0x180 <= fn <= 0x500 and cob_id & 0x7F:
            meaning = _pdo_values(layout or make_layout(), fn, data)
        elif fn in (0x580, 0x600) and len(data) >= 4:
            index, sub = struct.unpack_from("<HB", data, 1)
            kind = {0x2: "read", 0x1: "write", 0x4: "abort"}.get(data[0] >> 5, "")
            if fn == 0x580:
                kind = {0x2: "read reply", 0x3: "write ok", 0x4: "abort"}.get(data[0] >> 5, "")
            meaning = f"{kind} 0x{index:04X}:{sub:02X}"
            if data[0] >> 5 == 4 and len(data) >= 8:
                meaning += f" code 0x{struct.unpack_from('<I', data, 4)[0]:08X}"
    except (struct.error, IndexError):
        meaning = ""
    return f"{name:<18} {data.hex(' '):<24} {meaning}".rstrip()
