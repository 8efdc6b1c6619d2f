"""fieldbus.modbus.codec: register layouts, scale/offset, and what happens at the edges."""

from __future__ import annotations

import math
import struct

import pytest

from fieldbus.modbus.codec import FLOAT32_MAX, CodecError, decode, decode_output, encode, round_half_away
from fieldbus.modbus.config import Conversion, ValueType, WordOrder

I16 = Conversion(ValueType.INT16)
U16 = Conversion(ValueType.UINT16)
F32 = Conversion(ValueType.FLOAT32)
F32_LITTLE = Conversion(ValueType.FLOAT32, WordOrder.LITTLE)


def f32_words(x: float) -> list[int]:
    """Independent reference: IEEE single, big-endian bytes, high word first."""
    b = struct.pack(">f", x)
    return [b[0] << 8 | b[1], b[2] << 8 | b[3]]


@pytest.mark.parametrize(("value", "regs"), [(0, [0]), (1, [1]), (-1, [0xFFFF]), (32767, [0x7FFF]),
                                             (-32768, [0x8000]), (-2, [0xFFFE])])
def test_int16_two_complement(value: int, regs: list[int]) -> None:
    assert encode(value, I16) == regs
    assert decode(regs, I16) == value


@pytest.mark.parametrize("value", [32768, -32769, 40000.0, 1e9])
def test_int16_out_of_range_is_an_error(value: float) -> None:
    with pytest.raises(CodecError, match=r"int16 range -32768\.\.32767"):
        encode(value, I16)


@pytest.mark.parametrize(("value", "regs"), [(0, [0]), (65535, [0xFFFF]), (32768, [0x8000])])
def test_uint16(value: int, regs: list[int]) -> None:
    assert encode(value, U16) == regs
    assert decode(regs, U16) == value


@pytest.mark.parametrize("value", [-1, 65536, -0.6, 65535.5])
def test_uint16_out_of_range_is_an_error(value: float) -> None:
    with pytest.raises(CodecError, match=r"uint16 range 0\.\.65535"):
        encode(value, U16)


def test_every_register_value_round_trips() -> None:
    for raw in range(65536):
        assert encode(decode([raw], U16), U16) == [raw]
        assert encode(decode([raw], I16), I16) == [raw]
        assert decode([raw], I16) == (raw - 65536 if raw >= 32768 else raw)


@pytest.mark.parametrize(("x", "n"), [(2.5, 3), (-2.5, -3), (0.5, 1), (-0.5, -1), (0.4999, 0), (-0.4999, 0),
                                      (1.5, 2), (2.4999, 2), (-1.5, -2)])
def test_rounding_is_half_away_from_zero(x: float, n: int) -> None:
    assert round_half_away(x) == n


def test_rounding_edges_at_the_range_limit() -> None:
    assert encode(32767.49, I16) == [0x7FFF]
    with pytest.raises(CodecError):
        encode(32767.5, I16)  # rounds to 32768
    assert encode(-32768.49, I16) == [0x8000]
    with pytest.raises(CodecError):
        encode(-32768.5, I16)
    assert encode(-0.49, U16) == [0]


def test_scale_and_offset_in_both_directions() -> None:
    out = Conversion(ValueType.INT16, scale=100.0, offset=10.0)
    assert encode(1.5, out) == [160]  # 1.5 * 100 + 10
    assert encode(-1.23, out) == [(-113) & 0xFFFF]
    inp = Conversion(ValueType.INT16, scale=0.01, offset=-1.0)
    assert decode([160], inp) == pytest.approx(0.6)  # 160 * 0.01 - 1
    assert decode([0xFFFF], inp) == pytest.approx(-1.01)
    assert decode_output([160], out) == 1.5  # what an output's registers stand for
    assert decode_output([(-113) & 0xFFFF], out) == pytest.approx(-1.23)
    # out of range is judged after scaling
    with pytest.raises(CodecError, match="gives register value 40010"):
        encode(400.0, out)


@pytest.mark.parametrize("x", [0.0, 1.5, -1.5, 3.25, 1e-3, 123456.789, -FLOAT32_MAX, FLOAT32_MAX, 1e-45])
def test_float32_word_orders(x: float) -> None:
    hi_lo = f32_words(x)
    assert encode(x, F32) == hi_lo
    assert encode(x, F32_LITTLE) == hi_lo[::-1]
    expect = struct.unpack(">f", struct.pack(">f", x))[0]
    assert decode(hi_lo, F32) == expect
    assert decode(hi_lo[::-1], F32_LITTLE) == expect


def test_float32_scale() -> None:
    c = Conversion(ValueType.FLOAT32, scale=2.0, offset=1.0)
    assert encode(1.25, c) == f32_words(3.5)
    assert decode(f32_words(3.5), c) == 8.0


@pytest.mark.parametrize("x", [3.5e38, -3.5e38, 1e300])
def test_float32_overflow_is_an_error(x: float) -> None:
    with pytest.raises(CodecError, match="float32 range"):
        encode(x, F32)


@pytest.mark.parametrize("conv", [I16, U16, F32])
@pytest.mark.parametrize("x", [math.nan, math.inf, -math.inf])
def test_non_finite_values_are_refused(conv: Conversion, x: float) -> None:
    with pytest.raises(CodecError, match="not a finite number"):
        encode(x, conv)


def test_scale_overflowing_to_infinity_is_refused() -> None:
    with pytest.raises(CodecError, match="not a finite number"):
        encode(1e308, Conversion(ValueType.FLOAT32, scale=1e10))


def test_non_finite_float_from_the_device_passes_through() -> None:
    assert math.isnan(decode(f32_words(math.nan), F32))
    assert decode([0x7F80, 0], F32) == math.inf


def test_wrong_register_count() -> None:
    with pytest.raises(CodecError, match="float32 takes 2 register"):
        decode([1], F32)
    with pytest.raises(CodecError, match="int16 takes 1 register"):
        decode([1, 2], I16)
