"""A periodic thread on absolute deadlines, which notices when it is late.

``sleep(period)`` in a loop drifts by the work's duration and hides stalls; here the k-th cycle is due
at ``t0 + k * period``: the thread sleeps until shortly before the deadline and spins the rest (Python's
sleep overshoots by 50-100 us typically, by milliseconds under load). A cycle that starts later than
``late_s`` after its deadline is *late*: counted, and reported to ``on_late`` (the daemon and
:func:`stream` make it a master fault: a drive that missed its SYNC window is not safe to keep
streaming to). Deadlines missed entirely are skipped, never made up in a burst.

Two things make the wake-up prompt on a PC, both what cyclictest and real-time Linux applications do:
SCHED_FIFO for the cycle thread (``realtime_priority``), and a PM QoS request on
``/dev/cpu_dma_latency`` (``cpu_latency_us``) held while the runner runs, which keeps the CPUs out of
the deep idle states (or, in a VM, out of the halt that hands the CPU back to the host) whose exit
takes hundreds of microseconds. Both need root or CAP_SYS_NICE; without them the runner logs it and
runs anyway. ``cpu_affinity`` pins the cycle thread to a set of CPUs (say, one kept free of other
work with ``isolcpus`` or a cgroup); a refused or invalid set is logged and the thread runs unpinned.

Garbage collection (``steer_gc``). CPython's cyclic collector runs when *any* thread's allocations
cross a threshold, on that thread, holding the interpreter lock for the whole pass: a young-generation
pass takes tens to hundreds of microseconds, a full (generation 2) pass over a large heap tens of
milliseconds. Triggered by the interpreter or a status publisher, it stalls the cycle thread
that wakes meanwhile; triggered by the step's own allocations, it stalls the step. With ``steer_gc``
the runner, at its start (after the caller's set-up), collects once, moves every object that exists by
then to the permanent generation (``gc.freeze``: never scanned again) and disables automatic
collection for the whole process; it then collects the young generations itself in the slack after a
step, when the time left before the next deadline exceeds twice the longest recent pass of that
generation (measured: the first pass of each generation waits for a slack of half a period, and times
itself), and a full collection only when the slack is at least half a period and at most every
``gc_full_every_s``.
If the slack never suffices, a young collection is forced after ``FORCE_FACTOR`` thresholds' worth
of allocations (counted: memory must stay bounded). At stop or error the runner restores the
collector's previous state (enabled or not; frozen objects unfrozen if none were frozen before).
``gc`` state is process-wide: only one steering runner at a time (a second one is refused).
"""

from __future__ import annotations

import contextlib
import gc
import logging
import os
import struct
import threading
import time
from array import array
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field

log = logging.getLogger(__name__)

#: an environment variable naming a folder: a :class:`PeriodicRunner` records, for each step, its
#: deadline, its start, its end (``time.monotonic``) and the thread's CPU seconds in it, and writes them
#: there at its end (``cycle-PID-TID.f64``: native doubles, four a step). A bench then tells a step
#: that started late because the one before ran long (its own work: CPU time near its duration) from
#: one held off (waiting for the interpreter lock or a CPU: duration well above its CPU time)
TRACE_ENV = "CANON_CYCLE_TRACE"


def write_trace(env: str, name: str, trace: array) -> None:
    """``trace`` as native doubles into the file ``name`` in the folder the environment variable ``env``
    names (:data:`TRACE_ENV`, :data:`fieldbus.canopen.sync_process.TRACE_ENV`); a failure is a warning."""
    folder = os.environ.get(env, "")
    try:
        with open(os.path.join(folder, name), "wb") as f:
            trace.tofile(f)
    except OSError as exc:
        log.warning("trace not written to %s: %s", folder, exc)


@dataclass
class CycleStats:
    """Per-cycle wake-up lateness (seconds after the deadline) and counts."""

    period_s: float
    cycles: int = 0
    late: int = 0
    skipped: int = 0
    lateness: list[float] = field(default_factory=list)
    started: float = 0.0
    ended: float = 0.0
    cpu_s: float = 0.0
    work_s: float = 0.0  # time spent inside step (the rest is sleeping and spinning to the deadline)
    gc_collections: list[int] = field(default_factory=lambda: [0, 0, 0])  # by generation, in the slack
    gc_forced: int = 0  # young collections forced without enough slack (garbage piled up)
    gc_max_s: float = 0.0  # longest collection the runner ran

    @property
    def achieved_period_s(self) -> float:
        return (self.ended - self.started) / self.cycles if self.cycles else 0.0


class CpuLatencyRequest:
    """A PM QoS request for CPU wake-up latency: while the file stays open, the kernel keeps every
    CPU's idle exit under ``us`` microseconds (0: polling idle). Closing the file ends the request."""

    PATH = "/dev/cpu_dma_latency"

    def __init__(self, us: int) -> None:
        if us < 0:
            raise ValueError(f"CPU latency must be >= 0 us, got {us}")
        self.us = us
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self) -> bool:
        """Make the request; False (logged) when the kernel's file cannot be opened (not root)."""
        if self._fd is not None:
            return True
        try:
            fd = os.open(self.PATH, os.O_WRONLY)
        except OSError as exc:
            log.info("no CPU latency request (%s: %s): idle CPUs may wake late", self.PATH, exc.strerror)
            return False
        try:
            os.write(fd, struct.pack("<i", self.us))
        except OSError as exc:
            os.close(fd)
            log.info("no CPU latency request (%s: %s)", self.PATH, exc.strerror)
            return False
        self._fd = fd
        return True

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def set_fifo(priority: int) -> str:
    """SCHED_FIFO at ``priority`` for the calling thread (Linux, root or CAP_SYS_NICE); the threads it
    starts afterwards inherit it. "" when done, else why it was refused.

    The cycle thread's priority alone does not keep its deadlines: every thread of its process that
    takes the interpreter lock (python-can's reader, whatever sends the state out) must be able to give
    it back at once. An ordinary thread holding the lock, preempted by any other busy process, stalls
    the cycle as long as it waits for a CPU (a priority inversion: with two CPU hogs and the cycle
    thread itself at SCHED_FIFO 80, ``bench/fieldbus.py --stress`` measured a SYNC deviation p99.9 of
    12-15 ms and single gaps up to 179 ms so; 1.3-2.3 ms with the other threads ranked below it).
    So a process whose cycle runs at SCHED_FIFO runs its other threads at SCHED_FIFO too, below it
    (:func:`helper_priority`)."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (AttributeError, OSError) as exc:
        return str(exc) or type(exc).__name__
    return ""


def helper_priority(cycle_priority: int) -> int:
    """The SCHED_FIFO priority of the threads that share the interpreter lock with a cycle thread at
    ``cycle_priority``: one below it (they never preempt it for a CPU), at least 1."""
    return max(1, cycle_priority - 1)


def rank_below_cycle(cycle_priority: int, who: str, logger: logging.Logger, below: int = 1) -> bool:
    """With a SCHED_FIFO cycle at ``cycle_priority`` (``[canopen] realtime_priority``; 0: none), the
    calling thread, and so every thread it starts afterwards, at SCHED_FIFO ``below`` under it (1:
    :func:`helper_priority`, the threads of the cycle's own process; negative: above it, as simulated
    drives standing in for hardware), within SCHED_FIFO's 1-99. A refusal (not root, no CAP_SYS_NICE)
    is a warning naming ``who``: they run at normal priority. True when ranked."""
    if cycle_priority <= 0:
        return False
    priority = min(99, max(1, cycle_priority - below))
    refused = set_fifo(priority)
    if refused:
        logger.warning("%s stay at normal priority (SCHED_FIFO %d refused: %s)", who, priority, refused)
    return not refused


@contextlib.contextmanager
def ranked_below_cycle(cycle_priority: int, who: str, logger: logging.Logger,
                       below: int = 1) -> Iterator[bool]:
    """:func:`rank_below_cycle` for the body of a ``with`` only: the calling thread's policy is given
    back at the end, so a tool's entry point called in-process (canon's ``main`` in a test, a user's
    script) does not leave that process's thread at real-time priority."""
    try:
        before = (os.sched_getscheduler(0), os.sched_getparam(0))
    except (AttributeError, OSError):
        before = None
    ranked = rank_below_cycle(cycle_priority, who, logger, below)
    try:
        yield ranked
    finally:
        if ranked and before is not None:
            with contextlib.suppress(OSError):
                os.sched_setscheduler(0, before[0], before[1])


class PeriodicRunner:
    """Call ``step(k, t)`` every ``period_s`` on its own thread (``k``: deadline number, ``t``: the
    deadline, ``time.monotonic`` seconds) until :meth:`stop`, ``cycles`` steps are done, or ``step``
    returns ``False``.

    ``tick``: pace the steps by an outside clock instead of absolute deadlines (the kernel's SYNC:
    :attr:`~fieldbus.canopen.master.CanopenMaster.sync_tick`). ``tick(until)`` waits until ``until``
    (``time.monotonic``) for the next tick and returns (time of the first tick not yet taken, time of
    the last, how many), or None when none came; ``tick(0.0)`` takes those already there."""

    def __init__(self, period_s: float, step: Callable[[int, float], bool | None], *,
                 cycles: int | None = None, late_s: float | None = None,
                 on_late: Callable[[int, float], None] | None = None, spin_s: float = 0.0003,
                 keep_lateness: bool = True, name: str = "canopen-cycle",
                 realtime_priority: int = 0, cpu_latency_us: int | None = None,
                 cpu_affinity: Iterable[int] | None = None, steer_gc: bool = False,
                 gc_full_every_s: float = 10.0,
                 tick: Callable[[float], tuple[float, float, int] | None] | None = None) -> None:
        if period_s <= 0:
            raise ValueError("period must be > 0")
        self.period_s = period_s
        self.step = step
        self.cycles = cycles
        self.late_s = period_s / 2 if late_s is None else late_s
        self.on_late = on_late
        self.spin_s = spin_s
        self.keep_lateness = keep_lateness
        self.realtime_priority = realtime_priority
        self.realtime = False  # True when the thread got SCHED_FIFO
        self.cpu_latency = None if cpu_latency_us is None else CpuLatencyRequest(cpu_latency_us)
        self.cpu_latency_held = False  # True when the CPU latency request was made
        self.cpu_affinity = frozenset(cpu_affinity) if cpu_affinity else None
        self.affinity_applied = False  # True when the thread was pinned to cpu_affinity
        self.native_id: int | None = None  # the cycle thread's kernel id, once running
        self.steer_gc = steer_gc
        self.gc_full_every_s = gc_full_every_s
        self.tick = tick
        self.stats = CycleStats(period_s)
        self._trace: array | None = array("d") if os.environ.get(TRACE_ENV) else None
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> PeriodicRunner:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()

    def join(self, timeout: float | None = None) -> bool:
        """Wait for the end; True when the thread has ended."""
        self._thread.join(timeout)
        return not self._thread.is_alive()

    def _set_realtime(self) -> None:
        """SCHED_FIFO for this thread (Linux, root or CAP_SYS_NICE): the kernel then wakes it ahead
        of ordinary threads; it still needs the interpreter lock (see ``sys.setswitchinterval``, and
        :func:`set_fifo` for the threads it shares that lock with)."""
        if not self.realtime_priority:
            return
        refused = set_fifo(self.realtime_priority)
        self.realtime = not refused
        if refused:
            log.warning("cycle thread stays at normal priority (SCHED_FIFO %d refused: %s)",
                        self.realtime_priority, refused)

    def _set_affinity(self) -> None:
        """Pin this thread (pid 0: the calling thread on Linux) to ``cpu_affinity``."""
        if self.cpu_affinity is None:
            return
        try:
            os.sched_setaffinity(0, self.cpu_affinity)
            self.affinity_applied = True
        except (AttributeError, OSError, ValueError) as exc:
            log.warning("cycle thread not pinned to CPUs %s (refused: %s); it runs on any CPU",
                        sorted(self.cpu_affinity), exc)

    def _run(self) -> None:
        self.native_id = threading.get_native_id()
        self._set_realtime()
        self._set_affinity()
        if self.cpu_latency is not None:
            self.cpu_latency_held = self.cpu_latency.acquire()
        steer = _GcSteering(self) if self.steer_gc else None
        if steer is not None and not steer.begin():
            steer = None
        st = self.stats
        cpu0 = time.thread_time()
        try:
            if self.tick is None:
                self._run_on_clock(steer)
            else:
                self._run_on_ticks(self.tick, steer)
        except BaseException as exc:  # reported to the caller through .error
            self.error = exc
            log.exception("periodic step failed")
        finally:
            st.ended = time.monotonic()
            st.cpu_s = time.thread_time() - cpu0
            if self._trace is not None:
                write_trace(TRACE_ENV, f"cycle-{os.getpid()}-{self.native_id}.f64", self._trace)
            if steer is not None:
                steer.end()
            if self.cpu_latency is not None:
                self.cpu_latency.release()

    def _step_at(self, k: int, deadline: float, now: float, missed: int = 0) -> bool:
        """Step ``k`` of ``deadline``, started at ``now`` (``missed`` ticks skipped before it): its
        lateness recorded and reported; False when the step asks to end the loop."""
        st = self.stats
        late = now - deadline
        if self.keep_lateness:
            st.lateness.append(late)
        if late > self.late_s or missed:
            st.late += 1
            st.skipped += missed
            if self.on_late is not None:
                self.on_late(k, late)
        st.cycles += 1
        trace = self._trace
        cpu = time.thread_time() if trace is not None else 0.0
        result = self.step(k, deadline)
        end = time.monotonic()
        st.work_s += end - now
        if trace is not None:
            trace.extend((deadline, now, end, time.thread_time() - cpu))
        return result is not False

    def _run_on_clock(self, steer: _GcSteering | None) -> None:
        """Steps on absolute deadlines ``t0 + k * period``."""
        st = self.stats
        period = self.period_s
        t0 = time.monotonic() + period
        st.started = t0
        k = 0
        while not self._stop.is_set() and (self.cycles is None or st.cycles < self.cycles):
            deadline = t0 + k * period
            now = time.monotonic()
            if deadline - now > self.spin_s:
                time.sleep(deadline - now - self.spin_s)
            while (now := time.monotonic()) < deadline:
                pass
            if not self._step_at(k, deadline, now):
                break
            k += 1
            if steer is not None:
                steer.after_step(t0 + k * period - self.spin_s)
            behind = int((time.monotonic() - (t0 + k * period)) // period)
            if behind > 0:  # deadlines already gone: late, and skipped (never a burst to catch up)
                st.late += 1
                st.skipped += behind
                if self.on_late is not None:
                    self.on_late(k, time.monotonic() - (t0 + k * period))
                k += behind

    def _run_on_ticks(self, tick: Callable[[float], tuple[float, float, int] | None],
                      steer: _GcSteering | None) -> None:
        """Steps paced by ``tick`` (the kernel's SYNC as the master sees it): each step right after the
        next tick, its deadline the tick's time. Ticks that came while a step ran count as skipped (the
        step is late), as does a tick that does not come within a period of when it was due: then the
        step runs on the clock, so that a stopped tick source is noticed by the step (the master faults)
        and the loop goes on. A tick from before the last step began, seen only after it (its reader held
        up), brings no step: that step's setpoints already wait for the tick after it, and a second
        step would send two setpoints between two SYNCs (the drive takes the later: two periods' travel
        in one, a velocity step past its limit at speed, EMCY 0x8400)."""
        st = self.stats
        period = self.period_s
        tick(0.0)  # ticks from before the start (queued while nothing waited) are not this loop's
        due = time.monotonic() + period  # the next tick, at the latest
        st.started = due
        prev: float | None = None  # the time of the last tick taken
        stepped = 0.0  # when the last step began
        k = 0
        while not self._stop.is_set() and (self.cycles is None or st.cycles < self.cycles):
            got = tick(due + period)
            now = time.monotonic()
            if got is None:
                deadline, missed = due, 1
                prev, due = due, due + period
            elif got[1] < stepped:
                # ticks that were out before the last step began, seen only now (their reader was held
                # up, so that step ran on the clock or late): what it sent is for the tick after them. A
                # step now would put a second setpoint before that one tick, two periods' travel in one
                prev, due = got[1], got[1] + period
                continue
            else:
                deadline, last, n = got
                # by the ticks' times too: the step may take ticks itself (the master's cycle counts the
                # SYNCs it sees), and those missed are this loop's as well
                missed = n - 1 if prev is None else max(n - 1, round((last - prev) / period) - 1)
                prev, due = last, last + period
            k += missed
            stepped = now
            if not self._step_at(k, deadline, now, missed):
                break
            k += 1
            if steer is not None:
                steer.after_step(due - self.spin_s)


class _GcSteering:
    """The garbage collector driven from a :class:`PeriodicRunner`'s slack (see the module docstring)."""

    #: a young collection is forced, slack or not, once this many thresholds of allocations piled up
    FORCE_FACTOR = 20
    _owner: PeriodicRunner | None = None  # the one steering runner (gc state is process-wide)
    _owner_lock = threading.Lock()

    def __init__(self, runner: PeriodicRunner) -> None:
        self.runner = runner
        self.was_enabled = True
        self.was_frozen = 0
        self.estimate: list[float | None] = [None, None, None]  # longest recent pass per generation, s
        self.last_full = 0.0

    def begin(self) -> bool:
        with _GcSteering._owner_lock:
            if _GcSteering._owner is not None:
                log.warning("garbage collection already steered by %s: %s leaves it alone",
                            _GcSteering._owner._thread.name, self.runner._thread.name)
                return False
            _GcSteering._owner = self.runner
        self.was_enabled = gc.isenabled()
        self.was_frozen = gc.get_freeze_count()
        gc.disable()
        gc.collect()  # before the first deadline: the set-up's garbage is not frozen
        gc.freeze()
        self.last_full = time.monotonic()
        return True

    def end(self) -> None:
        if self.was_frozen == 0:
            gc.unfreeze()
        if self.was_enabled:
            gc.enable()
        with _GcSteering._owner_lock:
            _GcSteering._owner = None

    def _collect(self, generation: int) -> None:
        t = time.perf_counter()
        gc.collect(generation)
        took = time.perf_counter() - t
        st = self.runner.stats
        st.gc_collections[generation] += 1
        st.gc_max_s = max(st.gc_max_s, took)
        # the estimate follows a longer pass at once and decays slowly towards shorter ones
        est = self.estimate
        old = est[generation]
        est[generation] = took if old is None or took > old else 0.9 * old + 0.1 * took

    def _fits(self, generation: int, slack: float) -> bool:
        est = self.estimate[generation]
        if est is None:  # not measured yet: only in a generous slack
            return slack >= self.runner.period_s / 2
        return slack > 2 * est

    def after_step(self, wake_at: float) -> None:
        """Collect what is due and fits before ``wake_at`` (monotonic time the runner must be awake)."""
        count = gc.get_count()
        threshold = gc.get_threshold()
        now = time.monotonic()
        slack = wake_at - now
        if (count[2] >= threshold[2] and slack >= self.runner.period_s / 2 and self._fits(2, slack)
                and now - self.last_full >= self.runner.gc_full_every_s):
            self._collect(2)
            self.last_full = now
        elif count[1] >= threshold[1] and self._fits(1, slack):
            self._collect(1)
        elif count[0] >= threshold[0] and self._fits(0, slack):
            self._collect(0)
        elif count[0] >= self.FORCE_FACTOR * threshold[0]:
            self.runner.stats.gc_forced += 1
            self._collect(0)


def stream(master, trajectory: Callable[[float], Sequence[float]], seconds: float, *,
           fault_on_late: bool = True, late_s: float | None = None) -> PeriodicRunner:
    """Stream ``trajectory(t)`` (positions at ``t`` seconds from the start, ``t`` advancing one period per
    executed cycle) to ``master`` for ``seconds`` worth of cycles on a :class:`PeriodicRunner`; started,
    not joined, at the master's ``realtime_priority``. A late cycle is a master fault unless
    ``fault_on_late`` is False."""
    period = master.config.cycle_s
    n = max(1, round(seconds / period))
    sent = [0]

    def step(k: int, deadline: float) -> None:
        # one setpoint per executed cycle, as from the planner: after skipped deadlines the trajectory
        # carries on from where it was (a jump would fault the drives)
        master.cycle(trajectory(sent[0] * period))
        sent[0] += 1

    def late(k: int, by: float) -> None:
        if fault_on_late:
            master.raise_fault(0, f"cycle {k} late by {1000 * by:.2f} ms (period {1000 * period:g} ms)")

    return PeriodicRunner(period, step, cycles=n, late_s=late_s, on_late=late, tick=master.sync_tick,
                          realtime_priority=master.config.realtime_priority).start()
