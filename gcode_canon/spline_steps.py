"""G5 (cubic spline), G5.1 (quadratic B-spline), G5.2/G5.3 (NURBS block) as LinuxCNC reads them
(interp_convert.cc ``convert_spline``, ``convert_nurbs``); the curve becomes arcs and lines as
LinuxCNC's canon makes them (:mod:`gcode_canon.splines`). A mixin of
:class:`gcode_canon.interpreter.Interpreter`.

In the active plane (G17 X/Y, G18 Z/X, G19 Y/Z), LinuxCNC's words:

* ``G5.1 X Y I J``: from here to the end point, I J the control point relative to the start (in
  G18 I is along X and J along Z). Order 3.
* ``G5 X Y I J P Q``: a cubic (order 4) from here to the end point; I J the first control point
  relative to the start, P Q the second relative to the end. Without I and J, the previous G5's
  ``-P -Q`` (a smooth continuation).
* ``G5.2 X Y P L`` starts a NURBS: the start and each following line's ``X Y P`` (P the weight)
  are its control points, ``L`` its order (default 3, at least 3); ``G5.3`` ends the block and moves
  along the curve. X and Y of the points are read from where the tool stood when the block began.
* ``G6.2 X Y R K P Q`` (Lo Valvo's NURBS): P the order and Q the interpolation on the first line,
  then a control point (weight R, knot K) a line, or a knot alone; cut once the last P knots are
  equal. The moves: :func:`gcode_canon.splines.nurbs_g6_moves` (docs/interpreter.md).

canon refuses, where LinuxCNC does something else: a curve through infinity (a G5.2 point's weight
not positive: LinuxCNC takes the first line's P as it is, -1 without P), splines with cutter
compensation on (LinuxCNC refuses G5 and G5.1;
its G5.2 ignores the compensation), splines in inverse time (G93) and outside G17/G18/G19. A G5
without I and J ends at its X Y words as LinuxCNC documents it (LinuxCNC master's code leaves that
end point unset there).
"""

from __future__ import annotations

import itertools
import math
from typing import TYPE_CHECKING

from gcode_canon.commands import FeedMode, Plane, StraightFeed
from gcode_canon.errors import GCodeError

if TYPE_CHECKING:
    from gcode_canon import splines
    from gcode_canon.lexer import Block
    from gcode_canon.modal import ModalLine

SPLINE_MOTIONS = (50, 51, 52, 62)
"""G5, G5.1, G5.2, G6.2 (motion codes times ten); G5.3 (53) is in group 0."""


class SplineMixin:
    """G5, G5.1, G5.2, G5.3 (module docstring)."""

    def _spline_reset(self) -> None:
        """LinuxCNC's ``nurbs_reset_global_variables`` (program start and M2); the G5 continuation
        (LinuxCNC's cycle_i, cycle_j) is kept."""
        self._nurbs_cps: list[tuple[float, float, float]] = []
        self._nurbs_order = 3
        self._g5_ij = getattr(self, "_g5_ij", (0.0, 0.0))
        self._g6_cps: list[tuple[float, float, float, float]] = []  # G6.2: (first, second, R, K)
        self._g6_lines = 0  # LinuxCNC's ff_G6_line_counter
        self._g6_q = 0
        self._g6_order = getattr(self, "_g6_order", 3)
        # LinuxCNC reads R and K of a G6.2 line without them from its block, as the last line set them
        self._g6_rk = getattr(self, "_g6_rk", (0.0, 0.0))
        self.splines_done = getattr(self, "splines_done", 0)  # curves moved along (the rs274 oracle)

    def _spline(self, motion: int, block: Block, previous: int) -> None:
        """A G5, G5.1 or G5.2 line; ``previous`` the motion mode before it."""
        if self.plane not in (Plane.XY, Plane.XZ, Plane.YZ):  # type: ignore[attr-defined]
            raise GCodeError("Splines need the XY, XZ or YZ plane (G17, G18, G19)")
        if motion == 52:
            self._nurbs_point(block, previous)
            return
        if motion == 62:
            self._nurbs_g6(block)
            return
        name = "G5" if motion == 50 else "G5.1"
        if self.comp is not None:  # type: ignore[attr-defined]
            raise GCodeError("Cannot convert spline with cutter radius compensation")
        self._spline_feed_check(block, name)
        if any(letter in block.words for letter in "abc"):
            raise GCodeError("Splines may not have motion in A, B, or C")
        w = block.words
        has_i, has_j = "i" in w, "j" in w
        scale = self.scale  # type: ignore[attr-defined]
        first, second, _ = self.plane._value_  # type: ignore[attr-defined]
        here = self.prog  # type: ignore[attr-defined]
        start = (here[first], here[second])
        if motion == 51:
            if not (has_i and has_j):
                raise GCodeError("Must specify both I and J with G5.1 or G6.1")
        elif has_i != has_j:
            raise GCodeError("Must specify both I and J, or neither")
        if motion == 50 and ("p" not in w or "q" not in w):
            raise GCodeError("Must specify both P and Q with G5")
        if has_i:
            i, j = block.take("i") * scale, block.take("j") * scale  # type: ignore[operator]
            ij = _plane_ij(self.plane, i, j)  # type: ignore[attr-defined]
        else:
            ij = self._g5_ij
        target = self._target(block)  # type: ignore[attr-defined]
        end = (target[first], target[second])
        c1 = (start[0] + ij[0], start[1] + ij[1])
        if motion == 51:
            cps = [(*start, 1.0), (*c1, 1.0), (*end, 1.0)]
            order = 3
        else:
            p, q = block.take("p") * scale, block.take("q") * scale  # type: ignore[operator]
            c2 = (end[0] + p, end[1] + q)  # LinuxCNC: P along the first axis, Q the second, in every plane
            cps = [(*start, 1.0), (*c1, 1.0), (*c2, 1.0), (*end, 1.0)]
            order = 4
            self._g5_ij = _plane_ij(self.plane, -p, -q)  # type: ignore[attr-defined]
        self._spline_out(cps, order, target)

    def _spline_feed_check(self, block: Block, name: str) -> None:
        if self.feed_mode is FeedMode.INVERSE_TIME:  # type: ignore[attr-defined]
            raise GCodeError(f"{name} in inverse time feed mode (G93) is not supported")
        if self.feed_mode is FeedMode.UNITS_PER_MINUTE and self.feed == 0.0:  # type: ignore[attr-defined]
            raise GCodeError("Cannot make arc with zero feed rate" if name != "G5.2"
                             else "Cannot make a NURBS with 0 feedrate")

    def _nurbs_point(self, block: Block, previous: int) -> None:
        """One G5.2 line: a control point, or the first one's weight (LinuxCNC ``convert_nurbs``)."""
        plane = self.plane  # type: ignore[attr-defined]
        first, second, _ = plane._value_
        letters = "xyz"
        a, b = letters[first], letters[second]
        w = block.words
        has_a, has_b = a in w, b in w
        if has_a != has_b:
            pair = " and ".join(sorted((a.upper(), b.upper())))
            raise GCodeError(f"You must specify both {pair} coordinates for Control Points")
        weight = block.take("p")
        if previous != 52:
            self._nurbs_cps = []
        cps = self._nurbs_cps
        if not has_a and weight is not None and weight > 0 and cps:
            raise GCodeError(f"Can specify P without {a.upper()} and {b.upper()} only for the first "
                             "control point")
        if (weight is None or weight <= 0) and cps:
            raise GCodeError("Must specify positive weight P for every Control Point")
        if self.comp is not None:  # type: ignore[attr-defined]
            raise GCodeError("Cannot convert spline with cutter radius compensation")
        self._spline_feed_check(block, "G5.2")
        if not cps:
            here = self.prog  # type: ignore[attr-defined]
            first_weight = weight if not has_a and weight is not None and weight > 0 else 1.0
            cps.append((here[first], here[second], first_weight))
            self._nurbs_order = 3
        order = self._int_word(block, "l", "G5.2")  # type: ignore[attr-defined]
        if order is not None and order > 3:
            self._nurbs_order = order
        if has_a:
            target = self._target(block)  # type: ignore[attr-defined]
            # LinuxCNC checks the weight of every point but the first line's: that one takes its P as
            # it is, and without P the word's unset value, -1
            cps.append((target[first], target[second], -1.0 if weight is None else weight))

    def _nurbs_g6(self, block: Block) -> None:
        """One G6.2 line (Lo Valvo's NURBS, LinuxCNC ``convert_nurbs``): the first names the order P
        and the interpolation Q; every line a control point X Y (in the plane) with its weight R and
        knot K, or a knot alone (K; the point is then the current one). The curve is cut once the
        last ``order`` knots are equal (a clamped end)."""
        plane = self.plane  # type: ignore[attr-defined]
        first, second, _ = plane._value_
        a, b = "xyz"[first], "xyz"[second]
        w = block.words
        has_a, has_b = a in w, b in w
        if has_a != has_b:
            pair = " and ".join(sorted((a.upper(), b.upper())))
            raise GCodeError(f"You must specify both {pair} coordinates for Control Points")
        cps = self._g6_cps
        p, q, k = block.take("p"), block.take("q"), block.take("k")
        r = block.take("r")
        self._g6_rk = (self._g6_rk[0] if r is None else r, self._g6_rk[1] if k is None else k)
        r_number, k_number = self._g6_rk
        if p is None and not cps:
            raise GCodeError("Program the nurbs order P in the first block of instruction")
        if p is not None and abs(int(p + 0.5) - p) >= 0.0001:
            raise GCodeError("nurbs order P number is not an integer")
        if (q is None or q <= 0) and not cps:
            raise GCodeError("Program the nurbs Q value (1,2,3) in the first block of nurbs instruction")
        if q is not None:
            if q < 1.0 or q > 3.0:
                raise GCodeError("nurbs Q value not in range 1 to 3")
            if abs(int(q + 0.5) - q) >= 0.0001:
                raise GCodeError("nurbs Q number is not an integer")
        if r_number <= 0 and cps:
            raise GCodeError("Must specify positive nurbs weight R for every Control Point")
        if k_number < 0 and cps:
            raise GCodeError("Must specify nurbs K number for every Control Point")
        if k is not None and abs(int(k + 0.5) - k) >= 0.0001:
            raise GCodeError("nurbs K number is not an integer")
        if self.comp is not None:  # type: ignore[attr-defined]
            raise GCodeError("Cannot convert spline with cutter radius compensation")
        if self.feed_mode is FeedMode.INVERSE_TIME:  # type: ignore[attr-defined]
            raise GCodeError("G6.2 in inverse time feed mode (G93) is not supported")
        if self.feed_mode is FeedMode.UNITS_PER_MINUTE and self.feed == 0.0:  # type: ignore[attr-defined]
            raise GCodeError("Cannot make a nurbs with 0 feedrate")
        if any(letter in w for letter in "abcuvw"):
            raise GCodeError("Splines may not have motion in A, B, or C")
        if p is not None:
            self._g6_order = int(p + 0.5)
        if self._g6_lines == 0:
            self._g6_q = int(q + 0.5) if q is not None else 0
        if has_a or k is not None:
            target = self._target(block)  # type: ignore[attr-defined]
            cps.append((target[first], target[second], r_number, k_number))
        self._g6_lines += 1
        order, lines = self._g6_order, self._g6_lines
        if len(cps) > order and 0 <= lines - order < len(cps) and lines - 1 < len(cps) \
                and cps[lines - 1][3] == cps[lines - order][3]:
            self._nurbs_g6_out(cps, order)

    def _nurbs_g6_out(self, cps: list[tuple[float, float, float, float]], order: int) -> None:
        """The G6.2 curve's moves (splines.nurbs_g6_moves); LinuxCNC's current point afterwards is
        the last line's point (its X and Y: in G18 and G19 the plane's two coordinates go there)."""
        first, second, _ = self.plane._value_  # type: ignore[attr-defined]
        scale = self.scale  # type: ignore[attr-defined]
        knots = [c[3] for c in cps]
        if any(b < a for a, b in itertools.pairwise(knots)) or not knots[-1] > 0:
            raise GCodeError("nurbs knots K must not decrease and must end above 0")
        if len(set(knots[:order])) > 1:
            # the curve starts at the order-th knot: LinuxCNC evaluates it from the first (NaN there)
            raise GCodeError(f"nurbs knots K must start with {order} equal values (the order P)")
        points = [(c[0], c[1], c[2]) for c in cps[: len(cps) - order]]
        from gcode_canon import splines  # here, for G5 G6 only: not every program's start-up (1 ms)

        # the curve in program units, as LinuxCNC's canon computes it (knots are not lengths)
        moves = splines.nurbs_g6_moves([(x / scale, y / scale, wt) for x, y, wt in points], knots, order)
        target = list(self.prog)  # type: ignore[attr-defined]
        target[first], target[second] = cps[-1][0], cps[-1][1]
        self._spline_out([], order, target, [splines.SplineMove(
            (m.end[0] * scale, m.end[1] * scale),
            None if m.centre is None else (m.centre[0] * scale, m.centre[1] * scale), m.ccw) for m in moves])
        self._g6_cps = []
        self._g6_lines = 0
        self.motion = 800  # type: ignore[attr-defined]  # LinuxCNC: no motion mode (-1)

    def _nurbs_end(self, ml: ModalLine) -> None:
        """G5.3: the NURBS block collected since G5.2 becomes moves."""
        if ml.g.get(1) not in (None, 52):
            raise GCodeError("Between G5.2 and G5.3 codes, only additional G5.2 codes are allowed.")
        if self.motion != 52:  # type: ignore[attr-defined]
            raise GCodeError("Cannot use G5.3 without G5.2 first")
        cps, order = self._nurbs_cps, self._nurbs_order
        if len(cps) < order:
            raise GCodeError(f"You must specify a number of control points at least equal to the order "
                             f"L = {order}")
        first, second, _ = self.plane._value_  # type: ignore[attr-defined]
        target = list(self.prog)  # type: ignore[attr-defined]
        target[first], target[second] = cps[-1][0], cps[-1][1]
        self._spline_out(cps, order, target)
        self._nurbs_cps = []
        self.motion = 800  # type: ignore[attr-defined]  # LinuxCNC: no motion mode (-1)

    def _spline_out(self, cps: list[tuple[float, float, float]], order: int, target: list[float],
                    moves: list[splines.SplineMove] | None = None) -> None:
        """The curve's arcs and lines from the current point (``moves``, else the G5/G5.1/G5.2
        curve of ``cps``); the position ends at ``target``."""
        first, second, _ = self.plane._value_  # type: ignore[attr-defined]
        self._after_comp = False
        self.splines_done += 1
        f, n = self.file, self.line  # type: ignore[attr-defined]
        if moves is None:
            from gcode_canon import splines

            moves = splines.nurbs_moves(cps, order)
        if not all(math.isfinite(v) for mv in moves for v in (*mv.end, *(mv.centre or ()))):
            raise GCodeError("NURBS goes through infinity: a control point's weight (G5.2 P, G6.2 R) is not "
                             "positive (a first G5.2 point without P has the weight -1, as in LinuxCNC)")
        for mv in moves:
            start = self.prog  # type: ignore[attr-defined]
            end = list(start)
            end[first], end[second] = mv.end
            if mv.centre is None:
                pose = self._to_machine(end)  # type: ignore[attr-defined]
                self.prog, self.pos = end, pose  # type: ignore[attr-defined]
                self._emit(StraightFeed(pose, file=f, line=n))  # type: ignore[attr-defined]
            else:
                self._arc_out(start, end, mv.centre[0], mv.centre[1], not mv.ccw,  # type: ignore[attr-defined]
                              1 if mv.ccw else -1)
        self.prog = target  # type: ignore[attr-defined]
        self.pos = self._to_machine(target)  # type: ignore[attr-defined]


def _plane_ij(plane: Plane, i: float, j: float) -> tuple[float, float]:
    """I and J (along X/Y in G17, Y/Z in G19, X/Z in G18) in the plane's (first, second) order."""
    return (j, i) if plane is Plane.XZ else (i, j)
