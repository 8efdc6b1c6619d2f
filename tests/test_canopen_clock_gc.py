"""PeriodicRunner: garbage collection steered into the slack between steps, and CPU affinity."""

from __future__ import annotations

import gc
import itertools
import logging
import os
import threading
import time
import weakref

import pytest

from fieldbus.canopen.clock import PeriodicRunner


class Cycle:
    """A node that points at itself: freed only by the cyclic collector."""

    def __init__(self) -> None:
        self.me = self


def _churn(n: int) -> None:
    for _ in range(n):
        Cycle()


@pytest.fixture
def gc_events():
    """(phase, generation, in_step, thread id, time) of every collection while the test runs."""
    state = {"in_step": False, "first": float("inf"), "last": 0.0}
    events: list[tuple[str, int, bool, int, float]] = []

    def callback(phase: str, info: dict) -> None:
        events.append((phase, info["generation"], state["in_step"], threading.get_ident(), time.monotonic()))

    gc.callbacks.append(callback)
    try:
        yield state, events
    finally:
        gc.callbacks.remove(callback)


def _run_with_churn(state: dict, steer_gc: bool, freed: list[int]) -> PeriodicRunner:
    """A 4 ms runner whose step allocates cyclic garbage (as much as gc's young threshold) while another
    thread allocates cyclic garbage as fast as it can; bounded to 60 cycles and 10 s."""
    per_step = gc.get_threshold()[0]

    def step(k: int, t: float) -> None:
        state["in_step"] = True
        state["first"] = min(state["first"], time.monotonic())
        try:
            for _ in range(per_step):
                c = Cycle()
                weakref.finalize(c, freed.append, 1) if _ % 100 == 0 else None
            time.sleep(0.0002)  # the other thread gets the interpreter inside the step too
        finally:
            state["in_step"] = False
            state["last"] = time.monotonic()

    stop = threading.Event()

    def hog() -> None:
        end = time.monotonic() + 10
        while not stop.is_set() and time.monotonic() < end:
            _churn(200)

    other = threading.Thread(target=hog, daemon=True)
    other.start()
    runner = PeriodicRunner(0.004, step, cycles=60, steer_gc=steer_gc).start()
    try:
        assert runner.join(10)
    finally:
        stop.set()
        other.join(10)
    assert runner.error is None
    return runner


def test_steered_gc_never_starts_inside_a_step(gc_events):
    state, events = gc_events
    freed: list[int] = []
    runner = _run_with_churn(state, True, freed)
    starts = [e for e in events if e[0] == "start"]
    assert starts, "the runner never collected"
    assert [e for e in starts if e[2]] == []  # none while a step ran
    # from the first step to the last, every collection ran on the cycle thread, none on the allocating one
    running = [e for e in starts if state["first"] <= e[4] <= state["last"]]
    assert running and {e[3] for e in running} == {runner._thread.ident}
    assert sum(runner.stats.gc_collections) > 0 and freed  # garbage was collected, memory stays bounded


def test_unsteered_gc_does_start_inside_steps(gc_events):
    """The same load without steering: the collector runs inside steps (what the option prevents)."""
    state, events = gc_events
    _run_with_churn(state, False, [])
    assert [e for e in events if e[0] == "start" and e[2]]


@pytest.mark.parametrize("enabled", [True, False])
def test_gc_state_restored_after_stop(enabled: bool):
    was = gc.isenabled()
    (gc.enable if enabled else gc.disable)()
    try:
        during: list[tuple[bool, int]] = []
        runner = PeriodicRunner(0.002, lambda k, t: during.append((gc.isenabled(), gc.get_freeze_count())),
                                cycles=5, steer_gc=True).start()
        assert runner.join(5)
        assert during[0][0] is False and during[0][1] > 0  # disabled, set-up frozen while running
        assert gc.isenabled() is enabled and gc.get_freeze_count() == 0
    finally:
        (gc.enable if was else gc.disable)()


def test_gc_state_restored_after_a_step_fails():
    def step(k: int, t: float) -> None:
        raise RuntimeError("boom")

    runner = PeriodicRunner(0.002, step, steer_gc=True).start()
    assert runner.join(5)
    assert isinstance(runner.error, RuntimeError)
    assert gc.isenabled() and gc.get_freeze_count() == 0


def test_a_second_steering_runner_leaves_gc_to_the_first(caplog):
    release = threading.Event()
    first = PeriodicRunner(0.002, lambda k, t: None if not release.is_set() else False, steer_gc=True,
                           name="first").start()
    try:
        time.sleep(0.05)
        with caplog.at_level(logging.WARNING, logger="fieldbus.canopen.clock"):
            second = PeriodicRunner(0.002, lambda k, t: None, cycles=5, steer_gc=True, name="second").start()
            assert second.join(5)
        assert "already steered by first" in caplog.text
        assert not gc.isenabled()  # the second one's end did not re-enable what the first disabled
    finally:
        release.set()
        assert first.join(5)
    assert gc.isenabled() and gc.get_freeze_count() == 0


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="Linux only")
def test_cpu_affinity_pins_the_cycle_thread_only():
    cpu = max(os.sched_getaffinity(0))
    seen: list[set[int]] = []
    runner = PeriodicRunner(0.002, lambda k, t: seen.append(os.sched_getaffinity(runner.native_id)),
                            cycles=5, cpu_affinity=[cpu])
    runner.start()  # assigned first: the first step reads it and may run before start() returns
    assert runner.join(5)
    assert runner.affinity_applied
    assert seen and all(s == {cpu} for s in seen)
    assert os.sched_getaffinity(0) != {cpu} or len(os.sched_getaffinity(0)) == 1  # caller not pinned


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="Linux only")
def test_refused_cpu_affinity_is_logged_and_the_runner_runs(caplog):
    with caplog.at_level(logging.WARNING, logger="fieldbus.canopen.clock"):
        runner = PeriodicRunner(0.002, lambda k, t: None, cycles=5, cpu_affinity=[4095]).start()
        assert runner.join(5)
    assert not runner.affinity_applied and runner.stats.cycles == 5
    assert "not pinned to CPUs [4095]" in caplog.text


def test_the_step_trace_records_each_step_with_its_cpu_time(tmp_path, monkeypatch):
    """CANON_CYCLE_TRACE: deadline, start, end and CPU seconds of every step, written at the runner's
    end; a step that computes shows CPU time near its duration, one that sleeps shows almost none."""
    from array import array

    from fieldbus.canopen.clock import TRACE_ENV

    monkeypatch.setenv(TRACE_ENV, str(tmp_path))

    def step(k: int, t: float) -> None:
        if k == 3:
            end = time.thread_time() + 0.004  # 4 ms of this thread's CPU
            while time.thread_time() < end:
                pass
        elif k == 6:
            time.sleep(0.004)  # 4 ms off the CPU

    runner = PeriodicRunner(0.01, step, cycles=10, late_s=1.0).start()
    assert runner.join(10.0)
    files = list(tmp_path.glob(f"cycle-{os.getpid()}-{runner.native_id}.f64"))
    assert len(files) == 1
    trace = array("d")
    trace.frombytes(files[0].read_bytes())
    rows = [tuple(trace[i:i + 4]) for i in range(0, len(trace), 4)]
    assert len(rows) == runner.stats.cycles == 10
    for deadline, start, end, cpu in rows:
        assert start >= deadline - 1e-6 and end >= start and 0.0 <= cpu <= end - start + 1e-3
    deadlines = [r[0] for r in rows]
    gaps = [(b - a) / 0.01 for a, b in itertools.pairwise(deadlines)]  # whole periods (late: skipped)
    assert all(g >= 1 - 1e-6 and g == pytest.approx(round(g), abs=1e-6) for g in gaps)
    _, s3, e3, c3 = rows[3]
    assert c3 >= 0.004 and e3 - s3 >= 0.004
    _, s6, e6, c6 = rows[6]
    assert e6 - s6 >= 0.004 and c6 < 0.002
