"""Group 0 of the interpreter: G10 (tool table and coordinate system data), G28/G30 (and their .1),
G92/G92.1/G92.2/G92.3 and G52, each as LinuxCNC's ``convert_setup``, ``convert_setup_tool``,
``convert_home``, ``convert_savehome`` and ``convert_axis_offsets`` do. A mixin of
:class:`gcode_canon.interpreter.Interpreter` (its state is the interpreter's)."""

from __future__ import annotations

import math

from gcode_canon.commands import Pose, SetG92Offset, StraightTraverse
from gcode_canon.errors import GCodeError
from gcode_canon.expressions import near_int
from gcode_canon.lexer import AXIS_LETTERS, Block
from gcode_canon.modal import ModalLine
from gcode_canon.offsets import N_AXES, ROTARY_INDEXES, system_base


class Group0Mixin:
    """G10, G28/G30, G52/G92 (see the module docstring)."""

    def _step_group0(self, block: Block, ml: ModalLine) -> None:
        code = ml.g.get(0)
        if code is None or code in (40, 530, 110):
            return
        if code in (120, 130):
            self._full_circle(code, block)
        elif code == 100:
            self._g10(block)
        elif code in (280, 300):
            self._go_home(block, 5161 if code == 280 else 5181)
        elif code in (281, 301):
            # LinuxCNC (convert_savehome): the machine position, the tool length offset included
            base = 5161 if code == 281 else 5181
            for k in range(N_AXES):
                self.params.set_system(base + k, self.pos[k])
        elif code == 920 or code == 520:
            self._g92(block, local=code == 520)
        elif code == 921 or code == 922:
            if code == 921:
                for k in range(N_AXES):
                    self.params.set_system(5211 + k, 0.0)
            self.params.set_system(5210, 0.0)
            self._set_g92([0.0] * N_AXES)
        elif code == 53:
            self._nurbs_end(ml)
        elif code == 923:
            self.params.set_system(5210, 1.0)
            self._set_g92([self.params.numbered[5211 + k] for k in range(N_AXES)])

    def _g10_tool(self, level: int, block: Block) -> None:
        """Tool table edits: LinuxCNC's G10 L1 / L10 / L11, gcode-canon's G10 L1 (radius) and L3
        (height and diameter), as :func:`gcode_canon.dialect.resolve` decides. The table file is
        rewritten atomically after each edit (never in a dry run)."""
        from dataclasses import replace

        from gcode_canon.dialect import Action, resolve
        from gcode_canon.tooltable import Tool, ToolTable

        meaning = resolve(f"G10 L{level}", self.dialect)
        if not meaning.accepted:
            raise GCodeError(meaning.error or f"G10 L{level} is not accepted")
        what = f"G10 L{level}"
        number = self._int_word(block, "p", what)
        if number is None:
            raise GCodeError(f"{what} needs a P word (the tool number)")
        if self.tool_table is None:
            self.tool_table = ToolTable()
            self._implicit_table = True
        tool = self.tool_table.get(number)
        if tool is None:
            if not self._implicit_table:
                raise GCodeError(f"{what} P{number}: tool {number} is not in the tool table")
            tool = Tool(number, pocket=min(number, 1000))
        scale = self.scale
        w = block.words
        offset = list(tool.offset)
        action = meaning.action
        try:
            if action is Action.TOOL_RADIUS:
                extra = sorted(set(w) - {"p", "r", "l"})
                if extra or "r" not in w:
                    raise GCodeError("G10 L1 (gcode-canon) takes P and R only: the tool radius")
                tool = replace(tool, diameter=2.0 * w["r"] * scale)
            elif action is Action.TOOL_HEIGHT_DIAMETER:
                extra = sorted(set(w) - {"p", "h", "d", "l"})
                if extra or not ("h" in w or "d" in w):
                    raise GCodeError("G10 L3 takes P with H (tool height) and/or D (diameter) only")
                if "h" in w:
                    offset[2] = w["h"] * scale
                tool = replace(tool, offset=Pose(*offset), diameter=w["d"] * scale if "d" in w
                               else tool.diameter)
            else:
                given = [k for k, letter in enumerate(AXIS_LETTERS) if letter in w]
                if level == 1:
                    if not given and not any(x in w for x in "rijq"):
                        raise GCodeError("G10 L1 without offsets has no effect")
                    for k in given:
                        offset[k] = w[AXIS_LETTERS[k]] * (1.0 if k in ROTARY_INDEXES else scale)
                else:
                    if not given:
                        raise GCodeError(f"{what} without axis words has no effect")
                    offset = self._touch_off_tool(level, w, given, offset)
                diameter = tool.diameter
                if "r" in w:
                    diameter = 2.0 * w["r"] * scale
                orientation = near_int(w["q"], "Q word of G10 L1") if "q" in w else tool.orientation
                tool = replace(tool, offset=Pose(*offset), diameter=diameter,
                               front_angle=w.get("i", tool.front_angle),
                               back_angle=w.get("j", tool.back_angle), orientation=orientation)
        except (ValueError, TypeError) as exc:
            raise GCodeError(f"{what} P{number}: {exc}") from None
        self.tool_table.set(tool)
        if number == self.current_tool:
            self._set_tool_parameters(number)
        path = self.settings.tool_table
        if path is not None and not self.settings.dry_run:
            self.tool_table.write(path)

    def _touch_off_tool(self, level: int, w: dict[str, float], given: list[int],
                        offset: list[float]) -> list[float]:
        """G10 L10 / L11: the offsets that make the current point read the given coordinates in the
        active system (L10) or in G59.3 without G92 (L11), as LinuxCNC's convert_setup_tool: X and Y
        are worked out in the system's rotated frame; given only one of them, the tool's offset
        along the other rotated axis is kept."""
        scale = self.scale
        if level == 10:
            base, g92, rot = list(self.frames.g5x), list(self.frames.g92), self.frames.rotation
        else:
            nums = self.params.numbered
            base = [nums[system_base(9) + k] for k in range(N_AXES)]
            g92, rot = [0.0] * N_AXES, nums[system_base(9) + 9]
        c, s = math.cos(math.radians(rot)), math.sin(math.radians(rot))

        def rotate(x: float, y: float, sign: float = 1.0) -> tuple[float, float]:
            return x * c - sign * y * s, sign * x * s + y * c

        # find_current_in_system_without_tlo: the machine point in the destination system
        t = [self.pos[k] - base[k] for k in range(N_AXES)]
        t[0], t[1] = rotate(t[0], t[1], -1.0)
        t = [a - b for a, b in zip(t, g92, strict=True)]
        value = {k: w[AXIS_LETTERS[k]] * (1.0 if k in ROTARY_INDEXES else scale) for k in given}
        out = list(offset)
        if 0 in value and 1 in value:
            out[0], out[1] = rotate(t[0] - value[0], t[1] - value[1])
        elif 0 in value or 1 in value:
            ox, oy = rotate(offset[0], offset[1], -1.0)  # keep the part along the other rotated axis
            ox, oy = (0.0, oy) if 0 in value else (ox, 0.0)
            ox, oy = rotate(ox, oy)
            dx, dy = (t[0] - value[0], 0.0) if 0 in value else (0.0, t[1] - value[1])
            dx, dy = rotate(dx, dy)
            out[0], out[1] = dx + ox, dy + oy
        for k in given:
            if k >= 2:
                out[k] = t[k] - value[k]
        return out

    def _set_g92(self, values: list[float]) -> None:
        self.frames.g92 = values
        self._offsets_changed()
        self._emit(SetG92Offset(Pose(*values), file=self.file, line=self.line))

    def _g92(self, block: Block, local: bool = False) -> None:
        """G92 (the current point gets the given coordinates) and G52 (LinuxCNC's local offset: the
        given values are the offsets). Both live in the same registers (#5210-#5219), so G92.1/G92.2/
        G92.3 and the parameter file's persistence apply to G52 too, as in LinuxCNC."""
        name = "G52" if local else "G92"
        if "@" in block.words or "^" in block.words:
            raise GCodeError(f"Polar coordinates (@ ^) cannot be used with {name}")
        if not block.has_axes() and not local:
            raise GCodeError("All axes missing with G92")
        current = [p + o for p, o in zip(self.prog, self.frames.g92, strict=True)]
        values = list(self.frames.g92)
        for k, letter in enumerate(AXIS_LETTERS):
            value = block.take(letter)
            if value is not None:
                if k not in ROTARY_INDEXES:
                    value *= self.scale
                values[k] = value if local else current[k] - value
        for k in range(N_AXES):
            self.params.set_system(5211 + k, values[k])
        self.params.set_system(5210, 1.0)
        self._set_g92(values)

    def _go_home(self, block: Block, base: int) -> None:
        self._after_comp = False
        f, n = self.file, self.line
        given = [k for k, letter in enumerate(AXIS_LETTERS) if letter in block.words]
        if given or "@" in block.words or "^" in block.words:
            target = self._target(block)
            self.prog = target
            self.pos = self._to_machine(target)
            self._emit(StraightTraverse(self.pos, file=f, line=n))
        else:
            given = list(range(N_AXES))
        # LinuxCNC (find_relative): the stored position is where the machine goes, the tool length
        # offset not added, except on rotary axes (where LinuxCNC leaves it in when not wrapped)
        tool = self.frames.tool
        home = [self.params.numbered[base + k] + (tool[k] if k in ROTARY_INDEXES else 0.0)
                for k in range(N_AXES)]
        if self.frames.rotation != 0.0 and len(given) < N_AXES:
            # LinuxCNC find_relative: the named axes take the stored position's coordinates in the
            # (rotated) program frame, so G28 X alone also moves machine Y when the system is rotated
            prog_home = self._from_machine(home)
            target = list(self.prog)
            for k in given:
                target[k] = prog_home[k]
            self.prog = target
            self.pos = self._to_machine(target)
        else:
            end = list(self.pos)
            for k in given:
                end[k] = home[k]
            self.pos = Pose(*end)
            self.prog = self._from_machine(self.pos)
        self._emit(StraightTraverse(self.pos, file=f, line=n))

    def _g10(self, block: Block) -> None:
        level = self._int_word(block, "l", "G10")
        if level in (1, 3, 10, 11):
            self._g10_tool(level, block)
            return
        if level not in (2, 20):
            raise GCodeError(f"Invalid L word with G10: L{level} (L1, L2, L3, L10, L11 or L20)")
        p = self._int_word(block, "p", f"G10 L{level}")
        if p is None:
            raise GCodeError(f"G10 L{level} needs a P word (coordinate system 1-9, 0 for the active one)")
        if p > 9:
            raise GCodeError(f"G10 L{level} P{p}: coordinate system number out of range (0-9)")
        if "@" in block.words or "^" in block.words:
            raise GCodeError("Polar coordinates (@ ^) cannot be used with G10")
        index = p or self.frames.g5x_index
        base = system_base(index)
        nums = self.params.numbered
        old = [nums[base + k] for k in range(N_AXES)]
        rotation = nums[base + 9]
        r = block.take("r")
        if r is not None:
            if level == 20:
                raise GCodeError("R not allowed in G10 L20")
            rotation = r  # G91 has no effect on G10 L2 (LinuxCNC)
        new = list(old)
        if level == 2:
            for k, letter in enumerate(AXIS_LETTERS):
                value = block.take(letter)
                if value is not None:
                    if k not in ROTARY_INDEXES:
                        value *= self.scale
                    new[k] = value
        else:
            # L20: the current point gets the given coordinates in system `index` (G91 or not).
            absolute = [m - t for m, t in zip(self.pos, self.frames.tool, strict=True)]
            g92 = self.frames.g92
            c, s = math.cos(math.radians(rotation)), math.sin(math.radians(rotation))
            # the current point as system `index` calls it now; axes not given keep that
            dx, dy = absolute[0] - old[0], absolute[1] - old[1]
            current = [a - o - g for a, o, g in zip(absolute, old, g92, strict=True)]
            current[0] = dx * c + dy * s - g92[0]
            current[1] = -dx * s + dy * c - g92[1]
            desired = list(current)
            for k, letter in enumerate(AXIS_LETTERS):
                value = block.take(letter)
                if value is not None:
                    desired[k] = value if k in ROTARY_INDEXES else value * self.scale
            px, py = desired[0] + g92[0], desired[1] + g92[1]
            new[0] = absolute[0] - (px * c - py * s)
            new[1] = absolute[1] - (px * s + py * c)
            for k in range(2, N_AXES):
                new[k] = absolute[k] - (desired[k] + g92[k])
        for k in range(N_AXES):
            self.params.set_system(base + k, new[k])
        self.params.set_system(base + 9, rotation)
        if index == self.frames.g5x_index:
            self._select_system(index)
