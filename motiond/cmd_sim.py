"""``canon sim drives|io|inject``: simulated hardware as a separate process, and fault injection.

``drives`` runs the configured CiA 402 drives on a python-can bus (``motiond.cmd_sim_drives``);
``io`` runs the Modbus I/O module on loopback or a serial port (``motiond.cmd_sim_io``); ``inject``
faults one running simulated drive over SDO, as a test bench would (``motiond.cmd_sim_inject``).
Each target module has the usual ``add_arguments(parser)`` and ``run(args)``.
"""

from __future__ import annotations

import argparse
import importlib

TARGETS: dict[str, tuple[str, str]] = {
    "drives": ("motiond.cmd_sim_drives", "simulated CiA 402 servo drives on a CAN bus"),
    "io": ("motiond.cmd_sim_io", "simulated Modbus TCP I/O module on 127.0.0.1"),
    "inject": ("motiond.cmd_sim_inject", "make a simulated drive fault with an EMCY, by SDO over the bus"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="target", metavar="TARGET")
    sub.required = True
    for name, (module, help_text) in TARGETS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_sim_module=module)
        try:
            importlib.import_module(module).add_arguments(p)
        except ModuleNotFoundError as exc:
            if exc.name != module:
                raise
            p.set_defaults(_sim_missing=True)


def run(args: argparse.Namespace) -> int:
    if getattr(args, "_sim_missing", False):
        from motiond.cli import UserError

        raise UserError(f"'sim {args.target}' is not available in this build")
    return int(importlib.import_module(args._sim_module).run(args) or 0)
