"""The issue's "done when": examples/demo_part.ngc (spindle, coolant, probing, rigid tapping, a thread)
runs on examples/mill_spindle.toml with ``canon run``, and the run summary (``--json``) lists every
function switched, in the order and on the lines the program switches them, the probe's trip among
them. The expected lines are found in the program's text, not written here."""

from __future__ import annotations

import json
import re
import socket
import subprocess
import sys
from pathlib import Path

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
PROGRAM = EXAMPLES / "demo_part.ngc"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _code(text: str) -> str:
    return re.sub(r"\(.*?\)", "", text)


def has(text: str, word: str) -> bool:
    return re.search(rf"(?<![\w.]){re.escape(word)}(?![\d.])", _code(text)) is not None


def lines_of(word: str) -> list[int]:
    """The program's lines that carry G/M word ``word`` (comments left out)."""
    return [k for k, text in enumerate(PROGRAM.read_text().splitlines(), 1) if has(text, word)]


def number(pattern: str) -> float:
    """The number ``pattern``'s group finds in the program (its words, not comments)."""
    m = re.search(pattern, _code(PROGRAM.read_text()))
    assert m is not None, pattern
    return float(m.group(1))


def expected() -> list[tuple[str, float, int]]:
    """(function, value, line) in program order, from the M words and the probing move: M9 switches
    off the coolant that is on there."""
    out: list[tuple[str, float, int]] = []
    coolant: list[str] = []
    for k, text in enumerate(PROGRAM.read_text().splitlines(), 1):
        if has(text, "M3"):
            out.append(("spindle_on", 1.0, k))
        for word, name in (("M7", "coolant_mist"), ("M8", "coolant_flood")):
            if has(text, word):
                coolant.append(name)
                out.append((name, 1.0, k))
        if has(text, "M9"):
            out += [(c, 0.0, k) for c in coolant]
            coolant = []
        if has(text, "M5"):
            out.append(("spindle_on", 0.0, k))
        if has(text, "G38.2"):
            out.append(("probe", 1.0, k))
    return out


def test_the_whole_program_demo_switches_every_function_in_order(tmp_path: Path) -> None:
    text = (EXAMPLES / "mill_spindle.toml").read_text()
    assert "port = 5022" in text
    config = tmp_path / "mill.toml"  # its simulated module on a free port: runs may share the PC
    config.write_text(text.replace("port = 5022", f"port = {free_port()}"))
    for word in ("M3", "M8", "G38.2", "M7", "G33.1", "G33", "M9", "M5"):
        assert lines_of(word), f"the demo program has no {word}"
    r = subprocess.run([sys.executable, "-m", "motiond.cli", "run", "--json", "--no-telemetry", "--config",
                        str(config), str(PROGRAM)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr + r.stdout
    d = json.loads(r.stdout)
    assert d["ok"], d["error"]
    got = [(o["name"], o["value"], o["line"]) for o in d["outputs_switched"] if o["kind"] == "function"]
    assert got == expected()
    cycles = [o["cycle"] for o in d["outputs_switched"] if o["kind"] == "function"]
    assert cycles == sorted(cycles)  # switched in the order of the program, cycle by cycle
    assert d["axes"]["z"]["final_commanded"] == 0.0  # G53 G0 Z0 at the end: back up


def test_the_demo_probes_taps_and_threads_where_the_program_says(tmp_path: Path) -> None:
    """In this process, with the setpoints traced: the probe trips at the simulated work's surface
    ([io.sim] probe_z), the tap goes 8 mm below it and the thread 6 mm, as the program's words say,
    while the mist is on; and the functions switch in the cycles of their lines."""
    import tomllib

    from test_drive_outputs import started

    config = EXAMPLES / "mill_spindle.toml"
    surface = tomllib.loads(config.read_text())["io"]["sim"]["probe_z"]
    depth = {w: number(rf"{re.escape(w)} Z\[#<top> - ([\d.]+)\]") for w in ("G33.1", "G33")}
    with started(config, tmp_path) as m:
        m.trace = []
        result = m.wait_job(m.run(PROGRAM), 120.0)
        assert result is not None and result.ok, result.error if result else "timeout"
        trace = list(m.trace)
    got = [(o.name, o.value, o.line) for o in result.outputs if o.kind == "function"]
    assert got == expected()
    at = {(o.name, o.value): o.cycle for o in result.outputs if o.kind == "function"}
    z_of = {c: pos[2] for c, _t, pos, _ev in trace}
    x_of = {c: pos[0] for c, _t, pos, _ev in trace}
    top = z_of[at[("probe", 1.0)]]  # #5063: the commanded Z of the cycle that saw the trip
    assert abs(top - surface) < 0.5, (top, surface)  # within a poll or so of travel at F300
    during = [c for c in z_of if at[("coolant_mist", 1.0)] <= c <= at[("coolant_mist", 0.0)]]
    tap = [z_of[c] for c in during if abs(x_of[c] - x_of[during[0]]) < 1e-9]
    thread = [z_of[c] for c in during if abs(x_of[c] - x_of[during[-1]]) < 1e-9]
    assert x_of[during[0]] != x_of[during[-1]]  # the thread is cut elsewhere
    # the tap goes as deep as the spindle overshoots while it reverses (docs/planner.md): by the
    # revolutions it turns stopping at the slower of its ramp and its inertia, times the pitch
    sp = tomllib.loads(config.read_text())["canopen"]["spindle"]
    rps = number(r"M3 S(\d+)") / 60.0
    decel = min(sp["acceleration"], sp["sim_acceleration"]) / 60.0
    overshoot = number(r"G33\.1 .*K([\d.]+)") * rps * rps / (2.0 * decel)
    bottom = top - depth["G33.1"]
    assert bottom - overshoot - 0.1 <= min(tap) <= bottom + 1e-6, (min(tap), bottom, overshoot)
    assert abs(min(thread) - (top - depth["G33"])) < 0.05, (min(thread), top)
