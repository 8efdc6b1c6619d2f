"""Modal groups (LinuxCNC's tables), the per-line checks on them, and the order of execution.

G codes are held times ten (G38.2 -> 382). :data:`G_GROUPS` lists every code this dialect knows;
:data:`G_UNSUPPORTED` the known ones this build refuses with a clear message (each is a later
module: canned cycles, cutter compensation, lathe modes ...).
"""

from __future__ import annotations

from gcode_canon.errors import GCodeError
from gcode_canon.lexer import Block

G_GROUPS: dict[int, int] = {}
for _group, _codes in {
    0: (40, 100, 280, 281, 300, 301, 530, 920, 921, 922, 923, 520, 53),
    1: (0, 10, 20, 30, 330, 331, 382, 383, 384, 385, 730, 740, 760, 800, 810, 820, 830, 840, 850, 860, 870,
        880, 890, 50, 51, 52, 62, 700, 710, 711, 712, 720, 721, 722),
    2: (170, 180, 190, 171, 181, 191),
    3: (900, 910),
    4: (901, 911),
    5: (930, 940, 950),
    6: (200, 210),
    7: (400, 410, 420, 411, 421),
    8: (430, 431, 432, 490),
    10: (980, 990),
    12: (540, 550, 560, 570, 580, 590, 591, 592, 593),
    13: (610, 611, 640),
    14: (960, 970),
    15: (70, 80),
    16: (150, 160),  # gcode-canon polar mode (G15/G16)
    17: (500, 510),  # scaling (G50/G51)
    18: (680, 690),  # rotation (G68/G69)
    19: (220, 230),  # mirroring (G22/G23, gcode-canon)
}.items():
    for _code in _codes:
        G_GROUPS[_code] = _group
for _code in (110, 120, 130):  # gcode-canon G11 (end of G10 data), full circle G12/G13 (non-modal)
    G_GROUPS[_code] = 0

G_UNSUPPORTED: dict[int, str] = {
    171: "G17.1 (UV plane)",
    181: "G18.1 (WU plane)",
    191: "G19.1 (VW plane)",
}

G_AXIS_USERS_GROUP0 = frozenset((100, 280, 300, 920, 520))
"""Group-0 codes that take axis words (the motion mode is suspended on their line)."""

M_GROUPS: dict[int, int] = {}
for _group, _codes in {
    4: (0, 1, 2, 30, 60, 98, 99),
    5: (62, 63, 64, 65, 66, 67, 68),
    6: (6, 61),
    7: (3, 4, 5, 19, 70, 71, 72, 73),  # LinuxCNC puts M19 and the modal-state codes in the spindle group
    8: (7, 8, 9),  # M7 and M8 may both be on, but not be set on one line
    9: (48, 49, 50, 51, 52, 53),
    10: tuple(range(100, 200)),  # user M codes (LinuxCNC's group 10): only those the machine binds
}.items():
    for _code in _codes:
        M_GROUPS[_code] = _group


def gname(code10: int) -> str:
    """382 -> 'G38.2', 10 -> 'G1'."""
    whole, tenth = divmod(code10, 10)
    return f"G{whole}.{tenth}" if tenth else f"G{whole}"


AXIS_USER_CODES = frozenset((*G_AXIS_USERS_GROUP0, 431, 432, 220, 230, 510, 680))
"""Codes other than the motion mode that take the line's axis words (G10 G28 G30 G92 G43.1, and the
gcode-canon transforms G22 G23 G51 G68)."""


class ModalLine:
    """The G and M codes of one line, by group, after the checks."""

    __slots__ = ("axis_user", "g", "m")

    def __init__(self) -> None:
        self.g: dict[int, int] = {}
        self.m: dict[int, int] = {}
        self.axis_user = False  # see AXIS_USER_CODES


def sort_codes(block: Block, user_mcodes: frozenset[int] = frozenset()) -> ModalLine:
    """Group the line's codes; unknown codes, two of one group, and unsupported codes are errors.
    ``user_mcodes``: the M100-M199 the machine binds (the others are refused)."""
    line = ModalLine()
    for code in block.g:
        group = G_GROUPS.get(code)
        if group is None:
            raise GCodeError(f"Unknown G code used: {gname(code)}")
        if group in line.g:
            raise GCodeError(
                f"Two G codes used from the same modal group: {gname(line.g[group])} and {gname(code)}"
            )
        line.g[group] = code
    for code in block.m:
        if 100 <= code <= 199 and code not in user_mcodes:
            raise GCodeError(f"M{code}: user-defined M code not bound on this machine (bind it in the "
                             "machine file's [io.mcodes])")
        group = M_GROUPS.get(code)
        if group is None:
            raise GCodeError(f"Unknown M code used: M{code}")
        if group in line.m:
            raise GCodeError(f"Two M codes used from the same modal group: M{line.m[group]} and M{code}")
        line.m[group] = code
    for code in line.g.values():
        what = G_UNSUPPORTED.get(code)
        if what is not None:
            raise GCodeError(f"{what} is not supported yet")
    line.axis_user = not AXIS_USER_CODES.isdisjoint(block.g)
    return line
