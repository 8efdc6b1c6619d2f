"""The ``canon`` command line.

Each sub-command lives in its own module ``motiond.cmd_<name>`` with two functions:
``add_arguments(parser)`` and ``run(args) -> int``. They are imported only when used, so
``canon check`` does not pay for importing the fieldbus stack.

User mistakes (bad G-code, a bad configuration, a missing file) are printed to stderr as one line,
``FILE:LINE: message`` where there is a line, and give exit status 1; no traceback.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import sys
from collections.abc import Sequence
from pathlib import Path

from gcode_canon.errors import GCodeError
from motiond.configkit import ConfigError, special_file
from motiond.logsetup import setup_logging

# name -> (module, one-line help). Add a line here for a new sub-command.
COMMANDS: dict[str, tuple[str, str]] = {
    "check": ("motiond.cmd_check", "interpret a program without a machine and print its canonical commands"),
    "plan": ("motiond.cmd_plan", "plan a program without a machine: setpoints checked against the limits"),
    "config": ("motiond.cmd_config", "check a machine file offline (every table) and print the machine"),
    "run": ("motiond.cmd_run", "run a program on the machine (the built-in simulated demo by default)"),
    "daemon": ("motiond.cmd_daemon", "run the machine as a daemon, commanded and watched over LCM"),
    "sim": ("motiond.cmd_sim", "run simulated drives or I/O as a separate process, or inject a drive fault"),
    "drives": ("motiond.cmd_drives", "scan the CANopen drives against the configuration, or write DCFs"),
    "can-dump": ("motiond.cmd_can_dump", "watch a CAN bus with CANopen frames named and decoded"),
    "spy": ("motiond.cmd_spy", "watch the machine's LCM traffic in lcm-spy, canon's types decoded"),
    "log": ("motiond.cmd_log", "record the machine's LCM traffic into a log file (lcm-logger)"),
    "ctl": ("motiond.cmd_ctl", "send one command to the running daemon over LCM and print its reply"),
    "status": ("motiond.cmd_status", "watch the machine's status and events from LCM (live table or --once)"),
}


class UserError(Exception):
    """A mistake the user can fix (wrong option, missing file): printed as one line, exit 1."""


def program_file(name: str) -> Path:
    """The G-code program named on the command line, or a :class:`UserError` that says what is wrong
    with it: missing, a directory, not a regular file (a device such as /dev/null, a pipe), unreadable."""
    import stat

    path = Path(name)
    try:
        st = path.stat()
    except FileNotFoundError:
        raise UserError(f"{name}: no such file") from None
    except OSError as exc:
        raise UserError(f"{name}: {exc.strerror}") from None
    if stat.S_ISDIR(st.st_mode):
        raise UserError(f"{name}: is a directory, not a G-code program")
    kind = special_file(st.st_mode)
    if kind is not None:
        raise UserError(f"{name}: is {kind} file, not a G-code program (a regular file is needed)")
    try:
        with path.open("rb"):
            pass
    except OSError as exc:
        raise UserError(f"{name}: cannot read: {exc.strerror or exc}") from None
    return path


def add_common(parser: argparse.ArgumentParser, *, program: bool = True) -> None:
    """Options that mean the same for check, plan and run."""
    parser.add_argument("--config", metavar="machine.toml", help="machine configuration file")
    parser.add_argument("--tool-table", metavar="FILE", help="LinuxCNC-format tool table (as rs274 -t)")
    parser.add_argument("--var", metavar="FILE", help="parameter file (as rs274 -v)")
    parser.add_argument("--json", action="store_true", help="machine-readable output")
    if program:
        parser.add_argument("file", metavar="FILE.ngc", help="G-code program")


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("canon")
    except PackageNotFoundError:
        return "(not installed: version unknown)"


class _VersionAction(argparse.Action):
    """``--version``, looked up only when asked for (importlib.metadata takes a tenth of canon check's
    start-up)."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:  # type: ignore[override]
        print(f"canon {_version()}")  # on stdout, as argparse's own version action
        parser.exit()


def build_parser(only: str | None = None, *, others: bool = True) -> argparse.ArgumentParser:
    """The whole command line; with ``only`` (the sub-command the command line names), the other
    sub-commands' modules are not imported (their parsers hold only their help line): ``canon check``
    starts without importing the fieldbus and LCM stacks. With ``others`` false as well, the other
    sub-commands are left out (for a command line that cannot print the list of sub-commands,
    :func:`_lists_no_commands`): their eleven parsers cost ``canon check`` about 3 ms of its start-up."""
    parser = argparse.ArgumentParser(prog="canon", description="canon: G-code to CiA 402 servo drives")
    parser.add_argument("--version", action=_VersionAction, nargs=0, help="show the version and exit")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="more log output: -v canon's debug messages, -vv the libraries' too "
                             "(default: canon's at INFO, pymodbus/canopen/python-can at WARNING)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name, (module, help_text) in COMMANDS.items():
        if only is not None and name != only:
            if others and importlib.util.find_spec(module) is not None:  # one still being built: left out
                p = sub.add_parser(name, help=help_text, description=help_text)
                p.set_defaults(_module=module)
            continue
        try:
            mod = importlib.import_module(module)
        except ModuleNotFoundError as exc:
            if exc.name != module:
                raise
            continue  # a sub-command still being built in this tree
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module)
        mod.add_arguments(p)
    return parser


def _named_command(argv: Sequence[str]) -> str | None:
    """The sub-command the arguments name (the first argument that is not an option), if known."""
    for arg in argv:
        if not arg.startswith("-"):
            return arg if arg in COMMANDS else None
    return None


def _lists_no_commands(argv: Sequence[str]) -> bool:
    """True when nothing before the sub-command can make the top-level parser print its help (the list
    of sub-commands): every argument there is ``--verbose`` or ``-v``, ``-vv`` ... (``-h``, ``--he``
    or ``-vh`` would print it; anything else is left to the whole parser)."""
    for arg in argv:
        if not arg.startswith("-"):
            return True
        if arg != "--verbose" and (len(arg) < 2 or arg.strip("v") != "-"):  # ("-" is an argument)
            return False
    return True


def main(argv: Sequence[str] | None = None) -> int:
    words = sys.argv[1:] if argv is None else argv
    named = _named_command(words)
    parser = build_parser(named, others=named is None or not _lists_no_commands(words))
    args = parser.parse_args(argv)
    setup_logging(args.verbose)
    module = importlib.import_module(args._module)
    try:
        return int(module.run(args) or 0)
    except (GCodeError, ConfigError, UserError) as exc:
        print(f"canon {args.command}: {exc}" if isinstance(exc, UserError) else str(exc), file=sys.stderr)
        return 1
    except BrokenPipeError:
        # `canon check big.ngc | head`: not an error.
        sys.stderr.close()
        return 0
    except KeyboardInterrupt:
        print("canon: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    # `python -m motiond.cli`: run the copy imported as motiond.cli, so that sub-commands which
    # raise motiond.cli.UserError are caught as the same class.
    from motiond.cli import main as _main

    sys.exit(_main())
