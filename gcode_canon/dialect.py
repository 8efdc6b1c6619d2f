"""G-code dialects, and the codes whose meaning depends on the dialect.

Why: canon reads LinuxCNC's RS274/NGC first, but also programs written for gcode-canon (a C
interpreter with Fanuc-family extensions) and for Grbl. A handful of codes mean different things in
those worlds. The project's rule (``/work/shared/README.md``): gcode-canon's extensions are ours to
support where they do not clash with LinuxCNC's meaning; where they clash, **LinuxCNC's meaning wins
by default** and the dialect option (``Dialect.GCODE_CANON``) selects the other. This module is the
one table of those codes and :func:`resolve`, which the interpreter core consults when it meets one
of them; the geometry lives in :mod:`gcode_canon.transforms`.

How the core uses it::

    meaning = resolve("G10 L1", settings.dialect)      # or resolve("G68", ...), resolve("O", ...)
    if not meaning.accepted:
        raise GCodeError(meaning.error)                # LinuxCNC's own message
    match meaning.action: ...                          # Action says which behaviour to run

``"O"`` stands for a numbered O word that is *not* LinuxCNC o-word control (``O<n> sub``, ``call``,
``if``, ``while`` ... mean the same in every dialect and never come here).

``resolve(..., extensions=False)`` gives strict LinuxCNC behaviour (what ``rs274`` itself says),
e.g. for comparing output with LinuxCNC line by line. A code not in the table has no dialect
difference: ``resolve`` returns ``Action.STANDARD`` and the core does what it always does.

What LinuxCNC does was checked in LinuxCNC's source (master, 2026): the G-code table ``gees[]`` in
``interp_array.cc`` has no entry for G11, G12, G13, G15, G16, G22, G23, G50, G51, G68 or G69, so
``read_g`` fails with "Unknown g code used"; ``check_g_codes`` in ``interp_check.cc`` accepts G10
only with L0, L1, L2, L10, L11 and L20; ``convert_setup_tool`` (``interp_convert.cc``) is G10 L1;
``read_o`` / ``convert_control_functions`` (``interp_read.cc``, ``interp_o_word.cc``) and
``convert_stop`` handle the Fanuc-style numbered programs (bare ``O<n>``, M98, M99), documented in
``docs/src/gcode/o-code.adoc`` ("Fanuc-Style Numbered Programs").

Grbl (``Dialect.GRBL``) knows none of these codes (its parser refuses them as unsupported, and its
G10 takes only L2 and L20), so no Grbl program contains them; the Grbl dialect resolves them as the
default (LinuxCNC) dialect does. Grbl's other differences are not this table's business.
"""

from __future__ import annotations

import enum
import re
from dataclasses import dataclass


class Dialect(enum.Enum):
    """The G-code dialect a program is read in (configuration / CLI option)."""

    LINUXCNC = "linuxcnc"
    GCODE_CANON = "gcode-canon"
    GRBL = "grbl"

    @classmethod
    def parse(cls, text: str) -> Dialect:
        """From a configuration or command-line value (case and ``_``/``-`` do not matter).
        ``ValueError`` names the accepted values; the caller adds the key or option."""
        key = text.strip().lower().replace("_", "-")
        for d in cls:
            if d.value == key:
                return d
        choices = ", ".join(d.value for d in cls)
        raise ValueError(f"unknown G-code dialect {text!r} (choose one of: {choices})")


DEFAULT_DIALECT = Dialect.LINUXCNC

GRBL_JUNCTION_DEVIATION_MM = 0.01
"""Grbl's default junction deviation (``$11``): in the Grbl dialect a program that sets no G64 P
runs as under ``G64 P0.01`` (mm) instead of LinuxCNC's G64 without P (corners as fast as possible).
Grbl's other differences handled by the interpreter: end of file ends the program (no M2/M30/%
needed), and ``$`` system-command lines in a file are skipped with a warning."""


class Origin(enum.Enum):
    """Whose meaning a resolved code has."""

    LINUXCNC = "linuxcnc"  # LinuxCNC's own meaning
    GCODE_CANON = "gcode-canon"  # gcode-canon's (selected by the dialect, or an extension)
    FANUC = "fanuc"  # a Fanuc-family meaning gcode-canon's document does not spell out
    REFUSED = "refused"  # an error, as LinuxCNC gives it


class Action(enum.Enum):
    """The behaviour the core runs for a resolved code."""

    STANDARD = "standard"  # not dialect-dependent: the core's usual handling
    REFUSE = "refuse"  # raise GCodeError(meaning.error)
    # G10 L1 / L3
    TOOL_TABLE_ENTRY = "tool_table_entry"  # LinuxCNC G10 L1 P R X..W I J Q
    TOOL_RADIUS = "tool_radius"  # gcode-canon G10 L1 P R
    TOOL_HEIGHT_DIAMETER = "tool_height_diameter"  # gcode-canon G10 L3 P H D
    DATA_INPUT_END = "data_input_end"  # gcode-canon G11: ends G10 data input; nothing to do here
    # transforms.py
    FULL_CIRCLE_CW = "full_circle_cw"  # G12
    FULL_CIRCLE_CCW = "full_circle_ccw"  # G13
    POLAR_OFF = "polar_off"  # G15
    POLAR_ON_CURRENT = "polar_on_current"  # G16, radius from the current position (gcode-canon)
    POLAR_ON_FANUC = "polar_on_fanuc"  # G16, origin at program zero in G90, current position in G91
    MIRROR_ON = "mirror_on"  # G22
    MIRROR_OFF = "mirror_off"  # G23
    SCALE_OFF = "scale_off"  # G50
    SCALE_ON = "scale_on"  # G51
    ROTATION_ON = "rotation_on"  # G68
    ROTATION_OFF = "rotation_off"  # G69
    # numbered programs
    CALL_NUMBERED = "call_numbered"  # LinuxCNC M98 P L: call a numbered subprogram defined later
    RETURN_NUMBERED = "return_numbered"  # LinuxCNC M99: return (in the main program: end, or loop)
    CALL_LABEL = "call_label"  # gcode-canon M98 P: jump to a remembered O number, come back at M99
    RETURN_LABEL = "return_label"  # gcode-canon M99: back to the line after the M98
    PROGRAM_NUMBER = "program_number"  # LinuxCNC bare O<n>: numbered (sub)program start
    PROGRAM_LABEL = "program_label"  # gcode-canon O<n>: remember (n, position), run the rest of the line


@dataclass(frozen=True, slots=True)
class Meaning:
    """What a code means in a dialect: the behaviour, whose it is, a one-line summary for error
    messages and ``canon check --json``, and LinuxCNC's error text when it is refused."""

    code: str
    dialect: Dialect
    action: Action
    origin: Origin
    summary: str
    error: str | None = None

    @property
    def accepted(self) -> bool:
        return self.action is not Action.REFUSE


@dataclass(frozen=True, slots=True)
class _Side:
    action: Action
    origin: Origin
    summary: str


@dataclass(frozen=True, slots=True)
class CodeEntry:
    """One dialect-dependent code.

    ``linuxcnc`` is LinuxCNC's own meaning, or None when LinuxCNC refuses the code with
    ``linuxcnc_error``; ``gcode_canon`` is the meaning under ``Dialect.GCODE_CANON``; ``extension``
    is what the default dialect does when LinuxCNC has no meaning (an extension that clashes with
    nothing; ``resolve(extensions=False)`` refuses it instead)."""

    code: str
    linuxcnc: _Side | None
    linuxcnc_error: str | None
    gcode_canon: _Side
    extension: _Side | None = None

    @property
    def clash(self) -> bool:
        """True when LinuxCNC gives the code a meaning of its own (so it wins by default)."""
        return self.linuxcnc is not None


UNKNOWN_G = "Unknown g code used"  # LinuxCNC NCE_UNKNOWN_G_CODE_USED
G10_BAD_L = "Line with G10 does not have L0, L1, L10, L11, L2, or L20"  # interp_check.cc

_L, _C, _F = Origin.LINUXCNC, Origin.GCODE_CANON, Origin.FANUC

_ENTRIES = (
    CodeEntry(
        "G10 L1",
        _Side(Action.TOOL_TABLE_ENTRY, _L,
              "set tool table entry P: R radius (diameter 2R), X Y Z A B C U V W offsets, I front angle, "
              "J back angle, Q orientation; error 'G10 L1 without offsets has no effect' with none"),
        None,
        _Side(Action.TOOL_RADIUS, _C, "set the radius of tool P to R (P and R only)"),
    ),
    CodeEntry(
        "G10 L3", None, G10_BAD_L,
        _Side(Action.TOOL_HEIGHT_DIAMETER, _C, "set tool P's height to H and diameter to D"),
    ),
    CodeEntry(
        "G11", None, UNKNOWN_G,
        _Side(Action.DATA_INPUT_END, _C, "end of G10 data input (a no-op: each G10 is one block)"),
    ),
    CodeEntry(
        "G12", None, UNKNOWN_G,
        _Side(Action.FULL_CIRCLE_CW, _C,
              "full circle clockwise, radius I, around the current position (gcode-canon parses G12 "
              "without moving yet; the Haas/Fanuc-style circle its document names)"),
    ),
    CodeEntry(
        "G13", None, UNKNOWN_G,
        _Side(Action.FULL_CIRCLE_CCW, _C,
              "full circle counter-clockwise, radius I, around the current position (as G12)"),
    ),
    CodeEntry(
        "G15", None, UNKNOWN_G,
        _Side(Action.POLAR_OFF, _C, "cartesian coordinates (polar off)"),
    ),
    CodeEntry(
        "G16", None, UNKNOWN_G,
        _Side(Action.POLAR_ON_CURRENT, _C,
              "polar coordinates: first-axis word = radius from the current position, second-axis "
              "word = angle in degrees"),
        _Side(Action.POLAR_ON_FANUC, _F,
              "polar coordinates as Fanuc: first-axis word = radius, second = angle (degrees); "
              "origin at the program zero in G90 (like LinuxCNC's @ ^ words), the current position "
              "in G91 with incremental angle"),
    ),
    CodeEntry(
        "G22", None, UNKNOWN_G,
        _Side(Action.MIRROR_ON, _C,
              "mirror the axes named by axis words about those coordinates (Fanuc's G22 is the "
              "stored stroke check, a meaning canon does not have)"),
    ),
    CodeEntry(
        "G23", None, UNKNOWN_G,
        _Side(Action.MIRROR_OFF, _C, "cancel mirroring"),
    ),
    CodeEntry(
        "G50", None, UNKNOWN_G,
        _Side(Action.SCALE_OFF, _F, "cancel scaling (Fanuc; not in gcode-canon's document)"),
    ),
    CodeEntry(
        "G51", None, UNKNOWN_G,
        _Side(Action.SCALE_ON, _F,
              "scale about the X Y Z centre by P (all axes) or I J K (per axis), Fanuc; not in "
              "gcode-canon's document"),
    ),
    CodeEntry(
        "G68", None, UNKNOWN_G,
        _Side(Action.ROTATION_ON, _F,
              "rotate the active plane by R degrees about its first/second-axis centre words "
              "(Fanuc; LinuxCNC rotates XY only, with G10 L2 R)"),
    ),
    CodeEntry(
        "G69", None, UNKNOWN_G,
        _Side(Action.ROTATION_OFF, _F, "cancel G68 rotation"),
    ),
    CodeEntry(
        "M98",
        _Side(Action.CALL_NUMBERED, _L,
              "call numbered subprogram P (defined later in the file by a bare O<P> line and ended "
              "by M99), L times (default 1, L0 none); #1-#30 stay global; error if disabled by "
              "DISABLE_FANUC_STYLE_SUB"),
        None,
        _Side(Action.CALL_LABEL, _C,
              "jump to the position remembered for program number P (an O word already read) and "
              "come back after M99"),
    ),
    CodeEntry(
        "M99",
        _Side(Action.RETURN_NUMBERED, _L,
              "return from a numbered subprogram; in the main program it ends the program like M2 "
              "(the stand-alone interpreter) or restarts it from the top (LinuxCNC's task: endless "
              "program)"),
        None,
        _Side(Action.RETURN_LABEL, _C, "return to the line after the calling M98"),
    ),
    CodeEntry(
        "O",
        _Side(Action.PROGRAM_NUMBER, _L,
              "a bare O<n> line (only a comment may follow) starts numbered program n: O1 may open "
              "the main program, later ones are subprograms reached only by M98 (execution flows "
              "into them: the main program must end with M2/M30 first); anything else after the "
              "number is 'Unexpected character after O-word' (O<n> sub/call/if ... are LinuxCNC's "
              "o-word control and are not dialect-dependent)"),
        None,
        _Side(Action.PROGRAM_LABEL, _C,
              "O<n> first on the line (after N) remembers (n, position) for M98; the rest of the "
              "line runs (O<n> sub/call/if ... stay LinuxCNC's o-word control)"),
    ),
)

TABLE: dict[str, CodeEntry] = {e.code: e for e in _ENTRIES}
"""The dialect-dependent codes by normalised name (``"G10 L1"``, ``"G68"``, ``"M98"``, ``"O"``)."""

_CODE_RE = re.compile(r"\s*([gmo])\s*(\d+(?:\.\d*)?)?\s*(?:l\s*(\d+(?:\.0*)?))?\s*$", re.IGNORECASE)


def normalise(code: str) -> str:
    """``"g10l1"`` -> ``"G10 L1"``, ``"G068"`` -> ``"G68"``, ``"o1234"`` -> ``"O"`` (every program
    number resolves alike). ``ValueError`` for text that is not a G/M code or an O word."""
    m = _CODE_RE.match(code)
    if m is None or (m.group(1).lower() != "o" and m.group(2) is None):
        raise ValueError(f"not a G or M code or an O word: {code!r}")
    letter = m.group(1).upper()
    if letter == "O":
        return "O"
    number = float(m.group(2))
    text = f"{letter}{int(number)}" if number.is_integer() else f"{letter}{number:g}"
    if m.group(3) is not None:
        if letter != "G" or text != "G10":
            raise ValueError(f"an L word only selects a G10 form: {code!r}")
        text += f" L{int(float(m.group(3)))}"
    return text


def resolve(code: str, dialect: Dialect = DEFAULT_DIALECT, *, extensions: bool = True) -> Meaning:
    """The meaning of ``code`` in ``dialect``.

    * ``Dialect.GCODE_CANON``: gcode-canon's meaning for every code in the table.
    * ``Dialect.LINUXCNC`` (default) and ``Dialect.GRBL``: LinuxCNC's meaning where it has one;
      where LinuxCNC refuses the code, the extension (gcode-canon's meaning, or Fanuc's for G16),
      unless ``extensions`` is False, which refuses it with LinuxCNC's own message.
    * A code outside the table: ``Action.STANDARD`` (no dialect difference).
    """
    name = normalise(code)
    entry = TABLE.get(name)
    if entry is None:
        return Meaning(name, dialect, Action.STANDARD, Origin.LINUXCNC, "no dialect difference")
    if dialect is Dialect.GCODE_CANON:
        side = entry.gcode_canon
    elif entry.linuxcnc is not None:
        side = entry.linuxcnc
    elif extensions:
        side = entry.extension or entry.gcode_canon
    else:
        return Meaning(name, dialect, Action.REFUSE, Origin.REFUSED,
                       f"refused by LinuxCNC: {entry.linuxcnc_error}", entry.linuxcnc_error)
    return Meaning(name, dialect, side.action, side.origin, side.summary)


def table_rows() -> list[tuple[str, str, str]]:
    """``(code, LinuxCNC, gcode-canon)`` summaries, for documentation and ``canon check --help``."""
    rows = []
    for e in _ENTRIES:
        lcnc = e.linuxcnc.summary if e.linuxcnc is not None else f"error: {e.linuxcnc_error}"
        rows.append((e.code, lcnc, e.gcode_canon.summary))
    return rows
