"""``canon run FILE.ngc`` on the built-in demo machine (and on examples/canon.toml), as a process.

Runs use ``--no-telemetry`` or ``memq://`` so that nothing joins a multicast group; one test runs on
the default URL inside the private network namespace (``multicast``), one in a namespace with no
multicast route (the fallback). The example part programs take 40 to 80 s of machine time each and
are marked ``slow``.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from motiond.config import load_machine
from planner import DEMO_MACHINE, plan_all

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = ROOT / "examples"

SHORT = """%
G21 G90 G94 G64 P0.01
G0 Z5
G0 X10 Y5
M62 P0
G1 Z-1 F600
G1 X20 Y15 F1200
G2 X30 Y5 I5 J-5
M63 P0
M67 E1 Q12.5
G0 Z5
M65 P1
G0 X12.5 Y7.25 Z3
M2
%
"""


def canon(*args: str, timeout: float = 120.0, cwd: Path | None = None,
          prefix: tuple[str, ...] = ()) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*prefix, sys.executable, "-m", "motiond.cli", *args], capture_output=True,
                          text=True, timeout=timeout, cwd=cwd or ROOT)


def expected_final(program: Path) -> tuple[float, ...]:
    """Where the program ends, from the interpreter and planner without a machine (canon plan's way)."""
    from gcode_canon import Interpreter, InterpreterSettings

    interp = Interpreter(InterpreterSettings(dry_run=True))
    last = None
    for sp in plan_all(interp.run_file(program), DEMO_MACHINE):
        last = sp
    assert last is not None
    return last.positions


@pytest.fixture
def short(tmp_path: Path) -> Path:
    p = tmp_path / "short.ngc"
    p.write_text(SHORT)
    return p


def test_json_summary_positions_peaks_outputs(short: Path) -> None:
    r = canon("run", "--json", "--no-telemetry", str(short))
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    assert d["ok"] and d["program"] == str(short)
    assert d["motion_process"] == "thread"  # the demo machine: "auto" keeps its Modbus I/O beside the motion
    assert tuple(d["final_positions"][a] for a in "xyz") == (12.5, 7.25, 3.0)  # the last G0 of SHORT
    for a in "xyz":
        assert d["final_actual"][a] == pytest.approx(d["final_positions"][a], abs=1e-3)
        axis = d["axes"][a]
        assert 0 < axis["peak_velocity"] <= axis["max_velocity"] * 1.01
        assert 0 < axis["peak_acceleration"] <= axis["max_acceleration"] * 1.01
        assert 0 < axis["peak_jerk"] <= axis["max_jerk"] * 1.01
        assert 0 < d["following_error_max"][a] < 1.0  # the drives' window is 1 mm
    assert d["cycle_s"] > 1.0 and d["duration_s"] >= d["cycle_s"] * 0.9
    outs = [(o["kind"], o["index"], o["value"], o["synced"], o["line"]) for o in d["outputs_switched"]]
    # M65 is immediate: performed when the planner takes it in, ahead of the motion before it
    assert ("digital", 1, 0.0, False, 12) in outs
    synced = [o for o in outs if o[3]]
    assert synced == [("digital", 0, 1.0, True, 5), ("digital", 0, 0.0, True, 9),
                      ("analog", 1, 12.5, True, 10)]
    cycles = {(o["index"], o["line"]): o["cycle"] for o in d["outputs_switched"]}
    assert cycles[(0, 5)] < cycles[(0, 9)] <= cycles[(1, 10)]


def test_table_summary(short: Path) -> None:
    r = canon("run", "--url", "memq://", str(short))
    assert r.returncode == 0, r.stderr
    out = r.stdout
    assert "short.ngc" in out and "outputs switched: 4" in out
    assert "motion side in a thread of this process" in " ".join(out.split())  # rich wraps long lines
    for row in ("X mm", "Y mm", "Z mm"):
        assert row in out
    assert "12.5000" in out and "7.2500" in out


def test_gcode_error_exits_1_with_file_and_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.ngc"
    bad.write_text("%\nG0 X5\nG1 X10\nM2\n%\n")
    r = canon("run", "--no-telemetry", str(bad))
    assert r.returncode == 1
    assert r.stderr.strip().splitlines()[-1] == f"{bad}:3: Cannot do G1 with zero feed rate"
    assert "Traceback" not in r.stderr


def test_missing_file_and_bad_config(tmp_path: Path) -> None:
    r = canon("run", "--no-telemetry", str(tmp_path / "none.ngc"))
    assert r.returncode == 1 and "no such file" in r.stderr and "Traceback" not in r.stderr
    cfg = tmp_path / "m.toml"
    cfg.write_text((EXAMPLES / "canon.toml").read_text().replace("max_jerk = 50000.0", "max_jerk = -1.0", 1))
    prog = tmp_path / "p.ngc"
    prog.write_text(SHORT)
    r = canon("run", "--no-telemetry", "--config", str(cfg), str(prog))
    assert r.returncode == 1 and "Traceback" not in r.stderr
    assert f"{cfg}: axes.x.max_jerk: must be > 0" in r.stderr


def test_example_config_loads_and_runs(short: Path, tmp_path: Path) -> None:
    config = load_machine(str(EXAMPLES / "canon.toml"))
    assert config.limits.names == ("x", "y", "z")
    from motiond.config_canopen import canopen_for_machine
    from motiond.config_modbus import modbus_for
    from telemetry.config import TelemetryConfig

    can = canopen_for_machine(config)
    assert can.simulate and [d.node_id for d in can.drives] == [1, 2, 3]
    assert modbus_for(config) is not None
    assert TelemetryConfig.from_table(config.telemetry).status_hz == 50
    # the simulated module of the example listens on 5020: run on a copy with a free port
    text = (EXAMPLES / "canon.toml").read_text().replace("port = 5020", f"port = {_free_port()}")
    cfg = tmp_path / "canon.toml"
    cfg.write_text(text)
    short.write_text(SHORT.replace("M67 E1", "M67 E0"))  # the example maps analog output 0 only
    r = canon("run", "--json", "--no-telemetry", "--config", str(cfg), str(short))
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    assert d["machine"] == "example mill" and d["motion_process"] == "thread"
    assert d["final_positions"] == {"x": 12.5, "y": 7.25, "z": 3.0}


def test_parameters_written_with_var(tmp_path: Path) -> None:
    prog = tmp_path / "g10.ngc"
    prog.write_text("%\nG10 L2 P1 X3.25\nG0 X0\nM2\n%\n")
    var = tmp_path / "p.var"
    r = canon("run", "--no-telemetry", "--var", str(var), str(prog))
    assert r.returncode == 0, r.stderr
    values = dict(line.split() for line in var.read_text().splitlines() if line.strip())
    assert float(values["5221"]) == 3.25


def test_no_multicast_route_falls_back_with_one_warning(short: Path) -> None:
    if os.geteuid() != 0 or shutil.which("unshare") is None or shutil.which("ip") is None:
        pytest.skip("needs root and unshare/ip to make a network namespace without a multicast route")
    # a namespace with loopback up and no route at all: LCM's udpm cannot work, canon run carries on
    script = f"ip link set lo up && exec {sys.executable} -m motiond.cli run --json {short}"
    r = subprocess.run(["unshare", "--net", "sh", "-c", script], capture_output=True, text=True, timeout=120,
                       cwd=ROOT)
    assert r.returncode == 0, r.stderr
    warnings = [line for line in r.stderr.splitlines() if "WARNING" in line]
    assert len(warnings) == 1 and "ip route add 224.0.0.0/4 dev lo" in warnings[0]
    assert "memq" in warnings[0]
    assert json.loads(r.stdout)["ok"]


@pytest.mark.multicast
def test_default_url_inside_the_namespace(short: Path) -> None:
    r = canon("run", "--json", str(short))
    assert r.returncode == 0, r.stderr
    assert "WARNING" not in r.stderr
    assert json.loads(r.stdout)["final_positions"] == {"x": 12.5, "y": 7.25, "z": 3.0}


@pytest.mark.slow
@pytest.mark.parametrize("name", ["pocket.ngc", "drill_pattern.ngc", "surface.ngc"])
def test_example_programs(name: str) -> None:
    program = EXAMPLES / name
    r = canon("run", "--json", "--no-telemetry", str(program), timeout=300)
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    want = expected_final(program)
    assert tuple(d["final_positions"][a] for a in "xyz") == pytest.approx(want, abs=1e-9)
    for a in "xyz":
        assert d["final_actual"][a] == pytest.approx(want["xyz".index(a)], abs=1e-3)
    if name == "drill_pattern.ngc":  # the coolant valve: M62 P0 on, M63 P0 off, both synchronized
        outs = [(o["index"], o["value"], o["synced"]) for o in d["outputs_switched"]
                if o["kind"] != "function"]  # the I/O map's spindle and coolant are listed too
        assert outs == [(0, 1.0, True), (0, 0.0, True)]


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
