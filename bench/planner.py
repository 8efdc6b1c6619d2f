"""Planner benchmark: planning speed against real time, and cycle time against bounds.

    python bench/planner.py [--segments 100000] [--feed 2000] [--step 0.2] [--check]

(1) A 3-D surfacing toolpath (a raster over a wavy surface, ``--segments`` short G1 segments in G64
    P0.01) is planned at 2 ms on one core; the figure is the program's run time divided by the wall
    time the planning took (target: at least 50x faster than real time).
(2) The program's cycle time against a lower bound, each segment at its feed (capped by the axis
    velocities along it) with the acceleration limit alone from and to rest, no jerk, corners or
    curvature; and against the same program in exact-stop mode (G61.1), planned the same way.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from gcode_canon.commands import (
    MotionControlMode,
    Pose,
    ProgramEnd,
    SetFeedRate,
    SetMotionControlMode,
    StraightFeed,
    StraightTraverse,
)
from planner import DEMO_MACHINE, check_stream, plan_all


def surfacing(segments: int, step: float, feed: float, mode: SetMotionControlMode) -> list:
    """Raster rows along X over z = 2 sin(x/7) cos(y/5) + 0.5 sin(x/2.3), stepping 0.5 mm in Y."""
    per_row = 500
    rows = max(1, segments // per_row)
    prog: list = [mode, SetFeedRate(feed), StraightTraverse(Pose(0, 0, 5))]
    line = 1
    for row in range(rows):
        y = row * 0.5
        xs = [i * step for i in range(per_row + 1)]
        if row % 2:
            xs.reverse()
        for k, x in enumerate(xs):
            if row > 0 and k == 0:
                continue  # the step over in Y to the next row is the row's first segment
            z = 2.0 * math.sin(x / 7.0) * math.cos(y / 5.0) + 0.5 * math.sin(x / 2.3)
            prog.append(StraightFeed(Pose(x, y, z), file="surface.ngc", line=line))
            line += 1
    prog.append(ProgramEnd(file="surface.ngc", line=line))
    return prog


def lower_bound(prog: list, machine=DEMO_MACHINE) -> float:
    """Each segment at its feed capped by the axis velocities, acceleration limit alone, from rest
    at the start to rest at the end (time-optimal bang-bang on the path length)."""
    names = machine.names
    pos = [0.0] * len(names)
    caps: list[tuple[float, float, float]] = []  # (length, speed cap, path acceleration limit)
    feed = 0.0
    for cmd in prog:
        if isinstance(cmd, SetFeedRate):
            feed = cmd.rate / 60.0
        if not isinstance(cmd, StraightFeed | StraightTraverse):
            continue
        end = [cmd.end[i] for i in machine.pose_index]
        d = [e - p for e, p in zip(end, pos, strict=True)]
        length = math.sqrt(sum(x * x for x in d))
        if length == 0:
            continue
        u = [abs(x) / length for x in d]
        v = min(a.max_velocity / ui for a, ui in zip(machine.axes, u, strict=True) if ui > 0)
        acc = min(a.max_acceleration / ui for a, ui in zip(machine.axes, u, strict=True) if ui > 0)
        if isinstance(cmd, StraightFeed):
            v = min(v, feed)
        caps.append((length, v, acc))
        pos = end
    # forward and backward passes with the acceleration limit (v^2 = v0^2 + 2 a s)
    n = len(caps)
    fwd = [0.0] * (n + 1)
    for i, (length, v, acc) in enumerate(caps):
        fwd[i + 1] = min(v, math.sqrt(fwd[i] ** 2 + 2 * acc * length))
    bwd = [0.0] * (n + 1)
    for i in range(n - 1, -1, -1):
        length, v, acc = caps[i]
        bwd[i] = min(v, math.sqrt(bwd[i + 1] ** 2 + 2 * acc * length))
    total = 0.0
    for i, (length, v, acc) in enumerate(caps):
        v0 = min(fwd[i], bwd[i])
        v1 = min(fwd[i + 1], bwd[i + 1])
        # accelerate from v0 towards v, decelerate to v1, cruise between
        peak = min(v, math.sqrt((2 * acc * length + v0 * v0 + v1 * v1) / 2))
        d_up = (peak * peak - v0 * v0) / (2 * acc)
        d_dn = (peak * peak - v1 * v1) / (2 * acc)
        total += (peak - v0) / acc + (peak - v1) / acc + max(length - d_up - d_dn, 0.0) / peak
    return total


def plan(prog: list) -> tuple[int, float, float]:
    """Cycles, CPU seconds of this process (one core: the figure that counts on a shared machine)
    and wall seconds."""
    wall, cpu = time.perf_counter(), time.process_time()
    count = 0
    for _sp in plan_all(prog, DEMO_MACHINE):
        count += 1
    return count, time.process_time() - cpu, time.perf_counter() - wall


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--segments", type=int, default=100_000)
    parser.add_argument("--step", type=float, default=0.2, help="segment length along X, mm")
    parser.add_argument("--feed", type=float, default=2000.0, help="mm/min")
    parser.add_argument("--check", action="store_true", help="also run the checker on the blended stream")
    args = parser.parse_args()
    T = DEMO_MACHINE.cycle_s

    blended = surfacing(args.segments, args.step, args.feed,
                        SetMotionControlMode(MotionControlMode.CONTINUOUS, 0.01))
    moves = sum(isinstance(c, StraightFeed) for c in blended)
    print(f"surfacing toolpath: {moves} segments of {args.step} mm at F{args.feed:g}, G64 P0.01, "
          f"cycle {T * 1e3:g} ms, demo machine")
    cycles, cpu, wall = plan(blended)
    run_time = cycles * T
    print(f"(1) planned {cycles} cycles ({run_time:.1f} s of motion) in {cpu:.2f} s of CPU "
          f"({wall:.2f} s wall): "
          f"{run_time / cpu:.0f}x faster than real time ({cpu / cycles * 1e6:.1f} us per cycle, "
          f"{cpu / moves * 1e6:.0f} us per segment)")
    bound = lower_bound(blended)
    exact = surfacing(args.segments, args.step, args.feed,
                      SetMotionControlMode(MotionControlMode.EXACT_STOP_MODAL))
    exact_cycles, exact_cpu, _ = plan(exact)
    print(f"(2) cycle time {run_time:.1f} s; lower bound (feed, acceleration alone) {bound:.1f} s: "
          f"ratio {run_time / bound:.2f}; exact stop (G61.1) {exact_cycles * T:.1f} s: "
          f"ratio {run_time / (exact_cycles * T):.2f} (exact stop planned at "
          f"{exact_cycles * T / exact_cpu:.0f}x real time)")
    if args.check:
        from array import array

        import numpy as np

        flat = array("d")
        for sp in plan_all(blended, DEMO_MACHINE):
            flat.extend(sp.positions)
        report = check_stream(np.frombuffer(flat).reshape(-1, 3), blended)
        worst = {ax: round(max(r.velocity, r.acceleration, r.jerk), 3)
                 for ax, r in ((ax, report.ratio(ax)) for ax in report.axes)}
        print(f"check: worst ratio to limits per axis {worst}, max deviation {report.max_deviation:.4f} mm, "
              f"ok={report.ok}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
