"""The master on a real SocketCAN interface (vcan0): the SYNC period as an independent listener sees it,
with the SYNC timed by the kernel (python-can's periodic send: the broadcast manager) and by the master.

``python bench/fieldbus.py --bus socketcan [--sync both|kernel|master] [--seconds 5]`` (where vcan0
exists; on a machine whose kernel has no CAN: ``tests/vcan/run-vm --bench --seconds 3 --drives 2
--periods-ms 10``, in the emulated VM, where the figures show that the kernel's SYNC works, not how
well a PC keeps time).

Per case (drives x period x SYNC mode): the drives simulated in another process on vcan0 (``canon sim
drives``, as the stressed bench has them: in the master's process they slowed its cycle further in
the emulated VM), a sine move
streamed for ``--seconds`` with the cycle paced as the daemon paces it (by the SYNCs it sees, with the
kernel's SYNC; on absolute deadlines with the master's), and a listener on its own socket (filtered to
the SYNC, the kernel's receive time stamps) measuring every SYNC period: p50/p99/p99.9/max, the
periods longer than 1.5 x the cycle, the cycles the runner saw late or skipped, the SYNCs that found
no new setpoint (the master's count; kernel SYNC only) and the setpoints the drives missed; the first
cycle's delay after enable(), the longest gap between cycles and the longest gc pass (a stalled cycle
told from a stalled SYNC). Reported, not judged (docs/canopen.md, "Benchmark").
"""

from __future__ import annotations

import argparse
import gc
import math
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Protocol

import can
import numpy as np

from fieldbus.canopen.clock import PeriodicRunner
from fieldbus.canopen.config import CanBusConfig, CanopenConfig, DriveConfig
from fieldbus.canopen.master import CanopenMaster
from fieldbus.canopen.sync import SYNC_COB_ID


class DriveProcessLike(Protocol):
    """``bench/fieldbus.py``'s ``DriveProcess``: ``canon sim drives`` in a child process."""

    def close(self) -> int: ...  # the setpoints the drives missed


class SyncListener:
    """The SYNC frames on ``channel`` with the kernel's receive time, read on a thread of their own."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="socketcan", channel=channel,
                           can_filters=[{"can_id": SYNC_COB_ID, "can_mask": 0x7FF, "extended": False}])
        self.times: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, name="sync-listener", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(0.05)
            if msg is not None:
                self.times.append(msg.timestamp)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self.bus.shutdown()


def case(n: int, period: float, seconds: float, sync: str, channel: str, rt: int, latency: int | None,
         layout: tuple[str, int], sine_step: Callable[..., Callable[[int, float], None]],
         drive_process: Callable[..., DriveProcessLike]) -> dict[str, str]:
    drives = tuple(DriveConfig("xyzabc"[i], i + 1) for i in range(n))
    config = CanopenConfig(CanBusConfig("socketcan", channel), drives, cycle_s=period, feedback_timeout_s=1.0,
                           heartbeat_consumer_ms=2000, pdo_layout=layout[0], following_error_every=layout[1],
                           sync=sync)
    tmp = tempfile.TemporaryDirectory()
    sims = drive_process(n, channel, Path(tmp.name), interface="socketcan")
    master = CanopenMaster(config, check_budget=False)
    listener = SyncListener(channel)
    # the set-up's objects frozen now: the runner's first full collection (before its first cycle, the
    # kernel's SYNC already running since enable()) then walks only what enable() left
    gc.collect()
    gc.freeze()
    starts: list[float] = []  # time.monotonic() of every cycle, the last of enable() first
    runner: PeriodicRunner | None = None
    drives_missed = 0
    try:
        master.boot()
        master.enable()
        sine = sine_step(master, period, master.positions())

        def step(k: int, t: float) -> None:
            starts.append(time.monotonic())
            sine(k, t)

        t_start, m_start = time.time(), time.monotonic()
        starts.append(m_start)
        runner = PeriodicRunner(period, step, cycles=round(seconds / period), realtime_priority=rt,
                                cpu_latency_us=latency, tick=master.sync_tick).start()
        ended = runner.join(seconds * 3 + 30)
        t_end = time.time()
        fault = master.fault
        if fault is not None:
            print(f"{n} drives, {1000 * period:g} ms, SYNC by {master.sync_mode}: fault "
                  f"{fault.time - m_start:.1f} s into the run: {fault}", file=sys.stderr)
        if not ended:
            print(f"{n} drives, {1000 * period:g} ms, SYNC by {master.sync_mode}: the cycle thread had not "
                  f"done its {runner.cycles} cycles after {t_end - t_start:.0f} s (stopped)", file=sys.stderr)
    finally:
        if runner is not None:  # the master is not shut down under a running cycle
            runner.stop()
            runner.join(30.0)
        master.shutdown()
        drives_missed = sims.close()
        listener.close()
        tmp.cleanup()
        gc.unfreeze()
    times = [t for t in listener.times if t_start <= t <= t_end]
    gaps = np.diff(np.array(times)) * 1e3 if len(times) > 1 else np.array([math.nan])
    st = runner.stats
    return {
        "case": f"{n} drives, {1000 * period:g} ms", "sync": master.sync_mode,
        "syncs": f"{len(times)} in {t_end - t_start:.1f} s",
        "p50": f"{np.percentile(gaps, 50):.3f}", "p99": f"{np.percentile(gaps, 99):.3f}",
        "p999": f"{np.percentile(gaps, 99.9):.3f}", "max": f"{gaps.max():.3f}",
        "long": str(int(np.sum(gaps > 1.5e3 * period))),
        "late": f"{st.late} / {st.skipped}",
        "first": f"{1e3 * (starts[1] - starts[0]):.0f}" if len(starts) > 1 else "-",
        "gap": f"{1e3 * float(np.diff(starts[1:]).max()):.0f}" if len(starts) > 2 else "-",
        "gc": f"{1e3 * st.gc_max_s:.0f}",
        "master": str(master.missed_setpoints) if master.sync_mode == "kernel" else "-",
        "drives": str(drives_missed) + (" (fault)" if fault else ""),
    }


def run(args: argparse.Namespace, layout_for: Callable[[int, float], tuple[str, int]],
        sine_step: Callable[..., Callable[[int, float], None]], print_table: Callable[..., None], rt: int,
        latency: int | None, drive_process: Callable[..., DriveProcessLike]) -> int:
    """``bench/fieldbus.py --bus socketcan``: its move (``sine_step``), its table (``print_table``) and
    its drives' process (``drive_process``: ``DriveProcess``)."""
    import os

    if not os.path.exists(f"/sys/class/net/{args.channel}"):
        print(f"no {args.channel} here: `ip link add dev {args.channel} type vcan && ip link set up "
              f"{args.channel}` (a kernel with CAN), or tests/vcan/run-vm --bench")
        return 2
    modes = ("kernel", "master") if args.sync == "both" else (args.sync,)
    rows = []
    for period_ms in (float(p) for p in args.periods_ms.split(",")):
        for n in (int(x) for x in args.drives.split(",")):
            for mode in modes:
                rows.append(case(n, period_ms / 1000.0, args.seconds, mode, args.channel, rt, latency,
                                 layout_for(n, period_ms / 1000.0), sine_step, drive_process))
    title = (f"CANopen master on socketcan {args.channel}: the SYNC period a listener sees, "
             f"{args.seconds:g} s per case, {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}, "
             f"SCHED_FIFO {rt or 'off'} (reported, not judged)")
    cols = [("case", "case"), ("sync", "SYNC by"), ("syncs", "SYNCs"), ("p50", "period p50 ms"),
            ("p99", "p99 ms"), ("p999", "p99.9 ms"), ("max", "max ms"), ("long", "> 1.5 periods"),
            ("late", "late / skipped cycles"), ("first", "1st cycle ms after enable"),
            ("gap", "longest cycle gap ms"), ("gc", "longest gc ms"),
            ("master", "SYNCs without new setpoint"), ("drives", "drive missed setpoints")]
    print_table(title, cols, rows)
    return 0
