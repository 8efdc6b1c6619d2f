"""The drive's CiA 402 touch probe (0x60B8-0x60BD): the simulated drive latches at its trip point inside
the cycle, the master arms it, sees the trip in TPDO4 and reads the latched position."""

from __future__ import annotations

import pytest
from canopen_helpers import Rig, make_config, wait_for

from fieldbus.canopen.drive_sim import SimDrive
from fieldbus.canopen.master import CanopenError
from fieldbus.canopen.touch_probe import TouchProbe

TRIP = -12_345  # counts: -1.2345 mm at 10000 counts/mm
STEP = 0.0137  # mm per cycle: the trip falls inside a cycle, 137 counts of travel each


def probe_rig(**sim_kw: object) -> Rig:
    config = make_config(1, touch_probe=1)
    return Rig(config, [SimDrive(1, probe_trip_counts=TRIP, **sim_kw)])  # type: ignore[arg-type]


def test_the_probe_latches_the_trip_point_not_the_cycle() -> None:
    r = probe_rig()
    try:
        r.up()
        tp = TouchProbe.of(r.master)
        assert tp is not None and tp.axis == "x"
        tp.arm(toward=True)
        assert not tp.tripped
        seen: list[int] = []

        def down(k: int) -> list[float]:
            if tp.tripped and not seen:
                seen.append(k)
            return [-STEP * min(k, 200)]

        r.run(220, down)
        assert seen, "the trip never reached the master in TPDO4"
        result = tp.result()
        assert result.tripped
        assert abs(result.counts - TRIP) <= 1  # the drive's latch: one count, not a cycle's 137
        assert result.position == pytest.approx(TRIP / 10000.0, abs=1e-4)
        assert r.sim(1)._value(0x60B8) == 0  # disarmed after reading
        # armed for the negative edge (contact lost), moving further into contact: no latch
        tp.arm(toward=False)
        r.run(20, lambda k: [-STEP * (200 + k)])
        assert not tp.tripped and not tp.result().tripped
    finally:
        r.close()


def test_first_event_only_and_rearming_clears() -> None:
    r = probe_rig()
    try:
        r.up()
        tp = TouchProbe.of(r.master)
        assert tp is not None
        tp.arm(toward=True)
        # into contact and out; then the surface is higher and the probe goes in again: the first
        # edge is the one kept
        path = [-0.02 * k for k in range(80)] + [-1.6 + 0.02 * k for k in range(81)]
        r.run(len(path), lambda k: [path[k]])
        with r.sim(1).lock:
            r.sim(1).probe_trip_counts = TRIP // 2
        r.run(100, lambda k: [-0.01 * k])
        assert wait_for(lambda: tp.tripped, 1.0)
        first = tp.result()
        assert first.tripped and abs(first.counts - TRIP) <= 1
        tp.arm(toward=True)  # re-armed: the stored edge is cleared
        assert not tp.tripped and not tp.result().tripped
    finally:
        r.close()


def test_a_drive_without_touch_probe_objects_is_refused_naming_node_and_object() -> None:
    r = probe_rig(absent_objects={0x60B9})
    try:
        with pytest.raises(CanopenError, match=r"node 1 \(axis x\).*touch_probe = 1.*0x60B9 \(touch probe "
                                               r"status"):
            r.master.boot()
    finally:
        r.close()
