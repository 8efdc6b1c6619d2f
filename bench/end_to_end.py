"""End-to-end figures of the daemon: start-up, status latency, CPU use while running.

    python bench/end_to_end.py [--seconds 8]            # anywhere (LCM on memq:// inside the process)
    tests/netns-run python bench/end_to_end.py           # also the multi-process rig on udpm/udp_multicast

Prints:

1. ``canon run`` to the first setpoint: from starting the process to the cycle that streams the first
   setpoint (demo machine, boot of 3 simulated drives and the I/O included), with the time Python
   takes to start and import the CLI as the reference.
2. Status latency: from the cycle in which the master read the drives' positions to the moment an
   LCM subscriber has decoded the ``canon.status`` carrying them (status at 50 Hz), p50/p99/max.
3. CPU use at 2 ms with 3 drives while a program runs: the demo machine in one process (drives
   simulated in the same process), and, when multicast works (inside the namespace), the daemon alone
   with the drives and the I/O module in their own processes; the idle daemon as the reference.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

PROGRAM = """%
G21 G90 G94 G64 P0.01
G1 X10 Y5 Z2 F3000
M62 P0
G1 X60 Y40 F3000
G2 X80 Y20 I10 J-10
G1 X20 Y10 Z-1
M63 P0
G1 X0 Y0 Z5 F3000
M2
%
"""
"""At most 50 mm/s: a SYNC lost between processes then never makes a target step the drive refuses."""


def pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, int(q * len(s)))]


def first_setpoint(program: Path, runs: int = 3) -> None:
    starts, refs, boots = [], [], []
    for _ in range(runs):
        t0 = time.monotonic()
        subprocess.run([sys.executable, "-c", "import motiond.cli"], cwd=ROOT, check=True)
        refs.append(time.monotonic() - t0)
        t0 = time.monotonic()
        r = subprocess.run([sys.executable, "-m", "motiond.cli", "run", "--json", "--no-telemetry",
                            str(program)], cwd=ROOT, capture_output=True, text=True, timeout=120)
        if r.returncode != 0:
            print(f"canon run failed: {r.stderr}")
            return
        d = json.loads(r.stdout)
        starts.append(d["first_setpoint_monotonic"] - t0)
        boots.append(d["duration_s"])
    print("1. canon run -> first setpoint (demo machine, 3 simulated drives, I/O module)")
    print(f"   first setpoint after {statistics.median(starts) * 1e3:.0f} ms (median of {runs}; "
          f"min {min(starts) * 1e3:.0f}, max {max(starts) * 1e3:.0f})")
    print(f"   reference: python start + import motiond.cli {statistics.median(refs) * 1e3:.0f} ms")


def in_process(program: Path, seconds: float) -> None:
    from motiond.config import load_machine
    from motiond.control_client import shared_memq
    from motiond.runtime import Machine
    from telemetry.config import TelemetryConfig
    from telemetry.lcmtypes.canon import status

    lc = shared_memq()
    latencies: list[float] = []
    machine: Machine | None = None

    def on_status(_c: str, data: bytes) -> None:
        s = status.decode(data)
        t = time.monotonic()
        if machine is not None and s.state == "running":
            src = machine.status_data_t.get(s.seq)
            if src:
                latencies.append(t - src)

    lc.subscribe("CANON_STATUS", on_status)
    stop = threading.Event()

    def handle() -> None:
        while not stop.is_set():
            lc.handle_timeout(50)

    th = threading.Thread(target=handle, daemon=True)
    th.start()
    machine = Machine(load_machine(None), lc=lc, telemetry=TelemetryConfig(url="memq://"))
    machine.start()
    machine.bring_up()
    time.sleep(1.0)
    c0, w0 = time.process_time(), time.monotonic()
    time.sleep(2.0)
    idle_cpu = (time.process_time() - c0) / (time.monotonic() - w0)
    late0 = machine.late_cycles
    c0, w0 = time.process_time(), time.monotonic()
    runs = 0
    while time.monotonic() - w0 < seconds:
        job = machine.run(program)
        res = machine.wait_job(job, 60)
        runs += 1
        if res is None or not res.ok:
            print(f"   run failed: {res.error if res else 'timeout'}")
            break
    wall = time.monotonic() - w0
    cpu = (time.process_time() - c0) / wall
    late = machine.late_cycles - late0
    machine.shutdown()
    stop.set()
    th.join(1)
    print("2. status latency (master reads the drives' positions -> subscriber decoded canon.status, "
          "memq, 50 Hz)")
    if latencies:
        print(f"   {len(latencies)} snapshots: p50 {pct(latencies, 0.5) * 1e3:.2f} ms, p99 "
              f"{pct(latencies, 0.99) * 1e3:.2f} ms, max {max(latencies) * 1e3:.2f} ms")
    print("3. CPU at 2 ms, 3 drives, one process (master + 3 simulated drives + I/O + telemetry)")
    print(f"   running: {100 * cpu:.0f} % of one core over {wall:.1f} s ({runs} runs), late cycles {late} "
          f"(worst {machine.worst_late_s * 1e3:.1f} ms); reference idle and enabled: {100 * idle_cpu:.0f} %")


def _proc_cpu(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def multi_process(program: Path, seconds: float, tmp: Path) -> None:
    sys.path.insert(0, str(ROOT / "tests"))
    from test_end_to_end import Hmi, Proc, _free_port, config_text  # type: ignore[import-not-found]

    port = _free_port()
    cfg = tmp / "machine.toml"
    cfg.write_text(config_text("239.74.200.17", port))
    procs = [Proc("drives", ["sim", "drives", "--config", str(cfg)], "simulating drives"),
             Proc("io", ["sim", "io", "--port", str(port)], "listening on")]
    try:
        daemon = Proc("daemon", ["daemon", "--config", str(cfg), "--var", str(tmp / "p.var"), "--enable",
                                 "--state-dir", str(tmp), "--program-dir", str(program.parent),
                                 "--late-fault-ms", "1000", "--feedback-timeout-ms", "400"],
                      "canon daemon: machine")
        procs.append(daemon)
        os.environ["CANON_KEY_FILE"] = str(tmp / "command.key")  # made by the daemon at its start
        os.environ.pop("CANON_KEY", None)
        hmi = Hmi()
        hmi.wait(lambda s: s.state == "idle" and s.enabled, what="enabled")
        c0, w0 = _proc_cpu(daemon.p.pid), time.monotonic()
        hmi.pump(2.0)
        idle = (_proc_cpu(daemon.p.pid) - c0) / (time.monotonic() - w0)
        c0, w0 = _proc_cpu(daemon.p.pid), time.monotonic()
        runs = 0
        while time.monotonic() - w0 < seconds:
            hmi.ok("run", [str(program)])
            hmi.wait(lambda s: s.state != "idle", what="running", timeout=10)
            end = hmi.wait(lambda s: s.state in ("idle", "fault"), what="idle", timeout=60)
            if end.state == "fault":  # udp_multicast lost a burst of frames on a loaded PC
                print(f"   a run faulted: {end.last_error}")
                break
            runs += 1
        cpu = (_proc_cpu(daemon.p.pid) - c0) / (time.monotonic() - w0)
        print("3b. CPU of the daemon alone (drives and I/O in their own processes, udp_multicast, LCM udpm)")
        print(f"   running: {100 * cpu:.0f} % of one core ({runs} runs); reference idle and enabled: "
              f"{100 * idle:.0f} %")
    finally:
        for p in reversed(procs):
            p.stop()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=8.0, help="how long to run programs for the CPU figure")
    args = ap.parse_args()
    from telemetry.publisher import TelemetryUnavailable, preflight
    from telemetry.url import DEFAULT_URL

    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    with tempfile.TemporaryDirectory() as d:
        program = Path(d) / "bench.ngc"
        program.write_text(PROGRAM)
        first_setpoint(program)
        in_process(program, args.seconds)
        try:
            preflight(DEFAULT_URL)
            multicast = os.environ.get("CANON_NETNS") == "1"
        except TelemetryUnavailable:
            multicast = False
        if multicast:
            multi_process(program, args.seconds, Path(d))
        else:
            print("3b. (skipped: run inside tests/netns-run for the multi-process figure)")


if __name__ == "__main__":
    main()
