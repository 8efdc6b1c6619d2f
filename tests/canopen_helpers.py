"""Shared set-up for the CANopen tests: configurations, a rig of simulated drives plus a master."""

from __future__ import annotations

import itertools
import os
import time
from collections.abc import Callable

from fieldbus.canopen.config import CanBusConfig, CanopenConfig, DriveConfig
from fieldbus.canopen.drive_sim import SimDrive
from fieldbus.canopen.localbus import LocalBus
from fieldbus.canopen.master import CanopenMaster
from fieldbus.canopen.sim_process import SimBus

_counter = itertools.count()
AXES = "xyzabc"


def unique_channel() -> str:
    return f"canon-test-{os.getpid()}-{next(_counter)}"


def make_config(n: int = 3, *, bus: CanBusConfig | None = None, cycle_s: float = 0.002,
                **overrides: object) -> CanopenConfig:
    drive_kw = {k: overrides.pop(k) for k in list(overrides) if k in DriveConfig.__dataclass_fields__}
    drives = tuple(DriveConfig(AXES[i], i + 1, **drive_kw) for i in range(n))  # type: ignore[arg-type]
    # a shared test machine stalls threads for tens of ms: a lost-TPDO fault only after 0.5 s here
    overrides.setdefault("feedback_timeout_s", 0.5)
    return CanopenConfig(bus or CanBusConfig("virtual", unique_channel()), drives, cycle_s=cycle_s,
                         **overrides)  # type: ignore[arg-type]


class Rig:
    """Simulated drives and a master on one virtual channel, in this process."""

    def __init__(self, config: CanopenConfig, sims: list[SimDrive] | None = None, **master_kw: object):
        self.config = config
        self.sims = SimBus(sims if sims is not None else [SimDrive(d.node_id) for d in config.drives],
                           config.bus)
        self.master = CanopenMaster(config, **master_kw)  # type: ignore[arg-type]

    def sim(self, node_id: int) -> SimDrive:
        return self.sims[node_id]

    def up(self) -> Rig:
        self.master.boot()
        self.master.enable()
        return self

    def run(self, cycles: int, positions: Callable[[int], list[float]] | None = None) -> None:
        """``cycles`` cycles on absolute deadlines, from the calling thread (bounded)."""
        period = self.config.cycle_s
        t = time.monotonic()
        for k in range(cycles):
            self.master.cycle(positions(k) if positions else None)
            t += period
            delay = t - time.monotonic()
            if delay > 0:
                time.sleep(delay)

    def close(self) -> None:
        try:
            self.master.shutdown()
        finally:
            self.sims.close()


def wait_for(predicate: Callable[[], bool], timeout: float = 5.0, step: float = 0.005) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(step)
    return predicate()


SYNC_COB_ID = 0x80


class LocalListener:
    """Every frame on a canon_local channel, with the sender's time stamp (canon_local carries it)."""

    def __init__(self, channel: str) -> None:
        self.bus = LocalBus(channel=channel)
        self.frames: list[tuple[float, int]] = []
        self.payloads: list[tuple[float, int, bytes]] = []  # the same frames with their data

    def drain(self, quiet_s: float = 0.2) -> None:
        """Read what was sent until now: until a frame sent after the call, or nothing for ``quiet_s``
        (bounded: 100,000 frames)."""
        now = time.time()
        for _ in range(100_000):
            msg = self.bus.recv(quiet_s)
            if msg is None:
                return
            self.frames.append((msg.timestamp, msg.arbitration_id))
            self.payloads.append((msg.timestamp, msg.arbitration_id, bytes(msg.data)))
            if msg.timestamp > now:
                return

    def syncs(self, t0: float = 0.0, t1: float = float("inf")) -> list[float]:
        return [t for t, cob in self.frames if cob == SYNC_COB_ID and t0 <= t <= t1]

    def close(self) -> None:
        self.bus.shutdown()
