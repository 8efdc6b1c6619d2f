"""``canon sim drives``: the configured CiA 402 drives, simulated, on a python-can bus, until stopped.

All drives share one bus object and one reader thread (udp_multicast loses frames otherwise). The
master (``canon run`` or a test) finds them as it would real drives: boot-up, SDO, PDOs, heartbeat.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from fieldbus.canopen.config import AxisScale


def _indexes(text: str) -> tuple[int, ...]:
    try:
        values = tuple(int(v, 0) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a list of object indexes: {text!r} (e.g. 0x6085,0x60C2)") \
            from None
    if any(not 0x1000 <= v <= 0xFFFF for v in values):
        raise argparse.ArgumentTypeError(f"object indexes are 0x1000 to 0xFFFF: {text!r}")
    return values


def _param(text: str) -> tuple[tuple[int, int], int]:
    try:
        where, value = text.split("=")
        index, _, sub = where.partition(":")
        return (int(index, 0), int(sub, 0) if sub else 0), int(value, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not INDEX[:SUB]=VALUE: {text!r} (e.g. 0x6080=1500)") from None


def _limit(text: str) -> tuple[str, float | None, float | None]:
    try:
        axis, _, span = text.partition("=")
        lo, sep, hi = span.partition(":")
        if not axis or not sep or not (lo.strip() or hi.strip()):
            raise ValueError
        return axis.strip(), float(lo) if lo.strip() else None, float(hi) if hi.strip() else None
    except ValueError:
        raise argparse.ArgumentTypeError(f"not AXIS=MIN:MAX (either may be left out): {text!r} "
                                         "(e.g. y=-5:120 or x=:50)") from None


def _probe(text: str) -> tuple[str, float]:
    try:
        axis, _, where = text.partition("=")
        if not axis.strip():
            raise ValueError
        return axis.strip(), float(where)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not AXIS=POSITION: {text!r} (e.g. z=-3.2)") from None


HOME_SWITCH_HALF_WIDTH = 0.5
"""``--home``: the home switch is active this far (machine units) either side of its position."""


def limit_counts(scale: AxisScale, lo: float | None, hi: float | None) -> tuple[int | None, int | None]:
    """``(negative, positive)`` limit switch positions in the drive's counts for switches at machine
    positions ``lo``/``hi``: with a negative scale (direction -1) the machine's maximum is the drive's
    negative side."""
    lo_c = None if lo is None else scale.to_counts(lo)
    hi_c = None if hi is None else scale.to_counts(hi)
    return (lo_c, hi_c) if scale.scale > 0 else (hi_c, lo_c)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="machine.toml", help="machine configuration file (demo: x y z)")
    parser.add_argument("--interface", help="python-can interface, instead of the file's canopen.interface")
    parser.add_argument("--channel", help="python-can channel, instead of the file's canopen.channel")
    parser.add_argument("--lag-ms", type=float, default=2.0, help="servo lag time constant (default 2)")
    parser.add_argument("--order", type=int, choices=(1, 2), default=1,
                        help="servo dynamics: 1 first-order lag, 2 second-order (default 1)")
    parser.add_argument("--boot-delay-ms", type=float, default=0.0, help="delay of the boot-up message")
    parser.add_argument("--seconds", type=float, default=0.0, help="stop after this long (default: never)")
    parser.add_argument("--tick-ms", type=float, default=2.0,
                        help="the drives' own clock, between SYNCs: heartbeat, event TPDOs, homing, timed "
                             "faults (default 2; slower costs less CPU, e.g. in an emulated machine)")
    parser.add_argument("--rpdo-timeout-syncs", type=int, default=0, metavar="N",
                        help="RPDO deadline monitoring: fault (EMCY 0x8250) after N SYNCs in Operation "
                             "enabled without a target (default 0: off)")
    parser.add_argument("--absent", type=_indexes, default=(), metavar="0xIIII,...",
                        help="objects the drives do not have (SDO abort 0x06020000), e.g. 0x6085,0x60C2")
    parser.add_argument("--param", type=_param, action="append", default=[], metavar="0xIIII[:S]=VALUE",
                        help="a value the drives have instead of their EDS default, e.g. 0x6080=1500 "
                             "(max motor speed, rpm) or 0x608F:1=10000 (encoder counts); repeatable. "
                             "Without it the motor is sized to fit the file's axes")
    parser.add_argument("--limit", type=_limit, action="append", default=[], metavar="AXIS=MIN:MAX",
                        help="limit switches of an axis at these machine positions (0x60FD bits 0/1, from "
                             "the actual position; the drive only reports them), e.g. y=-5:120; repeatable")
    parser.add_argument("--probe", type=_probe, metavar="AXIS=POSITION",
                        help="the probe input of that axis's drive (its touch probe, 0x60B8-0x60BD) is "
                             "active at and below this machine position, e.g. z=-3.2 for a surface at Z-3.2 "
                             "(instead of the file's canopen.axes.<a>.sim_probe_position)")
    parser.add_argument("--home", type=_probe, action="append", default=[], metavar="AXIS=POSITION",
                        help="a home switch of that axis's drive (0x60FD bit 2), active within "
                             f"{HOME_SWITCH_HALF_WIDTH:g} mm of this machine position, for homing by the "
                             "drive (homing = \"cia402\", methods 19-30); repeatable")
    parser.add_argument("--strict", action="store_true",
                        help="take 'enable operation' in Quick stop active at once, during the stop ramp "
                             "(CiA 402 transition 16, as strict drives do)")


def run(args: argparse.Namespace) -> int:
    import signal
    import threading

    from fieldbus.canopen.drive_sim import SimDrive, motor_for
    from fieldbus.canopen.drive_sim_probe import sim_probe
    from motiond.config_canopen import canopen_for_tool

    config, bus = canopen_for_tool(args.config, args.interface, args.channel)
    if args.rpdo_timeout_syncs < 0:
        from motiond.cli import UserError

        raise UserError(f"--rpdo-timeout-syncs {args.rpdo_timeout_syncs}: must not be negative")
    if not 0.5 <= args.tick_ms <= 100.0:
        from motiond.cli import UserError

        raise UserError(f"--tick-ms {args.tick_ms:g}: must be between 0.5 and 100")
    from fieldbus.canopen.config import AxisScale

    switches = {}
    axes = {d.axis: d for d in config.drives}
    for axis, lo, hi in args.limit:
        if axis not in axes:
            from motiond.cli import UserError

            raise UserError(f"--limit {axis}=...: no axis {axis!r} (axes: {', '.join(axes)})")
        try:
            switches[axis] = limit_counts(AxisScale(axes[axis]), lo, hi)
        except OverflowError as exc:
            from motiond.cli import UserError

            raise UserError(f"--limit {axis}=...: {exc}") from None
    named = [("--home", a) for a, _ in args.home]
    if args.probe is not None:
        named.append(("--probe", args.probe[0]))
    for option, axis in named:
        if axis not in axes:
            from motiond.cli import UserError

            raise UserError(f"{option} {axis}=...: no axis {axis!r} (axes: {', '.join(axes)})")
    homes = {a: {"home_switch_counts": AxisScale(axes[a]).to_counts(at),
                 "home_switch_window_counts": round(HOME_SWITCH_HALF_WIDTH * abs(AxisScale(axes[a]).scale))}
             for a, at in args.home}
    drives = [SimDrive(d.node_id, d.eds_path, lag_s=args.lag_ms / 1000.0, order=args.order,
                       boot_delay_s=args.boot_delay_ms / 1000.0, rpdo_timeout_syncs=args.rpdo_timeout_syncs,
                       absent_objects=args.absent,
                       negative_limit_counts=switches.get(d.axis, (None, None))[0],
                       positive_limit_counts=switches.get(d.axis, (None, None))[1],
                       parameters={**motor_for(d, d.eds_path), **dict(args.param)}, **homes.get(d.axis, {}),
                       **sim_probe(d, args.probe[1] if args.probe is not None and args.probe[0] == d.axis
                                   else None))
              for d in config.drives]
    for d in drives:
        d.reenable_during_quick_stop_ramp = args.strict
    if config.spindle is not None:  # [canopen.spindle]: its simulated drive, with the file's inertia
        from fieldbus.canopen.drive_sim_velocity import sim_spindle

        drives.append(sim_spindle(config.spindle, boot_delay_s=args.boot_delay_ms / 1000.0))
    stop = threading.Event()
    # the handlers are given back on the way out: called in-process (canon's own main, a test), a
    # handler left behind that only sets this event swallowed every later Ctrl-C of that process
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        # they stand in for hardware, which answers every SYNC whatever else the PC runs: with a
        # SCHED_FIFO cycle in the file, just below it, level with the master's other threads (the
        # daemon's own simulated drives' process runs one above the cycle: motiond/runtime/sim_drives_proc.py)
        import logging

        from fieldbus.canopen.clock import ranked_below_cycle

        log = logging.getLogger(__name__)
        with ranked_below_cycle(config.realtime_priority, "the simulated drives", log):
            _serve(args, drives, bus, config, stop)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0


def _serve(args: argparse.Namespace, drives: list[Any], bus: Any, config: Any, stop: Any) -> None:
    """Run the simulated drives on ``bus`` until ``stop`` (an Event) or ``--seconds``, then print
    their report."""
    import sys

    from fieldbus.canopen.sim_process import SimBus

    try:
        sims = SimBus(drives, bus, tick_s=args.tick_ms / 1000.0)
    except Exception as exc:  # python-can: no such interface or channel
        from motiond.cli import UserError

        raise UserError(f"cannot open {bus.interface} bus {bus.channel!r}: {exc}") from None
    try:
        names = ", ".join(f"{d.axis}={d.node_id}" for d in config.drives)
        if config.spindle is not None:
            names += f", spindle={config.spindle.node_id}"
        print(f"simulating drives {names} on {bus.interface} {bus.channel}", flush=True)
        stop.wait(args.seconds or None)
    finally:
        sims.close()
    for d in drives:
        print(f"node {d.id}: syncs {d.syncs}, missed setpoints {d.missed_setpoints}, late syncs "
              f"{d.late_syncs}, emcy {[hex(c) for c in d.emcys]}", file=sys.stderr)
