"""What CAM programs write (issue 17): corners in G64 without P, rotary axes under G64 P, zero-length
moves under exact stop, collinear and rounded pieces, tiny segments, the feed's effect on a chain.

Each test checks a property of the plan (a ratio, an ordering, a bound from the limits), never a
figure copied from the planner's output; ``check_stream`` judges limits, deviation and stops.
"""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest

from gcode_canon.commands import (
    ArcFeed,
    DigitalOutput,
    ExactStopBlock,
    MotionControlMode,
    Plane,
    Pose,
    ProgramEnd,
    SetFeedRate,
    SetMotionControlMode,
    StraightFeed,
)
from planner import DEMO_MACHINE, AxisLimits, MachineLimits, check_stream, plan_all

T = DEMO_MACHINE.cycle_s
A_X = DEMO_MACHINE.axes[0].max_acceleration
G61_1 = SetMotionControlMode(MotionControlMode.EXACT_STOP_MODAL)


def g64(p: float = 0.0, q: float = 0.0) -> SetMotionControlMode:
    return SetMotionControlMode(MotionControlMode.CONTINUOUS, p, q)


def numbered(cmds: list) -> list:
    return [dataclasses.replace(c, line=i + 1, file="cam.ngc") for i, c in enumerate(cmds)]


def run(prog: list, machine: MachineLimits = DEMO_MACHINE):
    prog = numbered(prog)
    sps = list(plan_all(prog, machine, max_cycles=2_000_000))
    report = check_stream(sps, prog, machine)
    assert report.ok, report.problems()
    return sps, report


def square(feed: float) -> list:
    return [g64(), SetFeedRate(feed)] + [StraightFeed(Pose(x, y, 0)) for x, y in
                                         ((100, 0), (100, 100), (0, 100), (0, 0), (100, 0))] + [ProgramEnd()]


def corner_speed(sps: list, corner: tuple[float, float]) -> float:
    """The path speed at the setpoint nearest the corner."""
    pts = np.array([sp.positions for sp in sps])
    k = int(np.argmin(np.linalg.norm(pts[:, :2] - np.array(corner), axis=1)))
    return float(np.linalg.norm(pts[k + 1] - pts[k - 1])) / (2 * T)


@pytest.mark.parametrize("feed", [600.0, 1500.0])
def test_g64_without_p_blends_only_as_much_as_the_feed_needs(feed: float) -> None:
    """LinuxCNC's rule: the blend is sized by the speed it must keep (here the feed), never half the
    segment: the corner deviation is of the order of v^2/a, and the corner is passed at the feed."""
    sps, report = run(square(feed))
    v = feed / 60.0
    assert report.max_deviation <= 1.1 * v * v / A_X
    assert report.max_deviation < 0.01 * 50.0  # far below half a side (what it was)
    # the blend keeps the path speed at the feed; the tool's speed at the blend's middle is that
    # times |w1 + w2| / 2 (the quintic blend's parameter is not arc length): 0.707 here
    assert corner_speed(sps, (100.0, 100.0)) >= 0.97 * v * math.sqrt(0.5)
    assert len(sps) * T <= 500.0 / v + 0.5  # no time lost at the corners beyond starting and stopping


def test_g64_without_p_deviation_grows_with_the_feed() -> None:
    _, slow = run(square(600.0))
    _, fast = run(square(1500.0))
    assert fast.max_deviation > 2.0 * slow.max_deviation  # (v^2: 6.25 times)


ROTARY = MachineLimits(axes=(*DEMO_MACHINE.axes, AxisLimits("a", 360.0, 3000.0, 50000.0)), cycle_s=T)


@pytest.mark.parametrize("p", [0.02, 0.1])
def test_g64_p_with_a_rotary_move_keeps_the_tolerance(p: float) -> None:
    """The tolerance holds over all axes together (mm and degrees): so in XYZ and in A alone."""
    prog = [g64(p), SetFeedRate(1000), StraightFeed(Pose(10, 0, 0, a=0)), StraightFeed(Pose(10, 10, 0, a=30)),
            StraightFeed(Pose(0, 10, 0, a=30)), StraightFeed(Pose(0, 0, 0, a=0)), ProgramEnd()]
    _sps, report = run(prog, ROTARY)
    assert report.max_deviation <= p
    assert report.max_deviation > 0.1 * p  # the corners were blended (not stopped)


@pytest.mark.parametrize("where", ["first", "middle", "last"])
def test_zero_length_move_under_g61_1_passes_its_own_check(where: str) -> None:
    moves = [StraightFeed(Pose(10, 0, 0)), StraightFeed(Pose(10, 5, 0))]
    zero = {"first": 0, "middle": 1, "last": 2}[where]
    at = Pose(0, 0, 0) if zero == 0 else moves[zero - 1].end
    moves.insert(zero, StraightFeed(at))
    _, report = run([G61_1, SetFeedRate(1000), *moves, ProgramEnd()])
    assert report.stops_total >= 2 and not report.stops_missed


def test_zero_length_g9_move_before_any_motion() -> None:
    _, report = run([g64(0.01), SetFeedRate(1000), ExactStopBlock(), StraightFeed(Pose(0, 0, 0)),
                     StraightFeed(Pose(10, 5, 0)), ProgramEnd()])
    assert not report.stops_missed


def line_pieces(length: float, pieces: int, feed: float, mode: SetMotionControlMode) -> list:
    """A line along (1, 0.6) as ``pieces`` collinear moves, written with 4 decimals."""
    return [mode, SetFeedRate(feed)] + [StraightFeed(Pose(round(length * k / pieces, 4),
                                                          round(0.6 * length * k / pieces, 4), 0))
                                        for k in range(1, pieces + 1)] + [ProgramEnd()]


@pytest.mark.parametrize("mode", [g64(0.01), g64(), SetMotionControlMode(MotionControlMode.EXACT_PATH)],
                         ids=["G64P", "G64", "G61"])
@pytest.mark.parametrize(("length", "pieces"), [(50.0, 250), (5.0, 5000)])
def test_a_line_as_collinear_pieces_takes_the_time_of_one_line(mode, length: float, pieces: int) -> None:
    one, _ = run(line_pieces(length, 1, 6000, mode))
    many, report = run(line_pieces(length, pieces, 6000, mode))
    assert len(many) <= 1.03 * len(one)
    assert report.max_deviation <= 1e-3


def test_merged_pieces_still_name_their_lines_in_order() -> None:
    sps, _ = run(line_pieces(50.0, 250, 600, g64(0.01)))
    lines = [sp.line for sp in sps if sp.line]
    assert lines == sorted(lines)
    assert set(range(3, 253)) <= set(lines)  # at F600 a cycle covers 0.02 mm, a piece 0.2 mm: all seen


def test_a_reversal_along_the_line_is_not_merged_away() -> None:
    prog = [g64(0.01), SetFeedRate(3000)] + [StraightFeed(Pose(x, 0, 0)) for x in (10, 5, 10, 5, 10)] + [
        ProgramEnd()]
    sps, _ = run(prog)
    x = np.array([sp.positions[0] for sp in sps])
    turns = np.sum(np.diff(np.sign(np.diff(x[np.abs(np.diff(x, append=x[-1])) > 1e-9]))) != 0)
    assert turns >= 4  # out, back, out, back, out: every reversal is travelled
    assert x.min() <= 5.0 + 1e-6 and np.sum(x >= 10.0 - 1e-6) > 0


def circle_chords(radius: float, step: float, sweep: float, feed: float, p: float) -> tuple[list, list]:
    """An arc of ``radius`` about the origin from (radius, 0) turning by ``sweep``, written as chords of
    ``step`` mm with 4 decimals, and the same arc as one G3."""
    n = round(sweep * radius / step)
    end = Pose(round(radius * math.cos(sweep), 4), round(radius * math.sin(sweep), 4), 0)
    head = [g64(p), SetFeedRate(feed), StraightFeed(Pose(radius, 0, 0))]
    chords = head + [StraightFeed(Pose(round(radius * math.cos(k * sweep / n), 4),
                                       round(radius * math.sin(k * sweep / n), 4), 0)) for k in range(1, n)]
    arc = ArcFeed(end, Pose(), Plane.XY, 1)
    return [*chords, StraightFeed(end), ProgramEnd()], [*head, arc, ProgramEnd()]


@pytest.mark.parametrize(("radius", "step", "feed"), [(10.0, 0.01, 6000), (20.0, 0.01, 6000),
                                                   (10.0, 0.05, 6000), (20.0, 0.1, 3000), (10.0, 0.1, 6000)])
def test_chords_of_a_circle_take_the_time_of_the_arc(radius: float, step: float, feed: float) -> None:
    """Dense chords that lie within the merge tolerance of one arc are planned as that arc: the cycle
    time is the G3's (they took 1.1-1.8 times as long as chains of merged lines; chords of 0.05-0.1 mm,
    of which only 4-9 lie within P/4 of one line, 1.04-1.22 times), the path stays within P of the
    chords, and the setpoints still name the chords' lines in order."""
    chords, arc = circle_chords(radius, step, 4.0, feed, 0.01)
    sps, report = run(chords)
    one, _ = run(arc)
    assert len(sps) <= 1.03 * len(one)
    assert report.max_deviation <= 0.01
    lines = [sp.line for sp in sps if sp.line]
    assert lines == sorted(lines) and len(chords) - 1 in lines


G61 = SetMotionControlMode(MotionControlMode.EXACT_PATH)


@pytest.mark.parametrize(("mode", "radius", "step"),
                         [(g64(), 20.0, 0.01), (g64(), 20.0, 0.05), (g64(), 10.0, 0.1), (g64(), 5.0, 0.1),
                          (G61, 20.0, 0.01), (G61, 10.0, 0.05)])
def test_chords_of_a_circle_without_p_take_the_time_of_the_arc(mode, radius: float, step: float) -> None:
    """In G64 without P and in G61 the merge tolerance is about the rounding of 4 decimals: the
    rounding noise of the fit's middle point alone spoils the three-point circle, so the centre is
    refitted to all points, and an arc may hold the rounding plus the chords' own sagitta (2e-4 mm);
    the chords are then planned as the arc (they took 2.9-3.5 times the G3's time in G64 without P,
    10-17 times in G61); ``run`` checks that the path in G61 stays within the exact path's 1 um. In
    G64 without P the points must lie within the same 2e-4 mm and the chords within 1e-3 mm of the
    arc: 0.1 mm chords on R 10 mm (sagitta 1.25e-4 mm) split into arcs where a point's rounding was
    near its largest, and a short first arc made the corner into it slow (1.12-1.16 times the G3);
    on R 5 mm (sagitta 2.5e-4 mm) none was merged (3 times the G3)."""
    chords, arc = circle_chords(radius, step, 2.0, 6000, 0.0)
    chords[0] = arc[0] = mode
    sps, _ = run(chords)
    one, _ = run(arc)
    assert len(sps) <= 1.03 * len(one)


def spiral(segments: int, step: float, feed: float, decimals: int, p: float = 0.01) -> list:
    r0, r1 = 3.0, 12.0
    length = segments * step
    theta_end = length / (0.5 * (r0 + r1))
    b = (r1 - r0) / theta_end
    prog: list = [g64(p), SetFeedRate(feed), StraightFeed(Pose(r0, 0, 0))]
    theta = 0.0
    for k in range(segments):
        theta += step / math.hypot(r0 + b * theta, b)
        r = r0 + b * theta
        prog.append(StraightFeed(Pose(round(r * math.cos(theta), decimals),
                                      round(r * math.sin(theta), decimals), round(k / segments, decimals))))
    return [*prog, ProgramEnd()]


@pytest.mark.parametrize("decimals", [3, 4])
@pytest.mark.parametrize("p", [0.01, 0.05])
def test_rounding_to_3_or_4_decimals_does_not_change_the_plan(p: float, decimals: int) -> None:
    fine, _ = run(spiral(600, 0.05, 1000, 8, p))
    rounded, report = run(spiral(600, 0.05, 1000, decimals, p))
    assert abs(len(rounded) - len(fine)) <= 0.03 * len(fine)
    assert report.max_deviation <= p


def test_a_higher_feed_never_takes_longer_through_a_chain() -> None:
    times = [len(run(spiral(400, 0.2, f, 4))[0]) for f in (1000, 1500, 2000, 2500, 3000, 4000)]
    assert all(b <= a for a, b in itertools.pairwise(times)), times


def test_tiny_segments_run_near_the_acceleration_bound() -> None:
    """20,000 moves of 0.001 mm at F6000 (each shorter than a cycle's travel): within 1.5 times the
    time of the whole path at the feed from rest to rest under the acceleration limit alone."""
    step = 0.001 / math.sqrt(2.0)
    prog = [g64(0.01), SetFeedRate(6000)] + [StraightFeed(Pose(round(step * k, 4), round(step * k, 4), 0))
                                             for k in range(1, 20001)] + [ProgramEnd()]
    sps, _ = run(prog)
    v, a, length = 100.0, A_X * math.sqrt(2.0), 20.0  # along the diagonal both axes share the work
    bound = length / v + v / a  # accelerating and braking cost v/(2a) each
    assert len(sps) * T <= 1.5 * bound


def test_an_output_on_a_move_shorter_than_a_cycle_is_not_lost() -> None:
    """A synced output rides on the first setpoint of its move; a 1 um move at F600 lies between two
    samples, so it rides on the first setpoint after it (it was dropped)."""
    prog = [g64(), SetFeedRate(600), StraightFeed(Pose(10, 0, 0)),
            DigitalOutput(1, True, synced=True), StraightFeed(Pose(10.001, 0, 0)),
            DigitalOutput(2, True, synced=True), StraightFeed(Pose(12, 0, 0)), ProgramEnd()]
    sps, _ = run(prog)
    outs = [e.index for sp in sps for e in sp.events if isinstance(e, DigitalOutput)]
    assert sorted(outs) == [1, 2]


@pytest.mark.parametrize("wave", [(7.77, 0.0725, 1.70, 0.324), (3.9037, 0.0681, 1.4249, 0.3614)])
def test_a_higher_feed_never_takes_longer_on_a_wavy_chain(wave: tuple[float, float, float, float]) -> None:
    """CAM-like waves (0.2 mm chords, 3 decimals, G64 P0.005): the smoothing and chaining decisions
    and the pieces' path limits do not depend on the feed, so the pieces do not change with F and a
    higher F only lifts speed caps. (The second wave took 2.6 % longer at F3000 than at F2500 when a
    chain ended where its next span fell below 85 % of the feed.)"""
    a1, f1, a2, f2 = wave
    xs = [0.2 * k for k in range(1, 401)]
    pts = [(round(x, 3), round(a1 * math.sin(f1 * x) + a2 * math.sin(f2 * x), 3), 0) for x in xs]
    times = []
    for feed in (2000, 2500, 3000, 4000):
        sps, _ = run([g64(0.005), SetFeedRate(feed)] + [StraightFeed(Pose(*p)) for p in pts] + [ProgramEnd()])
        times.append(len(sps))
    assert all(b <= a for a, b in itertools.pairwise(times)), times


@pytest.mark.parametrize("radius", [5.0, 20.0])
def test_arc_fit_refits_the_centre_where_rounding_spoils_three_points(radius: float) -> None:
    """Points of a circle rounded to 4 decimals, tolerance 1e-4 mm (the rounding itself): wherever the
    three-point circle misses, the refitted centre is tried, and every arc returned bounds the true
    distance of the points from it (``dev``)."""
    from planner.arcfit import fit_arc

    planes = [(0, 1), (0, 2), (1, 2)]
    found = plain = 0
    for n, step in itertools.product((8, 30, 120), (0.01, 0.03)):
        for k0 in range(0, 40, 4):
            pts = [(round(radius * math.cos((k0 + k) * step / radius), 4),
                    round(radius * math.sin((k0 + k) * step / radius), 4), 0.0) for k in range(n + 2)]
            refit = fit_arc(pts[0], pts[1:-1], pts[-1], 1e-4, planes, refine=True)
            three = fit_arc(pts[0], pts[1:-1], pts[-1], 1e-4, planes)
            plain += three is not None
            if three is not None:
                assert refit is not None  # refitting only where the plain fit fails
            if refit is None:
                continue
            found += 1
            c = (refit.c0, refit.c1)
            r = math.dist(pts[0][:2], c)
            assert abs(math.dist(pts[-1][:2], c) - r) <= 1e-9  # the arc still ends on both end points
            assert max(abs(math.dist(p[:2], c) - r) for p in pts) <= refit.dev <= 1e-4
    assert found > plain  # the refit finds arcs the three points miss


def test_each_cycle_reads_a_piece_as_its_position_and_line() -> None:
    """The cycle loop reads the running piece once per cycle (``sample``: position and programmed move
    together, one lookup of the part): the same values as ``pos`` and ``cmd_at`` on every kind of
    piece CAM code becomes (smoothed chains over merged lines, merged lines, merged arcs, blends),
    forwards, backwards and beyond both ends."""
    from planner import Planner
    from planner.segments import Seg

    chords, _ = circle_chords(10.0, 0.05, 3.0, 3000, 0.01)
    collinear = [StraightFeed(Pose(0.5 * k, 0, 0)) for k in range(1, 20)]  # on to (10, 0), the arc's start
    prog = numbered([*chords[:2], *collinear, *chords[2:-1], *spiral(300, 0.2, 2000, 4)])
    p = Planner(DEMO_MACHINE, auto_release=True)
    p.feed_many(prog)
    p.flush()
    kinds = set()
    for item in p._q[p._h:]:
        if not isinstance(item, Seg):
            continue
        piece = item.piece
        kinds.add(type(piece).__name__)
        grid = [piece.length * k / 97 for k in range(-3, 101)]
        for s in [*grid, *reversed(grid)]:
            pos, cmd = piece.sample(s)
            assert (pos, cmd) == (piece.pos(s), piece.cmd_at(s))
    assert {"Chain", "MergedLine", "MergedArc"} <= kinds, kinds


def test_arc_fit_holds_each_point_within_its_own_tolerance() -> None:
    """G64 without P allows the chords' sagitta (1e-3 mm) but not the points: a point 5e-4 mm off the
    circle fits within the chords' tolerance alone, and is refused with the points' 2e-4 mm."""
    from planner.arcfit import fit_arc

    pts = [(10.0 * math.cos(k * 0.005), 10.0 * math.sin(k * 0.005), 0.0) for k in range(41)]
    pts[13] = (pts[13][0] * (1 + 5e-5), pts[13][1] * (1 + 5e-5), 0.0)  # 5e-4 mm outwards
    planes = [(0, 1), (0, 2), (1, 2)]
    loose = fit_arc(pts[0], pts[1:-1], pts[-1], 1e-3, planes, refine=True)
    assert loose is not None and 5e-4 <= loose.dev <= 1e-3
    assert fit_arc(pts[0], pts[1:-1], pts[-1], 1e-3, planes, refine=True, point_tol=2e-4) is None


def test_g61_stops_at_every_vertex_no_arc_holds() -> None:
    """G61 keeps the exact path: chords no arc holds within 2e-4 mm (0.2 mm on R 20 mm, sagitta
    2.5e-4 mm) turn by a corner at every vertex, and the motion stops on each (a setpoint on every
    programmed point, as LinuxCNC's G61 stops where its kink rule does not pass the turn); dense
    chords of the same circle (0.05 mm) are merged into the arc and do not stop."""
    sparse, _ = circle_chords(20.0, 0.2, 1.0, 6000, 0.0)
    dense, _ = circle_chords(20.0, 0.05, 1.0, 6000, 0.0)
    for prog, stops in ((sparse, True), (dense, False)):
        prog[0] = G61
        sps, _ = run(prog)
        pts = np.array([sp.positions for sp in sps])
        vertices = [(c.end.x, c.end.y, c.end.z) for c in prog[3:] if isinstance(c, StraightFeed)]
        met = sum(np.min(np.linalg.norm(pts - np.array(v), axis=1)) <= 1e-9 for v in vertices)
        if stops:
            assert met == len(vertices)
        else:
            assert met <= 2  # the arc's end (and at most one other by chance)
