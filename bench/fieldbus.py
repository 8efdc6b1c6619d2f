"""Cycle timing of the CANopen master with simulated drives on python-can's virtual bus.

For 3 and 6 drives at 4, 2 and 1 ms: the achieved period, the cycle start's lateness after its
absolute deadline (p50, p99, p99.9, max: the jitter the drives see on SYNC), missed cycles (late by
more than half a period, or skipped), the drives' missed setpoints, and the master's CPU use (its
cycle thread, spinning included, and its bus reader thread). The reference row of each period is the
same periodic thread with an empty step, and the same in C (``bench/rt_floor.c``, compiled here when a
C compiler exists: cyclictest's method): the floor this machine's kernel and scheduler set, with
Python and without.

The cycle thread runs as the daemon's does: SCHED_FIFO at ``--rt-priority`` and a CPU latency request
(/dev/cpu_dma_latency, ``--cpu-latency-us``; both need root). The virtual bus has no bitrate: the bus
load column is what the configuration would put on a 1 Mbit/s bus in the chosen PDO layout (the master
refuses over 70 % there; here a case over it is marked, and runs anyway).

    python bench/fieldbus.py              # 30 s per case; per case the PDO layout that fits 1 Mbit/s
    python bench/fieldbus.py --seconds 10 --rt-priority 80 --layout compact --fe-every 4
    python bench/fieldbus.py --stress --seconds 60 --rt-priority 80 --steer-gc on  # root; fieldbus_stress.py
    python bench/fieldbus.py --bus socketcan --seconds 5   # vcan0, kernel SYNC: bench/fieldbus_vcan.py
"""

from __future__ import annotations

import argparse
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from fieldbus.canopen.busload import fitting_layouts  # noqa: E402
from fieldbus.canopen.clock import PeriodicRunner  # noqa: E402
from fieldbus.canopen.config import CanBusConfig, CanopenConfig, DriveConfig  # noqa: E402
from fieldbus.canopen.drive_sim import SimDrive  # noqa: E402
from fieldbus.canopen.master import CanopenMaster  # noqa: E402
from fieldbus.canopen.pdo import make_layout  # noqa: E402
from fieldbus.canopen.sim_process import SimBus  # noqa: E402


def sine_step(master: CanopenMaster, period: float, start: tuple[float, ...]) -> Callable[[int, float], None]:
    """The benches' move: every axis 10 mm either side of ``start`` at 0.5 Hz, one setpoint per step
    (after a stall the trajectory continues, it does not jump)."""
    done = [0]

    def step(k: int, t: float) -> None:
        s = 10.0 * math.sin(2 * math.pi * 0.5 * done[0] * period)
        done[0] += 1
        master.cycle([p + s for p in start])

    return step


def print_table(title: str, cols: list[tuple[str, str]], rows: list[dict]) -> None:
    """Rows (dicts) as a table: ``cols`` are (key, column title)."""
    table = Table(title=title)
    for _, heading in cols:
        table.add_column(heading, justify="right")
    for r in rows:
        table.add_row(*(r[k] for k, _ in cols))
    Console(width=190).print(table)


def thread_cpu(thread) -> float:
    try:
        return time.clock_gettime(time.pthread_getcpuclockid(thread.ident))
    except (OSError, AttributeError, TypeError):
        return math.nan


def row(label: str, runner: PeriodicRunner, seconds: float, extra: dict) -> dict:
    st = runner.stats
    late = np.array(st.lateness) * 1e6
    return {
        "case": label,
        "period": f"{1000 * st.achieved_period_s:.4f}",
        "p50": f"{np.percentile(late, 50):.0f}",
        "p99": f"{np.percentile(late, 99):.0f}",
        "p999": f"{np.percentile(late, 99.9):.0f}",
        "max": f"{late.max():.0f}",
        "missed": str(st.late + st.skipped),
        **extra,
    }


RT = 0
LATENCY: int | None = 0
LAYOUT = "auto"
FE_EVERY = 1


def layout_for(n: int, period: float) -> tuple[str, int]:
    """``--layout auto``: the layout the master would accept on 1 Mbit/s (the standard one with
    following error every SYNC where it fits, else the first that fits); none fits: standard."""
    if LAYOUT != "auto":
        return LAYOUT, FE_EVERY
    fits = fitting_layouts(n, period, 1_000_000, 0.70, 100, 100)
    return (fits[0][0].name, fits[0][0].following_error_every) if fits else ("standard", 1)


def reference(period: float, seconds: float) -> dict:
    runner = PeriodicRunner(period, lambda k, t: None, cycles=round(seconds / period),
                            realtime_priority=RT, cpu_latency_us=LATENCY).start()
    runner.join(seconds * 3 + 10)
    return row(f"reference: Python, empty step, {1000 * period:g} ms", runner, seconds,
               {"setpoints": "-", "cpu": f"{100 * runner.stats.cpu_s / seconds:.0f}", "work": "-",
                "load": "-", "layout": "-"})


def c_reference(period: float, seconds: float, exe: Path | None) -> dict | None:
    """``rt_floor`` (C, clock_nanosleep to absolute deadlines) with the same priority and latency."""
    if exe is None:
        return None
    out = subprocess.run([str(exe), str(round(period * 1e6)), str(round(seconds / period)), str(RT),
                          str(-1 if LATENCY is None else LATENCY)], capture_output=True, text=True,
                         timeout=seconds * 3 + 10)
    try:
        p50, p99, p999, worst, missed = out.stdout.split()
    except ValueError:
        print(f"rt_floor failed: {out.stderr.strip()}", file=sys.stderr)
        return None
    return {"case": f"reference: C, kernel floor, {1000 * period:g} ms", "period": "-", "p50": p50,
            "p99": p99, "p999": p999, "max": worst, "missed": missed, "setpoints": "-", "cpu": "-",
            "work": "-", "load": "-", "layout": "-"}


def build_rt_floor(tmp: Path) -> Path | None:
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        print("no C compiler: the C reference rows are left out", file=sys.stderr)
        return None
    exe = tmp / "rt_floor"
    res = subprocess.run([cc, "-O2", "-o", str(exe), str(ROOT / "bench" / "rt_floor.c")],
                         capture_output=True, text=True)
    if res.returncode != 0:
        print(f"rt_floor did not compile: {res.stderr.strip()}", file=sys.stderr)
        return None
    return exe


class DriveProcess:
    """``canon sim drives`` on udp_multicast (or ``interface``: socketcan) in a child process (the
    master's process then holds only the master); its report of missed setpoints is read when it ends."""

    def __init__(self, n: int, group: str, tmp: Path, interface: str = "udp_multicast") -> None:
        text = "".join(f"[axes.{'xyzabc'[i]}]\n" for i in range(n))
        text += f'[canopen]\ninterface = "{interface}"\nchannel = "{group}"\n'
        text += "".join(f"[canopen.axes.{'xyzabc'[i]}]\nnode_id = {i + 1}\n" for i in range(n))
        (tmp / "bench.toml").write_text(text)
        self.proc = subprocess.Popen([sys.executable, "-m", "motiond.cli", "sim", "drives", "--config",
                                      str(tmp / "bench.toml")], cwd=ROOT, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if not line.startswith("simulating"):
            raise SystemExit(f"canon sim drives did not start: {line}{self.proc.stderr.read()}")

    def close(self) -> int:
        self.proc.terminate()
        try:
            _, err = self.proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            _, err = self.proc.communicate(timeout=10)
        return sum(int(m) for m in re.findall(r"missed setpoints (\d+)", err))


def case(n: int, period: float, seconds: float, interface: str = "virtual") -> dict:
    drives = tuple(DriveConfig("xyzabc"[i], i + 1) for i in range(n))
    if interface == "virtual":
        bus = CanBusConfig("virtual", f"bench-{os.getpid()}-{n}-{period}")
    else:
        bus = CanBusConfig("udp_multicast", f"239.74.165.{1 + os.getpid() % 250}")
    layout, every = layout_for(n, period)
    config = CanopenConfig(bus, drives, cycle_s=period, feedback_timeout_s=1.0, heartbeat_consumer_ms=2000,
                           pdo_layout=layout, following_error_every=every)
    tmp = tempfile.TemporaryDirectory()
    sims: SimBus | DriveProcess
    if interface == "virtual":
        sims = SimBus([SimDrive(i + 1) for i in range(n)], config.bus)
    else:
        sims = DriveProcess(n, bus.channel, Path(tmp.name))
    master = CanopenMaster(config, check_budget=False)
    missed_setpoints = 0
    try:
        master.boot()
        master.enable()
        start = master.positions()

        step = sine_step(master, period, start)
        reader = master.network.notifier._readers[0]
        cpu0 = thread_cpu(reader)
        runner = PeriodicRunner(period, step, cycles=round(seconds / period), realtime_priority=RT,
                                cpu_latency_us=LATENCY).start()
        runner.join(seconds * 3 + 10)
        reader_cpu = thread_cpu(reader) - cpu0
        if isinstance(sims, SimBus):
            missed_setpoints = sum(d.missed_setpoints for d in sims.drives.values())
        fault = master.fault
        if fault is not None:
            print(f"{n} drives, {1000 * period:g} ms: master fault: {fault}", file=sys.stderr)
    finally:
        master.shutdown()
        if isinstance(sims, SimBus):
            sims.close()
        else:
            missed_setpoints = sims.close()
        tmp.cleanup()
    st = runner.stats
    return row(f"{n} drives, {1000 * period:g} ms", runner, seconds, {
        "setpoints": str(missed_setpoints) + (" (fault)" if fault else ""),
        "cpu": f"{100 * (st.cpu_s + reader_cpu) / seconds:.0f}",
        "work": f"{1e6 * st.work_s / max(st.cycles, 1):.0f}",
        "load": f"{100 * master.load.fraction:.0f}" + (" over" if master.load.fraction > 0.70 else ""),
        "layout": f"{layout}, FE/{every}",
    })


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=None,
                    help="length of each case (default 30; with --stress 60)")
    ap.add_argument("--drives", default="3,6", help="drive counts (default 3,6)")
    ap.add_argument("--periods-ms", default="4,2,1", help="cycle periods (default 4,2,1)")
    ap.add_argument("--rt-priority", type=int, default=0,
                    help="SCHED_FIFO priority of the cycle thread (needs root; default 0: normal)")
    ap.add_argument("--cpu-latency-us", type=int, default=0,
                    help="CPU wake-up latency requested on /dev/cpu_dma_latency while cycling (needs root; "
                         "default 0, as the daemon; -1: no request)")
    ap.add_argument("--layout", choices=("auto", "standard", "compact"), default="auto",
                    help="PDO layout (default auto: per case, the one the master accepts on 1 Mbit/s)")
    ap.add_argument("--fe-every", type=int, default=1, help="following error TPDO every n SYNCs (default 1)")
    ap.add_argument("--switch-interval-ms", type=float, default=0.5,
                    help="the interpreter's thread switch interval (default 0.5; Python's own is 5)")
    ap.add_argument("--bus", choices=("virtual", "udp_multicast", "socketcan"), default="virtual",
                    help="udp_multicast: the drives in another process (`canon sim drives`); run it inside "
                         "tests/netns-run. socketcan: on --channel (vcan0), the SYNC period a listener sees "
                         "with the kernel's SYNC and the master's (bench/fieldbus_vcan.py; --seconds default "
                         "5)")
    ap.add_argument("--channel", default="vcan0", help="--bus socketcan: the interface (default vcan0)")
    ap.add_argument("--sync", choices=("both", "kernel", "master"), default="both",
                    help="--bus socketcan: who times the SYNC (default both: each case twice)")
    ap.add_argument("--stress", action="store_true",
                    help="the stressed case (bench/fieldbus_stress.py): two CPU hogs, a 100 Hz status load, "
                         "drives in another process on udp_multicast, the C reference in the same run "
                         "(--seconds default 60)")
    ap.add_argument("--steer-gc", choices=("on", "off", "both"), default="both",
                    help="--stress: the cycle runner's garbage collection steering (default both: each case "
                         "twice)")
    ap.add_argument("--arrangement", choices=("own", "in-process", "both"), default="both",
                    help="--stress: own: the daemon's [motion] process = \"own\" (a Machine here, the "
                         "master in its motion process); in-process: the master in the bench's process "
                         "beside a status thread (the earlier measurement); default both")
    ap.add_argument("--task-priority", type=int, default=-1,
                    help="--stress, own: SCHED_FIFO priority of the task process (default: 50, as "
                         "examples/canon.service runs the daemon, when --rt-priority is above it; 0: normal)")
    ap.add_argument("--drives-priority", type=int, default=-1,
                    help="--stress: SCHED_FIFO priority of the simulated drives' process (default: "
                         "--rt-priority minus one; 0: normal)")
    ap.add_argument("--stress-period-ms", type=float, default=2.0, help="--stress: cycle period (default 2)")
    ap.add_argument("--setpoint-lead", type=int, default=1,
                    help="--stress, SYNC by a process: [canopen] setpoint_lead, the SYNCs ahead the SYNC "
                         "process holds setpoints for (default 1)")
    ap.add_argument("--stress-sync", choices=("master", "process", "both"), default="both",
                    help="--stress, own: who sends the SYNC on udp_multicast, the master's cycle or a SYNC "
                         "process of its own ([canopen] sync = \"process\"); default both")
    args = ap.parse_args()
    if args.stress:
        import fieldbus_stress

        global RT, LATENCY, LAYOUT, FE_EVERY
        args.seconds = 60.0 if args.seconds is None else args.seconds
        RT = args.rt_priority
        LATENCY = None if args.cpu_latency_us < 0 else args.cpu_latency_us
        LAYOUT, FE_EVERY = args.layout, args.fe_every
        sys.setswitchinterval(args.switch_interval_ms / 1000.0)
        return fieldbus_stress.run(args, layout_for, build_rt_floor)
    if args.bus == "socketcan":
        import fieldbus_vcan

        args.seconds = 5.0 if args.seconds is None else args.seconds
        LAYOUT, FE_EVERY = args.layout, args.fe_every
        sys.setswitchinterval(args.switch_interval_ms / 1000.0)
        return fieldbus_vcan.run(args, layout_for, sine_step, print_table, args.rt_priority,
                                 None if args.cpu_latency_us < 0 else args.cpu_latency_us, DriveProcess)
    if args.bus == "udp_multicast" and os.environ.get("CANON_NETNS") != "1":
        ap.error("--bus udp_multicast joins a multicast group: run it as tests/netns-run python "
                 "bench/fieldbus.py --bus udp_multicast")
    args.seconds = 30.0 if args.seconds is None else args.seconds
    RT = args.rt_priority
    LATENCY = None if args.cpu_latency_us < 0 else args.cpu_latency_us
    LAYOUT, FE_EVERY = args.layout, args.fe_every
    make_layout("standard" if LAYOUT == "auto" else LAYOUT, FE_EVERY)  # a bad --fe-every fails here
    tmp = tempfile.TemporaryDirectory()
    exe = build_rt_floor(Path(tmp.name))
    sys.setswitchinterval(args.switch_interval_ms / 1000.0)
    rows = []
    for period_ms in (float(p) for p in args.periods_ms.split(",")):
        c_row = c_reference(period_ms / 1000.0, min(args.seconds, 10.0), exe)
        if c_row is not None:
            rows.append(c_row)
        rows.append(reference(period_ms / 1000.0, min(args.seconds, 10.0)))
        for n in (int(x) for x in args.drives.split(",")):
            rows.append(case(n, period_ms / 1000.0, args.seconds, args.bus))
    where = "virtual bus, drives in this process" if args.bus == "virtual" else \
        "udp_multicast, drives in another process"
    tmp.cleanup()
    title = (f"CANopen master, {where}, PDO layout {LAYOUT}, {args.seconds:g} s per case, {os.cpu_count()} "
             f"CPUs, load average {os.getloadavg()[0]:.1f}, SCHED_FIFO {RT or 'off'}, CPU latency request "
             f"{'off' if LATENCY is None else f'{LATENCY} us'}, switch interval "
             f"{args.switch_interval_ms:g} ms")
    cols = [("case", "case"), ("period", "period ms"), ("p50", "late p50 us"), ("p99", "p99 us"),
            ("p999", "p99.9 us"), ("max", "max us"), ("missed", "missed cycles"),
            ("setpoints", "drive missed setpoints"), ("cpu", "master CPU %"), ("work", "cycle work us"),
            ("load", "bus load % at 1 Mbit/s"), ("layout", "PDO layout")]
    print_table(title, cols, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
