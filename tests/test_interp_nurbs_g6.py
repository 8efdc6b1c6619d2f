"""G6.2 (Lo Valvo's NURBS, LinuxCNC's convert_nurbs and canon's NURBS_G6_FEED): the words, checks and
messages of LinuxCNC's interpreter, the curve from the control points, weights R and knots K, moved
along as LinuxCNC's Q1 interpolation does. The curves are checked against their definitions here
(a rational quarter circle, a cubic Bezier); rs274, which prints no points for G6.2, checks what it
accepts and where the tool goes after each curve (LinuxCNC's nc_files/nurbs/G6)."""

from __future__ import annotations

import math
import random
from pathlib import Path

import pytest

from gcode_canon import splines
from gcode_canon.commands import ArcFeed, StraightFeed
from tests import rs274_oracle as oracle
from tests.test_interp_helpers import error, run


def _moves(text: str) -> list:
    return [c for c in run(text, tool_table=None) if isinstance(c, (StraightFeed, ArcFeed))]


W45 = math.cos(math.pi / 4)
QUARTER = f"G21 F100\nG6.2 X10 Y0 R1 K0 P3 Q1\nX10 Y10 R{W45:.12f} K0\nX0 Y10 R1 K0\n" + "G6.2 K1\n" * 3


def test_g6_2_rational_quarter_circle_is_arcs_on_that_circle() -> None:
    moves = _moves(QUARTER)
    assert isinstance(moves[0], StraightFeed) and moves[0].end[:2] == pytest.approx((10.0, 0.0))
    assert moves[-1].end[:2] == pytest.approx((0.0, 10.0))
    arcs = [m for m in moves if isinstance(m, ArcFeed)]
    assert len(arcs) >= 10  # 15 x 3 samples of the parameter, each a biarc
    for m in moves:
        assert math.hypot(m.end[0], m.end[1]) == pytest.approx(10.0, abs=1e-6)
    for a in arcs:  # a biarc between points of a circle with its tangents is that circle
        # (the tangents are LinuxCNC's central differences: a short arc's centre moves a little)
        assert a.center[:2] == pytest.approx((0.0, 0.0), abs=2e-2) and a.turns == 1


def test_g6_2_clamped_order_4_is_the_cubic_bezier() -> None:
    pts = [(0.0, 0.0), (2.0, 6.0), (8.0, 6.0), (10.0, 0.0)]
    text = "G21 F100\nG0 X-1 Y-1\nG6.2 X0 Y0 R1 K0 P4 Q2\nX2 Y6 R1 K0\nX8 Y6 R1 K0\nX10 Y0 R1 K0\n" + \
        "G6.2 K1\n" * 4
    moves = _moves(text)
    bezier = [tuple(sum(math.comb(3, i) * t ** i * (1 - t) ** (3 - i) * p[c] for i, p in enumerate(pts))
                    for c in range(2)) for t in (j / 2000 for j in range(2001))]
    assert moves[0].end[:2] == pytest.approx((0.0, 0.0))  # from X-1 Y-1 straight to the curve's start
    for m in moves:
        assert min(math.dist(m.end[:2], b) for b in bezier) < 5e-3


def test_g6_2_in_g18_takes_x_and_z_and_the_line_after_it_starts_where_linuxcnc_says() -> None:
    text = ("G18 G21 F100\nG0 X1 Y3 Z1\nG6.2 X10 Z0 R1 K0 P3 Q3\nX10 Z10 R0.7071 K0\nX0 Z10 R1 K0\n"
            "G6.2 K1\nG6.2 K1\nG6.2 K1\nG1 Y5")
    moves = _moves(text)
    assert all(m.end[1] == pytest.approx(3.0) for m in moves[:-1])  # in the XZ plane
    # LinuxCNC's current point after the curve: the last line's point (a K line: where the tool was)
    assert moves[-1].end[:3] == pytest.approx((1.0, 5.0, 1.0))


def test_point_local_is_the_global_evaluation() -> None:
    r = random.Random(3)
    for _ in range(20):
        k = r.randint(2, 5)
        cps = [(r.uniform(-9, 9), r.uniform(-9, 9), r.uniform(0.2, 3)) for _ in range(r.randint(k, k + 4))]
        inner = sorted(r.sample((1.0, 2.0, 3.0, 3.5), len(cps) - k))  # distinct: a continuous curve
        kv = [0.0] * k + inner + [4.0] * k
        for u in (0.0, 0.7, 1.5, 2.2, 3.9, 4.0):
            assert splines.point_local(u, k, cps, kv) == pytest.approx(splines.point(u, k, cps, kv))


@pytest.mark.parametrize(("text", "message"), [
    ("F100\nG6.2 X1 Y1 R1 K0 Q1", "Program the nurbs order P in the first block"),
    ("F100\nG6.2 X1 Y1 R1 K0 P3", "Program the nurbs Q value (1,2,3)"),
    ("F100\nG6.2 X1 Y1 R1 K0 P3 Q4", "nurbs Q value not in range 1 to 3"),
    ("F100\nG6.2 X1 Y1 R1 K0 P3.5 Q1", "nurbs order P number is not an integer"),
    ("F100\nG6.2 X1 Y1 R1 K0.5 P3 Q1", "nurbs K number is not an integer"),
    ("F100\nG6.2 X1 Y1 R1 K0 P3 Q1\nX2 Y2 R0 K0", "Must specify positive nurbs weight R"),
    ("F100\nG6.2 X1 Y1 R1 K0 P3 Q1\nX2 R1 K0", "You must specify both X and Y coordinates"),
    ("G6.2 X1 Y1 R1 K0 P3 Q1", "Cannot make a nurbs with 0 feedrate"),
    ("F100\nG6.2 X1 Y1 R1 K2 P2 Q1\nX2 Y2 R1 K1\nG6.2 K0\nG6.2 K0", "knots K must not decrease"),
    ("F100\nG6.2 X1 Y1 R1 K0 P2 Q1\nX2 Y2 R1 K1\nG6.2 K2\nG6.2 K2", "must start with 2 equal values"),
])
def test_refusals(text: str, message: str) -> None:
    assert message in str(error(text, tool_table=None))


# --- against LinuxCNC's rs274 ---------------------------------------------------------------------

BINARY = oracle.rs274_binary()


@pytest.mark.rs274
@pytest.mark.skipif(BINARY is None, reason=f"rs274 is not built in {oracle.rs274_dir()}")
@pytest.mark.parametrize("name", ["Curva_Stella #1=1.ngc", "Curva_Mazatrol #1=2-xy-yz-zx.ngc",
                                  "homer #1=1.ngc", "Ruota_dentata #1=2.ngc"])
def test_linuxcnc_g6_programs(name: str) -> None:
    assert BINARY is not None
    theirs, ours = oracle.run_both(oracle.nc_file_case(f"nurbs/G6/{name}"), BINARY)
    assert oracle.compare(theirs, ours) is None
    assert sum(m.kind == "nurbs" for m in theirs.moves) == sum(m.kind == "nurbs" for m in ours.moves) >= 1


@pytest.mark.rs274
@pytest.mark.skipif(BINARY is None, reason=f"rs274 is not built in {oracle.rs274_dir()}")
@pytest.mark.parametrize("program", [
    QUARTER + "G1 X3\nG91 G1 Y1\nM2",
    "G20 F10\nG0 X1 Y1\nG6.2 X1 Y1 R1 K0 P2 Q3\nX2 Y0 R2 K0\nX3 Y1 R1 K1\nG6.2 K2\nG6.2 K2\nG91 G1 X1\nM2",
    "G21 F100\nG6.2 X1 Y1 R1 K0 P3\nM2",
    "G21 F100\nG6.2 X1 Y1 R1 K0 P3 Q1\nX2 Y2 R-1 K0\nM2",
])
def test_against_rs274(program: str, tmp_path: Path) -> None:
    assert BINARY is not None
    theirs, ours = oracle.run_program(program, tmp_path, BINARY)
    assert oracle.compare(theirs, ours) is None
