"""``canon daemon``: the machine as a service, commanded and watched over LCM, until SIGTERM/SIGINT.

It loads and checks the machine file (errors name the file and the key), boots the drives and the
I/O, and waits in E-stop for commands on ``CANON_COMMAND`` (each answered on ``CANON_REPLY``);
status goes out on ``CANON_STATUS`` at ``[telemetry] status_hz`` and events on ``CANON_EVENT``.
``canon ctl`` sends commands, ``canon status`` shows the status.

On SIGTERM or SIGINT: a moving program first comes to rest on its path (jerk-limited), then the
drives are stopped and disabled, the outputs go to their safe values, the parameter file is written,
and the daemon exits 0 (1 when the parameter file could not be written: the message names it and
says why).

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
    parser.add_argument("--program-dir", action="append", metavar="DIR",
                        help="a directory the run command takes programs from (repeatable; default: "
                             "[interpreter] program_path, else 'programs' in the state directory)")
    parser.add_argument("--enable", action="store_true",
                        help="leave E-stop and enable the drives at start (benches, simulations)")
    parser.add_argument("--late-fault-ms", type=float, metavar="MS",
                        help="a cycle starting later than this is a fault (default: 10 cycles, at least "
                             "50 ms; 1 s with simulated drives in the canon process: [motion] "
                             "process \"thread\")")
    parser.add_argument("--feedback-timeout-ms", type=float, metavar="MS",
                        help="a drive sending no TPDO for this long is a fault (default 100; 500 with "
                             "simulated drives in the canon process)")


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


def key_file(tele: Any, state_directory: str | None) -> Path:
    """The command key's file: ``[telemetry] key_file``, else ``command.key`` in the state directory."""
    from telemetry.auth import KEY_FILE_NAME

    if tele.key_file:
        return Path(tele.key_file)
    return state_dir(state_directory) / KEY_FILE_NAME


def load_key(path: Path) -> bytes:
    """The daemon's command key, created at first start (mode 0640); a ``UserError`` says what is wrong."""
    from motiond.cli import UserError
    from telemetry.auth import CommandKeyError, load_or_create_key

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        return load_or_create_key(path)
    except OSError as exc:
        raise UserError(f"{path.parent}: {exc.strerror or exc}") from None
    except CommandKeyError as exc:
        raise UserError(str(exc)) from None


def program_dirs(args_dirs: list[str] | None, config: Any, state_directory: str | None) -> list[Path]:
    """Where ``run`` finds programs: ``--program-dir``, else ``[interpreter] program_path``, else
    ``programs`` in the state directory (created). A ``UserError`` names a missing directory."""
    from motiond.cli import UserError

    if args_dirs:
        dirs = [Path(d) for d in args_dirs]
        for d in dirs:
            if not d.is_dir():
                raise UserError(f"--program-dir {d}: no such directory")
        return dirs
    if config.interpreter.program_path:
        return list(config.interpreter.program_path)
    directory = state_dir(state_directory) / "programs"
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"program directory {directory}: {exc.strerror}") from None
    return [directory]


def start(config: Any, lc: Any, tele: Any, *, key: bytes, var_file: str | os.PathLike[str] | None = None,
          programs: list[Path] | None = None,
          tool_table: str | None = None, late_fault_s: float | None = None,
          modbus_port: int | None = None, feedback_timeout_s: float | None = None) -> tuple[Any, Any]:
    """Start a :class:`motiond.runtime.Machine` and its :class:`telemetry.commands.CommandServer` on
    ``lc``, commands signed with ``key``, ``run`` taking programs from ``programs`` (None: the machine
    file's ``program_path``); returns both (stop the server, then shut the machine down)."""
    from motiond.runtime import Machine
    from telemetry.commands import CommandServer

    machine = Machine(config, lc=lc, telemetry=tele, var_file=var_file, tool_table=tool_table,
                      late_fault_s=late_fault_s, modbus_port=modbus_port,
                      feedback_timeout_s=feedback_timeout_s)
    if programs is not None:
        machine.program_dirs = list(programs)
    machine.start()
    # an E-stop's own socket's thread ranks with the task's stop path (own mode's pipe readers)
    server = CommandServer(lc, machine.handle_command, key=key, url=tele.url,
                           on_security=machine.security_event,
                           estop_thread=getattr(machine.motion, "ranked", None)).start()
    return machine, server


ROOT_WARNING = ("canon daemon: WARNING: running as root. It needs no more than real-time scheduling "
                "(CAP_SYS_NICE): run it as a dedicated user, as examples/canon.service does")


def root_warning() -> str | None:
    """The warning for a daemon run as root (any file it opens, any program it runs: as root)."""
    return ROOT_WARNING if hasattr(os, "geteuid") and os.geteuid() == 0 else None


def stop_then_shutdown(machine: Any) -> bool:
    """SIGTERM or SIGINT: a moving program (or jog) first comes to rest on its path, jerk-limited, then
    the machine shuts down (drives disabled, outputs safe, parameters saved). True when the motion was
    at rest before the drives were disabled."""
    from motiond.runtime import STOP_TIMEOUT_S

    at_rest = machine.stop_on_path(STOP_TIMEOUT_S)
    if not at_rest:
        print(f"canon daemon: the motion was not at rest after {STOP_TIMEOUT_S:g} s: the drives were "
              "disabled while moving", file=sys.stderr, flush=True)
    machine.shutdown()
    return at_rest


def run(args: argparse.Namespace) -> int:
    from motiond.config import load_machine
    from motiond.instance_lock import lock_machine

    config = load_machine(args.config)
    lock = lock_machine(args.config, config, args.state_dir)
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
    from telemetry.url import with_receive_buffer

    warning = root_warning()
    if warning:
        print(warning, file=sys.stderr, flush=True)
    tele = TelemetryConfig.from_table(config.telemetry)
    if args.url:
        tele = TelemetryConfig.from_table(Table({**config.telemetry.data, "url": args.url}, "--url",
                                                "telemetry"))
    try:  # a larger receive buffer: a burst of commands waits in the kernel instead of being dropped
        lc = open_lcm(with_receive_buffer(tele.url))
    except TelemetryUnavailable as exc:
        raise UserError(str(exc)) from None
    var = parameter_file(args.var, config, args.state_dir)
    from gcode_canon.atomicfile import remove_stray_temps

    remove_stray_temps(var)  # of saves interrupted before (a kill, a power cut)
    key_path = key_file(tele, args.state_dir)
    key = load_key(key_path)
    programs = program_dirs(args.program_dir, config, args.state_dir)
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    machine = server = None
    try:
        try:
            machine, server = start(config, lc, tele, key=key, var_file=var, programs=programs,
                                    tool_table=args.tool_table,
                                    late_fault_s=_seconds(args.late_fault_ms),
                                    feedback_timeout_s=_seconds(args.feedback_timeout_ms))
            if args.enable:
                machine.bring_up()
        except (MachineError, CommandRefused) as exc:
            raise UserError(str(exc)) from None
        print(f"canon daemon: machine {config.limits.name!r} up ({machine.n} axes, cycle "
              f"{machine.T * 1e3:g} ms); commands on CANON_COMMAND at {tele.url} "
              f"(signed with the key in {key_path}); "
              f"parameters in {var}; programs from {', '.join(str(p) for p in programs)}",
              file=sys.stderr, flush=True)
        while not stop.wait(0.2):
            pass
        print("canon daemon: stopping", file=sys.stderr, flush=True)
    finally:
        if server is not None:
            server.stop()
        if machine is not None:
            stop_then_shutdown(machine)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if machine is not None and machine.save_error:
        print(f"canon daemon: {machine.save_error}", file=sys.stderr, flush=True)
        return 1
    return 0
