"""``canon plan``: plan a program without a machine and report what the drives would get.

The program is interpreted as ``canon check`` does (a dry run), planned from rest at machine zero on
the configured machine (the demo mill without ``--config``), and the setpoint stream is measured
with ``planner.check_stream``: the run time, each axis's peak velocity, acceleration and jerk
against its limits, the deviation from the programmed path and the exact stops.

``--plot out.png`` draws the programmed path under the planned one (3D and XY top view), the worst
deviation with its source line, and the velocity, acceleration and jerk over time with the limits
(:mod:`motiond.plan_plot`); ``--html out.html`` the same interactively (hover gives the time, the source
line and the speed); ``--setpoints out.csv`` writes the stream (``t,file,line,x,y,z,...,vx,vy,
vz,...``, one row per cycle); ``--json`` prints the
summary as one JSON object. ``--max-time`` bounds the planned machine time (8 h by default): past it
the plan stops with ``FILE:LINE`` of the line being planned (a slip such as ``F0.0001`` planned for
ever and filled the memory). Exit status 0 when the stream passes every check, 2 when it does not
(a planner fault to report), 1 for a user mistake.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from motiond.cli import UserError, add_common, program_file

MAX_TIME_S = 8 * 3600.0
"""Default bound on the planned machine time: the setpoints are all kept for the checks (about
100 bytes a cycle, 1.4 GB for 8 h at 2 ms), and a slip such as ``F0.0001`` would plan for years."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from motiond.interp_settings import add_arguments as add_interp_arguments

    add_common(parser)
    parser.add_argument("--plot", metavar="out.png", help="draw tool path, velocity, acceleration, jerk")
    parser.add_argument("--html", metavar="out.html",
                        help="interactive figure (hover: time, source line, speed), one self-contained file")
    parser.add_argument("--setpoints", metavar="out.csv", help="write the setpoint stream as CSV")
    parser.add_argument("--max-time", metavar="SECONDS", type=float, default=MAX_TIME_S,
                        help="stop with an error when the planned run passes this much machine time "
                             f"(default: {MAX_TIME_S / 3600:g} h; a feed rate typo otherwise plans for ever)")
    add_interp_arguments(parser)


def run(args: argparse.Namespace) -> int:
    import time
    from array import array

    import numpy as np

    from gcode_canon.errors import GCodeError
    from gcode_canon.interpreter import Interpreter
    from gcode_canon.machine import DryRunMachine
    from motiond.config_check import load_checked
    from motiond.interp_settings import settings_from_args
    from motiond.progress import line_progress, tracked
    from planner import check_stream, plan_all

    program_file(args.file)
    if not args.max_time > 0.0:  # NaN too
        raise UserError(f"--max-time must be a positive number of seconds, got {args.max_time}")
    if args.plot:
        from motiond.plan_plot import check_plot_path

        check_plot_path(args.plot)
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

        src: list[tuple[str, int]] = []  # each setpoint's source file and line
        max_cycles = args.max_time / machine.cycle_s
        for sp in plan_all(recorded(), machine):
            flat.extend(sp.positions)
            src.append((sp.file, sp.line))
            if len(src) > max_cycles:
                raise GCodeError(f"the planned run passes {args.max_time:g} s of machine time (--max-time) "
                                 "in this line: a feed rate too low, or a move too long?", sp.file, sp.line)
    planning_s = time.perf_counter() - started
    pts = np.frombuffer(flat, dtype=float).reshape(-1, n) if len(flat) else np.zeros((0, n))
    report = check_stream(pts, commands, machine)
    summary = _summary(args.file, config, report, planning_s)
    if args.setpoints:
        _write_csv(args.setpoints, machine, pts, src)
    if args.plot:
        from motiond.plan_plot import build_figure, save_figure

        save_figure(build_figure(args.file, machine, pts, src, commands, report), args.plot)
    if args.html:
        from motiond.plan_plot import build_html_figure, save_html

        save_html(build_html_figure(args.file, machine, pts, src, commands, report), args.html)
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


def _write_csv(path: str, machine: Any, pts: Any, src: list[tuple[str, int]]) -> None:
    """One row per cycle: time, the setpoint's source file and line, positions, per-axis velocities
    (the difference from the cycle before over the cycle time, as the drives see it)."""
    import csv
    import io

    import numpy as np

    from gcode_canon.atomicfile import atomic_write

    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow(["t", "file", "line", *machine.names, *(f"v{a}" for a in machine.names)])
    T = machine.cycle_s
    vel = np.diff(np.vstack([np.zeros((1, pts.shape[1])), pts]), axis=0) / T if len(pts) else pts
    for k, (row, v) in enumerate(zip(pts.tolist(), vel.tolist(), strict=True)):
        file, line = src[k]
        w.writerow([f"{(k + 1) * T:.6f}", file, line, *map(repr, row), *(f"{x:.6g}" for x in v)])
    try:
        atomic_write(path, out.getvalue().encode())
    except OSError as exc:
        raise UserError(f"{path}: cannot write: {exc.strerror}") from None
