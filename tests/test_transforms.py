"""Program transforms (gcode_canon.transforms): G15/G16 polar, G22/G23 mirror, G50/G51 scaling,
G68/G69 rotation, their composition, and the G12/G13 full circle.

Every expected value is worked out by hand in the comments (mirror about m: x -> 2m - x; scale
about c by s: x -> c + s (x - c); rotation by t about q: d -> (d1 cos t - d2 sin t,
d1 sin t + d2 cos t)). Positions are 9-tuples in AXES order (x y z a b c u v w).
"""

from __future__ import annotations

import contextlib
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gcode_canon.commands import AXES, Plane
from gcode_canon.errors import GCodeError
from gcode_canon.transforms import (
    ArcResult,
    PlaneMove,
    PolarOrigin,
    PolarState,
    ProgramTransform,
    cos_sin,
    full_circle,
    polar_letters,
    polar_target,
)

SQRT3_2 = math.sqrt(3) / 2


def pos(**kw: float) -> tuple[float, ...]:
    return tuple(kw.get(a, 0.0) for a in AXES)


def approx(values, abs_tol: float = 1e-9):
    return pytest.approx(tuple(values), abs=abs_tol)


# --- basics ---------------------------------------------------------------------------------------


def test_cos_sin_exact_at_right_angles():
    assert cos_sin(0) == (1.0, 0.0)
    assert cos_sin(90) == (0.0, 1.0)
    assert cos_sin(180) == (-1.0, 0.0)
    assert cos_sin(-90) == (0.0, -1.0)  # -90 = 270
    assert cos_sin(450) == (0.0, 1.0)  # 450 = 360 + 90
    assert cos_sin(30) == pytest.approx((SQRT3_2, 0.5))


def test_identity_changes_nothing():
    t = ProgramTransform()
    assert t.identity
    p = pos(x=1.5, y=-2, z=3, a=45, w=7)
    assert t.apply_position(p) == p
    assert t.invert_position(p) == p
    assert t.apply_point((1.0, 2.0)) == (1.0, 2.0)
    assert not t.flips()
    assert t.comp_side("left") == "left"


def test_cancel_returns_identity():
    t = (ProgramTransform().with_mirror({"x": 3}).with_scale(pos(x=1), 2.0)
         .with_rotation((1, 1), 30))
    assert not t.identity
    assert t.cancel_mirror().cancel_scale().cancel_rotation().identity
    assert t.cancel_all().identity
    assert t.with_plane(Plane.XZ).cancel_all().plane is Plane.XZ


def test_360_degree_rotation_is_identity():
    assert ProgramTransform().with_rotation((5, 5), 360).identity
    assert not ProgramTransform().with_rotation((5, 5), 360).rotating


# --- G22/G23 mirror -------------------------------------------------------------------------------


def test_mirror_x_about_10():
    t = ProgramTransform().with_mirror({"x": 10.0})
    # x: 2*10 - 3 = 17; y unchanged
    assert t.apply_point((3.0, 4.0)) == (17.0, 4.0)
    assert t.mirrored == ("x",)
    assert t.flips()  # one in-plane axis mirrored
    assert t.arc_clockwise(True) is False  # G2 becomes G3
    assert t.arc_clockwise(False) is True
    assert t.comp_side("left") == "right"  # G41 becomes G42
    assert t.comp_side("right") == "left"


def test_mirror_both_plane_axes_keeps_direction():
    t = ProgramTransform().with_mirror({"x": 0.0, "y": 0.0})
    # (3, 4) -> (-3, -4): a half turn, not a reflection
    assert t.apply_point((3.0, 4.0)) == (-3.0, -4.0)
    assert not t.flips()
    assert t.arc_clockwise(True) is True


def test_mirror_of_normal_axis_flips_only_planes_containing_it():
    t = ProgramTransform().with_mirror({"z": 1.0})
    # z: 2*1 - 5 = -3 (3-tuple in G17 is (x, y, z))
    assert t.apply_point((1.0, 2.0, 5.0)) == (1.0, 2.0, -3.0)
    assert not t.flips(Plane.XY)  # Z is the normal of G17: arcs keep their direction
    assert t.flips(Plane.XZ)  # Z is G18's first axis
    assert t.flips(Plane.YZ)


def test_g22_accumulates_axes_and_g23_cancels_some_or_all():
    t = ProgramTransform().with_mirror({"x": 1.0}).with_mirror({"y": 2.0})
    assert t.mirrored == ("x", "y")
    t2 = t.with_mirror({"x": 5.0})  # a new line for X replaces the old one
    assert t2.apply_point((0.0, 0.0)) == (10.0, 4.0)  # 2*5 - 0, 2*2 - 0
    assert t.cancel_mirror(["x"]).mirrored == ("y",)
    assert t.cancel_mirror().mirrored == ()


def test_g22_without_axes_is_an_error():
    with pytest.raises(GCodeError, match="G22 needs at least one axis word"):
        ProgramTransform().with_mirror({})


def test_gcode_canon_g22_example():
    # gcode-canon: in G91, "G22 X10" mirrors X about 10 from the current position, and a following
    # "G01 X2" moves the machine 2 *away* from the mirror line (towards the origin of X).
    machine_x = 5.0
    old = ProgramTransform()
    prog = list(pos(x=machine_x))
    new = old.with_mirror({"x": prog[0] + 10.0})  # mirror line at 15
    # The machine stays put: prog' = T_new^-1(T_old(prog)) = 2*15 - 5 = 25
    prog = list(new.invert_position(old.apply_position(prog)))
    assert prog[0] == 25.0
    assert new.apply_position(prog)[0] == machine_x
    prog[0] += 2.0  # G91 G1 X2 -> programmed 27
    after = new.apply_position(prog)[0]  # 2*15 - 27 = 3
    assert after == 3.0
    assert after < machine_x  # moved 2 away from the line at 15, towards X0
    assert abs(after - 15.0) == abs(machine_x - 15.0) + 2.0


def test_mirror_arc_swaps_direction_and_mirrors_centre():
    t = ProgramTransform().with_mirror({"y": 0.0})
    # G2 from (0,0) to (10,0) around (5,0)... end (10, 0) and centre (5, 5): y -> -y
    res = t.apply_arc((10.0, 0.0), (5.0, 5.0), clockwise=True)
    assert res == ArcResult((10.0, 0.0), (5.0, -5.0), False, 1.0)


def test_plane_local_points_follow_the_active_plane():
    t = ProgramTransform().with_mirror({"z": 1.0}).with_plane(Plane.XZ)
    # G18 local (z, x): z = 2*1 - 3 = -1, x unchanged
    assert t.apply_point((3.0, 2.0)) == (-1.0, 2.0)
    assert t.invert_point((-1.0, 2.0)) == (3.0, 2.0)
    assert t.flips()  # Z is in the G18 plane
    assert t.comp_side("left") == "right"


# --- G50/G51 scaling ------------------------------------------------------------------------------


def test_uniform_scale_about_centre():
    t = ProgramTransform().with_scale(pos(x=10, y=20), 2.0)
    # x: 10 + 2*(15-10) = 20; y: 20 + 2*(25-20) = 30; z: 0 + 2*(3-0) = 6
    assert t.apply_point((15.0, 25.0, 3.0)) == (20.0, 30.0, 6.0)
    assert t.scaling
    assert not t.flips()


def test_scale_leaves_rotary_axes_alone():
    t = ProgramTransform().with_scale(pos(), 2.0)
    out = t.apply_position(pos(x=1, a=30, u=4))
    # linear x and u doubled, A (degrees) untouched
    assert out == pos(x=2, a=30, u=8)


def test_per_axis_scale_ijk():
    t = ProgramTransform().with_scale(pos(x=10, y=20), {"x": 2.0, "y": 3.0})
    # x: 10 + 2*(15-10) = 20; y: 20 + 3*(25-20) = 35; z factor 1
    assert t.apply_point((15.0, 25.0, 3.0)) == (20.0, 35.0, 3.0)


def test_non_uniform_scaling_of_an_arc_is_an_error():
    t = ProgramTransform().with_scale(pos(), {"x": 2.0, "y": 3.0})
    with pytest.raises(GCodeError, match="Non-uniform scaling of an arc"):
        t.apply_arc((1.0, 0.0), (0.5, 0.0), clockwise=True)
    with pytest.raises(GCodeError, match="Non-uniform scaling of an arc"):
        t.scale_radius(5.0)
    # The same scale is fine for an arc in G19 (Y Z) only if Y and Z agree: they do not (3 vs 1)
    with pytest.raises(GCodeError):
        t.apply_arc((1.0, 0.0), (0.5, 0.0), clockwise=True, plane=Plane.YZ)
    # ...but an arc in G17 with only Z scaled differently (a helix pitch) is fine
    helix = ProgramTransform().with_scale(pos(), {"x": 2.0, "y": 2.0, "z": 5.0})
    res = helix.apply_arc((1.0, 0.0, 1.0), (0.5, 0.0), clockwise=False)
    # end (2, 0, 5), centre (1, 0), radius doubled
    assert res == ArcResult((2.0, 0.0, 5.0), (1.0, 0.0), False, 2.0)


def test_scaled_arc_and_r_word():
    t = ProgramTransform().with_scale(pos(x=10, y=10), 0.5)
    # G3 to (20, 10) around (15, 10) (radius 5): end 10 + 0.5*10 = 15, centre 10 + 0.5*5 = 12.5
    res = t.apply_arc((20.0, 10.0), (15.0, 10.0), clockwise=False)
    assert res == ArcResult((15.0, 10.0), (12.5, 10.0), False, 0.5)
    assert t.scale_radius(5.0) == 2.5  # R5 -> R2.5
    assert t.scale_radius(-8.0) == -4.0  # the sign (long arc) is kept


def test_negative_scale_factor_is_a_mirror_image():
    t = ProgramTransform().with_scale(pos(), {"x": -1.0, "y": 1.0})
    assert t.apply_point((3.0, 4.0)) == (-3.0, 4.0)
    assert t.flips()
    assert t.scale_radius(5.0) == 5.0  # |-1| = |1|: uniform in magnitude


def test_result_out_of_range_is_a_gcode_error():
    t = ProgramTransform().with_scale(pos(), 1e300)
    with pytest.raises(GCodeError, match="Coordinate out of range"):
        t.apply_point((1e300, 0.0))  # 1e600 overflows to inf


def test_scale_errors():
    with pytest.raises(GCodeError, match="zero"):
        ProgramTransform().with_scale(pos(), 0.0)
    with pytest.raises(GCodeError, match="zero"):
        ProgramTransform().with_scale(pos(), {"y": 0.0})
    with pytest.raises(GCodeError, match="rotary axis A"):
        ProgramTransform().with_scale(pos(), {"a": 2.0})
    with pytest.raises(GCodeError, match="finite"):
        ProgramTransform().with_scale(pos(), math.inf)
    with pytest.raises(ValueError):
        ProgramTransform().with_scale((0.0, 0.0), 2.0)  # wiring bug: not a full position
    with pytest.raises(ValueError):
        ProgramTransform().with_scale(pos(), {"q": 2.0})


# --- G68/G69 rotation -----------------------------------------------------------------------------


def test_rotation_90_about_centre():
    t = ProgramTransform().with_rotation((10.0, 0.0), 90.0)
    # d = (20-10, 0-0) = (10, 0) -> (0, 10); + centre = (10, 10)
    assert t.apply_point((20.0, 0.0)) == (10.0, 10.0)
    assert t.rotating


def test_rotation_30_degrees():
    t = ProgramTransform().with_rotation((0.0, 0.0), 30.0)
    # (2, 0) -> (2 cos30, 2 sin30) = (1.7320508, 1)
    assert t.apply_point((2.0, 0.0)) == approx((2 * SQRT3_2, 1.0))
    # (0, 2) -> (-2 sin30, 2 cos30) = (-1, 1.7320508)
    assert t.apply_point((0.0, 2.0)) == approx((-1.0, 2 * SQRT3_2))


def test_rotation_incremental_angle():
    t = ProgramTransform().with_rotation((0.0, 0.0), 30.0).with_rotation((0.0, 0.0), 60.0, incremental=True)
    assert t.rotation_angle == 90.0
    assert t.apply_point((1.0, 0.0)) == (0.0, 1.0)


def test_arc_rotates_with_its_centre():
    t = ProgramTransform().with_rotation((10.0, 0.0), 90.0)
    # end (20, 0) -> (10, 10) as above; centre (15, 0): d = (5, 0) -> (0, 5) -> (10, 5)
    res = t.apply_arc((20.0, 0.0, -1.0), (15.0, 0.0), clockwise=True)
    assert res == ArcResult((10.0, 10.0, -1.0), (10.0, 5.0), True, 1.0)


def test_rotation_in_g18():
    # G18: local (first, second) = (Z, X); rotation +90 turns +Z towards +X.
    t = ProgramTransform().with_plane(Plane.XZ).with_rotation((0.0, 0.0), 90.0)
    assert t.rotation_plane is Plane.XZ
    assert t.apply_point((1.0, 0.0)) == (0.0, 1.0)  # Z1 X0 -> Z0 X1
    # Full position: x=0, z=1 -> x=1, z=0; y untouched
    assert t.apply_position(pos(x=0, y=7, z=1)) == pos(x=1, y=7, z=0)


def test_rotation_refuses_arcs_in_another_plane():
    t = ProgramTransform().with_rotation((0.0, 0.0), 45.0)  # G17 rotation
    with pytest.raises(GCodeError, match="leave its plane"):
        t.apply_arc((1.0, 0.0), (0.5, 0.0), clockwise=True, plane=Plane.XZ)
    # A point of G18 without its normal (Y) cannot follow an XY rotation...
    with pytest.raises(GCodeError, match="G68 rotation"):
        t.apply_point((1.0, 0.0), plane=Plane.XZ)
    # ...with it, it can: local (z, x, y) = (5, 1, 0) -> x, y rotated by 45: (0.7071, 0.7071)
    out = t.apply_point((5.0, 1.0, 0.0), plane=Plane.XZ)
    assert out == approx((5.0, math.sqrt(0.5), math.sqrt(0.5)))
    # A rotation of the UV plane does not touch an XY arc.
    uv = ProgramTransform().with_rotation((0.0, 0.0), 45.0, plane=Plane.UV)
    res = uv.apply_arc((1.0, 0.0), (0.5, 0.0), clockwise=True)
    assert res == ArcResult((1.0, 0.0), (0.5, 0.0), True, 1.0)


# --- composition order (Fanuc: mirror, then scale, then rotate) -----------------------------------


def test_composition_order_mirror_scale_rotate():
    t = (ProgramTransform().with_mirror({"x": 0.0}).with_scale(pos(), 2.0)
         .with_rotation((0.0, 0.0), 90.0))
    # (1, 2) --mirror X--> (-1, 2) --scale 2--> (-2, 4) --rotate 90--> (-4, -2)
    assert t.apply_point((1.0, 2.0)) == (-4.0, -2.0)
    # Rotating first would give: (1,2) -> (-2,1) -> (-4,2) -> mirror (4,2): a different point.
    assert t.apply_point((1.0, 2.0)) != (4.0, 2.0)


def test_composition_does_not_depend_on_the_order_the_codes_were_given():
    a = ProgramTransform().with_mirror({"x": 1.0}).with_scale(pos(x=2, y=3), 1.5).with_rotation((4, 5), 33)
    b = ProgramTransform().with_rotation((4, 5), 33).with_scale(pos(x=2, y=3), 1.5).with_mirror({"x": 1.0})
    p = pos(x=7.25, y=-3.5, z=2)
    assert a == b
    assert a.apply_position(p) == b.apply_position(p)


def test_rotation_centre_is_scaled():
    # Fanuc: in G51 mode the G68 centre is scaled too. G51 P2 about 0, G68 X5 Y0 R180:
    t = ProgramTransform().with_scale(pos(), 2.0).with_rotation((5.0, 0.0), 180.0)
    # The programmed centre (5,0) scales to (10,0) and is the fixed point of the rotation.
    assert t.apply_point((5.0, 0.0)) == (10.0, 0.0)
    # (6,0) -> scale (12,0) -> 180 about (10,0) -> (8,0) = scale(rotate((6,0)) = (4,0)) = (8,0)
    assert t.apply_point((6.0, 0.0)) == (8.0, 0.0)


def test_scale_centre_is_mirrored():
    t = ProgramTransform().with_mirror({"x": 10.0}).with_scale(pos(x=0.0), 2.0)
    # the scaling centre X0 mirrors to 20; p=1 -> mirror 19 -> 20 + 2*(19-20) = 18
    assert t.apply_point((1.0, 0.0)) == (18.0, 0.0)


def test_mirror_reverses_the_machine_rotation():
    # Fanuc: with one plane axis mirrored, a G68 rotation turns the other way on the machine.
    t = ProgramTransform().with_mirror({"x": 0.0}).with_rotation((0.0, 0.0), 90.0)
    # (1, 0) -> mirror (-1, 0) -> rotate +90 -> (0, -1): clockwise from the mirrored start
    assert t.apply_point((1.0, 0.0)) == (0.0, -1.0)


def test_transform_change_keeps_machine_still():
    old = ProgramTransform().with_rotation((0.0, 0.0), 90.0)
    new = old.with_scale(pos(x=1, y=1), 3.0)
    prog = pos(x=2, y=5, z=1)
    machine = old.apply_position(prog)
    prog2 = new.invert_position(machine)
    assert new.apply_position(prog2) == approx(machine)


# --- G15/G16 polar --------------------------------------------------------------------------------


def test_polar_letters():
    assert polar_letters(Plane.XY) == ("x", "y")  # gcode-canon: X radius, Y angle
    assert polar_letters(Plane.XZ) == ("z", "x")  # G18: Z radius, X angle (Fanuc: first/second axis)
    assert polar_letters(Plane.YZ) == ("y", "z")


def test_polar_gcode_canon_is_relative_to_current_position():
    # current (10, 5), X2 Y90: (10 + 2 cos90, 5 + 2 sin90) = (10, 7), in G90 and G91 alike
    for incremental in (False, True):
        point, state = polar_target((10.0, 5.0), 2.0, 90.0, incremental=incremental,
                                    origin=PolarOrigin.CURRENT, state=PolarState())
        assert point == (10.0, 7.0)
        assert state == PolarState(2.0, 90.0)
    # Y word omitted: the last angle (90) is reused; X3 -> (10, 8)
    point, _ = polar_target((10.0, 5.0), 3.0, None, incremental=False, origin=PolarOrigin.CURRENT,
                            state=PolarState(2.0, 90.0))
    assert point == (10.0, 8.0)


def test_polar_fanuc_g90_origin_is_program_zero():
    # G90: radius 2 angle 90 from (0, 0): (0, 2), whatever the current position
    point, _ = polar_target((10.0, 5.0), 2.0, 90.0, incremental=False, origin=PolarOrigin.FANUC,
                            state=PolarState())
    assert point == (0.0, 2.0)
    # LinuxCNC's @1^90 is Y1: the same in G90
    point, _ = polar_target((0.0, 0.0), 1.0, 90.0, incremental=False, origin=PolarOrigin.FANUC,
                            state=PolarState())
    assert point == (0.0, 1.0)
    # radius omitted: the current position's radius, hypot(3, 4) = 5; angle 90 -> (0, 5)
    point, _ = polar_target((3.0, 4.0), None, 90.0, incremental=False, origin=PolarOrigin.FANUC,
                            state=PolarState())
    assert point == approx((0.0, 5.0))


def test_polar_fanuc_g90_angle_omitted_keeps_current_direction():
    # from (3, 4) (angle atan2(4, 3)), radius word 10, no angle word: 10 * (3/5, 4/5) = (6, 8)
    point, state = polar_target((3.0, 4.0), 10.0, None, incremental=False, origin=PolarOrigin.FANUC,
                                state=PolarState())
    assert point == approx((6.0, 8.0))
    assert state.angle == pytest.approx(math.degrees(math.atan2(4, 3)))


def test_polar_fanuc_g91_origin_is_current_position_and_angle_adds():
    # G91: from (10, 5), last angle 30, words X2 Y60 -> angle 90 -> (10, 7)
    point, state = polar_target((10.0, 5.0), 2.0, 60.0, incremental=True, origin=PolarOrigin.FANUC,
                                state=PolarState(1.0, 30.0))
    assert point == (10.0, 7.0)
    assert state == PolarState(2.0, 90.0)


def test_polar_in_g18():
    # G18 local (Z, X): from (0, 0), Z-word radius 10, X-word angle 30 -> Z = 10 cos30 = 8.660, X = 5
    point, _ = polar_target((0.0, 0.0), 10.0, 30.0, incremental=False, origin=PolarOrigin.FANUC,
                            state=PolarState())
    assert point == approx((10 * SQRT3_2, 5.0))
    # gcode-canon in G18 from (z=1, x=2): Z-word 4, X-word 180 -> (1 - 4, 2) = (-3, 2)
    point, _ = polar_target((1.0, 2.0), 4.0, 180.0, incremental=False, origin=PolarOrigin.CURRENT,
                            state=PolarState())
    assert point == (-3.0, 2.0)


def test_polar_errors():
    with pytest.raises(GCodeError, match="Polar radius"):
        polar_target((0.0, 0.0), math.nan, 0.0, incremental=False, origin=PolarOrigin.FANUC,
                     state=PolarState())
    with pytest.raises(GCodeError, match="out of range"):
        polar_target((1e308, 0.0), 1e308, 0.0, incremental=False, origin=PolarOrigin.CURRENT,
                     state=PolarState())


# --- G12/G13 full circle --------------------------------------------------------------------------


def test_g12_full_circle_expansion():
    moves = full_circle((10.0, 20.0), 5.0, clockwise=True)
    # lead-in along +first axis to (10+5, 20); a full clockwise turn around (10, 20); back to centre
    assert moves == [
        PlaneMove("feed", (15.0, 20.0)),
        PlaneMove("arc", (15.0, 20.0), centre=(10.0, 20.0), clockwise=True),
        PlaneMove("feed", (10.0, 20.0)),
    ]


def test_g13_with_tool_radius():
    moves = full_circle((0.0, 0.0), 5.0, clockwise=False, tool_radius=1.5)
    # the tool centre runs on 5 - 1.5 = 3.5 so that the pocket has radius 5
    assert moves[0] == PlaneMove("feed", (3.5, 0.0))
    assert moves[1] == PlaneMove("arc", (3.5, 0.0), centre=(0.0, 0.0), clockwise=False)
    assert moves[2].end == (0.0, 0.0)


def test_full_circle_errors():
    with pytest.raises(GCodeError, match="G12: I word"):
        full_circle((0.0, 0.0), None, clockwise=True)
    with pytest.raises(GCodeError, match="must be positive"):
        full_circle((0.0, 0.0), 0.0, clockwise=False)
    with pytest.raises(GCodeError, match="G13: circle radius"):
        full_circle((0.0, 0.0), -2.0, clockwise=False)
    with pytest.raises(GCodeError, match="not greater than the tool radius"):
        full_circle((0.0, 0.0), 2.0, clockwise=True, tool_radius=2.0)
    with pytest.raises(GCodeError, match="negative tool radius"):
        full_circle((0.0, 0.0), 2.0, clockwise=True, tool_radius=-0.5)


def test_full_circle_through_mirror_turns_the_other_way():
    t = ProgramTransform().with_mirror({"x": 0.0})
    arc = full_circle((10.0, 0.0), 2.0, clockwise=True)[1]
    res = t.apply_arc(arc.end, arc.centre, arc.clockwise)
    # end (12, 0) -> (-12, 0), centre (10, 0) -> (-10, 0), G12 runs counter-clockwise
    assert res == ArcResult((-12.0, 0.0), (-10.0, 0.0), False, 1.0)


# --- properties -----------------------------------------------------------------------------------

coord = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)
finite = st.floats(allow_nan=False, allow_infinity=False)
letters = st.sampled_from(AXES)


@settings(max_examples=200, deadline=None)
@given(angle=st.floats(-720, 720), cx=coord, cy=coord, p=st.tuples(coord, coord), q=st.tuples(coord, coord))
def test_rotation_preserves_distances(angle, cx, cy, p, q):
    t = ProgramTransform().with_rotation((cx, cy), angle)
    tp, tq = t.apply_point(p), t.apply_point(q)
    assert math.dist(tp, tq) == pytest.approx(math.dist(p, q), rel=1e-9, abs=1e-6)


@settings(max_examples=200, deadline=None)
@given(lines=st.dictionaries(letters, coord, min_size=1), p=st.tuples(*[coord] * 9))
def test_mirror_twice_is_identity(lines, p):
    t = ProgramTransform().with_mirror(lines)
    assert t.apply_position(t.apply_position(p)) == approx(p, abs_tol=1e-6)
    assert t.with_mirror(lines) == t  # G22 twice on the same lines is the same mirror


@settings(max_examples=200, deadline=None)
@given(m=st.dictionaries(letters, coord), s=st.floats(0.01, 100), sc=st.tuples(*[coord] * 9),
       angle=st.floats(-360, 360), rc=st.tuples(coord, coord), p=st.tuples(*[coord] * 9))
def test_inverse_undoes_transform(m, s, sc, angle, rc, p):
    t = ProgramTransform().with_scale(sc, s).with_rotation(rc, angle)
    if m:
        t = t.with_mirror(m)
    assert t.invert_position(t.apply_position(p)) == approx(p, abs_tol=1e-3)


@settings(max_examples=300, deadline=None)
@given(
    m=st.dictionaries(letters, finite),
    s=st.one_of(finite, st.dictionaries(st.sampled_from("xyzuvw"), finite)),
    sc=st.tuples(*[finite] * 9),
    angle=finite,
    rc=st.tuples(finite, finite),
    plane=st.sampled_from(list(Plane)),
    p=st.tuples(*[finite] * 9),
    local=st.tuples(finite, finite, finite),
    centre=st.tuples(finite, finite),
    r=st.one_of(st.none(), finite),
    a=st.one_of(st.none(), finite),
    cw=st.booleans(),
)
def test_only_gcode_errors_for_finite_inputs(m, s, sc, angle, rc, plane, p, local, centre, r, a, cw):
    steps = [
        lambda t: t.with_mirror(m),
        lambda t: t.with_scale(sc, s),
        lambda t: t.with_rotation(rc, angle),
        lambda t: t.with_plane(plane),
    ]
    t = ProgramTransform()
    for step in steps:
        with contextlib.suppress(GCodeError):
            t = step(t)
    for call in (
        lambda: t.apply_position(p),
        lambda: t.invert_position(p),
        lambda: t.apply_point(local[:2]),
        lambda: t.apply_point(local),
        lambda: t.invert_point(local),
        lambda: t.apply_arc(local, centre, cw),
        lambda: t.scale_radius(local[0]),
        lambda: t.comp_side("left"),
        lambda: polar_target(centre, r, a, incremental=cw, origin=PolarOrigin.FANUC, state=PolarState()),
        lambda: polar_target(centre, r, a, incremental=cw, origin=PolarOrigin.CURRENT,
                             state=PolarState(local[0], local[1])),
        lambda: full_circle(centre, r, cw, tool_radius=abs(local[2])),
    ):
        with contextlib.suppress(GCodeError):
            call()
