"""G70, G71, G72 (LinuxCNC's lathe cycles, gcode_canon/lathe_cycles.py and lathe_profile.py).

The plain tests check what a roughing cycle must do, worked out from the profile here: layers I
apart, never into the finished part plus its allowance D, ending on the profile; the differential
test compares with rs274 on LinuxCNC's own programs (tests/interp g71-*, g72-*, nc_files lathe_g7x*)
and on programs written here."""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest

from gcode_canon.commands import ArcFeed, StraightFeed, StraightTraverse
from tests import rs274_oracle as oracle
from tests.test_interp_helpers import error, run

# a stepped shaft: radius 5 from Z0 to Z-10, radius 8 from Z-10 to Z-20, stock radius 10
PROFILE = "O100 SUB\nG1 X5 Z0\nZ-10\nX8\nZ-20\nX10\nO100 ENDSUB\n"


def _radius_at(z: float) -> float:
    return 5.0 if z > -10.0 else 8.0


def _moves(text: str) -> list:
    return [c for c in run(text) if isinstance(c, (StraightFeed, StraightTraverse, ArcFeed))]


def test_g71_cuts_layers_i_apart_and_leaves_d_on_the_profile() -> None:
    moves = _moves(f"G18 G21 F100\n{PROFILE}G0 X12 Z2\nG71 Q100 X10 Z1 D0.5 I1 R0.3")
    feeds = [m for m in moves if isinstance(m, StraightFeed)]
    assert feeds
    for m in feeds:  # no cut goes into the part plus its allowance
        x, z = m.end[0], m.end[2]
        if -20.0 < z < 0.0:
            assert x >= _radius_at(z) + 0.5 - 1e-6 or abs(x - (_radius_at(z) + 0.5)) < 1e-6, (x, z)
    # roughing layers along Z at X = 10 - k * I (from the start X down), I = 1
    levels = sorted({round(m.end[0], 6) for m in feeds if m.end[2] < -1.0 and m.end[0] < 10})
    assert {9.0, 8.0, 7.0, 6.0} <= set(levels)
    # the last pass runs along the profile offset by D (also along Z at the shoulder): radius 5.5 to
    # Z-9.5, a rounded corner, radius 8.5 to Z-19.5
    assert any(m.end[0] == pytest.approx(5.5) and m.end[2] == pytest.approx(-9.5) for m in feeds)
    assert any(m.end[0] == pytest.approx(8.5) and m.end[2] == pytest.approx(-19.5) for m in feeds)


def test_g71_1_cuts_no_pockets_and_g72_cuts_along_x() -> None:
    pocket = "O100 SUB\nG1 X5 Z0\nZ-5\nX3 Z-8\nZ-12\nX5 Z-15\nZ-20\nX10\nO100 ENDSUB\n"
    full = _moves(f"G18 G21 F100\n{pocket}G0 X12 Z2\nG71 Q100 X10 Z1 D0 I1 R0.3")
    outer = _moves(f"G18 G21 F100\n{pocket}G0 X12 Z2\nG71.1 Q100 X10 Z1 D0 I1 R0.3")
    pockets = _moves(f"G18 G21 F100\n{pocket}G0 X12 Z2\nG71.2 Q100 X10 Z1 D0 I1 R0.3")

    def in_pocket(moves: list) -> list:
        return [m for m in moves if -12.001 <= m.end[2] <= -7.999]

    # the pocket (radius 3 between Z-8 and Z-12) is cut by G71 and G71.2, not by G71.1; G71.2 cuts
    # less than G71 (only the pocket)
    assert min(m.end[0] for m in in_pocket(full)) == pytest.approx(3.0)
    assert min(m.end[0] for m in in_pocket(pockets)) == pytest.approx(3.0)
    assert not in_pocket(outer)
    assert len(pockets) < len(full)
    facing = _moves(f"G18 G21 F100\n{PROFILE}G0 X12 Z2\nG72 Q100 X10 Z1 D0 I1 R0.3")
    feeds = [m for m in facing if isinstance(m, StraightFeed)]
    # G72 faces: its layers are Z levels I apart, cut along X
    along_x = [(a, b) for a, b in itertools.pairwise(feeds)
               if abs(a.end[2] - b.end[2]) < 1e-9 and abs(a.end[0] - b.end[0]) > 1]
    assert len({round(a.end[2], 6) for a, _ in along_x}) >= 5


def test_g70_finishes_along_the_profile_in_p_passes() -> None:
    moves = _moves(f"G18 G21 F100\n{PROFILE}G0 X12 Z2\nG70 Q100 X10 Z1 D1 E0 P2")
    feeds = [m for m in moves if isinstance(m, StraightFeed)]
    # two passes from D1 to E0: (P - 1) x (D - E) / P + E = 0.5 mm off the profile, then on it
    assert any(m.end[0] == pytest.approx(5.5) and m.end[2] == pytest.approx(-9.5) for m in feeds)
    assert any(m.end[0] == pytest.approx(5.0) and m.end[2] == pytest.approx(-10.0) for m in feeds)
    assert feeds[-1].end[0] == pytest.approx(10.0) and feeds[-1].end[2] == pytest.approx(-20.0)


def test_g70_with_cutter_compensation_starts_its_pass_uncompensated_then_enters() -> None:
    """LinuxCNC's do_g70: the pass's first rapid with compensation switched off, to the pass start
    itself; the compensation's entry move from there; the profile then offset by the tool radius."""
    moves = _moves(f"G18 G21 F100\n{PROFILE}G0 X12 Z2\nG42.1 D0.4\nG70 Q100 X10 Z1 D0.5")
    traverses = [m for m in moves if isinstance(m, StraightTraverse)]
    assert traverses[1].end[:3] == pytest.approx((10.0, 0.0, 1.0))  # X10 Z1 exactly: no offset
    feeds = [m for m in moves if isinstance(m, StraightFeed)]
    # one pass (P1) on the profile (E0), the tool's centre 0.2 outside it: X5.2 and X8.2 along Z
    assert any(m.end[0] == pytest.approx(5.2) and m.end[2] == pytest.approx(-9.8) for m in feeds)
    assert any(m.end[0] == pytest.approx(8.2) and m.end[2] == pytest.approx(-19.8) for m in feeds)
    assert all(m.end[0] >= _radius_at(m.end[2]) + 0.2 - 1e-9 for m in feeds if -20 < m.end[2] < 0)


def test_the_profile_sub_runs_its_control_flow_and_sees_its_own_position() -> None:
    # #<_x> inside the profile is where the profile has got to (LinuxCNC moves its current point)
    prof = ("O100 SUB\nG1 X5 Z0\nO101 REPEAT [2]\nG1 Z[#<_z>-5]\nO101 ENDREPEAT\nX[#<_x>+5]\nO100 ENDSUB\n")
    moves = _moves(f"G18 G21 F100\n{prof}G0 X12 Z2\nG70 Q100 X12 Z1 P1")
    assert moves[-1].end[0] == pytest.approx(10.0) and moves[-1].end[2] == pytest.approx(-10.0)


@pytest.mark.parametrize(("text", "message"), [
    ("G18 F100\nG71 X10 Z1", "requires a Q word"),
    (f"G17 F100\n{PROFILE}G71 Q100 X10 Z1", "can only be used in XZ plane (G18)"),
    (f"G18 F100\n{PROFILE}G71 Q100 X10 Z1 I0", "I must be greater than zero"),
    ("G18 F100\nO100 SUB\nG91 G1 U1\nO100 ENDSUB\nG91 G71 Q100 X1 Z1", "Cannot use U in incremental mode"),
    ("G18 F100\nO100 SUB\nG1 X1 Z1 A1 C1\nO100 ENDSUB\nG71 Q100 X1 Z3", "Both A and C parameters"),
    (f"G18 F100\n{PROFILE}G71 Q100 X10 Z1 P2", "P word"),
    (f"G18 F100\n{PROFILE}G0 X12 Z2\nG42.1 D1\nG71 Q100 X10 Z1", "cannot be used with cutter compensation"),
    # LinuxCNC's second pass: its uncompensated rapid back to the start, then the compensated one
    (f"G18 F100\n{PROFILE}G0 X12 Z2\nG42.1 D0.4\nG70 Q100 X10 Z1 D0.5 P2",
     "Straight traverse in concave corner cannot be reached by the tool without gouging"),
])
def test_refusals(text: str, message: str) -> None:
    assert message in str(error(text))


BINARY = oracle.rs274_binary()


@pytest.mark.rs274
@pytest.mark.skipif(BINARY is None, reason=f"rs274 is not built in {oracle.rs274_dir()}")
@pytest.mark.parametrize("name", ["lathe_g70_71_demo.ngc", "lathe_g7x_face_boring.ngc",
                                  "lathe_g7x_quadrants.ngc"])
def test_linuxcnc_lathe_programs(name: str) -> None:
    assert BINARY is not None
    assert oracle.compare(*oracle.run_both(oracle.nc_file_case(name), BINARY)) is None


@pytest.mark.rs274
@pytest.mark.skipif(BINARY is None, reason=f"rs274 is not built in {oracle.rs274_dir()}")
@pytest.mark.parametrize("program", [
    f"G18 G21 F100\n{PROFILE}G0 X12 Z2\nG71 Q100 X10 Z1 D0.5 I1 R0.3\nG70 Q100 X10 Z1 D0.5 P2\nM2",
    "G18 G21 F100\nO100 SUB\nG1 X5 Z0\nZ-5\nX3 Z-8\nZ-12\nG2 X5 Z-15 R4\nG1 Z-20 A1\nX10\nO100 ENDSUB\n"
    "G0 X12 Z2\nG71 Q100 X10 Z1 D0.2 I0.7 R0.2\nG71.1 Q100 X10 Z1 D0 I1\nG71.2 Q100 X10 Z1 D0 I1\nM2",
    f"G18 G20 F4\n{PROFILE}G0 X12 Z2\nG72 Q100 X10 Z1 D0.02 I0.1 R0.01\nG72.1 Q100 X10 Z1 I0.2\nM2",
    f"G18 G21 F100\n{PROFILE}G0 X12 Z2\nG42.1 D0\nG70 Q100 X10 Z1 D0.5 P2\nG40\nG0 X15\nM2",
])
def test_against_rs274(program: str, tmp_path: Path) -> None:
    assert BINARY is not None
    theirs, ours = oracle.run_program(program, tmp_path, BINARY)
    assert oracle.compare(theirs, ours) is None
    assert len(theirs.moves) > 10


def _g70_comp_program(seed: int) -> str:
    """A random profile finished by G70 (1-3 passes) under G41.1/G42.1 of a random radius and lathe
    tool orientation, entered before the cycle or by its first compensated rapid."""
    import random

    r = random.Random(seed * 7 + 1)
    lines = _random_profile_program(seed).splitlines()
    k = next(n for n, line in enumerate(lines) if line.startswith("G7"))
    words = lines[k].split()
    lines[k] = "G70 " + " ".join(w for w in words[1:] if w[0] in "QXZD") + f" P{r.choice((1, 2, 3))}"
    side, dia, orient = r.choice(("G41.1", "G42.1")), r.choice((0.1, 0.4, 0.8)), r.choice((0, 2, 3))
    entry = f"\nG1 X{float(words[2][1:]) + 1:.3f} Z1.5" if r.random() < 0.5 else ""
    lines[k] = f"{side} D{dia} L{orient}{entry}\n{lines[k]}\nG40\nG0 X30"
    return "\n".join(lines)


@pytest.mark.rs274
@pytest.mark.skipif(BINARY is None, reason=f"rs274 is not built in {oracle.rs274_dir()}")
def test_g70_with_cutter_compensation_against_rs274(tmp_path: Path) -> None:
    """The same moves where rs274 accepts; the same message where it refuses (LinuxCNC's uncompensated
    rapids interleave with the compensation's held move, and its later passes often gouge)."""
    assert BINARY is not None
    # canon's cutter compensation refuses a held move cut back past its start whatever follows;
    # LinuxCNC lets it through before an arc or a near-tangent join (gouging): cutter_comp.py
    gouges_kept = {35}
    accepted = 0
    for seed in range(60):
        theirs, ours = oracle.run_program(_g70_comp_program(seed), tmp_path / str(seed), BINARY)
        if seed in gouges_kept:
            assert theirs.error is None and "cannot be reached by the tool without gouging" in str(ours.error)
            continue
        if theirs.error is None:
            accepted += 1
            assert oracle.compare(theirs, ours) is None, (seed, oracle.compare(theirs, ours))
        else:
            assert ours.error is not None and theirs.error.split(":")[-1].strip() in ours.error, (
                seed, theirs.error, ours.error)
    assert accepted >= 5


def _random_profile_program(seed: int) -> str:
    """A stepped shaft (X growing as Z goes down: what the cycles accept) with random steps, arcs and
    corners, and one of the cycles with random depth."""
    import random

    r = random.Random(seed)
    x = r.uniform(1, 4)
    lines = ["O100 SUB", f"G1 X{x:.3f} Z0"]
    z = 0.0
    for _ in range(r.randint(2, 6)):
        dz, dx = r.choice((0.0, r.uniform(0.5, 6.0))), r.choice((0.0, r.uniform(0.3, 2.0)))
        if dz == 0.0 and dx == 0.0:
            dz = 2.0
        z, x = z - dz, x + dx
        chord = (dz * dz + dx * dx) ** 0.5
        moves = [f"G1 X{x:.3f} Z{z:.3f}"]
        if dz > 0 and dx > 0:
            moves += [f"G{k} X{x:.3f} Z{z:.3f} R{chord * r.uniform(0.8, 3):.3f}" for k in (2, 3)]
        corner = r.choice(("", "", f" A{r.uniform(0.1, 0.5):.2f}", f" C{r.uniform(0.1, 0.5):.2f}"))
        lines.append(r.choice(moves) + corner)
    lines.append(f"G1 X{x + 2:.3f}\nO100 ENDSUB")
    code = r.choice(("G70", "G71", "G71.1", "G71.2", "G72", "G72.1", "G72.2"))
    depth = r.choice((0.05, 0.3, 1.0, 2.5))
    return ("G18 G21 F100\n" + "\n".join(lines)
            + f"\nG0 X{x + 4:.3f} Z2\n{code} Q100 X{x + 2:.3f} Z1 D0.2 I{depth} R0.2\nM2")


@pytest.mark.parametrize("seed", range(40))
def test_random_profiles_end_or_refuse_cleanly(seed: int) -> None:
    """Any profile: moves, or a G-code error that names the problem; no internal error, no hang."""
    from gcode_canon.errors import GCodeError

    try:
        run(_random_profile_program(seed))
    except GCodeError as exc:
        assert "internal error" not in str(exc), str(exc)


@pytest.mark.rs274
@pytest.mark.skipif(BINARY is None, reason=f"rs274 is not built in {oracle.rs274_dir()}")
def test_random_profiles_against_rs274(tmp_path: Path) -> None:
    """What rs274 accepts moves the same; what it refuses canon refuses, a profile with the same G7X
    message (canon's line in error sends nothing, LinuxCNC has sent the line's rapid: not compared)."""
    assert BINARY is not None
    accepted = 0
    for seed in range(60):
        theirs, ours = oracle.run_program(_random_profile_program(seed), tmp_path / str(seed), BINARY)
        if theirs.error is None:
            accepted += 1
            assert oracle.compare(theirs, ours) is None, (seed, oracle.compare(theirs, ours))
        else:
            assert ours.error is not None, (seed, theirs.error)
            if theirs.error.startswith("G7X error"):
                assert theirs.error.split(":")[-1] in ours.error, (seed, theirs.error, ours.error)
    assert accepted >= 5
