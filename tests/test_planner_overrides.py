"""M48-M53 in the planner: override switches queued with each move, as LinuxCNC does.

The programs go through the interpreter, so the commands are the ones a user's M49 / M50 P0 / M52 /
M53 really produce. Speeds are measured from the setpoints (cycle-to-cycle distance over T), per
source line.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from gcode_canon import Interpreter, InterpreterSettings
from gcode_canon.commands import Canon, SetOverrides
from planner import DEMO_MACHINE, Planner, Setpoint, check_stream

T = DEMO_MACHINE.cycle_s
F = 3000.0  # mm/min
V = F / 60.0  # programmed path speed, mm/s

SQUARE = f"""G21 G90 G64 P0.01 F{F:g}
G1 X100
M49
G1 X100 Y100
M48
G1 X0 Y100
M50 P0
G1 X0 Y0
M50 P1
G1 X50 Y0
"""
"""Lines 2, 6 and 10 obey the override; 4 (M49) and 8 (M50 P0) do not."""


def commands(text: str) -> list[Canon]:
    interp = Interpreter(InterpreterSettings(require_program_end=False))
    return list(interp.run_string(text))


Action = Callable[[Planner, int, Setpoint | None], None]


def run(program: list[Canon], action: Action | None = None, limit: int = 40000,
        ) -> tuple[Planner, list[Setpoint]]:
    """Pull the whole stream; ``action(planner, cycle, last setpoint)`` runs before each pull."""
    p = Planner()
    p.feed_many(program)
    p.flush()
    out: list[Setpoint] = []
    for k in range(limit):
        if action is not None:
            action(p, k, out[-1] if out else None)
        sp = p.next_setpoint()
        if sp is None:
            break
        out.append(sp)
    else:
        pytest.fail("the stream did not end")
    return p, out


def speeds(out: list[Setpoint]) -> np.ndarray:
    """Path speed of each setpoint (from the one before it; 0 for the first)."""
    pts = np.array([s.positions for s in out])
    return np.concatenate([[0.0], np.linalg.norm(np.diff(pts, axis=0), axis=1) / T])


def peak_by_line(out: list[Setpoint]) -> dict[int, float]:
    v = speeds(out)
    peaks: dict[int, float] = {}
    for sp, speed in zip(out, v, strict=True):
        if sp.positions is not None and sp.line:
            peaks[sp.line] = max(peaks.get(sp.line, 0.0), float(speed))
    return peaks


def override_at_start(factor: float) -> Action:
    def act(p: Planner, k: int, _sp: Setpoint | None) -> None:
        if k == 0:
            p.set_feed_override(factor)
    return act


def test_m49_and_m50_p0_moves_run_at_programmed_feed_while_the_others_follow_the_override() -> None:
    program = commands(SQUARE)
    _p, out = run(program, override_at_start(0.5))
    report = check_stream(out, program)
    assert report.ok, report.problems()
    peaks = peak_by_line(out)
    for line in (2, 6, 10):  # override in force: half the feed
        assert peaks[line] == pytest.approx(0.5 * V, rel=1e-3), line
    for line in (4, 8):  # M49, M50 P0: the programmed feed, override or not
        assert peaks[line] == pytest.approx(V, rel=1e-3), line


def test_without_any_switch_the_override_applies_everywhere() -> None:
    program = commands(SQUARE.replace("M49\n", "").replace("M50 P0\n", ""))
    _p, out = run(program, override_at_start(0.5))
    peaks = peak_by_line(out)
    assert max(peaks.values()) == pytest.approx(0.5 * V, rel=1e-3)


def test_the_switches_ride_on_as_events() -> None:
    program = commands(SQUARE)
    _p, out = run(program)
    seen = [e for sp in out for e in sp.events if isinstance(e, SetOverrides)]
    assert [(e.line, e.feed) for e in seen] == [(3, False), (5, True), (7, False), (9, True)]


def test_override_changed_during_an_m49_move_does_not_touch_it_and_applies_after_m48() -> None:
    program = commands(SQUARE)

    def act(p: Planner, _k: int, sp: Setpoint | None) -> None:
        if sp is not None and sp.line == 4 and p.feed_override == 1.0:
            p.set_feed_override(0.4)  # while the M49 move runs

    _p, out = run(program, act)
    report = check_stream(out, program)
    assert report.ok, report.problems()
    peaks = peak_by_line(out)
    assert peaks[4] == pytest.approx(V, rel=1e-3)
    assert peaks[6] == pytest.approx(0.4 * V, rel=1e-3)


def test_override_zero_does_not_stop_an_m49_move_but_stops_the_next_m48_one() -> None:
    program = commands(SQUARE)
    state = {"set": -1}

    def act(p: Planner, k: int, sp: Setpoint | None) -> None:
        if sp is not None and sp.line == 4 and state["set"] < 0:
            p.set_feed_override(0.0)
            state["set"] = k
        elif state["set"] >= 0 and k == state["set"] + 2000:
            p.set_feed_override(1.0)

    _p, out = run(program, act)
    report = check_stream(out, program)
    assert report.ok, report.problems()
    v = speeds(out)
    lines = np.array([sp.line for sp in out])
    assert v[lines == 4].max() == pytest.approx(V, rel=1e-3)  # ran on at full feed
    # it stopped on line 6 (override in force) and stayed there until the override came back
    k0 = state["set"]
    stopped = np.nonzero(v[k0: k0 + 2000] == 0.0)[0]
    assert len(stopped) > 500
    x, y, _z = out[k0 + stopped[-1]].positions  # at rest on the M48 move (line 6: Y100, X from 100 to 0)
    assert y == pytest.approx(100.0, abs=0.01) and 0.0 < x < 100.0
    assert v[k0 + 2000:][lines[k0 + 2000:] == 6].max() == pytest.approx(V, rel=1e-3)


def test_hold_and_resume_still_work_inside_an_m49_move() -> None:
    program = commands(SQUARE)
    state = {"held": -1}

    def act(p: Planner, k: int, sp: Setpoint | None) -> None:
        if k == 0:
            p.set_feed_override(0.5)
        if sp is not None and sp.line == 4 and state["held"] < 0 and sp.positions[1] > 30.0:
            p.hold()
            state["held"] = k
        elif state["held"] >= 0 and k == state["held"] + 300:
            p.resume()

    p, out = run(program, act)
    report = check_stream(out, program)
    assert report.ok, report.problems()
    v = speeds(out)
    k0 = state["held"]
    assert np.all(v[k0 + 150: k0 + 300] == 0.0)  # held at rest
    y_hold = out[k0 + 200].positions[1]
    assert 30.0 < y_hold < 100.0 and out[k0 + 200].positions[0] == pytest.approx(100.0, abs=1e-9)
    lines = np.array([sp.line for sp in out])
    after = v[k0 + 300:][lines[k0 + 300:] == 4]
    assert after.max() == pytest.approx(V, rel=1e-3)  # resumed at the full programmed feed
    assert peak_by_line(out)[6] == pytest.approx(0.5 * V, rel=1e-3)
    assert not p.holding


def test_adaptive_feed_scales_only_moves_queued_under_m52() -> None:
    program = commands(f"G21 G90 G61 F{F:g}\nG1 X100\nM52 P1\nG1 X0\nM52 P0\nG1 X100\n")

    def act(p: Planner, k: int, _sp: Setpoint | None) -> None:
        if k == 0:
            p.set_adaptive_feed(0.3)

    _p, out = run(program, act)
    report = check_stream(out, program)
    assert report.ok, report.problems()
    peaks = peak_by_line(out)
    assert peaks[2] == pytest.approx(V, rel=1e-3)
    assert peaks[4] == pytest.approx(0.3 * V, rel=1e-3)
    assert peaks[6] == pytest.approx(V, rel=1e-3)


def test_feed_stop_input_stops_moves_unless_m53_p0() -> None:
    program = commands(f"G21 G90 G61 F{F:g}\nG1 X100\nM53 P0\nG1 X0\nM53 P1\nG1 X100\n")
    state = {"second": -1}

    def act(p: Planner, k: int, sp: Setpoint | None) -> None:
        if k == 100:
            p.set_feed_stop(True)  # on line 2: it stops there
        elif k == 700:
            p.set_feed_stop(False)
        elif sp is not None and sp.line == 4 and state["second"] < 0 and sp.positions[0] < 60:
            p.set_feed_stop(True)  # on the M53 P0 move: ignored; line 6 waits at its start
            state["second"] = k
        elif state["second"] >= 0 and k == state["second"] + 1500:
            p.set_feed_stop(False)

    _p, out = run(program, act)
    report = check_stream(out, program)
    assert report.ok, report.problems()
    v = speeds(out)
    lines = np.array([sp.line for sp in out])
    assert np.all(v[400:700] == 0.0)  # stopped on line 2 (rest setpoints carry no line)
    assert 10.0 < out[500].positions[0] < 100.0
    assert v[lines == 4].max() == pytest.approx(V, rel=1e-3)  # the M53 P0 move ignores the input
    k1 = state["second"]
    rest = np.nonzero(v[k1:k1 + 1500] == 0.0)[0] + k1
    assert len(rest) > 600  # waited at the start of line 6 until the input went off
    assert all(out[k].positions[0] == pytest.approx(0.0, abs=1e-9) for k in rest[-10:])
    assert out[-1].positions[0] == pytest.approx(100.0)
