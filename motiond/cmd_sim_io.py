"""``canon sim io``: run the simulated Modbus I/O module(s) until SIGINT/SIGTERM.

Without ``--config`` it serves the demo machine's module by Modbus TCP on 127.0.0.1:5020; with a
machine file, one module per ``[[modbus.devices]]`` with ``simulate = true`` (each on its configured
port and unit). ``--port`` overrides the port when there is one module (0 picks a free one; the line
``listening on 127.0.0.1:PORT`` says which).

``--serial PORT`` serves one module by Modbus RTU on that serial port instead (the other end of a
null-modem cable or of a pty pair, whose first end the machine file's device names in ``serial``):
the demo module's layout without ``--config``; with it, the file's one device that has ``serial``
(its unit, line settings and map). ``--baudrate N`` overrides the baud rate. The module is wired as
the file's ``[io]`` map says (the demo machine's without ``--config``: :mod:`motiond.sim_wiring`):
the E-stop chain and the door closed, the spindle at speed a while after it is switched on.
``--script FILE`` gives the inputs a behaviour:

```toml
[[rule]]                 # 0.3 s after coil 0 is written on, discrete input 0 goes on
on = "coil"              # coil or holding_register
address = 0
equals = 1
after_s = 0.3
set = "discrete_input"   # coil, discrete_input, holding_register, input_register
set_address = 0
value = 1
# device = "io"          # optional: only that module

[[at]]                   # 1 s after start, input register 2 becomes 1234
after_s = 1.0
set = "input_register"
set_address = 2
value = 1234
```
"""

from __future__ import annotations

import argparse
import contextlib
import queue
import signal
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # heavy imports stay inside run(): `canon check` builds this parser too
    from fieldbus.modbus.config import ModbusConfig
    from fieldbus.modbus.sim import Rule


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="machine.toml", help="machine file (default: the demo machine)")
    parser.add_argument("--port", type=int, metavar="N", help="TCP port (one module only; 0: any free port)")
    parser.add_argument("--serial", metavar="PORT", help="serve Modbus RTU on this serial port, not TCP")
    parser.add_argument("--baudrate", type=int, metavar="N", help="with --serial: baud rate (default: the "
                        "device's in --config, else 19200)")
    parser.add_argument("--script", metavar="FILE", help="TOML file of rules and timed input changes")
    parser.add_argument("--size", type=int, default=256, metavar="N",
                        help="entries in each table (coils, inputs, registers); default 256")
    parser.add_argument("--log-writes", action="store_true", help="print every write the module receives")


def run(args: argparse.Namespace) -> int:
    # Every line goes through one printer thread: whole lines in order, and a reader that falls
    # behind on the pipe never stalls a module's event loop (which logs its writes).
    lines: queue.SimpleQueue[str | None] = queue.SimpleQueue()

    def printer() -> None:
        while (text := lines.get()) is not None:
            with contextlib.suppress(BrokenPipeError, ValueError):  # reader gone: keep draining
                print(text, flush=True)

    say = lines.put
    printer_thread = threading.Thread(target=printer, name="sim-io-log", daemon=True)
    printer_thread.start()
    try:
        return _serve(args, say)
    finally:
        lines.put(None)
        printer_thread.join(5.0)


def _serve(args: argparse.Namespace, say: Callable[[str], None]) -> int:
    from fieldbus.modbus.sim import SimIoModule, size_for
    from motiond.cli import UserError
    from motiond.config_io import IoMap, demo_io, io_for, modbus_with_io
    from motiond.config_modbus import demo_modbus, read_modbus
    from motiond.configkit import Table, load_toml
    from motiond.sim_wiring import apply, wiring_for

    cfg: ModbusConfig | None = None
    io = IoMap()
    if args.config:
        raw = load_toml(args.config)
        cfg = read_modbus(Table(raw, args.config))
        if cfg is not None and "io" in raw:  # the module answers like the machine's wiring (sim_wiring)
            from motiond.config import load_machine

            io = io_for(load_machine(args.config), cfg)
            cfg = modbus_with_io(cfg, io)
        if cfg is None:
            raise UserError(f"{args.config}: no [[modbus.devices]] to simulate")
        if args.serial:
            devices = [d for d in cfg.devices if d.serial]
            if len(devices) != 1:
                raise UserError(f"{args.config}: --serial simulates the one [[modbus.devices]] that has "
                                f"serial = ...; the file has {len(devices)}")
        else:
            devices = _devices_to_serve(cfg, args.config, say)
    else:
        devices = list(demo_modbus().devices)
        io = demo_io(demo_modbus())
    wiring = wiring_for(io)
    if args.serial is not None:
        if not args.serial.strip():
            raise UserError("--serial needs a port, e.g. /dev/ttyUSB0")
        if args.port is not None:
            raise UserError("--port is for Modbus TCP; with --serial there is no port number")
    if args.baudrate is not None:
        if args.serial is None:
            raise UserError("--baudrate needs --serial")
        if args.baudrate <= 0:
            raise UserError(f"--baudrate must be > 0, got {args.baudrate}")
    if args.port is not None:
        if len(devices) != 1:
            raise UserError("--port needs exactly one simulated device")
        if not 0 <= args.port <= 65535:
            raise UserError(f"--port must be 0..65535, got {args.port}")
    if not 1 <= args.size <= 4096:
        raise UserError(f"--size must be 1..4096, got {args.size}")
    rules, timed = _read_script(args.script) if args.script else ([], [])
    for _dev, rule in rules:
        if max(rule.when_address, rule.set_address) >= args.size:
            raise UserError(f"{args.script}: a rule uses an address beyond --size {args.size}")
    for _dev, item in timed:
        if item[2] >= args.size:
            raise UserError(f"{args.script}: an [[at]] entry uses an address beyond --size {args.size}")

    modules: list[tuple[str, SimIoModule]] = []
    for dev in devices:
        port = args.port if args.port is not None else dev.port
        mine = [r for name, r in rules if name in ("", dev.name)]
        size = size_for(cfg, dev.name, args.size) if cfg is not None else args.size
        if args.serial:
            baud = args.baudrate if args.baudrate is not None else dev.baudrate
            mod = SimIoModule(unit=dev.unit, size=size, rules=mine, serial=args.serial, baudrate=baud,
                              parity=dev.parity, stopbits=dev.stopbits, bytesize=dev.bytesize)
        else:
            mod = SimIoModule(host="127.0.0.1", port=port, unit=dev.unit, size=size, rules=mine)
        apply(mod, wiring.get(dev.name))
        modules.append((dev.name, mod))
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        for name, mod in modules:
            if args.log_writes:  # one flushed line per write, for tests reading a pipe
                mod.add_listener(lambda rec, name=name: say(
                    f"{rec.t:.6f} {name}: write {rec.table} {rec.address} = "
                    f"{' '.join(map(str, rec.values))}"))
            try:
                mod.start()
            except OSError as exc:
                raise UserError(str(exc)) from None
            for dev_name, (after_s, table, address, value) in timed:
                if dev_name in ("", name):
                    mod.schedule(after_s, table, address, value)
            line = (f" (Modbus RTU, {mod.baudrate} baud, {mod.bytesize}{mod.parity}{mod.stopbits})"
                    if mod.serial else "")
            say(f"simulated I/O module {name!r} (unit {mod.unit}) listening on {mod.where}{line}")
        say("stop with Ctrl-C")
        while not stop.wait(0.5):
            pass
    finally:
        for _name, mod in modules:
            mod.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    say("stopped")
    return 0


_LOOPBACK = ("127.0.0.1", "localhost", "::1")


def _devices_to_serve(cfg: ModbusConfig, path: str, say: Callable[[str], None]) -> list[Any]:
    """The Modbus TCP devices of the file that a daemon would connect to on this host and that nobody
    else serves: ``simulate = false`` on a loopback host. A file with none of those: its ``simulate =
    true`` devices (which a daemon with this file serves itself: said in a note)."""
    from motiond.cli import UserError

    tcp = [d for d in cfg.devices if not d.serial]
    needed = [d for d in tcp if not d.simulate and d.host in _LOOPBACK]
    if needed:
        return needed
    simulated = [d for d in tcp if d.simulate]
    if simulated:
        names = ", ".join(repr(d.name) for d in simulated)
        say(f"note: a daemon with {path} serves {names} itself (simulate = true): this module is for "
            "other clients, or for a daemon whose file says simulate = false")
        return simulated
    where = ", ".join(f"{d.name!r} at {d.serial or f'{d.host}:{d.port}'}" for d in cfg.devices)
    raise UserError(f"{path}: no [[modbus.devices]] to serve on this host ({where}): a device is served "
                    "when its host is 127.0.0.1 or localhost (or with --serial, the one with serial = ...)")


def _read_script(path: str) -> tuple[list[tuple[str, Rule]], list[tuple[str, tuple[float, str, int, int]]]]:
    """Rules and timed changes from a script file; errors name the file and the key."""
    from fieldbus.modbus.sim import TABLES, WRITABLE, Rule
    from motiond.configkit import Table, load_toml, non_negative, one_of

    root = Table(load_toml(path), path)
    rules: list[tuple[str, Rule]] = []
    timed: list[tuple[str, tuple[float, str, int, int]]] = []
    for t in root.array_of_tables("rule"):
        rule = Rule(
            when_table=t.get("on", str, check=one_of(*WRITABLE)),
            when_address=t.get("address", int, check=_addr),
            equals=int(t.get("equals", int)),
            after_s=t.get("after_s", float, 0.0, check=non_negative),
            set_table=t.get("set", str, check=one_of(*TABLES)),
            set_address=t.get("set_address", int, check=_addr),
            value=t.get("value", int, check=_value),
        )
        rules.append((t.get("device", str, ""), rule))
        t.check_unknown()
    for t in root.array_of_tables("at"):
        item = (t.get("after_s", float, check=non_negative), t.get("set", str, check=one_of(*TABLES)),
                t.get("set_address", int, check=_addr), t.get("value", int, check=_value))
        timed.append((t.get("device", str, ""), item))
        t.check_unknown()
    root.check_unknown()
    return rules, timed


def _addr(v: int) -> str | None:
    return None if 0 <= v <= 4095 else "must be an address 0..4095"


def _value(v: int) -> str | None:
    return None if 0 <= v <= 65535 else "must be 0..65535 (a bit is 0 or 1)"

