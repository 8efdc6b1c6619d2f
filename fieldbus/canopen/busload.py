"""The load a configuration puts on the CAN bus, computed before the master starts.

Each frame's length in bits counts the worst-case bit stuffing of a classic CAN frame with an 11-bit
identifier: 47 bits of frame overhead plus 8 per data byte, plus one stuff bit per four bits of the
34 + 8n stuffable bits. Per cycle: one SYNC, and per drive one RPDO (target, controlword: 6 bytes)
and two TPDOs (statusword and position actual: 6 bytes; following error: 4 bytes); heartbeats on top.
"""

from __future__ import annotations

from dataclasses import dataclass


def frame_bits(data_bytes: int) -> int:
    """Worst-case bits on the wire of a classic CAN frame with an 11-bit identifier."""
    if not 0 <= data_bytes <= 8:
        raise ValueError(f"a CAN frame holds 0 to 8 data bytes, not {data_bytes}")
    stuffable = 34 + 8 * data_bytes
    return 47 + 8 * data_bytes + (stuffable - 1) // 4


# data bytes of the frames the master sets up for each drive, every SYNC
RPDO_BYTES = (6,)
TPDO_BYTES = (6, 4)
SYNC_BYTES = 0
HEARTBEAT_BYTES = 1


@dataclass(frozen=True)
class BusLoad:
    frames_per_s: float
    bits_per_s: float
    bitrate: int

    @property
    def fraction(self) -> float:
        return self.bits_per_s / self.bitrate

    def describe(self) -> str:
        return (f"{self.frames_per_s:,.0f} frames/s, {self.bits_per_s / 1000:,.0f} kbit/s = "
                f"{100 * self.fraction:.1f} % of {self.bitrate / 1000:,.0f} kbit/s")


def bus_load(n_drives: int, cycle_s: float, bitrate: int, heartbeat_ms: int = 0,
             master_heartbeat_ms: int = 0) -> BusLoad:
    """Frames and bits per second of cyclic traffic for ``n_drives`` at ``cycle_s``."""
    per_cycle_frames = 1 + n_drives * (len(RPDO_BYTES) + len(TPDO_BYTES))
    per_cycle_bits = frame_bits(SYNC_BYTES) + n_drives * (
        sum(map(frame_bits, RPDO_BYTES)) + sum(map(frame_bits, TPDO_BYTES)))
    frames = per_cycle_frames / cycle_s
    bits = per_cycle_bits / cycle_s
    if heartbeat_ms > 0:
        frames += n_drives * 1000.0 / heartbeat_ms
        bits += n_drives * frame_bits(HEARTBEAT_BYTES) * 1000.0 / heartbeat_ms
    if master_heartbeat_ms > 0:
        frames += 1000.0 / master_heartbeat_ms
        bits += frame_bits(HEARTBEAT_BYTES) * 1000.0 / master_heartbeat_ms
    return BusLoad(frames, bits, bitrate)
