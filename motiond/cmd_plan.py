"""``canon plan``: plan a program without a machine and report what the drives would get.

The program is interpreted as ``canon check`` does (a dry run), planned from rest at machine zero on
the configured machine (the demo mill without ``--config``), and the setpoint stream is measured
with ``planner.check_stream``: the run time, each axis's peak velocity, acceleration and jerk
against its limits, the deviation from the programmed path and the exact stops.

``--plot out.png`` draws the tool path and the velocity, acceleration and jerk over time;
``--setpoints out.csv`` writes the stream (``t,x,y,z,...``, one row per cycle); ``--json`` prints the
summary as one JSON object. Exit status 0 when the stream passes every check, 2 when it does not
(a planner fault to report), 1 for a user mistake.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from motiond.cli import UserError, add_common, program_file


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from motiond.interp_settings import add_arguments as add_interp_arguments

    add_common(parser)
    parser.add_argument("--plot", metavar="out.png", help="draw tool path, velocity, acceleration, jerk")
    parser.add_argument("--setpoints", metavar="out.csv", help="write the setpoint stream as CSV")
    add_interp_arguments(parser)


def run(args: argparse.Namespace) -> int:
    import time
    from array import array

    import numpy as np

    from gcode_canon.interpreter import Interpreter
    from gcode_canon.machine import DryRunMachine
    from motiond.config_check import load_checked
    from motiond.interp_settings import settings_from_args
    from motiond.progress import line_progress, tracked
    from planner import check_stream, plan_all

    program_file(args.file)
    config = load_checked(args.config)
    machine = config.limits
    settings = settings_from_args(config, args, dry_run=True)
    interp = Interpreter(settings, DryRunMachine())
    started = time.perf_counter()
    n = len(machine.axes)
    flat = array("d")
    commands: list[Any] = []
    show = sys.stderr.isatty() and not args.json
    with line_progress(f"planning {Path(args.file).name}", args.file, enabled=show) as advance:
        # interpreted lazily as the planner asks (its lookahead window), kept for the check
        source = tracked(interp.run_file(args.file), args.file, advance)

        def recorded() -> Iterator[Any]:
            for cmd in source:
                commands.append(cmd)
                yield cmd

        for sp in plan_all(recorded(), machine):
            flat.extend(sp.positions)
    planning_s = time.perf_counter() - started
    pts = np.frombuffer(flat, dtype=float).reshape(-1, n) if len(flat) else np.zeros((0, n))
    report = check_stream(pts, commands, machine)
    summary = _summary(args.file, config, report, planning_s)
    if args.setpoints:
        _write_csv(args.setpoints, machine, pts)
    if args.plot:
        _plot(args.plot, args.file, machine, pts, report)
    if args.json:
        import json

        print(json.dumps(summary))
    else:
        _print_table(summary, report)
    if not report.ok:
        for problem in report.problems():
            print(f"canon plan: {args.file}: {problem}", file=sys.stderr)
        return 2
    return 0


def _summary(file: str, config: Any, report: Any, planning_s: float) -> dict[str, Any]:
    def peaks(p: Any) -> dict[str, float]:
        return {"velocity": p.velocity, "acceleration": p.acceleration, "jerk": p.jerk}

    return {
        "file": file,
        "machine": config.limits.name,
        "config": config.path,
        "cycle_s": report.cycle_s,
        "duration_s": report.duration_s,
        "cycles": report.cycles,
        "axes": list(report.axes),
        "units": {a.name: a.unit for a in config.limits.axes},
        "limits": {ax: peaks(report.limits[ax]) for ax in report.axes},
        "peaks": {ax: peaks(report.peaks[ax]) for ax in report.axes},
        "within_limits": report.within_limits,
        "max_deviation": report.max_deviation,
        "deviation_ok": report.deviation_excess <= 0.0,
        "exact_stops": report.stops_total,
        "exact_stops_missed": [{"file": f, "line": ln, "point": list(p)} for f, ln, p in report.stops_missed],
        "final_position": dict(zip(report.axes, report.final_position, strict=True)),
        "ok": report.ok,
        "planning_s": planning_s,
    }


def _print_table(summary: dict[str, Any], report: Any) -> None:
    from rich.console import Console
    from rich.table import Table

    console = Console(width=None if sys.stdout.isatty() else 120)
    cycles = summary["cycles"]
    console.print(f"[bold]{summary['file']}[/bold] on {summary['machine']}: cycle time "
                  f"[bold]{summary['duration_s']:.3f} s[/bold] ({cycles} cycles of "
                  f"{summary['cycle_s'] * 1e3:g} ms), planned in {summary['planning_s']:.2f} s")
    table = Table(show_header=True, header_style="bold")
    table.add_column("axis")
    table.add_column("unit")
    for name in ("velocity", "acceleration", "jerk"):
        table.add_column(f"{name}: peak / limit", justify="right")
    for ax in summary["axes"]:
        cells = []
        for name in ("velocity", "acceleration", "jerk"):
            peak, limit = summary["peaks"][ax][name], summary["limits"][ax][name]
            ratio = peak / limit
            text = f"{peak:,.0f} / {limit:,.0f} ({ratio * 100:.0f} %)"
            cells.append(f"[red]{text}[/red]" if ratio > 1.01 else text)
        table.add_row(ax.upper(), summary["units"][ax], *cells)
    console.print(table)
    dev = summary["max_deviation"]
    console.print(f"path deviation: max {dev * 1000:.4f} µm" if dev < 1e-3 else
                  f"path deviation: max {dev:.4f} mm (blends)", highlight=False)
    missed = len(summary["exact_stops_missed"])
    console.print(f"exact stops reached: {summary['exact_stops'] - missed} of {summary['exact_stops']}")
    console.print("[green]all checks pass[/green]" if report.ok else "[red]checks failed[/red]")


def _write_csv(path: str, machine: Any, pts: Any) -> None:
    import io

    from gcode_canon.atomicfile import atomic_write

    out = io.StringIO()
    out.write(",".join(["t", *machine.names]) + "\n")
    T = machine.cycle_s
    for k, row in enumerate(pts.tolist(), start=1):
        out.write(f"{k * T:.6f}," + ",".join(repr(v) for v in row) + "\n")
    try:
        atomic_write(path, out.getvalue().encode())
    except OSError as exc:
        raise UserError(f"{path}: cannot write: {exc.strerror}") from None


def _envelope(t: Any, y: Any, buckets: int = 4000) -> tuple[Any, Any, Any]:
    """Min and max of ``y`` in at most ``buckets`` time slices, so that no peak is lost in the plot."""
    import numpy as np

    if len(y) <= buckets:
        return t, y, y
    k = int(np.ceil(len(y) / buckets))
    m = len(y) // k * k
    return t[:m:k], y[:m].reshape(-1, k).min(axis=1), y[:m].reshape(-1, k).max(axis=1)


def _plot(path: str, title: str, machine: Any, pts: Any, report: Any) -> None:
    import os
    import tempfile

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    T = machine.cycle_s
    start = np.zeros((3, pts.shape[1]))
    padded = np.vstack([start, pts, np.repeat(pts[-1:], 3, axis=0)]) if len(pts) else start
    fig = plt.figure(figsize=(14, 9), layout="constrained")
    grid = fig.add_gridspec(3, 2, width_ratios=(1.1, 1.4))
    names = machine.names
    linear = [i for i, a in enumerate(machine.axes) if not a.rotary]
    ax_path = fig.add_subplot(grid[:, 0], projection="3d" if len(linear) >= 3 else None)
    speed = np.linalg.norm(np.diff(padded[2:-3][:, linear[:3]], axis=0), axis=1) / T
    if len(pts) > 1 and len(linear) >= 3:
        xs, ys, zs = (pts[:, i] for i in linear[:3])
        sc = ax_path.scatter(xs, ys, zs, c=speed, s=1, cmap="viridis")
        ax_path.set_zlabel(names[linear[2]].upper())
    elif len(pts) > 1 and len(linear) >= 2:
        sc = ax_path.scatter(pts[:, linear[0]], pts[:, linear[1]], c=speed, s=1, cmap="viridis")
    else:
        sc = None
    if sc is not None:
        fig.colorbar(sc, ax=ax_path, shrink=0.6, label="path speed (units/s)")
        ax_path.set_xlabel(names[linear[0]].upper())
        ax_path.set_ylabel(names[linear[1]].upper())
    ax_path.set_title(f"{os.path.basename(title)}: tool path, {report.duration_s:.2f} s")
    for row, (order, key) in enumerate(((1, "velocity"), (2, "acceleration"), (3, "jerk"))):
        ax = fig.add_subplot(grid[row, 1])
        d = np.diff(padded, order, axis=0) / T**order
        t = (np.arange(len(d)) - 2) * T
        for i, name in enumerate(names):
            tt, lo, hi = _envelope(t, d[:, i])
            line = ax.plot(tt, hi, lw=0.8, label=name.upper())[0]
            if lo is not hi:
                ax.fill_between(tt, lo, hi, color=line.get_color(), alpha=0.5)
            limit = getattr(report.limits[name], key)
            ax.axhline(limit, color=line.get_color(), ls="--", lw=0.6)
            ax.axhline(-limit, color=line.get_color(), ls="--", lw=0.6)
        ax.set_ylabel(f"{key} (/s{'' if order == 1 else '²' if order == 2 else '³'})")
        ax.grid(alpha=0.3)
        if row == 0:
            ax.legend(loc="upper right", ncol=len(names), fontsize="small")
            ax.set_title("per axis, from the setpoints (dashed: limits)")
    ax.set_xlabel("time (s)")
    directory = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix=".plot.", suffix=".png", dir=directory)
    os.close(fd)
    try:
        fig.savefig(tmp, dpi=110)
        os.replace(tmp, path)
    except OSError as exc:
        raise UserError(f"{path}: cannot write: {exc.strerror}") from None
    finally:
        plt.close(fig)
        if os.path.exists(tmp):
            os.unlink(tmp)
