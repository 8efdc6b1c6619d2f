"""A simulated Modbus I/O module, for tests, demos and ``canon sim io``.

It is a real pymodbus server (``ModbusTcpServer`` over a ``SimDevice`` with four separate tables:
coils, discrete inputs, holding registers, input registers, addressed bit by bit) bound to
127.0.0.1, or a ``ModbusSerialServer`` speaking Modbus RTU on a serial port (``serial=``; without
hardware, one end of a :class:`fieldbus.modbus.serialport.PtyLink`), run on its own thread with its
own event loop (pymodbus builds a server inside a running loop). The module's contents live in this
class, not in pymodbus's runtime: the ``SimDevice`` access hook copies them into the answer of every
request and takes every write from it. That is what lets it

* record every write with a ``time.monotonic()`` stamp taken when the request arrives
  (:attr:`SimIoModule.writes`, :meth:`SimIoModule.wait_write`), so tests can time outputs;
* have its inputs set from any thread (:meth:`SimIoModule.set`) or scripted: a :class:`Rule` such as
  "0.3 s after coil 0 is written on, discrete input 0 goes on", or a change at a given time
  (:meth:`SimIoModule.schedule`);
* misbehave on purpose: answer slowly (:attr:`SimIoModule.delay_s`) or with a Modbus exception
  (:meth:`SimIoModule.fail`), and go away and come back (:meth:`SimIoModule.stop`, then
  :meth:`SimIoModule.start` again on the same port).

To try RTU without hardware, :class:`fieldbus.modbus.serialport.PtyLink` joins two pseudo-terminals
like a null-modem cable: the module serves on one end, the client opens the other.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from pymodbus.constants import ExcCodes

from fieldbus.modbus.config import ModbusConfig
from fieldbus.modbus.serialport import serial_port_problem

log = logging.getLogger(__name__)

TABLES = ("coil", "discrete_input", "holding_register", "input_register")
BIT_TABLES = ("coil", "discrete_input")
WRITABLE = ("coil", "holding_register")

# function code -> table it touches
_FC_TABLE = {1: "coil", 5: "coil", 15: "coil", 2: "discrete_input", 4: "input_register",
             3: "holding_register", 6: "holding_register", 16: "holding_register",
             22: "holding_register", 23: "holding_register"}


@dataclass(frozen=True, slots=True)
class WriteRecord:
    """One write request as the module received it."""

    t: float
    """``time.monotonic()`` when the request reached the module (before it answered)."""
    table: str
    """``coil`` or ``holding_register``."""
    address: int
    values: tuple[int, ...]
    """The values written from ``address`` on; coils as 0/1."""
    function_code: int


@dataclass(frozen=True, slots=True)
class Rule:
    """When ``when_table[when_address]`` is written with ``equals``, set ``set_table[set_address]``
    to ``value`` ``after_s`` seconds later (an input answering an output, like a clamp closing)."""

    when_table: str
    when_address: int
    equals: int
    after_s: float
    set_table: str
    set_address: int
    value: int

    def __post_init__(self) -> None:
        if self.when_table not in WRITABLE:
            raise ValueError(f"a rule fires on a write to one of {', '.join(WRITABLE)}, "
                             f"not {self.when_table!r}")
        if self.set_table not in TABLES:
            raise ValueError(f"unknown table {self.set_table!r} (one of {', '.join(TABLES)})")
        if self.after_s < 0:
            raise ValueError(f"after_s must be >= 0, got {self.after_s}")


class SimIoModule:
    """A Modbus I/O module with ``size`` entries in each of the four tables: Modbus TCP on 127.0.0.1,
    or Modbus RTU on the serial port ``serial`` (with ``baudrate``, ``parity``, ``stopbits``,
    ``bytesize``; needs pyserial).

    ``port=0`` takes a free port; :attr:`port` holds the real one once :meth:`start` returns, and a
    restart after :meth:`stop` binds the same port again. ``unit`` is the unit id it answers (0: any).
    """

    def __init__(self, *, host: str = "127.0.0.1", port: int = 0, unit: int = 1, size: int = 256,
                 rules: tuple[Rule, ...] | list[Rule] = (), serial: str = "", baudrate: int = 19200,
                 parity: str = "N", stopbits: int = 1, bytesize: int = 8) -> None:
        if size < 1 or size > 4096:
            raise ValueError(f"size must be 1..4096, got {size}")
        if host not in ("127.0.0.1", "localhost", "::1"):  # house rule: simulators stay on this host
            raise ValueError(f"a simulated module listens on loopback only, not {host!r}")
        if parity not in ("N", "E", "O") or stopbits not in (1, 2) or bytesize not in (7, 8) or baudrate <= 0:
            raise ValueError(f"bad serial settings: baudrate {baudrate}, parity {parity!r}, "
                             f"stopbits {stopbits}, bytesize {bytesize}")
        self.host = host
        self.port = port
        self.serial = serial
        self.baudrate = baudrate
        self.parity = parity
        self.stopbits = stopbits
        self.bytesize = bytesize
        self.unit = unit
        self.size = size
        self.rules: list[Rule] = list(rules)
        #: inputs computed when a request reads them: (table, address, fn() -> 0/1 or register value);
        #: e.g. a probe that trips at a height (motiond.sim_wiring)
        self.computed: list[tuple[str, int, Callable[[], int]]] = []
        self.delay_s = 0.0
        """Every answer is held back this long (to provoke client timeouts)."""
        self.writes: list[WriteRecord] = []
        self.requests = 0
        self._data: dict[str, list[int]] = {t: [0] * size for t in TABLES}
        self._fail: dict[tuple[str, int], ExcCodes] = {}
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._listeners: list[Callable[[WriteRecord], None]] = []

    # --- life cycle -----------------------------------------------------------------------------

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def where(self) -> str:
        """``127.0.0.1:5020`` or the serial port, for messages."""
        return self.serial if self.serial else f"{self.host}:{self.port}"

    def start(self, timeout: float = 5.0) -> SimIoModule:
        """Start serving (a thread with its own loop); returns once the port is listening."""
        if self.running:
            return self
        self._ready.clear()
        self._error = None
        self._thread = threading.Thread(target=self._run, name=f"sim-io:{self.where}", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout):
            raise TimeoutError(f"simulated I/O module did not start within {timeout} s")
        if self._error is not None:
            self._thread.join(timeout)
            self._thread = None
            if self.serial:
                raise OSError(f"simulated I/O module cannot open serial port {self.serial}: {self._error}")
            raise OSError(f"simulated I/O module cannot listen on {self.host}:{self.port}: {self._error}")
        return self

    def stop(self, timeout: float = 5.0) -> None:
        """Stop serving and drop every client connection; the contents are kept for a restart."""
        thread, loop, stop = self._thread, self._loop, self._stop
        if thread is None:
            return
        if loop is not None and stop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):  # loop closed meanwhile
                loop.call_soon_threadsafe(stop.set)
        thread.join(timeout)
        if thread.is_alive():
            raise TimeoutError(f"simulated I/O module on {self.where} did not stop within {timeout} s")
        self._thread = None

    def __enter__(self) -> SimIoModule:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _run(self) -> None:
        try:
            asyncio.run(self._serve())
        except BaseException as exc:  # reported to start(); never lost silently
            log.exception("simulated I/O module failed")
            self._error = exc
            self._ready.set()

    async def _serve(self) -> None:
        from pymodbus.simulator import DataType, SimData, SimDevice

        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        bits = [SimData(0, count=self.size, values=False, datatype=DataType.BITS)]
        regs = [SimData(0, count=self.size, values=0, datatype=DataType.REGISTERS)]
        device = SimDevice(
            id=self.unit,
            simdata=(list(bits), list(bits), list(regs), list(regs)),
            use_bit_addressing=True,
            action=self._access,
        )
        if self.serial:
            problem = serial_port_problem(self.serial, self.baudrate, self.parity, self.stopbits,
                                          self.bytesize)
            if problem:
                self._error = OSError(problem)
                self._ready.set()
                return
            from pymodbus.framer import FramerType
            from pymodbus.server import ModbusSerialServer

            server = ModbusSerialServer(device, framer=FramerType.RTU, port=self.serial,
                                        baudrate=self.baudrate, parity=self.parity, stopbits=self.stopbits,
                                        bytesize=self.bytesize)
        else:
            from pymodbus.server import ModbusTcpServer

            server = ModbusTcpServer(device, address=(self.host, self.port))
        try:
            await server.serve_forever(background=True)
        except RuntimeError as exc:
            self._error = exc
            self._ready.set()
            return
        sockets = getattr(server.transport, "sockets", None) or []
        if sockets:
            self.port = sockets[0].getsockname()[1]
        log.info("simulated I/O module serving on %s (unit %d)", self.where, self.unit)
        self._ready.set()
        try:
            await self._stop.wait()
        finally:
            await server.shutdown()
            await asyncio.sleep(0)  # let the transports close

    # --- what the server calls for every request -----------------------------------------------

    async def _access(self, function_code: int, start_address: int, address: int, count: int,
                      registers: list[int], set_values: list[int] | list[bool] | None) -> ExcCodes | None:
        """pymodbus's ``SimDevice`` hook: record writes, apply rules, refresh the table it answers from."""
        t = time.monotonic()
        table = _FC_TABLE.get(function_code)
        if table is None:
            return ExcCodes.ILLEGAL_FUNCTION
        if self.delay_s > 0:
            await asyncio.sleep(self.delay_s)
        # pymodbus passes bit tables' ``count`` in registers (16 bits each), register tables' in registers
        if set_values:
            end = address + len(set_values)
        elif table in BIT_TABLES:
            end = (address // 16 + count) * 16
        else:
            end = address + count
        fired: list[Rule] = []
        with self._lock:
            self.requests += 1
            for a in range(address, min(end, self.size)):
                code = self._fail.get((table, a))
                if code is not None:
                    return code
            if set_values:
                values = tuple(int(v) for v in set_values)
                data = self._data[table]
                for i, v in enumerate(values):
                    if 0 <= address + i < self.size:
                        data[address + i] = v
                rec = WriteRecord(t, table, address, values, function_code)
                self.writes.append(rec)
                for rule in self.rules:
                    if rule.when_table == table and address <= rule.when_address < address + len(values) \
                            and values[rule.when_address - address] == rule.equals:
                        fired.append(rule)
                self._changed.notify_all()
            for c_table, c_address, fn in self.computed:
                if c_table == table and 0 <= c_address < self.size:
                    self._data[table][c_address] = int(fn())
            self._fill(table, start_address, registers, address, end)
        for rule in fired:
            asyncio.get_running_loop().call_later(rule.after_s, self.set, rule.set_table, rule.set_address,
                                                  rule.value)
        if set_values:
            for listener in list(self._listeners):
                listener(rec)
        return None

    def _fill(self, table: str, start_address: int, registers: list[int], address: int, end: int) -> None:
        """Copy entries ``address`` to ``end`` (exclusive) of this module's table into the pymodbus block
        it answers from (bit tables: 16 bits per register, ``start_address`` counted in registers)."""
        data = self._data[table]
        last = len(registers) - 2  # the last entry is pymodbus's end marker
        if table in BIT_TABLES:
            first = max(0, address // 16 - start_address)
            for r in range(first, min(last, (end - 1) // 16 - start_address) + 1):
                word = 0
                base = (start_address + r) * 16
                for b in range(16):
                    if base + b < self.size and data[base + b]:
                        word |= 1 << b
                registers[r] = word
        else:
            for r in range(max(0, address - start_address), min(last, end - 1 - start_address) + 1):
                if start_address + r < self.size:
                    registers[r] = data[start_address + r]

    # --- for tests and scripts (any thread) -----------------------------------------------------

    def set(self, table: str, address: int, value: int | bool) -> None:
        """Set one entry: a bit (0/1) or a register (0..65535)."""
        self._check(table, address)
        v = int(value)
        if table in BIT_TABLES:
            v = 1 if v else 0
        elif not 0 <= v <= 65535:
            raise ValueError(f"register value must be 0..65535, got {value}")
        with self._lock:
            self._data[table][address] = v
            self._changed.notify_all()

    def set_registers(self, table: str, address: int, values: list[int]) -> None:
        """Set consecutive registers at once (a float32 pair changes atomically for readers)."""
        for i in range(len(values)):
            self._check(table, address + i)
        with self._lock:
            for i, v in enumerate(values):
                if not 0 <= v <= 65535:
                    raise ValueError(f"register value must be 0..65535, got {v}")
                self._data[table][address + i] = int(v)
            self._changed.notify_all()

    def get(self, table: str, address: int) -> int:
        self._check(table, address)
        with self._lock:
            return self._data[table][address]

    def registers(self, table: str, address: int, count: int) -> list[int]:
        with self._lock:
            return list(self._data[table][address:address + count])

    def schedule(self, after_s: float, table: str, address: int, value: int | bool) -> None:
        """Set an entry ``after_s`` seconds from now (needs the module running)."""
        self._check(table, address)
        loop = self._loop
        if loop is None or not self.running:
            raise RuntimeError("the simulated module is not running")
        loop.call_soon_threadsafe(loop.call_later, after_s, self.set, table, address, value)

    def fail(self, table: str, address: int, code: ExcCodes | None = ExcCodes.DEVICE_FAILURE) -> None:
        """Answer every request touching ``table[address]`` with exception ``code`` (None: stop)."""
        with self._lock:
            if code is None:
                self._fail.pop((table, address), None)
            else:
                self._fail[(table, address)] = code

    def add_listener(self, fn: Callable[[WriteRecord], None]) -> None:
        """Call ``fn(record)`` on the module's loop after every write."""
        self._listeners.append(fn)

    def writes_to(self, table: str, address: int) -> list[WriteRecord]:
        """Writes that covered ``table[address]``, oldest first."""
        with self._lock:
            return [w for w in self.writes
                    if w.table == table and w.address <= address < w.address + len(w.values)]

    def wait_write(self, table: str, address: int, value: int | None = None, *, since: int = 0,
                   timeout: float = 2.0) -> WriteRecord | None:
        """First write (from record number ``since`` on) that covered ``table[address]`` (with
        ``value`` there, if given); waits up to ``timeout`` s; None if none came."""
        deadline = time.monotonic() + timeout
        with self._lock:
            while True:
                for w in self.writes[since:]:
                    if w.table == table and w.address <= address < w.address + len(w.values) \
                            and (value is None or w.values[address - w.address] == int(value)):
                        return w
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._changed.wait(left)

    def _check(self, table: str, address: int) -> None:
        if table not in TABLES:
            raise ValueError(f"unknown table {table!r} (one of {', '.join(TABLES)})")
        if not 0 <= address < self.size:
            raise ValueError(f"{table} {address} is outside 0..{self.size - 1}")


def size_for(config: ModbusConfig, device: str, minimum: int = 256) -> int:
    """Entries per table a simulated ``device`` needs to hold everything the configuration maps."""
    regs = [*config.analog_outputs, *config.analog_inputs]
    addrs = [m.coil for m in config.digital_outputs if m.device == device]
    addrs += [m.address for m in config.digital_inputs if m.device == device]
    addrs += [m.register + m.conversion.type.registers - 1 for m in regs if m.device == device]
    addrs += [p.address + p.registers - 1 for p in config.named if p.device == device]
    return min(max(minimum, max(addrs, default=0) + 1), 4096)


def start_simulated(config: ModbusConfig, timeout: float = 5.0) -> list[SimIoModule]:
    """Start one module per ``simulate = true`` device (its port and unit, big enough for its map),
    for the daemon and the demo machine; stop them with :meth:`SimIoModule.stop`."""
    started: list[SimIoModule] = []
    try:
        for dev in config.devices:
            if dev.simulate:
                mod = SimIoModule(host="127.0.0.1", port=dev.port, unit=dev.unit,
                                  size=size_for(config, dev.name))
                started.append(mod.start(timeout))
    except BaseException:
        for mod in started:
            mod.stop()
        raise
    return started
