"""The stressed bench's C reference beside a case (bench/fieldbus_stress.py ``Beside``): bench/rt_floor.c
ended by SIGTERM writes what it has, and the wake-ups due within the case's window are the ones taken."""

from __future__ import annotations

import importlib.util
import shutil
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def load(name: str, file: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "bench" / file)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_c_reference_beside_a_case_takes_the_wake_ups_of_its_window(tmp_path: Path) -> None:
    if shutil.which("cc") is None and shutil.which("gcc") is None:
        pytest.skip("no C compiler: the bench leaves its C reference out")
    bench = load("bench_fieldbus", "fieldbus.py")  # by path: ``fieldbus`` is the project's package
    stress = load("bench_fieldbus_stress", "fieldbus_stress.py")
    exe = bench.build_rt_floor(tmp_path)
    assert exe is not None
    beside = stress.Beside(exe, 0.002, 0, tmp_path)  # normal priority: any user may run it
    time.sleep(0.5)  # bounded: it runs until closed
    t0 = time.monotonic() - 0.4
    ref = beside.close((t0, t0 + 0.3))
    assert beside.proc.returncode == 0  # SIGTERM ends it with its record written
    assert ref is not None
    assert abs(ref["n"] - 150) <= 1  # every 2 ms in 0.3 s, by when each was due, however late
    assert 0 <= ref["p50"] <= ref["p99"] <= ref["p999"] <= ref["max"]
