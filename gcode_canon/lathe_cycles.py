"""G70 (finishing), G71/G71.1/G71.2 and G72/G72.1/G72.2 (roughing along Z / along X) as LinuxCNC's
``convert_g7x`` reads them; the geometry is :mod:`gcode_canon.lathe_profile`. A mixin of
:class:`gcode_canon.interpreter.Interpreter`.

``G71 Q<n> X Z D I R U W`` in G18: a rapid to X Z, then the profile is read from subroutine ``o<n>``
(run for its control flow and parameters only: every line's X/Z (or U/W, incremental) ends a
segment, G0/G1 lines, G2/G3 arcs with I K or R, and A (fillet) or C (chamfer) corners; nothing is
executed), then cut: D the allowance left on the profile, I the depth of cut (default 1), R the
retract (0.5), U W a shift of the finished profile. G7x.1 leaves the pockets out, G7x.2 cuts only
them. ``G70 Q<n> X Z D E P``: P passes (1) from D down to E (0) along the profile.

G70 may run with cutter compensation on (G71/G72 may not), as LinuxCNC's: the line's rapid and
each pass's first rapid are made with the compensation switched off, straight to their points and
out at once, ahead of the move the compensation holds back (:meth:`CutterCompensator.jump`); the rest
of the pass goes through the compensation, its first rapid the entry move if none was made before.
Where canon differs from LinuxCNC: a G2/G3 with R too small for its ends is refused (LinuxCNC
computes a NaN centre).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from gcode_canon.arcs import centre_ijk
from gcode_canon.commands import Plane, StraightFeed, StraightTraverse
from gcode_canon.errors import GCodeError

if TYPE_CHECKING:
    from gcode_canon import lathe_profile as lp
    from gcode_canon.lexer import Block
    from gcode_canon.modal import ModalLine

LATHE_CYCLES = (700, 710, 711, 712, 720, 721, 722)
"""G70, G71, G71.1, G71.2, G72, G72.1, G72.2 (times ten)."""

LATHE_WORDS = {700: "dpqe", 710: "diqr", 711: "diqr", 712: "diqr", 720: "diqr", 721: "diqr", 722: "diqr"}
"""The words each cycle's line uses besides axis words (LinuxCNC check_other_codes)."""

_EQUAL = 0.0001  # LinuxCNC's TOLERANCE_EQUAL


class _Capture:
    """The profile being read from the Q subroutine."""

    def __init__(self, start: complex, incremental: bool, ijk_absolute: bool) -> None:
        self.start = start
        self.incremental = incremental
        self.ijk_absolute = ijk_absolute
        self.motion = 0  # LinuxCNC's motion mode after the cycle's rapid
        self.path: list[lp.Segment] = []


class _Moves:
    """The cycle's moves (program units, z + x*1j) as canonical commands."""

    def __init__(self, interp, block: Block) -> None:
        self.i, self.block = interp, block
        self.last = 0

    def _target(self, p: complex) -> list[float]:
        t = list(self.i.prog)
        t[0], t[2] = p.imag * self.i.scale, p.real * self.i.scale
        return t

    def _compensated(self, target: list[float], centre: tuple[float, float] | None = None,
                     ccw: bool = False, rapid: bool = False) -> None:
        """G70 with cutter compensation on: the move goes through the compensation as a G0/G1/G2/G3
        of the program would (in the XZ plane: Z first, X second, Y normal)."""
        from gcode_canon import cutter_comp  # with compensation only: not at every start-up

        i = self.i
        others = tuple(target[k] for k in range(len(target)) if k not in (2, 0, 1))
        end = (target[2], target[0])
        if centre is None:
            seg = cutter_comp.Line2(i.comp.programmed, end, target[1], others, i.line, rapid)
        else:
            i._comp_normal = i.prog[1]
            seg = cutter_comp.Arc2(i.comp.programmed, end, centre, ccw, target[1], others, i.line)
        i._comp_move(seg)
        i.prog = target

    def _line(self, p: complex, feed: bool) -> None:
        i = self.i
        target = self._target(p)
        end = i._to_machine(target)
        if not math.isfinite(sum(end)):
            raise GCodeError("Coordinate out of range")
        if feed:
            i._require_feed(self.block, "G1")
        self.last = 10 if feed else 0
        if i.comp is not None:
            self._compensated(target, rapid=not feed)
            return
        i.prog, i.pos = target, end
        i._emit((StraightFeed if feed else StraightTraverse)(end, file=i.file, line=i.line))
        self.last = 10 if feed else 0

    def rapid_uncompensated(self, end: complex) -> None:
        """A rapid made with cutter compensation switched off (LinuxCNC's G70 at each pass's start):
        straight to ``end``, out at once ahead of any move the compensation holds back."""
        if self.i.comp is None:
            self._line(end, False)
            return
        self.i._rapid_uncompensated(self._target(end))
        self.last = 0

    def straight(self, end: complex) -> None:
        self._line(end, True)

    def rapid(self, end: complex) -> None:
        self._line(end, False)

    def arc(self, ccw: bool, centre: complex, end: complex) -> None:
        i = self.i
        s = i.scale
        if abs(i.prog[2] / s - end.real) < _EQUAL and abs(i.prog[0] / s - end.imag) < _EQUAL:
            return  # LinuxCNC's motion_machine leaves out arcs that end where they start
        i._require_feed(self.block, "G3" if ccw else "G2")
        self.last = 30 if ccw else 20
        if i.comp is not None:
            self._compensated(self._target(end), (centre.real * s, centre.imag * s), ccw)
            return
        i._arc_out(list(i.prog), self._target(end), centre.real * s, centre.imag * s, not ccw,
                   1 if ccw else -1)
        self.last = 30 if ccw else 20


class LatheCycleMixin:
    """G70, G71, G72 (module docstring)."""

    _g7x: _Capture | None = None

    def _lathe_cycle(self, code: int, block: Block) -> None:
        # the profile's geometry imported here, for G7x only: not every program's start-up
        from gcode_canon import lathe_profile as lp

        cycle, sub = divmod(code, 10)
        name = f"G{cycle}.{sub}"
        q = block.take("q")
        if q is None:
            raise GCodeError("G7x.x  requires a Q word")
        comp = self.comp  # type: ignore[attr-defined]
        if comp is not None and cycle != 70:
            raise GCodeError(f"{name} cannot be used with cutter compensation enabled")
        if self.plane is not Plane.XZ:  # type: ignore[attr-defined]
            raise GCodeError(f"{name} can only be used in XZ plane (G18)")
        scale = self.scale  # type: ignore[attr-defined]
        w = block.words
        x, z = self.prog[0] / scale, self.prog[2] / scale  # type: ignore[attr-defined]
        incremental = not self.absolute  # type: ignore[attr-defined]
        if "x" in w:
            x = x + w["x"] if incremental else w["x"]
        if "z" in w:
            z = z + w["z"] if incremental else w["z"]
        if block.has_axes():
            # LinuxCNC switches to G90 before this rapid: its words are read as absolute
            self.absolute = True  # type: ignore[attr-defined]
            try:
                target = self._target(block)  # type: ignore[attr-defined]
            finally:
                self.absolute = not incremental  # type: ignore[attr-defined]
            self._rapid_uncompensated(target)
        cap = _Capture(complex(z, x), incremental, self.ijk_absolute)  # type: ignore[attr-defined]
        self._read_profile(int(q), cap)
        path = cap.path
        if len(path) <= 1:
            self.motion = cap.motion  # type: ignore[attr-defined]
            return
        d, e, i, r = w.get("d", 0.0), w.get("e", 0.0), w.get("i", 1.0), w.get("r", 0.5)
        u, w_shift, passes = w.get("u", 0.0), w.get("w", 0.0), int(w.get("p", 1.0))
        if i <= 0:
            raise GCodeError("G7X error: I must be greater than zero.")
        front, back = path[0].e - path[0].s, path[-1].e - path[-1].s
        last = cap.start
        out = _Moves(self, block)
        profile = lp.Profile(path)
        try:
            if cycle == 70:
                profile.g70(out, x, z, d, e, passes)
            elif cycle == 71:
                if abs(back.real) > 0 and front.imag * (x - last.imag) < 0:
                    path.append(lp.Line(last, complex(last.real, x)))
                profile.g71(out, sub, x, z, u, w_shift, d, i, r)
            else:
                if abs(back.imag) > 0 and front.real * (z - last.real) < 0:
                    path.append(lp.Line(last, complex(z, last.imag)))
                profile.g71(out, sub, x, z, u, w_shift, d, i, r, rotate=True)
        except lp.ProfileError as exc:
            raise GCodeError(f"G7X error: {exc.message}") from None
        self.motion = out.last  # type: ignore[attr-defined]

    def _rapid_uncompensated(self, target: list[float]) -> None:
        """A rapid to ``target`` (program frame) made with cutter compensation switched off, as
        LinuxCNC's convert_g7x makes the line's rapid and G70 each pass's first: straight there, out at
        once, ahead of any move the compensation holds back, the compensation told of the jump."""
        end = self._to_machine(target)  # type: ignore[attr-defined]
        if not math.isfinite(sum(end)):
            raise GCodeError("Coordinate out of range")
        self.prog, self.pos = target, end  # type: ignore[attr-defined]
        self._out.append(StraightTraverse(end, file=self.file, line=self.line))  # type: ignore[attr-defined]
        comp = self.comp  # type: ignore[attr-defined]
        if comp is not None:
            comp.jump((target[2], target[0]))

    def _read_profile(self, q: int, cap: _Capture) -> None:
        """Run subroutine o<q> for its control flow and parameters; its moves make the profile."""
        flow = self.flow  # type: ignore[attr-defined]
        depth = len(flow.frames)
        saved = (self.file, self.line, self._fast_ok, self._out, list(self.prog))  # type: ignore[attr-defined]
        limit = self.settings.max_loop_iterations  # type: ignore[attr-defined]
        self._g7x = cap
        try:
            flow.execute(f"o{q}call")  # the folded o-word line
            lines = 0
            while len(flow.frames) > depth:
                source = self.source  # type: ignore[attr-defined]
                raw = next(source, None)
                if raw is None:
                    flow.at_end_of_source(source)
                    continue
                self.line = source.line  # type: ignore[attr-defined]
                lines += 1
                if lines > limit:
                    raise GCodeError(f"G7x profile o{q}: more than {limit} lines read (max_loop_iterations)")
                try:
                    self._execute_line(raw)  # type: ignore[attr-defined]
                except GCodeError as exc:
                    raise exc.located(self.file, self.line) from None  # type: ignore[attr-defined]
        finally:
            self._g7x = None
            # the line's own output so far, and the position (LinuxCNC moves its current point along
            # the profile while reading it: #<_x> #<_z> read it there)
            self.file, self.line, self._fast_ok, self._out, self.prog = saved  # type: ignore[attr-defined]

    def _profile_line(self, block: Block, ml: ModalLine) -> None:
        """One line of the profile subroutine (LinuxCNC convert_g7x's reading loop)."""
        from gcode_canon import lathe_profile as lp

        cap = self._g7x
        assert cap is not None
        w = block.words
        start = cap.start
        end = 0j if cap.incremental else start
        if "u" in w:
            if cap.incremental:
                raise GCodeError("G7x error: Cannot use U in incremental mode (G91)")
            if "x" in w:
                raise GCodeError("G7x error: Cannot use U and X in the same block")
            u = w["u"] / 2 if self.diameter_mode else w["u"]  # type: ignore[attr-defined]
            end = complex(end.real, end.imag + u)
        elif "x" in w:
            end = complex(end.real, w["x"])
        if "w" in w:
            if cap.incremental:
                raise GCodeError("G7x error: Cannot use W in incremental mode (G91)")
            if "z" in w:
                raise GCodeError("G7x error: Cannot use W and Z in the same block")
            end = complex(end.real + w["w"], end.imag)
        elif "z" in w:
            end = complex(w["z"], end.imag)
        if cap.incremental:
            end += start
        if start != end:
            scale = self.scale  # type: ignore[attr-defined]
            self.prog[0], self.prog[2] = end.imag * scale, end.real * scale  # type: ignore[attr-defined]
        motion = ml.g.get(1)
        if motion is not None:
            cap.motion = motion
        if start == end:
            return
        motion = cap.motion
        if motion in (0, 10):
            cap.path.append(lp.Line(start, end))
        elif motion in (20, 30):
            cap.path.append(self._profile_arc(motion, start, end, w, cap))
        else:
            cap.start = end
            return
        if "a" in w and "c" in w:
            raise GCodeError("G7X error: Both A and C parameters on a corner")
        if "a" in w:
            cap.path.append(lp.Fillet(w["a"], end))
        if "c" in w:
            cap.path.append(lp.Chamfer(w["c"], end))
        cap.start = end

    def _profile_arc(self, motion: int, start: complex, end: complex, w: dict[str, float],
                     cap: _Capture) -> lp.Arc:
        from gcode_canon import lathe_profile as lp

        if "r" in w:
            if "i" in w or "k" in w:
                raise GCodeError("G7X error: both R and I or K flag used for arc")
            r = w["r"]
            chord = abs(end - start) ** 2
            q = (r * r - chord / 4) / chord if chord else -1.0
            if q < 0:
                raise GCodeError(f"G7X error: arc radius R{r:g} too small for its end points")
            d = 1j * math.sqrt(q) * (end - start)
            centre = (start + end) / 2.0 + (d if motion == 30 else -d)
        else:
            if "i" not in w and "k" not in w:
                raise GCodeError("G7X error: either I or K must be present for arc")
            centre = complex(w.get("k", 0.0), w.get("i", 0.0))
            if not cap.ijk_absolute:
                centre += start
            s = self.scale  # type: ignore[attr-defined]
            # LinuxCNC checks the arc as G2/G3 would (arc_data_ijk)
            centre_ijk(motion == 20, (start.real * s, start.imag * s), (end.real * s, end.imag * s),
                       (centre.real * s, centre.imag * s), 1, self.inch)  # type: ignore[attr-defined]
        return lp.Arc(motion == 30, start, centre, end)
