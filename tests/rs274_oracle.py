"""LinuxCNC's stand-alone interpreter ``rs274`` as an oracle for canon's interpreter (no tests here).

``tools/build-rs274`` builds it into ``$CANON_RS274_DIR`` (default ``~/.cache/canon/rs274``). Both
interpreters run the same program on the same machine: a metric one (``[TRAJ] LINEAR_UNITS = mm``,
so tool tables and parameter files are millimetres for both), the same tool table and parameter file
(each on its own copy) and the same subroutine path. What is compared is the motion: every
canonical move (traverse, feed, arc, probe) in machine millimetres, and whether the program is
accepted.

rs274 prints program units with 4 decimals and its offsets as separate calls; they are applied as
LinuxCNC's ``emccanon.cc`` does (units, then G92, the XY rotation, G5x, the tool offset), and two
points agree when every coordinate is within the rounding of the printed values.
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from gcode_canon.commands import (
    ArcFeed,
    Pose,
    Probe,
    RigidTap,
    SetToolNumber,
    StraightFeed,
    StraightTraverse,
    ToolChange,
    rotate_about_z,
)
from gcode_canon.errors import GCodeError
from gcode_canon.interpreter import Interpreter

MM_PER_INCH = 25.4
TIMEOUT_S = 20.0
MAX_MOVES = 200_000


def rs274_dir() -> Path:
    return Path(os.environ.get("CANON_RS274_DIR") or Path.home() / ".cache" / "canon" / "rs274")


def rs274_binary() -> Path | None:
    path = rs274_dir() / "bin" / "rs274"
    return path if path.exists() else None


def linuxcnc_tree() -> Path:
    return rs274_dir() / "linuxcnc"


@dataclass
class Move:
    kind: str  # traverse, feed, arc, probe, tap, nurbs
    end: tuple[float, ...]  # machine mm/deg, X Y Z A B C
    centre: tuple[float, float] | None = None  # arcs: in-plane centre, machine mm
    turns: int = 0
    tol: float = 1e-4


@dataclass
class Result:
    moves: list[Move] = field(default_factory=list)
    error: str | None = None  # None: accepted
    prints: list[str] = field(default_factory=list)  # (PRINT,...) output


@dataclass
class Case:
    """One program and how to run it (paths inside ``workdir`` once staged)."""

    name: str
    directory: Path  # copied as a whole to a temporary directory before each run
    program: str  # relative to directory
    tool_table: str | None = None  # relative to directory; None: LinuxCNC's sim.tbl
    var_file: str | None = None
    ini: str | None = None  # the case's own INI (LINEAR_UNITS = mm is added)
    block_delete: bool = False
    subroutine_path: list[str] = field(default_factory=list)  # relative to directory


# --- rs274 ---------------------------------------------------------------------------------------

_CALL = re.compile(r"^\s*\d+\s+N\S*\s+([A-Z_0-9.]+)\((.*)\)\s*$")
_NUM = re.compile(r"-?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?|-?nan|-?inf")


_SPLINE_DEBUG = re.compile(r"\(emc/rs274ngc/interp_convert\.cc \d+\)\s*$|^X\s+\S+, Y\s+\S+ W\s+\S+$|^Oops \(")


def _numbers(text: str) -> list[float]:
    return [float(v) for v in _NUM.findall(text)]


def parse_rs274(stdout: str, prints: list[str] | None = None) -> list[Move]:
    """Canonical calls (program units) to moves in machine mm; other lines (the (PRINT,...) output,
    which rs274 writes between them) go to ``prints``."""
    factor = 1.0
    g5x = [0.0] * 6
    g92 = [0.0] * 6
    tool = [0.0] * 6
    rot = 0.0
    plane = "XY"
    moves: list[Move] = []
    err = {"g5x": 0.0, "g92": 0.0, "tool": 0.0}  # rounding of each offset as printed (mm)

    def tol() -> float:
        # each printed value is rounded to 0.5e-4 program units (of its own time); a rotation mixes X, Y
        return 1.5 * (0.5e-4 * factor + sum(err.values())) * (1.5 if rot else 1.0) + 1e-9

    def machine(p: list[float]) -> list[float]:
        out = [v * factor if k < 3 else v for k, v in enumerate(p)]
        out = [v + o for v, o in zip(out, g92, strict=True)]
        if rot:
            c, s = math.cos(math.radians(rot)), math.sin(math.radians(rot))
            out[0], out[1] = out[0] * c - out[1] * s, out[0] * s + out[1] * c
        return [v + o + t for v, o, t in zip(out, g5x, tool, strict=True)]

    for line in stdout.splitlines():
        m = _CALL.match(line)
        if m is None:
            if "NURBS_G6_FEED" in line:
                moves.append(Move("nurbs", ()))
            elif _SPLINE_DEBUG.search(line):
                continue  # LinuxCNC's convert_spline prints its control points on stdout
            elif prints is not None and line.strip():
                prints.append(line)
            continue
        name, args = m.groups()
        if name == "USE_LENGTH_UNITS":
            factor = MM_PER_INCH if "INCHES" in args else 1.0
        elif name == "SELECT_PLANE":
            plane = args.rsplit("_", 1)[-1]
        elif name == "SET_G5X_OFFSET":
            v = _numbers(args)[1:7]
            g5x = [x * factor if k < 3 else x for k, x in enumerate(v)]
            err["g5x"] = 0.5e-4 * factor
        elif name == "SET_G92_OFFSET":
            v = _numbers(args)[:6]
            g92 = [x * factor if k < 3 else x for k, x in enumerate(v)]
            err["g92"] = 0.5e-4 * factor
        elif name == "SET_XY_ROTATION":
            rot = _numbers(args)[0]
        elif name == "USE_TOOL_LENGTH_OFFSET":
            v = _numbers(args)[:6]
            tool = [x * factor if k < 3 else x for k, x in enumerate(v)]
            err["tool"] = 0.5e-4 * factor
        elif name in ("STRAIGHT_TRAVERSE", "STRAIGHT_FEED", "STRAIGHT_PROBE"):
            kind = {"STRAIGHT_TRAVERSE": "traverse", "STRAIGHT_FEED": "feed"}.get(name, "probe")
            moves.append(Move(kind, tuple(machine(_numbers(args)[:6])), tol=tol()))
        elif name == "RIGID_TAP":
            v = _numbers(args)[:3]
            moves.append(Move("tap", tuple(machine([*v, 0.0, 0.0, 0.0])[:3]), tol=tol()))
        elif name == "NURBS_G5_FEED":
            moves.append(Move("nurbs", ()))
        elif name == "ARC_FEED":
            v = _numbers(args)
            e1, e2, c1, c2, turns, en = v[:6]
            abc = v[6:9]
            order = {"XY": (0, 1, 2), "YZ": (1, 2, 0), "XZ": (2, 0, 1)}[plane]
            end = [0.0] * 6
            end[order[0]], end[order[1]], end[order[2]] = e1, e2, en
            end[3:6] = abc
            centre = list(end)
            centre[order[0]], centre[order[1]] = c1, c2
            mc = machine(centre)
            moves.append(Move("arc", tuple(machine(end)), (mc[order[0]], mc[order[1]]), int(turns),
                              tol=tol()))
    return moves


def run_rs274(binary: Path, work: Path, case: Case) -> Result:
    args = [str(binary), "-g", "-i", str(work / "_oracle.ini"), "-t", str(_tool_table(work, case))]
    if case.var_file:
        args += ["-v", str(work / case.var_file)]
    if case.block_delete:
        args.append("-b")
    args.append(case.program)
    try:
        p = subprocess.run(args, cwd=work, capture_output=True, text=True, timeout=TIMEOUT_S,
                           errors="replace")
    except subprocess.TimeoutExpired:
        return Result([], "rs274: timeout")
    prints: list[str] = []
    moves = parse_rs274(p.stdout, prints)
    if p.returncode != 0:
        lines = [ln for ln in p.stderr.splitlines() if ln.strip() != "executing"]
        # the message, then the offending line (LinuxCNC's own bad/ test reads it so)
        message = lines[-2] if len(lines) >= 2 else lines[-1] if lines else f"rs274 exit {p.returncode}"
        return Result(moves, message, prints)
    return Result(moves, None, prints)


# --- canon ---------------------------------------------------------------------------------------


class OracleMachine:
    """Answers as rs274's stand-alone canon does: inputs read their default (0); a probe ends at its
    target (tripped for G38.2/G38.4, not for G38.3/G38.5) and the machine then stands 0.254 mm back
    towards the start; after a tool change the
    position read back is its program position (the last move's, shifted by G5x/G92 changes since,
    not by rotation or tool offset changes) in the offsets now in force. A real machine reports
    where it is, which canon then reads in the new offsets."""

    def __init__(self) -> None:
        self.interp: Interpreter | None = None
        # rs274's stand-alone canon, mirrored: its program position (set by each move, shifted by G5x
        # and G92 changes since, not by rotation or tool offset changes), mm
        self.p = [0.0] * 9
        self.p_g5x = [0.0] * 9
        self.p_g92 = [0.0] * 9
        self.after_change = False
        self.prints: list[str] = []
        self.jumps: list[Pose] = []
        self.after_probe: Pose | None = None

    def wait_input(self, cmd) -> float:
        return 0.0

    def probe(self, cmd: Probe) -> tuple[Pose, bool]:
        # rs274's canon: the probe position is the target; the position afterwards is 0.254 mm
        # (0.01 in) back towards the start (its STRAIGHT_PROBE "models backing the probe off")
        assert self.interp is not None
        start, end = self.interp.pos, cmd.end
        d = [a - b for a, b in zip(start[:3], end[:3], strict=True)]
        length = math.sqrt(sum(v * v for v in d))
        if length > 0:
            back = 0.254  # mm: 0.01 in is the same distance
            self.after_probe = Pose(*(e + back * v / length for e, v in zip(end[:3], d, strict=True)),
                                    *end[3:])
        # its GET_EXTERNAL_PROBE_TRIPPED_VALUE is 0 (#5070 reads 0), and it never refuses a probe that
        # did not trip: G38.3/G38.5 untripped, G38.2/G38.4 tripped (canon refuses them untripped)
        return cmd.end, cmd.mode.error_on_miss

    def current_position(self) -> Pose | None:
        if self.after_probe is not None:
            where, self.after_probe = self.after_probe, None
            return where
        if not self.after_change or self.interp is None:
            return None
        self.after_change = False
        # its GET_EXTERNAL_POSITION: that program position, read in the offsets now in force
        f = self.interp.frames
        # SET_G5X_OFFSET / SET_G92_OFFSET shift it by (old - new): p + (p_g5x - g5x) + (p_g92 - g92);
        # emccanon then adds G92, rotates, adds G5x and the tool offset
        p_now = [p + a - b + c - d for p, a, b, c, d in zip(self.p, self.p_g5x, f.g5x, self.p_g92, f.g92,
                                                            strict=True)]
        x = [p + g for p, g in zip(p_now, f.g92, strict=True)]
        c, s_ = math.cos(math.radians(f.rotation)), math.sin(math.radians(f.rotation))
        x[0], x[1] = x[0] * c - x[1] * s_, x[0] * s_ + x[1] * c
        where = Pose(*(a + b + t for a, b, t in zip(x, f.g5x, f.tool, strict=True)))
        if any(abs(a - b) > 1e-9 for a, b in zip(where, self.interp.pos, strict=True)):
            self.jumps.append(where)  # rs274 shows this jump as the next (otherwise null) move
        return where

    def print_text(self, text: str) -> None:
        self.prints.append(text)

    def follow(self, cmd) -> None:
        """Keep the mirror of rs274's canon up to date with one command canon emitted."""
        if cmd.MOVES:
            assert self.interp is not None
            f = self.interp.frames
            # the move's end as the canon call had it (program frame): with cutter compensation the
            # compensated point, not the programmed one the interpreter holds
            if isinstance(cmd, (StraightTraverse, StraightFeed, ArcFeed)):
                self.p = f.machine_to_program(cmd.end)
            else:
                self.p = list(self.interp.prog)
            self.p_g5x, self.p_g92 = list(f.g5x), list(f.g92)


def run_canon(work: Path, case: Case) -> Result:
    from gcode_canon.settings import InterpreterSettings

    sub_path = [work / d for d in _ini_subroutine_path(work, case)] + [work / d for d in case.subroutine_path]
    settings = InterpreterSettings(
        var_file=work / case.var_file if case.var_file else None,
        tool_table=_tool_table(work, case), dry_run=True, subroutine_path=sub_path,
        block_delete=case.block_delete, max_loop_iterations=100_000, log_dir=work,
        axes="xyzabc",  # rs274 without [TRAJ] COORDINATES reads X Y Z A B C only
        disable_g92_persistence=_ini_flag(work, case, "DISABLE_G92_PERSISTENCE"),
        ini_values=_ini_values(work, case) if _ini_flag(work, case, "INI_VARS") else {},
        disable_fanuc_style_sub=_ini_flag(work, case, "DISABLE_FANUC_STYLE_SUB"),
    )
    result = Result()
    machine = OracleMachine()
    spline: tuple | None = None  # (count, file, line) of the spline whose moves are being read
    try:
        interp = Interpreter(settings, machine)
        machine.interp = interp
        for cmd in interp.run_file(work / case.program):
            while machine.jumps:
                result.moves.append(Move("jump", tuple(machine.jumps.pop(0)[:6])))
            machine.follow(cmd)
            if isinstance(cmd, (ToolChange, SetToolNumber)):
                machine.after_change = True
            if isinstance(cmd, (StraightFeed, ArcFeed)) and interp.splines_done and (
                    spline is None or spline[0] != interp.splines_done or spline[1:] == (cmd.file, cmd.line)):
                # a spline's arcs and lines: one NURBS_G5_FEED on rs274, which prints no points
                if spline is None or spline[0] != interp.splines_done:
                    spline = (interp.splines_done, cmd.file, cmd.line)
                    result.moves.append(Move("nurbs", ()))
                continue
            if isinstance(cmd, (StraightTraverse, StraightFeed, Probe)):
                kind = {StraightTraverse: "traverse", StraightFeed: "feed"}.get(type(cmd), "probe")
                result.moves.append(Move(kind, tuple(cmd.end[:6])))
            elif isinstance(cmd, RigidTap):
                result.moves.append(Move("tap", tuple(cmd.end[:3])))
            elif isinstance(cmd, ArcFeed):
                first, second, _ = cmd.plane.value
                centre = _centre_at_end(cmd)
                result.moves.append(Move("arc", tuple(cmd.end[:6]), (centre[first], centre[second]),
                                         int(cmd.turns)))
            if len(result.moves) > MAX_MOVES:
                result.error = "canon: too many moves"
                break
    except GCodeError as exc:
        result.error = str(exc)
    result.prints = machine.prints
    return result


def _centre_at_end(cmd: ArcFeed) -> Pose:
    """The arc's centre moved along its axis to the end's height, as rs274 prints it (canon's is at
    the start's): the same point when the arc is no helix or its plane is not turned (``rotation``)."""
    normal = [0.0] * 9
    normal[cmd.plane.value[2]] = 1.0
    n = rotate_about_z(Pose(*normal), cmd.rotation)
    along = sum((e - c) * k for e, c, k in zip(cmd.end, cmd.center, n, strict=True))
    return Pose(*(c + along * k for c, k in zip(cmd.center, n, strict=True)))


def _ini_flag(work: Path, case: Case, key: str) -> bool:
    if not case.ini or not (work / case.ini).exists():
        return False
    m = re.search(rf"(?im)^\s*{key}\s*=\s*(\S+)", (work / case.ini).read_text(errors="replace"))
    return bool(m) and m.group(1).lower() in ("1", "true", "yes", "on")


def _ini_values(work: Path, case: Case) -> dict[str, float]:
    """The case INI's numbers as #<_ini[section]name> reads them (LinuxCNC: strtod of the value)."""
    import configparser

    parser = configparser.ConfigParser(strict=False, interpolation=None, comment_prefixes=("#", ";"))
    assert case.ini is not None
    parser.read_string((work / case.ini).read_text(errors="replace"))
    out: dict[str, float] = {}
    for section in parser.sections():
        for name, value in parser.items(section):
            with contextlib.suppress(ValueError, IndexError):
                out[f"{section}]{name}".lower()] = float(value.split()[0])
    return out


def _ini_subroutine_path(work: Path, case: Case) -> list[str]:
    if not case.ini or not (work / case.ini).exists():
        return []
    m = re.search(r"(?im)^\s*SUBROUTINE_PATH\s*=\s*(.*)$", (work / case.ini).read_text(errors="replace"))
    return [p.strip() for p in m.group(1).split(":") if p.strip()] if m else []


def _tool_table(work: Path, case: Case) -> Path:
    if case.tool_table:
        return work / case.tool_table
    return work / "_sim.tbl"


def stage(case: Case, tmp: Path) -> Path:
    """A fresh copy of the case's directory with the oracle's INI and default tool table."""
    work = tmp / "work"
    if work.exists():
        shutil.rmtree(work)
    shutil.copytree(case.directory, work, symlinks=True, ignore=_only_text)
    template = work / f"{case.var_file}.template"
    if case.var_file and not (work / case.var_file).exists() and template.exists():
        shutil.copy(template, work / case.var_file)  # as the case's test.sh does
    ini = ""
    if case.ini:
        ini = (work / case.ini).read_text(errors="replace")
        ini = re.sub(r"(?im)^\s*LINEAR_UNITS\s*=.*$", "", ini)
    paths = ":".join(str(work / d) for d in case.subroutine_path)
    extra = "\n[TRAJ]\nLINEAR_UNITS = mm\n"
    if paths and "SUBROUTINE_PATH" not in ini:
        if re.search(r"(?im)^\[RS274NGC\]", ini):
            ini = re.sub(r"(?im)^\[RS274NGC\].*$", f"[RS274NGC]\nSUBROUTINE_PATH = {paths}", ini, count=1)
        else:
            extra += f"\n[RS274NGC]\nSUBROUTINE_PATH = {paths}\n"
    (work / "_oracle.ini").write_text(ini + extra)
    sim = linuxcnc_tree() / "configs" / "sim" / "sim.tbl"
    if sim.exists():
        shutil.copy(sim, work / "_sim.tbl")
    else:
        (work / "_sim.tbl").write_text("")
    return work


_KEEP = {".ngc", ".nc", ".tbl", ".var", ".ini", ".txt", ".template", ""}


def _only_text(directory: str, names: list[str]) -> list[str]:
    return [n for n in names if Path(n).suffix.lower() not in _KEEP and not (Path(directory) / n).is_dir()]


def run_both(case: Case, binary: Path) -> tuple[Result, Result]:
    with tempfile.TemporaryDirectory(prefix="canon-oracle-") as tmp:
        work = stage(case, Path(tmp) / "a")
        theirs = run_rs274(binary, work, case)
        work = stage(case, Path(tmp) / "b")
        ours = run_canon(work, case)
    return theirs, ours


def run_program(text: str, tmp: Path, binary: Path) -> tuple[Result, Result]:
    """Both interpreters on a program given as text (staged in a directory of its own under tmp)."""
    d = tmp / "case"
    d.mkdir(parents=True)
    (d / "p.ngc").write_text(text + "\n")
    return run_both(Case("p", d, "p.ngc"), binary)


def nc_file_case(name: str) -> Case:
    """One of LinuxCNC's nc_files by its name relative to nc_files."""
    (case,) = [c for c in nc_file_cases(linuxcnc_tree() / "nc_files") if c.name == name]
    return case


def _drop_null(moves: list[Move]) -> list[Move]:
    """Straight moves to where the previous move ended change nothing (LinuxCNC's canned cycles emit
    some, canon does not): left out of the comparison on both sides."""
    out: list[Move] = []
    prev: tuple[float, ...] | None = (0.0,) * 6  # both start at machine zero
    for mv in moves:
        if mv.kind in ("traverse", "feed") and prev is not None and len(prev) == len(mv.end) and all(
                abs(a - b) <= mv.tol for a, b in zip(prev, mv.end, strict=True)):
            continue
        out.append(mv)
        prev = mv.end if mv.end else prev
    return out


def _match_jumps(theirs: list[Move], ours: list[Move]) -> tuple[list[Move], list[Move]]:
    """Where the oracle machine moved canon's position (a tool change read back), rs274's next,
    otherwise null, move goes there: canon gets the same traverse; a jump rs274 does not show is
    dropped (its next move simply starts from there)."""
    out: list[Move] = []
    for mv in ours:
        if mv.kind != "jump":
            out.append(mv)
            continue
        k = len(out)  # the lists are in step up to here (or compare reports the first difference)
        if k < len(theirs):
            t = theirs[k]
            if t.kind == "traverse" and all(abs(x - y) <= t.tol for x, y in zip(t.end, mv.end, strict=False)):
                out.append(Move("traverse", mv.end, tol=t.tol))
    return theirs, out


def compare(theirs: Result, ours: Result) -> str | None:
    """None when they agree, else the first difference in words."""
    theirs_moves, ours_moves = _match_jumps(theirs.moves, ours.moves)
    theirs = Result(_drop_null(theirs_moves), theirs.error, theirs.prints)
    ours = Result(_drop_null(ours_moves), ours.error, ours.prints)
    n = min(len(theirs.moves), len(ours.moves))
    for k in range(n):
        a, b = theirs.moves[k], ours.moves[k]
        why = _differ(a, b)
        if why:
            return f"move {k + 1}: {why}"
    if (theirs.error is None) != (ours.error is None):
        if theirs.error is None:
            return f"canon refuses after {len(ours.moves)} moves: {ours.error}"
        return f"rs274 refuses after {len(theirs.moves)} moves ({theirs.error}), canon accepts"
    if len(theirs.moves) != len(ours.moves):
        return f"rs274 {len(theirs.moves)} moves, canon {len(ours.moves)}"
    for k, (a, b) in enumerate(zip(theirs.prints, ours.prints, strict=False)):
        if not _same_text(a, b):
            return f"PRINT {k + 1}: {a!r} on rs274, {b!r} on canon"
    if theirs.error is None and len(theirs.prints) != len(ours.prints):
        return f"rs274 printed {len(theirs.prints)} lines, canon {len(ours.prints)}"
    return None


def _same_text(a: str, b: str) -> bool:
    """Equal text, numbers within the rounding of LinuxCNC's %f (and of unit conversions)."""
    na, nb = _NUM.findall(a), _NUM.findall(b)
    if _NUM.sub("#", a).strip() != _NUM.sub("#", b).strip() or len(na) != len(nb):
        return False
    try:
        return all(abs(float(x) - float(y)) <= 2e-4 * max(1.0, abs(float(x))) for x, y in zip(na, nb,
                                                                                              strict=True))
    except ValueError:
        return na == nb


def _differ(a: Move, b: Move) -> str | None:
    if a.kind != b.kind:
        return f"rs274 {a.kind} {_fmt(a.end)}, canon {b.kind} {_fmt(b.end)}"
    if a.kind == "nurbs":
        return None
    tol = a.tol
    if any(abs(x - y) > tol for x, y in zip(a.end, b.end, strict=False)):
        return f"{a.kind} to {_fmt(a.end)} on rs274, {_fmt(b.end)} on canon"
    if a.kind == "arc":
        if a.turns != b.turns:
            return f"arc turns {a.turns} on rs274, {b.turns} on canon"
        if a.centre and b.centre and any(abs(x - y) > tol for x, y in zip(a.centre, b.centre, strict=True)):
            return f"arc centre {_fmt(a.centre)} on rs274, {_fmt(b.centre)} on canon"
    return None


def _fmt(v) -> str:
    return "(" + ", ".join(f"{x:.4f}" for x in v) + ")"


# --- the cases -------------------------------------------------------------------------------------

_RS274_CALL = re.compile(r"\brs274\b([^|;&>\n]*)")


def interp_cases(root: Path) -> list[Case]:
    """LinuxCNC's tests/interp: every rs274 run of a test.sh (not the plug-in, python or compile ones),
    and each program of bad/ and good/."""
    cases: list[Case] = []
    for script in sorted(root.rglob("test.sh")):
        d = script.parent
        text = script.read_text(errors="replace").replace("\\\n", " ")
        if "linuxcnc " in text or "rs274" not in text:
            continue
        for m in _RS274_CALL.finditer(text):
            words = m.group(1).split()
            if "-p" in words or not words:
                continue
            case = _case_from_words(d, root, words)
            if case is None:
                continue
            for prog in _expand(d, case.program):
                name = f"{d.relative_to(root)}/{prog}" + (f" [{case.ini}]" if case.ini else "")
                if any(c.name == name for c in cases):
                    continue
                cases.append(Case(name, d, prog, case.tool_table, case.var_file,
                                  case.ini, case.block_delete, ["."]))
    for sub in ("bad", "good"):
        for prog in sorted((root / sub).glob("*.ngc")):
            cases.append(Case(f"{sub}/{prog.name}", root / sub, prog.name, subroutine_path=["."]))
    return cases


def _case_from_words(d: Path, root: Path, words: list[str]) -> Case | None:
    case = Case("", d, "", subroutine_path=["."])
    it = iter(words)
    positional: list[str] = []
    for w in it:
        if w in ("-t", "-v", "-i", "-n", "-l"):
            value = next(it, "").strip("\"'")
            if w == "-t":
                case.tool_table = value
            elif w == "-v":
                case.var_file = value
            elif w == "-i":
                case.ini = value
        elif w == "-b":
            case.block_delete = True
        elif w.startswith("-") or w.startswith("2"):
            continue
        else:
            positional.append(w.strip("\"'"))
    if not positional:
        return None
    case.program = positional[0]
    return case


def _expand(d: Path, program: str) -> list[str]:
    if "$" in program:
        pattern = re.sub(r"\$\{?\w+\}?", "*", program)
        return sorted(p.name for p in d.glob(pattern))
    return [program] if (d / program).exists() else []


def nc_file_cases(root: Path) -> list[Case]:
    """Every .ngc of LinuxCNC's nc_files, run from its own directory (its subroutines found there)."""
    return [Case(str(p.relative_to(root)), p.parent, p.name, subroutine_path=["."])
            for p in sorted(root.rglob("*.ngc"))]
