"""``canon plan --plot`` and ``--setpoints``: the figure's data (programmed path under the planned one,
top view at equal scale, units, distinguishable limits, the worst deviation with its source line) and
the CSV's source lines and velocities."""

from __future__ import annotations

import csv
import math
from array import array
from pathlib import Path

import numpy as np
import pytest

from gcode_canon import Interpreter, InterpreterSettings
from motiond import cli
from motiond.plan_plot import build_figure
from planner import DEMO_MACHINE, check_stream, plan_all

# a 40 x 30 rectangle at 6000 mm/min in G64 P0.5: the corners are rounded by up to 0.5 mm
SQUARE = """%
G21 G90 G94 G64 P0.5
G0 Z1
G1 Z0 F6000
G1 X40
G1 Y30
G1 X0
G1 Y0
M2
%
"""
CORNERS = [(40.0, 0.0), (40.0, 30.0), (0.0, 30.0)]


@pytest.fixture
def square(tmp_path: Path) -> Path:
    p = tmp_path / "square.ngc"
    p.write_text(SQUARE)
    return p


def figure_for(path: Path):  # type: ignore[no-untyped-def]
    commands = list(Interpreter(InterpreterSettings(dry_run=True)).run_file(path))
    flat = array("d")
    src = []
    for sp in plan_all(commands, DEMO_MACHINE):
        flat.extend(sp.positions)
        src.append((sp.file, sp.line))
    pts = np.frombuffer(flat).reshape(-1, 3)
    report = check_stream(pts, commands, DEMO_MACHINE)
    return build_figure(str(path), DEMO_MACHINE, pts, src, commands, report), pts, report


def test_figure_shows_the_programmed_path_the_top_view_and_the_worst_deviation(square: Path) -> None:
    import matplotlib.pyplot as plt

    fig, pts, report = figure_for(square)
    try:
        (top,) = [a for a in fig.axes if a.get_title().startswith("top view XY")]
        assert top.get_aspect() == 1.0  # equal scaling
        assert top.get_xlabel() == "X (mm)" and top.get_ylabel() == "Y (mm)"
        programmed = [ln for ln in top.get_lines() if ln.get_gid() == "programmed"]
        vertices = {(float(x), float(y)) for ln in programmed for x, y in ln.get_xydata()}
        for corner in CORNERS:  # the sharp corners as programmed, which the planned path rounds
            assert corner in vertices
            assert min(math.dist(corner, p[:2]) for p in pts) > 0.1
        (planned,) = [c for c in top.collections if c.get_gid() == "planned"]
        assert len(planned.get_offsets()) == len(pts)
        assert planned.get_zorder() > max(ln.get_zorder() for ln in programmed)  # drawn over it
        (worst,) = [c for c in top.collections if c.get_gid() == "worst"]
        wx, wy = worst.get_offsets()[0]
        near = min(range(3), key=lambda i: math.dist(CORNERS[i], (wx, wy)))
        assert math.dist(CORNERS[near], (wx, wy)) < 0.6  # at a rounded corner
        (label,) = [t for t in top.texts if t.get_gid() == "worst-label"]
        value = float(label.get_text().split()[2])
        assert value == pytest.approx(report.max_deviation, rel=0.05) and 0.1 < value <= 0.5 + 1e-6
        line = int(label.get_text().split("line ")[1])
        assert line in (5, 6, 7, 8)  # a setpoint of one of the two moves meeting at that corner
        assert any(a.name == "3d" for a in fig.axes)
        (vel,) = [a for a in fig.axes if a.get_ylabel().startswith("velocity")]
        assert vel.get_ylabel() == "velocity (mm/s)"
        limits = [ln for ln in vel.get_lines() if ln.get_gid() == "limit-velocity"]
        labels = {ln.get_label() for ln in limits if not ln.get_label().startswith("_")}
        assert labels == {"limit X Y ±200 mm/s", "limit Z ±100 mm/s"}  # X and Y share one line
        styles = {ln.get_label(): ln.get_linestyle() for ln in limits if not ln.get_label().startswith("_")}
        assert len(set(styles.values())) == 2
    finally:
        plt.close(fig)


def test_csv_has_source_lines_and_velocities(square: Path, tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "sp.csv"
    assert cli.main(["plan", "--json", "--setpoints", str(out), str(square)]) == 0
    capsys.readouterr()
    with out.open() as fh:
        rows = list(csv.DictReader(fh))
    assert {r["file"] for r in rows} == {str(square)}
    lines = [int(r["line"]) for r in rows]
    assert lines == sorted(lines) and set(lines) >= {3, 4, 5, 6, 7, 8}
    xs = np.array([float(r["x"]) for r in rows])
    vx = np.array([float(r["vx"]) for r in rows])
    assert vx[1:] == pytest.approx(np.diff(xs) / 0.002, abs=1e-3)
    cruising = [float(r["vx"]) for r in rows if r["line"] == "5" and 10 < float(r["x"]) < 30]
    assert cruising and max(cruising) == pytest.approx(100.0, rel=1e-3)  # F6000 = 100 mm/s along X


def test_html_figure_hover_gives_time_line_and_speed(square: Path, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    from motiond.plan_plot import build_html_figure

    commands = list(Interpreter(InterpreterSettings(dry_run=True)).run_file(square))
    flat = array("d")
    src = []
    for sp in plan_all(commands, DEMO_MACHINE):
        flat.extend(sp.positions)
        src.append((sp.file, sp.line))
    pts = np.frombuffer(flat).reshape(-1, 3)
    report = check_stream(pts, commands, DEMO_MACHINE)
    fig = build_html_figure(str(square), DEMO_MACHINE, pts, src, commands, report)
    traces = {t.name: t for t in fig.data}
    programmed = traces["programmed"]
    xy = {(x, y) for x, y in zip(programmed.x, programmed.y, strict=True) if x is not None}
    assert set(CORNERS) <= xy
    planned = traces["planned"]
    assert len(planned.x) == len(pts)  # a short program: every setpoint
    assert "line %{text}" in planned.hovertemplate and "speed" in planned.hovertemplate
    assert list(planned.text) == [str(line) for _f, line in src]
    t, speed = planned.customdata[:, 0], planned.customdata[:, 1]
    assert t[0] == pytest.approx(0.002) and max(speed) == pytest.approx(100.0, rel=1e-3)
    assert fig.layout.scene.aspectmode == "data"  # equal scaling
    out = tmp_path / "p.html"
    assert cli.main(["plan", "--json", "--html", str(out), str(square)]) == 0
    capsys.readouterr()
    text = out.read_text()
    assert "<html>" in text and "plotly" in text and "https://cdn" not in text.split("<body>")[0]
