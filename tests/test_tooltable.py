"""gcode_canon.tooltable: LinuxCNC's tool table format, read strictly and written atomically."""

from __future__ import annotations

import errno
import logging
import math
import os
import re
import textwrap
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gcode_canon import atomicfile
from gcode_canon.commands import Pose
from gcode_canon.errors import GCodeError
from gcode_canon.tooltable import MAX_POCKET, Tool, ToolTable, format_tool_line, read_tool_table


def table_file(tmp_path: Path, text: str) -> Path:
    f = tmp_path / "tool.tbl"
    f.write_text(textwrap.dedent(text))
    return f


def raises_at(path: Path, line: int, match: str) -> GCodeError:
    with pytest.raises(GCodeError) as info:
        read_tool_table(path)
    assert re.search(match, info.value.message), info.value.message
    assert info.value.file == str(path)
    assert info.value.line == line
    return info.value


# --- reading ----------------------------------------------------------------------------------------


def test_full_line_from_the_manual(tmp_path):
    f = table_file(tmp_path, "T1 P1 X+0.0 Y0 Z0.511 A0 B0 C0 U0 V0 W0 D0.125 I0 J0 Q0 ;comment\n")
    assert read_tool_table(f).get(1) == Tool(
        number=1, pocket=1, offset=Pose(z=0.511), diameter=0.125, comment="comment"
    )


def test_every_word_lands_in_its_field(tmp_path):
    f = table_file(
        tmp_path,
        "T7 P3 X1 Y2 Z3 A4 B5 C6 U7 V8 W9 D10 I11 J12 Q4 ;lathe tool\n",
    )
    tool = read_tool_table(f).get(7)
    assert tool == Tool(
        number=7,
        pocket=3,
        offset=Pose(x=1, y=2, z=3, a=4, b=5, c=6, u=7, v=8, w=9),
        diameter=10,
        front_angle=11,
        back_angle=12,
        orientation=4,
        comment="lathe tool",
    )


def test_any_order_any_case_any_spacing_comments_and_blank_lines(tmp_path):
    f = table_file(
        tmp_path,
        """\
        ; a whole-line comment: T99 P99 is not a tool
        ;

        \t  ; indented comment
        d3   z-1.5e1\tp2  t2 ;drill; 3 mm
        T1 P1 D0.125000 Z+0.511000 ;1/8 end mill
        T5 P4
        """,
    )
    table = read_tool_table(f)
    assert [t.number for t in table.tools()] == [1, 2, 5]
    assert table.get(2) == Tool(number=2, pocket=2, offset=Pose(z=-15.0), diameter=3.0, comment="drill; 3 mm")
    assert table.get(1) == Tool(
        number=1, pocket=1, offset=Pose(z=0.511), diameter=0.125, comment="1/8 end mill"
    )
    assert table.get(5) == Tool(number=5, pocket=4)
    assert table.get(99) is None


def test_pocket_may_be_left_out(tmp_path):
    f = table_file(tmp_path, "T3 Z10\n")
    assert read_tool_table(f).get(3) == Tool(number=3, pocket=0, offset=Pose(z=10.0))


def test_tool_zero_is_no_tool_unless_the_table_has_a_t0_line(tmp_path):
    assert read_tool_table(table_file(tmp_path, "T1 P1\n")).get(0) is None
    torch = read_tool_table(table_file(tmp_path, "T0 P1 X0.5 Y-0.5 ;torch\n")).get(0)
    assert torch == Tool(number=0, pocket=1, offset=Pose(x=0.5, y=-0.5), comment="torch")


def test_empty_file_is_an_empty_table(tmp_path):
    assert len(read_tool_table(table_file(tmp_path, ""))) == 0


def test_crlf_and_bom_are_accepted(tmp_path):
    f = tmp_path / "tool.tbl"
    f.write_bytes(b"\xef\xbb\xbfT1 P1 Z1 ;a\r\nT2 P2\r\n")
    table = read_tool_table(f)
    assert table.get(1) == Tool(number=1, pocket=1, offset=Pose(z=1.0), comment="a")
    assert 2 in table


def test_missing_file_is_filenotfound(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_tool_table(tmp_path / "absent.tbl")


@pytest.mark.parametrize(
    ("line", "match"),
    [
        ("T1 P1 R0.5", r"unknown word 'R0\.5'"),
        ("   1      1    +0.511000    0.125000  1/8 end mill", "unknown word '1'"),  # pre-2.4 format
        ("P1 Z1 ;no tool number", "without a T word"),
        ("T1 T2", "T word given twice"),
        ("T1 Z1 z2", "Z word given twice"),
        ("T1.5 P1", "tool number in 'T1.5' is not an integer"),
        ("Tx P1", "not an integer"),
        ("T P1", "not an integer"),
        ("T-1 P1", "tool number -1 out of range"),
        ("T99999999999 P1", "out of range"),
        ("T1 P1001", f"pocket 1001 out of range \\(0 to {MAX_POCKET}\\)"),
        ("T1 P-2", "pocket -2 out of range"),
        ("T1 Pone", "pocket in 'Pone' is not an integer"),
        ("T1 Z1,5", r"Z offset in 'Z1,5' is not a number"),
        ("T1 D", "diameter in 'D' is not a number"),
        ("T1 Dnan", "diameter in 'Dnan' is not a number"),
        ("T1 I1e999", "front angle in 'I1e999' is not a finite number"),
        ("T1 Q10", "orientation Q10 out of range"),
        ("T1 Q1.5", "orientation in 'Q1.5' is not an integer"),
        ("T1 \u01315", "unknown word"),  # dotless i: upper-cases to I, but is not the I word
    ],
)
def test_bad_lines_name_the_file_and_line(tmp_path, line, match):
    f = table_file(tmp_path, f"; header\nT40 P40\n{line}\n")
    raises_at(f, 3, match)


def test_duplicate_tool_number_names_both_lines(tmp_path):
    f = table_file(tmp_path, "T4 P1\nT5 P2\n\nt4 P3\n")
    raises_at(f, 4, "T4 already defined on line 1")


def test_duplicate_pocket_is_a_warning(tmp_path, caplog):
    f = table_file(tmp_path, "T4 P1\nT5 P1\nT6 P0\nT7 P0\n")
    with caplog.at_level(logging.WARNING, logger="gcode_canon.tooltable"):
        assert len(read_tool_table(f)) == 4
    assert [r.getMessage() for r in caplog.records] == [f"{f}:2: pocket P1 already holds the tool of line 1"]


@pytest.mark.parametrize(
    ("data", "line", "match"),
    [
        (b"T1 P1 ;caf\xe9\n", 1, "not UTF-8"),
        (b"T1 P1\nT2\x00 P2\n", 2, "NUL byte"),
        (b"T1 P1 ;" + b"x" * 100_000 + b"\n", 1, "longer than"),
    ],
)
def test_binary_junk_is_a_clear_error(tmp_path, data, line, match):
    f = tmp_path / "tool.tbl"
    f.write_bytes(data)
    raises_at(f, line, match)


def test_directory_is_a_gcode_error(tmp_path):
    with pytest.raises(GCodeError, match="cannot read tool table"):
        read_tool_table(tmp_path)


# --- the table and its tools ------------------------------------------------------------------------


def test_get_set_remove_and_sorted_iteration():
    table = ToolTable([Tool(number=9, pocket=2), Tool(number=3, pocket=1)])
    table.set(Tool(number=5, pocket=3, diameter=6.0))
    table.set(Tool(number=9, pocket=4))  # replaces
    assert [t.number for t in table.tools()] == [3, 5, 9]
    assert [t.number for t in table] == [3, 5, 9]
    assert table.get(9) == Tool(number=9, pocket=4)
    assert len(table) == 3 and 5 in table and 4 not in table
    table.remove(5)
    table.remove(12345)
    assert table.get(5) is None and len(table) == 2


@pytest.mark.parametrize(
    "kwargs",
    [
        {"number": -1},
        {"number": 1, "pocket": MAX_POCKET + 1},
        {"number": 1, "orientation": 10},
        {"number": 1, "diameter": math.nan},
        {"number": 1, "offset": Pose(z=math.inf)},
        {"number": 1, "comment": "two\nlines"},
    ],
)
def test_invalid_tool_is_a_value_error(kwargs):
    with pytest.raises(ValueError):
        Tool(**kwargs)


def test_values_are_normalised_so_they_write_and_read_back_equal():
    tool = Tool(number=True, pocket=2, offset=(1, 2, 3), diameter=6, comment="  drill \t")
    assert tool.number == 1 and type(tool.number) is int
    assert tool.offset == Pose(x=1.0, y=2.0, z=3.0) and all(type(v) is float for v in tool.offset)
    assert type(tool.diameter) is float
    assert tool.comment == "drill"
    with pytest.raises(TypeError):
        Tool(number=1.0)
    with pytest.raises(TypeError):
        Tool(number=1, orientation=2.5)


def test_line_format():
    tool = Tool(
        number=3, pocket=5, offset=Pose(x=-1.5, z=12.25), diameter=6.0, orientation=2, comment="drill"
    )
    assert format_tool_line(tool) == "T3 P5 X-1.5 Z+12.25 D+6.0 Q2 ;drill"
    assert format_tool_line(Tool(number=0)) == "T0 P0"
    assert format_tool_line(Tool(number=1, front_angle=0.1, back_angle=-1e-20)) == "T1 P0 I+0.1 J-1e-20"


# --- writing ----------------------------------------------------------------------------------------


def test_write_then_read_is_exact(tmp_path):
    table = ToolTable(
        [
            Tool(number=1, pocket=1, offset=Pose(z=0.1 + 0.2), diameter=1 / 3, comment="1/8 end mill"),
            Tool(number=0, pocket=0, offset=Pose(x=-0.0, y=5e-324), comment="no tool"),
            Tool(number=42, pocket=7, offset=Pose(*[i * 1.1 for i in range(1, 10)]), front_angle=95.5,
                 back_angle=155.25, orientation=9, comment="lathe; left hand"),
        ]
    )  # fmt: skip
    f = tmp_path / "out.tbl"
    table.write(f)
    assert read_tool_table(f) == table
    lines = f.read_text().splitlines()
    assert [line.split()[0] for line in lines] == ["T0", "T1", "T42"]


def test_write_keeps_a_backup_and_leaves_no_temporaries(tmp_path):
    f = tmp_path / "tool.tbl"
    ToolTable([Tool(number=1, pocket=1, offset=Pose(z=1.0))]).write(f)
    assert not (tmp_path / "tool.tbl.bak").exists()
    ToolTable([Tool(number=1, pocket=1, offset=Pose(z=2.0))]).write(f)
    assert read_tool_table(tmp_path / "tool.tbl.bak").get(1).offset.z == 1.0
    assert read_tool_table(f).get(1).offset.z == 2.0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tool.tbl", "tool.tbl.bak"]


def test_write_failure_is_a_gcode_error_and_the_old_table_stays(tmp_path, monkeypatch):
    f = tmp_path / "tool.tbl"
    ToolTable([Tool(number=1, pocket=1)]).write(f)
    before = f.read_bytes()
    real_write = os.write
    calls = 0

    def disk_full(fd, data):
        nonlocal calls
        calls += 1
        if calls == 1:
            return real_write(fd, bytes(data)[:5])
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(atomicfile.os, "write", disk_full)
    with pytest.raises(GCodeError, match="cannot save the tool table: No space left") as info:
        ToolTable([Tool(number=i, pocket=i) for i in range(1, 50)]).write(f)
    monkeypatch.undo()
    assert info.value.file == str(f)
    assert f.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tool.tbl"]


def test_crash_before_the_rename_leaves_the_old_table(tmp_path, monkeypatch):
    f = tmp_path / "tool.tbl"
    old = ToolTable([Tool(number=1, pocket=1, offset=Pose(z=1.0))])
    old.write(f)

    class Crash(BaseException):
        pass

    def die(*args, **kwargs):
        raise Crash

    monkeypatch.setattr(atomicfile.os, "replace", die)
    with pytest.raises(Crash):
        ToolTable([Tool(number=1, pocket=1, offset=Pose(z=2.0))]).write(f)
    monkeypatch.undo()
    assert read_tool_table(f) == old


# --- properties -------------------------------------------------------------------------------------

JUNK_TOKENS = st.sampled_from(
    ["T1", "T", "P2", "P", "Z+1.5", "D", "Q3", "Q12", "X1e999", "Ynan", ";", "; c", " ", "\t", "\n", "\r",
     "\x00", "\xe9", "R1", "t2", "1", "-", ".", "T-1", "\ufeff", "P1001", "I", "J0.5"]
)  # fmt: skip


def joined(tokens: list[str]) -> bytes:
    return "".join(tokens).encode()


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.one_of(st.binary(max_size=400), st.lists(JUNK_TOKENS, max_size=60).map(joined)))
def test_junk_never_raises_anything_but_gcode_error(tmp_path, data):
    f = tmp_path / "junk.tbl"
    f.write_bytes(data)
    try:
        table = read_tool_table(f)
    except GCodeError as e:
        assert e.file == str(f) and e.line >= 1
        return
    for tool in table:
        assert isinstance(tool, Tool)


finite = st.floats(allow_nan=False, allow_infinity=False)
tools = st.builds(
    Tool,
    number=st.integers(0, 2**31 - 1),
    pocket=st.integers(0, MAX_POCKET),
    offset=st.builds(Pose, finite, finite, finite, finite, finite, finite, finite, finite, finite),
    diameter=finite,
    front_angle=finite,
    back_angle=finite,
    orientation=st.integers(0, 9),
    comment=st.text(
        st.characters(blacklist_categories=["Cs"], blacklist_characters="\r\n\0"), max_size=30
    ).map(str.strip),
)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(tools, max_size=8, unique_by=lambda t: t.number))
def test_any_table_round_trips(tmp_path, tool_list):
    f = tmp_path / "prop.tbl"
    table = ToolTable(tool_list)
    table.write(f, backup=False)
    assert read_tool_table(f) == table
