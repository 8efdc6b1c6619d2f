"""Dialect table (gcode_canon.dialect).

The expected meanings come from LinuxCNC's source (master, 2026), read for this test: ``gees[]`` in
interp_array.cc has -1 (unknown) at G11, G12, G13, G15, G16, G22, G23, G50, G51, G68, G69, so
read_g says "Unknown g code used"; check_g_codes (interp_check.cc) refuses G10 L3 with "Line with
G10 does not have L0, L1, L10, L11, L2, or L20"; convert_setup_tool is G10 L1 (P tool, R radius,
axis offsets, I J Q); read_o / convert_stop handle bare O<n>, M98 and M99 (Fanuc-style numbered
programs). gcode-canon's meanings come from its compatibility document.
"""

from __future__ import annotations

import pytest

from gcode_canon.dialect import (
    DEFAULT_DIALECT,
    TABLE,
    Action,
    Dialect,
    Origin,
    normalise,
    resolve,
    table_rows,
)

LINUXCNC_UNKNOWN = ["G11", "G12", "G13", "G15", "G16", "G22", "G23", "G50", "G51", "G68", "G69"]


def test_default_dialect_is_linuxcnc():
    assert DEFAULT_DIALECT is Dialect.LINUXCNC
    assert resolve("G10 L1").dialect is Dialect.LINUXCNC


def test_parse_dialect_names():
    assert Dialect.parse("linuxcnc") is Dialect.LINUXCNC
    assert Dialect.parse(" GCODE_CANON ") is Dialect.GCODE_CANON
    assert Dialect.parse("gcode-canon") is Dialect.GCODE_CANON
    assert Dialect.parse("Grbl") is Dialect.GRBL
    with pytest.raises(ValueError, match="choose one of: linuxcnc, gcode-canon, grbl"):
        Dialect.parse("fanuc")


@pytest.mark.parametrize(
    ("text", "name"),
    [("G10 L1", "G10 L1"), ("g10l1", "G10 L1"), ("G10 L3", "G10 L3"), ("G068", "G68"), ("g12", "G12"),
     ("M98", "M98"), ("m099", "M99"), ("O1234", "O"), ("o", "O"), ("G17.1", "G17.1"), ("G10 L2", "G10 L2")],
)
def test_normalise(text, name):
    assert normalise(text) == name


@pytest.mark.parametrize("text", ["", "X10", "G", "G1 L2", "M98 L3", "G10 Lx"])
def test_normalise_rejects_non_codes(text):
    with pytest.raises(ValueError):
        normalise(text)


def test_table_covers_the_brief():
    assert set(TABLE) == {"G10 L1", "G10 L3", "G11", "G12", "G13", "G15", "G16", "G22", "G23", "G50",
                          "G51", "G68", "G69", "M98", "M99", "O"}
    # LinuxCNC has its own meaning (a clash, LinuxCNC wins by default) exactly for these:
    assert {code for code, e in TABLE.items() if e.clash} == {"G10 L1", "M98", "M99", "O"}


def test_g10_l1_linuxcnc_wins_by_default():
    m = resolve("G10 L1", Dialect.LINUXCNC)
    assert m.action is Action.TOOL_TABLE_ENTRY and m.origin is Origin.LINUXCNC
    assert "R radius" in m.summary
    g = resolve("G10 L1", Dialect.GCODE_CANON)
    assert g.action is Action.TOOL_RADIUS and g.origin is Origin.GCODE_CANON
    assert resolve("G10 L1", Dialect.GRBL).action is Action.TOOL_TABLE_ENTRY


def test_g10_l3_is_an_extension_linuxcnc_refuses():
    assert resolve("G10 L3").action is Action.TOOL_HEIGHT_DIAMETER
    assert resolve("G10 L3", Dialect.GCODE_CANON).action is Action.TOOL_HEIGHT_DIAMETER
    strict = resolve("G10 L3", extensions=False)
    assert not strict.accepted
    assert strict.action is Action.REFUSE and strict.origin is Origin.REFUSED
    assert strict.error == "Line with G10 does not have L0, L1, L10, L11, L2, or L20"


@pytest.mark.parametrize("code", LINUXCNC_UNKNOWN)
def test_unknown_to_linuxcnc_refused_in_strict_mode(code):
    strict = resolve(code, Dialect.LINUXCNC, extensions=False)
    assert not strict.accepted
    assert strict.error == "Unknown g code used"
    # gcode-canon's dialect accepts them whatever extensions says
    assert resolve(code, Dialect.GCODE_CANON, extensions=False).accepted


@pytest.mark.parametrize(
    ("code", "action"),
    [("G11", Action.DATA_INPUT_END), ("G12", Action.FULL_CIRCLE_CW), ("G13", Action.FULL_CIRCLE_CCW),
     ("G15", Action.POLAR_OFF), ("G22", Action.MIRROR_ON), ("G23", Action.MIRROR_OFF),
     ("G50", Action.SCALE_OFF), ("G51", Action.SCALE_ON), ("G68", Action.ROTATION_ON),
     ("G69", Action.ROTATION_OFF)],
)
def test_extensions_same_in_every_dialect(code, action):
    for dialect in Dialect:
        m = resolve(code, dialect)
        assert m.accepted and m.action is action, dialect


def test_g16_polar_origin_depends_on_dialect():
    # gcode-canon: "X is the radius relative to the current position"
    assert resolve("G16", Dialect.GCODE_CANON).action is Action.POLAR_ON_CURRENT
    # elsewhere Fanuc's rule (program zero in G90, like LinuxCNC's own @ ^ words)
    fanuc = resolve("G16", Dialect.LINUXCNC)
    assert fanuc.action is Action.POLAR_ON_FANUC and fanuc.origin is Origin.FANUC
    assert resolve("G16", Dialect.GRBL).action is Action.POLAR_ON_FANUC


def test_numbered_programs():
    assert resolve("M98").action is Action.CALL_NUMBERED
    assert resolve("M99").action is Action.RETURN_NUMBERED
    assert resolve("O100").action is Action.PROGRAM_NUMBER
    assert "Unexpected character after O-word" in resolve("O100").summary
    assert resolve("M98", Dialect.GCODE_CANON).action is Action.CALL_LABEL
    assert resolve("M99", Dialect.GCODE_CANON).action is Action.RETURN_LABEL
    assert resolve("O100", Dialect.GCODE_CANON).action is Action.PROGRAM_LABEL
    # LinuxCNC's meanings are never refused, strict or not
    for code in ("M98", "M99", "O1", "G10 L1"):
        assert resolve(code, extensions=False).origin is Origin.LINUXCNC


def test_codes_outside_the_table_are_standard():
    for code in ("G0", "G10 L2", "G10 L20", "M3", "G17.1"):
        for dialect in Dialect:
            m = resolve(code, dialect)
            assert m.action is Action.STANDARD and m.accepted


def test_table_rows_for_documentation():
    rows = dict((code, (lcnc, gc)) for code, lcnc, gc in table_rows())
    assert rows["G68"][0] == "error: Unknown g code used"
    assert rows["G10 L1"][1].startswith("set the radius of tool P")
    assert len(rows) == len(TABLE)
