"""The status shows the modal state of the block being executed, not the interpreter's read-ahead.

The interpreter reads up to 2000 commands ahead of the motion; the modal codes, feed and tool in
``canon.status`` must follow the motion instead (``motiond.runtime.ModalState`` riding with the
setpoints). The demo machine with no telemetry (``lc=None``); ``Machine.status()`` is sampled while a
long move runs and after the program's next move has begun. Bounded waits only.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from motiond.config import load_machine
from motiond.runtime import Machine
from motiond.states import State

# A 2 s move (100 mm at 50 mm/s) on line 3 in G90 G17 F3000 with the coolant off, then on later lines
# G91, G18, M7 and F2000, and a second 1.8 s move on line 7 that runs in them (X from 100 back to 40).
# G61: the reversal at X100 is a stop, not a blend (the line shown changes at the stop). The closing %
# ends the program without M2's resets, so the interpreter, which has read it all long
# before the first move ends, stays in the later state.
PROGRAM = """%
G21 G90 G17 G94 G61
G1 X100 F3000
G91
G18
M7
G1 X-60 F2000
%
"""


@pytest.fixture
def machine(tmp_path: Path) -> Iterator[Machine]:
    m = Machine(load_machine(None), lc=None, var_file=tmp_path / "params.var")
    m.start()
    try:
        m.bring_up()
        yield m
    finally:
        m.shutdown()


def sample_until(m: Machine, pred: Callable[[Any], bool], what: str, timeout: float = 10.0) -> list[Any]:
    """Statuses every 5 ms until one satisfies ``pred`` (it is the last one); at most ``timeout`` s."""
    out: list[Any] = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        s = m.status()
        out.append(s)
        if pred(s):
            return out
        time.sleep(0.005)
    raise AssertionError(f"status never showed {what} within {timeout} s (last: X {out[-1].commanded[0]}, "
                         f"state {out[-1].state}, codes {list(out[-1].gcodes)})")


def test_status_modal_codes_follow_the_executing_block(machine: Machine, tmp_path: Path) -> None:
    prog = tmp_path / "modal.ngc"
    prog.write_text(PROGRAM)
    job = machine.run(prog)
    # the interpreter has long read past line 7 while line 2's move runs
    first = sample_until(machine, lambda s: s.commanded[0] > 90.0, "X past 90 on the first move")
    during = [s for s in first if 5.0 < s.commanded[0] < 90.0]
    assert len(during) > 20, "too few samples during the first move"
    assert "G91" in machine.interp.active_gcodes() and machine.interp.feed == 2000.0  # read ahead
    for s in during:
        assert s.line == 3
        g, m = list(s.gcodes), list(s.mcodes)
        assert "G90" in g and "G17" in g and "G91" not in g and "G18" not in g, g
        assert g[0] == "G1"
        assert "M9" in m and "M7" not in m, m
        assert s.feed_rate == 3000.0
    # the second move (X from 100 down to 40) runs in G91 G18 M7 F2000
    second = sample_until(machine, lambda s: s.commanded[0] < 50.0 and s.line == 7,
                          "X below 50 on the second move")
    back = [s for s in second if s.line == 7 and s.commanded[0] < 95.0]
    assert back, "no sample during the second move"
    for s in back:
        g, m = list(s.gcodes), list(s.mcodes)
        assert "G91" in g and "G18" in g and "G90" not in g and "G17" not in g, g
        assert "M7" in m, m
        assert s.feed_rate == 2000.0
    result = machine.wait_job(job, 20.0)
    assert result is not None and result.ok, result.error if result else "no result"
    deadline = time.monotonic() + 5.0
    while machine.states.state is not State.IDLE and time.monotonic() < deadline:
        time.sleep(0.01)
    end = machine.status()  # no job: the interpreter's state, which the machine has now reached
    assert "G91" in end.gcodes and "G18" in end.gcodes and "M7" in end.mcodes and end.feed_rate == 2000.0


@pytest.mark.parametrize(("dialect", "shown", "hidden"), [
    ("linuxcnc", ["G17", "G21", "G54", "G64"], ["G8", "G15", "G50", "G69", "G23"]),
    ("gcode-canon", ["G17", "G8", "G15", "G50", "G69", "G23"], []),
])
def test_status_modal_codes_are_dialect_aware(tmp_path: Path, dialect: str, shown: list[str],
                                              hidden: list[str]) -> None:
    from motiond.interp_settings import build_settings

    config = load_machine(None)
    m = Machine(config, lc=None, interp_settings=build_settings(config, dialect=dialect, dry_run=False))
    try:
        m.start()
        codes = list(m.status().gcodes)
    finally:
        m.shutdown()
    for code in shown:
        assert code in codes, codes
    for code in hidden:
        assert code not in codes, codes


def test_an_active_extension_still_shows_in_the_linuxcnc_dialect() -> None:
    from gcode_canon.dialect import Dialect
    from motiond.status_view import status_gcodes

    codes = ("G1", "G17", "G21", "G90", "G91.1", "G94", "G40", "G49", "G80", "G54", "G64", "G97", "G8",
             "G16", "G50", "G68", "G23")
    assert status_gcodes(codes, Dialect.LINUXCNC)[-3:] == ("G97", "G16", "G68")
