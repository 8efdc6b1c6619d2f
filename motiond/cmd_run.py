"""``canon run FILE.ngc``: boot the machine, run one program on it, print a summary, exit.

With no ``--config`` it runs on the built-in demo machine: three simulated drives on canon's local
CAN bus (``canon_local``, a channel of the run's own; with the Modbus I/O on the machine
``[motion] process = "auto"`` keeps the motion side a thread of this process, and master and drives
then share python-can's virtual bus), the simulated Modbus
I/O module on loopback (a free port), LCM on the default
URL (a host with no multicast route gets one warning line and telemetry inside this process only).
It is the daemon's core (:class:`motiond.runtime.Machine`) doing what an operator would: leave
E-stop, enable the drives, run the file, then shut down safely.

``--start-line N`` runs from line N (:meth:`motiond.runtime.Machine.run`, docs/daemon.md): a start
line the program never reaches, or one inside a subroutine or loop body, exits 1 with ``FILE:LINE:``
and the reason, nothing moved.

Exit status 0 when the program ran to its end; 1 with ``FILE:LINE: message`` (a G-code error) or the
fault's reason (a drive, the I/O, a late cycle) on stderr; 130 on Ctrl-C or SIGTERM: a jerk-limited
stop on the path, then "stopped at FILE:LINE (resume with --start-line LINE)" and the parameters saved.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

SETTLE_S = 0.5  # after the last setpoint, wait this long at most for the drives to settle


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from motiond.cli import add_common
    from motiond.interp_settings import add_arguments as add_interp_arguments

    add_common(parser)
    add_interp_arguments(parser, block_delete=False)
    parser.add_argument("--no-telemetry", action="store_true", help="publish nothing on LCM")
    parser.add_argument("--url", help="LCM URL for status and events (default: [telemetry] url)")
    parser.add_argument("--start-line", type=_line_number, default=1, metavar="N",
                        help="run from line N: the lines before it are interpreted without moving, then "
                             "tool, spindle, coolant and override switches are restored and the machine "
                             "approaches the start point (Z up, X Y, Z down) (default 1: the whole file)")
    parser.add_argument("--state-dir", metavar="DIR",
                        help="where the machine's lock lives (one run or daemon per machine file; default "
                             "as canon daemon's)")
    parser.add_argument("--late-fault-ms", type=float, metavar="MS",
                        help="a cycle starting later than this is a fault (default: 10 cycles, at least "
                             "50 ms; 1 s with simulated drives in the canon process: [motion] "
                             "process \"thread\")")


def _line_number(text: str) -> int:
    """``--start-line``: a line number, 1 or more (argparse reports the error as a usage error)."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"a line number (1 or more) is needed, got {text!r}")
    return value


def _fmt(v: float) -> str:
    return f"{v:.3g}" if abs(v) < 1000 else f"{v / 1000:.3g}k"


def timing_verdict(late_s: list[float], period_s: float, limit_s: float,
                   heartbeat_consumer_ms: int, drive_timeout_ms: float = 0.0,
                   lead: int = 1) -> tuple[str, str]:
    """Late cycles judged against what a real drive tolerates: ``("ok" | "rough" | "fault", words)``.

    A cycle late by less than a period still delivers its setpoint before the next SYNC. One late by
    more leaves a real drive a SYNC (or more) without a new target: it holds the last one, a velocity
    step. Real drives fault when the gap between two setpoints (a period plus the lateness) passes their
    own setpoint timeout (``drive_timeout_ms``, ``[canopen] drive_setpoint_timeout_ms`` as commissioned
    on the drives); when that is not configured, ``limit_s`` stands in for it (canon's late-cycle fault on
    real drives, ten cycles but at least 50 ms). A stall beyond the drives' heartbeat consumer time
    silences the master's heartbeat too: the drives fault on that as well.

    ``lead``: ``[canopen] setpoint_lead``, the SYNCs ahead the SYNC process holds setpoints for: a cycle
    then reaches the drives late only by what it was late beyond ``lead - 1`` periods.
    """
    period_ms = period_s * 1000
    n = len(late_s)
    if n == 0:
        return "ok", "every cycle on time: a real drive would have been happy"
    worst = max(late_s)
    slack = (lead - 1) * period_s
    at_drive = [by - slack for by in late_s]  # how late the setpoint reached the drives
    missed = sum(1 for by in at_drive if by > period_s)
    if drive_timeout_ms > 0:
        tolerance = f"the drives' setpoint timeout ({drive_timeout_ms:g} ms)"

        def beyond(by: float) -> bool:
            return (by + period_s) * 1000 > drive_timeout_ms
    else:
        tolerance = f"canon's late-cycle limit for real drives ({limit_s * 1000:g} ms)"

        def beyond(by: float) -> bool:
            return by > limit_s
    over = [tolerance] if beyond(worst - slack) else []
    if heartbeat_consumer_ms and worst * 1000 > heartbeat_consumer_ms:
        over.append(f"the drives' heartbeat consumer time ({heartbeat_consumer_ms} ms)")
    if over:
        silent = heartbeat_consumer_ms / 1000 if heartbeat_consumer_ms else float("inf")
        k = sum(1 for by in late_s if beyond(by - slack) or by > silent)
        return "fault", (f"NOT fit for a real machine: the worst cycle started {worst * 1000:.1f} ms late, "
                         f"beyond {' and '.join(over)}; on real drives the run would have stopped with a "
                         f"fault ({k} such cycle{'s' if k != 1 else ''})")
    within = "one period" if lead == 1 else f"{lead} periods (the setpoint lead)"
    if missed == 0:
        return "ok", (f"{n} cycles late but each by less than {within} ({period_ms:g} ms, worst "
                      f"{worst * 1000:.1f} ms): every setpoint arrived before its SYNC; a real drive "
                      "would not have noticed")
    plural = "s" if missed != 1 else ""
    return "rough", (f"{missed} cycle{plural} late by more than {within} ({period_ms:g} ms, worst "
                     f"{worst * 1000:.1f} ms): a real drive would have held its last setpoint for a SYNC or "
                     f"more each time (a velocity step, a jolt), within {tolerance}: no fault, but rough "
                     "motion")


def time_breakdown(result: Any, period_s: float) -> dict[str, float]:
    """Where a run's wall time went: moving, before the first setpoint, standing (dwells, waits, the
    planner waiting for the interpreter), and deadlines that never ran (the process not scheduled)."""
    executed = result.cycles * period_s
    moving = result.moving_cycles * period_s
    before = min(result.first_setpoint_s, max(executed - moving, 0.0))
    return {
        "total_s": result.duration_s,
        "moving_s": moving,
        "before_first_setpoint_s": before,
        "standing_s": max(executed - moving - before, 0.0),
        "skipped_s": max(result.duration_s - executed, 0.0),
    }


def _tolerances(machine: Any) -> tuple[float, int, float]:
    """What a real machine of this configuration tolerates: canon's late-cycle limit for real drives,
    the drives' heartbeat consumer time and their setpoint timeout as configured (not the simulation's
    relaxed values; 0: not configured)."""
    from motiond.config_canopen import canopen_for_machine

    configured = canopen_for_machine(machine.config)
    hb = configured.heartbeat_consumer_ms if configured.heartbeat_producer_ms else 0
    return max(10 * machine.T, 0.050), hb, configured.drive_setpoint_timeout_ms


def _lead(machine: Any) -> int:
    """The setpoint lead the run had (``[canopen] setpoint_lead``; 1 without the SYNC process)."""
    from motiond.config_canopen import canopen_for_machine

    configured = canopen_for_machine(machine.config)
    return configured.setpoint_lead if configured.sync_source == "process" else 1


#: where the motion side ran, by ``[motion] process`` mode (docs/daemon.md)
_WHERE = {"own": "in its own process", "thread": "in a thread of this process"}


def summary_dict(machine: Any, result: Any) -> dict[str, Any]:
    """The run's figures as plain data (``--json`` prints it)."""
    axes = {}
    for i, a in enumerate(machine.limits.axes):
        pk = result.peaks[a.name]
        axes[a.name] = {
            "unit": a.unit,
            "peak_velocity": pk.velocity, "max_velocity": a.max_velocity,
            "peak_acceleration": pk.acceleration, "max_acceleration": a.max_acceleration,
            "peak_jerk": pk.jerk, "max_jerk": a.max_jerk,
            "following_error_max": pk.following_error,
            "final_commanded": result.final_commanded[i] if result.final_commanded else None,
            "final_actual": result.final_actual[i] if result.final_actual else None,
            "program_final": result.expected_final[i] if result.expected_final else None,
        }
    limit_s, hb, drive_timeout_ms = _tolerances(machine)
    lead = _lead(machine)
    verdict, words = timing_verdict(result.late_s, machine.T, limit_s, hb, drive_timeout_ms, lead)
    return {
        "timing": {"verdict": verdict, "text": words, "real_late_limit_ms": limit_s * 1000,
                   "setpoint_lead": lead,
                   "heartbeat_consumer_ms": hb, "drive_setpoint_timeout_ms": drive_timeout_ms,
                   "late_by_more_than_a_period": sum(1 for by in result.late_s if by > machine.T)},
        "time": time_breakdown(result, machine.T),
        "program": result.program,
        "ok": result.ok,
        "error": result.error,
        "machine": machine.limits.name,
        "motion_process": machine.motion_mode,
        "duration_s": result.duration_s,
        "cycle_s": result.cycle_s,
        "cycles": result.cycles,
        "period_ms": machine.T * 1000.0,
        "late_cycles": result.late_cycles,
        "first_setpoint_monotonic": machine.first_setpoint_t,
        "worst_late_ms": machine.worst_late_s * 1000.0,
        "axes": axes,
        "peaks": {n: {"velocity": v["peak_velocity"], "acceleration": v["peak_acceleration"],
                      "jerk": v["peak_jerk"]} for n, v in axes.items()},
        "following_error_max": {n: v["following_error_max"] for n, v in axes.items()},
        "final_positions": {n: v["final_commanded"] for n, v in axes.items()},
        "final_actual": {n: v["final_actual"] for n, v in axes.items()},
        "outputs_switched": [
            {"cycle": o.cycle - result.first_cycle, "kind": o.kind, "index": o.index,
             "value": o.value, "synced": o.synced, "line": o.line, "name": o.name}
            for o in result.outputs],
    }


def print_summary(machine: Any, result: Any, console: Any) -> None:
    from rich import box
    from rich.table import Table

    d = summary_dict(machine, result)
    console.print(f"[bold]{result.program}[/] on {d['machine']}: ran in {d['duration_s']:.2f} s, motion "
                  f"{d['cycle_s']:.3f} s ({d['cycles']} cycles of {d['period_ms']:g} ms), "
                  f"{d['late_cycles']} late cycles (worst {d['worst_late_ms']:.1f} ms), motion side "
                  f"{_WHERE[d['motion_process']]}", highlight=False)
    console.print(f"timing: {d['timing']['text']}", highlight=False)
    tb = d["time"]
    if tb["total_s"] > 1.05 * tb["moving_s"] + 0.5:
        parts = [f"{tb['moving_s']:.2f} s moving"]
        if tb["before_first_setpoint_s"] >= 0.05:
            parts.append(f"{tb['before_first_setpoint_s']:.2f} s before the first setpoint (reading and "
                         "planning ahead, starting the drives' stream)")
        if tb["standing_s"] >= 0.05:
            parts.append(f"{tb['standing_s']:.2f} s standing (dwells, waits for inputs or tool changes, the "
                         "planner waiting for the interpreter)")
        if tb["skipped_s"] >= 0.05:
            parts.append(f"{tb['skipped_s']:.2f} s of cycles that never ran (deadlines skipped: the process "
                         "was not scheduled in time: a loaded or non-real-time PC)")
        console.print(f"where the {tb['total_s']:.2f} s went: " + "; ".join(parts), highlight=False)
    t = Table(box=box.SIMPLE_HEAD)
    for col in ("axis", "velocity", "acceleration", "jerk", "FE max", "final"):
        t.add_column(col, justify="left" if col == "axis" else "right", no_wrap=True)

    def pl(peak: float, limit: float) -> str:
        return f"{_fmt(peak)}/{_fmt(limit)} {100 * peak / limit:.0f}%"

    for name, a in d["axes"].items():
        t.add_row(f"{name.upper()} {a['unit']}", pl(a["peak_velocity"], a["max_velocity"]),
                  pl(a["peak_acceleration"], a["max_acceleration"]), pl(a["peak_jerk"], a["max_jerk"]),
                  f"{a['following_error_max']:.4f}", f"{a['final_commanded']:.4f}")
    t.caption = "peak / limit per second, per second², per second³ (machine units)"
    console.print(t)
    outs = d["outputs_switched"]
    if outs:
        words = [f"{o['name']}={o['value']:g} (line {o['line']})" if o["kind"] == "function" else
                 f"{'D' if o['kind'] == 'digital' else 'A'}{o['index']}="
                 f"{int(o['value']) if o['kind'] == 'digital' else o['value']:g} (line {o['line']}"
                 f"{', synced' if o['synced'] else ''})" for o in outs]
        console.print(f"outputs switched: {len(outs)}: " + ", ".join(words), highlight=False)
    else:
        console.print("outputs switched: none")


def _settle(machine: Any, timeout: float = SETTLE_S) -> None:
    """Wait until the drives report the commanded position (within a count or so)."""
    import time

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        motion = machine.motion
        if all(abs(a - c) <= 2e-4 for a, c in zip(motion.actual, motion.commanded, strict=True)):
            return
        time.sleep(0.01)


def stop_report(program: str, place: tuple[str, int]) -> str:
    """Where an interrupted run stopped, in the words ``--start-line`` needs."""
    file, line = place
    if line <= 0:
        return f"stopped before the first motion of {program} (nothing to resume: run it from the start)"
    if not file or _same_file(file, program):
        return f"stopped at {program}:{line} (resume with --start-line {line})"
    return (f"stopped at {file}:{line}, inside a subroutine that {program} calls (--start-line takes a "
            f"line of {program}: the line of the call)")


def _same_file(a: str, b: str) -> bool:
    import os

    try:
        return os.path.samefile(a, b)
    except OSError:
        return a == b


def _file_state(path: Any) -> tuple[int, int] | None:
    import os

    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_ino, st.st_mtime_ns


def _interrupted(machine: Any, program: str) -> int:
    """Ctrl-C or SIGTERM while the program runs: a jerk-limited stop on the path (the planner's
    abort, the drives kept streaming until the motion is at rest), then the machine shut down (drives
    disabled, outputs safe, parameters written) and the place to resume from printed."""
    from motiond.runtime import STOP_TIMEOUT_S

    at_rest = machine.stop_on_path(STOP_TIMEOUT_S)
    place = machine.motion_place
    var = machine.interp.settings.var_file
    before = _file_state(var) if var is not None else None
    machine.shutdown()
    print(f"canon run: interrupted: {stop_report(program, place)}", file=sys.stderr)
    if not at_rest:
        print(f"canon run: the motion was not at rest after {STOP_TIMEOUT_S:g} s: the drives were "
              "disabled while moving", file=sys.stderr)
    if var is not None:
        after = _file_state(var)
        if after is not None and after != before:
            print(f"canon run: parameters saved to {var}", file=sys.stderr)
        else:
            print(f"canon run: the parameters could not be saved to {var}", file=sys.stderr)
    return 130


def run(args: argparse.Namespace) -> int:
    import logging

    from motiond.cli import program_file
    from motiond.config_check import load_checked
    from motiond.instance_lock import lock_machine
    from motiond.interp_settings import settings_from_args

    if not getattr(args, "verbose", 0):  # the error is printed once, below, not also as a log line
        for name in ("motiond.runtime", "fieldbus"):
            logging.getLogger(name).setLevel(logging.CRITICAL)
    path = program_file(args.file)
    config = load_checked(args.config)
    settings = settings_from_args(config, args, dry_run=False)
    lock = lock_machine(args.config, config, args.state_dir)
    try:
        return _run_locked(args, path, config, settings)
    finally:
        lock.release()


WAIT_TICK_S = 0.1


def wait_for_job(machine: Any, job: Any, tick: Any = None) -> Any:
    """The job's result, waited for in ticks of :data:`WAIT_TICK_S` (``tick()`` after each).

    Never one unbounded wait: a SIGINT or SIGTERM that the kernel hands to another of the process's
    threads (any thread may take a process-directed signal) does not wake a main thread blocked on a
    lock, and Python runs the handler only when the main thread runs again; an unbounded wait let a
    Ctrl-C go unheeded until the program ended (seen under load). A tick bounds that delay to 0.1 s."""
    while True:
        result = machine.wait_job(job, WAIT_TICK_S)
        if result is not None:
            return result
        if tick is not None:
            tick()


def _run_locked(args: argparse.Namespace, path: Any, config: Any, settings: Any) -> int:
    import signal

    from rich.console import Console

    from motiond.cli import UserError
    from motiond.runtime import Machine, MachineError
    from motiond.states import CommandRefused
    from telemetry.config import TelemetryConfig
    from telemetry.publisher import open_lcm

    tele = TelemetryConfig.from_table(config.telemetry)
    if args.url:
        from motiond.configkit import Table

        tele = TelemetryConfig.from_table(Table({**config.telemetry.data, "url": args.url}, "--url",
                                                "telemetry"))
    lc = None if args.no_telemetry else open_lcm(tele.url, fallback="memq")
    late = args.late_fault_ms / 1000.0 if args.late_fault_ms is not None else None
    machine = Machine(config, lc=lc, telemetry=tele, late_fault_s=late, interp_settings=settings)
    err = Console(stderr=True, highlight=False)
    out = Console(highlight=False)

    def on_term(*_: object) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, on_term)
    try:
        try:
            machine.start()
            machine.bring_up()
            job = machine.run(path, args.start_line)
        except (MachineError, CommandRefused) as exc:
            raise UserError(str(exc)) from None
        result = None
        try:
            if err.is_terminal and not args.json:
                from rich.progress import (
                    BarColumn,
                    Progress,
                    TaskProgressColumn,
                    TextColumn,
                    TimeElapsedColumn,
                    TimeRemainingColumn,
                )

                with Progress(TextColumn("{task.description}"), BarColumn(),
                              TextColumn("line {task.completed:.0f}/{task.total:.0f}"), TaskProgressColumn(),
                              TimeElapsedColumn(), TimeRemainingColumn(), console=err,
                              transient=True) as progress:
                    task = progress.add_task(path.name, total=max(job.lines_total, 1))
                    result = wait_for_job(machine, job, lambda: progress.update(
                        task, completed=min(job.line, job.lines_total)))
            else:
                result = wait_for_job(machine, job)
        except KeyboardInterrupt:
            return _interrupted(machine, str(path))
        assert result is not None
        if not result.ok:
            print(result.error or "program aborted", file=sys.stderr)
            return 1
        if machine.interp.save_error is not None:
            err = machine.interp.save_error
            print(f"{err.file}: {err.message}", file=sys.stderr)
            return 1
        _settle(machine)
        result.final_actual = tuple(machine.motion.actual)
        if args.json:
            import json

            print(json.dumps(summary_dict(machine, result)))
        else:
            print_summary(machine, result, out)
        return 0
    except KeyboardInterrupt:
        print("canon run: interrupted", file=sys.stderr)
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous)
        machine.shutdown()
