"""The per-line checks that run before anything on a line is executed: which words the line's codes
use, and what cutter compensation forbids (LinuxCNC's ``interp_check.cc``: ``check_g_codes``,
``check_m_codes``, ``check_other_codes``). A mixin of :class:`gcode_canon.interpreter.Interpreter`."""

from __future__ import annotations

from gcode_canon import cycles
from gcode_canon.codes import PLANE_BY_CODE
from gcode_canon.commands import Plane
from gcode_canon.errors import GCodeError
from gcode_canon.lathe_cycles import LATHE_WORDS
from gcode_canon.lexer import Block
from gcode_canon.modal import G_AXIS_USERS_GROUP0, ModalLine, gname
from gcode_canon.spindle_sync import SYNC_MOTIONS, SYNC_WORDS, check_sync_block
from gcode_canon.spline_steps import SPLINE_MOTIONS


class BlockChecksMixin:
    """Word and code checks of one line (module docstring)."""

    def _effective_motion(self, ml: ModalLine) -> int | None:
        """The motion code that uses this line's axis words, or None when something else takes them."""
        if ml.axis_user:
            return None
        motion = ml.g.get(1)
        return self.motion if motion is None else motion

    def _check_block(self, block: Block, ml: ModalLine, shape: int) -> None:
        """:meth:`_check_words`, remembered: a line with the same codes and word letters (``shape``,
        :meth:`_shape`) in the same modal state (motion, plane, distance mode, compensation on or
        off) passes again; only M19's checks read the words' values, and they run every time."""
        key = (shape, self.motion, self.plane._value_[2], self.absolute, self.comp is None)
        passed = self._checks_passed
        if key in passed:
            if ml.m.get(7) == 19:
                self._check_orient_words(block.words, ml)
            return
        self._check_words(block, ml)
        if len(passed) >= 4096:
            passed.clear()
        passed.add(key)

    def _check_words(self, block: Block, ml: ModalLine) -> None:
        w = block.words
        g0 = ml.g.get(0)
        g1 = ml.g.get(1)
        has_axes = block.has_axes()
        if has_axes and self._missing_axes:
            for letter in w:
                if letter in self._missing_axes or (letter in "@^" and self._missing_axes & {"x", "y"}):
                    axis = letter.upper() if letter not in "@^" else "X or Y"
                    raise GCodeError(f"{letter.upper()} word used, but the machine has no {axis} axis")
        axis_user0 = ml.axis_user
        if has_axes:
            if axis_user0 and g1 is not None and g1 != 800:
                raise GCodeError("Cannot use two G codes that both use axis values: "
                                 f"{_axis_user_name(ml)} and {gname(g1)}")
            if not axis_user0:
                motion = self.motion if g1 is None else g1
                if motion == 800:
                    if g1 == 800:
                        raise GCodeError("Cannot use axis values with G80")
                    raise GCodeError("Cannot use axis values without a G code that uses them")
        if g0 == 530:
            motion = self.motion if g1 is None else g1
            if motion not in (0, 10):
                raise GCodeError("Must use G0 or G1 with G53")
            if (not self.absolute and ml.g.get(3) != 900) or ml.g.get(3) == 910:
                raise GCodeError("Cannot use G53 incremental (G91)")
        motion = self._effective_motion(ml)
        if motion in SYNC_MOTIONS and (has_axes or g1 == motion):  # their own checks; their words used
            check_sync_block(motion, w)
            w = {k: v for k, v in w.items() if k not in SYNC_WORDS[motion]}
        arc = motion in (20, 30)
        if "@" in w or "^" in w:
            if self.plane is not Plane.XY:  # LinuxCNC enhance_block
                raise GCodeError("Cannot use polar coordinate except in G17 plane")
            if "x" in w or "y" in w:
                raise GCodeError("Cannot mix polar coordinates (@ ^) with X or Y words")
            if axis_user0 or g0 == 530:
                raise GCodeError(f"Polar coordinates (@ ^) cannot be used with {_axis_user_name(ml)}")
        ms = set(block.m)
        if self.settings.disable_fanuc_style_sub and ms & {98, 99}:  # LinuxCNC: when the line is read
            raise GCodeError(f"DISABLE_FANUC_STYLE_SUB is set, but found M{min(ms & {98, 99})}")
        takes_ijk = g0 in (100, 120, 130) or ml.g.get(17) == 510
        if motion in LATHE_WORDS and (has_axes or g1 == motion):  # G70-G72: their words used
            w = {k: v for k, v in w.items() if k not in LATHE_WORDS[motion]}
        spline = motion in SPLINE_MOTIONS and (has_axes or g1 == motion)
        if spline:  # G5: I J P Q; G5.1: I J; G5.2: P L; G6.2: P Q R K L (LinuxCNC check_other_codes)
            if "k" in w and motion != 62:
                raise GCodeError(f"K word with no G2, G3, G6.2, G33, G33.1, G76, or G87 to use it "
                                 f"({gname(motion)})")
            used = {50: "ijpq", 51: "ij", 52: "pl", 62: "pqrkl"}[motion]
            w = {k: v for k, v in w.items() if k not in used}
        for letter in "ijk":
            if letter in w and not arc and motion != 870 and not takes_ijk:
                raise GCodeError(f"{letter.upper()} word with no G2 or G3 to use it")
        cycle = motion in cycles.CYCLE_CODES
        orient = ml.m.get(7) == 19
        if "r" in w and not (arc or cycle or orient) and g0 != 100 and ml.g.get(18) != 680 and \
                ml.g.get(13) != 640:
            raise GCodeError("R word with no G code that uses it")
        if "p" in w and not (arc or g0 in (40, 100) or ml.g.get(17) == 510 or ml.g.get(13) == 640
                             or motion in (740, 820, 840, 860, 880, 890) or orient
                             or ms & {50, 51, 52, 53, 62, 63, 64, 65, 66, 98} or 10 in ml.m):
            raise GCodeError("P word with no G or M code that uses it")
        if "q" in w and not (ml.g.get(13) == 640 or ms & {61, 66, 67, 68} or motion in (730, 830)
                             or g0 == 100 or orient or 10 in ml.m):
            raise GCodeError("Q word with no G or M code that uses it")
        if orient:
            self._check_orient_words(w, ml)
        if "l" in w and not (g0 == 100 or 66 in ms or 98 in ms or cycle
                             or ml.g.get(7) in (410, 420, 411, 421)):
            # LinuxCNC (check_other_codes) takes L with G41/G42 too, and ignores it there
            raise GCodeError("L word with no G10, cutter compensation, canned cycle, M66 or M98 to use it")
        if "e" in w and not ms & {66, 67, 68}:
            raise GCodeError("E word with no M66, M67 or M68 to use it")
        if "h" in w and ml.g.get(8) not in (430, 432) and g0 != 100:
            raise GCodeError("H word with no G43 to use it")
        if "d" in w and motion not in (730, 830) and ml.g.get(7) not in (410, 420, 411, 421) and \
                g0 not in (100, 120, 130) and ml.g.get(14) != 960:
            raise GCodeError("D word with no G code that uses it (G41, G42, G41.1, G42.1, G73, G83, G96)")
        if self.comp is not None:
            self._check_comp(ml)
        if g0 == 100 and "l" not in w:
            raise GCodeError("Line with G10 does not have an L word")

    @staticmethod
    def _check_orient_words(w: dict[str, float], ml: ModalLine) -> None:
        """M19's own checks, LinuxCNC's (interp_check.cc), before anything on the line runs."""
        if "p" in w:
            p = w["p"]
            whole = round(p)
            if abs(whole - p) > 0.001:
                raise GCodeError("P value not an integer with M19")
            if not 0 <= whole <= 2:
                raise GCodeError("P value must be 0, 1 or 2 with M19")
        if "r" in w:
            if ml.g.get(13) == 640:
                raise GCodeError("R word is ambiguous on a line with both G64 and M19: use separate lines")
            if not 0.0 <= w["r"] <= 360.0:
                raise GCodeError("R value must be within 0..360 with M19")
        if "q" in w and not w["q"] > 0.0:
            raise GCodeError("Q word with M19 requires a value > 0")

    def _check_comp(self, ml: ModalLine) -> None:
        """What LinuxCNC refuses while cutter radius compensation is on."""
        plane = ml.g.get(2)
        if plane is not None and PLANE_BY_CODE.get(plane) is not self.plane:
            raise GCodeError("Cannot change planes with cutter radius compensation on")
        if ml.g.get(7) == 400:
            return
        g0 = ml.g.get(0)
        if g0 in (280, 300):
            raise GCodeError(f"Cannot use {gname(g0)} with cutter radius compensation on")
        if g0 == 530:
            raise GCodeError("Cannot use G53 with cutter radius compensation on")
        if g0 in (920, 921, 922, 923, 520):
            raise GCodeError("Cannot change axis offsets (G52, G92) with cutter radius compensation on")
        if ml.g.get(12) is not None:
            raise GCodeError("Cannot change coordinate systems with cutter radius compensation on")
        if ml.m.get(6) == 6:
            raise GCodeError("Cannot change tools with cutter radius compensation on")


def _axis_user_name(ml: ModalLine) -> str:
    g = ml.g
    if g.get(0) in G_AXIS_USERS_GROUP0:
        return gname(g[0])
    if g.get(0) == 530:
        return "G53"
    for group in (8, 19, 17, 18):
        if group in g:
            return gname(g[group])
    return "G43.1"

