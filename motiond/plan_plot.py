"""``canon plan --plot``: the figure that shows the part and what the planner made of it.

* the programmed path (from the canonical commands: lines exact, arcs and helices as fine polylines,
  rapids dotted) drawn under the planned setpoints, coloured by path speed, in a 3D view and in an
  XY top view with equal scaling;
* the worst deviation of the planned path from the programmed one marked, labelled with its size
  and the source line of the setpoint;
* per-axis velocity, acceleration and jerk over time with the limits (axes that share a limit share
  one labelled line; each limit its own line style), units from the machine, and the source lines
  at a few times along the top.

:func:`build_figure` returns the matplotlib figure (the tests read its data); :func:`save_figure`
writes it atomically. :func:`setpoint_deviation` gives each setpoint's distance from the programmed
path, measured against the pieces of its own source line and its neighbours.
"""

from __future__ import annotations

import itertools
import math
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from gcode_canon import commands as C
from planner.checker import turn_points

ARC_CHORD = 1e-4  # arcs become polylines whose chords stay this close to the arc (machine units)
NEIGHBOURS = 4  # pieces either side of a setpoint's own line that its deviation is measured against
LIMIT_STYLES = ("--", ":", "-.", (0, (5, 2, 1, 2)), (0, (1, 3)))


@dataclass(frozen=True)
class Piece:
    """One programmed move as a polyline in machine axes (rows: points)."""

    file: str
    line: int
    rapid: bool
    points: np.ndarray


def programmed_pieces(commands: list[Any], machine: Any, start: np.ndarray | None = None) -> list[Piece]:
    """The moves of the program in order, from ``start`` (machine zero by default)."""
    index = machine.pose_index
    where = {p: i for i, p in enumerate(index)}
    pos = np.zeros(len(index)) if start is None else np.asarray(start, dtype=float)
    out: list[Piece] = []
    for cmd in commands:
        if not isinstance(cmd, C.MOTION_TYPES):
            continue
        end = np.array([cmd.end[p] for p in index], dtype=float)  # type: ignore[attr-defined]
        if isinstance(cmd, C.ArcFeed) and cmd.plane.value[0] in where and cmd.plane.value[1] in where and (
                not cmd.rotation or (0 in where and 1 in where)):
            turn = (where[0], where[1], cmd.rotation) if cmd.rotation else None
            i0, i1 = where[cmd.plane.value[0]], where[cmd.plane.value[1]]
            flat = _arc_points(cmd, turn_points(pos, turn, -1), turn_points(end, turn, -1), i0, i1)
            pts = turn_points(flat, turn)
        else:
            pts = np.vstack([pos, end])
        out.append(Piece(cmd.file, cmd.line, isinstance(cmd, C.StraightTraverse), pts))
        pos = end
    return out


def _arc_points(cmd: Any, start: np.ndarray, end: np.ndarray, i0: int, i1: int) -> np.ndarray:
    """The arc's points (in the frame where it lies in its axis plane: ``start`` and ``end`` turned
    back by its ``rotation`` when it has one)."""
    p0, p1, _ = cmd.plane.value
    centre = C.rotate_about_z(cmd.center, -cmd.rotation)
    c0, c1 = centre[p0], centre[p1]
    a0 = math.atan2(start[i1] - c1, start[i0] - c0)
    a1 = math.atan2(end[i1] - c1, end[i0] - c0)
    full = 2 * math.pi
    if cmd.turns > 0:  # counter-clockwise
        sweep = (a1 - a0) % full
        sweep = (sweep if sweep > 1e-12 else full) + full * (cmd.turns - 1)
    else:
        sweep = -((a0 - a1) % full)
        sweep = (sweep if sweep < -1e-12 else -full) - full * (-cmd.turns - 1)
    r0 = math.hypot(start[i0] - c0, start[i1] - c1)
    r1 = math.hypot(end[i0] - c0, end[i1] - c1)
    r = max(r0, r1, 1e-9)
    step = 2 * math.acos(max(1 - ARC_CHORD / r, -1.0)) if r > ARC_CHORD else math.pi / 4
    n = max(2, min(int(abs(sweep) / max(step, 1e-6)) + 2, 20_000))
    f = np.linspace(0.0, 1.0, n)
    pts = start[None, :] + f[:, None] * (end - start)[None, :]  # the other axes (and a helix) linearly
    radius = r0 + f * (r1 - r0)
    angle = a0 + f * sweep
    pts[:, i0] = c0 + radius * np.cos(angle)
    pts[:, i1] = c1 + radius * np.sin(angle)
    pts[-1] = end
    return pts


def _to_polyline(points: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Distance of each row of ``pts`` from the polyline ``points``."""
    best = np.full(len(pts), np.inf)
    for a, b in itertools.pairwise(points):
        d = b - a
        dd = float(d @ d)
        t = np.clip((pts - a) @ d / dd, 0.0, 1.0) if dd > 0 else np.zeros(len(pts))
        best = np.minimum(best, np.linalg.norm(pts - a - t[:, None] * d, axis=1))
    return best


def setpoint_deviation(pts: np.ndarray, src: list[tuple[str, int]], pieces: list[Piece]) -> np.ndarray:
    """Each setpoint's distance from the programmed path (NaN where it has no source line): measured
    against the pieces of its own line and :data:`NEIGHBOURS` pieces either side (a blend rounds the
    corner between two moves; a smoothed chain of short lines spans several)."""
    dev = np.full(len(pts), np.nan)
    by_src: dict[tuple[str, int], list[int]] = {}
    for k, p in enumerate(pieces):
        by_src.setdefault((p.file, p.line), []).append(k)
    k = 0
    while k < len(pts):
        m = k
        while m + 1 < len(pts) and src[m + 1] == src[k]:
            m += 1
        own = by_src.get(src[k])
        if own:
            lo, hi = max(own[0] - NEIGHBOURS, 0), min(own[-1] + NEIGHBOURS, len(pieces) - 1)
            block = pts[k:m + 1]
            dev[k:m + 1] = np.min([_to_polyline(pieces[j].points, block) for j in range(lo, hi + 1)], axis=0)
        k = m + 1
    return dev


def _units(machine: Any, idx: list[int]) -> str:
    units = sorted({machine.axes[i].unit for i in idx})
    return ", ".join(units)


def build_figure(title: str, machine: Any, pts: np.ndarray, src: list[tuple[str, int]],
                 commands: list[Any], report: Any) -> Any:
    """The figure (module docstring); ``src``: each setpoint's (file, line)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    T = machine.cycle_s
    n = pts.shape[1]
    names = [a.upper() for a in machine.names]
    linear = [i for i, a in enumerate(machine.axes) if not a.rotary]
    pieces = programmed_pieces(commands, machine)
    padded = (np.vstack([np.zeros((3, n)), pts, np.repeat(pts[-1:], 3, axis=0)]) if len(pts)
              else np.zeros((3, n)))
    fig = plt.figure(figsize=(19, 9), layout="constrained")
    grid = fig.add_gridspec(3, 3, width_ratios=(1.15, 1.0, 1.35))
    speed = np.linalg.norm(np.diff(padded[2:-3][:, linear[:3]], axis=0), axis=1) / T if linear else \
        np.zeros(len(pts))
    dev = setpoint_deviation(pts, src, pieces) if len(pts) else np.zeros(0)
    worst = int(np.nanargmax(dev)) if len(dev) and not np.all(np.isnan(dev)) else None
    main = title

    def where(k: int) -> str:
        file, line = src[k]
        return f"line {line}" if file == main else f"{os.path.basename(file)}:{line}"

    label = ""
    if worst is not None:
        label = f"worst deviation {dev[worst]:.4g} {_units(machine, linear)}\n{where(worst)}"

    # 3D view and XY top view, programmed path under the planned one
    u = _units(machine, linear)
    views: list[Any] = []
    if len(linear) >= 3:
        ax3 = fig.add_subplot(grid[:, 0], projection="3d")
        views.append(ax3)
    if len(linear) >= 2:
        axy = fig.add_subplot(grid[:, 1])
        views.append(axy)
    i0, i1 = [*linear, 0, 0][:2]
    sc = None
    for ax in views:
        is3d = hasattr(ax, "get_zlim")
        dims = linear[:3] if is3d else [i0, i1]
        for p in pieces:
            ax.plot(*(p.points[:, i] for i in dims), color="0.55", lw=0.9 if p.rapid else 1.4,
                    ls=":" if p.rapid else "-", zorder=1, gid="programmed")
        if len(pts):
            sc = ax.scatter(*(pts[:, i] for i in dims), c=speed, s=1.5, cmap="viridis", zorder=2,
                            gid="planned")
        if worst is not None:
            at = [pts[worst, i] for i in dims]
            ax.scatter(*at, marker="x", s=80, color="red", zorder=5, gid="worst")
            if is3d:
                ax.text(*at, " " + label.replace("\n", ", "), color="red", fontsize="small")
            else:
                ax.annotate(label, at, xytext=(12, 12), textcoords="offset points", color="red",
                            fontsize="small", arrowprops={"arrowstyle": "-", "color": "red"},
                            gid="worst-label")
        ax.set_xlabel(f"{names[dims[0]]} ({machine.axes[dims[0]].unit})")
        ax.set_ylabel(f"{names[dims[1]]} ({machine.axes[dims[1]].unit})")
        if is3d:
            ax.set_zlabel(f"{names[dims[2]]} ({machine.axes[dims[2]].unit})")
            ax.set_title(f"{os.path.basename(title)}: {report.duration_s:.2f} s "
                         "(grey: programmed, dotted: rapids)")
            extent = np.ptp(pts[:, dims], axis=0) if len(pts) else np.ones(3)
            floor = 0.3 * max(float(extent.max()), 1e-6)  # true proportions, but a flat part keeps depth
            ax.set_box_aspect(tuple(max(float(v), floor) for v in extent))
        else:
            ax.set_aspect("equal", adjustable="datalim")
            ax.set_title(f"top view {names[dims[0]]}{names[dims[1]]} (equal scale)")
            ax.grid(alpha=0.3)
    if sc is not None:
        fig.colorbar(sc, ax=views, shrink=0.5, location="bottom", label=f"path speed ({u}/s)")

    # velocity, acceleration, jerk over time with the limits
    for row, (order, key) in enumerate(((1, "velocity"), (2, "acceleration"), (3, "jerk"))):
        ax = fig.add_subplot(grid[row, 2])
        d = np.diff(padded, order, axis=0) / T**order
        t = (np.arange(len(d)) - 2) * T
        colours = {}
        for i, name in enumerate(names):
            tt, lo, hi = _envelope(t, d[:, i])
            line = ax.plot(tt, hi, lw=0.8, label=name, gid=f"{key}-{name}")[0]
            colours[i] = line.get_color()
            if lo is not hi:
                ax.fill_between(tt, lo, hi, color=line.get_color(), alpha=0.5)
        groups: dict[tuple[float, str], list[int]] = {}
        for i, a in enumerate(machine.axes):
            groups.setdefault((float(getattr(report.limits[a.name], key)), a.unit), []).append(i)
        for g, ((limit, unit), members) in enumerate(sorted(groups.items())):
            colour = colours[members[0]] if len(members) == 1 else "black"
            style = LIMIT_STYLES[g % len(LIMIT_STYLES)]
            text = f"limit {' '.join(names[i] for i in members)} ±{limit:g} {unit}/s{_power(order)}"
            ax.axhline(limit, color=colour, ls=style, lw=0.9, label=text, gid=f"limit-{key}")
            ax.axhline(-limit, color=colour, ls=style, lw=0.9, gid=f"limit-{key}")
        all_units = sorted({a.unit for a in machine.axes})
        ax.set_ylabel(f"{key} ({', '.join(f'{un}/s{_power(order)}' for un in all_units)})")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", ncol=3, fontsize="x-small")
        if row == 0:
            ax.set_title("per axis, from the setpoints")
            _line_ticks(ax, src, T, main)
    ax.set_xlabel("time (s)")
    return fig


def _power(order: int) -> str:
    return "" if order == 1 else "²" if order == 2 else "³"


def _line_ticks(ax: Any, src: list[tuple[str, int]], T: float, main: str, ticks: int = 6) -> None:
    """Source lines at a few times, along the top of the velocity plot."""
    if not src:
        return
    idx = np.linspace(0, len(src) - 1, ticks).astype(int)
    top = ax.secondary_xaxis("top")
    top.set_xticks([(k + 1) * T for k in idx],
                   labels=[(f"L{src[k][1]}" if src[k][0] in (main, "") else
                            f"{os.path.basename(src[k][0])}:{src[k][1]}") for k in idx])
    top.tick_params(labelsize="x-small")


def _envelope(t: Any, y: Any, buckets: int = 4000) -> tuple[Any, Any, Any]:
    """Min and max of ``y`` in at most ``buckets`` time slices, so that no peak is lost in the plot."""
    if len(y) <= buckets:
        return t, y, y
    k = int(np.ceil(len(y) / buckets))
    m = len(y) // k * k
    return t[:m:k], y[:m].reshape(-1, k).min(axis=1), y[:m].reshape(-1, k).max(axis=1)


def check_plot_path(path: str) -> None:
    """A :class:`motiond.cli.UserError` before any planning when ``path``'s suffix names no format
    matplotlib writes (``--plot out.txt`` was a ValueError traceback after the whole plan)."""
    from matplotlib.backend_bases import FigureCanvasBase

    from motiond.cli import UserError

    suffix = os.path.splitext(path)[1].lower().lstrip(".")
    formats = FigureCanvasBase.get_supported_filetypes()
    if suffix and suffix not in formats:
        raise UserError(f"--plot {path}: .{suffix} is not an image format "
                        f"(one of: {', '.join(sorted(formats))})")


def save_figure(fig: Any, path: str) -> None:
    """Write the figure to ``path`` (the format from its suffix) through a temporary file."""
    import tempfile

    import matplotlib.pyplot as plt

    from motiond.cli import UserError

    directory = os.path.dirname(os.path.abspath(path))
    suffix = os.path.splitext(path)[1] or ".png"
    try:
        fd, tmp = tempfile.mkstemp(prefix=".plot.", suffix=suffix, dir=directory)
    except OSError as exc:
        plt.close(fig)
        raise UserError(f"{path}: cannot write: {exc.strerror}") from None
    os.close(fd)
    try:
        fig.savefig(tmp, dpi=110)
        _usual_mode(tmp)
        os.replace(tmp, path)
    except OSError as exc:
        raise UserError(f"{path}: cannot write: {exc.strerror}") from None
    finally:
        plt.close(fig)
        if os.path.exists(tmp):
            os.unlink(tmp)


HTML_POINTS = 60_000  # setpoints kept in the interactive figure (every k-th; the worst one always)


def build_html_figure(title: str, machine: Any, pts: np.ndarray, src: list[tuple[str, int]],
                      commands: list[Any], report: Any) -> Any:
    """An interactive plotly figure: the planned path over the programmed one in 3D (hover: time,
    source line, path speed, position), and each axis's velocity over time (hover: time, line)."""
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    T = machine.cycle_s
    names = [a.upper() for a in machine.names]
    linear = [i for i, a in enumerate(machine.axes) if not a.rotary][:3]
    pieces = programmed_pieces(commands, machine)
    n = pts.shape[1]
    before = np.vstack([np.zeros((1, n)), pts[:-1]]) if len(pts) else pts
    vel = (pts - before) / T
    speed = np.linalg.norm(vel[:, linear], axis=1) if len(pts) else np.zeros(0)
    dev = setpoint_deviation(pts, src, pieces) if len(pts) else np.zeros(0)
    keep = np.arange(0, len(pts), max(1, math.ceil(len(pts) / HTML_POINTS)))
    if len(dev) and not np.all(np.isnan(dev)):
        keep = np.union1d(keep, [int(np.nanargmax(dev))])
    t = (keep + 1) * T
    lines = [f"{src[k][1]}" if src[k][0] in (title, "") else f"{os.path.basename(src[k][0])}:{src[k][1]}"
             for k in keep]
    unit = _units(machine, linear)
    fig = make_subplots(rows=1, cols=2, column_widths=(0.55, 0.45),
                        specs=[[{"type": "scene"}, {"type": "xy"}]],
                        subplot_titles=(f"{os.path.basename(title)}: {report.duration_s:.2f} s",
                                        "velocity per axis"))
    xs, ys, zs = ([] for _ in range(3))
    for p in pieces:  # one trace, pieces separated by gaps
        for coords, i in ((xs, 0), (ys, 1), (zs, 2)):
            col = linear[i] if i < len(linear) else None
            coords.extend([*(p.points[:, col] if col is not None else np.zeros(len(p.points))), None])
    fig.add_trace(go.Scatter3d(x=xs, y=ys, z=zs, mode="lines", name="programmed",
                               line={"color": "grey", "width": 3}, hoverinfo="skip"), row=1, col=1)
    custom = np.column_stack([t, speed[keep], dev[keep]]) if len(keep) else np.zeros((0, 3))
    coords3 = [pts[keep, linear[i]] if i < len(linear) else np.zeros(len(keep)) for i in range(3)]
    fig.add_trace(go.Scatter3d(
        x=coords3[0], y=coords3[1], z=coords3[2], mode="markers", name="planned",
        marker={"size": 2, "color": speed[keep], "colorscale": "Viridis",
                "colorbar": {"title": {"text": f"speed ({unit}/s)"}, "x": 0.5}},
        text=lines, customdata=custom,
        hovertemplate=("t %{customdata[0]:.3f} s<br>line %{text}<br>speed %{customdata[1]:.4g} " + unit
                       + "/s<br>deviation %{customdata[2]:.4g} " + unit
                       + "<br>%{x:.4f}, %{y:.4f}, %{z:.4f}<extra></extra>")), row=1, col=1)
    for i, name in enumerate(names):
        fig.add_trace(go.Scatter(x=t, y=vel[keep, i], mode="lines", name=f"v{name}", text=lines,
                                 hovertemplate=(f"{name} " + "%{y:.4g} " + machine.axes[i].unit
                                                + "/s<br>t %{x:.3f} s<br>line %{text}<extra></extra>")),
                      row=1, col=2)
    fig.update_scenes(aspectmode="data", xaxis_title=f"{names[linear[0]]} ({unit})" if linear else "",
                      yaxis_title=f"{names[linear[1]]} ({unit})" if len(linear) > 1 else "",
                      zaxis_title=f"{names[linear[2]]} ({unit})" if len(linear) > 2 else "")
    units = ", ".join(sorted({a.unit for a in machine.axes}))
    fig.update_xaxes(title_text="time (s)", row=1, col=2)
    fig.update_yaxes(title_text=f"velocity ({units}/s)", row=1, col=2)
    fig.update_layout(height=800, legend={"orientation": "h"})
    return fig


def save_html(fig: Any, path: str) -> None:
    """Write the interactive figure as one self-contained HTML file (plotly.js inside: no network)."""
    import tempfile

    from motiond.cli import UserError

    directory = os.path.dirname(os.path.abspath(path))
    try:
        fd, tmp = tempfile.mkstemp(prefix=".plot.", suffix=".html", dir=directory)
    except OSError as exc:
        raise UserError(f"{path}: cannot write: {exc.strerror}") from None
    os.close(fd)
    try:
        fig.write_html(tmp, include_plotlyjs=True, full_html=True)
        _usual_mode(tmp)
        os.replace(tmp, path)
    except OSError as exc:
        raise UserError(f"{path}: cannot write: {exc.strerror}") from None
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _usual_mode(path: str) -> None:
    """A temporary file is private (0600); the figure gets what the umask gives a new file."""
    mask = os.umask(0)
    os.umask(mask)
    os.chmod(path, 0o666 & ~mask)
