"""``tests/run`` lists every stage's outcome even when one fails, and its exit status says so."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_a_failing_stage_does_not_hide_the_others() -> None:
    env = {**os.environ, "CANON_SKIP_VM": "1"}
    # a pytest run that fails at once (no such test file): ruff passes, pytest fails, the VM stage is
    # still reported, and the status is non-zero
    r = subprocess.run(["bash", "tests/run", "-q", "-p", "no:cacheprovider", "tests/no_such_test_file.py"],
                       capture_output=True, text=True, timeout=600, cwd=ROOT, env=env)
    assert r.returncode != 0
    summary = r.stdout[r.stdout.index("== summary"):].splitlines()[1:]
    assert summary[0].strip() == "ruff: passed"
    assert summary[1].strip().startswith("pytest") and "FAILED (exit status 4)" in summary[1]
    assert summary[2].strip() == "vcan suite in a VM: skipped (CANON_SKIP_VM=1)"
