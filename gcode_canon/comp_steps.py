"""G40/G41/G42 (and .1) in the interpreter: the modal state, the radius and the lathe orientation,
and the compensated segments of :mod:`gcode_canon.cutter_comp` turned into canonical commands in
machine coordinates. A mixin of :class:`gcode_canon.interpreter.Interpreter`."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from gcode_canon.commands import ArcFeed, Plane, StraightFeed, StraightTraverse
from gcode_canon.errors import GCodeError
from gcode_canon.expressions import near_int
from gcode_canon.lexer import Block
from gcode_canon.modal import ModalLine, gname
from gcode_canon.offsets import N_AXES

if TYPE_CHECKING:
    from gcode_canon import cutter_comp


class CutterCompMixin:
    """Cutter radius compensation glue (module docstring)."""

    def _step_cutter_comp(self, block: Block, ml: ModalLine) -> None:
        """G40 / G41 / G42 / G41.1 / G42.1: :mod:`gcode_canon.cutter_comp` does the geometry; the
        modal state, the radius, the lathe tool orientation and the block checks are here.

        The orientation (tool table Q for G41/G42, L for G41.1/G42.1, 0 without L) and its checks are
        LinuxCNC's ``convert_cutter_compensation_on`` (``interp_convert.cc``): a lathe orientation
        (1-8) is only meaningful in G18, so L in any other plane, or a tool with orientation 1-8 there,
        is an error; a G41/G42 L word is accepted and ignored, as there."""
        code = ml.g.get(7)
        if code is None:
            return
        if code == 400:
            self._comp_off()
            return
        name = gname(code)
        if self.comp is not None:
            raise GCodeError("Cannot turn cutter radius comp on when already on")
        if self.plane is Plane.YZ or self.plane.value[0] > 2:
            raise GCodeError(f"{name}: cutter radius compensation works in G17 or G18 only, not "
                             f"{self.plane.gcode}")
        d = block.take("d")
        orientation = 0
        if code in (411, 421):
            if d is None:
                raise GCodeError(f"{name} needs a D word (the tool diameter)")
            diameter = d * self.scale
            lword = self._int_word(block, "l", name)
            if lword is not None:
                if self.plane is not Plane.XZ:
                    raise GCodeError(f"{name} with L word, but plane is not G18")
                if lword > 9:
                    # *canon*: LinuxCNC's manual makes this an error, its source takes any L >= 0 (and
                    # an L above 9 then moves nothing but the lathe entry-arc pre-move)
                    raise GCodeError(f"{name} L{lword}: invalid tool orientation (0 to 9)")
                orientation = lword
        else:
            number = self.current_tool
            if d is not None:
                number = near_int(d, f"D word of {name}")
                if number < 0:
                    raise GCodeError(f"{name} D{number}: negative tool number")
            tool = self._tool(number)
            diameter = float(tool.diameter) if tool is not None else 0.0
            orientation = tool.orientation if tool is not None else 0
            if self.plane is not Plane.XZ and orientation not in (0, 9):
                raise GCodeError(f"{name} with lathe tool, but plane is not G18 (T{number} has "
                                 f"orientation Q{orientation})")
        first, second, normal = self.plane.value
        side = "left" if code in (410, 411) else "right"
        here = self.prog
        if self.xform_on:  # compensation works on the transformed path; a mirror swaps the side
            here = list(self.xform.apply_position(here))
            side = self.xform.comp_side(side, self.plane)
        from gcode_canon import cutter_comp  # with compensation only: not at every start-up

        self.comp = cutter_comp.CutterCompensator(side, diameter / 2.0, (here[first], here[second]),
                                                  orientation, here[normal])
        self._comp_normal = here[normal]
        self.comp_code = code
        self._after_comp = False

    def _comp_off(self) -> None:
        """G40 or the end of the program: the held move goes out at its offset end."""
        comp = self.comp
        if comp is None:
            return
        self.comp = None
        self.comp_code = 400
        self._comp_output(comp.finish())
        self._after_comp = True

    def _comp_move(self, seg: cutter_comp.Segment) -> None:
        assert self.comp is not None
        self._comp_output(self.comp.add(seg))

    def _comp_output(self, items: list) -> None:
        """Compensated segments to canonical commands (machine coordinates); held commands as they are."""
        from gcode_canon import cutter_comp  # with compensation only: not at every start-up

        first, second, normal = self.plane.value
        others = [k for k in range(N_AXES) if k not in (first, second, normal)]
        f = self.file
        for item in items:
            if isinstance(item, (cutter_comp.Line2, cutter_comp.Arc2)):
                prog = [0.0] * N_AXES
                prog[first], prog[second] = item.end
                prog[normal] = item.normal
                for k, v in zip(others, item.extra, strict=True):
                    prog[k] = v
                end = self.frames.to_machine(prog)
                if not math.isfinite(sum(end)):
                    raise GCodeError("Coordinate out of range")
                n = item.line or self.line
                if isinstance(item, cutter_comp.Line2):
                    cls = StraightTraverse if item.rapid else StraightFeed
                    self._out.append(cls(end, file=f, line=n))
                else:
                    centre = list(prog)
                    centre[first], centre[second] = item.center
                    centre[normal] = self._comp_normal
                    centre_pose = self.frames.to_machine(centre)
                    turns = item.turns if item.ccw else -item.turns
                    rotation = self.frames.arc_rotation(self.plane)
                    self._out.append(ArcFeed(end, centre_pose, self.plane, turns, rotation, file=f, line=n))
                self._comp_normal = item.normal
                self.pos = end
            else:
                self._out.append(item)

