"""Interleaved A/B timing of the interpreter: the working tree against a git ref, rs274 between them.

On a machine shared with other work a single timing swings by 30 % or more, and a load spike can
cover several runs that follow each other. This bench runs, round after round, the working tree's
canon, the ref's canon and LinuxCNC's rs274 one after the other (the order of the two canons swapped
every round), each in its own process, and keeps the least CPU time of each over the rounds: the
three see the same load, so the ratios between them hold better than single runs do.

The ref (``--vs-ref``, default ``HEAD``) is extracted with ``git archive`` into a temporary directory
and run with ``PYTHONPATH`` pointing at it (it comes before the editable install on ``sys.path``;
each child prints where it imported ``gcode_canon`` from and the bench checks it). Both ways are
timed: in process (a child that times ``Interpreter.run_file`` only, as ``bench/interpreter.py``
does, three times with a new Interpreter each, keeping the least) and ``canon check`` (the whole
child: start-up, interpretation and text to /dev/null, byte-compiled as in ``bench/interpreter.py``).
Every canon child gets the same ``PYTHONHASHSEED`` (``--hash-seed``), so that dict layouts do not
differ between the two sides: with random seeds and one run per child, the same code on both sides
once came out 15 % apart. The programs are ``bench/interpreter.py``'s plain and mixed ones.

Usage: ``python bench/interpreter_ab.py [LINES] [--vs-ref REF] [--rounds N] [--only plain|mixed]
[--way process|check]`` (100,000 lines, 6 rounds, both programs and both ways by default).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from interpreter import compiled_env, rs274_binary, timed_process, write_mixed, write_plain

ROOT = Path(__file__).resolve().parent.parent

# Run in the child: the CPU time of interpreting the program only (start-up excluded).
IN_PROCESS = """
import sys, time, gcode_canon
from gcode_canon.interpreter import Interpreter
from gcode_canon.settings import InterpreterSettings
best = None
for _ in range(int(sys.argv[2])):
    interp = Interpreter(InterpreterSettings(dry_run=True))
    c0 = time.process_time()
    n = 0
    for _ in interp.run_file(sys.argv[1]):
        n += 1
    cpu = time.process_time() - c0
    best = cpu if best is None else min(best, cpu)
print(best, n, gcode_canon.__file__)
"""

# ``canon check`` as the installed entry script runs it (``canon = motiond.cli:main``).
CHECK = "import sys; from motiond.cli import main; sys.exit(main())"


def extract(ref: str, into: Path) -> Path:
    """The tree of ``ref`` written under ``into`` (``git archive``), returned."""
    into.mkdir()
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", "--format=tar", ref],
                             check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    return into


def env_for(tree: Path, base: dict[str, str]) -> dict[str, str]:
    env = dict(base)
    env["PYTHONPATH"] = str(tree) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


INNER_RUNS = 3
"""Runs of the program inside each in-process child (a new Interpreter each), the least CPU kept."""


def in_process(tree: Path, program: Path, env: dict[str, str]) -> float:
    out = subprocess.run([sys.executable, "-c", IN_PROCESS, str(program), str(INNER_RUNS)],
                         env=env_for(tree, env),
                         capture_output=True, text=True, check=True, cwd=tree).stdout.split()
    if not Path(out[2]).resolve().is_relative_to(tree.resolve()):
        raise SystemExit(f"the child imported gcode_canon from {out[2]}, not from {tree}")
    return float(out[0])


def check(tree: Path, program: Path, env: dict[str, str]) -> float:
    return timed_process([sys.executable, "-c", CHECK, "check", str(program)], tree, env_for(tree, env))[1]


def main() -> None:
    parser = argparse.ArgumentParser(description="Interleaved timing: working tree vs a git ref vs rs274.")
    parser.add_argument("lines", nargs="?", type=int, default=100_000, help="lines per program (100,000)")
    parser.add_argument("--vs-ref", default="HEAD", metavar="REF", help="the git ref to compare with (HEAD)")
    parser.add_argument("--rounds", type=int, default=6, metavar="N", help="rounds; least CPU time kept (6)")
    parser.add_argument("--hash-seed", type=int, default=0, metavar="N",
                        help="PYTHONHASHSEED of every canon child (0)")
    parser.add_argument("--only", choices=("plain", "mixed"), help="one program only")
    parser.add_argument("--way", choices=("process", "check"), help="one way only")
    args = parser.parse_args()
    rs274 = rs274_binary()
    print(f"load average before: {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs; "
          f"least CPU time of {args.rounds} interleaved rounds")
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        trees = {"work": ROOT, args.vs_ref: extract(args.vs_ref, tmp / "ref")}
        ini = tmp / "mm.ini"
        ini.write_text("[TRAJ]\nLINEAR_UNITS = mm\n")
        env = compiled_env(tmp)
        env["PYTHONHASHSEED"] = str(args.hash_seed)  # the same str hashes (dict layouts) on both sides
        one = tmp / "one.ngc"
        one.write_text("G0 X1\nM2\n")
        for tree in trees.values():
            check(tree, one, env)  # writes the bytecode: not timed
        programs = {}
        for name, write in (("plain", write_plain), ("mixed", write_mixed)):
            if args.only in (None, name):
                programs[name] = tmp / f"{name}.ngc"
                write(programs[name], args.lines)
        ways = {"process": in_process, "check": check}
        ways = {w: f for w, f in ways.items() if args.way in (None, w)}
        best: dict[tuple[str, str, str], float] = {}
        for r in range(args.rounds):
            order = list(trees.items()) if r % 2 == 0 else list(trees.items())[::-1]
            for pname, program in programs.items():
                for label, tree in order:
                    for way, measure in ways.items():
                        cpu = measure(tree, program, env)
                        key = (pname, way, label)
                        best[key] = min(best.get(key, cpu), cpu)
                if rs274 is not None:
                    cpu = timed_process([str(rs274), "-g", "-i", str(ini), str(program)], tmp)[1]
                    key = (pname, "", "rs274")
                    best[key] = min(best.get(key, cpu), cpu)
            print(f"round {r + 1}/{args.rounds} done, load average {os.getloadavg()[0]:.2f}", flush=True)
        print(f"\n{args.lines:,d} lines; CPU seconds (ratio to rs274); target from issue #18")
        targets = {("plain", "check"): 1.3, ("mixed", "process"): 1.0, ("mixed", "check"): 1.3}
        for pname in programs:
            ref = best.get((pname, "", "rs274"))
            if ref is not None:
                print(f"{pname:6s} rs274 {ref:.3f}")
            for way in ways:
                cells = []
                for label in trees:
                    cpu = best[(pname, way, label)]
                    cells.append(f"{label} {cpu:.3f}" + (f" ({cpu / ref:.2f}x)" if ref else ""))
                target = targets.get((pname, way))
                print(f"{pname:6s} {way:8s} " + "   ".join(cells)
                      + (f"   target <= {target}x" if target else ""))
        print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
