"""Modbus I/O for M62-M68: configuration, value codec, the I/O worker, the executor the daemon calls,
and a simulated I/O module (``canon sim io``). See docs/modbus.md."""

from fieldbus.modbus.config import (
    AnalogInputMap,
    AnalogOutputMap,
    AnalogSource,
    Conversion,
    DigitalInputMap,
    DigitalOutputMap,
    DigitalSource,
    ModbusConfig,
    ModbusDevice,
    NamedPoint,
    ValueType,
    WordOrder,
)
from fieldbus.modbus.faults import (
    FaultKind,
    IoError,
    LinkDownError,
    ModbusConnectError,
    ModbusFault,
    WaitAborted,
)

__all__ = [
    "AnalogInputMap",
    "AnalogOutputMap",
    "AnalogSource",
    "Conversion",
    "DigitalInputMap",
    "DigitalOutputMap",
    "DigitalSource",
    "FaultKind",
    "IoError",
    "LinkDownError",
    "ModbusConfig",
    "ModbusConnectError",
    "ModbusDevice",
    "ModbusFault",
    "NamedPoint",
    "ValueType",
    "WaitAborted",
    "WordOrder",
]
