"""``canon plan``: summary, JSON, CSV of the stream, plot; errors as one line with exit status 1."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from motiond import cli

PROGRAM = """%
G21 G17 G90 G94 G64 P0.01
G0 Z50
G0 X10 Y10
G0 Z1
G1 Z-1 F300
G1 X30 F1200
G3 X40 Y20 I0 J10
G1 Y30
G4 P0.1
G1 X10
G0 Z5
M2
%
"""


@pytest.fixture
def program(tmp_path: Path) -> Path:
    path = tmp_path / "part.ngc"
    path.write_text(PROGRAM)
    return path


def run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = cli.main(["plan", *argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_json_summary(capsys: pytest.CaptureFixture[str], program: Path) -> None:
    code, out, err = run(capsys, "--json", str(program))
    assert code == 0, err
    summary = json.loads(out)
    assert summary["cycle_s"] == 0.002
    assert set(summary["limits"]) == {"x", "y", "z"} == set(summary["peaks"])
    assert summary["limits"]["x"] == {"velocity": 200.0, "acceleration": 2000.0, "jerk": 50000.0}
    for ax in "xyz":
        for key in ("velocity", "acceleration", "jerk"):
            assert 0 < summary["peaks"][ax][key] <= summary["limits"][ax][key] * 1.01
    # the rapids up to Z50 and down to Z1 run Z at its limit; the feeds are slower
    assert summary["peaks"]["z"]["velocity"] == pytest.approx(100.0, rel=0.02)
    # a lower bound on the time: the feed moves at their feed, the rapids at the axis maxima
    assert summary["duration_s"] > 98 / 100 + 2 / 5 + (20 + 15.7 + 10 + 30) / 20 + 0.1
    assert summary["max_deviation"] < 0.01 and summary["deviation_ok"]
    assert summary["ok"] and not summary["exact_stops_missed"]
    assert summary["final_position"] == {"x": 10.0, "y": 30.0, "z": 5.0}


def test_text_summary(capsys: pytest.CaptureFixture[str], program: Path) -> None:
    code, out, err = run(capsys, str(program))
    assert code == 0, err
    assert "cycle time" in out and "2 ms" in out
    assert "all checks pass" in out
    for word in ("velocity", "acceleration", "jerk", "X", "Y", "Z"):
        assert word in out


def test_setpoints_csv_and_plot(capsys: pytest.CaptureFixture[str], program: Path, tmp_path: Path) -> None:
    csv_path = tmp_path / "out.csv"
    png_path = tmp_path / "out.png"
    code, out, err = run(capsys, "--json", "--setpoints", str(csv_path), "--plot", str(png_path),
                         str(program))
    assert code == 0, err
    summary = json.loads(out)
    with csv_path.open() as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["t", "file", "line", "x", "y", "z", "vx", "vy", "vz"]
    assert len(rows) - 1 == summary["cycles"]
    assert float(rows[1][0]) == pytest.approx(0.002)
    assert [float(v) for v in rows[-1][3:6]] == [10.0, 30.0, 5.0]
    assert rows[-1][1:3] == [str(program), "13"]  # the last move, G0 Z5
    assert float(rows[-1][0]) == pytest.approx(summary["duration_s"])
    data = png_path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20000
    assert not list(tmp_path.glob(".plot.*"))


def test_config_changes_the_machine(capsys: pytest.CaptureFixture[str], program: Path,
                                    tmp_path: Path) -> None:
    machine = tmp_path / "m.toml"
    axes = "".join(f"[axes.{a}]\nmax_velocity = 50.0\nmax_acceleration = 500.0\nmax_jerk = 5000.0\n"
                   for a in "xyz")
    machine.write_text(f'[machine]\nname = "slow"\ncycle_ms = 4\n{axes}')
    code, out, err = run(capsys, "--json", "--config", str(machine), str(program))
    assert code == 0, err
    summary = json.loads(out)
    assert summary["cycle_s"] == 0.004 and summary["machine"] == "slow"
    assert summary["peaks"]["z"]["velocity"] == pytest.approx(50.0, rel=0.02)
    assert summary["peaks"]["x"]["jerk"] <= 5000 * 1.01


def test_user_errors_are_one_line(capsys: pytest.CaptureFixture[str], program: Path, tmp_path: Path) -> None:
    code, _, err = run(capsys, str(tmp_path / "missing.ngc"))
    assert code == 1 and "no such file" in err and "Traceback" not in err
    bad = tmp_path / "bad.toml"
    bad.write_text("[axes.x]\nmax_velocity = -1\nmax_acceleration = 1\nmax_jerk = 1\n")
    code, _, err = run(capsys, "--config", str(bad), str(program))
    assert code == 1 and err.strip() == f"{bad}: axes.x.max_velocity: must be > 0, got -1.0"
    nofeed = tmp_path / "nofeed.ngc"
    nofeed.write_text("G21 G90 G94\nG1 X5\nM2\n")
    code, _out, err = run(capsys, str(nofeed))
    assert code == 1 and err.strip().startswith(f"{nofeed}:2: ")


@pytest.mark.parametrize("name", ["pocket.ngc", "bolt_circle.ngc"])
def test_example_programs_pass_every_check(capsys: pytest.CaptureFixture[str], name: str) -> None:
    path = Path(__file__).resolve().parent.parent / "examples" / name
    if not path.is_file():
        pytest.skip(f"examples/{name} is not in this tree")
    code, out, err = run(capsys, "--json", str(path))
    assert code == 0, err
    summary = json.loads(out)
    assert summary["ok"] and summary["within_limits"] and summary["deviation_ok"]
