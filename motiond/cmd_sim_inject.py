"""``canon sim inject``: make a simulated drive (``canon sim drives``, another process) fault with an EMCY,
or work its local quick-stop input (``--quick-stop on|off``, sub 3 of the same object).

What a test bench does on a real bus: an SDO write from a separate CANopen client, here to the
simulated drive's simulation-only object 0x2F00 (sub 2 the delay in ms, then sub 1 the EMCY code;
see docs/canopen.md). The drive enters Fault, sends the EMCY and shows it in its statusword, as its
in-process ``SimDrive.inject_fault`` does. This client only does SDO to that one node: no NMT, no
SYNC, nothing else that would disturb a master streaming on the bus (the master does no SDO while it
streams, so their SDO channels do not clash).
"""

from __future__ import annotations

import argparse


def _code(text: str) -> int:
    try:
        value = int(text, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r} (e.g. 0x7300)") from None
    if not 0 <= value <= 0xFFFF:
        raise argparse.ArgumentTypeError(f"an EMCY code is 16 bits: {text!r}")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="machine.toml", help="machine configuration file (demo: x y z)")
    parser.add_argument("--interface", help="python-can interface, instead of the file's canopen.interface")
    parser.add_argument("--channel", help="python-can channel, instead of the file's canopen.channel")
    who = parser.add_mutually_exclusive_group(required=True)
    who.add_argument("--axis", help="the axis whose drive faults (its node id from the configuration)")
    who.add_argument("--node", type=int, help="the drive's node id")
    what = parser.add_mutually_exclusive_group(required=True)
    what.add_argument("--emcy", type=_code, metavar="CODE",
                      help="EMCY error code, e.g. 0x7300; 0 cancels faults still waiting for --delay-ms")
    what.add_argument("--quick-stop", choices=("on", "off"),
                      help="the drive's local quick-stop input: on (the drive stops itself), off (released)")
    parser.add_argument("--delay-ms", type=int, default=0, help="the drive faults this long after the write")
    parser.add_argument("--timeout", type=float, default=1.0, help="seconds to wait for each SDO answer")


def run(args: argparse.Namespace) -> int:
    import logging
    import struct
    import time

    import canopen
    from canopen.sdo import SdoAbortedError, SdoCommunicationError

    from fieldbus.canopen.drive_sim import (
        SIM_INJECT,
        SIM_INJECT_CODE,
        SIM_INJECT_DELAY_MS,
        SIM_QUICK_STOP_INPUT,
    )
    from motiond.cli import UserError
    from motiond.config_canopen import canopen_for_tool

    source = args.config or "the demo machine"
    config, bus = canopen_for_tool(args.config, args.interface, args.channel)
    if args.axis is not None:
        drive = next((d for d in config.drives if d.axis == args.axis), None)
        if drive is None:
            axes = ", ".join(d.axis for d in config.drives)
            raise UserError(f"{source}: no drive for axis {args.axis!r} in canopen.axes (axes: {axes})")
        node_id, name = drive.node_id, f"node {drive.node_id} (axis {drive.axis})"
    else:
        if not 1 <= args.node <= 127:
            raise UserError(f"--node {args.node}: a node id is 1 to 127")
        node_id, name = args.node, f"node {args.node}"
    if args.delay_ms < 0:
        raise UserError(f"--delay-ms {args.delay_ms}: must not be negative")

    if not getattr(args, "verbose", 0):  # its retry warnings; the error below says it in words
        logging.getLogger("canopen.sdo.client").setLevel(logging.CRITICAL)
    network = canopen.Network()
    try:
        network.connect(**bus.bus_kwargs())
    except Exception as exc:  # python-can: no such interface or channel
        raise UserError(f"cannot open {bus.interface} bus {bus.channel!r}: {exc}") from None
    try:
        # an empty dictionary: raw SDO to the object, which the drive's own dictionary checks
        node = network.add_node(canopen.RemoteNode(node_id, canopen.ObjectDictionary()))
        node.sdo.RESPONSE_TIMEOUT = args.timeout
        node.sdo.MAX_RETRIES = 3  # udp_multicast may lose a frame; a repeated write only faults again
        try:
            if args.quick_stop is not None:
                node.sdo.download(SIM_INJECT, SIM_QUICK_STOP_INPUT, bytes([args.quick_stop == "on"]))
            else:
                node.sdo.download(SIM_INJECT, SIM_INJECT_DELAY_MS, struct.pack("<I", args.delay_ms))
                node.sdo.download(SIM_INJECT, SIM_INJECT_CODE, struct.pack("<H", args.emcy))
        except SdoAbortedError as exc:
            raise UserError(f"{name}: SDO abort 0x{exc.code:08X} writing 0x{SIM_INJECT:04X} ({exc}); "
                            "only canon's simulated drives have this object") from None
        except SdoCommunicationError as exc:
            raise UserError(f"{name}: no SDO answer on {bus.interface} {bus.channel!r} ({exc}); "
                            "is 'canon sim drives' running on this bus?") from None
        if args.quick_stop is not None:
            print(f"{name}: local quick-stop input {args.quick_stop}", flush=True)
            return 0
        if args.emcy == 0:
            print(f"{name}: pending injected faults cancelled", flush=True)
            return 0
        deadline = time.monotonic() + args.delay_ms / 1000.0 + args.timeout
        while time.monotonic() < deadline and not any(e.code == args.emcy for e in node.emcy.log):
            time.sleep(0.01)
        seen = any(e.code == args.emcy for e in node.emcy.log)
        print(f"{name}: EMCY 0x{args.emcy:04X} injected"
              + (f" with a delay of {args.delay_ms} ms" if args.delay_ms else "")
              + ("; the drive sent it" if seen else "; its EMCY frame was not seen (lost on the bus?)"),
              flush=True)
        return 0
    finally:
        network.disconnect()
