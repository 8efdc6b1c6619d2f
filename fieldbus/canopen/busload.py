"""The load a configuration puts on the CAN bus, computed before the master starts.

Each frame's length in bits counts the worst-case bit stuffing of a classic CAN frame with an 11-bit
identifier: 47 bits of frame overhead plus 8 per data byte, plus one stuff bit per four bits of the
34 + 8n stuffable bits. Per cycle: one SYNC and each drive's SYNC-driven PDOs of the PDO layout
(:mod:`fieldbus.canopen.pdo`); event PDOs at their refresh rate and heartbeats on top.
"""

from __future__ import annotations

from dataclasses import dataclass

from fieldbus.canopen.pdo import LAYOUTS, PdoLayout, make_layout


def frame_bits(data_bytes: int) -> int:
    """Worst-case bits on the wire of a classic CAN frame with an 11-bit identifier."""
    if not 0 <= data_bytes <= 8:
        raise ValueError(f"a CAN frame holds 0 to 8 data bytes, not {data_bytes}")
    stuffable = 34 + 8 * data_bytes
    return 47 + 8 * data_bytes + (stuffable - 1) // 4


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
             master_heartbeat_ms: int = 0, layout: PdoLayout | None = None) -> BusLoad:
    """Frames and bits per second of cyclic traffic for ``n_drives`` at ``cycle_s`` with ``layout``
    (default: the standard layout, following error every SYNC)."""
    per_sync, per_second = (layout or make_layout()).frames()
    frames = (1 + n_drives * sum(k for _, k in per_sync)) / cycle_s
    bits = (frame_bits(SYNC_BYTES) + n_drives * sum(frame_bits(b) * k for b, k in per_sync)) / cycle_s
    frames += n_drives * sum(r for _, r in per_second)
    bits += n_drives * sum(frame_bits(b) * r for b, r in per_second)
    if heartbeat_ms > 0:
        frames += n_drives * 1000.0 / heartbeat_ms
        bits += n_drives * frame_bits(HEARTBEAT_BYTES) * 1000.0 / heartbeat_ms
    if master_heartbeat_ms > 0:
        frames += 1000.0 / master_heartbeat_ms
        bits += frame_bits(HEARTBEAT_BYTES) * 1000.0 / master_heartbeat_ms
    return BusLoad(frames, bits, bitrate)


_EVERY = (1, 2, 3, 4, 5, 8, 10, 16, 20, 25, 50, 100, 240)


def fitting_layouts(n_drives: int, cycle_s: float, bitrate: int, limit: float, heartbeat_ms: int = 0,
                    master_heartbeat_ms: int = 0,
                    status_refresh_ms: int = 100) -> list[tuple[PdoLayout, BusLoad]]:
    """For each layout, the one with the fewest following-error PDOs that keeps ``n_drives`` at
    ``cycle_s`` under ``limit`` (layouts that cannot are left out), best first: following error most
    often, then the standard layout."""
    out = []
    for name in LAYOUTS:
        for every in _EVERY:
            layout = make_layout(name, every, status_refresh_ms)
            load = bus_load(n_drives, cycle_s, bitrate, heartbeat_ms, master_heartbeat_ms, layout)
            if load.fraction <= limit:
                out.append((layout, load))
                break
    return sorted(out, key=lambda f: f[0].following_error_every)


def alternatives(n_drives: int, cycle_s: float, bitrate: int, limit: float, heartbeat_ms: int = 0,
                 master_heartbeat_ms: int = 0, status_refresh_ms: int = 100) -> list[str]:
    """Settings that would fit ``n_drives`` under ``limit``: for each layout the fewest following-error
    PDOs needed at this cycle, and the shortest whole-millisecond cycle with following error every SYNC.
    For the refusal message: the user chooses, the master never silently drops traffic."""
    out = [f'pdo_layout = "{layout.name}" with following_error_every = {layout.following_error_every} '
           f"({100 * load.fraction:.1f} %)"
           for layout, load in sorted(fitting_layouts(n_drives, cycle_s, bitrate, limit, heartbeat_ms,
                                                      master_heartbeat_ms, status_refresh_ms),
                                      key=lambda f: LAYOUTS.index(f[0].name))]
    for name in LAYOUTS:
        layout = make_layout(name, 1, status_refresh_ms)
        for ms in range(max(1, int(cycle_s * 1000) + 1), 11):
            load = bus_load(n_drives, ms / 1000.0, bitrate, heartbeat_ms, master_heartbeat_ms, layout)
            if load.fraction <= limit:
                out.append(f'pdo_layout = "{name}" with cycle_ms = {ms} ({100 * load.fraction:.1f} %)')
                break
    return out
