"""bench/interpreter.py takes canon's runs and rs274's in turn (one of each per round), so that a slow
stretch of the machine falls on both sides of the ratio, and keeps the least CPU time of each."""

from __future__ import annotations

import importlib.util
import itertools
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parent.parent


def bench() -> ModuleType:
    spec = importlib.util.spec_from_file_location("bench_interpreter", ROOT / "bench" / "interpreter.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_measurements_take_turns_one_of_each_per_round() -> None:
    b = bench()
    order: list[str] = []
    cpu = itertools.count(10, -1)  # each later run takes less CPU

    def measure(name: str):
        def run() -> tuple[float, float]:
            order.append(name)
            return 0.0, float(next(cpu))
        return run

    results = b.interleaved(3, {"canon": measure("canon"), "rs274": measure("rs274")})
    assert order == ["canon", "rs274"] * 3
    assert [r[1] for r in results["canon"]] == [10.0, 8.0, 6.0]
    assert [r[1] for r in results["rs274"]] == [9.0, 7.0, 5.0]
    assert b.least(results["canon"]) == (0.0, 6.0) and b.least(results["rs274"]) == (0.0, 5.0)
