"""Engineering values <-> Modbus registers: int16, uint16, float32 (two registers, either word order),
with scale and offset (see :class:`fieldbus.modbus.config.Conversion`).

Out-of-range values are an error, never a silent clamp: an analog output drives something physical
(laser power, a valve, a spindle reference), and sending the limit instead of what the program asked
is a wrong machine state nobody sees. :class:`CodecError` says what was asked and what fits; the
executor reports it before anything is written. Integers are rounded half away from zero (2.5 -> 3,
-2.5 -> -3), the way a person rounds, not Python's half-to-even. Non-finite values (NaN, inf) are
refused on the way out; on the way in, a float32 register pair holding NaN or inf is passed through,
since that is what the device said.

The byte and word layout itself is pymodbus's ``convert_to_registers``/``convert_from_registers``.
"""

from __future__ import annotations

import math

from pymodbus.client import AsyncModbusTcpClient

from fieldbus.modbus.config import Conversion, ValueType

_DT = AsyncModbusTcpClient.DATATYPE
_DATATYPE = {ValueType.INT16: _DT.INT16, ValueType.UINT16: _DT.UINT16, ValueType.FLOAT32: _DT.FLOAT32}
_INT_RANGE = {ValueType.INT16: (-32768, 32767), ValueType.UINT16: (0, 65535)}
FLOAT32_MAX = 3.4028234663852886e38


class CodecError(ValueError):
    """A value that cannot be represented in the configured register type."""


def round_half_away(x: float) -> int:
    """Round to the nearest integer, halves away from zero."""
    return math.floor(abs(x) + 0.5) * (1 if x >= 0 else -1)


def encode(value: float, conv: Conversion) -> list[int]:
    """Registers (0..65535 each) for engineering ``value``; :class:`CodecError` if it does not fit."""
    if not math.isfinite(value):
        raise CodecError(f"{value!r} is not a finite number")
    raw = value * conv.scale + conv.offset
    if not math.isfinite(raw):
        raise CodecError(f"{value!r} scaled by {conv.scale} is not a finite number")
    if conv.type is ValueType.FLOAT32:
        if abs(raw) > FLOAT32_MAX:
            raise CodecError(f"{value!r} gives {raw!r}, outside the float32 range +-{FLOAT32_MAX:.7g}")
        number: int | float = float(raw)
    else:
        lo, hi = _INT_RANGE[conv.type]
        number = round_half_away(raw)
        if not lo <= number <= hi:
            raise CodecError(
                f"{value!r} gives register value {number}, outside the {conv.type.value} range {lo}..{hi}"
            )
    return AsyncModbusTcpClient.convert_to_registers(
        number, _DATATYPE[conv.type], word_order=conv.word_order.value
    )


def decode(registers: list[int] | tuple[int, ...], conv: Conversion) -> float:
    """Engineering value of an input from the registers read (as many as the type takes)."""
    return _raw(registers, conv) * conv.scale + conv.offset


def decode_output(registers: list[int] | tuple[int, ...], conv: Conversion) -> float:
    """Engineering value an output's registers stand for: the inverse of :func:`encode`."""
    return (_raw(registers, conv) - conv.offset) / conv.scale


def _raw(registers: list[int] | tuple[int, ...], conv: Conversion) -> float:
    if len(registers) != conv.type.registers:
        raise CodecError(f"{conv.type.value} takes {conv.type.registers} register(s), got {len(registers)}")
    raw = AsyncModbusTcpClient.convert_from_registers(
        list(registers), _DATATYPE[conv.type], word_order=conv.word_order.value
    )
    assert isinstance(raw, int | float)
    return float(raw)
