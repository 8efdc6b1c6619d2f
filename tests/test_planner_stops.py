"""Stops the planner must always make within the limits: the end of the program after the feed
override is lowered, and a quick stop on curved pieces. Bounds come from the machine's limits."""

from __future__ import annotations

import math

import numpy as np

from gcode_canon import Interpreter, InterpreterSettings
from gcode_canon.commands import Canon
from planner import DEMO_MACHINE, Planner, Setpoint, check_stream

T = DEMO_MACHINE.cycle_s


def commands(text: str) -> list[Canon]:
    return list(Interpreter(InterpreterSettings(require_program_end=False)).run_string(text))


def sine_lines(n: int = 100, h: float = 0.3, amp: float = 3.0, wavelength: float = 10.0) -> str:
    """A smooth curve as many short lines (CAM style), G64 P0.001, F6000."""
    out = ["G21 G90 G64 P0.001 F6000", "G1 X0 Y0"]
    for i in range(1, n + 1):
        x = i * h
        out.append(f"G1 X{x:.5f} Y{amp * math.sin(2 * math.pi * x / wavelength):.5f}")
    return "\n".join(out) + "\n"


def pull(program: list[Canon], actions: dict[int, tuple[str, float | None]]) -> list[Setpoint]:
    p = Planner(DEMO_MACHINE)
    p.feed_many(program)
    p.flush()
    out: list[Setpoint] = []
    for k in range(200_000):
        if k in actions:
            name, arg = actions[k]
            getattr(p, name)(*(() if arg is None else (arg,)))
        sp = p.next_setpoint()
        if sp is None:
            return out
        out.append(sp)
    raise AssertionError("the stream did not end")


def test_override_cut_near_the_end_still_ends_at_rest() -> None:
    """Override 1.9, then 0.3 shortly before the end: a replan of the running piece must leave the
    last piece room to stop (it once ended at 11 mm/s, the stream stopping dead: 3451 % of the jerk
    limit). Lowering the override never makes stopping harder."""
    program = commands(sine_lines())
    n = len(pull(program, {0: ("set_feed_override", 1.9)}))
    worst = 0.0
    for before_end in range(20, 64, 2):
        out = pull(program, {0: ("set_feed_override", 1.9), n - before_end: ("set_feed_override", 0.3)})
        report = check_stream(out, program, DEMO_MACHINE)
        assert report.ok, (before_end, report.problems())
        pos = np.array([sp.positions for sp in out])
        last_speed = np.linalg.norm(pos[-1] - pos[-2]) / T
        # at rest: the last step is at most what the jerk limit allows in one cycle from rest
        assert last_speed <= min(a.max_jerk for a in DEMO_MACHINE.axes) * T * T, (before_end, last_speed)
        worst = max(worst, report.worst_ratio)
    assert worst <= 1.0


def quick_stop_peaks(text: str, cycles: range) -> dict[str, float]:
    """Worst per-axis jerk / (ratio x max_jerk) and acceleration / quick_stop_deceleration over quick
    stops at each cycle in ``cycles`` (ratio = quick_stop_deceleration / max_acceleration)."""
    program = commands(text)
    worst = {"jerk": 0.0, "acceleration": 0.0}
    for at in cycles:
        out = pull(program, {at: ("quick_stop", None)})
        report = check_stream(out, program, DEMO_MACHINE)
        assert report.max_deviation < 0.02  # on the path (the stop is)
        for axis in DEMO_MACHINE.axes:
            ratio = max(1.0, axis.quick_stop / axis.max_acceleration)
            peaks = report.peaks[axis.name]
            worst["jerk"] = max(worst["jerk"], peaks.jerk / (ratio * axis.max_jerk))
            worst["acceleration"] = max(worst["acceleration"], peaks.acceleration / axis.quick_stop)
    return worst


def test_quick_stop_on_arcs_keeps_the_jerk_within_its_ratio() -> None:
    """On an arc the path acceleration is small (centripetal budget), so scaling the quick-stop jerk
    by quick_stop / path acceleration multiplied it far beyond (640k mm/s^3 against 2.5 x 50k)."""
    text = ("G21 G90 G64 P0.01 F6000\nG1 X10 Y0\nG3 X-10 Y0 I-10 J0\nG3 X10 Y0 I10 J0\n"
            "G61 F3000\nG2 X14 Y0 I2 J0\nG2 X10 Y0 I-2 J0\n")
    worst = quick_stop_peaks(text, range(30, 700, 29))
    assert worst["jerk"] <= 1.01, worst
    assert worst["acceleration"] <= 1.01, worst
    # and it is still a quick stop: somewhere it brakes harder than any normal move may
    x = DEMO_MACHINE.axis("x")
    assert worst["acceleration"] > 1.05 * x.max_acceleration / x.quick_stop, worst


def test_quick_stop_on_smoothed_short_lines_keeps_the_jerk_within_its_ratio() -> None:
    worst = quick_stop_peaks(sine_lines(), range(40, 560, 37))
    assert worst["jerk"] <= 1.01, worst
    assert worst["acceleration"] <= 1.01, worst


def test_quick_stop_on_a_line_still_uses_the_quick_stop_deceleration() -> None:
    """The cap must not weaken a quick stop on a line: it still brakes beyond max_acceleration."""
    program = commands("G21 G90 G61 F6000\nG1 X200\n")
    out = pull(program, {400: ("quick_stop", None)})
    report = check_stream(out, program, DEMO_MACHINE)
    x = DEMO_MACHINE.axis("x")
    ratio = x.quick_stop / x.max_acceleration
    assert x.max_acceleration * 1.05 < report.peaks["x"].acceleration <= x.quick_stop * 1.01
    assert report.peaks["x"].jerk <= ratio * x.max_jerk * 1.01
