"""Run from line: ``Machine.run(path, start_line)``, ``canon run --start-line``, the LCM ``run`` verb.

The demo machine (simulated drives on a private virtual bus, the simulated I/O module on a free
loopback port) with no telemetry (``lc=None``): the events it emits are recorded by wrapping
``Machine.event``, the setpoints through ``Machine.trace``. The lines before the start line must
move nothing, the state they leave (work offset, tool, spindle, coolant, override switches) must be
restored, the approach must raise Z first, and the rest must land where a full run lands.
"""

from __future__ import annotations

import math
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from gcode_canon import commands as C
from motiond.cli import UserError
from motiond.cmd_ctl import split_arguments
from motiond.config import load_machine
from motiond.runtime import Machine
from motiond.states import CommandRefused, State
from telemetry.commands import make_command

ROOT = Path(__file__).resolve().parent.parent

# Line numbers matter: the tests start at lines 9 and 11.
PART = """%
G21 G90 G94 G17 G61
G10 L2 P1 X10 Y5 Z0
G54
T2 M6
S1200 M3
M8 M50 P0
G0 X0 Y0 Z5
G1 Z-1 F300
G1 X20 F600
G1 Y10
G0 Z5
G0 X0 Y0
M5 M9
M2
%
"""
START = 11  # G1 Y10
START_POINT = (30.0, 5.0, -1.0)  # the end of line 10 in machine coordinates (G54 X10 Y5)
REST = [(30.0, 15.0, -1.0), (30.0, 15.0, 5.0), (10.0, 5.0, 5.0)]  # the ends of lines 11, 12, 13
SKIPPED_POINT = (10.0, 5.0, 5.0)  # line 8's G0: the first motion of a full run

TOL = 1e-6


class Recorder:
    """A started, enabled demo machine whose events are kept as (severity, text, kind, file, line)."""

    def __init__(self, tmp: Path, config: str | None = None, **kw: Any) -> None:
        self.machine = Machine(load_machine(config), lc=None, var_file=tmp / "params.var", **kw)
        self.events: list[tuple[str, str, str, str, int]] = []
        emit = self.machine.event

        def event(severity: str, text: str, *, kind: str = "", source: str = "motiond", file: str = "",
                  line: int = 0) -> None:
            self.events.append((severity, text, kind, file, line))
            emit(severity, text, kind=kind, source=source, file=file, line=line)

        self.machine.event = event  # type: ignore[method-assign]
        try:
            self.machine.start()
            self.machine.bring_up()
        except BaseException:  # no fixture will shut it down: its processes and threads must not outlive it
            self.machine.shutdown()
            raise

    def kinds(self, kind: str) -> list[tuple[str, str, str, str, int]]:
        return [e for e in self.events if e[2] == kind]

    def run(self, path: Path, start_line: int = 0, timeout: float = 30.0) -> Any:
        job = self.machine.run(path, start_line)
        result = self.machine.wait_job(job, timeout)
        assert result is not None, f"{path} did not finish within {timeout} s"
        wait_for(lambda: self.machine.states.state is State.IDLE, "IDLE after the job")
        return result

    def mdi(self, line: str) -> None:
        job = self.machine.mdi(line)
        result = self.machine.wait_job(job, 20.0)
        assert result is not None and result.ok, f"MDI {line}: {result.error if result else 'timeout'}"
        wait_for(lambda: self.machine.states.state is State.IDLE, "IDLE after MDI")


def wait_for(pred: Callable[[], bool], what: str, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return
        time.sleep(0.01)
    raise AssertionError(f"never saw {what} within {timeout} s")


@pytest.fixture
def rec(tmp_path: Path) -> Iterator[Recorder]:
    r = Recorder(tmp_path)
    try:
        yield r
    finally:
        r.machine.shutdown()


def program(tmp: Path, text: str, name: str = "part.ngc") -> Path:
    p = tmp / name
    p.write_text(text)
    return p


def near(a: tuple[float, ...], b: tuple[float, ...], tol: float = TOL) -> bool:
    return all(abs(x - y) <= tol for x, y in zip(a, b, strict=True))


def on_segment(p: tuple[float, ...], a: tuple[float, ...], b: tuple[float, ...]) -> bool:
    """``p`` on the straight segment from ``a`` to ``b`` (within TOL)."""
    ab = [y - x for x, y in zip(a, b, strict=True)]
    ap = [y - x for x, y in zip(a, p, strict=True)]
    L2 = sum(v * v for v in ab)
    t = sum(u * v for u, v in zip(ab, ap, strict=True)) / L2
    if not -TOL <= t <= 1 + TOL:
        return False
    return math.dist(p, [x + t * v for x, v in zip(a, ab, strict=True)]) <= 1e-5


def tail_from(trace: list[Any], point: tuple[float, ...]) -> list[tuple[float, ...]]:
    """The setpoint positions from the last cycle at ``point`` before the machine leaves it for good."""
    pos = [tuple(t[2]) for t in trace]
    first = next(i for i, p in enumerate(pos) if near(p, point))
    k = first
    while k + 1 < len(pos) and near(pos[k + 1], point):
        k += 1
    return pos[k:]


def passes(positions: list[tuple[float, ...]], points: list[tuple[float, ...]]) -> bool:
    """Whether the path visits ``points`` in this order."""
    i = 0
    for p in positions:
        if i < len(points) and near(p, points[i]):
            i += 1
    return i == len(points)


def test_run_from_line_restores_state_approaches_safely_and_lands_as_a_full_run(
        rec: Recorder, tmp_path: Path) -> None:
    m = rec.machine
    prog = program(tmp_path, PART)
    rec.mdi("G53 G0 X50 Y40 Z20")  # the machine stands high, away from the start point
    start = (50.0, 40.0, 20.0)
    assert m.interp.current_tool == 0
    m.trace = []
    res = rec.run(prog, START)
    assert res.ok, res.error
    trace = list(m.trace)
    pos = [tuple(t[2]) for t in trace]

    # nothing of lines 1-10 moved: the first setpoint is where the machine stood, line 8's G0 point
    # (10, 5, 5) is never visited before the start point, and the first motion is the approach
    assert near(pos[0], start, 1e-3)
    reach = next(i for i, p in enumerate(pos) if near(p, START_POINT))
    assert not any(near(p, SKIPPED_POINT, 1e-3) for p in pos[:reach])

    # approach: the start Z (-1) is below the machine (20): X Y first at Z 20, then Z down alone
    xy_done = next(i for i, p in enumerate(pos) if near(p[:2], START_POINT[:2]))
    high = (START_POINT[0], START_POINT[1], start[2])
    for p in pos[:xy_done + 1]:
        assert p[2] == pytest.approx(start[2], abs=TOL), f"Z moved before X Y arrived: {p}"
        assert on_segment(p, start, high), f"off the straight X Y approach: {p}"
    for p in pos[xy_done:reach + 1]:
        assert near(p[:2], START_POINT[:2]), f"X Y moved while Z went down: {p}"
        assert START_POINT[2] - TOL <= p[2] <= start[2] + TOL

    # the state the skipped lines left, restored before the X Y approach, in the setpoints' events
    events = [(k, ev) for k, t in enumerate(trace) for ev in t[3]]
    by_type = {type(ev): (k, ev) for k, ev in reversed(events)}  # the first of each type
    k_tool, tool = by_type[C.ToolChange]
    assert tool.tool == 2 and k_tool <= xy_done
    k_sp, spindle = by_type[C.SpindleOn]
    assert spindle.direction is C.SpindleDirection.CW and spindle.rpm == 1200.0 and k_sp <= xy_done
    k_cool, coolant = by_type[C.Coolant]
    assert (coolant.mist, coolant.flood) == (False, True) and k_cool <= xy_done + 1
    leave = next(i for i in range(reach, len(pos)) if pos[i][1] > START_POINT[1] + TOL)  # line 11 moves
    overrides = [ev for k, ev in events if isinstance(ev, C.SetOverrides) and k <= leave]
    assert overrides and overrides[-1].feed is False  # M50 P0 of line 7, after the approach's own
    assert any(e[2] == "tool_change" and "T2" in e[1] for e in rec.events)
    info = [e for e in rec.kinds("run_from_line") if e[0] == "INFO"]
    assert info and info[0][3] == str(prog) and info[0][4] == START
    assert "T2 M6" in info[0][1] and "M3 S1200" in info[0][1] and "M8" in info[0][1]

    assert m.status().tool == 2 and m.interp.current_tool == 2

    # the remaining moves land where a full run lands: the same setpoints from the start point on
    rest = tail_from(trace, START_POINT)
    assert passes(rest, REST)
    m.trace = []
    full = rec.run(prog)
    assert full.ok, full.error
    full_rest = tail_from(list(m.trace), START_POINT)
    assert len(rest) == len(full_rest)
    assert all(near(a, b, 1e-9) for a, b in zip(rest, full_rest, strict=True))
    assert near(res.final_commanded, full.final_commanded, 1e-12)
    wait_for(lambda: near(tuple(m.motion.actual), REST[-1], 1e-3), "the drives at the end")


def test_approach_raises_z_first_when_the_start_point_is_higher(rec: Recorder, tmp_path: Path) -> None:
    m = rec.machine
    prog = program(tmp_path, PART)
    rec.mdi("G53 G0 X50 Y40 Z-3")  # the machine stands low
    m.trace = []
    res = rec.run(prog, 9)  # G1 Z-1 F300: starts at the end of line 8, machine (10, 5, 5)
    assert res.ok, res.error
    pos = [tuple(t[2]) for t in m.trace]
    up = next(i for i, p in enumerate(pos) if p[2] == pytest.approx(5.0, abs=TOL))
    for p in pos[:up + 1]:
        assert near(p[:2], (50.0, 40.0)), f"X or Y moved before Z was up: {p}"
    arrived = next(i for i, p in enumerate(pos) if near(p, SKIPPED_POINT))
    for p in pos[up:arrived + 1]:
        assert p[2] == pytest.approx(5.0, abs=TOL) and on_segment(p, (50.0, 40.0, 5.0), SKIPPED_POINT)
    # the spindle starts after Z is up and before X Y move
    k_sp = next(k for k, t in enumerate(m.trace) for ev in t[3] if isinstance(ev, C.SpindleOn))
    assert up <= k_sp and all(near(p[:2], (50.0, 40.0)) for p in pos[:k_sp + 1])
    assert passes(pos[arrived:], [(10.0, 5.0, -1.0), START_POINT, *REST])


def test_start_line_beyond_the_end_is_refused_at_once(rec: Recorder, tmp_path: Path) -> None:
    prog = program(tmp_path, PART)
    with pytest.raises(CommandRefused, match=rf"^{prog}:99: cannot start at line 99: the program has only "
                                             r"16 lines"):
        rec.machine.run(prog, 99)
    assert rec.machine.states.state is State.IDLE and rec.machine.job is None


UNREACHED = """%
G21 G90
#1 = 0
o10 if [#1 GT 0]
  G0 X5
o10 endif
G0 X1
o<sub> sub
  G0 Y2
o<sub> endsub
o20 while [#1 LT 2]
  G0 X[#1]
  #1 = [#1 + 1]
o20 endwhile
o<sub> call
M2
G0 X9
%
"""


@pytest.mark.parametrize(("line", "words"), [
    (5, "never executes it"),  # a branch not taken
    (9, "inside subroutine o<sub> (sub at line 8), here called from"),  # run when called from line 15
    (12, "inside the body of loop o20 while (line 11)"),
    (17, "the program ends at line 16"),
])
def test_unreachable_start_lines_are_refused_nothing_moved(rec: Recorder, tmp_path: Path, line: int,
                                                           words: str) -> None:
    m = rec.machine
    prog = program(tmp_path, UNREACHED)
    m.trace = []
    res = rec.run(prog, line)
    assert not res.ok
    assert res.error.startswith(f"{prog}:{line}: cannot start at line {line}: "), res.error
    assert words in res.error
    assert m.trace == []  # not one setpoint
    assert m.states.state is State.IDLE and m.states.snapshot().enabled  # a refusal, not a fault
    assert m.status().last_error == res.error
    errors = [e for e in rec.kinds("run_from_line") if e[0] == "ERROR"]
    assert errors and errors[-1][1] == res.error
    # and the machine runs the next program as usual
    assert rec.run(prog, 7).ok


def test_sub_never_called_and_probe_before_the_start_are_refused(rec: Recorder, tmp_path: Path) -> None:
    m = rec.machine
    prog = program(tmp_path, "%\nG21 G90\no<s> sub\n  G0 X1\no<s> endsub\nG0 X2\nM2\n%\n")
    res = rec.run(prog, 4)
    assert not res.ok and res.error.startswith(f"{prog}:4: ") and \
        "inside the definition of subroutine o<s> (lines 3-5)" in res.error
    probe = program(tmp_path, "%\nG21 G90\nG38.2 Z-5 F100\nG0 Z10\nG0 X5\nM2\n%\n", "probe.ngc")
    res = rec.run(probe, 5)
    assert not res.ok and res.error.startswith(f"{probe}:3: cannot start at line 5: the probe at line 3")
    comp = program(tmp_path, "%\nG21 G90 F500\nG41 D1\nG1 X10\nG1 Y10\nG40\nG0 X0\nM2\n%\n", "comp.ngc")
    res = rec.run(comp, 5)
    assert not res.ok and "cutter radius compensation (G41)" in res.error
    assert m.trace is None or m.trace == []
    assert m.states.state is State.IDLE


def test_run_verb_second_value_and_ctl_words(rec: Recorder, tmp_path: Path) -> None:
    m = rec.machine
    prog = program(tmp_path, PART)
    assert split_arguments("run", [str(prog), "11"]) == ([str(prog)], [11.0])
    for bad in ("0", "2.5"):
        with pytest.raises(UserError, match="start line must be a line number"):
            split_arguments("run", [str(prog), bad])
    m.program_dirs = [tmp_path]  # the run verb takes programs from the program directories only
    refusal = m.handle_command(make_command("run", [str(prog)], [40.0]))
    assert refusal is not None and refusal.startswith(f"{prog}:40: cannot start at line 40")
    assert m.handle_command(make_command("run", [str(prog)], [float(START)])) is None
    wait_for(lambda: m.job is None and m.states.state is State.IDLE, "the end of the run from line", 30.0)
    info = [e for e in rec.kinds("run_from_line") if e[0] == "INFO"]
    assert info and info[-1][4] == START
    assert near(tuple(m.motion.commanded), REST[-1])


def canon(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "motiond.cli", *args], capture_output=True, text=True,
                          timeout=120, cwd=ROOT)


def test_canon_run_start_line(tmp_path: Path) -> None:
    import json

    prog = program(tmp_path, PART)
    done = canon("run", "--no-telemetry", "--json", "--start-line", str(START), str(prog))
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["ok"]
    assert [summary["final_positions"][a] for a in "xyz"] == pytest.approx(list(REST[-1]), abs=TOL)
    refused = canon("run", "--no-telemetry", "--start-line", "17", str(program(tmp_path, UNREACHED, "u.ngc")))
    assert refused.returncode == 1
    assert "u.ngc:17: cannot start at line 17: the program ends at line 16" in refused.stderr
    assert "Traceback" not in refused.stderr
    bad = canon("run", "--no-telemetry", "--start-line", "0", str(prog))
    assert bad.returncode == 2 and "--start-line" in bad.stderr


def test_run_from_line_under_g96_restores_the_surface_speed_as_rpm(rec: Recorder, tmp_path: Path) -> None:
    """G96 before the start line: the restored S is a surface speed, so the mode goes first and the
    spindle gets the rpm of the X it starts at (planner/css.py), never the S number as rpm."""
    from planner.css import css_rpm

    m = rec.machine
    prog = program(tmp_path, "G21 G90 G17\nG0 X40 Y0 Z5\nG96 D1200 S100 M3\nG1 X30 F600\nG1 X20\nM5\nM2\n")
    m.trace = []
    res = rec.run(prog, 5)  # G1 X20: starts at X30
    assert res.ok, res.error
    speeds = [(t[2][0], ev.rpm) for t in m.trace for ev in t[3]
              if isinstance(ev, C.SpindleOn | C.SetSpindleSpeed)]
    assert speeds and all(rpm != 100.0 for _x, rpm in speeds), speeds
    centre = 0.0  # no X offsets: the radius is machine X
    for x, rpm in speeds:
        assert rpm == pytest.approx(css_rpm(100_000.0, x - centre, 1200.0), rel=1e-9), (x, rpm)
