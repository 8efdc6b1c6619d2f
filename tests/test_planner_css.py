"""G96 constant surface speed on the planner's side (planner/css.py): the S number is a surface speed,
so the speeds the setpoints carry are rpm computed from the commanded X radius, at most D."""

from __future__ import annotations

import itertools
import math
import statistics
from collections.abc import Callable, Iterator

import pytest

from gcode_canon.commands import SetSpindleSpeed, SpindleOn
from planner import DEMO_MACHINE, Planner, Setpoint, plan_all
from planner.css import CSS_MIN_INTERVAL_S, CSS_STEP, css_rpm
from planner.segments import PlannerError
from tests.test_interp_helpers import run as interpret

FACE = "G21 G90 G18\nG0 X40 Z1\nG96 D1500 S100 M3\nG1 X5 Z0 F300\nG97 S600\nG1 X10\nM5\n"


Followed = tuple[tuple[float, ...], Setpoint, float, float, str]


def speeds(text: str) -> list[tuple[float, float, float]]:
    """(t, commanded X, rpm) of every speed a setpoint carries (M3's and the S events)."""
    out = []
    for sp in plan_all(interpret(text), DEMO_MACHINE, max_cycles=2_000_000):
        for ev in sp.events:
            if isinstance(ev, SetSpindleSpeed | SpindleOn):
                out.append((sp.t, sp.positions[0], ev.rpm))
    return out


def test_css_rpm_is_surface_over_circumference_capped_at_d() -> None:
    assert css_rpm(100_000.0, 20.0, 5000.0) == pytest.approx(100_000.0 / (2 * math.pi * 20.0))
    assert css_rpm(100_000.0, 1.0, 1500.0) == 1500.0
    assert css_rpm(100_000.0, 0.0, 1500.0) == 1500.0


def test_facing_in_g96_speeds_the_spindle_up_as_the_radius_shrinks_then_g97_gives_its_rpm() -> None:
    got = speeds(FACE)
    surface = 100 * 1000.0  # S100 m/min in G21, mm/min
    css = [s for s in got if s[2] != 600.0]
    assert css[0][2] == pytest.approx(css_rpm(surface, 40.0, 1500.0), rel=1e-9)  # M3 at X40
    # every speed sent under G96 is the rpm of the X it was sent at, never the surface number 100
    for _t, x, rpm in css:
        assert rpm == pytest.approx(css_rpm(surface, x, 1500.0), rel=1e-9)
        assert rpm != 100.0
    rpms = [s[2] for s in css]
    assert rpms == sorted(rpms)  # X only shrinks: the speed only rises
    assert max(rpms) == 1500.0  # at X5 the surface speed asks 3183 rpm: D caps it
    assert len(css) > 5  # followed along the move, not set once
    # not a flood: a new speed only after CSS_STEP of change and CSS_MIN_INTERVAL_S
    for (t0, _x0, r0), (t1, _x1, r1) in itertools.pairwise(css[1:]):
        assert t1 - t0 >= CSS_MIN_INTERVAL_S - 1e-9 and (abs(r1 - r0) > CSS_STEP * r0 * 0.999 or r1 == 1500.0)
    assert got[-1][2] == 600.0  # G97 S600: rpm again


def test_a_rigid_tap_under_g96_is_refused_naming_the_line() -> None:
    with pytest.raises(PlannerError) as err:
        list(plan_all(interpret("G21 G18\nG0 X0\nG96 D1000 S100 M3\nG33.1 Z-5 K1\n"), DEMO_MACHINE,
                      max_cycles=200_000))
    assert err.value.line == 4 and "G96" in str(err.value) and "G33.1" in str(err.value)


def test_g33_under_g96_cuts_at_the_pitch_times_the_g96_rpm_where_it_cuts() -> None:
    """As LinuxCNC: under G96 the spindle turns at the rpm of the commanded X and the thread follows it
    (without the spindle's position: at the rpm it is commanded to, S60 m/min at X20: 477 rpm)."""
    sps = list(plan_all(interpret("G21 G90 G18\nG0 X20 Z1\nG96 D1500 S60 M3\nG33 Z-20 K1.5\nM5\n"),
                        DEMO_MACHINE, max_cycles=2_000_000))
    T = DEMO_MACHINE.cycle_s
    vz = [abs(b.positions[2] - a.positions[2]) / T for a, b in itertools.pairwise(sps) if b.line == 4]
    assert max(vz) == pytest.approx(1.5 * css_rpm(60_000.0, 20.0, 1500.0) / 60.0, rel=1e-6)


def test_a_followed_thread_under_g96_without_d_is_refused_naming_the_line() -> None:
    """Followed on the spindle's position a thread under G96 is planned at D: without D it cannot be."""
    p = Planner(DEMO_MACHINE)
    p.follow_taps = True
    with pytest.raises(PlannerError) as err:
        p.feed_many(interpret("G21 G90 G18\nG0 X20 Z1\nG96 S60 M3\nG33 Z-20 K1.5\nM5\n"))
        p.flush()
    assert err.value.line == 4 and "D word" in str(err.value)


def follow(p: Planner, spindle_rpm: Callable[[float], float], cycles: int) -> Iterator[Followed]:
    """Run planner ``p`` (``follow_taps``) on a spindle turning ``spindle_rpm(X of the last setpoint)``
    each cycle, sync points released at once: per setpoint (the position before it, the setpoint, the
    revolutions turned in its cycle, the revolutions in all, what ``follow_spindle`` returned)."""
    revs, x = 0.0, p.position[0]
    for _ in range(cycles):
        turned = spindle_rpm(x) / 60 * p.T
        revs += turned
        why = p.follow_spindle(revs)
        before = p.position
        sp = p.next_setpoint()
        if p.waiting_for is not None:
            p.release()
        if sp is None:
            return
        x = sp.positions[0]
        yield before, sp, turned, revs, why


def per_rev(text: str, line: int, surface: float, d: float) -> list[float]:
    """Feed per revolution (mm) of every cycle of ``line``: the path's travel over the G96 rpm of where
    the axes are (what a spindle turning at the speed G96 commands turns in that cycle)."""
    sps = list(plan_all(interpret(text), DEMO_MACHINE, max_cycles=2_000_000))
    T = DEMO_MACHINE.cycle_s
    return [math.dist(a.positions, b.positions) / (css_rpm(surface, b.positions[0], d) / 60.0 * T)
            for a, b in itertools.pairwise(sps) if a.line == line and b.line == line]


def test_g95_under_g96_feeds_f_per_revolution_as_the_rpm_rises_toward_the_centre() -> None:
    """Facing from X40 to X5 under G96 S100 D1500 with G95 F0.2 (the usual lathe pairing, as LinuxCNC
    runs it): the feed rises with the rpm toward the centre, every revolution advancing 0.2 mm (never
    more; a little less where the line's pieces change speed), up to D's 1500 rpm (5 mm/s)."""
    text = "G21 G90 G18\nG0 X40 Z1\nG96 D1500 S100 M3\nG95 G1 X5 Z0 F0.2\nM5\n"
    got = per_rev(text, 4, 100_000.0, 1500.0)
    assert len(got) > 1000
    assert max(got) <= 0.2 * (1 + 1e-6)
    assert sum(f >= 0.2 * 0.96 for f in got) / len(got) >= 0.95
    assert statistics.median(got) == pytest.approx(0.2, rel=0.02)


def test_g95_arc_under_g96_is_planned_at_its_lowest_rpm() -> None:
    """An arc under G96 with G95 runs at F times the lowest rpm along it: never more than F per
    revolution."""
    text = "G21 G90 G18\nG0 X20 Z0\nG96 D1500 S100 M3\nG95 G3 X10 Z-5 R8 F0.1\nM5\n"
    got = per_rev(text, 4, 100_000.0, 1500.0)
    assert len(got) > 100
    assert max(got) <= 0.1 * (1 + 1e-6) and statistics.median(got) > 0.05


def test_a_followed_thread_under_g96_keeps_its_pitch_when_d_is_beyond_the_axes() -> None:
    """Planned at D where D times the pitch is beyond Z's max_velocity, the axis's cap would shorten the
    pitch on the spindle's clock: it is planned at the rpm the axis allows instead, and each revolution
    still advances the pitch."""
    p = Planner(DEMO_MACHINE)
    p.follow_taps = True
    pitch = 4.0
    assert pitch * 5000 / 60 > DEMO_MACHINE.axes[2].max_velocity
    p.feed_many(interpret(f"G21 G90 G18\nG0 X20 Z1\nG96 D5000 S60 M3\nG33 Z-60 K{pitch}\nM5\n"))
    p.flush()
    steps = [before[2] - sp.positions[2] for before, sp, *_ in follow(p, lambda x: 300.0, 200_000)
             if sp.line == 4]
    cruise = [s for s in steps if s > 0.99 * max(steps)]
    assert len(cruise) > 100
    assert statistics.median(cruise) == pytest.approx(pitch * 300 / 60 * p.T, rel=1e-6)


def test_followed_g76_under_g96_cuts_every_pass_in_the_same_groove_at_its_own_rpm() -> None:
    """G76 under G96 followed on a spindle that turns at the G96 rpm of the commanded X (lagging it at
    1500 rpm/s): each pass has its own rpm, and all are cut in the same groove (Z + pitch x revolutions
    the same in every pass's cruise)."""
    p = Planner(DEMO_MACHINE)
    p.follow_taps = True
    pitch, T = 2.0, DEMO_MACHINE.cycle_s
    p.feed_many(interpret(f"G21 G18 G90 G8\nG0 X12 Z5\nG96 D1500 S30 M3\nG76 P{pitch} Z-25 I-2 J0.4 K1.2 "
                          "R1.5 H1\nG0 X20 Z5\nM5\n"))
    p.flush()
    rpm = [0.0]

    def lagging(x: float) -> float:
        want = css_rpm(30_000.0, x, 1500.0)
        rpm[0] += max(-1500 * T, min(1500 * T, want - rpm[0]))
        return rpm[0]

    samples = []  # (Z step, revolutions turned, Z + pitch x revolutions, rpm)
    for before, sp, turned, revs, _why in follow(p, lagging, 400_000):
        if sp.line == 4 and -20.0 < sp.positions[2] < 0.0:
            samples.append((sp.positions[2] - before[2], turned, sp.positions[2] + pitch * revs,
                            turned * 60 / T))
    cruise = [(lock, r) for dz, turned, lock, r in samples if abs(dz + pitch * turned) < 1e-6]
    rpms = sorted({round(r) for _lock, r in cruise})
    assert rpms[-1] > 1.05 * rpms[0]  # the passes turn at different rpm (their X)
    phases = [lock % pitch for lock, _r in cruise]
    off = [min(abs(q - phases[0]), pitch - abs(q - phases[0])) for q in phases]
    assert len(cruise) > 1000 and max(off) < 1e-6  # one groove


@pytest.mark.parametrize("code", ["G33 Z-20 K{pitch}", "G76 P{pitch} Z-20 I-0.5 J0.2 K1"])
def test_a_thread_faster_than_its_axes_under_g97_is_refused_naming_the_line(code: str) -> None:
    """G97: S times the pitch beyond an axis's max_velocity would have the axis lag the spindle, a
    thread cut at the wrong pitch without a word. It is refused naming the line and the highest S;
    at that S it is planned."""
    pitch = 4.0
    z_cap = DEMO_MACHINE.axes[2].max_velocity
    top = z_cap * 60.0 / pitch  # Z alone moves at the pitch: 1500 rpm
    prog = "G21 G90 G18\nG0 X20 Z1\nG97 S{s} M3\n" + code.format(pitch=pitch) + "\nM5\n"
    with pytest.raises(PlannerError) as err:
        list(plan_all(interpret(prog.format(s=top * 1.05)), DEMO_MACHINE, max_cycles=2_000_000))
    text = str(err.value)
    assert err.value.line == 4 and "max_velocity" in text and f"S{math.floor(top):g}" in text
    sps = list(plan_all(interpret(prog.format(s=top)), DEMO_MACHINE, max_cycles=2_000_000))
    T = DEMO_MACHINE.cycle_s
    vz = [abs(b.positions[2] - a.positions[2]) / T for a, b in itertools.pairwise(sps) if b.line == 4]
    assert max(vz) <= z_cap * (1 + 1e-6)


@pytest.mark.parametrize("followed", [False, True])
def test_a_thread_under_g96_whose_rpm_outruns_the_axes_is_refused_naming_the_line(followed: bool) -> None:
    """G96 S60 D5000 with a pitch of 4: at X5 the spindle turns at 1910 rpm, Z would need 127 mm/s
    (its max_velocity is 100: at most 1500 rpm). Planned at the G96 rpm the axes' cap would shorten the
    pitch; followed, planned at D capped to 1500 rpm while the spindle turns at 1910, the axes would
    run past their max_velocity on its clock. Both refused naming the line; at X7 (1364 rpm) planned."""
    pitch, x_top = 4.0, 60_000.0 / (2 * math.pi * 1500.0)  # the radius at which G96 S60 gives 1500 rpm
    prog = "G21 G90 G18\nG0 X{x} Z1\nG96 D5000 S60 M3\nG33 Z-20 K4\nM5\n"

    def plan(x: float) -> list:
        p = Planner(DEMO_MACHINE)
        p.follow_taps = followed
        p.feed_many(interpret(prog.format(x=x)))
        p.flush()
        return [sp for _b, sp, *_ in follow(p, lambda x: css_rpm(60_000.0, x, 5000.0), 200_000)]

    assert css_rpm(60_000.0, 5.0, 5000.0) * pitch / 60 > DEMO_MACHINE.axes[2].max_velocity
    with pytest.raises(PlannerError) as err:
        plan(5.0)
    text = str(err.value)
    assert err.value.line == 4 and "G96" in text and "max_velocity" in text and "at most 1500 rpm" in text
    assert x_top < 7.0
    assert any(sp.line == 4 for sp in plan(7.0))


@pytest.mark.parametrize("code", ["G33 Z-60 K4", "G76 P4 Z-60 I-0.5 J0.2 K1"])
def test_a_spindle_too_fast_for_the_pitch_stops_following_naming_the_line_and_axis(code: str) -> None:
    """G97 S1500 with a pitch of 4 is planned (Z at its max_velocity of 100 mm/s). A spindle measured
    10 % faster (an override on the drive, an overshoot) would carry Z to 110 mm/s on its clock: once Z's
    speed over the last 20 ms is beyond 1.05 x its max_velocity, following stops with a fault naming
    the line and Z, and the move runs on at its planned pace (within max_velocity) for the machine's
    fault to ramp down. 3 % faster is ridden through, at the pitch."""
    T, z_cap = DEMO_MACHINE.cycle_s, DEMO_MACHINE.axes[2].max_velocity
    prog = f"G21 G90 G18\nG0 X20 Z1\nG97 S1500 M3\n{code}\nM5\n"

    def run(factor: float) -> tuple[list[float], list[float], list[str], int | None]:
        p = Planner(DEMO_MACHINE)
        p.feed_many(interpret(prog))
        p.flush()
        vz, steps, faults, at = [], [], [], None
        for before, sp, turned, _revs, why in follow(p, lambda x: 1500.0 * factor, 400_000):
            if why:
                faults.append(why)
                at = len(vz)
            if sp.line == 4:
                vz.append(abs(sp.positions[2] - before[2]) / T)
                steps.append(abs(sp.positions[2] - before[2]) / (4.0 * turned))
        return vz, steps, faults, at

    vz, _steps, faults, at = run(1.10)
    assert len(faults) == 1 and at is not None
    assert faults[0].split(": ")[0].endswith(":4")  # FILE:LINE
    assert "axis Z" in faults[0] and "max_velocity 100" in faults[0] and "1650 rpm" in faults[0]
    assert max(vz[:at]) > 1.05 * z_cap  # it did outrun Z before the fault
    assert max(vz[at:]) <= z_cap * (1 + 1e-6)  # then on at the planned pace
    vz, steps, faults, _at = run(1.03)
    assert faults == [] and max(vz) == pytest.approx(1.03 * z_cap, rel=1e-6)
    cruise = [s for v, s in zip(vz, steps, strict=True) if v > (1 - 1e-7) * max(vz)]
    assert len(cruise) > 50 and all(s == pytest.approx(1.0, rel=1e-6) for s in cruise)  # at the pitch
