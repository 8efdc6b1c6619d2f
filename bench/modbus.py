"""Modbus I/O on loopback: round-trip latency of a coil write and of an input read, and the poll rate
sustained with 64 inputs.

The simulated module runs as ``canon sim io`` in its own process (a real module is outside the daemon
too) and logs each write with the system-wide monotonic clock, so the time from a setpoint handed to
``IoExecutor.on_setpoint`` to its M62/M63 write arriving at the module is measured too. The round
trips are given through canon's I/O worker and, as the reference, with a bare pymodbus client in a
loop of its own (the floor for Modbus TCP from Python on this machine).

    python bench/modbus.py [--n 2000] [--seconds 3]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import re
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from fieldbus.modbus.config import (  # noqa: E402
    AnalogInputMap,
    Conversion,
    DigitalInputMap,
    DigitalOutputMap,
    ModbusConfig,
    ModbusDevice,
    ValueType,
)
from fieldbus.modbus.executor import IoExecutor  # noqa: E402
from gcode_canon.commands import DigitalOutput, InputKind, WaitInput, WaitMode  # noqa: E402
from planner.setpoints import Setpoint  # noqa: E402


def pct(xs: list[float], p: float) -> float:
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(p / 100 * len(xs)))]


def row(name: str, xs: list[float]) -> str:
    ms = [x * 1000 for x in xs]
    return (f"{name:<52} p50 {pct(ms, 50):7.3f} ms   p99 {pct(ms, 99):7.3f} ms   "
            f"max {max(ms):7.3f} ms   (n={len(ms)})")


WRITES: list[tuple[float, int, int]] = []  # (time at the module, coil, value) from its write log


def start_sim() -> tuple[subprocess.Popen[str], int]:
    cmd = [sys.executable, "-m", "motiond.cli", "sim", "io", "--port", "0", "--size", "256", "--log-writes"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, cwd=ROOT)
    assert proc.stdout is not None
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        m = re.search(r"listening on 127\.0\.0\.1:(\d+)", line)
        if m:
            threading.Thread(target=_read_log, args=(proc,), daemon=True).start()
            return proc, int(m.group(1))
        if not line and proc.poll() is not None:
            break
    proc.kill()
    raise SystemExit("canon sim io did not start")


def _read_log(proc: subprocess.Popen[str]) -> None:
    assert proc.stdout is not None
    for line in proc.stdout:  # keeps the pipe drained, too
        m = re.match(r"^(\d+\.\d+) \S+: write coil (\d+) = (\d)$", line.strip())
        if m:
            WRITES.append((float(m.group(1)), int(m.group(2)), int(m.group(3))))


async def reference(port: int, n: int) -> tuple[list[float], list[float]]:
    from pymodbus.client import AsyncModbusTcpClient

    c = AsyncModbusTcpClient("127.0.0.1", port=port, timeout=1.0, retries=0, reconnect_delay=0)
    assert await c.connect()
    writes, reads = [], []
    for i in range(n):
        t = time.perf_counter()
        await c.write_coil(100, bool(i & 1), device_id=1)
        writes.append(time.perf_counter() - t)
    for _ in range(n):
        t = time.perf_counter()
        rr = await c.read_discrete_inputs(0, count=64, device_id=1)
        reads.append(time.perf_counter() - t)
        assert not rr.isError()
    c.close()
    return writes, reads


def config(port: int, poll_ms: float, digital: int, analog: int) -> ModbusConfig:
    dev = ModbusDevice("io", port=port, timeout_s=0.5, retries=3, poll_ms=poll_ms)
    return ModbusConfig(
        devices=(dev,),
        digital_outputs=(DigitalOutputMap(0, "io", 100),),
        digital_inputs=tuple(DigitalInputMap(i, "io", i) for i in range(digital)),
        analog_inputs=tuple(AnalogInputMap(i, "io", i, Conversion(ValueType.INT16)) for i in range(analog)),
    )


def through_worker(port: int, n: int) -> tuple[list[float], list[float], list[float]]:
    """Coil write posted -> confirmed; on_setpoint cost on the cycle loop; M66 L0 fresh read."""
    writes, calls, reads = [], [], []
    with IoExecutor(config(port, 20.0, 64, 0)) as ex:
        for i in range(n):
            t = time.monotonic()
            fut = ex.execute(DigitalOutput(index=0, on=bool(i & 1), synced=False))
            done = fut.result(2.0)
            writes.append(done - t)
        for i in range(n):
            sp = Setpoint(0.0, (0.0,), events=(DigitalOutput(index=0, on=bool(i & 1), synced=True),))
            t = time.perf_counter()
            ex.on_setpoint(sp)
            calls.append(time.perf_counter() - t)
            time.sleep(0.001)
        # M66 L0 asks for a read at once and returns its value: about one round trip
        for _ in range(min(n, 200)):
            t = time.monotonic()
            ex.wait_input(WaitInput(kind=InputKind.DIGITAL, index=5, mode=WaitMode.IMMEDIATE, timeout=0.0))
            reads.append(time.monotonic() - t)
    return writes, calls, reads


def synced_latency(port: int, n: int, cycle_s: float) -> list[float]:
    """M62/M63 on a setpoint handed over by a cycle loop -> the write arriving at the module."""
    sent: list[float] = []
    with IoExecutor(config(port, 20.0, 64, 0)) as ex:
        time.sleep(0.1)
        first = len(WRITES)
        t_next = time.monotonic()
        for i in range(n):
            t_next += cycle_s
            while time.monotonic() < t_next:
                time.sleep(max(0.0, t_next - time.monotonic() - 0.0002))
            sp = Setpoint(0.0, (0.0,), events=(DigitalOutput(index=0, on=bool(i & 1), synced=True),))
            sent.append(time.monotonic())
            ex.on_setpoint(sp)
            t_next += 4 * cycle_s  # at rest for a few cycles between moves
        deadline = time.monotonic() + 5
        while len([w for w in WRITES[first:] if w[1] == 100]) < n and time.monotonic() < deadline:
            time.sleep(0.01)
    got = [w for w in WRITES[first:] if w[1] == 100][:n]
    assert [w[2] for w in got] == [i & 1 for i in range(len(got))], "writes out of order"
    return [w[0] - t for w, t in zip(got, sent, strict=False)]


def poll_rate(port: int, poll_ms: float, digital: int, analog: int, seconds: float) -> tuple[float, float]:
    with IoExecutor(config(port, poll_ms, digital, analog)) as ex:
        time.sleep(0.2)
        p0, t0 = ex.worker.counters["polls"], time.monotonic()
        ages = []
        while time.monotonic() - t0 < seconds:
            ages.append(ex.state().input_age_s)
            time.sleep(0.003)
        polls = ex.worker.counters["polls"] - p0
        rate = polls / (time.monotonic() - t0)
    return rate, statistics.median(ages) * 1000


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=2000, help="round trips per latency figure")
    ap.add_argument("--seconds", type=float, default=3.0, help="duration of each poll-rate run")
    args = ap.parse_args()
    proc, port = start_sim()
    try:
        load = " ".join(f"{x:.2f}" for x in os.getloadavg())
        print(f"simulated module: canon sim io, own process, 127.0.0.1:{port}; "
              f"Python {sys.version.split()[0]}; {os.cpu_count()} CPUs, load average {load}")
        ref_w, ref_r = asyncio.run(reference(port, args.n))
        print(row("reference: bare pymodbus write_coil", ref_w))
        print(row("reference: bare pymodbus read 64 discrete inputs", ref_r))
        w, calls, reads = through_worker(port, args.n)
        print(row("canon: M64/M65 execute -> device confirmed", w))
        print(row("canon: on_setpoint with one M62 (cycle-loop cost)", calls))
        print(row("canon: M66 L0 fresh read (poll 20 ms)", reads))
        lat = synced_latency(port, min(args.n, 1000), 0.002)
        print(row("canon: M62/M63 setpoint handed over -> at module", lat))
        print(f"{'':<52} within one 2 ms cycle: {sum(x < 0.002 for x in lat) / len(lat):6.1%}")
        for poll_ms, d, a in ((0.0, 64, 0), (1.0, 64, 0), (5.0, 64, 0), (0.0, 32, 32), (20.0, 64, 0)):
            rate, age = poll_rate(port, poll_ms, d, a, args.seconds)
            target = "back to back" if poll_ms == 0 else f"every {poll_ms:g} ms"
            print(f"poll rate, {d} digital + {a} analog inputs, {target:<13}: {rate:8.1f} polls/s"
                  f"   median input age {age:6.2f} ms")
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
    return 0


if __name__ == "__main__":
    sys.exit(main())
