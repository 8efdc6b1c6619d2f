"""The simulated drive homes as its homing method (0x6098) says: direction, and the switch or index pulse
it stops at; the switches keep their physical place when the count is re-based on the home offset."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator

import pytest
from canopen_helpers import Rig, make_config

from fieldbus.canopen.clock import PeriodicRunner
from fieldbus.canopen.drive_sim import SimDrive

NEG, POS, HOME = -30_000, 60_000, 20_000  # counts: negative and positive limit switches, home switch


@contextlib.contextmanager
def cycling(r: Rig) -> Iterator[None]:
    """The master's cycle on its own thread for the body (at most 10 s), then stopped and joined; no
    fault standing afterwards."""
    runner = PeriodicRunner(r.config.cycle_s, lambda k, t: r.master.cycle(None), cycles=5000,
                            late_s=1.0).start()
    try:
        yield
    finally:
        runner.stop()
        assert runner.join(5.0)
    assert r.master.fault is None, r.master.fault


def home(method: int, **sim_kw: int) -> tuple[SimDrive, float, float]:
    """Home axis x with ``method`` from count 0; the drive, and the lowest and highest count it
    travelled through while homing (in its counts before homing)."""
    sim = SimDrive(1, negative_limit_counts=NEG, positive_limit_counts=POS, home_switch_counts=HOME,
                   **sim_kw)  # type: ignore[arg-type]
    seen = [0.0, 0.0]
    step = sim._homing_step

    def watched(dt: float) -> None:
        step(dt)
        if sim._homing:
            seen[0], seen[1] = min(seen[0], sim.actual), max(seen[1], sim.actual)

    sim._homing_step = watched  # type: ignore[method-assign]
    # 1 mm = 10000 counts; the EDS's 100000 counts/s: at most 1.2 s of travel in these tests
    r = Rig(make_config(1, homing="cia402", homing_method=method), [sim])
    try:
        r.up()
        with cycling(r):
            assert r.master.home("x") == pytest.approx(0.0)
    finally:
        r.close()
    return sim, seen[0], seen[1]


@pytest.mark.parametrize(("method", "switch"), [(17, NEG), (18, POS)])
def test_homing_on_a_limit_switch_travels_toward_it_and_stops_on_its_edge(method: int, switch: int) -> None:
    sim, lowest, highest = home(method)
    # the count is now 0 at the switch: both switches moved by the same amount, the span kept
    assert (sim.negative_limit_counts, sim.positive_limit_counts) == (NEG - switch, POS - switch)
    if method == 17:
        assert highest == 0.0 and lowest > NEG - 1  # straight down to the negative switch
    else:
        assert lowest == 0.0 and highest < POS + 1  # straight up to the positive switch


def test_home_switch_methods_start_in_their_direction_and_reverse_on_the_limit_switch() -> None:
    sim, lowest, highest = home(23)  # home switch, positive limit switch: first direction positive
    assert lowest == 0.0 and highest < HOME + 1
    assert sim.home_switch_counts == 0 and sim.negative_limit_counts == NEG - HOME
    sim, lowest, highest = home(27)  # with the negative limit switch: first negative, reversed there
    assert lowest == pytest.approx(NEG) and highest < HOME + 1
    assert sim.home_switch_counts == 0 and sim.positive_limit_counts == POS - HOME


def test_index_pulse_methods_go_to_the_next_pulse_in_their_direction() -> None:
    # 0x608F: 50000 counts per revolution, an index pulse at every multiple; start at 0, on one
    sim, lowest, highest = home(33)
    assert lowest > -50_001 and highest == 0.0 and sim.negative_limit_counts == NEG + 50_000
    sim, lowest, highest = home(34)
    assert highest < 50_001 and lowest == 0.0 and sim.positive_limit_counts == POS - 50_000


def test_an_unsupported_method_is_a_homing_error() -> None:
    from fieldbus.canopen.master import CanopenError

    with pytest.raises(CanopenError, match=r"homing error .*method 36"):
        home(36)


def test_homing_onto_a_limit_switch_is_no_fault_when_no_cycle_check_saw_the_drive_arrive() -> None:
    """A busy PC: the cycle's checks did not run between the drive's arrival on the switch it homes on
    and the homing's end. The switch, active where homing ended, is armed (read from the drive), not
    taken for one that became active while the axis is driven."""
    sim = SimDrive(1, negative_limit_counts=NEG, positive_limit_counts=POS, home_switch_counts=HOME)
    r = Rig(make_config(1, homing="cia402", homing_method=17), [sim])
    try:
        r.up()
        check = r.master._check
        checks_after = []

        def held_off_while_homing(now: float, active: list) -> None:
            if any(d.homing for d in r.master.drives):
                return  # the cycle came too late to see the drive on its switch while homing
            checks_after.append(now)
            check(now, active)

        r.master._check = held_off_while_homing  # type: ignore[method-assign]
        with cycling(r):
            assert r.master.home("x") == pytest.approx(0.0)
            t0 = len(checks_after)
            deadline = time.monotonic() + 5.0
            while len(checks_after) < t0 + 20 and time.monotonic() < deadline:
                time.sleep(0.01)  # the checks after homing, with the switch active in the TPDOs
        assert len(checks_after) >= t0 + 20
        assert sim.digital_inputs() & 1  # still on the negative limit switch's edge
        assert r.master.fault is None, r.master.fault
    finally:
        r.close()


def test_an_interrupted_homing_ramps_down_and_then_shows_bit_10() -> None:
    """CiA 402's homing statusword (bits 13, 12, 10): 0 0 1 before the start, 0 0 0 while homing; after
    the start bit went 1 -> 0 the drive ramps down at 0x609A, then shows 0 0 1 (interrupted)."""
    from fieldbus.canopen import cia402

    sim = SimDrive(1, home_switch_counts=10**8)  # never reached
    r = Rig(make_config(1, homing="cia402", homing_method=19), [sim])
    try:
        r.up()
        d = r.master.drives[0]
        bits = cia402.SW_BIT13 | cia402.SW_BIT12 | cia402.SW_TARGET_REACHED
        with cycling(r):
            with r.master._lock:
                d.homing = True
            r.master._sdo(d, "homing method", 0x6098, 0, "b", 19)
            r.master._set_mode(d, cia402.MODE_HOMING)
            assert r.master._statusword(d) & bits == cia402.SW_TARGET_REACHED  # not started
            r.master._sdo(d, "cw", 0x6040, 0, "H", cia402.CW_ENABLE_OPERATION | cia402.CW_HOMING_START)
            time.sleep(0.2)
            assert r.master._statusword(d) & bits == 0  # homing
            at_stop: list[float] = []
            controlword = sim._controlword

            def noted(cw: int) -> None:
                at_stop.append(sim.actual)
                controlword(cw)

            sim._controlword = noted  # type: ignore[method-assign]
            r.master._sdo(d, "cw", 0x6040, 0, "H", cia402.CW_ENABLE_OPERATION)
            deadline = time.monotonic() + 2.0
            while not r.master._statusword(d) & cia402.SW_TARGET_REACHED and time.monotonic() < deadline:
                time.sleep(0.005)
            assert r.master._statusword(d) & bits == cia402.SW_TARGET_REACHED
            # 100000 counts/s ramped down at 1e6 counts/s^2: v^2 / 2a = 5000 counts (not an instant stop)
            assert sim.actual - at_stop[0] == pytest.approx(5000, abs=150)
            r.master._back_to_csp(d)
    finally:
        r.close()
