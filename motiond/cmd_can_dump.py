"""``canon can-dump``: watch a CAN bus with every CANopen frame named and decoded.

``canon can-dump --config machine.toml`` listens on the file's ``[canopen]`` bus; ``--interface`` and
``--channel`` choose another (``socketcan``/``vcan0``, ``udp_multicast``/``239.74.163.1`` ...). One line
per frame: time, COB-ID, name (SYNC, RPDO1 node 2 ...), data, meaning. ``python -m can.viewer`` shows
raw frames too (see docs/canopen.md).
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="machine.toml", help="machine configuration file")
    parser.add_argument("--interface", help="python-can interface (default: the file's, else virtual)")
    parser.add_argument("--channel", help="python-can channel (default: the file's, else canon)")
    parser.add_argument("--count", type=int, default=0, help="stop after this many frames")
    parser.add_argument("--seconds", type=float, default=0.0, help="stop after this long")
    parser.add_argument("--no-sync", action="store_true", help="hide SYNC, PDO and heartbeat frames")


def run(args: argparse.Namespace) -> int:
    import time

    from fieldbus.canopen.busopen import open_bus
    from fieldbus.canopen.dump import describe
    from motiond.cli import UserError
    from motiond.config_canopen import canopen_for_tool

    config, bus_cfg = canopen_for_tool(args.config, args.interface, args.channel)
    layout = config.layout
    try:
        bus = open_bus(bus_cfg)
    except Exception as exc:  # python-can: unknown interface, no such device, no permission
        raise UserError(f"cannot open {bus_cfg.interface} bus {bus_cfg.channel!r}: {exc}") from None
    end = time.monotonic() + args.seconds if args.seconds else None
    n = 0
    t0: float | None = None
    try:
        while (not args.count or n < args.count) and (end is None or time.monotonic() < end):
            msg = bus.recv(timeout=0.2)
            if msg is None or msg.is_error_frame:
                if msg is not None:
                    print(f"error frame 0x{msg.arbitration_id:X} {msg.data.hex(' ')}", flush=True)
                continue
            cob = msg.arbitration_id
            if args.no_sync and (cob == 0x80 or 0x180 <= cob < 0x580 or 0x700 < cob < 0x780):
                continue
            t0 = msg.timestamp if t0 is None else t0
            line = describe(cob, bytes(msg.data), layout)
            print(f"{msg.timestamp - t0:10.6f}  {cob:03X}  {line}", flush=True)
            n += 1
    except KeyboardInterrupt:
        pass
    finally:
        bus.shutdown()
    return 0
