"""The stressed case of ``bench/fieldbus.py --stress``: the master's cycle on a busy PC (issue 14).

While two CPU hogs run (``stress-ng --cpu 2``; installed with apt-get when missing and running as root,
else two Python busy loops in two processes, said in the output), 3 and 6 drives in another process on
udp_multicast (hop_limit 0, inside a loopback-only network namespace: the bench re-executes itself in
one through ``tests/netns-run`` when root) are driven at the chosen period, in two arrangements
(``--arrangement``, default both):

* ``own``, the daemon's: a :class:`~motiond.runtime.Machine` in the bench's process (the task side)
  with ``[motion] process = "own"``, so the master's cycle runs in the motion process it starts, as in
  ``canon daemon``; it runs a long program (every axis back and forth at once: each drive's setpoint
  changes every cycle), and its own ``canon-status`` thread publishes ``canon.status`` at 100 Hz on LCM
  (ttl=0) to a client process that counts it. The task process runs SCHED_FIFO 50 when
  ``--rt-priority`` is above it, as ``examples/canon.service`` runs the daemon (``--task-priority``;
  0: normal priority, as ``canon daemon`` started by hand). The master's timeouts are 1 s
  (``late_fault_s``, ``feedback_timeout_s``): what is measured is the SYNC, not a fault.
* ``in-process``, the earlier measurement: the master in the bench's process beside a status thread
  that builds a ``canon.status`` from the master's feedback at 100 Hz (a sine on every axis).

The drives' process records each SYNC (its CANopen reader thread, the one that runs the drives): the
kernel's receive time stamp of its datagram (SO_TIMESTAMPNS, what a drive's hardware would see) and the
time its reader got it. The SYNC period is taken from the kernel's stamps (p50, p99, p99.9, max, and
its deviation from the nominal period); the deviation p99.9 from the reader's times is a column of its
own (it adds the simulator's own scheduling), and so is the spread of the deviation's p99.9 taken
second by second (median / max). With the SYNC from a SYNC process, the column "at the SYNC process"
takes the period from the times it sent each SYNC (it records them when ``CANON_SYNC_TRACE`` names a
folder): the jitter canon itself puts on the SYNC, before the sockets, the kernel's loopback and the
receiving process add theirs. The drives count their missed setpoints. In the same run and under
the same hogs, ``bench/rt_floor.c`` gives the C reference: the kernel's wake-up lateness for a
periodic thread (:class:`Beside`), with the spread of its per-second p99.9. It runs beside each case,
at the SYNC process's priority and at its own phase, and its wake-ups due within the case's window are
taken: a host that takes the CPUs away now and then (a VM) then stops the reference in the same seconds
as the SYNC. It runs alone before the cases and again after them too, as a reference in other
seconds; a few seconds far above the median show a disturbed host there, and the bench says so.
Each row has the 1-minute load average when it ended; the ``own`` case prints the motion process's
threads during the measured window (policy and priority, CPU time, time runnable but waiting for a
CPU, preemptions).

Target (issue 14): no setpoint missed at any drive, and the SYNC period's deviation p99.9 no more
than 1.5 x the C reference's wake-up lateness p99.9 beside the case (without a C compiler: the lower of
the runs before and after the cases).

The drives' process gets the master's SCHED_FIFO priority minus one (``--drives-priority``): real
drives are hardware, and the point is the master's SYNC, not the simulator's own jitter under the hogs.

    sudo .venv/bin/python bench/fieldbus.py --stress --rt-priority 80 --steer-gc on            # 60 s a case
    sudo .venv/bin/python bench/fieldbus.py --stress --rt-priority 80 --arrangement own --drives 6 \
        --seconds 15 --task-priority 0

Measured (2-core VM shared with other agents and a second ``stress-ng --cpu 2``; figures in
docs/canopen.md, "Benchmark").
"""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from fieldbus.canopen.clock import TRACE_ENV as CYCLE_TRACE_ENV  # noqa: E402  (after the path)
from fieldbus.canopen.sync_process import TRACE_ENV  # noqa: E402  (after the path)

STATUS_CHANNEL = "CANON_STATUS"
DRIVES_PRIORITY = -1
"""The drives' process's SCHED_FIFO priority (``--drives-priority``; -1: the master's minus one)."""


# ---------------------------------------------------------------- the hogs
class Hogs:
    """Two CPU hogs for the whole stressed run; :meth:`stop` ends exactly the processes started here."""

    def __init__(self, n: int = 2) -> None:
        self.procs: list[subprocess.Popen] = []
        exe = shutil.which("stress-ng") or self._install()
        if exe is not None:
            self.what = f"stress-ng --cpu {n}"
            self.procs.append(subprocess.Popen([exe, "--cpu", str(n), "--quiet"], stdout=subprocess.DEVNULL,
                                               stderr=subprocess.DEVNULL, start_new_session=True))
        else:
            self.what = f"{n} Python busy loops in {n} processes (stress-ng not available)"
            for _ in range(n):
                self.procs.append(subprocess.Popen([sys.executable, "-c", "while True: pass"],
                                                   start_new_session=True))
        time.sleep(0.5)  # the hogs are spinning before anything is measured

    @staticmethod
    def _install() -> str | None:
        if os.geteuid() != 0 or shutil.which("apt-get") is None:
            return None
        print("installing stress-ng with apt-get ...", file=sys.stderr, flush=True)
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        res = subprocess.run(["apt-get", "install", "-y", "-q", "stress-ng"], capture_output=True, text=True,
                             env=env, timeout=600)
        if res.returncode != 0:
            print(f"apt-get install stress-ng failed: {res.stderr.strip()[-300:]}", file=sys.stderr)
        return shutil.which("stress-ng")

    def stop(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)  # its own session: stress-ng and its workers, no more
        for p in self.procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(10)


# ---------------------------------------------------------------- the drives' process
def drives_child(config_path: str, out_path: str, priority: int) -> int:
    """``--drives-child``: the configured drives on their bus, SYNC arrival times recorded on the drives'
    own reader thread; at SIGTERM the SYNC intervals and the drives' counts go to ``out_path`` (JSON)."""
    from fieldbus.canopen.drive_sim import SimDrive
    from fieldbus.canopen.sim_process import SimBus
    from motiond.config_canopen import canopen_for_tool

    if priority > 0:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))  # before any thread starts
        except OSError as exc:
            print(f"drives: SCHED_FIFO refused ({exc})", file=sys.stderr)
    config, bus = canopen_for_tool(config_path)
    drives = [SimDrive(d.node_id, d.eds_path) for d in config.drives]
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    arrivals: list[float] = []  # time.monotonic() when the drives' reader thread got it
    stamps: list[float] = []  # the kernel's receive time stamp of its datagram (SO_TIMESTAMPNS)
    sims = SimBus(drives, bus)

    def sync(can_id: int, data: bytes, ts: float) -> None:
        arrivals.append(time.monotonic())
        stamps.append(ts)

    # first among the SYNC's subscribers: the time it reached the drives, before they run their cycle
    sims.network.subscribers.setdefault(0x80, []).insert(0, sync)
    print("simulating", flush=True)
    try:
        stop.wait()
    finally:
        sims.close()
    # CLOCK_MONOTONIC is one clock for every process: the master picks its run's SYNCs by time
    result = {"arrivals": arrivals, "stamps": stamps,
              "missed_setpoints": {d.id: d.missed_setpoints for d in drives},
              "late_syncs": {d.id: d.late_syncs for d in drives},
              "emcy": {d.id: [hex(c) for c in d.emcys] for d in drives}}
    Path(out_path).write_text(json.dumps(result))
    return 0


class Drives:
    def __init__(self, n: int, group: str, tmp: Path, priority: int) -> None:
        text = "".join(f"[axes.{'xyzabc'[i]}]\n" for i in range(n))
        text += f'[canopen]\ninterface = "udp_multicast"\nchannel = "{group}"\n'
        text += "".join(f"[canopen.axes.{'xyzabc'[i]}]\nnode_id = {i + 1}\n" for i in range(n))
        (tmp / "stress.toml").write_text(text)
        self.out = tmp / "drives.json"
        self.proc = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--drives-child",
                                      str(tmp / "stress.toml"), str(self.out), str(priority)], cwd=ROOT,
                                     stdout=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if not line.startswith("simulating"):
            raise SystemExit(f"the drives' process did not start: {line}")

    def close(self) -> dict:
        self.proc.terminate()
        try:
            self.proc.wait(30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(10)
            return {}
        return json.loads(self.out.read_text()) if self.out.exists() else {}


# ---------------------------------------------------------------- the status load
def status_client(seconds: float, out_path: str) -> int:
    """``--status-client``: subscribe to the status and count what arrives."""
    import lcm

    from telemetry.url import DEFAULT_URL

    lc = lcm.LCM(DEFAULT_URL)
    got = [0]
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    lc.subscribe(STATUS_CHANNEL, lambda ch, data: got.__setitem__(0, got[0] + 1))
    print("subscribed", flush=True)
    end = time.monotonic() + seconds
    while time.monotonic() < end and not stop.is_set():
        try:
            lc.handle_timeout(50)
        except OSError:  # the select() interrupted by SIGTERM: the end
            if not stop.is_set():
                raise
    Path(out_path).write_text(str(got[0]))
    return 0


class StatusLoad:
    """A 100 Hz thread in the master's process that builds a ``canon.status`` from the master's
    feedback and publishes it (what the daemon's status side does), and a client process counting it."""

    def __init__(self, master, seconds: float, tmp: Path, hz: float = 100.0) -> None:
        import lcm

        from telemetry.url import DEFAULT_URL

        self.master = master
        self.period = 1.0 / hz
        self.lc = lcm.LCM(DEFAULT_URL)
        self.sent = 0
        self.out = tmp / "status.count"
        self.client = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--status-client",
                                        str(seconds + 5), str(self.out)], cwd=ROOT, stdout=subprocess.PIPE,
                                       text=True)
        assert self.client.stdout is not None
        self.client.stdout.readline()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="status-load", daemon=True)
        self._thread.start()

    def _snapshot(self):
        from telemetry.lcmtypes.canon.drive_status import drive_status
        from telemetry.lcmtypes.canon.status import status

        m = self.master
        fb = m.feedback()
        states = m.state
        s = status()
        s.utime = int(time.time() * 1e6)
        s.seq = self.sent
        s.machine, s.state, s.mode = "bench", "running", "auto"
        s.enabled = True
        s.num_axes = len(fb.positions)
        s.axis_names = [d.axis for d in states]
        s.homed = [True] * s.num_axes
        s.commanded = [d.commanded for d in states]
        s.actual = list(fb.positions)
        s.velocity = [0.0] * s.num_axes
        s.following_error = list(fb.following_errors)
        s.drives = []
        for d in states:
            ds = drive_status()
            ds.axis, ds.node_id, ds.nmt_state, ds.heartbeat_ok = d.axis, d.node, "OPERATIONAL", True
            ds.statusword, ds.cia402_state, ds.mode_display = d.statusword, d.state.name, 8
            ds.position_actual, ds.following_error, ds.error = d.actual_counts, 0, ""
            s.drives.append(ds)
        s.num_drives = len(s.drives)
        s.gcodes = ["G1", "G17", "G21", "G40", "G54", "G90", "G94"]
        s.num_gcodes = len(s.gcodes)
        s.mcodes = ["M5", "M9"]
        s.num_mcodes = len(s.mcodes)
        return s

    def _run(self) -> None:
        deadline = time.monotonic()
        while not self._stop.is_set():
            self.lc.publish(STATUS_CHANNEL, self._snapshot().encode())
            self.sent += 1
            deadline += self.period
            self._stop.wait(max(0.0, deadline - time.monotonic()))

    def close(self) -> tuple[int, int]:
        """(published, received by the client)."""
        self._stop.set()
        self._thread.join(5)
        self.client.terminate()
        self.client.wait(10)
        received = int(self.out.read_text()) if self.out.exists() else 0
        return self.sent, received


# ---------------------------------------------------------------- one case
def case(n: int, period: float, seconds: float, rt: int, latency: int | None, steer_gc: bool,
         layout_for, exe: Path | None = None) -> dict:

    from fieldbus.canopen.clock import PeriodicRunner
    from fieldbus.canopen.config import CanBusConfig, CanopenConfig, DriveConfig
    from fieldbus.canopen.master import CanopenMaster

    drives = tuple(DriveConfig("xyzabc"[i], i + 1) for i in range(n))
    bus = CanBusConfig("udp_multicast", f"239.74.166.{1 + os.getpid() % 250}")
    layout, every = layout_for(n, period)
    config = CanopenConfig(bus, drives, cycle_s=period, feedback_timeout_s=1.0, heartbeat_consumer_ms=2000,
                           pdo_layout=layout, following_error_every=every)
    tmp = tempfile.TemporaryDirectory()
    sims = Drives(n, bus.channel, Path(tmp.name), DRIVES_PRIORITY if DRIVES_PRIORITY >= 0 else max(0, rt - 1))
    master = CanopenMaster(config, check_budget=False)
    status: StatusLoad | None = None
    result: dict = {}
    runner = None
    beside = Beside(exe, period, rt, Path(tmp.name))
    ref = None
    try:
        master.boot()
        master.enable()
        start = master.positions()
        done = [0]

        def step(k: int, t: float) -> None:
            s = 10.0 * math.sin(2 * math.pi * 0.5 * done[0] * period)  # 10 mm amplitude, 0.5 Hz
            done[0] += 1
            master.cycle([p + s for p in start])

        status = StatusLoad(master, seconds, Path(tmp.name))
        runner = PeriodicRunner(period, step, cycles=round(seconds / period), realtime_priority=rt,
                                cpu_latency_us=latency, steer_gc=steer_gc).start()
        runner.join(seconds * 3 + 10)
        fault = master.fault
    finally:
        sent, received = status.close() if status is not None else (0, 0)
        master.shutdown()
        result = sims.close()
        st = runner.stats if runner is not None else None
        ref = beside.close((st.started, st.ended + period) if st is not None else (0.0, 0.0))
        tmp.cleanup()
    gc_mode = "steered" if steer_gc else "automatic"
    row = {"case": f"in-process: {n} drives, {1000 * period:g} ms, gc {gc_mode}",
           "status": f"{sent}/{received}"}
    st = runner.stats if runner is not None else None
    # the SYNCs of the streaming run, by the one system-wide monotonic clock (boot, enable and the
    # shutdown's SYNCs left out)
    window = (st.started, st.ended + period) if st is not None else (0.0, 0.0)
    gc_text = "-" if st is None or not steer_gc else \
        f"{sum(st.gc_collections)} ({st.gc_forced} forced), max {1e6 * st.gc_max_s:.0f} us"
    row["ref"] = ref
    return finish_row(row, window, period, result, fault, "-" if st is None else f"{st.late + st.skipped}",
                      gc_text)


# ---------------------------------------------------------------- one case, the daemon's arrangement
def machine_file(n: int, group: str, period: float, rt: int, latency: int | None, steer_gc: bool,
                 layout: str, every: int, sync: str = "master", lead: int = 1) -> str:
    """The machine file of the "own" case: ``[motion] process = "own"``, the drives on ``group`` (not
    simulated by the machine: the bench's drives' process records them), status at 100 Hz."""
    axes = "".join(f"\n[axes.{a}]\nmax_velocity = 200.0\nmax_acceleration = 2000.0\nmax_jerk = 50000.0\n"
                   f"quick_stop_deceleration = 5000.0\n" for a in "xyzabc"[:n])
    drives = "".join(f"\n[canopen.axes.{a}]\nnode_id = {i + 1}\n" for i, a in enumerate("xyzabc"[:n]))
    return (f'[machine]\nname = "stress"\ncycle_ms = {1000 * period:g}\n{axes}\n'
            f'[canopen]\ninterface = "udp_multicast"\nchannel = "{group}"\nheartbeat_producer_ms = 100\n'
            f'heartbeat_consumer_ms = 2000\nsdo_timeout_s = 1.0\nsimulate = false\n'
            f'realtime_priority = {rt}\ncpu_latency_us = {-1 if latency is None else latency}\n'
            f'steer_gc = {str(steer_gc).lower()}\npdo_layout = "{layout}"\nfollowing_error_every = {every}\n'
            f'sync = "{sync}"\n' + (f'setpoint_lead = {lead}\n' if sync == "process" else "") +
            f'{drives}\n[motion]\nprocess = "own"\n\n[telemetry]\nstatus_hz = 100\n')


def program(n: int, seconds: float) -> str:
    """Back and forth on every axis at once, longer than ``seconds``: each drive's setpoint changes
    (nearly) every cycle."""
    words = "XYZABC"[:n]
    there = " ".join(f"{w}{100 if w in 'XYZ' else 90}" for w in words)
    back = " ".join(f"{w}0" for w in words)
    lines = [f"G1 {there} F6000", f"G1 {back}"] * (int(seconds / 2) + 20)
    return "%\nG21 G90 G94\n" + "\n".join(lines) + "\nM2\n%\n"


def case_own(n: int, period: float, seconds: float, rt: int, latency: int | None, steer_gc: bool,
             layout_for, task_priority: int = 0, sync: str = "master", lead: int = 1,
             exe: Path | None = None) -> dict:
    """The daemon's arrangement: a :class:`~motiond.runtime.Machine` with ``[motion] process = "own"``
    here (the task side: its ``canon-status`` thread publishes ``canon.status`` at 100 Hz on LCM, ttl=0,
    a client process counts it), the master's cycle in the motion process it starts, running a long
    program; the drives in the bench's drives' process. ``sync``: who sends the SYNC, the master's
    cycle ("master") or a SYNC process of its own ("process", :mod:`fieldbus.canopen.sync_process`),
    which then also sends the setpoints, ``lead`` SYNCs ahead (``[canopen] setpoint_lead``)."""
    import lcm

    from motiond.config import load_machine
    from motiond.runtime import Machine
    from telemetry.url import DEFAULT_URL

    group = f"239.74.166.{1 + os.getpid() % 250}"
    layout, every = layout_for(n, period)
    tmp = tempfile.TemporaryDirectory()
    where = Path(tmp.name)
    (where / "machine.toml").write_text(machine_file(n, group, period, rt, latency, steer_gc, layout, every,
                                                       sync, lead))
    (where / "long.ngc").write_text(program(n, seconds))
    if sync == "process":  # the SYNC process records when it sent each SYNC (the sender's column)
        os.environ[TRACE_ENV] = str(where)
    os.environ[CYCLE_TRACE_ENV] = str(where)  # and the motion process's cycle its steps (late_steps)
    sims = Drives(n, group, where, DRIVES_PRIORITY if DRIVES_PRIORITY >= 0 else max(0, rt - 1))
    client = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--status-client",
                               str(seconds + 60), str(where / "status.count")], cwd=ROOT,
                              stdout=subprocess.PIPE, text=True)
    assert client.stdout is not None
    client.stdout.readline()
    beside = Beside(exe, period, rt, where)
    ref = None
    window = (0.0, 0.0)
    late = (0, 0.0)
    threads: list[dict] = []
    fault = ""
    sent0 = sent1 = 0
    result: dict = {}
    try:
        # the master's timeouts as the old in-process case: what is measured is the SYNC, not a fault
        if task_priority:  # as the shipped unit runs the daemon (CPUSchedulingPolicy=fifo): every thread
            # the task side starts from here, and the motion process, inherit it
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(task_priority))
        with Machine(load_machine(str(where / "machine.toml")), lc=lcm.LCM(DEFAULT_URL), late_fault_s=1.0,
                     feedback_timeout_s=1.0) as m:
            m.bring_up()
            m.run(str(where / "long.ngc"))
            deadline = time.monotonic() + 30.0
            while m.motion.commanded[0] < 1.0 and time.monotonic() < deadline and not m.last_error:
                time.sleep(0.01)
            late0, sent0 = m.motion.late_cycles, m.status_seq
            before = {r["tid"]: r for r in thread_sched(m.motion.pid)}
            t0 = time.monotonic()
            while time.monotonic() < t0 + seconds and not m.last_error:
                time.sleep(0.1)
            window = (t0, time.monotonic())
            late = (m.motion.late_cycles - late0, m.motion.worst_late_s)
            sent1 = m.status_seq
            threads = thread_sched(m.motion.pid)
            for r in threads:
                b = before.get(r["tid"], {"cpu_ms": 0.0, "wait_ms": 0.0, "invol": 0})
                r.update(cpu_ms=r["cpu_ms"] - b["cpu_ms"], wait_ms=r["wait_ms"] - b["wait_ms"],
                         invol=r["invol"] - b["invol"])
            fault = m.last_error
            m.stop_on_path(10.0)
    finally:
        if task_priority:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        client.terminate()
        client.wait(10)
        result = sims.close()
        ref = beside.close(window)
        os.environ.pop(TRACE_ENV, None)
        os.environ.pop(CYCLE_TRACE_ENV, None)
        received = int((where / "status.count").read_text()) if (where / "status.count").exists() else 0
        sent_at = [t for f in sorted(where.glob("sync-*.f64")) for t in read_trace(f)]
        steps = [read_trace(f) for f in sorted(where.glob("cycle-*.f64"))]
        tmp.cleanup()
    by = f"a SYNC process, setpoints {lead} ahead" if sync == "process" else "the cycle"
    row = {"case": f"own: {n} drives, {1000 * period:g} ms, gc {'steered' if steer_gc else 'automatic'}, "
                   f"SYNC by {by}",
           "status": f"{sent1 - sent0} in window/{received}", "ref": ref}
    print(f"  the motion process's threads during the window ({seconds:g} s): " + "; ".join(
        f"{r['tid']} {r['policy']} cpu {r['cpu_ms']:.0f} ms, waited {r['wait_ms']:.0f} ms, {r['invol']} "
        "preempted" for r in threads if r["cpu_ms"] > 0), flush=True)
    for trace in steps:
        print(late_steps(trace, window, period), flush=True)
    row = finish_row(row, window, period, result, fault, f"{late[0]} (worst {1e3 * late[1]:.1f} ms)", "-")
    inside = [t for t in sent_at if window[0] <= t <= window[1]]
    if len(inside) > 2:
        import numpy as np

        dev = np.abs(np.diff(np.array(inside)) * 1e6 - 1e6 * period)
        row["sender"] = f"{np.percentile(dev, 99):.0f} / {np.percentile(dev, 99.9):.0f} / {dev.max():.0f}"
    return row


def late_steps(trace: list[float], window: tuple[float, float], period: float, worst: int = 4) -> str:
    """The motion process's cycle steps in ``window`` (:data:`fieldbus.canopen.clock.TRACE_ENV`: deadline,
    start, end, CPU seconds each): the longest step with its CPU time, and the ``worst`` latest starts,
    each with the step before it (its duration and CPU time: a step that ran long delays the next by
    its own work; one far longer than its CPU time waited for the interpreter lock or a CPU) and the
    gap from that step's end to this start (a gap is a wake-up held off)."""
    rows = [tuple(trace[i:i + 4]) for i in range(0, len(trace) - 3, 4)]
    idx = [i for i, r in enumerate(rows) if window[0] <= r[1] <= window[1]]
    if not idx:
        return "  the cycle's steps: none in the window"
    longest = max(idx, key=lambda i: rows[i][2] - rows[i][1])
    d, s, e, c = rows[longest]
    parts = [f"  the cycle's steps ({len(idx)}): longest {1e3 * (e - s):.2f} ms (CPU {1e3 * c:.2f} ms); "
             "latest starts:"]
    for i in sorted(idx, key=lambda i: rows[i][1] - rows[i][0], reverse=True)[:worst]:
        d, s, _e, _c = rows[i]
        text = f"{1e3 * (s - d):.2f} ms late"
        if i > 0:
            _pd, ps, pe, pc = rows[i - 1]
            text += (f" after a step of {1e3 * (pe - ps):.2f} ms (CPU {1e3 * pc:.2f} ms) and a gap of "
                     f"{1e3 * (s - pe):.2f} ms")
        parts.append(text)
    return " ".join(parts[:1]) + " " + "; ".join(parts[1:])


def read_trace(path: Path) -> list[float]:
    """The doubles a trace file holds (:data:`fieldbus.canopen.sync_process.TRACE_ENV`: the SYNC
    process's send times; :data:`fieldbus.canopen.clock.TRACE_ENV`: the cycle's steps)."""
    from array import array

    times = array("d")
    times.frombytes(path.read_bytes())
    return list(times)


POLICIES = {0: "OTHER", 1: "FIFO", 2: "RR", 3: "BATCH", 5: "IDLE"}


def thread_sched(pid: int) -> list[dict]:
    """Each thread of ``pid`` (Linux /proc): scheduling policy and priority, CPU time, and the time it
    spent runnable but waiting for a CPU (schedstat's run delay), in ms; involuntary switches."""
    rows = []
    for task in sorted(Path(f"/proc/{pid}/task").iterdir(), key=lambda t: int(t.name)):
        try:
            stat = (task / "stat").read_text()
            run_ns, wait_ns, _ = (int(x) for x in (task / "schedstat").read_text().split())
            switches = {k.strip(): v.strip() for k, v in (ln.split(":", 1) for ln in
                        (task / "status").read_text().splitlines() if "ctxt_switches" in ln)}
        except (OSError, ValueError):
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        policy, prio = int(fields[38]), int(fields[37])
        rows.append({"tid": int(task.name), "policy": f"{POLICIES.get(policy, policy)} {prio}",
                     "cpu_ms": run_ns / 1e6, "wait_ms": wait_ns / 1e6,
                     "invol": int(switches.get("nonvoluntary_ctxt_switches", 0))})
    return rows


def per_second_p999(times_s, values) -> list[float]:
    """The p99.9 of ``values`` in each whole second of ``times_s`` (seconds, same length), in order;
    seconds with fewer than 100 values are left out."""
    import numpy as np

    times_s, values = np.asarray(times_s), np.asarray(values)
    if len(times_s) == 0:
        return []
    sec = np.floor(times_s - times_s[0]).astype(int)
    return [float(np.percentile(values[sec == k], 99.9)) for k in range(sec.max() + 1)
            if np.count_nonzero(sec == k) >= 100]


def spread(per_s: list[float]) -> dict:
    """Median, max and the seconds over 1 ms of per-second p99.9 figures (us)."""
    import numpy as np

    if not per_s:
        return {"med": math.nan, "max": math.nan, "over": 0, "n": 0}
    return {"med": float(np.median(per_s)), "max": max(per_s), "over": sum(v > 1000 for v in per_s),
            "n": len(per_s)}


def reference(period: float, seconds: float, exe: Path | None, rt: int, latency: int | None,
              when: str) -> dict | None:
    """``bench/rt_floor.c`` under the hogs for ``seconds``: its wake-up lateness (us) p50/p99/p99.9/max
    and the spread of its per-second p99.9 (the host taking the CPUs away shows there: a few seconds
    far above the others)."""
    import numpy as np

    if exe is None:
        return None
    with tempfile.TemporaryDirectory() as tmp:
        out_path = Path(tmp) / "late.txt"
        out = subprocess.run([str(exe), str(round(period * 1e6)), str(round(seconds / period)), str(rt),
                              str(-1 if latency is None else latency), str(out_path)], capture_output=True,
                             text=True, timeout=seconds * 3 + 10)
        if out.returncode != 0 or not out_path.exists():
            print(f"rt_floor failed: {out.stderr.strip()}", file=sys.stderr)
            return None
        late = np.loadtxt(out_path, dtype=np.int64) / 1e3  # us
    # the k-th wake-up is due k + 1 periods after the start
    return {"when": when, **lateness((np.arange(len(late)) + 1) * period, late),
            "missed": int(np.count_nonzero(late > 1e6 * period / 2)), "load": f"{os.getloadavg()[0]:.1f}"}


def lateness(due, late) -> dict:
    """Wake-up lateness ``late`` (us, each due at ``due`` s): p50/p99/p99.9/max and the spread of the
    per-second p99.9."""
    import numpy as np

    return {"n": len(late), "p50": float(np.percentile(late, 50)), "p99": float(np.percentile(late, 99)),
            "p999": float(np.percentile(late, 99.9)), "max": float(late.max()),
            "per_s": spread(per_second_p999(due, late))}


class Beside:
    """``bench/rt_floor.c`` running beside a case, at the SYNC process's priority (the master's plus one;
    its own wake-ups at its own phase): the C reference under the same hogs and, above all, at the same
    moments. A VM's host that takes the vCPUs away stops it and the SYNC alike, where a reference run
    before or after the case measures other seconds. It costs the case one wake-up a period."""

    def __init__(self, exe: Path | None, period: float, rt: int, tmp: Path) -> None:
        self.period = period
        self.path = tmp / "beside.txt"
        self.proc = None
        if exe is not None:
            self.proc = subprocess.Popen([str(exe), str(round(period * 1e6)), str(round(3600 / period)),
                                          str(min(99, rt + 1) if rt else 0), "-1", str(self.path)],
                                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    def close(self, window: tuple[float, float]) -> dict | None:
        """Ended (SIGTERM: it writes what it has); its wake-ups due within ``window`` (time.monotonic):
        lateness p50/p99/p99.9/max (us) and the spread of the per-second p99.9."""
        import numpy as np

        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.terminate()
        _out, err = self.proc.communicate(timeout=30)
        if self.proc.returncode != 0 or not self.path.exists():
            print(f"rt_floor beside the case failed: {err.strip()}", file=sys.stderr)
            return None
        with self.path.open() as f:
            start = int(f.readline().split()[-1]) / 1e9
        late = np.loadtxt(self.path, dtype=np.int64, ndmin=1) / 1e3  # us
        due = start + (np.arange(len(late)) + 1) * self.period
        inside = (due >= window[0]) & (due <= window[1])
        late, due = late[inside], due[inside]
        if len(late) < 100:
            return None
        return lateness(due, late)


def finish_row(row: dict, window: tuple[float, float], period: float, result: dict, fault, cycles: str,
               gc_text: str) -> dict:
    """The SYNC figures of the drives' records within ``window`` (time.monotonic) and their counts into
    ``row``. The SYNC period is taken from the kernel's receive time stamps of the SYNC datagrams at the
    drives' socket (what a drive's hardware would see); the same from the time the drives' Python reader
    thread got them is the column "at the drives' reader" (that adds the simulator's own scheduling)."""
    import numpy as np

    arrivals = np.array(result.get("arrivals", []))
    stamps = np.array(result.get("stamps", []))
    inside = (arrivals >= window[0]) & (arrivals <= window[1]) if len(arrivals) else np.zeros(0, bool)
    arrivals, stamps = arrivals[inside], stamps[inside] if len(stamps) == len(inside) else stamps[:0]
    row["syncs"] = str(len(stamps))
    if len(stamps) > 2:
        intervals = np.diff(stamps) * 1000  # ms
        dev = np.abs(intervals - 1000 * period) * 1000  # us
        row.update({"p50": f"{np.percentile(intervals, 50):.3f}",
                    "p99": f"{np.percentile(intervals, 99):.3f}",
                    "p999": f"{np.percentile(intervals, 99.9):.3f}", "max": f"{intervals.max():.3f}",
                    "dev50": float(np.percentile(dev, 50)), "dev99": float(np.percentile(dev, 99)),
                    "dev999": float(np.percentile(dev, 99.9)), "devmax": float(dev.max())})
        reader = np.abs(np.diff(arrivals) * 1e6 - 1e6 * period)
        row["reader"] = f"{np.percentile(reader, 99.9):.0f}"
        sp = spread(per_second_p999(stamps[1:], dev))
        row["per_s"] = f"{sp['med']:.0f} / {sp['max']:.0f} ({sp['over']} of {sp['n']} s > 1 ms)"
    missed = sum(result.get("missed_setpoints", {}).values()) if result else -1
    row["setpoints"] = str(missed) + (" (fault)" if fault else "")
    row["missed_n"] = missed
    row["fault"] = bool(fault)
    row["cycles"] = cycles
    row["gc"] = gc_text
    row["load"] = f"{os.getloadavg()[0]:.1f}"
    if fault:
        print(f"{row['case']}: fault: {fault}", file=sys.stderr)
    return row


def run(args, layout_for, build_rt_floor) -> int:
    """The stressed bench (``bench/fieldbus.py --stress``); in a private network namespace."""
    from rich.console import Console
    from rich.table import Table

    if os.environ.get("CANON_NETNS") != "1":
        if os.geteuid() != 0:
            print("--stress joins a multicast group: run it as root (it then makes a loopback-only network "
                  "namespace) or inside tests/netns-run", file=sys.stderr)
            return 2
        script = Path(sys.argv[0]).resolve()
        os.execv(str(ROOT / "tests" / "netns-run"),
                 [str(ROOT / "tests" / "netns-run"), sys.executable, str(script), *sys.argv[1:]])
    rt = args.rt_priority
    latency = None if args.cpu_latency_us < 0 else args.cpu_latency_us
    modes = {"on": [True], "off": [False], "both": [True, False]}[args.steer_gc]
    period = args.stress_period_ms / 1000.0
    tmp = tempfile.TemporaryDirectory()
    exe = build_rt_floor(Path(tmp.name))
    hogs = Hogs()
    global DRIVES_PRIORITY
    DRIVES_PRIORITY = args.drives_priority
    task_priority = args.task_priority if args.task_priority >= 0 else (50 if rt > 50 else 0)
    arrangements = {"own": ["own"], "in-process": ["in-process"], "both": ["own", "in-process"]}[
        args.arrangement]
    syncs = {"master": ["master"], "process": ["process"], "both": ["master", "process"]}[args.stress_sync]
    print(f"hogs: {hogs.what}; status load: 100 Hz canon.status on LCM (ttl=0), a client process "
          f"subscribed; own: the Machine's canon-status thread in the task process, the master in the "
          f"motion process; in-process: a status thread beside the master in this process", flush=True)
    rows = []
    try:
        refs = [reference(period, args.seconds, exe, rt, latency, "before the cases")]
        for n in (int(x) for x in args.drives.split(",")):
            for arrangement in arrangements:
                for steer in modes:
                    if arrangement != "own":
                        print(f"running {arrangement}: {n} drives, gc {'steered' if steer else 'automatic'} "
                              "...", flush=True)
                        rows.append(case(n, period, args.seconds, rt, latency, steer, layout_for, exe))
                        continue
                    for sync in syncs:
                        print(f"running own: {n} drives, gc {'steered' if steer else 'automatic'}, SYNC by "
                              f"{sync} ...", flush=True)
                        rows.append(case_own(n, period, args.seconds, rt, latency, steer, layout_for,
                                             task_priority, sync, args.setpoint_lead, exe))
        refs.append(reference(period, args.seconds, exe, rt, latency, "after the cases"))
    finally:
        hogs.stop()
        tmp.cleanup()
    table = Table(title=f"CANopen master under stress ({hogs.what}), udp_multicast, drives in another "
                        f"process, {args.seconds:g} s per case, {os.cpu_count()} CPUs, SCHED_FIFO "
                        f"{rt or 'off'}, CPU latency request {'off' if latency is None else f'{latency} us'}"
                        f", own: task process {f'SCHED_FIFO {task_priority}' if task_priority else 'normal'}")
    cols = [("case", "case"), ("syncs", "SYNCs at drives"), ("p50", "SYNC period p50 ms"), ("p99", "p99 ms"),
            ("p999", "p99.9 ms"), ("max", "max ms"), ("d50", "|dev| p50 us"), ("d99", "|dev| p99 us"),
            ("d999", "|dev| p99.9 us"), ("dmax", "|dev| max us"),
            ("reader", "|dev| p99.9 us at the drives' reader"),
            ("per_s", "per-second p99.9 us: median / max"),
            ("sender", "|dev| p99 / p99.9 / max us at the SYNC process (its send times)"),
            ("beside", "C reference beside the case: wake-up p99.9 us (per-second median / max)"),
            ("setpoints", "missed setpoints"),
            ("cycles", "master late cycles"), ("gc", "gc in slack"), ("status", "status sent/received"),
            ("load", "load avg (1 min)")]
    for _, title in cols:
        table.add_column(title, justify="right")
    refs_ok = [c for c in refs if c is not None]
    for c in refs_ok:
        sp = c["per_s"]
        table.add_row(f"reference: C wake-up lateness, {args.stress_period_ms:g} ms, {c['when']}", "-", "-",
                      "-", "-", "-", *(f"{c[k]:.0f}" for k in ("p50", "p99", "p999", "max")), "-",
                      f"{sp['med']:.0f} / {sp['max']:.0f} ({sp['over']} of {sp['n']} s > 1 ms)", "-",
                      str(c["missed"]), "-", "-", c["load"])
    # judged against the quieter reference: a host that took the CPUs away in one of them must not
    # make the target easier
    c_p999 = min((c["p999"] for c in refs_ok), default=math.nan)
    for r in rows:
        for k in ("50", "99", "999", "max"):
            r[f"d{k}"] = f"{r[f'dev{k}']:.0f}" if f"dev{k}" in r else "-"
        ref = r.get("ref")
        if ref is not None:
            r["beside"] = f"{ref['p999']:.0f} ({ref['per_s']['med']:.0f} / {ref['per_s']['max']:.0f})"
        table.add_row(*(r.get(k, "-") for k, _ in cols))
    Console(width=240).print(table)
    print("target: no setpoint missed at any drive, and SYNC period |deviation| p99.9 <= 1.5 x the C "
          "reference's wake-up p99.9, the C reference running beside the case (same hogs, same seconds); "
          "without it, the lower of its runs before and after the cases "
          f"({c_p999:.0f} us x 1.5 = {1.5 * c_p999:.0f} us)")
    for c in refs_ok:
        sp = c["per_s"]
        if sp["over"]:
            print(f"  the C reference {c['when']} was disturbed: its per-second p99.9 is {sp['med']:.0f} us "
                  f"(median) but {sp['max']:.0f} us at worst, {sp['over']} of {sp['n']} seconds over 1 ms: "
                  "something (in a VM most likely the host taking the vCPU away) stopped a SCHED_FIFO "
                  "thread that only sleeps; its p99.9 then says more about that than about this PC's floor")
    worst_ref = max((c["p999"] for c in refs_ok), default=math.nan)
    if len(refs_ok) == 2 and worst_ref > 3 * c_p999:
        print(f"  the C reference's p99.9 differs {worst_ref / c_p999:.1f}x between its runs before and "
              "after the cases: a reference in other seconds than the case's is a loose figure")
    ok_all = True
    for r in rows:
        missed_ok = r["missed_n"] == 0 and not r["fault"]  # a fault ended the stream early: not met
        ref = r.get("ref")
        floor = ref["p999"] if ref is not None else c_p999
        sync_ok = "dev999" in r and r["dev999"] <= 1.5 * floor
        ok_all &= missed_ok and sync_ok
        ratio = r["dev999"] / floor if "dev999" in r and floor > 0 else math.nan
        ratios = ", ".join(f"{r['dev999'] / c['p999']:.1f} x the run {c['when'].split()[0]} the cases"
                           for c in refs_ok if "dev999" in r and c["p999"] > 0)
        against = "the C reference beside it" if ref is not None else "the quieter C reference"
        print(f"  {r['case']}: setpoints {'met' if missed_ok else 'NOT met'}"
              f"{' (a fault ended the stream)' if r['fault'] else ''}, SYNC "
              f"{'met' if sync_ok else 'NOT met'} ({r.get('d999', '-')} us = {ratio:.1f} x {against}, "
              f"{floor:.0f} us; {ratios})")
    print(f"target {'met' if ok_all else 'NOT met'}")
    if not rt:
        print("note: without --rt-priority the C reference is an ordinary thread under the hogs too: its "
              "p99.9 (and so the SYNC target) says little; --rt-priority 80 is what a machine would run")
    return 0


if __name__ == "__main__":
    if len(sys.argv) == 5 and sys.argv[1] == "--drives-child":
        sys.exit(drives_child(sys.argv[2], sys.argv[3], int(sys.argv[4])))
    if len(sys.argv) == 4 and sys.argv[1] == "--status-client":
        sys.exit(status_client(float(sys.argv[2]), sys.argv[3]))
    sys.exit("run bench/fieldbus.py --stress")
