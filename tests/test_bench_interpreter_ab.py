"""bench/interpreter_ab.py runs both trees (the working tree and a git ref) and prints their times."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def test_the_ab_bench_times_the_working_tree_and_the_ref() -> None:
    if subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True).returncode:
        pytest.skip("not a git checkout: nothing to compare with")
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "interpreter_ab.py"), "300", "--rounds", "1",
                          "--vs-ref", "HEAD"], capture_output=True, text=True, timeout=300, check=True).stdout
    rows = [line.split() for line in out.splitlines() if line.startswith(("plain ", "mixed "))]
    timed = {(r[0], r[1]) for r in rows if r[1] in ("process", "check")}
    assert timed == {(p, w) for p in ("plain", "mixed") for w in ("process", "check")}, out
    for r in rows:
        if r[1] in ("process", "check"):
            assert r[2] == "work" and float(r[3]) > 0.0 and "HEAD" in r, out
