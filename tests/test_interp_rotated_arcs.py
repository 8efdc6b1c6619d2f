"""G2/G3 in G18/G19 while the coordinate system is rotated (G10 L2 R): LinuxCNC's ARC_FEED turns the
arc's plane with the rotation (emccanon.cc: the plane's axes and normal go through ``to_rotated``).
canon's ArcFeed carries the turn (``rotation``), and the planner, its checker and the plot follow
the turned plane. Against rs274 where it is built."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from gcode_canon.commands import (
    ArcFeed,
    MotionControlMode,
    Plane,
    Pose,
    ProgramEnd,
    SetFeedRate,
    SetMotionControlMode,
    rotate_about_z,
)
from planner import DEMO_MACHINE, check_stream, plan_all
from tests import rs274_oracle as oracle
from tests.test_interp_helpers import run


def _arcs(text: str) -> list[ArcFeed]:
    return [c for c in run(text) if isinstance(c, ArcFeed)]


def test_g18_arc_in_a_rotated_system_is_the_axis_plane_arc_turned_about_z() -> None:
    rot = "G21 G10 L2 P1 X1 Y2 R30\nG54 G0 X10 Y5 Z0\nF100\n"
    cmds = run(rot + "G18 G2 X20 Z0 I5 K0")
    (arc,) = [c for c in cmds if isinstance(c, ArcFeed)]
    start = [c for c in cmds if c.MOVES][-2].end
    (flat,) = _arcs("G21 G0 X10 Y5 Z0\nF100\nG18 G2 X20 Z0 I5 K0")  # the same arc unrotated
    assert arc.plane is Plane.XZ and arc.rotation == 30.0 and arc.turns == -1
    # machine = rotate(program) + G5x: the unrotated arc's end and centre turned by 30 degrees
    for got, want in ((arc.end, flat.end), (arc.center, flat.center)):
        turned = rotate_about_z(want, 30.0)
        assert got[:3] == pytest.approx((turned.x + 1, turned.y + 2, turned.z))
    # turned back about Z, start, end and centre share their Y (the normal), as in an XZ arc
    ys = [p.y for p in arc.unrotated(start)]
    assert ys == pytest.approx([ys[0]] * 3)
    assert rotate_about_z(start, -30.0).y != pytest.approx(start.y)
    # G19 turns too; G17 keeps the XY plane whatever the rotation (no turn)
    (yz,) = _arcs(rot + "G19 G3 Y9 Z4 J2 K2")
    (xy,) = _arcs(rot + "G17 G3 X12 Y7 I1 J1")
    assert (yz.plane, yz.rotation, xy.rotation) == (Plane.YZ, 30.0, 0.0)


def test_helix_and_spline_in_a_rotated_g18_are_accepted() -> None:
    helix = _arcs("G10 L2 P1 R-20\nG0 X10 Y5 Z0\nF100\nG18 G3 X14 Z-5 Y7 R5")
    assert helix[0].rotation == -20.0
    spline = _arcs("G10 L2 P1 R15\nF100\nG18 G5.1 X4 Z2 I1 J2")
    assert spline and all(a.rotation == 15.0 for a in spline)


def _turned_arc_program() -> list:
    # in the frame turned back: the XZ half circle from machine zero over centre Z5 to Z10, ccw
    return [SetMotionControlMode(MotionControlMode.EXACT_PATH), SetFeedRate(2000, line=1),
            ArcFeed(Pose(0, 0, 10), Pose(0, 0, 5), Plane.XZ, 1, 30.0, line=2),
            ArcFeed(Pose(*rotate_about_z(Pose(3, 0, 13), 30.0)), Pose(0, 0, 13), Plane.XZ, -1, 30.0, line=3),
            ProgramEnd(line=4)]


def test_planner_follows_the_turned_plane_and_the_checker_measures_it() -> None:
    prog = _turned_arc_program()
    sps = list(plan_all(prog, DEMO_MACHINE, max_cycles=1_000_000))
    report = check_stream(sps, prog, DEMO_MACHINE)
    assert report.ok, report.problems()
    assert report.max_deviation < 1e-3
    pts = np.array([s.positions for s in sps])[:, :3]
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    # every point in the vertical plane through Z turned 30 degrees from XZ ...
    assert np.abs(-s * pts[:, 0] + c * pts[:, 1]).max() < 1e-9
    # ... on the half circle of radius 5 about Z5 there (up to the blend at the join)
    first = pts[pts[:, 2] < 9.0]
    r = np.hypot(first[:, 0] * c + first[:, 1] * s, first[:, 2] - 5.0)
    assert np.abs(r - 5.0).max() < 1e-3
    assert (first[:, 0] * c + first[:, 1] * s).min() < -4.99  # ccw from +Z: through -X (turned)
    # the same stream against the arc left unturned is far off its path
    flat = [p if not isinstance(p, ArcFeed) else ArcFeed(p.end, p.center, p.plane, p.turns, line=p.line)
            for p in prog]
    assert check_stream(sps, flat, DEMO_MACHINE).max_deviation > 1.0


def test_plot_draws_the_turned_arc() -> None:
    from motiond.plan_plot import programmed_pieces

    (first, _second) = programmed_pieces(_turned_arc_program(), DEMO_MACHINE)
    pts = first.points[:, :3]
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    assert np.abs(-s * pts[:, 0] + c * pts[:, 1]).max() < 1e-9
    assert np.hypot(pts[:, 0] * c + pts[:, 1] * s, pts[:, 2] - 5.0) == pytest.approx(5.0)


BINARY = oracle.rs274_binary()


@pytest.mark.rs274
@pytest.mark.skipif(BINARY is None, reason=f"rs274 is not built in {oracle.rs274_dir()}")
@pytest.mark.parametrize("program", [
    "G21 G10 L2 P1 X1 Y2 R30\nG54 G18 G0 X10 Y5 Z0\nG2 X20 Z0 I5 K0 F100\nG3 X20 Z-5 Y7 R5"
    "\nG19 G3 Y10 Z0 R4\nG17 G2 X0 Y0 R20\nM2",
    "G20 G10 L2 P2 X0.5 R-65\nG55 G19 G0 Y1 Z1\nG91 G2 Y1 Z1 J0.5 K0.5 X0.3 P2 F10\nG90 G18 G3 X2 Z0 R3"
    "\nG5.1 X3 Z1 I0.5 J0.5\nM2",
    "G21 G10 L2 P1 R45\nT1 M6 G43\nG18 G0 X5 Y0 Z0\nG41 D1\nG1 X10 F100\nG2 X20 Z0 I5\nG1 X25"
    "\nG40 G1 X30\nM2",
])
def test_against_rs274(program: str, tmp_path: Path) -> None:
    assert BINARY is not None
    theirs, ours = oracle.run_program(program, tmp_path, BINARY)
    assert theirs.error is None
    assert oracle.compare(theirs, ours) is None
    assert any(m.kind == "arc" for m in ours.moves)
