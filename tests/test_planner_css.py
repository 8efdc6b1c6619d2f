"""G96 constant surface speed on the planner's side (planner/css.py): the S number is a surface speed,
so the speeds the setpoints carry are rpm computed from the commanded X radius, at most D."""

from __future__ import annotations

import itertools
import math

import pytest

from gcode_canon.commands import SetSpindleSpeed, SpindleOn
from planner import DEMO_MACHINE, plan_all
from planner.css import CSS_MIN_INTERVAL_S, CSS_STEP, css_rpm
from planner.segments import PlannerError
from tests.test_interp_helpers import run as interpret

FACE = "G21 G90 G18\nG0 X40 Z1\nG96 D1500 S100 M3\nG1 X5 Z0 F300\nG97 S600\nG1 X10\nM5\n"


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


@pytest.mark.parametrize("text", [
    "G21 G18\nG0 X20\nG96 S100 M3\nG95 G1 X10 F0.2\n",
    "G21 G18\nG0 X20\nG96 S100 M3\nG33 Z-5 K1\n",
])
def test_per_revolution_feed_and_spindle_sync_under_g96_are_refused_naming_the_line(text: str) -> None:
    with pytest.raises(PlannerError) as err:
        list(plan_all(interpret(text), DEMO_MACHINE, max_cycles=200_000))
    assert err.value.line == 4 and "G96" in str(err.value)
