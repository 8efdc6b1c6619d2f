"""``canon config check [--config FILE]``: the machine file checked offline, every table.

Nothing is opened but files: the axes, the interpreter's paths and tool table, ``[canopen]`` (node
ids, the drives' 32-bit ranges in counts, the EDS files, the bus budget the master would refuse),
``[modbus]`` (devices, every I/O binding, addresses) and ``[telemetry]``. A valid file prints the
machine it describes as tables and exits 0; otherwise each bad key is named on its own line
(``FILE: KEY: what is wrong``, at most one per section) and the exit status is 1.
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="config_command", metavar="ACTION")
    sub.required = True
    what = "check every table of the machine file offline and print the machine"
    check = sub.add_parser("check", help=what, description=what)
    check.add_argument("--config", metavar="machine.toml",
                       help="machine configuration file (default: the demo machine)")


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    from motiond.config_check import describe, validate_machine

    checked = validate_machine(args.config)  # ConfigErrors: printed one per line by motiond.cli
    console = Console(highlight=False)
    for part in describe(checked):
        console.print(part)
    console.print(f"{args.config or 'demo machine'}: ok")
    return 0
