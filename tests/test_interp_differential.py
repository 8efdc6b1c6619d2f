"""canon's interpreter against LinuxCNC's own (rs274), case by case: LinuxCNC's tests/interp, its
nc_files and seeded random programs (tests/rs274_oracle.py compares; docs/interpreter.md lists every
known difference and its reason).

Marked ``rs274``; skipped, with the reason, where ``tools/build-rs274`` has not built rs274.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from tests import random_programs
from tests import rs274_oracle as oracle

pytestmark = pytest.mark.rs274

BINARY = oracle.rs274_binary()
TREE = oracle.linuxcnc_tree()
NOT_BUILT = f"rs274 is not built in {oracle.rs274_dir()}: run tools/build-rs274 --git <linuxcnc repo>"

# Known differences, by case: the reason (docs/interpreter.md says more). "canon:" where canon is right.
KNOWN_INTERP = {
    "g84/g18/g98/g18-g98-g84.ngc": "canon: LinuxCNC permutes the G84 axes twice in G18/G19",
    "g84/g18/g99/g18-g99-g84.ngc": "canon: LinuxCNC permutes the G84 axes twice in G18/G19",
    "g84/g19/g98/g19-g98-g84.ngc": "canon: LinuxCNC permutes the G84 axes twice in G18/G19",
    "g84/g19/g99/g19-g99-g84.ngc": "canon: LinuxCNC permutes the G84 axes twice in G18/G19",
}

RANDOM_PROGRAMS = 300
RANDOM_SEED = 1
RANDOM_AGREEMENT = 0.99
"""Agreement the seeded random programs must keep (measured: docs/interpreter.md)."""


def _interp_cases() -> list[oracle.Case]:
    root = TREE / "tests" / "interp"
    return oracle.interp_cases(root) if BINARY and root.is_dir() else []


def _ids(cases: list[oracle.Case]) -> list[str]:
    return [c.name for c in cases]


INTERP_CASES = _interp_cases()


@pytest.mark.skipif(BINARY is None, reason=NOT_BUILT)
def test_the_oracle_finds_linuxcncs_cases() -> None:
    assert len(INTERP_CASES) >= 100
    assert len(oracle.nc_file_cases(TREE / "nc_files")) >= 200


@pytest.mark.skipif(BINARY is None, reason=NOT_BUILT)
@pytest.mark.parametrize("case", INTERP_CASES or [None], ids=_ids(INTERP_CASES) or ["not-built"])
def test_linuxcnc_interp_case(case: oracle.Case | None) -> None:
    assert case is not None and BINARY is not None
    why = oracle.compare(*oracle.run_both(case, BINARY))
    known = KNOWN_INTERP.get(case.name)
    if known is not None:
        if why is None:
            pytest.fail(f"{case.name} now agrees: remove it from KNOWN_INTERP ({known})")
        pytest.xfail(known)
    assert why is None, why


@pytest.mark.skipif(BINARY is None, reason=NOT_BUILT)
def test_seeded_random_programs(tmp_path: Path) -> None:
    assert BINARY is not None
    cases = random_programs.cases(RANDOM_PROGRAMS, RANDOM_SEED, tmp_path)
    differ = []
    for case in cases:
        why = oracle.compare(*oracle.run_both(case, BINARY))
        if why is not None:
            differ.append(f"{case.name}: {why}")
    share = 1.0 - len(differ) / len(cases)
    assert share >= RANDOM_AGREEMENT, f"{share:.1%} agree:\n" + "\n".join(differ)


def test_parse_rs274_applies_offsets_as_emccanon() -> None:
    """The oracle's own arithmetic, without rs274: inch program units, G92 then rotation then G5x
    then the tool offset (emccanon.cc rotate_and_offset_pos)."""
    out = "\n".join([
        "    1 N..... USE_LENGTH_UNITS(CANON_UNITS_INCHES)",
        "    2 N..... SET_G5X_OFFSET(1, 1.0000, 0.0000, 0.0000, 0.0000, 0.0000, 0.0000)",
        "    3 N..... SET_G92_OFFSET(1.0000, 0.0000, 0.0000, 0.0000, 0.0000, 0.0000)",
        "    4 N..... SET_XY_ROTATION(90.0000)",
        "    5 N..... USE_TOOL_LENGTH_OFFSET(0.0000 0.0000 1.0000, 0.0000 0.0000 0.0000, "
        "0.0000 0.0000 0.0000)",
        "    6 N..... STRAIGHT_FEED(1.0000, 0.0000, 0.0000, 0.0000, 0.0000, 0.0000)",
    ])
    (move,) = oracle.parse_rs274(out)
    # (1 + 1, 0) inches rotated 90 degrees -> (0, 2) in; + G5x X1 in; Z: tool 1 in
    assert move.kind == "feed"
    assert move.end[:3] == pytest.approx((25.4, 50.8, 25.4))


def test_compare_drops_null_moves_and_reports_the_first_difference() -> None:
    a = oracle.Result([oracle.Move("traverse", (0.0,) * 6), oracle.Move("feed", (1.0, 0, 0, 0, 0, 0))])
    b = oracle.Result([oracle.Move("feed", (1.0, 0, 0, 0, 0, 0))])
    assert oracle.compare(a, b) is None
    c = oracle.Result([oracle.Move("feed", (1.001, 0, 0, 0, 0, 0))])
    assert "move 1" in (oracle.compare(a, c) or "")
    assert "refuses" in (oracle.compare(a, oracle.Result(b.moves, "boom")) or "")
