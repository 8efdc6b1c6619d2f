"""Names and meanings of CANopen frames by COB-ID, for watching the bus (``canon can-dump``).

Decodes the predefined connection set (NMT, SYNC, EMCY, PDOs, SDO, heartbeat) and, for the PDO layout
the master sets up, the values: target and controlword, statusword (with the CiA 402 state), position
actual, following error.
"""

from __future__ import annotations

import struct

from fieldbus.canopen import cia402
from fieldbus.canopen.nmt_names import NMT_COMMANDS, NMT_STATES


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


def describe(cob_id: int, data: bytes) -> str:
    """One line: the frame's name and what its data means (as far as it is known)."""
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
        elif fn == 0x200 and len(data) == 6:
            target, cw = struct.unpack_from("<iH", data)
            meaning = f"target {target}, controlword 0x{cw:04X}"
        elif fn == 0x180 and len(data) == 6:
            sw, pos = struct.unpack_from("<Hi", data)
            meaning = f"statusword 0x{sw:04X} ({cia402.decode(sw)}), position {pos}"
        elif fn == 0x280 and len(data) == 4:
            meaning = f"following error {struct.unpack_from('<i', data)[0]}"
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
