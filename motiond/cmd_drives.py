"""``canon drives scan|dcf``: commissioning tools for the configured CANopen drives.

``scan`` reads what each configured drive says about itself (identity, names, supported modes, its
limits, which of the objects canon uses it has) and compares it with the machine file, as the boot
will: a table per drive (``--json`` too), every mismatch named; exit 1 when a drive does not answer or
does not fit. Read only: SDO uploads, no NMT. With ``[canopen] simulate = true`` (and the demo
machine) the simulated drives are started in this process for the scan.

``dcf`` writes one DCF per drive into ``--out``: the axis's EDS (or DCF) with canon's boot writes as
ParameterValue entries (after the file's own values and the machine file's extra SDO writes), for the
integrator's records and for other CANopen tools. Each file is written whole or not at all.
"""

from __future__ import annotations

import argparse
from typing import Any


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION")
    sub.required = True
    scan = sub.add_parser("scan", help="what each configured drive says, against the configuration",
                          description="what each configured drive says, against the configuration")
    scan.add_argument("--config", metavar="machine.toml", help="machine configuration file (demo: x y z)")
    scan.add_argument("--interface", help="python-can interface, instead of the file's canopen.interface")
    scan.add_argument("--channel", help="python-can channel, instead of the file's canopen.channel")
    scan.add_argument("--timeout", type=float, default=0.5, help="seconds to wait for each SDO answer")
    scan.add_argument("--json", action="store_true", help="machine-readable output")
    dcf = sub.add_parser("dcf", help="a DCF per drive of what canon writes at boot",
                         description="a DCF per drive of what canon writes at boot")
    dcf.add_argument("--config", metavar="machine.toml", help="machine configuration file (demo: x y z)")
    dcf.add_argument("--out", required=True, metavar="DIR", help="existing directory for the DCF files")


def run(args: argparse.Namespace) -> int:
    return _scan(args) if args.action == "scan" else _dcf(args)


def _scan(args: argparse.Namespace) -> int:
    import json
    import logging

    import canopen

    from fieldbus.canopen.scan import scan
    from motiond.cli import UserError
    from motiond.config_canopen import canopen_for_tool

    config, bus = canopen_for_tool(args.config, args.interface, args.channel)
    if not getattr(args, "verbose", 0):
        logging.getLogger("canopen.sdo.client").setLevel(logging.CRITICAL)
    sims = None
    if config.simulate:
        from fieldbus.canopen.drive_sim import SimDrive, motor_for
        from fieldbus.canopen.sim_process import SimBus

        try:
            sims = SimBus([SimDrive(d.node_id, d.eds_path, parameters=motor_for(d, d.eds_path))
                           for d in config.drives], bus)
        except Exception as exc:  # python-can: no such interface or channel
            raise UserError(f"cannot open {bus.interface} bus {bus.channel!r}: {exc}") from None
        _wait_booted(sims)
    network = canopen.Network()
    try:
        network.connect(**bus.bus_kwargs())
    except Exception as exc:
        if sims is not None:
            sims.close()
        raise UserError(f"cannot open {bus.interface} bus {bus.channel!r}: {exc}") from None
    try:
        results = scan(config, network, args.timeout)
    finally:
        network.disconnect()
        if sims is not None:
            sims.close()
    if args.json:
        print(json.dumps([r.as_dict() for r in results], indent=1))
    else:
        _print_tables(config, results)
    return 0 if all(r.answered and not r.mismatches for r in results) else 1


def _wait_booted(sims: Any) -> None:
    import time

    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline and any(d.nmt_state == 0 for d in sims.drives.values()):
        time.sleep(0.01)


def _print_tables(config: Any, results: list[Any]) -> None:
    from rich.console import Console
    from rich.table import Table

    from fieldbus.canopen.master import input_names

    out = Console(highlight=False)
    if not out.is_terminal:  # a file or a pipe: wide enough that the values stay on one line
        out = Console(highlight=False, width=140)
    for r, cfg in zip(results, config.drives, strict=True):
        t = Table(title=f"node {r.node} (axis {r.axis})", title_justify="left")
        t.add_column("object")
        t.add_column("the drive")
        t.add_column("the configuration")
        if not r.answered:
            t.add_row("0x1018 identity", "[red]no answer[/red]", "")
        else:
            for name in ("vendor id", "product code"):
                got, want = r.identity.get(name), r.expected.get(name)
                t.add_row(f"0x1018 {name}", _hex(got), _hex(want))
            for name in ("revision number", "serial number"):
                t.add_row(f"0x1018 {name}", _hex(r.identity.get(name)), "")
            for name, value in r.names.items():
                t.add_row(name, value if value is not None else "—", "")
            lim = r.limits
            modes = lim.get((0x6502, 0))
            t.add_row("0x6502 supported modes", "—" if modes is None else
                      f"0x{modes:08X} (CSP {'yes' if modes & 0x80 else 'NO'})", "CSP")
            per_unit = abs(cfg.counts_per_unit)
            rpm = lim.get((0x6080, 0))
            t.add_row("0x6080 max motor speed", "—" if rpm is None else f"{rpm} rpm",
                      f"max_velocity {cfg.max_velocity:g} = {cfg.max_velocity * per_unit:,.0f} counts/s")
            inc, revs = lim.get((0x608F, 1)), lim.get((0x608F, 2))
            t.add_row("0x608F encoder", "—" if inc is None else f"{inc} counts / {revs} rev",
                      "" if cfg.counts_per_revolution is None else f"{cfg.counts_per_revolution} counts/rev")
            acc = "" if cfg.max_acceleration is None else (
                f"max_acceleration {cfg.max_acceleration:g} = {cfg.max_acceleration * per_unit:,.0f} "
                "counts/s²")
            for index, name in ((0x60C5, "max acceleration"), (0x60C6, "max deceleration")):
                v = lim.get((index, 0))
                t.add_row(f"0x{index:04X} {name}", "—" if v is None else f"{v:,} counts/s²", acc)
            lo, hi = lim.get((0x607D, 1)), lim.get((0x607D, 2))
            soft = "" if cfg.min_position is None or cfg.max_position is None else \
                f"{cfg.min_position:g} to {cfg.max_position:g}"
            t.add_row("0x607D position limits", "—" if lo is None else f"{lo:,} to {hi:,}", soft)
            inputs = r.digital_inputs
            t.add_row("0x60FD digital inputs", "—" if inputs is None else
                      f"yes: 0x{inputs:08X} ({', '.join(input_names(inputs)) or 'none active'})",
                      "limit and home switches")
            t.add_row("0x60B8-0x60BD touch probes", ", ".join(str(n) for n in r.touch_probes) or "—",
                      f"touch_probe = {cfg.touch_probe}" if cfg.touch_probe else "")
            t.add_row("optional objects absent",
                      ", ".join(f"0x{i:04X}" for i in r.optional_absent) or "none", "")
        out.print(t)
        for m in r.mismatches:
            out.print(f"  [red]mismatch:[/red] node {r.node} (axis {r.axis}): {m}", soft_wrap=True)
        for n in r.notes:
            out.print(f"  [yellow]note:[/yellow] node {r.node} (axis {r.axis}): {n}", soft_wrap=True)
        if r.answered and not r.mismatches:
            out.print(f"  node {r.node} (axis {r.axis}): fits the configuration")
        out.print()


def _hex(v: int | None) -> str:
    return "—" if v is None else f"0x{v:08X}"


def _dcf(args: argparse.Namespace) -> int:
    import io
    from pathlib import Path

    import canopen

    from fieldbus.canopen.commissioning import boot_writes
    from gcode_canon.atomicfile import atomic_write_text
    from motiond.cli import UserError
    from motiond.config_canopen import canopen_for_tool

    out = Path(args.out)
    if not out.is_dir():
        raise UserError(f"--out {args.out}: no such directory")
    config, _bus = canopen_for_tool(args.config)
    written = []
    for cfg in config.drives:
        od = canopen.import_od(cfg.eds_path, cfg.node_id)
        writes = [(where, index, sub, value) for index, sub, _c, value, where in cfg.sdo]
        writes += [(what, index, sub, value) for what, index, sub, _c, value in boot_writes(config, cfg)]
        for what, index, sub, value in writes:
            try:
                obj = od[index]
                var = obj if isinstance(obj, canopen.objectdictionary.ODVariable) else obj[sub]
            except KeyError:
                raise UserError(f"{cfg.eds_path}: has no object 0x{index:04X}:{sub:02X} ({what}), which "
                                f"canon writes at boot to node {cfg.node_id} (axis {cfg.axis})") from None
            var.value = value
        buf = io.StringIO()
        canopen.export_od(od, buf, "dcf")
        path = out / f"{cfg.axis}-node{cfg.node_id}.dcf"
        try:
            atomic_write_text(path, buf.getvalue())
        except OSError as exc:
            raise UserError(f"{path}: {exc.strerror or exc}") from None
        written.append(path)
    for p in written:
        print(p)
    return 0
