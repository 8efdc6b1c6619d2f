"""Canned cycles (gcode_canon.cycles).

Every expected path below was worked out by hand from LinuxCNC's G-code manual (G73, G74, G80-G89,
G98/G99, "Preliminary and In-Between Motion", the G81 examples) and the cycle descriptions in its
interp_cycles.cc; the reasoning is in the comments. The G18 series reproduces the scenario of
LinuxCNC's tests/interp/g81/g18 programs (same start, words and order) and agrees with the moves of
their expected output.

Paths are compared in X Y Z (not plane-local), with the plane mapping written out by hand here, so
the plane mapping of the module is tested too. Notation: ("G0", x, y, z) rapid, ("G1", x, y, z)
feed, ("dwell", s), ("M3",)/("M4",) spindle on CW/CCW, ("M5",) spindle stop, ("orient", "M3"),
("M0",) program stop, ("ovr_off",)/("ovr_on",) overrides disabled/restored. The exact-path
bracket ops are left out of the paths and tested on their own.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gcode_canon.commands import Plane, Pose, SpindleDirection
from gcode_canon.cycles import (
    CYCLE_CODES,
    MAX_OPS,
    CycleContext,
    CycleOp,
    CycleResult,
    CycleState,
    CycleWords,
    cancel,
    expand_cycle,
    from_local,
    offset_letters,
    plane_axes,
    to_local,
)
from gcode_canon.errors import GCodeError

CW = SpindleDirection.CW
CCW = SpindleDirection.CCW

# Plane-local (first, second, normal) -> (x, y, z), written out by hand:
# G17: first X, second Y, normal Z.  G18: first Z, second X, normal Y.  G19: first Y, second Z, normal X.
XYZ: dict[Plane, Callable[[float, float, float], tuple[float, float, float]]] = {
    Plane.XY: lambda a, b, c: (a, b, c),
    Plane.XZ: lambda a, b, c: (b, c, a),
    Plane.YZ: lambda a, b, c: (c, a, b),
}
# The block's letters for (first, second, normal) axis words and their I/J/K offsets, by hand.
LETTERS = {Plane.XY: ("x", "y", "z", "i", "j", "k"), Plane.XZ: ("z", "x", "y", "k", "i", "j"),
           Plane.YZ: ("y", "z", "x", "j", "k", "i")}  # fmt: skip


def ctx(plane: Plane = Plane.XY, **kw: object) -> CycleContext:
    base: dict[str, object] = {"plane": plane, "feed_rate": 100.0, "spindle": CW}
    base.update(kw)
    return CycleContext(**base)  # type: ignore[arg-type]


def run(
    code: int | str,
    plane: Plane = Plane.XY,
    start_xyz: tuple[float, float, float] = (0.0, 0.0, 10.0),
    state: CycleState | None = None,
    **kw: object,
) -> CycleResult:
    """Run one cycle block. Keyword args that are single letters are the block's words; the rest
    go to CycleContext. ``start_xyz`` is X Y Z."""
    letters = {k: v for k, v in kw.items() if len(k) == 1}
    context = {k: v for k, v in kw.items() if len(k) > 1}
    words = CycleWords.from_letters(plane, letters)  # type: ignore[arg-type]
    start = to_local(plane, Pose(*start_xyz))
    return expand_cycle(code, words, state or CycleState(), ctx(plane, **context), start)


def path(result: CycleResult, plane: Plane) -> list[tuple[object, ...]]:
    out: list[tuple[object, ...]] = []
    for op in result.ops:
        if op.kind in ("traverse", "feed"):
            assert op.point is not None
            out.append(("G0" if op.kind == "traverse" else "G1", *XYZ[plane](*op.point)))
        elif op.kind == "dwell":
            out.append(("dwell", op.seconds))
        elif op.kind == "spindle_stop":
            out.append(("M5",))
        elif op.kind == "spindle_on":
            out.append(("M3",) if op.direction is CW else ("M4",))
        elif op.kind == "orient":
            out.append(("orient", "M3" if op.direction is CW else "M4"))
        elif op.kind == "program_stop":
            out.append(("M0",))
        elif op.kind == "overrides_off":
            out.append(("ovr_off",))
        elif op.kind == "overrides_restore":
            out.append(("ovr_on",))
        else:
            assert op.kind in ("exact_path_begin", "exact_path_end")
    return out


def same(actual: list[tuple[object, ...]], expected: list[tuple[object, ...]]) -> None:
    """Paths equal, numbers to 1e-9."""
    assert len(actual) == len(expected), f"\n{actual}\n!=\n{expected}"
    for got, want in zip(actual, expected, strict=True):
        assert got[0] == want[0], f"\n{actual}\n!=\n{expected}"
        assert got[1:] == pytest.approx(want[1:], abs=1e-9), f"\n{actual}\n!=\n{expected}"


# --- every cycle, G17 and G18, G98 and G99 ----------------------------------------------------------
#
# One hole, the same in every plane, written plane-locally: start at (first 0, second 0, normal 10),
# hole at first 3, second 4, R 2, bottom (normal word) -5. The clear level is 10 in G98 (the start,
# above R) and 2 in G99 (R). Every cycle begins with the preliminary / in-between moves: the start is
# above R, so no rapid up; rapid in the plane at the current level 10 to (3, 4), rapid down to R 2.


def _hole(code: int, clear: float) -> tuple[dict[str, float], list[tuple]]:
    """Extra words (plane-local names) and expected plane-local ops after reaching (3, 4, R2)."""
    if code == 810:
        # G81: feed to the bottom, rapid to clear.
        return {}, [("G1", 3, 4, -5), ("G0", 3, 4, clear)]
    if code == 820:
        # G82 P1.5: feed to the bottom, dwell P, rapid to clear.
        return {"p": 1.5}, [("G1", 3, 4, -5), ("dwell", 1.5), ("G0", 3, 4, clear)]
    if code == 830:
        # G83 Q3, no D, metric: peck clearance is LinuxCNC's default 1 mm.
        # Depths R-Q = -1, R-2Q = -4 are above the bottom -5; R-3Q = -7 is not, so the last feed is to -5.
        # Each peck: feed to the depth, rapid out to R (2), rapid back down to depth + 1.
        return {"q": 3.0}, [
            ("G1", 3, 4, -1), ("G0", 3, 4, 2), ("G0", 3, 4, 0),
            ("G1", 3, 4, -4), ("G0", 3, 4, 2), ("G0", 3, 4, -3),
            ("G1", 3, 4, -5), ("G0", 3, 4, clear),
        ]  # fmt: skip
    if code == 730:
        # G73 Q3 D0.5: same depths as G83, but the retract is only D (0.5) up from each depth.
        return {"q": 3.0, "d": 0.5}, [
            ("G1", 3, 4, -1), ("G0", 3, 4, -0.5),
            ("G1", 3, 4, -4), ("G0", 3, 4, -3.5),
            ("G1", 3, 4, -5), ("G0", 3, 4, clear),
        ]  # fmt: skip
    if code == 840:
        # G84 P0.5 with the spindle CW: overrides off, feed in, stop, CCW, dwell, feed out to clear,
        # stop, CW again, overrides back.
        return {"p": 0.5}, [
            ("ovr_off",), ("G1", 3, 4, -5), ("M5",), ("M4",), ("dwell", 0.5),
            ("G1", 3, 4, clear), ("M5",), ("M3",), ("ovr_on",),
        ]  # fmt: skip
    if code == 740:
        # G74 (left hand, spindle CCW): the same with the directions swapped.
        return {"p": 0.5}, [
            ("ovr_off",), ("G1", 3, 4, -5), ("M5",), ("M3",), ("dwell", 0.5),
            ("G1", 3, 4, clear), ("M5",), ("M4",), ("ovr_on",),
        ]  # fmt: skip
    if code == 850:
        # G85: feed to the bottom, feed back to R, rapid to clear (nothing to do in G99: already at R).
        tail = [("G0", 3, 4, clear)] if clear != 2 else []
        return {}, [("G1", 3, 4, -5), ("G1", 3, 4, 2), *tail]
    if code == 860:
        # G86 P0: feed to the bottom, dwell, spindle stop, rapid to clear, spindle on as before (CW).
        return {"p": 0.0}, [("G1", 3, 4, -5), ("dwell", 0.0), ("M5",), ("G0", 3, 4, clear), ("M3",)]
    if code == 870:
        # G87 offsets: first +1.5, second 0, top of the back bore (absolute) -2.
        # At R: rapid to the offset point (4.5, 4), stop and orient the spindle, rapid down to the
        # bottom through the hole, rapid to the hole axis, spindle on, feed up to -2 and back to the
        # bottom, stop and orient, back to the offset point, rapid out to clear, to the hole axis,
        # spindle on.
        return {"oi": 1.5, "oj": 0.0, "ok": -2.0}, [
            ("G0", 4.5, 4, 2), ("M5",), ("orient", "M3"), ("G0", 4.5, 4, -5), ("G0", 3, 4, -5),
            ("M3",), ("G1", 3, 4, -2), ("G1", 3, 4, -5), ("M5",), ("orient", "M3"),
            ("G0", 4.5, 4, -5), ("G0", 4.5, 4, clear), ("G0", 3, 4, clear), ("M3",),
        ]  # fmt: skip
    if code == 880:
        # G88 P2: feed to the bottom, dwell, spindle stop, program stop (manual retract), spindle on.
        return {"p": 2.0}, [("G1", 3, 4, -5), ("dwell", 2.0), ("M5",), ("M0",), ("M3",)]
    assert code == 890
    # G89 P1: feed to the bottom, dwell, feed out to clear.
    return {"p": 1.0}, [("G1", 3, 4, -5), ("dwell", 1.0), ("G1", 3, 4, clear)]


@pytest.mark.parametrize("code", sorted(CYCLE_CODES))
@pytest.mark.parametrize("plane", [Plane.XY, Plane.XZ])
@pytest.mark.parametrize("retract", [98, 99])
def test_each_cycle_in_g17_and_g18(code: int, plane: Plane, retract: int) -> None:
    clear = 10.0 if retract == 98 else 2.0
    extra, hole_ops = _hole(code, clear)
    f, s, n, oi, oj, ok = LETTERS[plane]
    local_names = {"p": "p", "q": "q", "d": "d", "oi": oi, "oj": oj, "ok": ok}
    words = {f: 3.0, s: 4.0, n: -5.0, "r": 2.0} | {local_names[k]: v for k, v in extra.items()}
    start = XYZ[plane](0.0, 0.0, 10.0)
    spindle = CCW if code == 740 else CW
    result = run(code, plane, start, retract_mode=retract, spindle=spindle, **words)
    local = [("G0", 3, 4, 10), ("G0", 3, 4, 2), *hole_ops]
    expected = [(op[0], *XYZ[plane](*op[1:])) if op[0] in ("G0", "G1") else op for op in local]
    same(path(result, plane), expected)
    # Where the interpreter should think the tool is: the hole at the clear level.
    assert XYZ[plane](*result.end) == pytest.approx(
        (3.0, 4.0, clear) if plane is Plane.XY else (4.0, clear, 3.0)
    )


def test_g81_g19_g98_and_g99() -> None:
    # G19: positions are Y Z, drilling along X. Start X5 Y0 Z0; G81 Y1 Z2 X-3 R2.
    # The start (X5) is above R (X2): rapid Y1 Z2 at X5, rapid to X2, feed to X-3, rapid to clear.
    g98 = run(810, Plane.YZ, (5, 0, 0), y=1, z=2, x=-3, r=2, retract_mode=98)
    same(path(g98, Plane.YZ), [("G0", 5, 1, 2), ("G0", 2, 1, 2), ("G1", -3, 1, 2), ("G0", 5, 1, 2)])
    g99 = run(810, Plane.YZ, (5, 0, 0), y=1, z=2, x=-3, r=2, retract_mode=99)
    same(path(g99, Plane.YZ), [("G0", 5, 1, 2), ("G0", 2, 1, 2), ("G1", -3, 1, 2), ("G0", 2, 1, 2)])


def test_g81_g17_1_uv_plane() -> None:
    # G17.1: positions U V, drilling along W; the X Y Z words are not cycle words there.
    words = CycleWords.from_letters(Plane.UV, {"u": 1, "v": 2, "w": -1, "r": 1})
    result = expand_cycle("G81", words, CycleState(), ctx(Plane.UV), (0.0, 0.0, 5.0))
    assert [(op.kind, op.point) for op in result.ops if op.point] == [
        ("traverse", (1, 2, 5)), ("traverse", (1, 2, 1)), ("feed", (1, 2, -1)), ("traverse", (1, 2, 5)),
    ]  # fmt: skip


# --- the manual's G81 examples ------------------------------------------------------------------------


def test_manual_example_1_absolute_g98() -> None:
    # G90 G98 G81 X4 Y5 Z1.5 R2.8 from X1 Y2 Z3: OLD_Z 3 is above R 2.8, so clear is 3.
    # Rapid to X4 Y5 (at Z3), rapid to Z2.8, feed to Z1.5, rapid to Z3.
    result = run(810, Plane.XY, (1, 2, 3), x=4, y=5, z=1.5, r=2.8)
    same(path(result, Plane.XY), [("G0", 4, 5, 3), ("G0", 4, 5, 2.8), ("G1", 4, 5, 1.5), ("G0", 4, 5, 3)])


def test_manual_example_1_in_g99_retracts_to_r() -> None:
    result = run(810, Plane.XY, (1, 2, 3), x=4, y=5, z=1.5, r=2.8, retract_mode=99)
    same(path(result, Plane.XY), [("G0", 4, 5, 3), ("G0", 4, 5, 2.8), ("G1", 4, 5, 1.5), ("G0", 4, 5, 2.8)])


def test_manual_example_2_incremental_l3() -> None:
    # G91 G98 G81 X4 Y5 Z-0.6 R1.8 L3 from X1 Y2 Z3: R = 3 + 1.8 = 4.8, bottom = 4.8 - 0.6 = 4.2.
    # OLD_Z 3 is below R: rapid straight up to Z4.8 first (clear Z is then 4.8).
    # Holes at X5 Y7, X9 Y12, X13 Y17: rapid in the plane at 4.8, feed to 4.2, rapid to 4.8.
    result = run(810, Plane.XY, (1, 2, 3), x=4, y=5, z=-0.6, r=1.8, l=3, incremental=True)
    same(
        path(result, Plane.XY),
        [
            ("G0", 1, 2, 4.8),
            ("G0", 5, 7, 4.8), ("G1", 5, 7, 4.2), ("G0", 5, 7, 4.8),
            ("G0", 9, 12, 4.8), ("G1", 9, 12, 4.2), ("G0", 9, 12, 4.8),
            ("G0", 13, 17, 4.8), ("G1", 13, 17, 4.2), ("G0", 13, 17, 4.8),
        ],
    )  # fmt: skip
    assert result.end == pytest.approx((13, 17, 4.8))


def test_preliminary_rapid_up_when_starting_below_r() -> None:
    # Manual example 5: G90 G98 G81 X4 Y5 Z-0.6 R1.8 from X0 Y0 Z0. Z0 is below R: rapid straight up to
    # Z1.8 at X0 Y0, then rapid in the plane to X4 Y5 at R, feed to -0.6, back to R (OLD_Z is below R, so
    # G98 also retracts to R).
    result = run(810, Plane.XY, (0, 0, 0), x=4, y=5, z=-0.6, r=1.8)
    same(
        path(result, Plane.XY), [("G0", 0, 0, 1.8), ("G0", 4, 5, 1.8), ("G1", 4, 5, -0.6), ("G0", 4, 5, 1.8)]
    )


# --- L repeats -----------------------------------------------------------------------------------


def test_l_repeats_in_g90_drill_the_same_hole() -> None:
    # G90 G98 G81 X3 Y4 Z-5 R2 L3 from Z10: the same hole three times; between repeats the tool is at
    # clear (10) above the hole: rapid to R, feed, rapid to 10.
    result = run(810, Plane.XY, (0, 0, 10), x=3, y=4, z=-5, r=2, l=3)
    hole = [("G0", 3, 4, 2), ("G1", 3, 4, -5), ("G0", 3, 4, 10)]
    same(path(result, Plane.XY), [("G0", 3, 4, 10), *hole, *hole, *hole])


def test_l_repeats_in_g90_g99() -> None:
    # Same in G99: clear is R, so after the first hole the tool just feeds again from R.
    result = run(810, Plane.XY, (0, 0, 10), x=3, y=4, z=-5, r=2, l=3, retract_mode=99)
    hole = [("G1", 3, 4, -5), ("G0", 3, 4, 2)]
    same(path(result, Plane.XY), [("G0", 3, 4, 10), ("G0", 3, 4, 2), *hole, *hole, *hole])


def test_l_given_as_float_whole_number() -> None:
    result = run(810, Plane.XY, (0, 0, 10), x=3, y=4, z=-5, r=2, l=2.0)
    assert sum(op.kind == "feed" for op in result.ops) == 2


def test_incremental_r_and_z_with_repeats_g99() -> None:
    # G91 G99 G81 X2 R-3 Z-4 L2 from X1 Y1 Z5: R = 5 - 3 = 2, bottom = 2 - 4 = -2; Y has no increment.
    # Hole 1 at X3 Y1: the tool is above R, so rapid in the plane at Z5, down to R, feed, back to R.
    # Hole 2 at X5 Y1: rapid in the plane at R (clear in G99), feed, back to R.
    result = run(810, Plane.XY, (1, 1, 5), x=2, r=-3, z=-4, l=2, incremental=True, retract_mode=99)
    same(
        path(result, Plane.XY),
        [
            ("G0", 3, 1, 5), ("G0", 3, 1, 2), ("G1", 3, 1, -2), ("G0", 3, 1, 2),
            ("G0", 5, 1, 2), ("G1", 5, 1, -2), ("G0", 5, 1, 2),
        ],
    )  # fmt: skip
    # Next block "X2" alone (same cycle): R and Z are sticky; R stays relative to the level the series
    # started from (5), so R is still 2 and the bottom -2. Hole at X7: rapid in the plane at R, drill.
    second = run(810, Plane.XY, (5, 1, 2), result.state, x=2, incremental=True, retract_mode=99)
    same(path(second, Plane.XY), [("G0", 7, 1, 2), ("G1", 7, 1, -2), ("G0", 7, 1, 2)])


def test_incremental_g18_series_of_linuxcnc_test() -> None:
    # LinuxCNC tests/interp/g81/g18/g98 "number 4": G18 G98, from X10 Y2 Z0, G91 G81 X1 Z1 Y-2 R-1 L2.
    # Drill axis Y. R = 2 - 1 = 1, bottom = 1 - 2 = -1, clear = OLD_Y 2.
    # Hole 1 at Z1 X11: rapid in the plane at Y2, down to Y1, feed to Y-1, rapid to Y2.
    # Hole 2 at Z2 X12: same.
    result = run(810, Plane.XZ, (10, 2, 0), x=1, z=1, y=-2, r=-1, l=2, incremental=True)
    same(
        path(result, Plane.XZ),
        [
            ("G0", 11, 2, 1), ("G0", 11, 1, 1), ("G1", 11, -1, 1), ("G0", 11, 2, 1),
            ("G0", 12, 2, 2), ("G0", 12, 1, 2), ("G1", 12, -1, 2), ("G0", 12, 2, 2),
        ],
    )  # fmt: skip
    # "number 5": from X20 Y2 Z0, G91 G81 X1 Z1 Y-2.5 R1 L2: R = 3, bottom 0.5, OLD_Y 2 < R: rapid up
    # to Y3 first, clear is then 3.
    result = run(810, Plane.XZ, (20, 2, 0), x=1, z=1, y=-2.5, r=1, l=2, incremental=True)
    same(
        path(result, Plane.XZ),
        [
            ("G0", 20, 3, 0),
            ("G0", 21, 3, 1), ("G1", 21, 0.5, 1), ("G0", 21, 3, 1),
            ("G0", 22, 3, 2), ("G1", 22, 0.5, 2), ("G0", 22, 3, 2),
        ],
    )  # fmt: skip


def test_g18_absolute_series_keeps_the_initial_level() -> None:
    # LinuxCNC tests/interp/g81/g18/g98 "numbers 1-3": G18 G98 G90, from X0 Y2 Z0, three G81 blocks
    # in a row: the initial level (OLD_Y) stays 2 across the blocks.
    # 1: X1 Z1 Y-1 R1: start above R: rapid Z1 X1 at Y2, down to Y1, feed Y-1, back to OLD_Y 2.
    one = run(810, Plane.XZ, (0, 2, 0), x=1, z=1, y=-1, r=1)
    same(path(one, Plane.XZ), [("G0", 1, 2, 1), ("G0", 1, 1, 1), ("G1", 1, -1, 1), ("G0", 1, 2, 1)])
    # 2: X1 Z2 Y0.5 R3 from X1 Y2 Z1: now Y2 is below R3: rapid up to Y3 where it is, then to Z2 at Y3
    # (clear is max(OLD_Y 2, R 3) = 3), feed to Y0.5, rapid to Y3.
    two = run(810, Plane.XZ, (1, 2, 1), one.state, x=1, z=2, y=0.5, r=3)
    same(path(two, Plane.XZ), [("G0", 1, 3, 1), ("G0", 1, 3, 2), ("G1", 1, 0.5, 2), ("G0", 1, 3, 2)])
    # 3: X1 Z3 Y4 R5 from X1 Y3 Z2: up to Y5, over to Z3, feed to Y4, rapid to Y5.
    three = run(810, Plane.XZ, (1, 3, 2), two.state, x=1, z=3, y=4, r=5)
    same(path(three, Plane.XZ), [("G0", 1, 5, 2), ("G0", 1, 5, 3), ("G1", 1, 4, 3), ("G0", 1, 5, 3)])
    assert three.state.initial_level == 2


# --- sticky words and the initial level -----------------------------------------------------------


def test_sticky_r_z_p_in_following_blocks() -> None:
    first = run(820, Plane.XY, (0, 0, 10), x=1, y=1, z=-2, r=1, p=0.25, retract_mode=99)
    # Next G82 block with only X: R1, Z-2 and P0.25 carry over. From X1 Y1 Z1 (R): rapid to X6 at R,
    # feed to -2, dwell 0.25, rapid to R.
    second = run(820, Plane.XY, (1, 1, 1), first.state, x=6, retract_mode=99)
    same(path(second, Plane.XY), [("G0", 6, 1, 1), ("G1", 6, 1, -2), ("dwell", 0.25), ("G0", 6, 1, 1)])


def test_sticky_q_for_g83() -> None:
    first = run(830, Plane.XY, (0, 0, 10), x=0, y=0, z=-2, r=0, q=5, retract_mode=99)
    second = run(830, Plane.XY, (0, 0, 0), first.state, x=1, retract_mode=99)
    # Q5 carried: one peck reaches the bottom at once (0 - 5 < -2): rapid to X1, feed to -2, back to R 0.
    same(path(second, Plane.XY), [("G0", 1, 0, 0), ("G1", 1, 0, -2), ("G0", 1, 0, 0)])


def test_initial_level_survives_a_change_of_cycle_and_g99_to_g98() -> None:
    # G99 G81 from Z10 R2: ends at R. Then G98 G82 R2 Z-5 P1 (a different cycle: R, Z, P required):
    # the series is unbroken, so OLD_Z is still 10: clear is 10. The tool is at R (not above it), so the
    # move to the new hole is made at the clear level (a slanted rapid up, as LinuxCNC does), then down
    # to R, feed, dwell, rapid to 10.
    first = run(810, Plane.XY, (0, 0, 10), x=3, y=4, z=-5, r=2, retract_mode=99)
    second = run(820, Plane.XY, (3, 4, 2), first.state, x=6, y=4, z=-5, r=2, p=1, retract_mode=98)
    same(
        path(second, Plane.XY),
        [("G0", 6, 4, 10), ("G0", 6, 4, 2), ("G1", 6, 4, -5), ("dwell", 1.0), ("G0", 6, 4, 10)],
    )


def test_cancel_forgets_the_initial_level_and_the_cycle() -> None:
    first = run(810, Plane.XY, (0, 0, 10), x=3, y=4, z=-5, r=2, retract_mode=99)
    state = cancel(first.state)
    assert state.motion is None and state.initial_level is None
    # After G80, from Z2: a G98 G81 with R1 clears to the new initial level 2, not to the old 10.
    again = run(810, Plane.XY, (3, 4, 2), state, x=5, y=4, z=-5, r=1)
    same(path(again, Plane.XY), [("G0", 5, 4, 2), ("G0", 5, 4, 1), ("G1", 5, 4, -5), ("G0", 5, 4, 2)])
    # ... and R is required again.
    with pytest.raises(GCodeError, match="R clearance plane unspecified"):
        run(810, Plane.XY, (3, 4, 2), state, x=5, z=-5)


# --- pecking details ------------------------------------------------------------------------------


def test_peck_clearance_default_inch_and_configured() -> None:
    # G73 Q1 from R0 to Z-1.5 in inch units on a metric machine: LinuxCNC's default clearance is the
    # machine's (1) used as a program-unit number: one peck at -1, retract 1 to 0, final feed to -1.5,
    # rapid out to R (G99).
    inch = run(730, Plane.XY, (0, 0, 1), z=-1.5, r=0, q=1, metric=False, retract_mode=99)
    same(
        path(inch, Plane.XY),
        [("G0", 0, 0, 0), ("G1", 0, 0, -1), ("G0", 0, 0, 0), ("G1", 0, 0, -1.5), ("G0", 0, 0, 0)],
    )
    # Configured G83 clearance 0.2: peck to -1, out to R0, back down to -0.8, final feed, out to R.
    conf = run(830, Plane.XY, (0, 0, 1), z=-1.5, r=0, q=1, g83_peck_clearance=0.2, retract_mode=99)
    same(
        path(conf, Plane.XY),
        [("G0", 0, 0, 0), ("G1", 0, 0, -1), ("G0", 0, 0, 0), ("G0", 0, 0, -0.8), ("G1", 0, 0, -1.5),
         ("G0", 0, 0, 0)],
    )  # fmt: skip


def test_peck_depths_do_not_accumulate_rounding() -> None:
    # R1 Q0.2 Z0.4: pecks at 0.8 and 0.6, then the bottom 0.4. Subtracting 0.2 three times from 1 gives
    # 0.4000000000000001, just above 0.4, which would add a useless extra peck.
    result = run(730, Plane.XY, (0, 0, 1), z=0.4, r=1, q=0.2, d=0.05, retract_mode=99)
    feeds = [op.point[2] for op in result.ops if op.kind == "feed" and op.point]
    assert feeds == pytest.approx([0.8, 0.6, 0.4])
    # R0 Q0.3 Z-0.9: 3 * 0.3 is 0.8999999999999999 in floating point, so the third peck depth lands a
    # hair above the bottom; it is the bottom: pecks at -0.3, -0.6, then the final feed to -0.9.
    result = run(830, Plane.XY, (0, 0, 1), z=-0.9, r=0, q=0.3, retract_mode=99)
    feeds = [op.point[2] for op in result.ops if op.kind == "feed" and op.point]
    assert feeds == pytest.approx([-0.3, -0.6, -0.9])


def test_q_deeper_than_the_hole_is_one_feed() -> None:
    result = run(830, Plane.XY, (0, 0, 10), z=-1, r=2, q=10)
    same(path(result, Plane.XY), [("G0", 0, 0, 2), ("G1", 0, 0, -1), ("G0", 0, 0, 10)])


def test_exact_path_brackets_the_cycle_after_the_preliminary_move() -> None:
    # LinuxCNC switches to exact path after the preliminary rapid up and restores the mode at the end.
    result = run(810, Plane.XY, (0, 0, 0), x=1, z=-1, r=1)
    kinds = [op.kind for op in result.ops]
    assert kinds == ["traverse", "exact_path_begin", "traverse", "feed", "traverse", "exact_path_end"]
    assert result.ops[0] == CycleOp("traverse", (0.0, 0.0, 1.0))


def test_g88_end_is_assumed_at_clear() -> None:
    result = run(880, Plane.XY, (0, 0, 10), x=1, y=1, z=-1, r=1, p=0, l=2, retract_mode=99)
    # Repeat after the manual retract: the in-plane rapid to the (same) hole at R is emitted, since
    # where the operator left the tool is unknown.
    same(
        path(result, Plane.XY),
        [("G0", 1, 1, 10), ("G0", 1, 1, 1), ("G1", 1, 1, -1), ("dwell", 0.0), ("M5",), ("M0",), ("M3",),
         ("G0", 1, 1, 1), ("G1", 1, 1, -1), ("dwell", 0.0), ("M5",), ("M0",), ("M3",)],
    )  # fmt: skip
    assert result.end == (1, 1, 1)


def test_g84_without_p_dwells_zero_and_incremental_g87_k() -> None:
    tap = run(840, Plane.XY, (0, 0, 10), z=-1, r=1, retract_mode=99)
    assert [op.seconds for op in tap.ops if op.kind == "dwell"] == [0.0]
    # G91 G87: K is measured from the bottom: R = 10 - 2 = 8, bottom = 8 - 6 = 2, top = 2 + 1 = 3.
    bore = run(870, Plane.XY, (0, 0, 10), z=-6, r=-2, i=1, j=0, k=1, incremental=True, retract_mode=99)
    feeds = [op.point for op in bore.ops if op.kind == "feed"]
    assert feeds == [(0, 0, 3), (0, 0, 2)]


# --- helpers ----------------------------------------------------------------------------------------


def test_plane_helpers() -> None:
    assert plane_axes(Plane.XZ) == ("z", "x", "y")
    assert offset_letters(Plane.XZ) == ("k", "i", "j")
    assert offset_letters(Plane.VW) == ("j", "k", "i")
    pose = Pose(1, 2, 3, 4, 5, 6, 7, 8, 9)
    assert to_local(Plane.YZ, pose) == (2, 3, 1)
    assert to_local(Plane.WU, pose) == (9, 7, 8)
    assert from_local(Plane.XZ, (30, 10, 20), pose) == Pose(10, 20, 30, 4, 5, 6, 7, 8, 9)
    words = CycleWords.from_letters(Plane.XZ, {"X": 1, "Z": 2, "Y": -3, "I": 4, "K": 5, "A": 0, "U": 1})
    assert (words.first, words.second, words.normal) == (2, 1, -3)
    assert (words.offset_first, words.offset_second, words.offset_normal) == (5, 4, None)
    assert words.extra_axes == {"a", "u"}


@pytest.mark.parametrize("code", ["G81", "g81", "81", 810])
def test_code_spellings(code: int | str) -> None:
    assert run(code, x=1, z=-1, r=1).state.motion == 810


# --- errors ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("code", "plane", "kw", "message"),
    [
        (810, Plane.XY, {"z": 3, "r": 2}, "R less than Z in cycle in XY plane"),
        (810, Plane.XZ, {"y": 3, "r": 2}, "R less than Y in cycle in XZ plane"),
        (810, Plane.YZ, {"x": 3, "r": 2}, "R less than X in cycle in YZ plane"),
        (810, Plane.XY, {"z": -1}, "R clearance plane unspecified in cycle"),
        (810, Plane.XY, {"r": 1}, "Z value unspecified in XY plane canned cycle"),
        (810, Plane.XZ, {"r": 1}, "Y value unspecified in XZ plane canned cycle"),
        (830, Plane.XY, {"z": -1, "r": 1}, "Q word missing with G83"),
        (730, Plane.XY, {"z": -1, "r": 1}, "Q word missing with G73"),
        (830, Plane.XY, {"z": -1, "r": 1, "q": 0}, "Negative or zero Q value used"),
        (730, Plane.XY, {"z": -1, "r": 1, "q": -0.5}, "Negative or zero Q value used"),
        (830, Plane.XY, {"z": -1, "r": 1, "q": 1, "d": -1}, "Negative peck clearance"),
        (820, Plane.XY, {"z": -1, "r": 1}, "Dwell time P word missing with G82"),
        (860, Plane.XY, {"z": -1, "r": 1}, "Dwell time P word missing with G86"),
        (880, Plane.XY, {"z": -1, "r": 1}, "Dwell time P word missing with G88"),
        (890, Plane.XY, {"z": -1, "r": 1}, "Dwell time P word missing with G89"),
        (820, Plane.XY, {"z": -1, "r": 1, "p": -1}, "Negative P word"),
        (870, Plane.XY, {"z": -1, "r": 1, "j": 0, "k": 0}, "I word missing with G87"),
        (870, Plane.XY, {"z": -1, "r": 1, "i": 0, "k": 0}, "J word missing with G87"),
        (870, Plane.XY, {"z": -1, "r": 1, "i": 0, "j": 0}, "K word missing with G87"),
        (870, Plane.XZ, {"y": -1, "r": 1, "i": 0, "k": 0}, "J word missing with G87"),
        (870, Plane.XY, {"z": -1, "r": 1, "i": 1, "j": 0, "k": 2}, "must lie between"),
        (810, Plane.XY, {"z": -1, "r": 1, "l": 0}, "Cannot do zero repeats of cycle"),
        (810, Plane.XY, {"z": -1, "r": 1, "l": -2}, "Negative L word used"),
        (810, Plane.XY, {"z": -1, "r": 1, "l": 2.5}, "L word must be a whole number"),
        (810, Plane.XY, {"z": -1, "r": 1, "a": 1}, "Cannot put an A in canned cycle"),
        (810, Plane.XY, {"z": -1, "r": 1, "w": 1}, "Cannot put a W in a canned cycle in the XY plane"),
        (810, Plane.UV, {"w": -1, "r": 1, "x": 1}, "Cannot put an X in a canned cycle in the UV plane"),
        (810, Plane.XY, {"z": -1, "r": math.nan}, "R word is not a finite number"),
        (870, Plane.XZ, {"y": -1, "r": 1, "i": 0, "k": 0, "j": math.inf}, "J word is not a finite number"),
        (810, Plane.XY, {"z": -1, "r": 1, "cutter_comp": True}, "cutter compensation"),
        (810, Plane.XY, {"z": -1, "r": 1, "inverse_time": True}, "inverse time"),
        (810, Plane.XY, {"z": -1, "r": 1, "feed_rate": 0.0}, "zero feed rate"),
        (860, Plane.XY, {"z": -1, "r": 1, "p": 0, "spindle": None}, "Spindle not turning in G86"),
        (870, Plane.XY, {"z": -1, "r": 1, "i": 0, "j": 0, "k": 0, "spindle": None}, "not turning in G87"),
        (880, Plane.XY, {"z": -1, "r": 1, "p": 0, "spindle": None}, "Spindle not turning in G88"),
        (840, Plane.XY, {"z": -1, "r": 1, "spindle": None}, "Spindle not turning in G84"),
        (840, Plane.XY, {"z": -1, "r": 1, "spindle": CCW}, "Spindle turning counterclockwise in G84"),
        (740, Plane.XY, {"z": -1, "r": 1, "spindle": CW}, "Spindle turning clockwise in G74"),
        (760, Plane.XZ, {"z": -1, "r": 1}, "G76 is not a canned cycle"),
        (800, Plane.XY, {"z": -1, "r": 1}, "G80 is not a canned cycle"),
        ("G8x", Plane.XY, {"z": -1, "r": 1}, "is not a G code"),
        (830, Plane.XY, {"z": -1000, "r": 0, "q": 0.001}, "more than"),
        # a Q so small that the number of pecks is infinite (hypothesis found it: an OverflowError)
        (830, Plane.XY, {"z": -1, "r": 0, "q": 5e-324}, "G83 would make more than"),
        (730, Plane.XY, {"z": -1, "r": 0, "q": 1e-300}, "G73 would make more than"),
        (810, Plane.XY, {"z": -1, "r": 0, "l": MAX_OPS}, "more than"),
    ],
)
def test_errors(code: int | str, plane: Plane, kw: dict[str, object], message: str) -> None:
    start = XYZ[plane](0.0, 0.0, 10.0) if plane in XYZ else (0.0, 0.0, 0.0)
    with pytest.raises(GCodeError, match=message.replace("(", r"\(")) as info:
        run(code, plane, start, **kw)
    assert info.value.file == "" and info.value.line == 0  # the interpreter locates it


def test_positions_that_overflow_are_refused() -> None:
    # G91 L3 with an X increment near the float limit: the third hole would be at infinity.
    with pytest.raises(GCodeError, match="out of range"):
        run(810, Plane.XY, (1e308, 0, 0), x=1e308, z=-1, r=1, l=3, incremental=True)


def test_a_different_cycle_needs_r_and_z_again() -> None:
    first = run(810, Plane.XY, (0, 0, 10), x=1, z=-1, r=1)
    with pytest.raises(GCodeError, match="R clearance plane unspecified"):
        run(820, Plane.XY, (1, 0, 10), first.state, x=2, z=-1, p=1)
    with pytest.raises(GCodeError, match="Z value unspecified"):
        run(820, Plane.XY, (1, 0, 10), first.state, x=2, r=1, p=1)


# --- property ---------------------------------------------------------------------------------------

_num = st.floats(min_value=-50, max_value=50, allow_nan=False)
_maybe = st.one_of(st.none(), _num)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_property_only_gcode_errors_and_feeds_inside_the_hole(data: st.DataObject) -> None:
    draw = data.draw
    code = draw(st.sampled_from([*sorted(CYCLE_CODES)] * 4 + [760, 800]), "code")
    plane = draw(st.sampled_from(list(Plane)), "plane")
    retract = draw(st.sampled_from([98, 99]), "retract")
    incremental = draw(st.booleans(), "incremental")
    start = draw(st.tuples(_num, _num, _num), "start")
    if draw(st.booleans(), "wild"):
        # Any words at all, mostly invalid: only GCodeError may come out.
        first, second, normal, r = (draw(_maybe) for _ in range(4))
        q = draw(st.one_of(st.none(), st.floats(min_value=-1, max_value=20)), "q")
        p = draw(st.one_of(st.none(), st.floats(min_value=-1, max_value=5)), "p")
        d = draw(st.one_of(st.none(), st.floats(min_value=-1, max_value=5)), "d")
        l_word = draw(st.one_of(st.none(), st.integers(-1, 4), st.floats(min_value=-1, max_value=4)), "l")
        offsets = draw(st.tuples(_maybe, _maybe, _maybe), "offsets")
        spindle = draw(st.sampled_from([None, CW, CCW]), "spindle")
        previous = draw(st.one_of(st.none(), st.sampled_from(sorted(CYCLE_CODES))), "previous")
    else:
        # Words that make a valid hole (R above the bottom, positive Q, G87 top inside the hole).
        first, second = draw(_maybe), draw(_maybe)
        r = draw(_num, "r")
        depth = draw(st.floats(min_value=0, max_value=30), "depth")
        normal = -depth if incremental else r - depth
        q = draw(st.floats(min_value=0.05, max_value=20), "q")
        p = draw(st.floats(min_value=0, max_value=5), "p")
        d = draw(st.one_of(st.none(), st.floats(min_value=0, max_value=5)), "d")
        l_word = draw(st.one_of(st.none(), st.integers(1, 4)), "l")
        fraction = draw(st.floats(min_value=0, max_value=1), "fraction")
        top = depth * fraction if incremental else r - depth + depth * fraction
        offsets = (draw(_num), draw(_num), top)
        spindle = CCW if code == 740 else CW
        previous = draw(st.sampled_from([None, code]), "previous")
    initial = draw(_maybe, "initial") if previous else None
    state = CycleState(motion=previous, initial_level=initial, normal=-3.0, r=1.0, q=0.5, p=0.0,
                       offsets=(0.5, 0.0, -1.0))  # fmt: skip
    words = CycleWords(first, second, normal, r, q, p, l_word, d, *offsets)
    context = CycleContext(plane=plane, incremental=incremental, retract_mode=retract, feed_rate=10.0,
                           spindle=spindle)  # fmt: skip
    try:
        result = expand_cycle(code, words, state, context, start)
    except GCodeError:
        return
    # The levels, restated from the manual: R (relative to the initial level in G91), the bottom
    # (relative to R in G91), clear = R in G99, the higher of the initial level and R in G98.
    level0 = state.initial_level if state.initial_level is not None else start[2]
    r_word = r if r is not None else state.r
    z_word = normal if normal is not None else state.normal
    r_level = r_word + level0 if incremental else r_word
    bottom = r_level + z_word if incremental else z_word
    clear = r_level if retract == 99 else max(level0, r_level)
    eps = 1e-6 * (1 + abs(r_level) + abs(bottom) + abs(clear))
    assert bottom <= r_level + eps
    assert len(result.ops) <= MAX_OPS
    pos: tuple[float, float, float] | None = start
    for op in result.ops:
        if op.kind == "program_stop":
            pos = None
        if op.point is None:
            continue
        a, b, c = op.point
        assert all(math.isfinite(v) for v in op.point)
        # Nothing ever goes below the bottom of the hole.
        assert c >= bottom - eps
        if op.kind == "feed":
            # A feed stays inside the hole: on the hole's axis-line, between the bottom and clear.
            assert bottom - eps <= c <= clear + eps
            assert pos is not None and (a, b) == pos[:2]
        elif pos is not None and (a, b) != pos[:2] and code != 870:
            # Rapids across the plane happen only at or above R (G87 moves sideways inside the hole
            # on purpose, with the spindle oriented).
            assert min(c, pos[2]) >= r_level - eps
        pos = op.point
    assert result.state.motion == code
    assert result.end[2] == clear
