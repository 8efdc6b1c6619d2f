"""Interpreter throughput: lines per second and peak memory on generated 1,000,000-line programs.

Two programs are written to a temporary directory and interpreted through ``Interpreter.run_file``
(lazily, as ``canon check`` does):

* plain: only ``G1 X.. Y.. Z..`` lines with an occasional F (the fast path);
* mixed: G1 moves, arcs (IJK and R), parameter assignments, expressions, comments, G0.

Peak memory is the process's maximum resident set (``resource``) and the peak of Python allocations
during the run (``tracemalloc``, measured on a shorter run because tracing slows Python down); the
second must not grow with the program's length, so it is printed for two lengths.

Where ``tools/build-rs274`` has built LinuxCNC's rs274 (``$CANON_RS274_DIR``), the same programs go
through it in the same run as the reference (its canonical calls to /dev/null, as ``canon check``'s
text goes to /dev/null), and ``canon check`` runs on them as a user would (a new process, start-up
included). Start-up alone is timed on a one-line program, and the import of the interpreter module.

``canon check`` runs byte-compiled, as an installed canon does (pip writes the ``.pyc`` files): where
``PYTHONDONTWRITEBYTECODE`` is set (as on the project's machines) its bytecode goes to a temporary
``PYTHONPYCACHEPREFIX``, written by a first run that is not timed; the start-up without bytecode
(every module compiled from source at each start) is printed beside it.

The figures move with the machine's load: ``--repeat N`` takes the least CPU time of N runs of each
(canon in process, ``canon check``, rs274), run in turn: one of each per round. The summary at the end
gives canon's CPU time over rs274's for each program and way (and the spread of that ratio within the
rounds), against the targets of issue #18 (in process at most 1.0x on the
mixed program, ``canon check`` at most 1.3x on both).

Usage: ``python bench/interpreter.py [LINES] [--repeat N]`` (default 1,000,000 lines, one run each).
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path

from gcode_canon.interpreter import Interpreter
from gcode_canon.settings import InterpreterSettings


def write_plain(path: Path, n: int) -> None:
    with open(path, "w") as f:
        f.write("G21 G90 G17 G94 F1000\n")
        for i in range(n - 2):
            x = 50.0 + 40.0 * math.cos(i * 0.001)
            y = 50.0 + 40.0 * math.sin(i * 0.001)
            if i % 1000 == 0:
                f.write(f"G1 X{x:.4f} Y{y:.4f} Z{-(i % 7) * 0.1:.3f} F{800 + i % 400}\n")
            else:
                f.write(f"G1 X{x:.4f} Y{y:.4f} Z{-(i % 7) * 0.1:.3f}\n")
        f.write("M2\n")


def write_mixed(path: Path, n: int) -> None:
    lines = [
        "G1 X{a:.3f} Y{b:.3f} F600",
        "G2 X{c:.3f} Y{b:.3f} I{r:.3f} J0",
        "G3 X{a:.3f} Y{b:.3f} R{r:.3f}",
        "#1 = [#1 + 0.5] #<depth> = [-[#1 MOD 3] * 0.25]",
        "G1 Z#<depth> (plunge)",
        "G1 X[{a:.3f} + SIN[#1] * 2] Y[{b:.3f} * COS[30]]",
        "G0 Z5",
        "X{a:.3f} Y[{b:.3f} + 1]",
    ]
    with open(path, "w") as f:
        f.write("G21 G90 G17 G94 #1=0 #<depth>=0 F600\n")
        written = 1
        i = 0
        while written < n - 1:
            a = 10.0 + (i % 50)
            b = 20.0 + (i % 30)
            r = 2.5
            for t in lines:
                f.write(t.format(a=a, b=b, c=a + 2 * r, r=r) + "\n")
            written += len(lines)
            i += 1
        f.write("M2\n")


def run(path: Path) -> tuple[float, float, int]:
    """Wall seconds, CPU seconds of this process, commands produced."""
    interp = Interpreter(InterpreterSettings(dry_run=True))
    count = 0
    c0 = time.process_time()
    t0 = time.perf_counter()
    for _ in interp.run_file(path):
        count += 1
    return time.perf_counter() - t0, time.process_time() - c0, count


def rs274_binary() -> Path | None:
    root = Path(os.environ.get("CANON_RS274_DIR") or Path.home() / ".cache" / "canon" / "rs274")
    binary = root / "bin" / "rs274"
    return binary if binary.exists() else None


def timed_process(args: list[str], cwd: Path, env: dict[str, str] | None = None) -> tuple[float, float]:
    """Wall seconds and CPU seconds (user + system) of one child process, output to /dev/null."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(args, cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=False, env=env)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def best(runs: int, measure):
    """The run of ``measure()`` (a tuple whose second item is CPU seconds) with the least CPU time."""
    return least([measure() for _ in range(runs)])


def interleaved(runs: int, measures: dict[str, Callable[[], tuple]]) -> dict[str, list[tuple]]:
    """Every run of each ``measure()`` (tuples whose second item is CPU seconds), taken in turn, one of each
    per round, for ``runs`` rounds.

    In turn, not all of canon's runs and then all of rs274's: a stretch of seconds in which the machine is
    slow (other work, this VM's host taking the CPU away) then falls on both sides of the comparison, where
    back to back it could fall on one side's runs only and move their ratio by half.
    """
    results: dict[str, list[tuple]] = {name: [] for name in measures}
    for _ in range(runs):
        for name, measure in measures.items():
            results[name].append(measure())
    return results


def least(results: list[tuple]) -> tuple:
    """The run with the least CPU time."""
    return min(results, key=lambda r: r[1])


def compiled_env(tmp: Path) -> dict[str, str]:
    """The environment for ``canon check`` with bytecode written and read (module docstring)."""
    env = dict(os.environ)
    if env.pop("PYTHONDONTWRITEBYTECODE", None) is not None:
        env["PYTHONPYCACHEPREFIX"] = str(tmp / "pycache")
    return env


def canon_command() -> list[str]:
    exe = shutil.which("canon", path=str(Path(sys.executable).parent)) or shutil.which("canon")
    return [exe] if exe else [sys.executable, "-m", "motiond.cli"]


def lines_of(path: Path) -> int:
    with open(path, "rb") as f:
        return sum(1 for _ in f)


def traced_peak(path: Path) -> int:
    tracemalloc.start()
    run(path)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return peak


def main() -> None:
    parser = argparse.ArgumentParser(description="Interpreter lines/s and memory on generated programs.")
    parser.add_argument("lines", nargs="?", type=int, default=1_000_000, help="lines per program (1,000,000)")
    parser.add_argument("--repeat", type=int, default=1, metavar="N",
                        help="runs of each measurement; the least CPU time is kept (1)")
    args = parser.parse_args()
    n, runs = args.lines, max(1, args.repeat)
    # The figures depend on what else runs: say so next to them.
    print(f"load average before: {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs; best of {runs} run(s)")
    ratios: dict[tuple[str, str], float] = {}
    rounds: dict[tuple[str, str], list[float]] = {}  # the ratio within each round, sorted
    with tempfile.TemporaryDirectory() as tmp:
        plain = Path(tmp) / "plain.ngc"
        mixed = Path(tmp) / "mixed.ngc"
        write_plain(plain, n)
        write_mixed(mixed, n)
        rs274 = rs274_binary()
        ini = Path(tmp) / "mm.ini"
        ini.write_text("[TRAJ]\nLINEAR_UNITS = mm\n")
        if rs274 is None:
            print("rs274 not built (tools/build-rs274): no reference in this run")
        one = Path(tmp) / "one.ngc"
        one.write_text("G0 X1\nM2\n")
        env = compiled_env(Path(tmp))
        check = [*canon_command(), "check"]
        timed_process([*check, str(one)], Path(tmp), env)  # writes the bytecode: not timed
        for name, path in (("plain G1", plain), ("mixed", mixed)):
            nlines = lines_of(path)
            measures: dict[str, Callable[[], tuple]] = {
                "in process": lambda path=path: run(path),
                "canon check": lambda path=path: timed_process([*check, str(path)], Path(tmp), env),
            }
            if rs274 is not None:
                measures["rs274"] = lambda path=path: timed_process(
                    [str(rs274), "-g", "-i", str(ini), str(path)], Path(tmp))
            results = interleaved(runs, measures)
            seconds, cpu, count = least(results["in process"])
            print(f"{name:9s}: {nlines:>9,d} lines in {seconds:6.2f} s = {nlines / seconds:>9,.0f} lines/s "
                  f"wall, {nlines / cpu:>9,.0f} lines/s CPU ({count:,d} commands), in process")
            check_wall, check_cpu = least(results["canon check"])
            print(f"{'':9s}  canon check: {check_wall:6.2f} s wall, {check_cpu:6.2f} s CPU")
            if rs274 is not None:
                ref_wall, ref_cpu = least(results["rs274"])
                print(f"{'':9s}  rs274:       {ref_wall:6.2f} s wall, {ref_cpu:6.2f} s CPU = "
                      f"{nlines / ref_cpu:>9,.0f} lines/s CPU; canon/rs274 CPU: in process "
                      f"{cpu / ref_cpu:.2f}x, canon check {check_cpu / ref_cpu:.2f}x")
                for way, mine in (("in process", cpu), ("canon check", check_cpu)):
                    ratios[(name, way)] = mine / ref_cpu
                    rounds[(name, way)] = sorted(
                        mine[1] / ref[1] for mine, ref in zip(results[way], results["rs274"], strict=True))
        wall, cpu = best(runs, lambda: timed_process([*check, str(one)], Path(tmp), env))
        print(f"start-up: canon check of a 2-line program {wall:.2f} s wall, {cpu:.2f} s CPU (byte-compiled)")
        if "PYTHONDONTWRITEBYTECODE" in os.environ:
            wall, cpu = best(runs, lambda: timed_process([*check, str(one)], Path(tmp)))
            print(f"start-up: the same without bytecode (PYTHONDONTWRITEBYTECODE) {wall:.2f} s wall, "
                  f"{cpu:.2f} s CPU")
        wall, cpu = timed_process([sys.executable, "-c", "import gcode_canon.interpreter"], Path(tmp), env)
        _, base_cpu = timed_process([sys.executable, "-c", "pass"], Path(tmp), env)
        print(f"start-up: importing gcode_canon.interpreter {cpu - base_cpu:.3f} s CPU over a bare "
              f"interpreter ({base_cpu:.3f} s)")
        print(f"max RSS after both runs: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.1f} MiB")
        small = Path(tmp) / "small.ngc"
        big = Path(tmp) / "big.ngc"
        write_mixed(small, 20_000)
        write_mixed(big, 100_000)
        p1, p2 = traced_peak(small), traced_peak(big)
        print(f"peak traced Python allocations: {p1 / 1024:.0f} KiB for 20,000 lines, "
              f"{p2 / 1024:.0f} KiB for 100,000 lines (must not grow with length)")
        print(f"load average after: {os.getloadavg()[0]:.2f}")
        print("reference (same kind of machine, from the project notes): pygcode ~30,000 lines/s")
    if ratios:
        print("\ncanon's CPU time / rs274's (same run: least of each; within a round: least-median-most)")
        for (name, way), target in ((("plain G1", "in process"), None), (("mixed", "in process"), 1.0),
                                    (("plain G1", "canon check"), 1.3), (("mixed", "canon check"), 1.3)):
            ratio = ratios[(name, way)]
            each = rounds[(name, way)]
            spread = f"{each[0]:.2f}-{statistics.median(each):.2f}-{each[-1]:.2f}x"
            verdict = "" if target is None else f"<= {target:.1f}x  {'met' if ratio <= target else 'NOT met'}"
            print(f"  {name:9s} {way:12s} {ratio:5.2f}x   {spread:>17s}   {verdict}")

if __name__ == "__main__":
    main()
