"""Run from line with user M codes (M100-M199) in the skipped lines: the last occurrence of each code
that sets outputs is replayed, in order, so every output ends as a full run would have left it, each
with its wait (motiond.runtime.run_from_line; docs/daemon.md, "Run from line").

The demo machine's M101 sets coil 14 to 1 and waits for discrete input 15 (which the simulated module
raises after sim_delay_s); M102 sets coil 14 to 0 (motiond.config_io.DEMO_MCODES)."""

from __future__ import annotations

import pytest
from test_machine_io_e2e import Rig, rig  # noqa: F401  (the fixture)

from motiond.config_io import DEMO_MCODES

PROGRAM = """%
G21 G90 G94
M101
G1 X5 F3000
M102
G1 X6
M101 P2
G1 X10
G1 X12
M2
%
"""
CLAMP = DEMO_MCODES["M101"]["set"][0]["coil"]


def full_run_value(line: int) -> int:
    """Coil 14 as the lines before ``line`` leave it: the value of the last M1xx before it."""
    value = 0
    for k, text in enumerate(PROGRAM.splitlines(), 1):
        if k < line and text.startswith("M10"):
            value = int(DEMO_MCODES[text.split()[0]]["set"][0]["value"])
    return value


@pytest.mark.parametrize("start", [6, 8])
def test_user_mcodes_before_the_start_line_are_replayed_to_their_last_state(rig: Rig, start: int) -> None:  # noqa: F811
    prog = rig.program(PROGRAM)
    n = len(rig.sim.writes)
    job = rig.machine.run(prog, start)
    result = rig.machine.wait_job(job, 30.0)
    assert result is not None and result.ok, result.error if result else "timeout"
    replayed = [(o.name, o.value) for o in result.outputs if o.kind == "function" and o.line == start]
    # the last of each code in order: start 6 replays M101 then M102, start 8 M102 then M101
    assert len(replayed) == 2 and replayed[-1][1] == full_run_value(start), replayed
    writes = [w.values[0] for w in rig.sim.writes_to("coil", CLAMP) if w in rig.sim.writes[n:]]
    assert writes[:2] == [int(v) for _n, v in replayed]  # on the module, before the start line's own
    info = [e[1] for e in rig.kinds("run_from_line") if e[0] == "INFO"]
    assert info and "M101 (as line" in info[0] and "M102 (as line" in info[0], info
