"""``canon daemon``: the machine as a service, commanded and watched over LCM, until SIGTERM/SIGINT.

It loads and checks the machine file (errors name the file and the key), boots the drives and the
I/O, and waits in E-stop for commands on ``CANON_COMMAND`` (each answered on ``CANON_REPLY``);
status goes out on ``CANON_STATUS`` at ``[telemetry] status_hz`` and events on ``CANON_EVENT``.
``canon ctl`` sends commands, ``canon status`` shows the status.

On SIGTERM or SIGINT: the program is cancelled, the drives are stopped and disabled, the outputs go
to their safe values, the parameter file is written, and the daemon exits 0.

The parameter file is ``--var``, else the configuration's ``[interpreter] var_file``, else
``<state dir>/<machine name>.var``; the state directory is
``--state-dir``, else ``$STATE_DIRECTORY`` (systemd's ``StateDirectory=``), else
``$XDG_STATE_HOME/canon``, else ``~/.local/state/canon``. A lock there (:mod:`motiond.instance_lock`)
refuses a second daemon or ``canon run`` for the same machine file, naming the first one's PID.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
from pathlib import Path
from typing import Any


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="machine.toml", help="machine configuration (default: the demo)")
    parser.add_argument("--tool-table", metavar="FILE", help="LinuxCNC-format tool table")
    parser.add_argument("--var", metavar="FILE", help="parameter file (default: in the state directory)")
    parser.add_argument("--state-dir", metavar="DIR",
                        help="where the parameter file lives by default, and the machine's lock (one run "
                             "or daemon per machine file)")
    parser.add_argument("--url", help="LCM URL (default: [telemetry] url)")
    parser.add_argument("--enable", action="store_true",
                        help="leave E-stop and enable the drives at start (benches, simulations)")
    parser.add_argument("--late-fault-ms", type=float, metavar="MS",
                        help="a cycle starting later than this is a fault (default: 10 cycles, at least "
                             "50 ms; 1 s with simulated drives)")
    parser.add_argument("--feedback-timeout-ms", type=float, metavar="MS",
                        help="a drive sending no TPDO for this long is a fault (default 100; 500 simulated)")


def _seconds(ms: float | None) -> float | None:
    return ms / 1000.0 if ms else None


def state_dir(arg: str | None = None) -> Path:
    if arg:
        return Path(arg)
    if os.environ.get("STATE_DIRECTORY"):
        return Path(os.environ["STATE_DIRECTORY"].split(":")[0])
    base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base) / "canon"


def default_var_file(machine_name: str, directory: Path) -> Path:
    slug = re.sub(r"[^A-Za-z0-9._-]+", "-", machine_name).strip("-") or "machine"
    return directory / f"{slug}.var"


def parameter_file(var: str | None, config: Any, state_directory: str | None) -> str | Path:
    """Where the daemon keeps its parameters: ``--var``, else the configuration's ``[interpreter]
    var_file``, else a file named after the machine in the state directory (created if needed)."""
    if var is not None:
        return var
    if config.interpreter.var_file is not None:
        return config.interpreter.var_file
    directory = state_dir(state_directory)
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        from motiond.cli import UserError

        raise UserError(f"state directory {directory}: {exc.strerror}") from None
    return default_var_file(config.limits.name, directory)


def start(config: Any, lc: Any, tele: Any, *, var_file: str | os.PathLike[str] | None = None,
          tool_table: str | None = None, late_fault_s: float | None = None,
          modbus_port: int | None = None, feedback_timeout_s: float | None = None) -> tuple[Any, Any]:
    """Start a :class:`motiond.runtime.Machine` and its :class:`telemetry.commands.CommandServer` on
    ``lc``; returns both (stop the server, then shut the machine down)."""
    from motiond.runtime import Machine
    from telemetry.commands import CommandServer

    machine = Machine(config, lc=lc, telemetry=tele, var_file=var_file, tool_table=tool_table,
                      late_fault_s=late_fault_s, modbus_port=modbus_port,
                      feedback_timeout_s=feedback_timeout_s)
    machine.start()
    server = CommandServer(lc, machine.handle_command, url=tele.url, token=tele.token).start()
    return machine, server


def run(args: argparse.Namespace) -> int:
    from motiond.config import load_machine
    from motiond.instance_lock import lock_machine

    config = load_machine(args.config)
    lock = lock_machine(args.config, config.limits.name, args.state_dir)
    try:
        return _run_locked(args, config)
    finally:
        lock.release()


def _run_locked(args: argparse.Namespace, config: Any) -> int:
    import signal
    import threading

    from motiond.cli import UserError
    from motiond.configkit import Table
    from motiond.runtime import MachineError
    from motiond.states import CommandRefused
    from telemetry.config import TelemetryConfig
    from telemetry.publisher import TelemetryUnavailable, open_lcm

    tele = TelemetryConfig.from_table(config.telemetry)
    if args.url:
        tele = TelemetryConfig.from_table(Table({**config.telemetry.data, "url": args.url}, "--url",
                                                "telemetry"))
    try:
        lc = open_lcm(tele.url)
    except TelemetryUnavailable as exc:
        raise UserError(str(exc)) from None
    var = parameter_file(args.var, config, args.state_dir)
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    machine = server = None
    try:
        try:
            machine, server = start(config, lc, tele, var_file=var, tool_table=args.tool_table,
                                    late_fault_s=_seconds(args.late_fault_ms),
                                    feedback_timeout_s=_seconds(args.feedback_timeout_ms))
            if args.enable:
                machine.bring_up()
        except (MachineError, CommandRefused) as exc:
            raise UserError(str(exc)) from None
        print(f"canon daemon: machine {config.limits.name!r} up ({machine.n} axes, cycle "
              f"{machine.T * 1e3:g} ms); commands on CANON_COMMAND at {tele.url}; parameters in {var}",
              file=sys.stderr, flush=True)
        while not stop.wait(0.2):
            pass
        print("canon daemon: stopping", file=sys.stderr, flush=True)
    finally:
        if server is not None:
            server.stop()
        if machine is not None:
            machine.shutdown()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0
