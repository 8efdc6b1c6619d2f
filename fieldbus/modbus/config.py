"""Typed configuration of the Modbus I/O side: devices and the maps from M62-M68 numbers to addresses.

These dataclasses are what ``motiond.config_modbus`` builds from the ``[[modbus.*]]`` arrays of the
machine file; nothing here reads TOML, so the I/O layer can be configured from code and tests alone.

Addresses are the zero-based numbers that travel on the wire (``coil = 0`` is the first coil), not
the 1-based "00001/10001/30001/40001" numbering of some device manuals.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field


class ValueType(enum.Enum):
    """How a number is laid out in registers."""

    INT16 = "int16"
    UINT16 = "uint16"
    FLOAT32 = "float32"  # IEEE 754 single, two registers

    @property
    def registers(self) -> int:
        return 2 if self is ValueType.FLOAT32 else 1


class WordOrder(enum.Enum):
    """Order of the two registers of a float32: ``big`` sends the high word first (Modbus habit)."""

    BIG = "big"
    LITTLE = "little"


class DigitalSource(enum.Enum):
    """Where a digital input (M66 P) is read from."""

    DISCRETE_INPUT = "discrete_input"
    COIL = "coil"


class AnalogSource(enum.Enum):
    """Where an analog input (M66 E) is read from."""

    INPUT_REGISTER = "input_register"
    HOLDING_REGISTER = "holding_register"


@dataclass(frozen=True, slots=True)
class Conversion:
    """Scaling between engineering values (what the program says) and register contents.

    Outputs: ``register = value * scale + offset``. Inputs: ``value = register * scale + offset``.
    The scale always multiplies in the direction the data travels, so an output with ``scale = 100``
    sends 1.5 as 150 and an input with ``scale = 0.01`` reads 150 as 1.5.
    """

    type: ValueType = ValueType.INT16
    word_order: WordOrder = WordOrder.BIG
    scale: float = 1.0
    offset: float = 0.0


@dataclass(frozen=True, slots=True)
class ModbusDevice:
    """One Modbus slave (an I/O module, a PLC, a gateway unit).

    With ``serial`` set the device is reached by Modbus RTU over that serial port (needs pyserial);
    otherwise by Modbus TCP at ``host``:``port``. ``timeout_s`` bounds each request and each connect
    attempt; a request that times out is tried ``retries`` more times with a doubling back-off before
    the link is declared lost. Inputs are polled every ``poll_ms``. ``simulate`` asks the daemon to
    start a simulated module (``fieldbus.modbus.sim``) for this device. With
    ``separate_poll_connection`` (TCP only) inputs are polled over a second connection, so that a
    write never waits behind a read; turn it off for a device that accepts one connection only.
    """

    name: str
    host: str = "127.0.0.1"
    port: int = 502
    unit: int = 1
    timeout_s: float = 0.5
    retries: int = 3
    poll_ms: float = 20.0
    simulate: bool = False
    serial: str = ""
    baudrate: int = 19200
    parity: str = "N"
    stopbits: int = 1
    bytesize: int = 8
    retry_backoff_s: float = 0.01
    reconnect_max_s: float = 2.0
    separate_poll_connection: bool = True

    @property
    def where(self) -> str:
        """Human-readable address, for messages: ``127.0.0.1:5020`` or ``/dev/ttyUSB0``."""
        return self.serial if self.serial else f"{self.host}:{self.port}"


@dataclass(frozen=True, slots=True)
class DigitalOutputMap:
    """M62-M65 P``index`` -> coil ``coil`` of ``device``; ``safe`` is written after a link loss."""

    index: int
    device: str
    coil: int
    safe: bool = False


@dataclass(frozen=True, slots=True)
class AnalogOutputMap:
    """M67/M68 E``index`` -> holding register(s) from ``register``; ``safe`` in engineering units."""

    index: int
    device: str
    register: int
    conversion: Conversion = field(default_factory=Conversion)
    safe: float = 0.0


@dataclass(frozen=True, slots=True)
class DigitalInputMap:
    """M66 P``index`` <- a discrete input (or a coil) ``address`` of ``device``."""

    index: int
    device: str
    address: int
    source: DigitalSource = DigitalSource.DISCRETE_INPUT


@dataclass(frozen=True, slots=True)
class AnalogInputMap:
    """M66 E``index`` <- input register(s) (or holding registers) from ``register`` of ``device``."""

    index: int
    device: str
    register: int
    conversion: Conversion = field(default_factory=Conversion)
    source: AnalogSource = AnalogSource.INPUT_REGISTER


POINT_TABLES = ("coil", "discrete_input", "input_register", "holding_register")
"""The four Modbus tables a named point can sit in."""


@dataclass(frozen=True, slots=True)
class NamedPoint:
    """A point the daemon itself reads or writes under a name (the machine file's I/O map: the E-stop
    input, the spindle-on coil ...), rather than under an M62-M68 number.

    Inputs (``output`` False) are polled with the M66 inputs and appear in
    :attr:`fieldbus.modbus.io_worker.InputSnapshot.named` by ``key``; a bit table gives 0.0/1.0, a
    register table the value converted by ``conversion``. Outputs (``output`` True) sit in a writable
    table (``coil``, ``holding_register``) and get ``safe`` (engineering units; 0/1 for a coil) at
    start, after a lost link and at stop, like the mapped outputs.
    """

    key: str
    device: str
    table: str
    address: int
    output: bool = False
    conversion: Conversion = field(default_factory=Conversion)
    safe: float = 0.0

    @property
    def bit(self) -> bool:
        return self.table in ("coil", "discrete_input")

    @property
    def registers(self) -> int:
        return 1 if self.bit else self.conversion.type.registers


@dataclass(frozen=True, slots=True)
class ModbusConfig:
    """Everything the Modbus side needs: the devices, the four maps and the named points."""

    devices: tuple[ModbusDevice, ...]
    digital_outputs: tuple[DigitalOutputMap, ...] = ()
    analog_outputs: tuple[AnalogOutputMap, ...] = ()
    digital_inputs: tuple[DigitalInputMap, ...] = ()
    analog_inputs: tuple[AnalogInputMap, ...] = ()
    named: tuple[NamedPoint, ...] = ()

    def __post_init__(self) -> None:
        problems = self.problems()
        if problems:
            raise ValueError("; ".join(problems))

    def device(self, name: str) -> ModbusDevice:
        for dev in self.devices:
            if dev.name == name:
                return dev
        raise KeyError(name)

    def problems(self) -> list[str]:
        """Cross-checks no single entry can make: unknown devices, duplicate numbers and names."""
        out: list[str] = []
        names = [d.name for d in self.devices]
        for name in sorted({n for n in names if names.count(n) > 1}):
            out.append(f"device name {name!r} used twice")
        groups: list[tuple[str, tuple]] = [
            ("digital output", self.digital_outputs),
            ("analog output", self.analog_outputs),
            ("digital input", self.digital_inputs),
            ("analog input", self.analog_inputs),
        ]
        for what, maps in groups:
            seen: set[int] = set()
            for m in maps:
                if m.device not in names:
                    out.append(f"{what} {m.index}: unknown device {m.device!r}")
                if m.index in seen:
                    out.append(f"{what} {m.index} mapped twice")
                seen.add(m.index)
        keys: set[str] = set()
        for p in self.named:
            if p.device not in names:
                out.append(f"point {p.key}: unknown device {p.device!r}")
            if p.key in keys:
                out.append(f"point {p.key} named twice")
            if p.table not in POINT_TABLES or (p.output and p.table not in ("coil", "holding_register")):
                out.append(f"point {p.key}: {'an output cannot be' if p.output else 'no'} table {p.table!r}")
            keys.add(p.key)
        return out

    def point(self, key: str) -> NamedPoint:
        for p in self.named:
            if p.key == key:
                return p
        raise KeyError(key)
