"""The E-stop input's and a Modbus limit switch's way to the drives, motion in the canon process or in
its own (``[motion] process``; docs/wiring.md, docs/daemon.md).

On the example machine (examples/canon.toml: simulated drives, the simulated Modbus module with its
wiring), a program moves X; the bench opens the E-stop chain (discrete input 8) or closes
``limit_x_max`` (discrete input 17) mid-move, ``--runs`` times each, and reports per mode:

* input -> acted: from the simulated module's input change to the I/O map acting on it (the Modbus
  poll, ``poll_ms`` plus the request, and the wait for the next pass of the I/O map: a cycle in both
  modes);
* acted -> quick stop sent ("own" only): from the task's I/O loop acting to the motion process sending
  the quick stop to the drives, i.e. the urgent pipe and the wake-up of its reader: what "own" adds. In
  one process the cycle thread sends it in the same call (0).

"own" needs udp_multicast for the drives simulated in a third process: run it in the private network
namespace, as root::

    tests/netns-run .venv/bin/python bench/io_stop_latency.py --runs 20
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

PROGRAM = "%\nG21 G90 G94\nG1 X250 F6000\nM2\n%\n"


def machine_file(tmp: Path, mode: str) -> Path:
    text = (ROOT / "examples" / "canon.toml").read_text()
    if mode == "own":
        lines = [ln for ln in text.splitlines() if not ln.startswith(("interface =", "channel ="))]
        text = "\n".join(lines).replace("[canopen]\n", '[canopen]\ninterface = "udp_multicast"\n'
                                        f'channel = "239.74.167.{1 + os.getpid() % 250}"\n'
                                        "sdo_timeout_s = 1.0\n", 1) + '\n[motion]\nprocess = "own"\n'
    path = tmp / f"{mode}.toml"
    path.write_text(text)
    return path


def wait(pred: object, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not pred():  # type: ignore[operator]
        if time.monotonic() > deadline:
            raise TimeoutError("the machine did not get there")
        time.sleep(0.002)


def run(mode: str, runs: int, tmp: Path) -> dict[str, list[tuple[float, float]]]:
    from motiond.config import load_machine
    from motiond.runtime import Machine
    from motiond.states import State

    m = Machine(load_machine(str(machine_file(tmp, mode))), lc=None, var_file=tmp / f"{mode}.var",
                modbus_port=0).start()
    prog = tmp / "x.ngc"
    prog.write_text(PROGRAM)
    out: dict[str, list[tuple[float, float]]] = {"estop": [], "limit": []}
    try:
        sim = m.sim_io["io"]
        m.bring_up()
        for kind, address, active, state in (("estop", 8, 0, State.ESTOP), ("limit", 17, 1, State.FAULTED)):
            for _ in range(runs):
                job = m.run(str(prog))
                wait(lambda: m.motion.commanded[0] > 20.0)
                t_set = time.monotonic()
                sim.set("discrete_input", address, active)
                wait(lambda s=state: m.states.state is s)
                seen = m.io_hooks.stop_seen
                assert seen is not None and seen[0] == kind, seen
                sent = 0.0
                if mode == "own":
                    def stop(k: str = kind) -> tuple[float, float, int, int] | None:
                        return m.motion.last_estop if k == "estop" else m.motion.last_quick_stop

                    t_seen = seen[1]
                    wait(lambda t=t_seen: stop() is not None and stop()[1] >= t - 0.5)  # type: ignore[index]
                    sent = stop()[1] - t_seen  # type: ignore[index]
                out[kind].append((seen[1] - t_set, sent))
                sim.set("discrete_input", address, 1 - active)
                m.wait_job(job, 10.0)
                if kind == "estop":
                    wait(lambda: m.io_hooks.mio.estop_problem() == "")
                    m.estop_reset()
                else:
                    wait(lambda: m.io_hooks.mio._inputs.get("limit_x_max") is False)
                    m.reset()
                m.enable()
                m.wait_job(m.mdi("G0 X0"), 30.0)
                wait(lambda: m.states.state is State.IDLE)
    finally:
        m.shutdown()
    return out


def ms(values: list[float]) -> str:
    if not values:
        return "-"
    v = sorted(values)
    return (f"median {statistics.median(v) * 1e3:6.2f}  p90 {v[int(0.9 * (len(v) - 1))] * 1e3:6.2f}  "
            f"max {v[-1] * 1e3:6.2f} ms")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--modes", default="thread,own")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        for mode in args.modes.split(","):
            res = run(mode, args.runs, Path(d))
            for kind, rows in res.items():
                print(f"{mode:6} {kind:5} input->acted  {ms([a for a, _ in rows])}")
                if mode == "own":
                    print(f"{mode:6} {kind:5} acted->sent   {ms([b for _, b in rows])}")
            print(f"{mode:6} load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
